"""A trial's marker trajectories for motion-capture tools, as C3D or TRC files.

The files themselves are :mod:`app.trajectories`'; here the trial is loaded as an
export (audited ``c3d_file``/``trc_file``, as :mod:`app.services.results`' exports),
with the focal length its C3D residuals are brought to mm with.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Literal

from sqlalchemy.orm import Session

from app.actors import Actor
from app.errors import NotFoundError
from app.models import Calibration
from app.reports.data import ReportData
from app.services.results import exported, load_report_data, result_of
from app.storage import Storage
from core.camera import rig_from_dict


def left_focal_px(db: Session, data: ReportData) -> float | None:
    """The focal length (px) of the left camera of the calibration that measured the
    trial, for the C3D residuals in mm; None when it is not known."""
    cal_id = data.calibration.id if data.calibration is not None else None
    cal = db.get(Calibration, cal_id) if cal_id is not None else None
    if cal is None or not cal.rig_json:
        return None
    k = rig_from_dict(cal.rig_json, source=f"calibration {cal.id}").cameras[0].K
    return 0.5 * float(k[0, 0] + k[1, 1])


def trajectory_file(
    db: Session,
    actor: Actor,
    trial_id: int,
    kind: Literal["c3d", "trc"],
    storage: Storage,
    revision: int | None = None,
) -> bytes:
    """The marker trajectories of the trial's current result, or of its revision
    ``revision``, as a C3D or TRC file (audited as ``c3d_file``/``trc_file``)."""
    trial, result = result_of(db, actor, trial_id, "export", revision)
    data = load_report_data(db, trial, storage, result, markers=True)
    if data.markers is None:
        raise NotFoundError(f"The markers file of trial {trial.id} is missing from storage.")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"trial.{kind}"
        from app.trajectories import write_c3d, write_trc  # ezc3d: not at start-up

        if kind == "c3d":
            write_c3d(path, data.markers, focal_px=left_focal_px(db, data))
        else:
            write_trc(path, data.markers)
        body = path.read_bytes()
    return exported(db, actor, trial, f"{kind}_file", body)
