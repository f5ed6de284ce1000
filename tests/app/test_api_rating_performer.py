# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""A rating given through the REST API names who answers for it, as one given on the page.

The page's rating records the logged-in clinician (``rated_by_user_id``), whom the FHIR
rating Observation names as its ``performer``; an API key's rating recorded nobody, so
the FHIR export of an API-rated trial had no performer. It now records the key's owner
(``bradyscope admin create-api-key --owner``); a key without an owner still names nobody.
"""

from __future__ import annotations

import pytest
from api_support import Api, api, make_api_key, make_user, video_pair  # noqa: F401
from sqlalchemy import select
from test_revisions import _trial

from app.models import ApiClient, User

PASSWORD = "correct horse battery"
RATING_SYSTEM = "urn:bradyscope:clinician-rating"


@pytest.fixture
def measured(api: Api, video_pair) -> int:
    return _trial(api, video_pair)


def _rating(bundle: dict) -> dict:
    found = [
        e["resource"]
        for e in bundle["entry"]
        if e["resource"].get("code", {}).get("coding", [{}])[0].get("system") == RATING_SYSTEM
    ]
    assert len(found) == 1, found
    return found[0]


def _owned_by(api: Api, key_name: str, email: str, display_name: str) -> int:
    owner = make_user(api.sessions, email, PASSWORD)
    with api.sessions() as db:
        db.get(User, owner).display_name = display_name
        db.scalars(select(ApiClient).where(ApiClient.name == key_name)).one().owner_user_id = owner
        db.commit()
    return owner


def _rate(api: Api, trial_id: int, headers: dict[str, str], rating: int) -> dict:
    r = api.client.patch(f"/api/v1/trials/{trial_id}", json={"clinician_rating": rating},
                         headers=headers)  # fmt: skip
    assert r.status_code == 200, r.text
    return r.json()


def _fhir(api: Api, trial_id: int) -> dict:
    r = api.client.get(f"/api/v1/trials/{trial_id}/fhir", headers=api.headers)
    assert r.status_code == 200, r.text
    return r.json()


def test_the_fhir_rating_of_an_api_rated_trial_names_the_keys_owner(
    api: Api, measured: int
) -> None:
    owner = _owned_by(api, "hospital", "dr.owner@example.org", "Dr. Owner")  # api.key's
    view = _rate(api, measured, api.headers, 3)
    assert view["rated_by_user_id"] == owner
    obs = _rating(_fhir(api, measured))
    assert obs["valueInteger"] == 3
    assert obs["performer"] == [{"display": "Dr. Owner"}]


def test_a_key_without_an_owner_names_nobody(api: Api, measured: int) -> None:
    key = make_api_key(api.sessions, name="no-owner")
    view = _rate(api, measured, {"Authorization": f"Bearer {key}"}, 1)
    assert view["rated_by_user_id"] is None
    obs = _rating(_fhir(api, measured))
    assert obs["valueInteger"] == 1 and "performer" not in obs
