# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""A signed visit becomes an amendment pending when anything its report printed changes:
a rating or its comment, a session's facts, a session joining the visit; not only a
result revision (which tests/app/test_signatures.py covers)."""

from __future__ import annotations

from api_support import Api, api, make_user, video_pair  # noqa: F401 - pytest fixtures
from fastapi.testclient import TestClient
from test_revisions import _trial

from app.models import RecordingSession, Signature, Trial

PASSWORD = "a long clinician passphrase 42"


def _signing(api: Api, video_pair) -> tuple[TestClient, dict[str, str], int, int]:
    trial_id = _trial(api, video_pair)
    with api.sessions() as db:
        session_id = int(db.get(Trial, trial_id).session_id)
    make_user(api.sessions, "dr.facts@example.org", PASSWORD)
    client = TestClient(api.app)
    r = client.post(
        "/api/v1/auth/login", json={"email": "dr.facts@example.org", "password": PASSWORD}
    )
    return client, {"X-CSRF-Token": r.json()["csrf_token"]}, session_id, trial_id


def _sign(client: TestClient, headers: dict[str, str], session_id: int) -> dict:
    r = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=headers
    )
    assert r.status_code == 201, r.text
    return r.json()


def _state(client: TestClient, session_id: int) -> dict:
    return client.get(f"/api/v1/sessions/{session_id}/signatures").json()


def test_a_rating_or_a_session_fact_changed_after_signing_is_an_amendment(
    api: Api, video_pair
) -> None:
    client, user, session_id, trial_id = _signing(api, video_pair)
    assert _sign(client, user, session_id)["number"] == 1
    assert _state(client, session_id)["status"] == "signed"

    # a rating and its comment, made after the signature (the result revision is the same)
    r = api.client.patch(
        f"/api/v1/trials/{trial_id}",
        json={"clinician_rating": 3, "comment": "slower after the tenth tap"},
        headers=api.headers,
    )
    assert r.status_code == 200, r.text
    state = _state(client, session_id)
    assert state["status"] == "amendment_pending"
    assert state["changes"] == [
        f"the rating of trial {trial_id} changed from none to 3",
        f"the rating comment of trial {trial_id} changed from none to a comment",
    ]
    two = _sign(client, user, session_id)
    assert (two["number"], two["amends_number"]) == (2, 1)
    assert _state(client, session_id)["status"] == "signed"

    # the medication state of the session, and a second session on the same day
    with api.sessions() as db:
        before = db.get(RecordingSession, session_id).medication_state
    after = "on" if before != "on" else "off"
    r = api.client.patch(
        f"/api/v1/sessions/{session_id}", json={"medication_state": after}, headers=api.headers
    )
    assert r.status_code == 200, r.text
    with api.sessions() as db:
        first = db.get(RecordingSession, session_id)
        later = RecordingSession(
            patient_id=first.patient_id,
            rig_id=first.rig_id,
            recorded_at=first.recorded_at.replace(minute=(first.recorded_at.minute + 1) % 60),
        )
        db.add(later)
        db.commit()
        later_id = later.id
    changes = _state(client, session_id)["changes"]
    assert changes == [
        f"the medication state of session {session_id} changed from {before} to {after}",
        f"session {later_id} joined the visit",
    ]
    assert _sign(client, user, session_id)["amends_number"] == 2
    again = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=user
    )
    assert again.status_code == 409 and "nothing changed" in again.json()["detail"]


def test_a_signature_made_before_the_facts_were_kept_compares_revisions_only(
    api: Api, video_pair
) -> None:
    """Signatures stored before migration 0017 have no facts: a rating made since does not
    make them pending (nothing says what they printed), a newer revision still does."""
    client, user, session_id, trial_id = _signing(api, video_pair)
    _sign(client, user, session_id)
    with api.sessions() as db:
        signed = db.query(Signature).one()
        legacy = Signature(
            **{
                c: getattr(signed, c)
                for c in (
                    "patient_id",
                    "session_id",
                    "visit_date",
                    "signed_by",
                    "signed_by_user_id",
                    "signed_at",
                    "sha256",
                    "size_bytes",
                    "trial_revisions",
                )
            },
            number=2,
            amends_number=1,
            pdf_path=signed.pdf_path + ".legacy",
            signed_facts=None,
        )
        db.add(legacy)
        db.commit()
    api.client.patch(
        f"/api/v1/trials/{trial_id}", json={"clinician_rating": 2}, headers=api.headers
    )
    assert _state(client, session_id)["status"] == "signed"


def test_hiding_a_trial_that_was_never_measured_is_an_amendment(api: Api, video_pair) -> None:
    """The visit report lists hidden trials with their reason, measured or not: hiding a
    failed trial after signing changes the report, so it makes an amendment pending."""
    from api_support import trial_files

    client, user, session_id, _ = _signing(api, video_pair)
    failed = api.client.post(
        f"/api/v1/sessions/{session_id}/trials",
        data={"hand": "right"},
        files=trial_files(*reversed(video_pair)),
        headers=api.headers,
    )
    assert failed.status_code == 201, failed.text
    failed_id = failed.json()["id"]
    _sign(client, user, session_id)
    r = api.client.request(
        "DELETE",
        f"/api/v1/trials/{failed_id}",
        json={"reason": "a false start"},
        headers=api.headers,
    )
    assert r.status_code in (200, 204), r.text
    state = _state(client, session_id)
    assert state["status"] == "amendment_pending"
    assert state["changes"] == [f"trial {failed_id} (not measured) was hidden"]


def test_a_change_of_clinician_is_said_without_account_ids(api: Api, video_pair) -> None:
    client, user, session_id, _ = _signing(api, video_pair)
    _sign(client, user, session_id)
    other = make_user(api.sessions, "dr.other@example.org", PASSWORD)
    with api.sessions() as db:
        db.get(RecordingSession, session_id).clinician_user_id = other
        db.commit()
    assert _state(client, session_id)["changes"] == [
        f"the clinician of session {session_id} changed from none to a clinician"
    ]
