# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Per-trial ratings through the API and FHIR, and the visit report (page 1 read with pdftotext)."""

from __future__ import annotations

import re
import shutil
import subprocess
from datetime import UTC, datetime

import pytest
from api_support import Api, api, seed_recording_target  # noqa: F401 - pytest fixtures
from fhir.resources.R4B.bundle import Bundle
from sample_trial import synthetic_trial

from app.models import RecordingSession, Result, Trial
from app.reports.catalogue import format_metric
from app.storage import Storage
from core.clinical import asymmetry_pct, medication_response_pct
from core.markers_csv import markers_csv_text
from core.version import software_version

needs_poppler = pytest.mark.skipif(
    shutil.which("pdftotext") is None, reason="poppler-utils (pdftotext) is not installed"
)


def _trial_with_result(api: Api, session_id: int, hand: str, **kw) -> tuple[int, dict]:
    """A trial with a known (synthetic) result, stored as the worker would."""
    markers, document = synthetic_trial(**kw)
    stored = Storage.from_settings(api.settings).write_bytes(
        "results", ".csv", markers_csv_text(markers).encode()
    )
    with api.sessions() as db:
        trial = Trial(session_id=session_id, hand=hand, status="succeeded")
        db.add(trial)
        db.flush()
        db.add(Result(trial_id=trial.id, document=document, markers_path=stored.path))
        db.commit()
        return trial.id, document


def test_rating_round_trip(api: Api):
    seeded = seed_recording_target(api)
    trial_id, _ = _trial_with_result(api, seeded.session_id, "left")
    h, url = api.headers, f"/api/v1/trials/{trial_id}"
    assert api.client.get(url, headers=h).json()["clinician_rating"] is None
    r = api.client.patch(
        url, json={"clinician_rating": 3, "comment": "Halts after tap 6."}, headers=h
    )
    assert r.status_code == 200, r.text
    assert (r.json()["clinician_rating"], r.json()["comment"]) == (3, "Halts after tap 6.")
    assert r.json()["rated_at"] is not None
    got = api.client.get(url, headers=h).json()
    assert (got["clinician_rating"], got["comment"]) == (3, "Halts after tap 6.")
    # Omitted fields stay; null clears.
    r = api.client.patch(url, json={"comment": "Revised."}, headers=h)
    assert (r.json()["clinician_rating"], r.json()["comment"]) == (3, "Revised.")
    r = api.client.patch(url, json={"clinician_rating": None}, headers=h)
    assert (r.json()["clinician_rating"], r.json()["comment"]) == (None, "Revised.")
    for bad in ({"clinician_rating": 5}, {"clinician_rating": -1}, {"rating": 2}):
        assert api.client.patch(url, json=bad, headers=h).status_code == 422, bad
    # A rating is a whole number: JSON true, "2" or 2.0 is refused, not read as 1 or 2.
    for bad in (True, "2", 2.0):
        r = api.client.patch(url, json={"clinician_rating": bad}, headers=h)
        assert r.status_code == 422 and "valid integer" in r.text, (bad, r.text)
    assert api.client.get(url, headers=h).json()["clinician_rating"] is None
    assert api.client.patch("/api/v1/trials/9999", json={}, headers=h).status_code == 404


def test_a_rating_belongs_to_its_hand(api: Api):
    """The left hand's result no longer shows the right hand's rating."""
    seeded = seed_recording_target(api)
    left, _ = _trial_with_result(api, seeded.session_id, "left")
    right, _ = _trial_with_result(api, seeded.session_id, "right")
    h = api.headers
    api.client.patch(f"/api/v1/trials/{right}", json={"clinician_rating": 3}, headers=h)
    api.client.patch(f"/api/v1/trials/{left}", json={"clinician_rating": 1}, headers=h)
    left_html = api.client.get(f"/api/v1/trials/{left}/report.html", headers=h).text
    right_html = api.client.get(f"/api/v1/trials/{right}/report.html", headers=h).text
    assert "<span data-rating>1</span>" in left_html
    assert "<span data-rating>3</span>" in right_html


