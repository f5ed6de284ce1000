"""Marker centres on an IR-lit hand (issue 19): skin, finger edges, partly hidden markers.

Images from the simulator's hand (``core.simulation.hand``: skin capsules under
the ring light, opaque markers, exact visible fractions) at known sub-pixel
centres; the default estimator (``"opaque_disc"``) against the centroid, and
the fit residual that sets partly hidden markers aside.
"""

from __future__ import annotations

import numpy as np
import pytest

from core import _blobs
from core.markers import MAX_FIT_RESIDUAL, MarkerParams, detect_markers
from core.simulation.hand import Capsules, SkinLook, composite_spheres, draw_skin
from core.simulation.render import DISC, SphereLayer
from core.simulation.rig import default_rig

CAM = default_rig().left  # 1280 x 1024, f = 1250 px
SKIN = SkinLook(level=57.0)  # a quarter of the markers: the pessimistic case
MARKER_Z_MM = 490.0
CENTROID = MarkerParams(centre_method="centroid")


def _finger(y_mm: float, z_mm: float = 500.0, radius_mm: float = 7.0) -> Capsules:
    """A finger along x facing the camera, its axis at height ``y_mm``."""
    return Capsules([[-60.0, y_mm, z_mm]], [[60.0, y_mm, z_mm]], [radius_mm], [radius_mm])


def _image(
    centre_mm: list[float], fingers: list[Capsules], *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, float]:
    """uint8 frame with the skin of ``fingers`` and one 5-mm marker; (image, true px, visible)."""
    canvas = np.full((1024, 1280), 14.0, np.float32)
    caps = Capsules(
        np.vstack([f.starts_mm for f in fingers]),
        np.vstack([f.ends_mm for f in fingers]),
        np.concatenate([f.start_radius_mm for f in fingers]),
        np.concatenate([f.end_radius_mm for f in fingers]),
    )
    skin = draw_skin(canvas, CAM, caps, SKIN)
    layer = SphereLayer(np.array([[centre_mm]]), np.array([2.5]), np.array([230.0]), DISC)
    vis = composite_spheres(canvas, CAM, layer, skin, psf_sigma_px=0.5)
    rng = np.random.default_rng(seed)
    canvas += rng.normal(0.0, 2.0, canvas.shape).astype(np.float32)
    img = np.clip(np.rint(canvas), 0, 255).astype(np.uint8)
    return img, CAM.project(np.array([centre_mm]))[0], float(vis[0])


def _error_px(img: np.ndarray, truth: np.ndarray, params: MarkerParams) -> tuple[float, float]:
    det = detect_markers(img, params=params, search_xy_px=truth[None])
    assert len(det) == 1
    return float(np.linalg.norm(det.xy_px[0] - truth)), float(det.fit_residual[0])


@pytest.mark.parametrize(
    ("edge_mm", "tol_px"),
    # through the disc (|edge| < 2.5 mm) the background is a step, not a plane
    [(-2.0, 0.1), (-1.0, 0.1), (0.0, 0.1), (1.5, 0.1), (3.0, 0.07), (6.0, 0.05), (9.0, 0.05)],
)
def test_opaque_disc_ignores_the_skin_edge_that_pulls_the_centroid(
    edge_mm: float, tol_px: float
) -> None:
    # the finger's lower silhouette runs edge_mm below the marker's centre (0: through it)
    centre = [0.3, 0.2, MARKER_Z_MM]
    img, truth, vis = _image(centre, [_finger(0.2 + edge_mm - 7.0)], seed=int(10 * edge_mm) + 50)
    assert vis == pytest.approx(1.0)
    err, residual = _error_px(img, truth, MarkerParams())
    assert err < tol_px  # px (the marker is 12 px across, 0.4 mm per px)
    assert residual < MAX_FIT_RESIDUAL  # a whole marker is measured


def test_centroid_is_pulled_by_skin_near_the_marker() -> None:
    """The case the fit exists for (fails if the skin stops biasing the centroid, i.e.
    if the scene no longer has the effect the estimator is tested against)."""
    centre = [0.3, 0.2, MARKER_Z_MM]
    errors = []
    for edge_mm in (1.5, 3.0, 6.0):
        img, truth, _ = _image(centre, [_finger(0.2 + edge_mm - 7.0)], seed=1)
        errors.append(_error_px(img, truth, CENTROID)[0])
    assert max(errors) > 0.2  # px: the centroid's bias on the same images


