"""The visit report's words, from its data (no database): what a printed page names."""

from __future__ import annotations

import dataclasses
import html as html_lib
import re
import shutil
import subprocess
from datetime import UTC, datetime, timedelta

import pytest
from sample_trial import sample_report_data, synthetic_trial

from app.reports.data import ReportData
from app.reports.rendering import render_report_pdf, render_visit_html, render_visit_pdf
from app.reports.visit import SessionFacts, SignatureLine, VisitData, task_groups
from core.version import software_version

needs_poppler = pytest.mark.skipif(
    shutil.which("pdftotext") is None, reason="poppler-utils (pdftotext) is not installed"
)


def _trial(trial_id: int, hand: str, med: str, minutes: int, **kw) -> ReportData:
    base = sample_report_data()
    _, doc = synthetic_trial(**kw)
    return dataclasses.replace(
        base,
        trial_id=trial_id,
        hand=hand,
        medication_state=med,
        result=doc,
        recorded_at=base.recorded_at + timedelta(minutes=minutes),  # 09:30 UTC + minutes
        timezone="Europe/Prague",
        clinician_rating=None,
        rating_comment=f"comment of #{trial_id}",
    )


def _visit(*trials: ReportData, **kw) -> VisitData:
    first = trials[0]
    return VisitData(
        patient_code="PD-0042",
        session_id=1,
        visit_date=first.recorded_at.date(),
        timezone="Europe/Prague",
        sessions=(SessionFacts(1, first.recorded_at, "off", "none"),),
        trials=trials,
        software_version=software_version(),
        generated_at=first.generated_at,
        **kw,
    )


def _text(html: str) -> str:
    return re.sub(r"\s+", " ", html_lib.unescape(re.sub(r"<[^>]+>", " ", html)))


def test_two_trials_of_one_side_and_state_are_told_apart_and_the_asymmetry_names_its_pair():
    first = _trial(12, "right", "off", 0, amplitude0_mm=30.0)  # 10:30 in Prague (CET)
    again = _trial(13, "right", "off", 12, amplitude0_mm=35.0)  # 10:42
    left = _trial(11, "left", "off", 5, amplitude0_mm=45.0)
    (group,) = task_groups([first, again, left])
    labels = [c.label for c in group.columns]
    assert len(set(labels)) == 3, labels
    assert "Right hand, medication off — trial #12, 10:30 CET" in labels
    assert "Right hand, medication off — trial #13, 10:42 CET" in labels
    assert "Left hand, medication off" in labels  # alone in its side and state: as before
    (note,) = group.pairs
    assert note == (
        "Right–left asymmetry, medication off: trial #13 (right) against trial #11 (left),"
        " the newest of each; not compared: trial #12."
    )

    html = render_visit_html(_visit(first, again, left))
    summary = re.search(r"<table class=\"summary[^>]*>.*?</thead>", html, re.S).group(0)
    heads = re.findall(r'<th scope="col" class="num">([^<]+)</th>', summary)
    assert len(heads) == 3 and len(set(heads)) == 3, heads
    ratings = re.search(r"<table class=\"compact ratings\".*?</table>", html, re.S).group(0)
    rows = re.findall(r'<tr><th scope="row">([^<]+)</th>', ratings)
    assert len(rows) == 3 and len(set(rows)) == 3, rows
    assert note in html_lib.unescape(html)


def test_one_trial_per_side_and_state_keeps_its_short_label_and_no_pair_note():
    right, left = _trial(3, "right", "off", 0), _trial(9, "left", "off", 5)
    (group,) = task_groups([right, left])
    assert [c.label for c in group.columns] == [
        "Right hand, medication off",
        "Left hand, medication off",
    ]
    assert group.pairs == ()


def _pdf_pages(pdf: bytes, tmp_path) -> list[str]:
    path = tmp_path / "report.pdf"
    path.write_bytes(pdf)
    text = subprocess.run(
        ["pdftotext", "-layout", str(path), "-"], check=True, capture_output=True, text=True
    ).stdout
    return [" ".join(page.split()) for page in text.split("\f") if page.strip()]


@needs_poppler
def test_every_page_of_the_trial_report_names_patient_task_side_date_and_state(tmp_path):
    data = dataclasses.replace(sample_report_data(), timezone="Europe/Prague")
    pages = _pdf_pages(render_report_pdf(data), tmp_path)
    assert len(pages) > 2
    running = (
        "PD-0042 · Finger tapping (MDS-UPDRS 3.4) · right hand · medication off"
        " · 2025-03-14 10:30 CET · trial #7"
    )
    for number, page in enumerate(pages, 1):
        assert page.startswith(running), (number, page[:200])


