# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Faults answer clearly (issue 18, findings 7-9).

- 7: a full or read-only data directory answers 507/503 with a sentence, nothing is
  half-written, and ``/health`` says so (a real tmpfs, filled up or remounted
  read-only: needs root, as on the development machines and CI);
- 8: deeply nested or malformed JSON on every JSON route is a 400/422, never a 500;
- 9: rig files are validated physically, by the API and by the command line.
"""

from __future__ import annotations

import copy
import errno
import json
import os
import shutil
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from api_support import (
    Api,
    api,  # noqa: F401
    make_api_key,
    rig_document,
    seed_recording_target,
    trial_files,
    video_pair,  # noqa: F401
)
from conftest import make_test_settings
from fastapi.routing import APIRoute, iter_route_contexts
from fastapi.testclient import TestClient

from app import faults
from app.cli import main
from app.db import dispose_engines, get_sessionmaker
from app.main import create_app
from app.models import Job, Patient, Trial, Video
from core.camera import read_rig, rig_from_dict
from core.errors import RigFileError

# --------------------------------------------------------------------------- finding 7


@pytest.fixture
def small_disk(
    tmp_path: Path, _migrated_sqlite_template: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Path]:
    """A 24 MB tmpfs holding a migrated data directory; unmounted afterwards. ``/health``
    probes it at every call here (its verdict must follow the disk filled and freed)."""
    monkeypatch.setattr(faults, "WRITE_CHECK_INTERVAL_S", 0.0)
    mount_point = tmp_path / f"disk-{uuid.uuid4().hex[:8]}"
    mount_point.mkdir()
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mount_point)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        if os.environ.get("CI"):
            pytest.fail(f"cannot mount a tmpfs in CI: {proc.stderr.strip()}")
        pytest.skip(f"cannot mount a tmpfs here (needs root): {proc.stderr.strip()}")
    try:
        data_dir = mount_point / "data"
        data_dir.mkdir()
        shutil.copyfile(_migrated_sqlite_template, data_dir / "bradyscope.sqlite3")
        yield data_dir
    finally:
        dispose_engines()
        subprocess.run(["umount", "-l", str(mount_point)], check=False)


def _fill_up(directory: Path) -> Path:
    """Write a file until the disk is full; returns it (delete it to free the space)."""
    filler = directory / "filler.bin"
    block = b"\0" * (1 << 20)
    with open(filler, "wb", buffering=0) as fh:
        try:
            while True:
                fh.write(block)
                fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        # the last bytes that fit, page by page
        try:
            while True:
                fh.write(b"\0" * 4096)
                fh.flush()
        except OSError:
            pass
    return filler


def _counts(api: Api) -> tuple[int, ...]:
    return api.count(Patient), api.count(Trial), api.count(Video), api.count(Job)


def _leftovers(api: Api) -> list[Path]:
    return [p for p in (api.settings.data_dir / "tmp").rglob("*") if p.is_file()]


def test_a_full_disk_answers_507_and_keeps_nothing_half_written(
    small_disk: Path, video_pair
) -> None:
    settings = make_test_settings(small_disk)
    app = create_app(settings)
    sessions = get_sessionmaker(settings)
    with TestClient(app) as client:
        api = Api(app, client, settings, sessions, make_api_key(sessions))
        seeded = seed_recording_target(api)
        assert client.get("/health").json()["status"] == "ok"
        before, files_before = _counts(api), api.stored_files()
        filler = _fill_up(small_disk)
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(*video_pair),
            headers=api.headers,
        )
        # before: a bare 500
        assert r.status_code == 507, r.text
        assert "storage is full" in r.json()["detail"] and "nothing was saved" in r.json()["detail"]
        health = client.get("/health")
        assert health.status_code == 503 and "full" in health.json()["detail"]
        filler.unlink()
        assert _counts(api) == before and api.stored_files() == files_before
        assert not _leftovers(api)
        assert client.get("/health").status_code == 200
        r = client.post(
            f"/api/v1/sessions/{seeded.session_id}/trials",
            data={"hand": "left"},
            files=trial_files(*video_pair),
            headers=api.headers,
        )
        assert r.status_code == 201, r.text


def test_a_read_only_data_directory_answers_503(small_disk: Path, video_pair) -> None:
    settings = make_test_settings(small_disk)
    app = create_app(settings)
    sessions = get_sessionmaker(settings)
    with TestClient(app) as client:
        api = Api(app, client, settings, sessions, make_api_key(sessions))
        seeded = seed_recording_target(api)
        before = _counts(api)
        # no file may be open for writing when a file system becomes read-only
        app.state.engine.dispose()
        dispose_engines()
        subprocess.run(["mount", "-o", "remount,ro", str(small_disk.parent)], check=True)
        try:
            for method, url, kwargs in (
                ("GET", "/api/v1/patients", {}),  # a read writes its audit event: refused too
                ("POST", "/api/v1/patients", {"json": {"code": "PD-RO"}}),
                (
                    "POST",
                    f"/api/v1/sessions/{seeded.session_id}/trials",
                    {"data": {"hand": "left"}, "files": trial_files(*video_pair)},
                ),
            ):
                r = client.request(method, url, headers=api.headers, **kwargs)
                # before: a bare 500
                assert r.status_code == 503, (url, r.text)
                assert "nothing was saved" in r.json()["detail"], r.text
            health = client.get("/health")
            assert health.status_code == 503  # before: {"status": "ok"} throughout
            assert health.json()["storage"] == "failed"
        finally:
            subprocess.run(["mount", "-o", "remount,rw", str(small_disk.parent)], check=True)
        assert _counts(api) == before and not _leftovers(api)
        assert client.get("/api/v1/patients", headers=api.headers).status_code == 200
        assert client.get("/health").status_code == 200


def test_health_checks_the_database(app_settings, db_sessionmaker) -> None:
    app = create_app(app_settings)
    with TestClient(app) as client:
        body = client.get("/health").json()
        assert body == {"status": "ok", "database": "ok", "storage": "ok"}
    broken = app_settings.model_copy(
        update={"database_url": "postgresql+psycopg://nobody@127.0.0.1:1/none"}
    )
    with TestClient(create_app(broken)) as client:
        r = client.get("/health")
        assert r.status_code == 503 and r.json()["database"] == "failed"
        assert "Database" in r.json()["detail"]


def test_health_tells_free_space_to_authenticated_callers_only(app_settings, db_sessionmaker):
    """A security review: ``/health`` (no authentication) told anyone the data directory's
    free bytes, which follow the clinic's recordings; a load balancer needs the verdict."""
    key = make_api_key(db_sessionmaker, scopes=("results:read",))
    with TestClient(create_app(app_settings)) as client:
        assert "data_dir_free_bytes" not in client.get("/health").json()
        bad = client.get("/health", headers={"Authorization": "Bearer bsk_nope"})
        assert bad.status_code == 200 and "data_dir_free_bytes" not in bad.json()
        body = client.get("/health", headers={"Authorization": f"Bearer {key}"}).json()
        assert body.pop("data_dir_free_bytes") > 0
        assert body == {"status": "ok", "database": "ok", "storage": "ok"}


