"""Calibration boards: their geometry and their detection in an image.

Two kinds of board are supported (INTERFACES.md, ``bradyscope calibrate``):

- ``chessboard``: ``cols x rows`` count the **inner corners** (OpenCV's pattern
  size). Corner ``k = r * cols + c`` sits at ``(c * square_mm, r * square_mm, 0)``
  in the board frame, in the order ``cv2.findChessboardCorners`` reports them.
- ``charuco``: ``cols x rows`` count the **squares** (OpenCV's ``CharucoBoard``
  size); corner ids and positions are ``CharucoBoard.getChessboardCorners()``:
  id ``k = r * (cols - 1) + c`` at ``((c + 1) * square_mm, (r + 1) * square_mm, 0)``.
  ChArUco boards may be seen partially.

The board frame has ``x`` along the columns, ``y`` along the rows (down the
printed board) and ``z`` into the board, so a camera facing the printed side
sees it with ``z`` pointing away from the camera.

Chessboard corners are located by ``cv2.findChessboardCorners`` followed by
``cv2.cornerSubPix`` with a window sized to the squares (``method="classic"``,
the default; ``"sb"`` uses the sector-based ``cv2.findChessboardCornersSB``
and ``"auto"`` falls back to it when the classic detector finds nothing).
``"classic"`` is the default because, on simulated boards with known corners the ``cornerSubPix`` corners
are about twice as accurate as ``findChessboardCornersSB(CALIB_CB_ACCURACY)``
(RMS ~0.035 px against ~0.07 px), ten times faster, and ``findChessboardCornersSB``
sometimes reports a grid one row or column larger than the board (into its
white margin) when the size asked for is wrong; see
``bench/bench_calibration.py`` and docs/calibration.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from core.camera import ImageSize

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

BoardKind = Literal["chessboard", "charuco"]
ChessboardMethod = Literal["auto", "classic", "sb"]

BOARD_FORMAT = "bradyscope.board/1"

#: Fewest ChArUco corners accepted in one view (a homography needs 4; 6 keeps
#: degenerate, nearly collinear partial views out).
MIN_CHARUCO_CORNERS = 6


@dataclass(frozen=True)
class BoardSpec:
    """A planar calibration board.

    Attributes
    ----------
    kind : {"chessboard", "charuco"}
    cols, rows : int
        Chessboard: inner corners per row / per column. ChArUco: squares.
    square_mm : float
        Side of one square (mm), as measured on the printed board.
    marker_mm : float or None
        ChArUco only: side of one ArUco marker (mm), smaller than ``square_mm``.
    dictionary : str or None
        ChArUco only: an OpenCV predefined dictionary name such as
        ``"DICT_4X4_1000"`` (the default when omitted).
    legacy : bool
        ChArUco only: the layout of boards printed with OpenCV before 4.6
        (``CharucoBoard.setLegacyPattern``): with an even number of rows,
        the top-left square is white instead of black, so the markers sit
        in the other squares. Boards with an odd number of rows are the same
        either way.
    """

    kind: BoardKind
    cols: int
    rows: int
    square_mm: float
    marker_mm: float | None = None
    dictionary: str | None = None
    legacy: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise ValueError(f"board kind must be 'chessboard' or 'charuco', got {self.kind!r}")
        if int(self.cols) != self.cols or int(self.rows) != self.rows:
            raise ValueError(f"cols and rows must be integers, got {self.cols}x{self.rows}")
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "square_mm", float(self.square_mm))
        if not (np.isfinite(self.square_mm) and self.square_mm > 0):
            raise ValueError(f"square_mm must be a positive length, got {self.square_mm}")
        if self.kind == "chessboard":
            if self.cols < 3 or self.rows < 3:
                raise ValueError(
                    f"a chessboard needs at least 3x3 inner corners, got {self.cols}x{self.rows}"
                )
            if self.cols == self.rows:
                raise ValueError(
                    f"a {self.cols}x{self.rows} chessboard is symmetric, so its orientation is"
                    " ambiguous; use a board whose inner-corner counts differ (e.g. 9x6)"
                )
            if self.marker_mm is not None or self.dictionary is not None or self.legacy:
                raise ValueError("marker_mm, dictionary and legacy apply to charuco boards only")
        else:
            if self.cols < 3 or self.rows < 3:
                raise ValueError(
                    f"a ChArUco board needs at least 3x3 squares, got {self.cols}x{self.rows}"
                )
            if self.marker_mm is None:
                raise ValueError("a charuco board needs marker_mm (the ArUco marker side, mm)")
            object.__setattr__(self, "marker_mm", float(self.marker_mm))
            assert self.marker_mm is not None
            if not (0 < self.marker_mm < self.square_mm):
                raise ValueError(
                    f"marker_mm must be positive and smaller than square_mm ({self.square_mm}),"
                    f" got {self.marker_mm}"
                )
            if self.dictionary is None:
                object.__setattr__(self, "dictionary", "DICT_4X4_1000")
            name = str(self.dictionary)
            if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
                raise ValueError(f"unknown ArUco dictionary {name!r}; use e.g. 'DICT_4X4_1000'")
            n_markers = (self.cols * self.rows) // 2
            dict_size = _aruco_dictionary(name).bytesList.shape[0]
            if n_markers > dict_size:
                raise ValueError(
                    f"a {self.cols}x{self.rows} ChArUco board needs {n_markers} markers but"
                    f" {name} holds only {dict_size}"
                )

    # -- geometry -----------------------------------------------------------
    @property
    def corner_grid(self) -> tuple[int, int]:
        """``(columns, rows)`` of the detectable corners."""
        if self.kind == "chessboard":
            return (self.cols, self.rows)
        return (self.cols - 1, self.rows - 1)

    @property
    def n_corners(self) -> int:
        """Number of detectable corners on the whole board."""
        c, r = self.corner_grid
        return c * r

    def object_points(self) -> FloatArray:
        """Board-frame positions of every corner, ``(n_corners, 3)`` mm, indexed by corner id."""
        c, r = self.corner_grid
        offset = 0.0 if self.kind == "chessboard" else self.square_mm
        xs, ys = np.meshgrid(np.arange(c), np.arange(r))
        pts = np.zeros((c * r, 3))
        pts[:, 0] = xs.ravel() * self.square_mm + offset
        pts[:, 1] = ys.ravel() * self.square_mm + offset
        return pts

    def outline_mm(self) -> tuple[float, float, float, float]:
        """The printed pattern's extent ``(x_min, y_min, x_max, y_max)`` in mm (board frame)."""
        s = self.square_mm
        if self.kind == "chessboard":
            return (-s, -s, self.cols * s, self.rows * s)
        return (0.0, 0.0, self.cols * s, self.rows * s)

    def describe(self) -> str:
        """A short human description, e.g. ``"9x6 inner-corner chessboard (25 mm squares)"``."""
        if self.kind == "chessboard":
            return (
                f"{self.cols}x{self.rows} inner-corner chessboard ({self.square_mm:g} mm squares)"
            )
        return (
            f"{self.cols}x{self.rows}-square ChArUco board ({self.square_mm:g} mm squares,"
            f" {self.marker_mm:g} mm {self.dictionary} markers"
            + (", legacy layout)" if self.legacy else ")")
        )

    def charuco_board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` of a ChArUco spec."""
        if self.kind != "charuco":
            raise ValueError("charuco_board() applies to charuco boards only")
        board = cv2.aruco.CharucoBoard(
            (self.cols, self.rows),
            self.square_mm,
            float(self.marker_mm or 0.0),
            _aruco_dictionary(str(self.dictionary)),
        )
        board.setLegacyPattern(bool(self.legacy))
        return board

    # -- JSON ---------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The board as a JSON-ready dict (``bradyscope.board/1``)."""
        doc: dict[str, Any] = {
            "format": BOARD_FORMAT,
            "kind": self.kind,
            "cols": self.cols,
            "rows": self.rows,
            "square_mm": self.square_mm,
        }
        if self.kind == "charuco":
            doc["marker_mm"] = self.marker_mm
            doc["dictionary"] = self.dictionary
            if self.legacy:
                doc["legacy"] = True
        return doc

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> BoardSpec:
        """Inverse of :meth:`to_dict`; also reads the service's form (``"board"`` for ``"kind"``).

        Unknown keys are ignored.

        Raises
        ------
        InputError
            A key is missing or a value is invalid (the message says which).
        """
        from core.errors import InputError

        if not isinstance(doc, dict):
            raise InputError(
                "the board description is not a JSON object; give kind, cols, rows, square_mm."
            )
        kind = doc.get("kind", doc.get("board"))
        missing = [
            k
            for k, v in (
                ("kind", kind),
                ("cols", doc.get("cols")),
                ("rows", doc.get("rows")),
                ("square_mm", doc.get("square_mm")),
            )
            if v is None
        ]
        if missing:
            raise InputError(
                f"the board description lacks {', '.join(missing)}; give kind, cols, rows, square_mm."
            )
        try:
            return cls(
                kind=cast(BoardKind, kind),
                cols=doc["cols"],
                rows=doc["rows"],
                square_mm=doc["square_mm"],
                marker_mm=doc.get("marker_mm"),
                dictionary=doc.get("dictionary"),
                legacy=_flag(doc.get("legacy", False)),
            )
        except (TypeError, ValueError) as exc:
            raise InputError(f"the board description is invalid: {exc}.") from exc


def _flag(value: Any) -> bool:
    """A JSON or form boolean (``true``, ``"true"``, ``"1"``, ``"on"``...)."""
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ("1", "true", "yes", "on"):
        return True
    if isinstance(value, str) and value.strip().lower() in ("", "0", "false", "no", "off"):
        return False
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    raise ValueError(f"legacy must be true or false, got {value!r}")


def _aruco_dictionary(name: str) -> Any:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@dataclass(frozen=True)
class BoardDetection:
    """The corners of one board found in one image.

    Attributes
    ----------
    ids : ndarray, shape (N,), int64
        Corner ids (indices into ``BoardSpec.object_points()``), increasing.
    corners_px : ndarray, shape (N, 2), float64
        Sub-pixel corner positions, OpenCV's ``(x, y)``.
    object_points_mm : ndarray, shape (N, 3), float64
        The same corners in the board frame (mm, ``z = 0``).
    image_size : ImageSize
        ``(width, height)`` of the image they were found in.
    """

    ids: IntArray
    corners_px: FloatArray
    object_points_mm: FloatArray
    image_size: ImageSize

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def flipped(self, board: BoardSpec) -> BoardDetection:
        """The same corners with the chessboard's 180-degree-rotated numbering.

        A chessboard's orientation is ambiguous up to a half turn; stereo
        calibration uses this to make the left and right numbering agree.
        """
        new_ids = board.n_corners - 1 - self.ids
        order = np.argsort(new_ids)
        ids = new_ids[order]
        return BoardDetection(
            ids=ids,
            corners_px=self.corners_px[order],
            object_points_mm=board.object_points()[ids],
            image_size=self.image_size,
        )


def _to_gray(image: NDArray[Any]) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    elif img.ndim != 2:
        raise ValueError(f"image must have shape (H, W) or (H, W, 3), got {img.shape}")
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating) and img.size and float(np.nanmax(img)) <= 1.0:
            img = img * 255.0
        img = np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def detect_board(
    image: NDArray[Any],
    board: BoardSpec,
    *,
    method: ChessboardMethod = "classic",
) -> BoardDetection | None:
    """Find a calibration board in an image, with sub-pixel corners.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        A grayscale or BGR image (uint8, or float in [0, 1]).
    board : BoardSpec
        The board to look for.
    method : {"auto", "classic", "sb"}, keyword-only
        Chessboard only: ``"classic"`` uses ``cv2.findChessboardCorners``
        followed by ``cv2.cornerSubPix``; ``"sb"`` uses
        ``cv2.findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``; ``"auto"``
        tries ``"classic"`` and then ``"sb"``.

    Returns
    -------
    BoardDetection or None
        ``None`` when the board is not found (a chessboard must be seen whole;
        a ChArUco board needs at least ``MIN_CHARUCO_CORNERS`` corners).
    """
    gray = _to_gray(image)
    size = ImageSize.of_image(gray)
    if board.kind == "chessboard":
        pts = _detect_chessboard(gray, board, method=method)
        if pts is None:
            return None
        ids = np.arange(board.n_corners, dtype=np.int64)
    else:
        found = _detect_charuco(gray, board)
        if found is None:
            return None
        ids, pts = found
    return BoardDetection(
        ids=ids,
        corners_px=pts,
        object_points_mm=board.object_points()[ids],
        image_size=size,
    )


def _detect_chessboard(
    gray: NDArray[np.uint8], board: BoardSpec, *, method: ChessboardMethod
) -> FloatArray | None:
    pattern = (board.cols, board.rows)
    if method == "auto":
        pts = _detect_chessboard(gray, board, method="classic")
        return pts if pts is not None else _detect_chessboard(gray, board, method="sb")
    if method == "sb":
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
        if not ok or corners is None:
            return None
        pts = corners.reshape(-1, 2).astype(np.float64)
    elif method == "classic":
        found = _find_chessboard_reduced(gray, pattern)
        if found is None:
            return None
        win = _subpix_window(found.reshape(-1, 2).astype(np.float64), pattern)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
        refined = cv2.cornerSubPix(gray, found, (win, win), (-1, -1), criteria)
        pts = np.asarray(refined, dtype=np.float64).reshape(-1, 2)
    else:
        raise ValueError(f"method must be 'auto', 'classic' or 'sb', got {method!r}")
    if pts.shape[0] != board.n_corners or not np.all(np.isfinite(pts)):
        return None
    return pts


#: Chessboards are searched first on the image reduced to at most this width (px).
REDUCED_WIDTH_PX = 800
_CLASSIC_FLAGS = (
    cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
)


def _find_chessboard_reduced(
    gray: NDArray[np.uint8], pattern: tuple[int, int]
) -> NDArray[np.float32] | None:
    """``cv2.findChessboardCorners``' corners (N, 1, 2) of ``gray``, or None.

    A large image is searched reduced (an integer factor, to at most
    :data:`REDUCED_WIDTH_PX` wide; the corners scaled back, to be refined at
    full resolution by ``cornerSubPix``). When the board is not found there
    (too small once reduced), the full image is searched.
    """
    h, w = gray.shape
    factor = -(-w // REDUCED_WIDTH_PX)  # ceil
    if factor > 1:
        small = cv2.resize(gray, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        ok, corners = cv2.findChessboardCorners(small, pattern, flags=_CLASSIC_FLAGS)
        if ok and corners is not None:
            # Pixel centres: (x + 0.5) * factor - 0.5 in the full image.
            full = (np.asarray(corners, dtype=np.float64) + 0.5) * factor - 0.5
            return np.ascontiguousarray(full, dtype=np.float32)
    ok, corners = cv2.findChessboardCorners(gray, pattern, flags=_CLASSIC_FLAGS)
    if not ok or corners is None:
        return None
    return np.ascontiguousarray(corners, dtype=np.float32)


def _subpix_window(pts: FloatArray, grid: tuple[int, int]) -> int:
    """Half-window for cornerSubPix: under half the smallest corner spacing, 2..11 px."""
    c, r = grid
    g = pts.reshape(r, c, 2)
    d = np.concatenate(
        [
            np.linalg.norm(np.diff(g, axis=1), axis=2).ravel(),
            np.linalg.norm(np.diff(g, axis=0), axis=2).ravel(),
        ]
    )
    return int(np.clip(np.floor(0.4 * float(np.min(d))), 2, 11))


def _detect_charuco(
    gray: NDArray[np.uint8], board: BoardSpec
) -> tuple[IntArray, FloatArray] | None:
    detector = _charuco_detector(board)
    corners, ids, _marker_corners, _marker_ids = detector.detectBoard(gray)
    if corners is None or ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids_arr = np.asarray(ids, dtype=np.int64).reshape(-1)
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(ids_arr)
    ids_arr, pts = ids_arr[order], pts[order]
    # Reject degenerate (collinear) partial views: they fix no homography.
    obj = board.object_points()[ids_arr][:, :2]
    centred = obj - obj.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[-1] < 0.5 * board.square_mm:
        return None
    return ids_arr, pts


_DETECTORS: dict[BoardSpec, Any] = {}


def _charuco_detector(board: BoardSpec) -> Any:
    """A cached ``cv2.aruco.CharucoDetector`` for a ChArUco spec (the board build is costly)."""
    det = _DETECTORS.get(board)
    if det is None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        charuco_params = cv2.aruco.CharucoParameters()
        charuco_params.tryRefineMarkers = True
        det = cv2.aruco.CharucoDetector(board.charuco_board(), charuco_params, params)
        if len(_DETECTORS) > 8:
            _DETECTORS.clear()
        _DETECTORS[board] = det
    return det


def chessboard_extends(image: NDArray[Any], detection: BoardDetection, board: BoardSpec) -> bool:
    """Whether chessboard corners continue past an edge of the detected grid.

    A chessboard larger than the ``cols x rows`` asked for is often found as a
    sub-grid. One grid step beyond each edge (extrapolated quadratically along
    the grid lines) there is then another X-shaped corner, where a correctly
    sized board has its outer edge. A point is X-shaped when the intensity on
    a circle of 0.3 grid steps around it is dominated by its second harmonic
    (two dark and two light sectors); a side continues when at least 80 % of
    its points inside the image are X-shaped.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
    detection : BoardDetection
        A whole-chessboard detection of ``board`` in ``image``.
    board : BoardSpec
        A chessboard.
    """
    if board.kind != "chessboard" or len(detection) != board.n_corners:
        raise ValueError("chessboard_extends needs a whole-chessboard detection")
    gray = _to_gray(image).astype(np.float32)
    h, w = gray.shape
    c, r = board.corner_grid
    g = detection.corners_px.reshape(r, c, 2)
    edges = (
        (g[:, 0], g[:, 1], g[:, 2]),
        (g[:, -1], g[:, -2], g[:, -3]),
        (g[0], g[1], g[2]),
        (g[-1], g[-2], g[-3]),
    )
    theta = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    h1_basis = np.exp(-1j * theta)
    h2_basis = np.exp(-2j * theta)
    for p0, p1, p2 in edges:
        beyond = 3 * p0 - 3 * p1 + p2
        radius = 0.3 * np.linalg.norm(beyond - p0, axis=1)
        xs = beyond[:, :1] + radius[:, None] * np.cos(theta)[None, :]
        ys = beyond[:, 1:] + radius[:, None] * np.sin(theta)[None, :]
        inside = (xs.min(axis=1) >= 0) & (ys.min(axis=1) >= 0)
        inside &= (xs.max(axis=1) <= w - 1) & (ys.max(axis=1) <= h - 1)
        if np.sum(inside) < 3:
            continue
        v = cv2.remap(
            gray, xs[inside].astype(np.float32), ys[inside].astype(np.float32), cv2.INTER_LINEAR
        ).astype(np.float64)
        v -= v.mean(axis=1, keepdims=True)
        h1 = np.abs(v @ h1_basis)
        h2 = np.abs(v @ h2_basis)
        x_shaped = h2 / (h1 + h2 + 1e-9) > 0.85
        if np.mean(x_shaped) >= 0.8:
            return True
    return False
