# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Each task end to end through the service (issue 16).

Simulated trials of hand movements (both hands), pronation–supination, toe
tapping and leg agility are uploaded through the REST API with their ``task``, measured by the
real worker, and read back: result.json (task, protocol labels, common keys,
the simulator's cycle count), the trial report, the visit report (each task
with its own rows, the right–left asymmetry of hand movements) and the FHIR
Bundle (the task's code system and Observation group).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from api_support import Api, api  # noqa: F401 - fixture

from app.worker import run_worker
from core.camera import ImageSize, StereoRig, write_rig
from core.protocols import marker_diameter_mm
from core.simulation.rig import default_rig
from core.simulation.session import ImagingScenario, SimulatedSession, simulate_session
from core.simulation.tasks import TaskScenario, rig_geometry
from core.tasks import Task

SIZE = ImageSize(640, 512)  # px: small, as the service's demo rig
TRIALS = (  # (task, side, duration_s, frequency_hz)
    (Task.HAND_MOVEMENTS, "right", 4.0, 2.0),
    (Task.HAND_MOVEMENTS, "left", 4.0, 1.8),
    (Task.PRONATION_SUPINATION, "right", 4.0, 1.6),
    (Task.TOE_TAPPING, "right", 3.0, 3.0),
    (Task.LEG_AGILITY, "left", 4.0, 1.8),
)


def _rig(task: Task) -> StereoRig:
    """The visit's rig (the hand tasks, and the foot 800 mm away), or for leg agility the
    cameras placed beside the leg, 1 m away (a rig of its own: the trial names it)."""
    if task is Task.LEG_AGILITY:
        return default_rig(image_size=SIZE, **rig_geometry(task)._asdict())
    return default_rig(image_size=SIZE)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[SimulatedSession]:
    out = []
    for k, (task, side, duration, freq) in enumerate(TRIALS):
        scenario = TaskScenario(task=task, side=side, duration_s=duration, frequency_hz=freq)
        out.append(
            simulate_session(
                tmp_path_factory.mktemp(f"{task.value}-{side}"),
                seed=40 + k,
                task=scenario,
                rig=_rig(task),
                imaging=ImagingScenario(
                    image_size=SIZE,
                    codec="mp4v",  # small files
                    # the foot's and leg's markers are 10 mm (docs/protocols.md): 5 mm at
                    # 800 mm is under 4 px at this size
                    marker_diameter_mm=marker_diameter_mm(task),
                ),
            )
        )
    return out


@pytest.mark.slow
def test_every_task_through_upload_worker_result_reports_and_fhir(
    api: Api, recordings: list[SimulatedSession], tmp_path: Path
) -> None:
    h = api.headers
    patient = api.client.post("/api/v1/patients", json={"code": "PD-0016"}, headers=h).json()
    rigs = {}
    for task, name in ((Task.HAND_MOVEMENTS, "clinic-T"), (Task.LEG_AGILITY, "clinic-T legs")):
        rig = api.client.post("/api/v1/rigs", json={"name": name}, headers=h).json()
        rig_file = tmp_path / f"{name}.json"
        write_rig(_rig(task), rig_file)
        cal = api.client.post(
            f"/api/v1/rigs/{rig['id']}/calibrations",
            files={"rig_json": ("rig.json", rig_file.read_bytes(), "application/json")},
            headers=h,
        )
        assert cal.status_code == 201, cal.text
        rigs[task] = rig["id"]
    rig = {"id": rigs[Task.HAND_MOVEMENTS]}
    session = api.client.post(
        "/api/v1/sessions",
        json={
            "patient_id": patient["id"],
            "rig_id": rig["id"],
            "recorded_at": "2026-11-20T09:30:00Z",
            "medication_state": "on",
        },
        headers=h,
    ).json()
    ids = []
    for (task, side, _, _), rec in zip(TRIALS, recordings, strict=True):
        files = {
            "left_video": ("left.mp4", rec.left_video.read_bytes(), "video/mp4"),
            "right_video": ("right.mp4", rec.right_video.read_bytes(), "video/mp4"),
        }
        # The leg agility trial names the rig placed beside the leg; the others are the
        # session's rig's.
        own = {"rig_id": str(rigs[task])} if task is Task.LEG_AGILITY else {}
        r = api.client.post(
            f"/api/v1/sessions/{session['id']}/trials",
            data={"hand": side, "task": task.value, **own},
            files=files,
            headers=h,
        )
        assert r.status_code == 201, r.text
        ids.append(r.json())
    assert run_worker(api.settings, once=True) == 2 * len(TRIALS)  # each analysis, its PDF

    for (task, _side, _, _), rec, made in zip(TRIALS, recordings, ids, strict=True):
        job = api.client.get(f"/api/v1/jobs/{made['job_id']}", headers=h).json()
        assert job["status"] == "succeeded", job
        doc = api.client.get(f"/api/v1/trials/{made['id']}/result", headers=h).json()
        assert doc["task"] == task.value
        measured_by = rigs.get(task, rig["id"])  # that rig's calibration measured it
        assert doc["calibration"]["rig_id"] == measured_by
        read = api.client.get(f"/api/v1/trials/{made['id']}", headers=h).json()
        assert read["rig_id"] == measured_by
        assert doc["markers"] == rec.truth["marker_names"]
        m = doc["metrics"]
        assert m["amplitude_unit"] == task.amplitude_unit
        assert m["cycle_count"] == rec.truth["cycle_count"]
        assert abs(m["amplitude_mean"] / rec.truth["amplitude_mean"] - 1) < 0.01
        csv = api.client.get(f"/api/v1/trials/{made['id']}/markers.csv", headers=h).text
        assert f",{rec.truth['marker_names'][-1]}," in csv
        report = api.client.get(f"/api/v1/trials/{made['id']}/report.html", headers=h).text
        assert task.heading in report
        fhir = api.client.get(f"/api/v1/trials/{made['id']}/fhir", headers=h).json()
        system = f"urn:bradyscope:{task.value.replace('_', '-')}-metric"
        codes = {
            c["code"]
            for e in fhir["entry"]
            for c in e["resource"].get("code", {}).get("coding", [])
            if c["system"] == system
        }
        assert {"cycle_count", "frequency_hz", f"amplitude_{task.amplitude_unit}_mean"} <= codes
        groups = [e for e in fhir["entry"] if "hasMember" in e["resource"]]
        assert len(groups) == 1
        assert groups[0]["resource"]["code"]["coding"][0]["code"] == task.value.replace("_", "-")

    visit = api.client.get(f"/api/v1/sessions/{session['id']}/report.html", headers=h).text
    la = Task.LEG_AGILITY
    for task in (Task.HAND_MOVEMENTS, Task.PRONATION_SUPINATION, Task.TOE_TAPPING, la):
        assert f'data-task="{task.value}"' in visit and task.heading in visit
    assert "Peak supination velocity" in visit  # the task's own words
    hm = visit.split('data-task="hand_movements"')[1].split('data-task="pronation')[0]
    assert "data-asymmetry" in hm  # right and left hand movements: their asymmetry
