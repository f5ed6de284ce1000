"""Exports: markers CSV round trip, C3D read back by an independent reader, TRC, FHIR."""

from __future__ import annotations

import base64
import io
import json

import numpy as np
import pytest
from sample_trial import sample_report_data, synthetic_trial

from app import exports, trajectories
from core import markers_csv


@pytest.fixture(scope="module")
def markers():
    return synthetic_trial()[0]


def test_markers_csv_has_the_interfaces_header_and_round_trips(markers):
    text = markers_csv.markers_csv_text(markers)
    lines = text.splitlines()
    assert lines[0] == "frame,time_s,marker,x_mm,y_mm,z_mm,status,reprojection_px"
    assert lines[1].startswith("0,0.0,thumb,")  # as docs/interfaces.md shows it
    assert len(lines) == 1 + markers.frames.size * 2  # one row per frame and marker
    back = markers_csv.read_markers_csv(io.StringIO(text))
    assert back.labels == markers.labels
    assert back.fps == pytest.approx(markers.fps)
    np.testing.assert_allclose(back.positions_mm, markers.positions_mm, atol=5e-4)  # mm, 3 decimals
    np.testing.assert_array_equal(back.status, markers.status)
    # Missing samples have empty coordinates, as INTERFACES.md says.
    assert lines[-2].split(",")[3:7] == ["", "", "", "missing"]


def test_markers_csv_rejects_a_table_without_the_columns():
    with pytest.raises(ValueError, match="lacks the columns"):
        markers_csv.read_markers_csv(io.StringIO("frame,x\n0,1\n"))


def test_marker_table_checks_shapes(markers):
    with pytest.raises(ValueError, match="positions_mm"):
        markers_csv.MarkerTable(
            fps=100.0,
            frames=markers.frames,
            labels=("thumb",),
            positions_mm=markers.positions_mm,
            status=markers.status,
            reprojection_px=markers.reprojection_px,
        )


@pytest.mark.filterwarnings("ignore:No analog data found:UserWarning")
def test_c3d_reads_back_with_an_independent_reader(tmp_path, markers):
    import c3d  # the pure-Python reader, independent of ezc3d which wrote the file

    focal_px = 1400.0
    path = trajectories.write_c3d(tmp_path / "trial.c3d", markers, focal_px=focal_px)
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)  # checks that the header's scale factor is POINT:SCALE's
        assert reader.point_rate == pytest.approx(markers.fps)
        step = abs(reader.point_scale)
        assert step == pytest.approx(np.nanmax(np.abs(markers.positions_mm)) / 32000, rel=1e-6)
        labels = [s.strip() for s in reader.point_labels]
        assert labels == list(markers.labels)
        assert reader.get("POINT:UNITS").string_value.strip() == "mm"
        frames = [points.copy() for _, points, _ in reader.read_frames()]
    pts = np.stack(frames)  # (T, M, 5): x, y, z, residual, camera mask
    assert pts.shape[:2] == markers.positions_mm.shape[:2]
    valid = np.isfinite(markers.positions_mm).all(axis=2)
    # float32 storage of ~600 mm coordinates: resolution ~6e-5 mm.
    np.testing.assert_allclose(pts[valid][:, :3], markers.positions_mm[valid], atol=1e-3)  # mm
    # Missing samples are flagged invalid (residual -1), not written as zeros.
    assert (pts[~valid][:, 3] < 0).all()
    # C3D's meaning of the fourth word: a measured sample has a positive residual (its
    # reprojection error at its depth, in mm, to one POINT:SCALE step) and the cameras
    # that saw it (1 and 2); an interpolated one residual 0 and no camera.
    measured = markers.status == "measured"
    interpolated = markers.status == "interpolated"
    assert measured.any() and interpolated.any()
    expected_mm = markers.reprojection_px * markers.positions_mm[:, :, 2] / focal_px
    np.testing.assert_allclose(pts[measured][:, 3], expected_mm[measured], atol=0.5 * step)
    assert (pts[measured][:, 3] > 0).all() and (pts[measured][:, 4] == 0b11).all()  # cameras 1, 2
    assert (pts[interpolated][:, 3] == 0).all() and (pts[interpolated][:, 4] == 0).all()


