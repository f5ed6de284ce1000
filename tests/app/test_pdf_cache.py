"""The PDF report cache on disk: names, bounds, erasure and clearing (no database)."""

from __future__ import annotations

import os
import time

import pytest

from app.reports.pdf_cache import KEEP_PER_TRIAL, ReportPdfCache

PDF = b"%PDF-1.7 a report"


def _key(n: int) -> str:
    return f"{n:064x}"


def _age(path, seconds_ago: float) -> None:
    t = time.time() - seconds_ago
    os.utime(path, (t, t))


def test_a_kept_report_is_found_by_its_patient_trial_and_key(tmp_path):
    cache = ReportPdfCache(tmp_path / "reports", max_bytes=10_000)
    assert cache.get(1, 2, _key(3)) is None  # nothing kept yet, not even the folder
    path = cache.put(1, 2, _key(3), PDF)
    assert path == tmp_path / "reports" / f"1-2-{_key(3)}.pdf"
    assert cache.get(1, 2, _key(3)) == PDF
    assert cache.get(1, 2, _key(4)) is None  # another content
    assert cache.get(1, 5, _key(3)) is None  # another trial
    assert cache.get(9, 2, _key(3)) is None  # another patient
    assert not list((tmp_path / "reports").glob("*.part"))  # written under a temporary name


def test_a_report_found_counts_as_just_used(tmp_path):
    cache = ReportPdfCache(tmp_path, max_bytes=10_000)
    path = cache.put(1, 2, _key(3), PDF)
    _age(path, 3600)
    assert cache.get(1, 2, _key(3)) == PDF
    assert time.time() - path.stat().st_mtime < 60  # s


def test_names_and_contents_are_checked(tmp_path):
    cache = ReportPdfCache(tmp_path, max_bytes=10_000)
    for key in ("ABC", "A" * 64, "../" + _key(1)[3:], _key(1) + "0"):
        with pytest.raises(ValueError, match="SHA-256"):
            cache.put(1, 2, key, PDF)
    for patient, trial in ((0, 2), (1, -2), (True, 2), ("1", 2)):
        with pytest.raises(ValueError, match="positive integer"):
            cache.get(patient, trial, _key(1))
    with pytest.raises(ValueError, match="only a PDF"):
        cache.put(1, 2, _key(1), b"<html>")
    with pytest.raises(ValueError, match="max_bytes"):
        ReportPdfCache(tmp_path, max_bytes=0)
    assert list(tmp_path.iterdir()) == []


def test_a_trial_keeps_its_most_recently_used_reports(tmp_path):
    cache = ReportPdfCache(tmp_path, max_bytes=10_000)
    other = cache.put(1, 3, _key(99), PDF)  # another trial of the same patient
    _age(other, 5000)
    for n in range(5):
        path = cache.put(1, 2, _key(n), PDF)
        _age(path, 1000 - n)  # put in the order 0, 1, 2, 3, 4
    kept = sorted(p.name for p in tmp_path.glob("1-2-*.pdf"))
    assert kept == [f"1-2-{_key(n)}.pdf" for n in range(5 - KEEP_PER_TRIAL, 5)]
    assert other.exists()


def test_the_cache_stays_within_its_bound_least_recently_used_first(tmp_path):
    pdf = PDF + b"x" * (1000 - len(PDF))
    cache = ReportPdfCache(tmp_path, max_bytes=3 * len(pdf))
    paths = {}
    for n in (1, 2, 3):
        paths[n] = cache.put(1, n, _key(n), pdf)
        _age(paths[n], 100 - n)  # put in the order 1, 2, 3
    assert cache.get(1, 1, _key(1)) == pdf  # the oldest is used again: kept longest
    paths[4] = cache.put(1, 4, _key(4), pdf)
    assert {n for n, p in paths.items() if p.exists()} == {1, 3, 4}
    assert sum(p.stat().st_size for p in cache.files()) <= cache.max_bytes


def test_forgetting_a_patient_removes_their_reports_only(tmp_path):
    cache = ReportPdfCache(tmp_path, max_bytes=10_000)
    cache.put(1, 2, _key(1), PDF)
    cache.put(1, 3, _key(2), PDF)
    cache.put(12, 4, _key(3), PDF)  # patient 12 starts like patient 1
    partial = tmp_path / f"1-2-{_key(5)}.pdf.0123.part"  # a report being written
    partial.write_bytes(PDF)
    assert cache.forget_patient(1) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"12-4-{_key(3)}.pdf"]
    assert cache.forget_patient(1) == 0


def test_clear_empties_the_cache(tmp_path):
    cache = ReportPdfCache(tmp_path / "reports", max_bytes=10_000)
    assert cache.clear() == 0  # no folder yet
    cache.put(1, 2, _key(1), PDF)
    cache.put(3, 4, _key(2), PDF)
    assert cache.clear() == 2 and cache.files() == []


def test_a_crashed_writers_temporary_file_goes_at_the_next_write(tmp_path):
    cache = ReportPdfCache(tmp_path, max_bytes=10_000)
    old = tmp_path / f"1-2-{_key(1)}.pdf.aaaa.part"
    fresh = tmp_path / f"1-2-{_key(1)}.pdf.bbbb.part"  # another process writing now
    for path in (old, fresh):
        path.write_bytes(b"%PDF half")
    _age(old, 2 * 3600)
    cache.put(3, 4, _key(2), PDF)
    assert not old.exists() and fresh.exists()
