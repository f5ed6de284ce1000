"""Helpers and fixtures for the REST API tests (imported by tests/app/test_api_*.py & co).

Everything runs over a real temporary SQLite database migrated by Alembic
(``app_settings`` from conftest.py) and real files: the videos are genuine
MPEG-4 files written with ``core.video.VideoWriter``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from app.apikeys import SCOPES, generate_api_key, hash_api_key
from app.main import create_app
from app.models import ApiClient, AuditEvent, Job, Result, Trial, User, Video
from app.passwords import hash_password
from app.settings import Settings
from app.storage import Storage
from core.camera import Camera, ImageSize, StereoRig, rig_to_dict
from core.video import VideoWriter

VIDEO_SIZE = ImageSize(160, 128)  # px, small on purpose: uploads are checked, not measured
VIDEO_FPS = 30.0  # Hz


def make_api_key(
    sessions: sessionmaker[Session], *, name: str = "hospital", scopes: tuple[str, ...] = SCOPES
) -> str:
    """Create an API client with ``scopes``; returns its key."""
    key, prefix = generate_api_key()
    with sessions() as db:
        db.add(
            ApiClient(name=name, key_prefix=prefix, key_hash=hash_api_key(key), scopes=list(scopes))
        )
        db.commit()
    return key


def make_user(
    sessions: sessionmaker[Session], email: str, password: str, *, role: str = "clinician"
) -> int:
    with sessions() as db:
        user = User(email=email.lower(), password_hash=hash_password(password), role=role)
        db.add(user)
        db.commit()
        return user.id


def write_video(
    path: Path,
    *,
    n_frames: int = 12,
    size: ImageSize = VIDEO_SIZE,
    fps: float = VIDEO_FPS,
    codec: str = "mp4v",
    noise: bool = False,
    shift_px: int = 0,
) -> Path:
    """A real video (MPEG-4 by default) of a bright dot moving on grey (or on noise).

    ``shift_px`` moves the dot sideways: the right camera's video of a pair differs
    from the left one (two identical files are refused as a pair).
    """
    yy, xx = np.mgrid[0 : size.height, 0 : size.width]
    rng = np.random.default_rng(3)
    with VideoWriter(path, fps=fps, image_size=size, codec=codec) as writer:
        for i in range(n_frames):
            frame = np.full((size.height, size.width), 60, np.uint8)
            if noise:  # incompressible: every frame takes its share of the file
                frame = rng.integers(0, 200, (size.height, size.width), dtype=np.uint8)
            cx, cy = 20 + shift_px + 5 * i, size.height / 2
            frame[(xx - cx) ** 2 + (yy - cy) ** 2 < 36] = 230
            writer.write(frame)
    return path


def rig_document(size: ImageSize = VIDEO_SIZE) -> dict[str, Any]:
    """A valid rig file (bradyscope.rig/1) for cameras of ``size`` with a 100 mm baseline."""
    K = np.array([[200.0, 0, size.width / 2], [0, 200.0, size.height / 2], [0, 0, 1]])
    left = Camera("left", size, K)
    right = Camera("right", size, K, t_cam_from_world_mm=np.array([-100.0, 0.0, 0.0]))
    return rig_to_dict(StereoRig(left, right, {"rms_px": 0.2}))


@dataclass
class Api:
    """A test client of a fresh app, with a full-scope API key."""

    app: Any
    client: TestClient
    settings: Settings
    sessions: sessionmaker[Session]
    key: str

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.key}"}

    def count(self, model: Any) -> int:
        with self.sessions() as db:
            return int(db.scalar(select(func.count()).select_from(model)) or 0)

    def audit_events(self) -> list[AuditEvent]:
        with self.sessions() as db:
            return list(db.scalars(select(AuditEvent).order_by(AuditEvent.id)))

    def stored_files(self) -> list[Path]:
        """Every file under the data directory's ``files/`` and ``tmp/``."""
        data = self.settings.data_dir
        return sorted(p for d in ("files", "tmp") for p in (data / d).rglob("*") if p.is_file())

    def recording_rows(self) -> tuple[int, int, int]:
        return self.count(Trial), self.count(Video), self.count(Job)


@pytest.fixture
def api(app_settings: Settings, db_sessionmaker: sessionmaker[Session]) -> Iterator[Api]:
    app = create_app(app_settings)
    key = make_api_key(db_sessionmaker)
    with TestClient(app) as client:
        yield Api(app, client, app_settings, db_sessionmaker, key)


@pytest.fixture(scope="session")
def video_pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("videos")
    return write_video(folder / "left.mp4"), write_video(folder / "right.mp4", shift_px=2)


@dataclass(frozen=True)
class Seeded:
    patient_id: int
    rig_id: int
    calibration_id: int
    session_id: int


def seed_recording_target(
    api: Api,
    *,
    rig_json: bytes | None = None,
    patient_code: str = "PD-0042",
    rig_name: str = "clinic-A",
) -> Seeded:
    """Patient, rig with a rig-file calibration (``rig_json``, default one of the test
    video size), and a session (off medication, 2026-03-01 09:30 UTC)."""
    import json

    if rig_json is None:
        rig_json = json.dumps(rig_document()).encode()
    h = api.headers
    patient = api.client.post("/api/v1/patients", json={"code": patient_code}, headers=h)
    rig = api.client.post("/api/v1/rigs", json={"name": rig_name}, headers=h)
    assert patient.status_code == 201 and rig.status_code == 201, (patient.text, rig.text)
    cal = api.client.post(
        f"/api/v1/rigs/{rig.json()['id']}/calibrations",
        files={"rig_json": ("rig.json", rig_json, "application/json")},
        headers=h,
    )
    assert cal.status_code == 201, cal.text
    session = api.client.post(
        "/api/v1/sessions",
        json={
            "patient_id": patient.json()["id"],
            "rig_id": rig.json()["id"],
            "recorded_at": "2026-03-01T09:30:00Z",
            "medication_state": "off",
        },
        headers=h,
    )
    assert session.status_code == 201, session.text
    return Seeded(patient.json()["id"], rig.json()["id"], cal.json()["id"], session.json()["id"])


def trial_files(
    left: Path | bytes, right: Path | bytes, *, names=("left.mp4", "right.mp4")
) -> dict:
    def content(x: Path | bytes) -> bytes:
        return x if isinstance(x, bytes) else Path(x).read_bytes()

    return {
        "left_video": (names[0], content(left), "video/mp4"),
        "right_video": (names[1], content(right), "video/mp4"),
    }


def add_result(api: Api, trial_id: int) -> None:
    """Store a known result for a trial, as the worker would (synthetic, not measured)."""
    from sample_trial import synthetic_trial

    from core.markers_csv import markers_csv_text

    markers, document = synthetic_trial()
    stored = Storage.from_settings(api.settings).write_bytes(
        "results", ".csv", markers_csv_text(markers).encode()
    )
    with api.sessions() as db:
        trial = db.get(Trial, trial_id)
        assert trial is not None
        trial.status = "succeeded"
        db.add(Result(trial_id=trial_id, document=document, markers_path=stored.path))
        db.commit()