@pytest.mark.filterwarnings("ignore:No analog data found:UserWarning")
def test_c3d_convention_the_axes_are_not_permuted(tmp_path, markers):
    import c3d

    path = trajectories.write_c3d(tmp_path / "trial.c3d", markers)
    with open(path, "rb") as fh:
        first = next(iter(c3d.Reader(fh).read_frames()))[1]
    # The synthetic thumb rests at (10, -30, 600) mm: x, y, z must arrive in that order.
    np.testing.assert_allclose(first[0, :3], [10.0, -30.0, 600.0], atol=0.1)  # mm, jitter 0.02


def test_trc_round_trip_and_header(tmp_path, markers):
    path = trajectories.write_trc(tmp_path / "trial.trc", markers)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("PathFileType\t4\t(X/Y/Z)\ttrial.trc")
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    assert header["Units"] == "mm"
    assert int(header["NumFrames"]) == markers.frames.size
    assert int(header["NumMarkers"]) == 2
    assert float(header["DataRate"]) == pytest.approx(markers.fps)
    fps, labels, pos = trajectories.read_trc(path)
    assert labels == markers.labels and fps == pytest.approx(markers.fps)
    np.testing.assert_allclose(pos, markers.positions_mm, atol=5e-5)  # mm, 4 decimals
    # Frame numbers start at 1; time is frame / fps.
    assert lines[6].split("\t")[:2] == ["1", "0.000000"]


def test_fhir_bundle_validates_and_carries_every_metric_and_the_pdf():
    from fhir.resources.R4B.bundle import Bundle
    from fhir.resources.R4B.diagnosticreport import DiagnosticReport
    from fhir.resources.R4B.observation import Observation

    data = sample_report_data(patient_code="PD-0099")
    pdf = b"%PDF-1.7 fake bytes for the attachment test"
    doc = exports.fhir_bundle(data, pdf)
    bundle = Bundle.model_validate(doc)
    assert bundle.type == "collection"
    # The clinician's rating is an Observation of its own (tests/app/test_visit_api.py).
    resources = [
        e["resource"]
        for e in doc["entry"]
        if "clinician-rating" not in str(e["resource"].get("code", ""))
        and "hasMember" not in e["resource"]  # the task's Observation group (below)
        and not e["resource"]
        .get("code", {})
        .get("coding", [{}])[0]
        .get("code", "")
        .endswith("_first_10")  # the first-10 values (the next test)
    ]
    kinds = [r["resourceType"] for r in resources]
    numeric = {
        k: v
        for k, v in data.result["metrics"].items()
        if isinstance(v, int | float) and not isinstance(v, bool)
    }
    assert kinds.count("Observation") == len(numeric) == 11
    assert kinds.count("DiagnosticReport") == 1 and kinds.count("Patient") == 1
    patient = resources[kinds.index("Patient")]
    assert patient["identifier"][0]["value"] == "PD-0099"
    units = {}
    for res in resources:
        if res["resourceType"] == "Observation":
            obs = Observation.model_validate(res)
            key = res["code"]["coding"][0]["code"]
            q = res["valueQuantity"]
            assert q["system"] == "http://unitsofmeasure.org"
            assert q["value"] == pytest.approx(numeric[key], rel=1e-6)
            units[key] = q["code"]
            assert obs.subject.reference == doc["entry"][0]["fullUrl"]
    assert units["amplitude_mm_mean"] == "mm"
    assert units["frequency_hz"] == "Hz"
    assert units["opening_velocity_mm_s_max"] == "mm/s"
    assert units["amplitude_decrement_mm_per_tap"] == "mm/{tap}"
    assert units["tap_count"] == units["amplitude_mm_cv"] == "1"
    report = DiagnosticReport.model_validate(resources[kinds.index("DiagnosticReport")])
    category = report.category[0]
    assert (category.coding[0].code, category.text) == ("OTH", "Movement analysis")
    n_first_10 = len(data.result["metrics_first_10"])
    assert len(report.result) == 11 + n_first_10 + 1  # the metrics, first 10, their group
    (group,) = [e for e in doc["entry"] if "hasMember" in e["resource"]]
    assert group["resource"]["code"]["coding"][0]["code"] == "finger-tapping"
    members = {m["reference"] for m in group["resource"]["hasMember"]}
    assert len(members) == 11 + n_first_10
    assert group["fullUrl"] in {r.reference for r in report.result}
    form = report.presentedForm[0]
    assert form.contentType == "application/pdf"
    assert base64.b64decode(doc["entry"][-1]["resource"]["presentedForm"][0]["data"]) == pdf
    # Every reference resolves inside the bundle.
    urls = {e["fullUrl"] for e in doc["entry"]}
    assert {r.reference for r in report.result} <= urls
    assert report.subject.reference in urls


