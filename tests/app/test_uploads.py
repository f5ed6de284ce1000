# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Uploads: accepted ones are stored completely; rejected ones leave nothing behind.

Every rejection is checked three ways: a 4xx with a clear sentence, no Trial /
Video / Job row, and no file under the data directory (stored or temporary).
"""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path

import httpx
import numpy as np
import pytest
from api_support import (  # noqa: F401 - fixtures
    Api,
    api,
    seed_recording_target,
    trial_files,
    video_pair,
    write_video,
)
from sqlalchemy import select

from app.models import Calibration, Job, Trial, Video
from core.camera import ImageSize


def _png_bytes() -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.full((64, 64), 128, np.uint8))
    assert ok
    return buf.tobytes()


def _assert_nothing_left(api: Api) -> None:
    assert api.recording_rows() == (0, 0, 0)
    assert api.stored_files() == []


def test_trial_upload_stores_videos_and_queues_one_job(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    left, right = video_pair
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "right"},
        files=trial_files(left, right),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text
    body = r.json()
    with api.sessions() as db:
        trial = db.get(Trial, body["id"])
        assert trial is not None and trial.hand == "right" and trial.status == "queued"
        videos = {v.side: v for v in db.scalars(select(Video).where(Video.trial_id == trial.id))}
        job = db.get(Job, body["job_id"])
        assert job is not None and job.kind == "analyze_trial" and job.trial_id == trial.id
    assert set(videos) == {"left", "right"}
    for side, source in (("left", left), ("right", right)):
        stored = api.settings.data_dir / videos[side].path
        data = Path(source).read_bytes()
        assert stored.read_bytes() == data  # stored byte for byte
        assert videos[side].sha256 == hashlib.sha256(data).hexdigest()
        assert videos[side].size_bytes == len(data)
        assert (videos[side].width, videos[side].height) == (160, 128)  # px, as written
        assert videos[side].frame_count == 12
        assert videos[side].original_filename == f"{side}.mp4"
        # server-generated path: the client's name never reaches the file system
        assert f"{side}.mp4" not in videos[side].path
    assert not list((api.settings.data_dir / "tmp").iterdir())


@pytest.mark.parametrize(
    ("case", "status", "words"),
    [
        ("empty", 415, "empty"),
        ("png_renamed", 415, "left.mp4 is a PNG image, not a video"),
        ("text_renamed", 415, "video"),
        ("truncated", 415, "left video"),
        ("truncated_mkv", 415, "incomplete"),
        ("corrupt", 415, "left video"),
        ("missing_right", 422, "right_video"),
        ("bad_hand", 422, "hand"),
        ("size_mismatch", 422, "160x128"),
    ],
)
def test_rejected_trial_upload_leaves_nothing(
    api: Api, video_pair, tmp_path: Path, case: str, status: int, words: str
) -> None:
    seeded = seed_recording_target(api)
    left, right = video_pair
    good = Path(left).read_bytes()
    data = {"hand": "left"}
    if case == "empty":
        files = trial_files(b"", right)
    elif case == "png_renamed":
        files = trial_files(_png_bytes(), right)
    elif case == "text_renamed":
        files = trial_files(b"this is not a video, just text\n" * 50, right)
    elif case == "truncated":
        files = trial_files(good[: len(good) // 2], right)
    elif case == "truncated_mkv":  # header intact, frames cut off: found by decoding the end
        whole = write_video(tmp_path / "l.mkv", codec="lossless", noise=True).read_bytes()
        # 12 incompressible frames (each ~8 % of the file): cutting 20 % loses the last 3,
        # one more than the 2 frames of slack a container's frame count is allowed
        files = trial_files(whole[: int(len(whole) * 0.8)], right, names=("l.mkv", "r.mp4"))
    elif case == "corrupt":
        rng = np.random.default_rng(7)
        files = trial_files(rng.integers(0, 256, len(good), dtype=np.uint8).tobytes(), right)
    elif case == "missing_right":
        files = {"left_video": trial_files(left, right)["left_video"]}
    elif case == "bad_hand":
        files, data = trial_files(left, right), {"hand": "both"}
    elif case == "size_mismatch":
        other = write_video(tmp_path / "big.mp4", size=ImageSize(192, 128))
        files = trial_files(left, other)
    else:  # pragma: no cover
        raise AssertionError(case)
    seeded_files = api.stored_files()  # nothing is stored for a rig-file calibration
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials", data=data, files=files, headers=api.headers
    )
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    assert words in detail and detail.endswith(".")
    assert api.recording_rows() == (0, 0, 0)
    assert api.stored_files() == seeded_files == []


def test_oversized_upload_is_refused_with_413_and_leaves_nothing(
    app_settings, db_sessionmaker
) -> None:
    from api_support import make_api_key
    from fastapi.testclient import TestClient

    from app.main import create_app

    settings = app_settings.model_copy(update={"max_upload_bytes": 20_000})
    big = bytes(200_000)  # 10x the limit
    key = make_api_key(db_sessionmaker)
    with TestClient(create_app(settings)) as client:
        api = Api(client.app, client, settings, db_sessionmaker, key)
        seeded = seed_recording_target(api)
        # declared length above the limit: refused before reading the body
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(big, big),
            headers=api.headers,
        )
        assert r.status_code == 413, r.text
        assert "limit" in r.json()["detail"]
        # streamed without a length (chunked): refused at the limit while streaming
        boundary = "xyzBOUNDARY"
        body = (
            (
                f'--{boundary}\r\nContent-Disposition: form-data; name="hand"\r\n\r\nleft\r\n'
                f'--{boundary}\r\nContent-Disposition: form-data; name="left_video"; '
                'filename="l.mp4"\r\nContent-Type: video/mp4\r\n\r\n'
            ).encode()
            + big
            + f"\r\n--{boundary}--\r\n".encode()
        )

        def chunks():
            for i in range(0, len(body), 8192):
                yield body[i : i + 8192]

        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            content=chunks(),
            headers={**api.headers, "Content-Type": f"multipart/form-data; boundary={boundary}"},
        )
        assert r.status_code == 413, r.text
        assert "left video" in r.json()["detail"]
        _assert_nothing_left(api)


def test_upload_that_is_not_multipart_is_refused(api: Api) -> None:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        json={"hand": "left"},
        headers=api.headers,
    )
    assert r.status_code == 415
    assert "multipart/form-data" in r.json()["detail"]
    _assert_nothing_left(api)


def test_malformed_multipart_body_is_refused(api: Api) -> None:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        content=b'--b\r\nContent-Disposition: form-data; name="left_video"; filename="x"\r\n\r\nabc',
        headers={**api.headers, "Content-Type": "multipart/form-data; boundary=b"},
    )
    assert r.status_code == 400, r.text
    _assert_nothing_left(api)


def test_upload_for_unknown_session_is_404_before_reading(api: Api, video_pair) -> None:
    left, right = video_pair
    r = api.client.post(
        "/api/v1/sessions/999/trials",
        data={"hand": "left"},
        files=trial_files(left, right),
        headers=api.headers,
    )
    assert r.status_code == 404
    _assert_nothing_left(api)


def test_ten_concurrent_uploads_all_succeed(api: Api, video_pair) -> None:
    seeded = seed_recording_target(api)
    left, right = video_pair
    files = trial_files(left, right)

    async def upload_all() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=api.app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await asyncio.gather(
                *(
                    client.post(
                        f"/api/v1/sessions/{seeded.session_id}/trials",
                        data={"hand": "left" if i % 2 else "right"},
                        files=files,
                        headers=api.headers,
                        timeout=60,
                    )
                    for i in range(10)
                )
            )

    responses = asyncio.run(upload_all())
    assert [r.status_code for r in responses] == [201] * 10, [r.text for r in responses]
    assert len({r.json()["id"] for r in responses}) == 10
    assert api.recording_rows() == (10, 20, 10)
    assert len(api.stored_files()) == 20


# -- calibration uploads -----------------------------------------------------------


def test_calibration_from_board_videos_queues_a_calibrate_job(api: Api, video_pair) -> None:
    h = api.headers
    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-B"}, headers=h).json()
    left, right = video_pair
    r = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        data={"board": "charuco", "cols": "7", "rows": "5", "square_mm": "30", "marker_mm": "22"},
        files=trial_files(left, right),
        headers=h,
    )
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["status"] == "pending" and body["job_id"] is not None
    with api.sessions() as db:
        job = db.get(Job, body["job_id"])
        assert job is not None and job.kind == "calibrate" and job.calibration_id == body["id"]
        assert db.scalar(select(Video.calibration_id).where(Video.side == "left")) == body["id"]
    listed = api.client.get(f"/api/v1/rigs/{rig['id']}/calibrations", headers=h).json()
    assert [c["board"]["dictionary"] for c in listed] == ["DICT_4X4_1000"]
    assert len(api.stored_files()) == 2
    # Its rig file is not ready yet: 409, as every "not ready" of the API (docs/api.md).
    rig_file = api.client.get(f"/api/v1/calibrations/{body['id']}/rig.json", headers=h)
    assert rig_file.status_code == 409 and "is being computed" in rig_file.json()["detail"]
    with api.sessions() as db:  # as the worker leaves a calibration that failed
        db.get(Job, body["job_id"]).status = "failed"
        db.get(Job, body["job_id"]).error = "the board was found in 4 of 120 left frames."
        db.get(Calibration, body["id"]).status = "failed"
        db.commit()
    rig_file = api.client.get(f"/api/v1/calibrations/{body['id']}/rig.json", headers=h)
    assert rig_file.status_code == 409, rig_file.text
    assert "failed: the board was found in 4 of 120 left frames. Retry" in rig_file.json()["detail"]


def test_board_videos_with_timestamps_files_are_timed_by_them(api: Api, tmp_path: Path) -> None:
    """A browser take sends each frame's capture time (as with a trial): a right WebM whose
    recorder squeezed its times (here: 90 frames stamped at 60 fps, 1.5 s, beside a 3-s
    left video) is refused as another recording without them, and with them is stored
    and handed to the calibration job at its real 30 fps."""
    from app.services.calibrations import calibration_inputs
    from app.storage import Storage

    h = api.headers
    rig = api.client.post("/api/v1/rigs", json={"name": "browser-boards"}, headers=h).json()
    left = write_video(tmp_path / "left.mp4", n_frames=90, fps=30.0)
    right = write_video(tmp_path / "right.mp4", n_frames=90, fps=60.0, shift_px=2)
    board = {"board": "chessboard", "cols": "9", "rows": "6", "square_mm": "25"}
    url = f"/api/v1/rigs/{rig['id']}/calibrations"
    refused = api.client.post(url, data=board, files=trial_files(left, right), headers=h)
    assert refused.status_code == 422, refused.text
    assert "cannot be recordings of the same test" in refused.json()["detail"]

    def times_csv(origin_s: float) -> bytes:
        return (
            "frame,time_s\n" + "".join(f"{i},{origin_s + i / 30:.6f}\n" for i in range(90))
        ).encode()

    files = {
        **trial_files(left, right),
        "left_times": ("left_times.csv", times_csv(12.0), "text/csv"),
        "right_times": ("right_times.csv", times_csv(40.5), "text/csv"),
    }
    r = api.client.post(url, data=board, files=files, headers=h)
    assert r.status_code == 201, r.text
    with api.sessions() as db:
        videos = {v.side: v for v in db.scalars(select(Video))}
        assert {side: v.fps for side, v in videos.items()} == pytest.approx(
            {"left": 30.0, "right": 30.0}, abs=0.01
        )
        inputs = calibration_inputs(db, Storage.from_settings(api.settings), r.json()["id"])
    assert inputs.right_times is not None and inputs.right_times.read_bytes() == times_csv(40.5)
    assert inputs.left_times is not None and inputs.left_times.read_bytes() == times_csv(12.0)
    assert len(api.stored_files()) == 4


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"board": "charuco", "cols": "7", "rows": "5", "square_mm": "30"}, "marker_mm"),
        ({"board": "circles", "cols": "7", "rows": "5", "square_mm": "30"}, "board"),
        ({"board": "chessboard", "cols": "1", "rows": "5", "square_mm": "30"}, "cols"),
        ({"board": "chessboard", "cols": "9", "rows": "6", "square_mm": "-3"}, "square_mm"),
        ({"board": "chessboard", "cols": "7", "rows": "7", "square_mm": "25"}, "symmetric"),
    ],
)
def test_calibration_with_bad_board_fields_leaves_nothing(
    api: Api, video_pair, fields: dict, words: str
) -> None:
    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-B"}, headers=api.headers).json()
    left, right = video_pair
    r = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        data=fields,
        files=trial_files(left, right),
        headers=api.headers,
    )
    assert r.status_code == 422, r.text
    assert words in r.json()["detail"]
    assert api.count(Job) == 0 and api.count(Video) == 0 and api.stored_files() == []


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "empty"),
        (b"{not json", "JSON"),
        (b'{"format": "bradyscope.rig/9", "cameras": []}', "format"),
    ],
)
def test_bad_rig_file_is_refused(api: Api, content: bytes, words: str) -> None:
    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-C"}, headers=api.headers).json()
    r = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        files={"rig_json": ("rig.json", content, "application/json")},
        headers=api.headers,
    )
    assert r.status_code == 422, r.text
    assert words in r.json()["detail"]
    assert api.stored_files() == []
    assert (
        api.client.get(f"/api/v1/rigs/{rig['id']}/calibrations", headers=api.headers).json() == []
    )


def test_upload_for_a_rig_without_calibration_is_409(api: Api, video_pair) -> None:
    h = api.headers
    patient = api.client.post("/api/v1/patients", json={"code": "PD-1"}, headers=h).json()
    rig = api.client.post("/api/v1/rigs", json={"name": "uncalibrated"}, headers=h).json()
    session = api.client.post(
        "/api/v1/sessions",
        json={"patient_id": patient["id"], "rig_id": rig["id"], "recorded_at": "2026-03-01T09:00"},
        headers=h,
    ).json()
    r = api.client.post(
        f"/api/v1/sessions/{session['id']}/trials",
        data={"hand": "left"},
        files=trial_files(*video_pair),
        headers=h,
    )
    assert r.status_code == 409
    assert "calibration" in r.json()["detail"]
    _assert_nothing_left(api)


def test_an_upload_that_stalls_is_dropped_and_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    """An operations review held an upload at 70 % for 150 s: its partial file stayed the
    whole time and a stopping server waited for it. Nothing arriving for UPLOAD_STALL_S
    drops it (400) and removes what was received."""
    import asyncio

    from starlette.requests import Request

    from app import uploads
    from app.storage import Storage

    monkeypatch.setattr(uploads, "UPLOAD_STALL_S", 0.3)
    storage = Storage(tmp_path / "data", report_cache_bytes=1 << 20)
    boundary = "b0undary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="left_video";'
        ' filename="l.mp4"\r\nContent-Type: video/mp4\r\n\r\n'
    ).encode() + b"\0" * 50_000
    sent = []

    async def receive():
        if not sent:
            sent.append(1)
            return {"type": "http.request", "body": head, "more_body": True}
        await asyncio.sleep(3600)  # the client holds the connection and sends nothing
        raise AssertionError("not reached")

    scope = {
        "type": "http", "method": "POST", "path": "/x", "query_string": b"",
        "headers": [(b"content-type", f"multipart/form-data; boundary={boundary}".encode()),
                    (b"content-length", b"200000")],
    }  # fmt: skip
    request = Request(scope, receive)

    async def upload():
        return await uploads.receive_multipart(
            request, storage=storage, file_fields={"left_video": ".video"}, max_file_bytes=1 << 30
        )

    with pytest.raises(uploads.UploadError, match="stalled: nothing arrived"):
        asyncio.run(asyncio.wait_for(upload(), 10))
    assert [p for p in storage.tmp_dir.rglob("*") if p.is_file()] == []


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        ({"foo": "bar"}, ["foo"]),
        ({"takeid": "take-0001", "offset_frame": "3"}, ["takeid", "offset_frame"]),
    ],
)
def test_an_upload_with_a_field_the_route_does_not_take_is_refused(
    api: Api, video_pair, extra: dict, named: list[str]
) -> None:
    """A misspelt field was dropped without a word (the trial stored without its take_id or
    offset); the JSON routes refuse extra fields with extra_forbidden, the uploads too."""
    seeded = seed_recording_target(api)
    events = len(api.audit_events())
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left", **extra},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["errors"] == [
        {"loc": ["body", n], "msg": "Extra inputs are not permitted", "type": "extra_forbidden"}
        for n in named
    ]
    assert all(repr(n) in body["detail"] for n in named) and "take_id" in body["detail"]
    _assert_nothing_left(api)
    outcomes = [(e.action, e.resource_type, e.outcome) for e in api.audit_events()[events:]]
    assert outcomes == [("create", "trial", "invalid")]


def test_a_calibration_upload_with_a_misspelt_field_is_refused(api: Api) -> None:
    import json

    from api_support import rig_document

    rig = api.client.post("/api/v1/rigs", json={"name": "clinic-D"}, headers=api.headers).json()
    r = api.client.post(
        f"/api/v1/rigs/{rig['id']}/calibrations",
        data={"valid_form": "2026-01-01T00:00:00Z"},
        files={"rig_json": ("rig.json", json.dumps(rig_document()).encode(), "application/json")},
        headers=api.headers,
    )
    assert r.status_code == 422, r.text
    assert [e["loc"] for e in r.json()["errors"]] == [["body", "valid_form"]]
    assert "valid_from" in r.json()["detail"]  # the fields it takes are listed
    assert (
        api.client.get(f"/api/v1/rigs/{rig['id']}/calibrations", headers=api.headers).json() == []
    )


def test_a_csrf_token_field_is_not_an_unknown_field(api: Api, video_pair) -> None:
    """A browser's script may send its form's csrf_token with an upload to the API (which
    reads the token from the X-CSRF-Token header): it is dropped, not refused."""
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left", "csrf_token": "anything"},
        files=trial_files(*video_pair),
        headers=api.headers,
    )
    assert r.status_code == 201, r.text


def test_the_openapi_document_says_uploads_take_no_other_field(api: Api) -> None:
    doc = api.client.get("/openapi.json").json()
    for path in ("/api/v1/sessions/{session_id}/trials", "/api/v1/rigs/{rig_id}/calibrations"):
        body = doc["paths"][path]["post"]["requestBody"]["content"]["multipart/form-data"]
        assert body["schema"]["additionalProperties"] is False


def test_an_earlier_trial_of_the_same_two_videos_is_named_as_sent_twice_or_swapped() -> None:
    """Finding 12 of the failure review: the same two videos uploaded with the cameras the
    other way round were warned of as "the same two videos" sent twice."""
    from app.upload_checks import sent_before

    left, right, other = "a" * 64, "b" * 64, "c" * 64
    earlier = [
        (3, "left", left), (3, "right", right),  # the same, as the same cameras
        (5, "left", right), (5, "right", left),  # the same, the other way round
        (7, "left", left), (7, "right", other),  # one video in common: nothing to say
    ]  # fmt: skip
    said = sent_before(earlier, left_sha256=left, right_sha256=right)
    assert said == [
        "trial 3 of this session holds the same two videos: if they were sent twice, hide one"
        " of the two trials.",
        "trial 5 of this session holds these two videos with the cameras the other way round:"
        " to measure them swapped, “Measure again” on trial 5 does it without a second trial;"
        " if that is why they were sent, hide one of the two.",
    ]
    assert sent_before(earlier[4:], left_sha256=left, right_sha256=right) == []
