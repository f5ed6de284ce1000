"""The algorithm version changes when, and only when, the numbers would change."""

from __future__ import annotations

import hashlib
import json

from core.metrics import compute_metrics
from core.simulation.kinematics import TappingScenario, simulate_tapping
from core.version import ALGORITHM_VERSION, software_document, software_version

# The measurement of one fixed simulated recording, rounded to 6 significant digits,
# hashed. When a change of core moves these numbers, bump ALGORITHM_VERSION in
# core/version.py and put the new pair here (the test prints the new digest).
PINNED = {
    "2026.1": "bf61c45b3ab9",
    # metrics at the frames' real capture times (core.resample): even frames unchanged
    "2026.2": "bf61c45b3ab9",
    # gray frames of AV1 videos: their luma plane, as for every other codec
    "2026.3": "bf61c45b3ab9",
    # lost frames from the room in the time line, not from long intervals (jittered times)
    "2026.4": "bf61c45b3ab9",
}


def _digest() -> str:
    truth = simulate_tapping(
        TappingScenario(
            duration_s=5.0,
            fps=100.0,
            decrement_mm_per_tap=-1.0,
            hesitations=(6,),
            halts=((8, 0.5),),
        ),
        seed=5,
    )
    result = compute_metrics(truth.positions_mm, 100.0).to_result()
    numbers = {k: v for k, v in result.items() if k in ("metrics", "metrics_first_10", "taps")}
    text = json.dumps(numbers, sort_keys=True, default=lambda v: v, allow_nan=True)
    rounded = json.dumps(
        json.loads(text, parse_float=lambda s: float(f"{float(s):.6g}")), sort_keys=True
    )
    return hashlib.sha256(rounded.encode()).hexdigest()[:12]


def test_numbers_match_the_algorithm_version():
    digest = _digest()
    assert PINNED.get(ALGORITHM_VERSION) == digest, (
        f"the measurement of the reference recording is now {digest}: if core changed the"
        f" numbers on purpose, bump ALGORITHM_VERSION (now {ALGORITHM_VERSION}) and pin the"
        " new digest in tests/core/test_version.py"
    )


def test_software_document():
    doc = software_document()
    assert doc == {"version": software_version(), "algorithm": ALGORITHM_VERSION}
    assert doc["version"] != "unknown"  # the package is installed (pip install -e .)


def test_result_document_names_the_software():
    import numpy as np

    from core.pipeline import Analysis

    analysis = Analysis(
        fps=100.0,
        frame_numbers=np.arange(0),
        positions_mm=np.zeros((0, 2, 3)),
        status=np.zeros((0, 2), dtype="<U12"),
        reprojection_px=np.zeros((0, 2)),
        marker_names=("thumb", "index"),
        sync={},
    )
    assert analysis.result_document()["software"] == software_document()