def test_fhir_bundle_rejects_a_malformed_resource(monkeypatch):
    import pydantic

    data = sample_report_data()
    original = exports._observation

    def without_status(*args, **kwargs):
        obs = original(*args, **kwargs)
        del obs["status"]  # required by FHIR R4
        return obs

    monkeypatch.setattr(exports, "_observation", without_status)
    with pytest.raises(pydantic.ValidationError, match="status"):
        exports.fhir_bundle(data, None)


def test_fhir_undefined_metric_has_a_data_absent_reason_and_guessed_units():
    import dataclasses

    from fhir.resources.R4B.bundle import Bundle

    data = sample_report_data()
    metrics = dict(data.result["metrics"])
    metrics["amplitude_decrement_onset_tap"] = None  # undefined: no clear decrement
    metrics["tapping_time_s"] = 7.5  # not in the catalogue: unit guessed from the name
    data = dataclasses.replace(data, result={**data.result, "metrics": metrics})
    doc = exports.fhir_bundle(data, None)
    Bundle.model_validate(doc)
    obs = {
        e["resource"]["code"]["coding"][0]["code"]: e["resource"]
        for e in doc["entry"]
        if e["resource"]["resourceType"] == "Observation"
    }
    assert "valueQuantity" not in obs["amplitude_decrement_onset_tap"]
    assert (
        obs["amplitude_decrement_onset_tap"]["dataAbsentReason"]["coding"][0]["code"]
        == "not-applicable"
    )
    assert obs["tapping_time_s"]["valueQuantity"]["code"] == "s"
    report = next(
        e["resource"] for e in doc["entry"] if e["resource"]["resourceType"] == "DiagnosticReport"
    )
    assert "presentedForm" not in report  # no PDF given, none attached


def test_fhir_values_are_the_results_and_a_revision_amends_the_same_resources():
    """A receiving system matches the resources of two revisions by their identifiers and
    sees the later one as amended (an integrator found every revision 'final', with no
    identifier, and values rounded to 6 decimals: 0.000935 for 0.0009354739957012296)."""
    import dataclasses

    first = exports.fhir_bundle(sample_report_data(), None)
    second = exports.fhir_bundle(dataclasses.replace(sample_report_data(), revision=2), None)

    def measured(doc):
        out = {}
        for e in doc["entry"]:
            r = e["resource"]
            if r["resourceType"] in ("Observation", "DiagnosticReport") and "identifier" in r:
                key = (r["identifier"][0]["system"], r["identifier"][0]["value"])
                if key[0] != "urn:bradyscope:trial-rating":  # not a measurement (below)
                    out[key] = r
        return out

    a, b = measured(first), measured(second)
    n = 11 + len(sample_report_data().result["metrics_first_10"]) + 1 + 1
    assert a.keys() == b.keys() and len(a) == n  # metrics, first 10, their panel, the report
    assert ("urn:bradyscope:trial-report", "7") in a
    assert ("urn:bradyscope:trial-observation", "7/frequency_hz") in a
    assert {r["status"] for r in a.values()} == {"final"}
    assert {r["status"] for r in b.values()} == {"amended"}
    # The version: the revision, then the digest of the resource's content.
    assert {r["meta"]["versionId"].split(".")[0] for r in a.values()} == {"1"}
    assert {r["meta"]["versionId"].split(".")[0] for r in b.values()} == {"2"}
    # The clinician's rating is not a measurement: it keeps its own status.
    rating = [e["resource"] for e in second["entry"] if "clinician-rating" in str(e["resource"])]
    assert rating[0]["status"] == "final"
    # Values exactly as result.json has them.
    metrics = sample_report_data().result["metrics"]
    for key in ("amplitude_mm_cv", "amplitude_mm_mean", "frequency_hz"):
        value = a[("urn:bradyscope:trial-observation", f"7/{key}")]["valueQuantity"]["value"]
        assert value == metrics[key], key
    # and over the first 10 taps, the values the pages, the summary and the trends show
    first_10 = sample_report_data().result["metrics_first_10"]
    for key in ("amplitude_mm_mean", "amplitude_decrement_mm_per_tap", "frequency_hz"):
        obs = a[("urn:bradyscope:trial-observation", f"7/{key}_first_10")]
        assert obs["valueQuantity"]["value"] == first_10[key], key
        assert obs["code"]["coding"][0]["code"] == f"{key}_first_10"
        assert obs["code"]["coding"][0]["display"].endswith(", first 10 taps")