def test_health_writes_a_file_at_most_every_few_seconds(
    app_settings, db_sessionmaker, monkeypatch
) -> None:
    """A security review: each unauthenticated call wrote, fsynced and removed a file; a
    loop of calls kept the disk busy. The write check's verdict is kept a few seconds."""
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd))[1])
    clock = [1000.0]
    monkeypatch.setattr(faults, "monotonic", lambda: clock[0])
    with TestClient(create_app(app_settings)) as client:
        for _ in range(20):
            assert client.get("/health").status_code == 200
        assert len(synced) == 1
        clock[0] += faults.WRITE_CHECK_INTERVAL_S
        assert client.get("/health").status_code == 200
        assert len(synced) == 2
    assert faults.WRITE_CHECK_INTERVAL_S <= 10  # seconds: a failing disk still shows soon


def test_a_data_directory_that_cannot_be_written_is_said_without_its_path(
    tmp_path: Path, monkeypatch
) -> None:
    """A security review: the public answer named the data directory's absolute path."""
    monkeypatch.setattr(faults, "WRITE_CHECK_INTERVAL_S", 0.0)
    blocked = tmp_path / "secret-location"
    blocked.mkdir()
    (blocked / "tmp").write_text("a file where the directory should be")
    problem = faults._check_writable(blocked)
    assert problem is not None and "cannot be written" in problem
    assert str(tmp_path) not in problem and "secret-location" not in problem


# --------------------------------------------------------------------------- finding 8


def _json_routes(app: Any) -> list[tuple[str, str]]:
    out = []
    for rc in iter_route_contexts(app.routes):
        route = getattr(rc, "route", rc)
        if not isinstance(route, APIRoute) or not rc.path.startswith("/api/v1/"):
            continue
        if route.body_field is None or route.openapi_extra:  # multipart routes parse themselves
            continue
        for method in sorted(route.methods - {"GET", "HEAD"}):
            out.append((method, rc.path.replace("{", "").replace("}", "")))
    return out


@pytest.mark.parametrize(
    "body",
    [b"[" * 50_000, b"{" * 50_000, b'{"a":' * 20_000, b'{"code": ', b"\xff\xfe", b"nan"],
    ids=["deep-list", "deep-object", "deep-keys", "truncated", "not-utf8", "not-json"],
)
def test_deep_or_malformed_json_is_refused_on_every_json_route(api: Api, body: bytes) -> None:
    routes = _json_routes(api.app)
    assert len(routes) >= 5  # patients, sessions, rigs, login...
    for method, path in routes:
        url = path.replace("patient_id", "1").replace("session_id", "1").replace("trial_id", "1")
        url = url.replace("rig_id", "1")
        r = api.client.request(
            method, url, content=body, headers={**api.headers, "Content-Type": "application/json"}
        )
        # before: 500 (RecursionError) for the deep ones
        assert r.status_code in (400, 404, 422), (method, url, r.status_code, r.text[:200])
        assert "detail" in r.json()


