# ruff: noqa: F811  (pytest fixtures imported from test_pages are parameters here)
"""The capture pages as served: login, what the cameras must deliver, camera permission.

The recording itself runs in the browser and is tested in tests/browser/test_capture.py.
"""

from __future__ import annotations

import re

from sqlalchemy import func, select
from test_pages import _new_session, client, login, seeded, tiny_videos  # noqa: F401 - fixtures

from app.models import AuditEvent, Job, RecordingSession, Rig, Trial, Video
from core.video import HOLE_FRAMES, HOLE_S


def test_the_capture_pages_need_a_login(client, seeded) -> None:
    for path in ("/sessions/1/capture", f"/rigs/{seeded['rig_id']}/capture"):
        r = client.get(path, follow_redirects=False)
        assert r.status_code == 303, path
        assert r.headers["location"].startswith("/login?next="), path


def test_the_session_capture_page_asks_for_the_rigs_resolution(
    client, seeded, db_sessionmaker
) -> None:
    login(client)
    session_page = client.get("/sessions/1")
    assert 'href="/sessions/1/capture"' in session_page.text  # "Record"
    assert "camera=()" in session_page.headers["permissions-policy"]
    reads_before = _session_reads(db_sessionmaker)
    r = client.get("/sessions/1/capture")
    assert r.status_code == 200
    html = r.text
    # The calibrated size of each camera (640 x 512 px, the seeded rig) goes to the script.
    assert 'data-left-size="640x512"' in html and 'data-right-size="640x512"' in html
    assert 'data-upload-url="/sessions/1/trials"' in html
    # The server's rule for a stretch without frames, which the page applies before sending.
    assert f'data-hole-s="{HOLE_S}" data-hole-frames="{HOLE_FRAMES}"' in " ".join(html.split())
    assert re.search(r'<label for="camera-left">Left camera</label>', html)
    assert re.search(r'<label for="camera-right">Right camera</label>', html)
    assert ">Start recording</button>" in html and ">Stop recording</button>" in html
    # The task: every task offered, finger tapping first chosen; the gate counts its 2 markers.
    task_select = re.search(r'<select id="capture-task" name="task"[^>]*>(.*?)</select>', html)
    assert task_select and '<label for="capture-task">Task</label>' in html
    options = re.findall(
        r'<option value="(\w+)" data-markers="(\d+)"[^>]*?( selected)?>', task_select[1]
    )
    assert [value for value, _, _ in options] == [
        "finger_tapping",
        "hand_movements",
        "pronation_supination",
        "toe_tapping",
        "leg_agility",
    ]
    assert options[0] == ("finger_tapping", "2", " selected")
    # The other tasks' marker protocols (docs/protocols.md): finger and wrist; three markers.
    assert [markers for _, markers, _ in options[1:]] == ["2", "3", "3", "3"]
    assert '<script src="/static/capture.js" defer></script>' in html
    assert "<script>" not in html  # no inline script (the CSP forbids them)
    # Only the capture pages may use the camera.
    assert r.headers["permissions-policy"].startswith("camera=(self)")
    assert _session_reads(db_sessionmaker) == reads_before + 1  # it names the patient: audited


def _session_reads(db_sessionmaker) -> int:
    with db_sessionmaker() as db:
        return len(
            db.scalars(
                select(AuditEvent).where(
                    AuditEvent.action == "read",
                    AuditEvent.resource_type == "session",
                    AuditEvent.resource_id == "1",
                )
            ).all()
        )


def test_the_task_can_be_chosen_in_the_link(client, seeded) -> None:
    login(client)
    html = client.get("/sessions/1/capture?task=toe_tapping").text
    assert re.search(
        r'<option value="toe_tapping" data-markers="\d+" data-limb="foot" selected>', html
    )
    assert "<span data-limb-text>foot</span>" in html  # the side is the foot's
    # An unknown task in the link is ignored: finger tapping, as without one.
    html = client.get("/sessions/1/capture?task=juggling").text
    assert re.search(
        r'<option value="finger_tapping" data-markers="2" data-limb="hand" selected>', html
    )


def test_a_missing_session_has_no_capture_page(client, seeded) -> None:
    login(client)
    r = client.get("/sessions/999/capture")
    assert r.status_code == 404
    assert "permissions-policy" in r.headers and "camera=()" in r.headers["permissions-policy"]