def _rating(doc: dict) -> dict | None:
    found = [
        e["resource"]
        for e in doc["entry"]
        if e["resource"].get("code", {}).get("coding", [{}])[0].get("system")
        == "urn:bradyscope:clinician-rating"
    ]
    assert len(found) <= 1
    return found[0] if found else None


def test_fhir_rating_is_identified_versioned_and_withdrawn_when_cleared():
    """A receiver replaces the rating it holds by its identifier, sees a changed rating as a
    new version, and withdraws a cleared one (reviewers found no identifier, no version,
    and a cleared rating that simply vanished from the next export)."""
    from dataclasses import replace
    from datetime import UTC, datetime

    from fhir.resources.R4B.observation import Observation

    rated = replace(
        sample_report_data(), rated_at=datetime(2025, 3, 14, 10, 5, tzinfo=UTC), rated_by="Dr. A"
    )
    first = _rating(exports.fhir_bundle(rated, None))
    assert first is not None
    assert first["identifier"] == [
        {"system": "urn:bradyscope:trial-rating", "value": "7/mds-updrs-3.4"}
    ]
    assert first["meta"]["versionId"].startswith("20250314T100500Z.")
    assert first["status"] == "final" and first["valueInteger"] == 2
    assert first["performer"] == [{"display": "Dr. A"}]
    # The same rating exported again: the same version.
    assert _rating(exports.fhir_bundle(rated, None))["meta"] == first["meta"]
    changed = replace(rated, clinician_rating=3, rated_at=datetime(2025, 3, 15, 8, 0, tzinfo=UTC))
    second = _rating(exports.fhir_bundle(changed, None))
    assert second["identifier"] == first["identifier"]
    assert second["meta"]["versionId"] != first["meta"]["versionId"]
    assert second["valueInteger"] == 3
    # Cleared: the same identifier comes back withdrawn, with no value.
    cleared = replace(
        rated, clinician_rating=None, rated_at=datetime(2025, 3, 16, 8, 0, tzinfo=UTC)
    )
    gone = _rating(exports.fhir_bundle(cleared, None))
    assert gone is not None, "a cleared rating must be withdrawn, not left out"
    Observation.model_validate(gone)
    assert gone["identifier"] == first["identifier"]
    assert gone["status"] == "entered-in-error"
    assert "valueInteger" not in gone and "performer" not in gone
    assert gone["meta"]["versionId"].startswith("20250316T080000Z.")
    assert gone["issued"] == "2025-03-16T08:00:00+00:00"
    # Never rated: nothing to withdraw.
    never = replace(rated, clinician_rating=None, rating_comment=None, rated_at=None)
    assert _rating(exports.fhir_bundle(never, None)) is None