def test_a_body_that_is_not_json_is_a_400_and_one_that_is_not_an_object_says_so(
    api: Api,
) -> None:
    """docs/api.md: an unreadable body is a 400 (it was a 422 "0: JSON decode error")."""
    for body in (b"hello", b'{"code": "PD-1",}', b'{"code": '):
        r = api.client.post(
            "/api/v1/patients",
            content=body,
            headers={**api.headers, "Content-Type": "application/json"},
        )
        assert r.status_code == 400, (body, r.text)
        assert "not valid JSON (at character" in r.json()["detail"], r.text
    r = api.client.post(
        "/api/v1/patients",
        content=b'{"code": "PD-1"}',
        headers={**api.headers, "Content-Type": "text/plain"},
    )
    assert r.status_code == 422 and "Content-Type: application/json" in r.json()["detail"]


def test_a_deeply_nested_rig_file_is_a_clear_422(api: Api) -> None:
    seeded = seed_recording_target(api)
    r = api.client.post(
        f"/api/v1/rigs/{seeded.rig_id}/calibrations",
        files={"rig_json": ("rig.json", b"[" * 50_000, "application/json")},
        headers=api.headers,
    )
    assert r.status_code == 422 and "nested too deeply" in r.json()["detail"]


# --------------------------------------------------------------------------- finding 9


def _bad_rig(change: str) -> dict[str, Any]:
    doc = copy.deepcopy(rig_document())
    left, right = doc["cameras"]
    if change == "zero baseline":
        right["t"] = [0.0, 0.0, 0.0]
    elif change == "focal 1e308":
        left["K"][0][0] = 1e308
    elif change == "principal point 1e9":
        left["K"][0][2] = 1e9
    elif change == 'K entry "640"':
        left["K"][0][0] = "640"
    elif change == "K entry true":
        left["K"][1][1] = True
    elif change == "negative focal":
        right["K"][1][1] = -200.0
    elif change == "not a rotation":
        right["R"] = [[2.0, 0, 0], [0, 1, 0], [0, 0, 1]]
    elif change == "image size text":
        left["image_size"] = ["160", 128]
    elif change == "dist null":
        left["dist"] = [0.0, None, 0.0, 0.0, 0.0]
    return doc


BAD_RIGS = {
    "zero baseline": "baseline",
    "focal 1e308": "focal length",
    "principal point 1e9": "principal point",
    'K entry "640"': "the text '640'",
    "K entry true": "JSON number",
    "negative focal": "focal length",
    "not a rotation": "rotation matrix",
    "image size text": "JSON number",
    "dist null": "JSON number",
}


@pytest.mark.parametrize("change", sorted(BAD_RIGS))
def test_impossible_rigs_are_refused_by_the_core_reader(change: str, tmp_path: Path) -> None:
    doc = _bad_rig(change)
    with pytest.raises(RigFileError, match=BAD_RIGS[change]):
        rig_from_dict(doc)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(RigFileError, match=BAD_RIGS[change]):
        read_rig(path)
    rig_from_dict(rig_document())  # the good one passes


def test_impossible_rigs_are_not_stored_as_ready(api: Api) -> None:
    seeded = seed_recording_target(api)
    for change in BAD_RIGS:
        r = api.client.post(
            f"/api/v1/rigs/{seeded.rig_id}/calibrations",
            files={
                "rig_json": ("rig.json", json.dumps(_bad_rig(change)).encode(), "application/json")
            },
            headers=api.headers,
        )
        # before: 201 "ready" for the first five
        assert r.status_code == 422, (change, r.text)
    calibrations = api.client.get(f"/api/v1/rigs/{seeded.rig_id}/calibrations", headers=api.headers)
    assert len(calibrations.json()) == 1  # only the seeded, valid one


def test_the_command_line_refuses_an_impossible_rig(tmp_path: Path, capsys, video_pair) -> None:
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(_bad_rig("zero baseline")))
    left, right = video_pair
    code = main(
        [
            "analyze",
            "--rig",
            str(rig),
            "--left",
            str(left),
            "--right",
            str(right),
            "-o",
            str(tmp_path / "o"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "baseline" in err and "Traceback" not in err


def test_the_openapi_document_lists_the_statuses_every_route_shares(api: Api) -> None:
    """A 1-MiB JSON body is a 413 on any route and the database may be unreachable (503);
    the document listed neither on PATCH /trials/{id} (found by an integrator-style review)."""
    doc = api.client.get("/openapi.json").json()
    patch = doc["paths"]["/api/v1/trials/{trial_id}"]["patch"]["responses"]
    assert {"400", "413", "503"} <= set(patch)
    upload = doc["paths"]["/api/v1/sessions/{session_id}/trials"]["post"]["responses"]
    assert {"400", "413", "415", "503", "507"} <= set(upload)
    get = doc["paths"]["/api/v1/patients/{patient_id}"]["get"]["responses"]
    assert "503" in get and "413" not in get  # no body read there
    r = api.client.patch(
        "/api/v1/trials/1", content=b'{"comment": "' + b"x" * (1 << 20) + b'"}',
        headers={**api.headers, "Content-Type": "application/json"},
    )  # fmt: skip
    assert r.status_code == 413
