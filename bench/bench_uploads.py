"""Upload speed of the REST API: stream + hash + decode checks + atomic store of one trial.

Prints, for a simulated 640x512 recording (2.5 s at 100 fps, lossless FFV1):
the pair's size, the time of ``POST /sessions/{id}/trials`` through the ASGI
app, the decode check of one video alone, and as a baseline the time to copy
the same bytes on the same disk (measured in the same run), with the ratio.

    python bench/bench_uploads.py            # ~30 s, most of it simulating
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "app"))


def main() -> None:
    from api_support import make_api_key
    from fastapi.testclient import TestClient

    from app.db import get_sessionmaker, migrate
    from app.main import create_app
    from app.settings import Settings
    from app.upload_checks import validate_video
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session

    work = Path(tempfile.mkdtemp(prefix="bench-uploads-"))
    try:
        sim = simulate_session(
            work / "sim",
            seed=11,
            tapping=TappingScenario(duration_s=2.5),
            imaging=ImagingScenario(image_size=ImageSize(640, 512)),
        )
        settings = Settings(data_dir=work / "data")
        migrate(settings)
        key = make_api_key(get_sessionmaker(settings))
        h = {"Authorization": f"Bearer {key}"}
        with TestClient(create_app(settings)) as c:
            p = c.post("/api/v1/patients", json={"code": "BENCH"}, headers=h).json()
            rig = c.post("/api/v1/rigs", json={"name": "bench"}, headers=h).json()
            c.post(
                f"/api/v1/rigs/{rig['id']}/calibrations",
                files={"rig_json": ("rig.json", sim.rig_path.read_bytes())},
                headers=h,
            )
            s = c.post(
                "/api/v1/sessions",
                json={"patient_id": p["id"], "rig_id": rig["id"], "recorded_at": "2026-01-01"},
                headers=h,
            ).json()
            left, right = sim.left_video.read_bytes(), sim.right_video.read_bytes()
            t0 = time.perf_counter()
            r = c.post(
                f"/api/v1/sessions/{s['id']}/trials",
                data={"hand": "left"},
                files={"left_video": ("l.mkv", left), "right_video": ("r.mkv", right)},
                headers=h,
            )
            upload_s = time.perf_counter() - t0
            assert r.status_code == 201, r.text
        t0 = time.perf_counter()
        validate_video(sim.left_video, label="the left video")
        check_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for src in (sim.left_video, sim.right_video):
            shutil.copyfile(src, work / f"copy-{src.name}")
        copy_s = time.perf_counter() - t0
        mb = (len(left) + len(right)) / 1e6
        print(f"pair: {mb:.1f} MB")
        print(
            f"upload (stream, sha256, decode checks, store): {upload_s:.2f} s ({mb / upload_s:.0f} MB/s)"
        )
        print(f"decode check of one video: {check_s:.2f} s")
        print(
            f"baseline, plain copy of the pair: {copy_s:.2f} s; upload/copy = {upload_s / copy_s:.1f}x"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