def test_fhir_bundle_identifier_names_its_content_and_the_report_its_trial():
    """A receiver that drops a Bundle whose identifier it has seen drops only the same
    content again: a revision or a rating gives another identifier (it was always
    ``urn:bradyscope:trial|7``), while the DiagnosticReport keeps the trial's."""
    from dataclasses import replace
    from datetime import UTC, datetime

    base = replace(sample_report_data(), rated_at=datetime(2025, 3, 14, 10, 5, tzinfo=UTC))

    def ids(data):
        doc = exports.fhir_bundle(data, b"%PDF-1.7 fake")
        (report,) = [
            e["resource"]
            for e in doc["entry"]
            if e["resource"]["resourceType"] == "DiagnosticReport"
        ]
        return doc["identifier"], report["identifier"]

    bundle, report = ids(base)
    assert bundle["system"] == "urn:bradyscope:trial-export"
    assert bundle["value"].startswith("7/1/")
    assert report == [{"system": "urn:bradyscope:trial-report", "value": "7"}]
    # Exported again later (another time, another PDF): the same content, the same identifier.
    again = replace(base, generated_at=datetime(2025, 4, 1, tzinfo=UTC))
    assert ids(again) == (bundle, report)
    others = {
        "revision": replace(base, revision=2),
        "rating": replace(base, clinician_rating=3, rated_at=datetime(2025, 3, 15, tzinfo=UTC)),
        "cleared rating": replace(base, clinician_rating=None),
        "comment": replace(base, rating_comment="Slowing from the 4th tap."),
        "patient code": replace(base, patient_code="PD-0043"),
        # what only the attached PDF shows: the DiagnosticReport's version follows it
        "session notes": replace(base, notes="Tremor at rest on the left."),
        "clinician": replace(base, clinician="dr.other@example.org"),
    }
    seen = {bundle["value"]}
    for what, data in others.items():
        other, other_report = ids(data)
        assert other["value"] not in seen, what
        assert other_report == report, what
        seen.add(other["value"])
    assert ids(others["revision"])[0]["value"].startswith("7/2/")


def _states(obs: dict) -> dict:
    """An Observation's session-state components by code: the value's code, the minutes,
    or the data-absent reason."""
    out = {}
    for c in obs.get("component", []):
        (coding,) = c["code"]["coding"]
        assert coding["system"] == "urn:bradyscope:session-state"
        if "valueCodeableConcept" in c:
            (value,) = c["valueCodeableConcept"]["coding"]
            out[coding["code"]] = (value["system"], value["code"])
        elif "valueQuantity" in c:
            q = c["valueQuantity"]
            out[coding["code"]] = (q["value"], q["system"], q["code"])
        else:
            out[coding["code"]] = ("absent", c["dataAbsentReason"]["coding"][0]["code"])
    return out


def test_fhir_every_observation_says_the_medication_and_dbs_state():
    """Two values of the right hand on the same day are told apart by ON/OFF on each
    Observation (a reviewer found the state only in the report's free-text conclusion)."""
    from dataclasses import replace
    from datetime import UTC, datetime

    from fhir.resources.R4B.bundle import Bundle

    off = replace(sample_report_data(), rated_at=datetime(2025, 3, 14, 10, 5, tzinfo=UTC))
    on = replace(off, medication_state="on", dbs_state="on", time_since_levodopa_min=60)
    unknown = replace(
        off, medication_state="unknown", dbs_state="unknown", time_since_levodopa_min=None
    )
    expected = {
        "off": {
            "medication-state": ("urn:bradyscope:medication-state", "off"),
            "dbs-state": ("urn:bradyscope:dbs-state", "none"),
            "time-since-levodopa": (720, "http://unitsofmeasure.org", "min"),
        },
        "on": {
            "medication-state": ("urn:bradyscope:medication-state", "on"),
            "dbs-state": ("urn:bradyscope:dbs-state", "on"),
            "time-since-levodopa": (60, "http://unitsofmeasure.org", "min"),
        },
        "unknown": {
            "medication-state": ("absent", "unknown"),
            "dbs-state": ("absent", "unknown"),
        },
    }
    versions = {}
    for name, data in (("off", off), ("on", on), ("unknown", unknown)):
        doc = exports.fhir_bundle(data, None)
        Bundle.model_validate(doc)
        observations = [
            e["resource"] for e in doc["entry"] if e["resource"]["resourceType"] == "Observation"
        ]
        # every metric, first-10 value, the panel and the rating
        assert len(observations) == 11 + len(data.result["metrics_first_10"]) + 1 + 1
        for obs in observations:
            assert _states(obs) == expected[name], (name, obs["code"]["coding"][0]["code"])
        versions[name] = {o["identifier"][0]["value"]: o["meta"]["versionId"] for o in observations}
    # The session's state edited: the same resources, each in a new version.
    assert versions["off"].keys() == versions["on"].keys()
    assert all(versions["off"][k] != versions["on"][k] for k in versions["off"])


