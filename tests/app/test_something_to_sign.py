"""Whether a visit has something to sign is one fact (``VisitSigning.something_to_sign``),
and the session page and the API tell the same sign warnings because of it.

The API decided it in its route (00ffa94) and the session page in its template, each
in its own words: two places that could drift apart.
"""

from __future__ import annotations

import html as html_lib
import re
from datetime import date

import pytest
from test_pages import PASSWORD, client, login, seeded  # noqa: F401 - fixtures
from test_visit_report_pages import _failed_take

from app.models import Signature, Trial
from app.services.signatures import VisitSigning


@pytest.mark.parametrize(
    ("signed", "current", "changes", "expected"),
    [
        (False, {}, [], False),  # no trial has a result: signing is refused
        (False, {"7": 1}, [], True),  # unsigned, a result
        (True, {"7": 1}, [], False),  # signed, nothing changed since
        (True, {"7": 2}, ["trial 7 is now at revision 2 (signed: 1)"], True),  # amendment
        (True, {}, ["trial 7 was hidden or lost its result"], False),  # nothing left to sign
    ],
)
def test_something_to_sign_needs_a_result_and_no_standing_signature(
    signed: bool, current: dict[str, int], changes: list[str], expected: bool
) -> None:
    state = VisitSigning(
        session=None,  # type: ignore[arg-type]  # the property reads no session
        visit_date=date(2026, 3, 1),
        signatures=[Signature(number=1)] if signed else [],
        current=current,
        changes=changes,
    )
    assert state.something_to_sign is expected


def _page_warnings(client, session_id: int) -> list[str] | None:  # noqa: F811
    """The sign warnings the session page shows, or None when it shows no sign form."""
    page = client.get(f"/sessions/{session_id}")
    assert page.status_code == 200, page.text[:300]
    if "data-sign-form" not in page.text:
        return None
    box = re.search(r"<div[^>]*data-sign-warnings>(.*?)</div>", page.text, re.S)
    if box is None:
        return []
    items = re.findall(r"<li>(.*?)</li>", box.group(1), re.S)
    return [html_lib.unescape(item) for item in items]


def _api_warnings(client, session_id: int, headers: dict[str, str]) -> list[str]:  # noqa: F811
    r = client.get(f"/api/v1/sessions/{session_id}/signatures", headers=headers)
    assert r.status_code == 200, r.text
    return r.json()["warnings"]


def test_the_page_and_the_api_tell_the_same_warnings_while_there_is_something_to_sign(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    headers = {"X-CSRF-Token": login(client)}
    left = seeded["trials"][(1, "left")]
    with db_sessionmaker() as db, db.begin():
        session_id = db.get(Trial, left).session_id
        _failed_take(db, session_id, "pronation_supination", "right")

    unsigned = _api_warnings(client, session_id, headers)
    assert unsigned, "a failed take is a warning before signing"
    assert _page_warnings(client, session_id) == unsigned

    signed = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=headers
    )
    assert signed.status_code == 201, signed.text
    # Nothing to sign: no form on the page, no warnings from the API (the failed take stays).
    assert _page_warnings(client, session_id) is None
    assert _api_warnings(client, session_id, headers) == []

    r = client.patch(f"/api/v1/trials/{left}", json={"clinician_rating": 3}, headers=headers)
    assert r.status_code == 200, r.text
    amend = _api_warnings(client, session_id, headers)  # an amendment is pending
    assert amend and any("failed" in w for w in amend)
    assert _page_warnings(client, session_id) == amend
