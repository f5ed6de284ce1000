"""``write_analysis``: the files of a run appear whole or not at all."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from core import pipeline


class _Stub:
    def __init__(self, value: int) -> None:
        self.value = value

    def result_document(self) -> dict:
        return {"run": self.value}


def test_a_full_disk_leaves_the_earlier_run_s_files_as_they_were(tmp_path: Path, monkeypatch):
    """An operations review: a full disk left a 4096-byte result.json (and a re-run would
    have truncated a good one)."""
    monkeypatch.setattr(
        pipeline, "write_markers_csv", lambda a, fh: fh.write(f"frame,run\n0,{a.value}\n")
    )
    pipeline.write_analysis(_Stub(1), tmp_path)  # type: ignore[arg-type]
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(before) == {"markers.csv", "result.json"} and b'"run": 1' in before["result.json"]
    real_fsync, calls = pipeline.os.fsync, []

    def fsync(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(pipeline.os, "fsync", fsync)
    with pytest.raises(OSError, match="No space left"):
        pipeline.write_analysis(_Stub(2), tmp_path)  # type: ignore[arg-type]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
