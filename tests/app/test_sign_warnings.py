"""The API's sign warnings are what to know *before signing*: said while there is
something to sign, not once the visit is signed and nothing changed since.

``GET /api/v1/sessions/{id}/signatures`` went on naming the visit's failed and pending
trials after the visit was signed, when there was nothing to sign (signing again is
refused, 409) and the session page showed no warning, only its "Signed" line.
"""

from __future__ import annotations

from datetime import UTC, datetime

from test_pages import PASSWORD, client, login, seeded  # noqa: F401 - fixtures
from test_visit_report_pages import _failed_take

from app.models import RecordingSession, Trial


def _state(client, session_id: int, headers: dict[str, str]) -> dict:  # noqa: F811
    r = client.get(f"/api/v1/sessions/{session_id}/signatures", headers=headers)
    assert r.status_code == 200, r.text
    return r.json()


def test_sign_warnings_are_said_while_there_is_something_to_sign(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    headers = {"X-CSRF-Token": login(client)}
    left = seeded["trials"][(1, "left")]
    with db_sessionmaker() as db, db.begin():
        session_id = db.get(Trial, left).session_id
        failed = _failed_take(db, session_id, "pronation_supination", "right")
        pending = _failed_take(db, session_id, "finger_tapping", "left", "running")
    for t in seeded["trials"].values():  # every measured trial rated: failed and pending left
        r = client.patch(f"/api/v1/trials/{t}", json={"clinician_rating": 1}, headers=headers)
        assert r.status_code == 200, r.text

    before = _state(client, session_id, headers)
    assert before["status"] == "unsigned"
    warnings = before["warnings"]
    assert len(warnings) == 2, warnings
    assert f"#{failed} (" in warnings[0] and f"#{pending} (" in warnings[1]

    signed = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=headers
    )
    assert signed.status_code == 201, signed.text
    assert signed.json()["warnings"] == warnings  # signed: what the clinician was told

    # Signed, nothing changed since: nothing to sign, so nothing to know before signing,
    # though the failed and pending trials are still there.
    after = _state(client, session_id, headers)
    assert after["status"] == "signed" and after["changes"] == []
    assert after["warnings"] == []
    again = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=headers
    )
    assert again.status_code == 409, again.text
    assert "warnings" not in again.json()  # nothing signed, nothing said but why

    # A change makes an amendment pending: something to sign again, and the warnings return.
    r = client.patch(f"/api/v1/trials/{left}", json={"clinician_rating": 2}, headers=headers)
    assert r.status_code == 200, r.text
    amend = _state(client, session_id, headers)
    assert amend["status"] == "amendment_pending"
    assert amend["warnings"] == warnings


def test_a_visit_without_a_measured_trial_has_nothing_to_sign_and_no_warnings(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    headers = {"X-CSRF-Token": login(client)}
    with db_sessionmaker() as db, db.begin():
        measured = db.get(RecordingSession, db.get(Trial, seeded["trials"][(1, "left")]).session_id)
        other_day = RecordingSession(
            patient_id=measured.patient_id,
            rig_id=measured.rig_id,
            recorded_at=datetime(2025, 6, 2, 9, tzinfo=UTC),  # a visit of its own
            medication_state="off",
            dbs_state="none",
        )
        db.add(other_day)
        db.flush()
        session_id = other_day.id
        _failed_take(db, session_id, "finger_tapping", "right")
    state = _state(client, session_id, headers)
    assert state["status"] == "unsigned" and state["signatures"] == []
    assert state["warnings"] == []  # signing is refused: no trial has a result
    r = client.post(
        f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD}, headers=headers
    )
    assert r.status_code == 409, r.text
