"""Board specs and board detection, against rendered boards with known corners."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core.boards import BoardSpec, detect_board
from core.camera import Camera, ImageSize
from core.simulation.boards import (
    DEFAULT_CHARUCO,
    DEFAULT_CHESSBOARD,
    board_texture,
    example_rig,
    random_board_poses,
    render_board_view,
)

SIZE = ImageSize(640, 512)


@pytest.fixture(scope="module")
def rig():
    return example_rig(image_size=SIZE)


def _render(rig, board, pose, *, seed=0, noise_std=1.5):
    """Left image of a board pose and the true pixel positions of every corner."""
    R, t = pose
    img = render_board_view(
        rig.left,
        board_texture(board),
        R,
        t,
        board=board,
        rng=np.random.default_rng(seed),
        noise_std=noise_std,
    )
    truth = rig.left.project(board.object_points() @ R.T + t)
    return img, truth


# -- BoardSpec ----------------------------------------------------------------


def test_chessboard_object_points_follow_opencv_order():
    board = BoardSpec("chessboard", cols=4, rows=3, square_mm=10.0)
    pts = board.object_points()
    assert pts.shape == (12, 3)
    # id k = r * cols + c at (c * s, r * s, 0): x varies fastest.
    np.testing.assert_allclose(pts[1], [10.0, 0.0, 0.0])
    np.testing.assert_allclose(pts[4], [0.0, 10.0, 0.0])
    np.testing.assert_allclose(pts[:, 2], 0.0)


def test_charuco_object_points_match_opencv_board():
    board = BoardSpec("charuco", cols=5, rows=4, square_mm=30.0, marker_mm=22.0)
    assert board.dictionary == "DICT_4X4_1000"
    assert board.corner_grid == (4, 3)
    np.testing.assert_allclose(
        board.object_points(), board.charuco_board().getChessboardCorners(), atol=1e-9
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "chessboard", "cols": 2, "rows": 5, "square_mm": 10}, "at least 3x3"),
        ({"kind": "chessboard", "cols": 7, "rows": 7, "square_mm": 10}, "symmetric"),
        ({"kind": "chessboard", "cols": 9, "rows": 6, "square_mm": 0}, "square_mm"),
        ({"kind": "chessboard", "cols": 9, "rows": 6, "square_mm": 10, "marker_mm": 7}, "charuco"),
        ({"kind": "charuco", "cols": 5, "rows": 4, "square_mm": 30}, "marker_mm"),
        ({"kind": "charuco", "cols": 5, "rows": 4, "square_mm": 30, "marker_mm": 30}, "smaller"),
        (
            {
                "kind": "charuco",
                "cols": 5,
                "rows": 4,
                "square_mm": 30,
                "marker_mm": 20,
                "dictionary": "DICT_NOPE",
            },
            "dictionary",
        ),
        (
            {
                "kind": "charuco",
                "cols": 20,
                "rows": 20,
                "square_mm": 30,
                "marker_mm": 20,
                "dictionary": "DICT_4X4_50",
            },
            "holds only",
        ),
        ({"kind": "circles", "cols": 5, "rows": 4, "square_mm": 30}, "kind"),
    ],
)
def test_boardspec_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BoardSpec(**kwargs)


def test_boardspec_round_trips_through_dict():
    legacy = dataclasses.replace(DEFAULT_CHARUCO, rows=6, legacy=True)
    for board in (DEFAULT_CHESSBOARD, DEFAULT_CHARUCO, legacy):
        assert BoardSpec.from_dict(board.to_dict()) == board
    assert "legacy" not in DEFAULT_CHARUCO.to_dict()  # older readers see the same document
    assert legacy.to_dict()["legacy"] is True and "legacy layout" in legacy.describe()
    # A form's check box sends text.
    assert BoardSpec.from_dict({**legacy.to_dict(), "legacy": "on"}) == legacy
    assert BoardSpec.from_dict({**legacy.to_dict(), "legacy": "false"}) == dataclasses.replace(
        legacy, legacy=False
    )
    with pytest.raises(ValueError, match="charuco boards only"):
        BoardSpec("chessboard", cols=9, rows=6, square_mm=25.0, legacy=True)


def test_legacy_charuco_layout_is_found_only_as_legacy(rig):
    """OpenCV < 4.6 printed even-row ChArUco boards with the markers in the other squares."""
    current = BoardSpec("charuco", cols=8, rows=6, square_mm=30.0, marker_mm=22.0)
    legacy = dataclasses.replace(current, legacy=True)
    pose = random_board_poses(rig, legacy, 1, rng=np.random.default_rng(4))[0]
    img, truth = _render(rig, legacy, pose)
    det = detect_board(img, legacy)
    assert det is not None and len(det) >= 0.9 * legacy.n_corners
    np.testing.assert_allclose(det.corners_px, truth[det.ids], atol=0.25)  # px
    assert detect_board(img, current) is None
    # ...and a current board is not found as a legacy one.
    img, _ = _render(rig, current, pose)
    assert detect_board(img, current) is not None and detect_board(img, legacy) is None


# -- detection ------------------------------------------------------------------


@pytest.mark.parametrize("method", ["classic", "sb"])
def test_chessboard_corners_are_subpixel_accurate(rig, method):
    board = DEFAULT_CHESSBOARD
    poses = random_board_poses(rig, board, 4, rng=np.random.default_rng(5))
    errors = []
    for k, pose in enumerate(poses):
        img, truth = _render(rig, board, pose, seed=k)
        det = detect_board(img, board, method=method)
        assert det is not None
        assert det.corners_px.shape == (54, 2) and det.object_points_mm.shape == (54, 3)
        assert det.image_size == SIZE
        err = det.corners_px - truth[det.ids]
        flipped = det.corners_px[::-1] - truth  # the half-turn numbering is also valid
        if np.abs(flipped).mean() < np.abs(err).mean():
            err = flipped
        errors.append(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    # Rendered with 1.5 gray-level noise: sub-pixel means well under 0.2 px.
    assert max(errors) < 0.15  # px RMS per view


def test_classic_chessboard_corners_beat_sector_based_ones(rig):
    """The measurement behind the default detector (docs/calibration.md)."""
    board = DEFAULT_CHESSBOARD
    poses = random_board_poses(rig, board, 6, rng=np.random.default_rng(11))
    rms = {"classic": [], "sb": []}
    for k, pose in enumerate(poses):
        img, truth = _render(rig, board, pose, seed=k)
        for method, out in rms.items():
            det = detect_board(img, board, method=method)
            assert det is not None
            err = min(
                np.sum((det.corners_px - truth) ** 2),
                np.sum((det.corners_px[::-1] - truth) ** 2),
            )
            out.append(err / len(truth))
    assert np.sqrt(np.mean(rms["classic"])) < np.sqrt(np.mean(rms["sb"]))


def test_charuco_ids_and_corners_match_truth(rig):
    board = DEFAULT_CHARUCO
    pose = random_board_poses(rig, board, 1, rng=np.random.default_rng(3))[0]
    img, truth = _render(rig, board, pose)
    det = detect_board(img, board)
    assert det is not None
    assert len(det) >= 0.9 * board.n_corners
    assert np.all(np.diff(det.ids) > 0)
    np.testing.assert_allclose(det.object_points_mm, board.object_points()[det.ids])
    np.testing.assert_allclose(det.corners_px, truth[det.ids], atol=0.25)  # px


def test_charuco_accepts_a_partial_view(rig):
    board = DEFAULT_CHARUCO
    pose = random_board_poses(rig, board, 1, rng=np.random.default_rng(3))[0]
    img, truth = _render(rig, board, pose)
    # Hide the right half of the board behind a gray occluder.
    cut = int(np.median(truth[:, 0]))
    img = img.copy()
    img[:, cut:] = 120
    det = detect_board(img, board)
    assert det is not None
    assert 6 <= len(det) < 0.7 * board.n_corners
    np.testing.assert_allclose(det.corners_px, truth[det.ids], atol=0.3)  # px
    assert np.all(det.corners_px[:, 0] < cut)


def test_no_board_gives_none(rig):
    rng = np.random.default_rng(0)
    blank = (120 + rng.normal(0, 2, (SIZE.height, SIZE.width))).clip(0, 255).astype(np.uint8)
    assert detect_board(blank, DEFAULT_CHESSBOARD) is None
    assert detect_board(blank, DEFAULT_CHARUCO) is None


def test_wrong_chessboard_size_is_not_found(rig):
    pose = random_board_poses(rig, DEFAULT_CHESSBOARD, 1, rng=np.random.default_rng(2))[0]
    img, _ = _render(rig, DEFAULT_CHESSBOARD, pose)
    assert detect_board(img, BoardSpec("chessboard", cols=7, rows=5, square_mm=25.0)) is None


def test_detection_accepts_color_and_float_images(rig):
    pose = random_board_poses(rig, DEFAULT_CHESSBOARD, 1, rng=np.random.default_rng(2))[0]
    img, _ = _render(rig, DEFAULT_CHESSBOARD, pose)
    ref = detect_board(img, DEFAULT_CHESSBOARD)
    bgr = np.repeat(img[:, :, None], 3, axis=2)
    as_float = img.astype(np.float64) / 255.0
    for variant in (bgr, as_float):
        det = detect_board(variant, DEFAULT_CHESSBOARD)
        assert det is not None and ref is not None
        np.testing.assert_allclose(det.corners_px, ref.corners_px, atol=0.02)  # px
    with pytest.raises(ValueError, match="shape"):
        detect_board(np.zeros((4, 4, 4, 4), np.uint8), DEFAULT_CHESSBOARD)


def test_flipped_numbering_is_a_half_turn(rig):
    board = DEFAULT_CHESSBOARD
    pose = random_board_poses(rig, board, 1, rng=np.random.default_rng(2))[0]
    img, _ = _render(rig, board, pose)
    det = detect_board(img, board)
    assert det is not None
    flip = det.flipped(board)
    np.testing.assert_allclose(flip.corners_px, det.corners_px[::-1])
    # The renumbered object points are the originals turned by 180 degrees about the centre.
    centre = board.object_points().mean(axis=0)
    old = det.object_points_mm[::-1]  # the old board position of each renumbered corner
    np.testing.assert_allclose(flip.object_points_mm[:, :2], 2 * centre[:2] - old[:, :2], atol=1e-9)
    assert flip.flipped(board).ids.tolist() == det.ids.tolist()


def test_rendered_corner_is_where_the_camera_model_puts_it():
    """Convention: pixel centres at integer coordinates (OpenCV), x = column."""
    cam = Camera(
        "c", ImageSize(320, 240), np.array([[300.0, 0, 160.0], [0, 300.0, 110.0], [0, 0, 1]])
    )
    board = BoardSpec("chessboard", cols=4, rows=3, square_mm=20.0)
    R = np.eye(3)
    t = np.array([-30.0, -20.0, 400.0])  # board centre on the optical axis
    img = render_board_view(
        cam, board_texture(board), R, t, board=board, rng=np.random.default_rng(0), noise_std=0.0
    )
    det = detect_board(img, board)
    assert det is not None
    truth = cam.project(board.object_points() @ R.T + t)
    err = det.corners_px - truth
    if np.abs(det.corners_px[::-1] - truth).mean() < np.abs(err).mean():
        err = det.corners_px[::-1] - truth
    np.testing.assert_allclose(err, 0.0, atol=0.1)  # px; a row/column swap would be ~10 px off


def test_boardspec_from_the_service_form_and_bad_documents():
    from core.errors import InputError

    doc = {"board": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0, "valid_from": None}
    assert BoardSpec.from_dict(doc) == DEFAULT_CHESSBOARD
    with pytest.raises(InputError, match="lacks square_mm"):
        BoardSpec.from_dict({"kind": "chessboard", "cols": 9, "rows": 6})
    with pytest.raises(InputError, match="symmetric"):
        BoardSpec.from_dict({"kind": "chessboard", "cols": 7, "rows": 7, "square_mm": 20})


def test_a_larger_chessboard_found_as_a_sub_grid_is_noticed(rig):
    from core.boards import BoardDetection, chessboard_extends

    board = DEFAULT_CHESSBOARD
    smaller = BoardSpec("chessboard", cols=board.cols - 1, rows=board.rows, square_mm=25.0)
    for k, pose in enumerate(random_board_poses(rig, board, 3, rng=np.random.default_rng(9))):
        img, _ = _render(rig, board, pose, seed=k)
        det = detect_board(img, board)
        assert det is not None
        assert not chessboard_extends(img, det, board)
        # The same corners minus the last column: an 8x6 grid inside a 9x6 board.
        keep = det.ids % board.cols != board.cols - 1
        ids = np.arange(smaller.n_corners)
        sub = BoardDetection(ids, det.corners_px[keep], smaller.object_points(), det.image_size)
        assert chessboard_extends(img, sub, smaller)
    with pytest.raises(ValueError, match="whole-chessboard"):
        chessboard_extends(img, sub, board)