def _lost_frames_table(markers, lost_after: tuple[int, ...], *, fps: float, jitter_s: float):
    """``markers`` as a camera that lost one frame after each of ``lost_after`` (frame
    numbers of the written video) records it: the rows of the lost instants removed, the
    others with their capture times (seeded jitter) and frame numbers of the video, the
    rate ``fps`` as result.json gives it (a median of jittered intervals can be off).
    Returns the table and each row's true slot (its instant's number at 60 fps)."""
    video = np.arange(markers.frames.size - len(lost_after))
    slots = video + (np.asarray(lost_after)[None, :] < video[:, None]).sum(axis=1)
    t_s = slots / 60.0 + np.random.default_rng(5).normal(scale=jitter_s, size=slots.size)
    t_s -= t_s[0]
    table = markers_csv.MarkerTable(
        fps=fps,
        frames=np.arange(slots.size, dtype=np.int64),
        labels=markers.labels,
        positions_mm=markers.positions_mm[slots],
        status=markers.status[slots],
        reprojection_px=markers.reprojection_px[slots],
        frame_time_s=t_s,
    )
    return table, slots


@pytest.mark.filterwarnings("ignore:No analog data found:UserWarning")
def test_c3d_and_trc_keep_each_frame_at_its_time_after_lost_frames(tmp_path):
    """Frame k of a C3D or TRC file is at k / rate: a lost frame is an invalid sample, not
    a frame less. A reviewer found a recording with 3 lost frames written as 297 frames at
    60.1 Hz: a reader put frame 101 at 1.664 s (taken at 1.699 s), all after frame 200
    ~50 ms early, and the TRC declared 60.1 Hz beside an irregular Time column."""
    import dataclasses

    import c3d

    markers = dataclasses.replace(synthetic_trial()[0], fps=60.0)  # Hz
    table, slots = _lost_frames_table(markers, (100, 101, 200), fps=60.1, jitter_s=0.001)
    assert table.frames.size == markers.frames.size - 3
    path = trajectories.write_c3d(tmp_path / "lost.c3d", table)
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)
        rate = reader.point_rate
        first_frame = reader.first_frame
        pts = np.stack([p.copy() for _, p, _ in reader.read_frames()])  # (T, M, 5)
    assert pts.shape[0] == markers.frames.size  # 300 frames: the lost ones are there
    assert rate == pytest.approx(60.0, abs=0.01)  # Hz: the capture times' rate, not 60.1
    assert first_frame == 1
    lost = np.setdiff1d(np.arange(markers.frames.size), slots)
    np.testing.assert_array_equal(lost, [101, 103, 203])  # after video frames 100, 101, 200
    assert (pts[lost][:, :, 3] == -1).all() and (pts[lost][:, :, :3] == 0).all()  # invalid
    valid = np.isfinite(table.positions_mm).all(axis=2)
    # Each written frame in the slot of its instant: k / rate is its capture time.
    np.testing.assert_allclose(pts[slots][valid][:, :3], table.positions_mm[valid], atol=1e-3)
    np.testing.assert_allclose(slots / rate, table.frame_time_s, atol=0.004)  # s: 1-ms jitter
    # The TRC: the same grid, a regular Time column at its DataRate, lost frames empty.
    trc = trajectories.write_trc(tmp_path / "lost.trc", table)
    lines = trc.read_text().splitlines()
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    assert int(header["NumFrames"]) == markers.frames.size
    assert float(header["DataRate"]) == pytest.approx(rate, abs=1e-3)
    rows = [ln.split("\t") for ln in lines[6:]]
    times = np.array([float(r[1]) for r in rows])
    np.testing.assert_allclose(times, np.arange(len(rows)) / float(header["DataRate"]), atol=2e-6)
    assert all(rows[k][2:] == [""] * 6 for k in lost)
    _, _, pos = trajectories.read_trc(trc)
    np.testing.assert_allclose(pos[slots][valid], table.positions_mm[valid], atol=5e-5)  # mm
    assert np.isnan(pos[lost]).all()