def test_a_session_whose_rig_has_no_calibration_says_so(client, seeded, db_sessionmaker) -> None:
    login(client)
    with db_sessionmaker() as db:
        rig = Rig(name="uncalibrated")
        db.add(rig)
        db.flush()
        session = db.get(RecordingSession, 1)
        assert session is not None
        session.rig_id = rig.id
        db.commit()
    html = client.get("/sessions/1/capture").text
    assert 'data-left-size=""' in html
    assert re.search(r'<p class="alert" role="alert">rig \d+ has no ready calibration', html)


def test_the_rig_capture_page_records_a_board_pair(client, seeded) -> None:
    login(client)
    rig_page = client.get(f"/rigs/{seeded['rig_id']}").text
    assert f'href="/rigs/{seeded["rig_id"]}/capture"' in rig_page
    r = client.get(f"/rigs/{seeded['rig_id']}/capture")
    assert r.status_code == 200
    html = r.text
    assert 'data-mode="calibration"' in html
    assert f'data-upload-url="/rigs/{seeded["rig_id"]}/calibrations"' in html
    # The current calibration's resolution comes first in the resolution choice.
    first = re.search(r'<select id="capture-size"[^>]*>\s*<option value="([^"]+)"', html)
    assert first and first.group(1) == "640x512"
    for label in ("Board", "Columns", "Rows", "Square size (mm)", "Left camera", "Right camera"):
        assert f">{label}" in html, label
    assert r.headers["permissions-policy"].startswith("camera=(self)")


def _count(db_sessionmaker, model) -> int:
    with db_sessionmaker() as db:
        return int(db.scalar(select(func.count()).select_from(model)) or 0)


def _stored(app_settings) -> list:
    data = app_settings.data_dir
    return sorted(p for d in ("files", "tmp") for p in (data / d).rglob("*") if p.is_file())


def test_a_take_sent_again_is_not_stored_twice(
    client, seeded, tiny_videos, db_sessionmaker, app_settings
) -> None:
    """After a lost connection the page cannot know whether its take was stored; it sends
    it again with the same take_id, and the server answers with the trial stored first."""
    token = login(client)
    session_url = _new_session(client, seeded, token)
    left, right = tiny_videos
    files = {
        "left_video": ("left.webm", left.read_bytes(), "video/webm"),
        "right_video": ("right.webm", right.read_bytes(), "video/webm"),
    }
    headers = {"X-CSRF-Token": token, "Accept": "application/json"}
    take = {"hand": "right", "task": "finger_tapping", "take_id": "4f1c2b9e-take-0001"}
    first = client.post(f"{session_url}/trials", data=take, files=files, headers=headers)
    assert first.status_code == 201, first.text
    assert first.json()["stored_before"] is False and first.json()["take"]["left"]
    counts = [_count(db_sessionmaker, m) for m in (Trial, Video, Job)]
    stored = _stored(app_settings)
    again = client.post(f"{session_url}/trials", data=take, files=files, headers=headers)
    assert again.status_code == 200, again.text
    body = again.json()
    assert body["stored_before"] is True
    assert (body["trial_id"], body["job_id"]) == (first.json()["trial_id"], first.json()["job_id"])
    assert [_count(db_sessionmaker, m) for m in (Trial, Video, Job)] == counts
    assert _stored(app_settings) == stored  # the second copy's files are gone too
    # Another take (another id) is another trial; an id that is not one is refused.
    other = client.post(
        f"{session_url}/trials",
        data=take | {"take_id": "4f1c2b9e-take-0002"},
        files=files,
        headers=headers,
    )
    assert other.status_code == 201 and other.json()["trial_id"] != body["trial_id"]
    bad = client.post(
        f"{session_url}/trials", data=take | {"take_id": "../x"}, files=files, headers=headers
    )
    assert bad.status_code == 422 and "take_id must be" in bad.json()["detail"], bad.text
    assert _count(db_sessionmaker, Trial) == counts[0] + 1
    # Hidden since, the take is not "stored before" any more: the hidden trial's id is not
    # answered (a security review found it was), and nothing is stored again.
    trial_id = first.json()["trial_id"]
    hide = client.delete(f"/api/v1/trials/{trial_id}", headers={"X-CSRF-Token": token})
    assert hide.status_code == 204, hide.text
    stored = _stored(app_settings)
    late = client.post(f"{session_url}/trials", data=take, files=files, headers=headers)
    assert late.status_code == 409 and "deleted" in late.json()["detail"], late.text
    assert str(trial_id) not in late.text
    assert _stored(app_settings) == stored