def test_fhir_bundle_holds_the_clinicians_rating_as_its_own_observation(api: Api):
    seeded = seed_recording_target(api)
    trial_id, document = _trial_with_result(api, seeded.session_id, "right")
    h = api.headers
    api.client.patch(
        f"/api/v1/trials/{trial_id}", json={"clinician_rating": 2, "comment": "Mild."}, headers=h
    )
    bundle = api.client.get(f"/api/v1/trials/{trial_id}/fhir", headers=h).json()
    Bundle.model_validate(bundle)  # valid FHIR (R4B models; R4-compatible for these resources)
    resources = [(e["fullUrl"], e["resource"]) for e in bundle["entry"]]
    ratings = [
        (url, r)
        for url, r in resources
        if r["resourceType"] == "Observation"
        and r["code"]["coding"][0]["system"] == "urn:bradyscope:clinician-rating"
    ]
    assert len(ratings) == 1
    url, rating = ratings[0]
    assert rating["valueInteger"] == 2 and rating["note"] == [{"text": "Mild."}]
    assert rating["category"][0]["text"] == "Clinician's rating"
    assert "valueQuantity" not in rating
    measured = [
        r
        for _, r in resources
        if r["resourceType"] == "Observation"
        and r["code"]["coding"][0]["system"] == "urn:bradyscope:finger-tapping-metric"
    ]
    assert len(measured) == len(document["metrics"]) + len(document["metrics_first_10"])
    (report,) = [r for _, r in resources if r["resourceType"] == "DiagnosticReport"]
    assert url not in {ref["reference"] for ref in report["result"]}  # not a measurement
    # A cleared rating comes back withdrawn, under the same identifier, with no value.
    api.client.patch(f"/api/v1/trials/{trial_id}", json={"clinician_rating": None}, headers=h)
    bundle = api.client.get(f"/api/v1/trials/{trial_id}/fhir", headers=h).json()
    Bundle.model_validate(bundle)
    (withdrawn,) = [
        e["resource"]
        for e in bundle["entry"]
        if "clinician-rating" in str(e["resource"].get("code"))
    ]
    assert withdrawn["identifier"] == rating["identifier"]
    assert withdrawn["meta"]["versionId"] != rating["meta"]["versionId"]
    assert withdrawn["status"] == "entered-in-error" and "valueInteger" not in withdrawn


def _visit(api: Api) -> dict:
    """One morning: off medication (09:30 UTC) and on (11:30), both hands each."""
    seeded = seed_recording_target(api)  # its session: off medication, 09:30 UTC
    with api.sessions() as db:
        on = RecordingSession(
            patient_id=seeded.patient_id,
            rig_id=seeded.rig_id,
            recorded_at=datetime(2026, 3, 1, 11, 30, tzinfo=UTC),
            medication_state="on",
            time_since_levodopa_min=90,
        )
        later = RecordingSession(  # another day: not part of the visit
            patient_id=seeded.patient_id,
            rig_id=seeded.rig_id,
            recorded_at=datetime(2026, 3, 8, 9, 30, tzinfo=UTC),
            medication_state="on",
        )
        db.add_all([on, later])
        db.commit()
        on_id, later_id = on.id, later.id
    docs, ids = {}, {}
    plan = {
        ("right", "off", seeded.session_id): dict(amplitude0_mm=40.0, frequency_hz=2.0),
        ("left", "off", seeded.session_id): dict(amplitude0_mm=52.0, frequency_hz=3.0),
        ("right", "on", on_id): dict(amplitude0_mm=48.0, frequency_hz=2.6),
        ("left", "on", on_id): dict(amplitude0_mm=54.0, frequency_hz=3.1),
        ("left", "on-later", later_id): dict(amplitude0_mm=99.0, frequency_hz=4.4),
    }
    for (hand, med, sid), kw in plan.items():
        ids[(hand, med)], docs[(hand, med)] = _trial_with_result(api, sid, hand, **kw)
    h = api.headers
    for (hand, med), rating in {
        ("right", "off"): 3,
        ("left", "off"): 1,
        ("right", "on"): 2,
    }.items():
        r = api.client.patch(
            f"/api/v1/trials/{ids[(hand, med)]}",
            json={"clinician_rating": rating, "comment": f"{hand}-{med} seen"},
            headers=h,
        )
        assert r.status_code == 200
    return {"session_id": seeded.session_id, "docs": docs, "ids": ids}


def _first10(doc: dict, key: str) -> float:
    return float(doc["metrics_first_10"][key])


