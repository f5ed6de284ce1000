"""The form fields of a calibration upload: the board description and ``valid_from``.

Read by :func:`app.services.calibrations.create_calibration` (the API's form and the rig
page's); each bad field is an :class:`app.uploads.InvalidUpload` naming it.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Any

import cv2

from app.models import utcnow
from app.uploads import InvalidUpload, ParsedUpload
from core.boards import BoardSpec

BOARDS = ("chessboard", "charuco")
DEFAULT_DICTIONARY = "DICT_4X4_1000"


def valid_from_field(upload: ParsedUpload, *, first: bool) -> datetime:
    raw = (upload.fields.get("valid_from") or "").strip()
    if raw:
        try:
            value = datetime.fromisoformat(raw.replace("Z", "+00:00"))
        except ValueError as exc:
            what = "valid_from must be an ISO 8601 date-time such as 2026-01-31T08:00:00Z."
            raise InvalidUpload(what, field="valid_from") from exc
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
    # A rig's first calibration (a failed one not counted) also covers sessions recorded
    # before it was uploaded.
    return datetime(1970, 1, 1, tzinfo=UTC) if first else utcnow()


def _number(
    upload: ParsedUpload, name: str, kind: type[int] | type[float], low: float, high: float
) -> Any:
    raw = upload.require_field(name)
    try:
        value = kind(raw)
    except ValueError:
        value = None
    if value is None or not math.isfinite(value) or not low <= value <= high:
        what = "a whole number" if kind is int else "a number"
        raise InvalidUpload(
            f"{upload.labels.get(name, name)} must be {what} between {low:g} and {high:g}.",
            field=name,
        )
    return value


def board_fields(upload: ParsedUpload) -> dict[str, Any]:
    board = upload.require_field("board").lower()
    if board not in BOARDS:
        what = f"board must be 'chessboard' or 'charuco', not {board[:20]!r}."
        raise InvalidUpload(what, field="board")
    fields: dict[str, Any] = {
        "board": board,
        "cols": _number(upload, "cols", int, 2, 200),
        "rows": _number(upload, "rows", int, 2, 200),
        "square_mm": _number(upload, "square_mm", float, 0.1, 1000.0),
    }
    if board == "charuco":
        fields["marker_mm"] = _number(upload, "marker_mm", float, 0.05, 1000.0)
        if fields["marker_mm"] >= fields["square_mm"]:
            raise InvalidUpload(
                "marker_mm must be smaller than square_mm for a ChArUco board.", field="marker_mm"
            )
        dictionary = (upload.fields.get("dictionary") or DEFAULT_DICTIONARY).strip()
        if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
            what = f"dictionary {dictionary[:40]!r} is not an ArUco dictionary name."
            raise InvalidUpload(what, field="dictionary")
        fields["dictionary"] = dictionary
        legacy = (upload.fields.get("legacy") or "").strip().lower()
        if legacy not in ("", "0", "false", "off", "no", "1", "true", "on", "yes"):
            what = f"legacy must be true or false, not {legacy[:20]!r}."
            raise InvalidUpload(what, field="legacy")
        if legacy in ("1", "true", "on", "yes"):
            fields["legacy"] = True  # a board printed with OpenCV before 4.6
    try:  # the measurement library's own rules for a board, too
        BoardSpec(
            kind="charuco" if board == "charuco" else "chessboard",
            cols=fields["cols"],
            rows=fields["rows"],
            square_mm=fields["square_mm"],
            marker_mm=fields.get("marker_mm"),
            dictionary=fields.get("dictionary"),
            legacy=bool(fields.get("legacy", False)),
        )
    except ValueError as exc:
        raise InvalidUpload(f"The board description is invalid: {exc}.") from exc
    return fields