@needs_poppler
def test_every_page_of_the_visit_report_names_what_it_shows(tmp_path):
    right = _trial(3, "right", "off", 0)
    left = _trial(9, "left", "on", 120)
    html = render_visit_html(_visit(right, left))
    # the per-trial heading names the task: two tasks of one hand read apart
    assert "Finger tapping: right hand, medication off — trial #3" in html_lib.unescape(html)
    pages = _pdf_pages(render_visit_pdf(_visit(right, left)), tmp_path)
    assert pages[0].startswith(
        "PD-0042 · visit of 2025-03-14 · summary of 2 trials: finger tapping · right and left"
        " · medication off and on"
    ), pages[0][:200]
    heads = {
        3: "PD-0042 · Finger tapping (MDS-UPDRS 3.4) · right hand · medication off"
        " · 2025-03-14 10:30 CET · trial #3",
        9: "PD-0042 · Finger tapping (MDS-UPDRS 3.4) · left hand · medication on"
        " · 2025-03-14 12:30 CET · trial #9",
    }
    definitions = "PD-0042 · visit of 2025-03-14 · definitions"
    shown = [
        next((h for h in (*heads.values(), definitions) if p.startswith(h)), None) for p in pages
    ]
    assert None not in shown[1:], [p[:120] for p in pages]
    assert set(shown[1:]) == {*heads.values(), definitions}
    for trial, head in heads.items():  # each trial's detail begins on a page headed by it
        first = next(p for p in pages if f"— trial #{trial}," in p)
        assert first.startswith(head), first[:200]


def test_a_copy_made_now_says_it_is_not_the_signed_record_and_where_that_is():
    right, left = _trial(3, "right", "off", 0), _trial(9, "left", "off", 5)
    unsigned = _text(render_visit_html(_visit(right, left)))
    assert "Not signed. No clinician has signed this visit report" in unsigned
    line = SignatureLine(
        signed_by="Dr. Sign",
        signed_at=right.recorded_at + timedelta(hours=3),
        number=1,
        revisions=((3, 1), (9, 1)),
    )
    later = _text(render_visit_html(_visit(right, left, signatures_on_record=(line,))))
    assert (
        "Not the signed record. This visit was signed as signature 1 on 2025-03-14 13:30 CET by"
        " Dr. Sign; this copy was generated later" in later
    )
    assert "/sessions/1/signed/1.pdf" in later
    # its signature box is not left blank to be taken for an unsigned record
    assert "Not in this copy: signed electronically as signature 1 by Dr. Sign" in later
    signed = _text(render_visit_html(_visit(right, left).signed(line)))
    assert "Not signed" not in signed and "Not the signed record" not in signed
    assert "Electronically signed by Dr. Sign" in signed


@needs_poppler
def test_two_trials_of_a_side_are_told_apart_by_their_own_time_not_the_sessions(tmp_path):
    """Both read "21:47 UTC", the session's start, though taken at 21:48 and 21:51."""
    session_at = datetime(2026, 11, 28, 21, 47, tzinfo=UTC)

    def take(trial_id: int, uploaded_at: datetime) -> ReportData:
        return dataclasses.replace(
            _trial(trial_id, "right", "off", 0),
            recorded_at=session_at,
            uploaded_at=uploaded_at,
            timezone="UTC",
        )

    first = take(17, session_at + timedelta(minutes=1))
    again = take(19, session_at + timedelta(minutes=4))
    later = take(23, datetime(2026, 11, 30, 8, 5, tzinfo=UTC))  # uploaded two days later
    (group,) = task_groups([first, again, later])
    assert [c.label for c in group.columns] == [
        "Right hand, medication off — trial #17, uploaded 21:48 UTC",
        "Right hand, medication off — trial #19, uploaded 21:51 UTC",
        "Right hand, medication off — trial #23, uploaded 2026-11-30 08:05 UTC",
    ]
    visit = dataclasses.replace(
        _visit(first, again, later),
        timezone="UTC",
        visit_date=session_at.date(),
        sessions=(SessionFacts(1, session_at, "off", "none"),),
    )
    text = " ".join(_pdf_pages(render_visit_pdf(visit), tmp_path))
    assert "trial #17, uploaded 2026-11-28 21:48 UTC, result revision" in text
    assert "trial #19, uploaded 2026-11-28 21:51 UTC, result revision" in text
    assert "· uploaded 2026-11-28 21:51 UTC · trial #19" in text  # the page's running head
    assert "trial #17, 2026-11-28 21:47" not in text