@needs_poppler
def test_visit_report_page_one_summarises_the_visit(api: Api, tmp_path):
    visit = _visit(api)
    r = api.client.get(f"/api/v1/sessions/{visit['session_id']}/report.pdf", headers=api.headers)
    assert r.status_code == 200 and r.headers["content-type"] == "application/pdf"
    # named as the trials' reports are, by the patient's code (not the internal id)
    name = r.headers["content-disposition"]
    assert re.search(r'filename="[A-Z0-9-]+-visit-\d{4}-\d\d-\d\d-report\.pdf"', name), name
    pdf = tmp_path / "visit.pdf"
    pdf.write_bytes(r.content)
    page1 = subprocess.run(
        ["pdftotext", "-f", "1", "-l", "1", str(pdf), "-"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    page1 = " ".join(page1.split())  # table cells wrap over lines
    docs = visit["docs"]
    for hand in ("Right", "Left"):
        for med in ("off", "on"):
            assert f"{hand} hand, medication {med}" in page1
    for key in ("frequency_hz", "amplitude_mm_mean", "opening_velocity_mm_s_max"):
        for trial in (("right", "off"), ("left", "off"), ("right", "on"), ("left", "on")):
            assert format_metric(key, _first10(docs[trial], key)) in page1, (key, trial)
    assert "99.0" not in page1 and "4.40" not in page1  # the next week's trial is another visit
    # Asymmetry (off: right against left) and medication response (right hand), in %.
    asym = asymmetry_pct(
        _first10(docs[("right", "off")], "amplitude_mm_mean"),
        _first10(docs[("left", "off")], "amplitude_mm_mean"),
    )
    response = medication_response_pct(
        _first10(docs[("right", "on")], "frequency_hz"),
        _first10(docs[("right", "off")], "frequency_hz"),
    )
    assert "asymmetry" in page1 and "Medication response" in page1
    assert f"{asym:+.0f} %" in page1 and f"{response:+.0f} %" in page1
    # The ratings and comments, and who made the numbers.
    assert "right-off seen" in page1 and "left-off seen" in page1 and "right-on seen" in page1
    assert f"bradyscope {software_version()}" in page1
    assert "Interpretation" in page1 and "Signature" in page1
    pages = subprocess.run(["pdfinfo", str(pdf)], check=True, capture_output=True, text=True).stdout
    assert int(next(ln for ln in pages.splitlines() if ln.startswith("Pages:")).split()[1]) > 1


def test_visit_report_html_and_its_404(api: Api):
    visit = _visit(api)
    h = api.headers
    html = api.client.get(f"/api/v1/sessions/{visit['session_id']}/report.html", headers=h).text
    assert html.count('data-summary-row="frequency_hz"') == 1  # one task group: finger tapping
    assert html.count("trial-detail") >= 4
    r = api.client.get("/api/v1/sessions/9999/report.pdf", headers=h)
    assert r.status_code == 404 and "detail" in r.json()


def test_calibration_quality_is_labelled_with_units():
    from app.web.rigs import _quality_items

    items = dict(
        _quality_items(
            {"rms_px_left": 0.21, "coverage_left": 0.62, "per_view": [1], "method": "opencv"}
        )
    )
    assert items == {
        "RMS reprojection error, left camera": "0.21 px",
        "Image coverage, left camera": "62 %",
    }


def test_a_json_file_that_is_not_a_rig_file_says_so():
    from core.camera import rig_from_dict
    from core.errors import RigFileError

    with pytest.raises(RigFileError, match="is not a rig file"):
        rig_from_dict({"patient": "x", "values": [1, 2]})


def test_two_identical_videos_are_refused(api: Api, tmp_path):
    from api_support import trial_files, write_video

    seeded = seed_recording_target(api)
    video = write_video(tmp_path / "same.mp4")
    r = api.client.post(
        f"/api/v1/sessions/{seeded.session_id}/trials",
        data={"hand": "left"},
        files=trial_files(video, video),
        headers=api.headers,
    )
    assert r.status_code == 422 and "same file" in r.json()["detail"], r.text
    assert api.stored_files() == []  # nothing kept


def test_calibration_form_errors_name_the_form_labels():
    from app.services.calibration_form import board_fields as _board_fields
    from app.uploads import InvalidUpload, ParsedUpload
    from app.web.rigs import CALIBRATION_FORM_LABELS

    upload = ParsedUpload(storage=None, fields={"board": "charuco", "cols": "8", "rows": "6"})
    upload.labels.update(CALIBRATION_FORM_LABELS)
    with pytest.raises(InvalidUpload, match=r"Fill in “Square size \(mm\)”"):
        _board_fields(upload)
    upload.fields["square_mm"] = "-3"
    with pytest.raises(InvalidUpload, match=r"^Square size \(mm\) must be a number"):
        _board_fields(upload)


def test_a_visit_report_asked_again_comes_from_the_cache_until_its_content_changes(api: Api):
    """A visit report took 1.5-3 s at every request (found in a clinician-style review):
    it is kept in the report cache, by its content, as the trials' reports are."""
    import time

    from app.reports.pdf_cache import ReportPdfCache

    visit = _visit(api)
    h, url = api.headers, f"/api/v1/sessions/{visit['session_id']}/report.pdf"
    cache = ReportPdfCache.of(Storage.from_settings(api.settings))
    first = api.client.get(url, headers=h)
    assert first.status_code == 200 and first.content.startswith(b"%PDF")
    kept = list(cache.directory.glob("*-visit-*.pdf"))
    assert len(kept) == 1 and kept[0].read_bytes() == first.content
    start = time.perf_counter()
    again = api.client.get(url, headers=h)
    assert again.content == first.content  # the same file, its "generated on" time with it
    assert time.perf_counter() - start < 1.0  # s: read, not made (made: 1.5-3 s)
    # A rating changes what the visit report shows: it is made anew.
    trial_id = visit["ids"][("right", "off")]
    r = api.client.patch(
        f"/api/v1/trials/{trial_id}", json={"comment": "Seen again for the cache."}, headers=h
    )
    assert r.status_code == 200
    changed = api.client.get(url, headers=h)
    assert changed.content != first.content
    assert len(list(cache.directory.glob("*-visit-*.pdf"))) == 2
    # every visit export stays audited, whether made or read
    exports = [e for e in api.audit_events() if e.resource_type == "visit_report_pdf"]
    assert len(exports) == 3