def test_on_the_dark_room_the_centroid_is_kept() -> None:
    img, truth, _ = _image([0.3, 0.2, MARKER_Z_MM], [_finger(60.0)], seed=2)
    det = detect_markers(img, search_xy_px=truth[None])
    ref = detect_markers(img, params=CENTROID, search_xy_px=truth[None])
    np.testing.assert_array_equal(det.xy_px, ref.xy_px)  # no fit: same centre, same cost
    assert np.isnan(det.fit_residual[0])
    assert np.linalg.norm(det.xy_px[0] - truth) < 0.05  # px


@pytest.mark.parametrize("cover_mm", [1.2, 1.8])
def test_a_marker_partly_behind_a_finger_is_not_taken_as_whole(cover_mm: float) -> None:
    # a second finger in front of the marker, its upper silhouette cover_mm into the disc
    centre = [0.3, 0.2, MARKER_Z_MM]
    front = _finger(0.2 + 2.5 - cover_mm + 6.0, z_mm=470.0, radius_mm=6.0)
    img, truth, vis = _image(centre, [_finger(-3.0), front], seed=3)
    assert 0.5 < vis < 0.95  # the truth: partly hidden
    err_centroid = _error_px(img, truth, CENTROID)[0]
    assert err_centroid > 0.3  # px: any centre of the visible part is biased
    _, residual = _error_px(img, truth, MarkerParams())
    assert residual > MAX_FIT_RESIDUAL  # so the pipeline sets it aside


@pytest.mark.parametrize(("cover_mm", "seed"), [(0.2, 3), (0.2, 4), (0.35, 5), (0.5, 6)])
def test_a_marker_a_few_percent_behind_a_finger_is_measured_with_the_edge(
    cover_mm: float, seed: int
) -> None:
    # 3-9 % of the disc behind a finger in front: the disc cut by the finger's edge
    # (edges=1, the default in detect_markers) finds the centre; the plain disc does not
    centre = [0.3, 0.2, MARKER_Z_MM]
    front = _finger(0.2 + 2.5 - cover_mm + 6.0, z_mm=470.0, radius_mm=6.0)
    img, truth, vis = _image(centre, [_finger(-3.0), front], seed=seed)
    assert 0.88 < vis < 0.98  # the truth: a few per cent hidden
    det = detect_markers(img, search_xy_px=truth[None])
    assert len(det) == 1
    assert np.linalg.norm(det.xy_px[0] - truth) < 0.05  # px (0.4 mm per px)
    d, rnd = float(det.diameter_px[0]), float(det.roundness[0])
    seeds = np.array([[*det.xy_px[0], 0.5 * d, 0.5 * d / rnd + 3.0, det.background[0],
                       det.background[0] + det.peak[0]]])  # fmt: skip
    plain = _blobs.fit_discs(img, seeds, np.zeros((0, 2)), 10, -1.0, 0)
    cut = _blobs.fit_discs(img, seeds, np.zeros((0, 2)), 10, -1.0, 1)
    assert np.linalg.norm(plain[0, :2] - truth) > 0.2  # px: the hidden part pulls it
    assert cut[0, _blobs.FIT_COLUMNS.index("edge_model")] == 1  # skin in front, found
    hidden = cut[0, _blobs.FIT_COLUMNS.index("hidden_share")]
    assert abs(hidden - (1.0 - vis)) < 0.04  # share of the disc


def test_a_marker_on_a_skin_step_keeps_the_edge_behind_it() -> None:
    # the finger's silhouette runs under the whole marker: a step of the background
    centre = [0.3, 0.2, MARKER_Z_MM]
    img, truth, vis = _image(centre, [_finger(0.2 + 1.0 - 7.0)], seed=7)
    assert vis == pytest.approx(1.0)
    det = detect_markers(img, search_xy_px=truth[None])
    seeds = np.array([[*det.xy_px[0], 0.5 * det.diameter_px[0], 9.0, det.background[0],
                       det.background[0] + det.peak[0]]])  # fmt: skip
    cut = _blobs.fit_discs(img, seeds, np.zeros((0, 2)), 10, -1.0, 1)
    assert cut[0, _blobs.FIT_COLUMNS.index("edge_model")] != 1  # nothing in front of it
    assert np.linalg.norm(det.xy_px[0] - truth) < 0.1  # px