def _leg_rig(db_sessionmaker) -> int:
    """A second rig of the clinic: the cameras placed beside the leg (1280 x 1024 px)."""
    from datetime import UTC, datetime

    from app.models import Calibration
    from core.camera import ImageSize, rig_to_dict
    from core.simulation.rig import default_rig

    with db_sessionmaker() as db:
        rig = Rig(name="clinic-A legs")
        db.add(rig)
        db.flush()
        doc = rig_to_dict(default_rig(image_size=ImageSize(1280, 1024), baseline_mm=700.0,
                                      convergence_mm=1000.0))  # fmt: skip
        db.add(
            Calibration(
                rig_id=rig.id, version=1, valid_from=datetime(2024, 1, 1, tzinfo=UTC),
                rig_json=doc, rms_px=0.2, quality={"rms_px": 0.2}, source="rig_file",
                status="ready", verdict="good",
            )
        )  # fmt: skip
        db.commit()
        return rig.id


def test_the_capture_page_records_with_another_rig_of_the_clinic(
    client, seeded, db_sessionmaker
) -> None:
    """Toe tapping and leg agility film from another placement, calibrated as a rig of its
    own: the page offers the clinic's other rigs, and with ``?rig=`` asks for that rig's
    resolution and sends its id with the take (the page's script reads data-trial-rig-id)."""
    legs = _leg_rig(db_sessionmaker)
    login(client)
    html = client.get("/sessions/1/capture?task=leg_agility").text
    assert 'data-trial-rig-id=""' in html  # the session's rig: the trial names none
    link = f'href="/sessions/1/capture?rig={legs}&amp;task=leg_agility" data-other-rig="{legs}"'
    assert link in html
    html = client.get(f"/sessions/1/capture?rig={legs}&task=leg_agility").text
    assert f'data-trial-rig-id="{legs}"' in html and f'data-rig-id="{legs}"' in html
    assert 'data-left-size="1280x1024"' in html and 'data-right-size="1280x1024"' in html
    assert "clinic-A legs</a> (not the session's" in html
    assert f'href="/rigs/{legs}/capture">Record the calibration board instead' in html
    assert f'data-other-rig="{seeded["rig_id"]}"' in html  # and back to the session's rig
    for bad in ("999", "x", "²", "9" * 20):
        assert client.get(f"/sessions/1/capture?rig={bad}").status_code == 404


def test_a_take_of_another_rig_is_checked_against_that_rig_and_shown_with_it(
    client, seeded, tiny_videos, db_sessionmaker
) -> None:
    legs = _leg_rig(db_sessionmaker)
    token = login(client)
    session_url = _new_session(client, seeded, token)
    page = client.get(session_url).text
    assert '<select id="rig-left" name="rig_id">' in page  # the upload form offers it
    assert f'<option value="{legs}">clinic-A legs</option>' in page
    left, right = tiny_videos  # 640 x 512 px: the session's rig's size, not the legs rig's
    files = {
        "left_video": ("left.webm", left.read_bytes(), "video/webm"),
        "right_video": ("right.webm", right.read_bytes(), "video/webm"),
    }
    headers = {"X-CSRF-Token": token, "Accept": "application/json"}
    take = {"hand": "left", "task": "leg_agility", "rig_id": str(legs)}
    refused = client.post(f"{session_url}/trials", data=take, files=files, headers=headers)
    assert refused.status_code == 422, refused.text
    assert "1280" in refused.json()["detail"]  # checked against the legs rig's resolution
    assert _count(db_sessionmaker, Trial) == 3  # seeded's only
    with db_sessionmaker() as db:  # the legs rig now stands where the session's did
        legs_rig = db.scalars(select(Rig).where(Rig.id == legs)).one()
        session_rig = db.get(Rig, seeded["rig_id"])
        assert session_rig is not None
        legs_rig.calibrations[0].rig_json = session_rig.calibrations[0].rig_json
        db.commit()
    stored = client.post(f"{session_url}/trials", data=take, files=files, headers=headers)
    assert stored.status_code == 201, stored.text
    with db_sessionmaker() as db:
        trial = db.get(Trial, stored.json()["trial_id"])
        assert trial is not None and trial.rig_id == legs
    page = client.get(session_url).text
    assert f'<span class="hint" data-trial-rig="{legs}">(rig clinic-A legs)</span>' in page