def test_uniform_grid_keeps_a_table_without_lost_frames_as_it_is():
    """Convention: a recording without capture times, or whose times are its frames at
    its rate, is written frame for frame at its own rate (what was right stays)."""
    markers = synthetic_trial()[0]
    assert trajectories.on_uniform_grid(markers) is markers  # no capture times: frame / fps
    from dataclasses import replace

    timed = replace(markers, frame_time_s=markers.frames / markers.fps)
    grid = trajectories.on_uniform_grid(timed)
    assert grid.fps == markers.fps  # the nominal rate, not a fitted 99.99999...
    np.testing.assert_array_equal(grid.frames, markers.frames)
    np.testing.assert_array_equal(grid.status, markers.status)
    np.testing.assert_array_equal(grid.positions_mm, markers.positions_mm)


@pytest.mark.filterwarnings("ignore:No analog data found:UserWarning")
def test_c3d_of_a_measured_recording_with_lost_frames_matches_the_capture_times(tmp_path):
    """End to end, as the reviewer did: a simulated take whose left camera lost a frame
    after its frames 100, 101 and 200 (variable frame rate, 1 ms of capture jitter),
    measured by the analysis, exported through markers.csv and result.json. Each of the
    C3D's frames is at k / POINT:RATE within the jitter of the instant the camera took it."""
    import ezc3d

    from core.camera import ImageSize, read_rig
    from core.pipeline import analyze_recording, write_analysis
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session
    from core.simulation.timing import CameraTiming

    left = CameraTiming(jitter_s=0.001, vfr=True, drop_after=(100, 101, 200))
    sim = simulate_session(
        tmp_path / "sim",
        seed=3,
        tapping=TappingScenario(duration_s=5.0, fps=60.0),
        imaging=ImagingScenario(
            image_size=ImageSize(640, 512),
            codec="h264",
            left_timing=left,
            right_timing=CameraTiming(jitter_s=0.001, vfr=True),
        ),
    )
    analysis = analyze_recording(read_rig(sim.rig_path), sim.left_video, sim.right_video)
    write_analysis(analysis, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["sync"]["dropped_frames_left"] == [100, 101, 200]
    table = markers_csv.read_markers_csv(tmp_path / "out" / "markers.csv", fps=doc["fps"])
    assert table.frames.size == 297  # the decoded frames

    c3d = ezc3d.c3d(str(trajectories.write_c3d(tmp_path / "trial.c3d", table)))
    rate = c3d["parameters"]["POINT"]["RATE"]["value"][0]
    points = c3d["data"]["points"]  # (4, M, T)
    assert points.shape[2] == 300  # every instant the camera took, lost ones included
    assert rate == pytest.approx(60.0, rel=1e-3)  # Hz
    true_s = np.asarray(sim.truth["cameras"]["left"]["true_time_s"])  # s, each decoded frame
    slots = np.rint(true_s * 60.0).astype(int)  # the instant's number at the camera's rate
    lost = np.setdiff1d(np.arange(300), slots)
    np.testing.assert_array_equal(lost, [101, 103, 203])
    # Invalid: residual -1, which ezc3d reads as NaN coordinates (zeros in the file: above).
    assert (c3d["data"]["meta_points"]["residuals"][0][:, lost] < 0).all()
    assert np.isnan(points[:3][:, :, lost]).all()
    # Each decoded frame is in the slot of its instant, k / rate its capture time.
    valid = np.isfinite(table.positions_mm).all(axis=2)  # (T, M)
    xyz = np.transpose(points[:3][:, :, slots], (2, 1, 0))  # (T, M, 3)
    np.testing.assert_allclose(xyz[valid], table.positions_mm[valid], atol=1e-3)  # mm
    np.testing.assert_allclose(slots / rate, true_s - true_s[0], atol=0.004)  # s, 1-ms jitter