def _glint(centres_px: list[tuple[float, float]], *, sigma_px: float = 3.0) -> np.ndarray:
    """Soft Gaussian glints (peak 230) on the dark room (14, noise sigma 2)."""
    yy, xx = np.mgrid[0:200, 0:240].astype(np.float64)
    canvas = np.full(xx.shape, 14.0)
    for cx, cy in centres_px:
        canvas += 230.0 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma_px**2))
    canvas += np.random.default_rng(4).normal(0.0, 2.0, canvas.shape)
    return np.clip(np.rint(canvas), 0, 255).astype(np.uint8)


def test_a_soft_glint_on_the_dark_room_is_not_fitted() -> None:
    # Its own halo lights the fit window's border (3 px beyond half its half-maximum width),
    # so the first dark-room test alone would fit it; the wider border is dark: centroid.
    truth = np.array([120.3, 100.6])
    img = _glint([tuple(truth)], sigma_px=3.5)
    det = detect_markers(img, search_xy_px=truth[None])
    ref = detect_markers(img, params=CENTROID, search_xy_px=truth[None])
    assert len(det) == 1
    # the first test's border (the fit window's, as core/_blobs.pyx cuts it) is lit
    hs = int(np.ceil(0.5 * det.diameter_px[0] / det.roundness[0] + 3.0))
    x, y = np.floor(det.xy_px[0] + 0.5).astype(int)
    win = img[y - hs : y + hs + 1, x - hs : x + hs + 1]
    border = np.sort(np.concatenate((win[0], win[-1], win[1:-1, 0], win[1:-1, -1])))
    bg, sigma = _blobs.background_and_noise(img, 16)
    threshold = bg + max(0.5 * MarkerParams().min_contrast, 4.0 * sigma)
    assert border[(9 * len(border)) // 10] > threshold
    assert np.isnan(det.fit_residual[0])  # not fitted
    np.testing.assert_array_equal(det.xy_px, ref.xy_px)
    assert np.linalg.norm(det.xy_px[0] - truth) < 0.05  # px: the centroid is exact here


def test_a_soft_glint_beside_another_blob_is_still_fitted() -> None:
    # another blob's centre within the wider border: the lit border may be that blob's
    a, b = np.array([110.3, 100.6]), np.array([120.3, 100.0])
    img = _glint([tuple(a), tuple(b)], sigma_px=2.0)
    det = detect_markers(img, search_xy_px=np.array([a, b]))
    assert len(det) == 2
    assert np.all(np.isfinite(det.fit_residual))  # both fitted, as before the wider test


def test_a_marker_on_lit_skin_is_measured_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seeds on a marker's flank over lit skin climb to its peak: the compiled search
    skips them instead of measuring the blob again (a duplicate row per seed, up to the
    region's seed limit, that cost ~1.8 ms a frame on the skin recording and, passed to
    the disc fit as other blobs' centres, hid a moving marker's own pixels from it)."""
    searched: list[np.ndarray] = []
    search = _blobs.search

    def recording_search(*args: object) -> tuple[np.ndarray, object]:
        rows, supports = search(*args)
        searched.append(rows)
        return rows, supports

    monkeypatch.setattr(_blobs, "search", recording_search)
    centre = [0.3, 0.2, MARKER_Z_MM]
    for axis_mm in (0.2, 3.0):  # on the nail: lit skin all round the marker
        img, truth, _ = _image(centre, [_finger(axis_mm)], seed=7)
        searched.clear()
        det = detect_markers(img)  # the full-frame search
        assert len(det) == 1 and np.linalg.norm(det.xy_px[0] - truth) < 0.1  # px
        (rows,) = searched
        xy = rows[:, :2]
        near = np.linalg.norm(xy[:, None] - xy[None], axis=2) < 1.0  # px
        assert np.count_nonzero(near) == len(rows), f"{len(rows)} rows for one blob"


def _one_call_at_a_time(
    img: np.ndarray, pts: np.ndarray, radius_px: float, params: MarkerParams
) -> np.ndarray:
    """The windowed detection as the compiled calls one after another (before
    ``_blobs.measure_regions`` made them one call)."""
    import math

    from core import markers

    reach = radius_px + 0.5 * params.diameter_px_max
    regions, point_region = _blobs.merged_windows(pts, reach, *img.shape)
    bg, sigma = _blobs.background_and_noise(img, 16)
    thr = bg + max(0.5 * params.min_contrast, 4.0 * sigma)
    rows, _ = _blobs.search(img, regions, thr, params.diameter_px_min, params.diameter_px_max,
                            params.min_contrast, params.max_elongation, params.min_fill,
                            params.reject_border, markers._ring_radius(params),
                            math.ceil(params.diameter_px_max * params.max_elongation) + 5,
                            64, False)  # fmt: skip
    kept = rows[_blobs.select(rows, pts, point_region, radius_px**2)]
    if params.centre_method == "opaque_disc" and len(kept):
        markers._fit_opaque_discs(img, kept, rows[:, :2], thr, sigma)
    return kept


@pytest.mark.parametrize("params", [MarkerParams(), CENTROID])
def test_the_one_call_windowed_detection_gives_the_same_bits(params: MarkerParams) -> None:
    """``_blobs.measure_regions`` (noise, search, selection and disc fits with the GIL
    released once a frame) gives bit for bit the rows of the calls one after another:
    markers on lit skin, at a finger's edge, partly hidden (a fit residual that sets
    them aside), on the dark room, and two markers whose windows merge."""
    from core.markers import _detected_rows

    cases = [
        ([0.3, 0.2, MARKER_Z_MM], [_finger(0.2)]),
        ([0.3, 0.2, MARKER_Z_MM], [_finger(6.0)]),
        # partly behind a finger in front (as in the test above)
        ([0.3, 0.2, MARKER_Z_MM], [_finger(-3.0), _finger(6.9, z_mm=470.0, radius_mm=6.0)]),
        ([0.3, 0.2, MARKER_Z_MM], [_finger(80.0)]),  # on the dark room
    ]
    n_fitted = n_hidden = 0
    for k, (centre, fingers) in enumerate(cases):
        img, truth, _ = _image(centre, fingers, seed=k)
        second = CAM.project(np.array([[centre[0] + 4.0, centre[1] + 9.0, MARKER_Z_MM]]))[0]
        img = np.maximum(img, _image([centre[0] + 4.0, centre[1] + 9.0, MARKER_Z_MM],
                                     [_finger(80.0)], seed=9 + k)[0])  # fmt: skip
        for pts in (truth[None], np.array([truth, second]), np.array([truth + 3.0])):
            got = _detected_rows(img, params, pts, 25.0, None)
            want = _one_call_at_a_time(img, np.ascontiguousarray(pts, dtype=float), 25.0, params)
            assert got.shape == want.shape and len(got) > 0
            assert got.tobytes() == want.tobytes()  # bit for bit, NaN included
            n_fitted += int(np.isfinite(got[:, 20]).sum())
            n_hidden += int((got[:, 20] > MAX_FIT_RESIDUAL).sum())
    if params.centre_method == "opaque_disc":
        assert n_fitted > n_hidden > 0  # whole and partly hidden markers were compared


def test_the_one_call_windowed_detection_checks_its_arguments() -> None:
    img = np.zeros((64, 64), np.uint8)
    pts = np.array([[10.0, 10.0]])
    region = np.array([[0, 0, 20, 20]], np.int32)
    owner = np.zeros(1, np.int32)
    args = (0.5, 3.0, 40.0, 4.0, 0.6, True, 23, 165, 64, True, 10, 3.0, 0.75, 0.15)
    with pytest.raises(ValueError, match="noise_step"):
        _blobs.measure_regions(img, region, pts, owner, 625.0, 0, 20.0, *args[1:])
    with pytest.raises(ValueError, match="not inside the image"):
        _blobs.measure_regions(img, region + 50, pts, owner, 625.0, 16, 20.0, *args[1:])
    with pytest.raises(ValueError, match="point_region"):
        _blobs.measure_regions(img, region, pts, owner[:0], 625.0, 16, 20.0, *args[1:])
    rows, thr, sigma = _blobs.measure_regions(img, region, pts, owner, 625.0, 16, 20.0, *args[1:])
    assert rows.shape == (0, len(_blobs.COLUMNS)) and thr == 10.0 and sigma == 0.7
