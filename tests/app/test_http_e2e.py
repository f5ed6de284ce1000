"""The INTERFACES.md REST flow over real HTTP against a running ``bradyscope serve``.

A fresh data directory, an API key made with ``bradyscope admin create-api-key``,
a simulated recording with known truth, uploaded as a hospital system would;
the embedded worker measures it, and result.json must match the simulator's
truth: tap count exact, frequency and mean amplitude within 1 %.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

pytestmark = pytest.mark.slow

JOB_TIMEOUT_S = 300.0  # generous: 2 shared cores; the clip is 2.5 s at 640x512
START_TIMEOUT_S = 60.0


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from app.cli import main; sys.exit(main())", *args]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def recording(simulated_session):
    # Same scenario as tests/app/test_worker.py, so the cached simulation is shared.
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario

    return simulated_session(
        seed=11,
        tapping=TappingScenario(duration_s=2.5),
        imaging=ImagingScenario(image_size=ImageSize(640, 512)),
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    data_dir = tmp_path_factory.mktemp("e2e-data")
    env = {**os.environ, "BRADYSCOPE_DATA_DIR": str(data_dir)}
    env.pop("BRADYSCOPE_DATABASE_URL", None)
    made = subprocess.run(
        _cli("admin", "create-api-key", "hospital-e2e"),
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert made.returncode == 0, made.stderr
    key = next(line for line in made.stdout.splitlines() if line.startswith("bsk_"))
    port = _free_port()
    log_path = data_dir / "serve.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            _cli("serve", "--host", "127.0.0.1", "--port", str(port)),
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            assert proc.poll() is None, log_path.read_text()[-3000:]
            try:
                if httpx.get(f"{base}/health", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.2)  # polling for start-up, not timing anything
        yield base, key
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _check(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, (
        f"{r.request.method} {r.request.url} -> {r.status_code}: {r.text}"
    )
    return r.json()


def test_interfaces_flow_over_http(server: tuple[str, str], recording) -> None:
    base, key = server
    api = httpx.Client(
        base_url=f"{base}/api/v1", headers={"Authorization": f"Bearer {key}"}, timeout=120
    )
    assert httpx.get(f"{base}/api/v1/patients").status_code == 401
    assert httpx.get(f"{base}/openapi.json").json()["info"]["title"] == "bradyscope"

    patient = _check(api.post("/patients", json={"code": "PD-0042"}), 201)
    rig = _check(api.post("/rigs", json={"name": "clinic-A"}), 201)
    cal = _check(
        api.post(
            f"/rigs/{rig['id']}/calibrations",
            files={"rig_json": ("rig.json", recording.rig_path.read_bytes(), "application/json")},
        ),
        201,
    )
    assert cal["status"] == "ready" and cal["job_id"] is None
    session = _check(
        api.post(
            "/sessions",
            json={
                "patient_id": patient["id"],
                "rig_id": rig["id"],
                "recorded_at": "2026-03-01T09:30:00Z",
                "medication_state": "off",
            },
        ),
        201,
    )
    with open(recording.left_video, "rb") as left, open(recording.right_video, "rb") as right:
        trial = _check(
            api.post(
                f"/sessions/{session['id']}/trials",
                data={"hand": "right"},
                files={
                    "left_video": (Path(recording.left_video).name, left),
                    "right_video": (Path(recording.right_video).name, right),
                },
            ),
            201,
        )
    assert set(trial) >= {"id", "job_id"}

    deadline = time.monotonic() + JOB_TIMEOUT_S
    seen_stages = set()
    while True:
        job = _check(api.get(f"/jobs/{trial['job_id']}"), 200)
        assert set(job) >= {"status", "progress", "stage", "error"}
        assert 0.0 <= job["progress"] <= 1.0
        seen_stages.add(job["stage"])
        if job["status"] in ("succeeded", "failed"):
            break
        assert time.monotonic() < deadline, f"job still {job} after {JOB_TIMEOUT_S} s"
        time.sleep(0.5)  # polling the job, as a hospital system does
    assert job["status"] == "succeeded", job["error"]

    result = _check(api.get(f"/trials/{trial['id']}/result"), 200)
    truth = recording.truth
    metrics = result["metrics"]
    assert result["format"] == "bradyscope.result/1"
    assert metrics["tap_count"] == truth["tap_count"]
    assert metrics["frequency_hz"] == pytest.approx(truth["frequency_hz"], rel=0.01)  # 1 %
    assert metrics["amplitude_mm_mean"] == pytest.approx(truth["amplitude_mm_mean"], rel=0.01)

    markers = api.get(f"/trials/{trial['id']}/markers.csv")
    assert markers.status_code == 200
    assert markers.text.splitlines()[0] == (
        "frame,time_s,marker,x_mm,y_mm,z_mm,status,reprojection_px"
    )
    html = api.get(f"/trials/{trial['id']}/report.html")
    assert html.status_code == 200 and "PD-0042" in html.text
    assert "default-src 'self'" in html.headers["content-security-policy"]


def test_oversized_upload_is_refused_before_the_body_is_sent(
    server: tuple[str, str], recording
) -> None:
    """Over a real socket: a declared body above the limit gets 413 at once, unread."""
    base, key = server
    api = httpx.Client(base_url=f"{base}/api/v1", headers={"Authorization": f"Bearer {key}"})
    patient = _check(api.post("/patients", json={"code": "PD-BIG"}), 201)
    rig = _check(api.post("/rigs", json={"name": "clinic-big"}), 201)
    _check(
        api.post(
            f"/rigs/{rig['id']}/calibrations",
            files={"rig_json": ("rig.json", recording.rig_path.read_bytes(), "application/json")},
        ),
        201,
    )
    session = _check(
        api.post(
            "/sessions",
            json={"patient_id": patient["id"], "rig_id": rig["id"], "recorded_at": "2026-03-02"},
        ),
        201,
    )
    host, port = base.removeprefix("http://").split(":")
    request = (
        f"POST /api/v1/sessions/{session['id']}/trials HTTP/1.1\r\n"
        f"Host: {host}\r\n"
        f"Authorization: Bearer {key}\r\n"
        "Content-Type: multipart/form-data; boundary=b\r\n"
        f"Content-Length: {10**13}\r\n"  # 10 TB announced, nothing sent
        "\r\n"
    ).encode()
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(request)
        answer = _read_response(sock)
    assert answer.split("\r\n", 1)[0].split()[1] == "413", answer
    assert "BRADYSCOPE_MAX_UPLOAD_BYTES" in answer
    trials = _check(api.get(f"/sessions/{session['id']}/trials"), 200)
    assert trials == []


def _read_response(sock: socket.socket) -> str:
    """One HTTP response: its head and the body its Content-Length announces.

    The server may write the head and the body in two segments, so one
    ``recv`` can return the head alone.
    """
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            return data.decode("latin-1")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = 0
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            length = int(value.strip())
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return (head + b"\r\n\r\n" + body).decode("latin-1")
