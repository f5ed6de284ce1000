"""Derived files of patients kept on disk under ``<data dir>/cache/``, bounded.

The shared part of :mod:`app.reports.pdf_cache` (trials' PDF reports) and
:mod:`app.reports.trend_cache` (patients' trend plots). A file is named
``<patient id>-...<suffix>`` after its content's key, so that a stale file is
never found and a patient's files can be removed at once:

- **Bounded**: each kind keeps a few files per trial or patient (the least
  recently used go first) and at most ``max_bytes`` in all, both enforced at
  every write.
- **Erasure and restore**: erasing a patient removes their files
  (:meth:`PatientFileCache.forget_patient`); restoring a backup empties the cache
  (:meth:`PatientFileCache.clear`). The cache is derived data and never backed up.
- **Several processes**: a file appears complete or not at all (written to a
  temporary name, fsynced, renamed); a file removed by another process
  meanwhile is a miss, not an error.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import ClassVar

_KEY = re.compile(r"^[0-9a-f]{64}$")
_STALE_PART_S = 3600.0  # a temporary file this old was left by a crashed process


class PatientFileCache:
    """Files kept in ``directory`` (created on the first write), at most ``max_bytes``."""

    suffix: ClassVar[str] = ""
    """The kept files' suffix (``.pdf``, ``.svg``)."""

    def __init__(self, directory: Path | str, *, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.directory = Path(directory)
        self.max_bytes = int(max_bytes)

    @staticmethod
    def check_id(name: str, value: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
        return value

    @staticmethod
    def check_key(key: str) -> str:
        if not isinstance(key, str) or not _KEY.match(key):
            raise ValueError(f"key must be a SHA-256 in lower-case hex, got {key!r}")
        return key

    def read(self, path: Path) -> bytes | None:
        """The file's bytes, or None; a file found counts as just used (kept longest)."""
        try:
            body = path.read_bytes()
        except FileNotFoundError:
            return None
        with contextlib.suppress(FileNotFoundError):
            os.utime(path)
        return body

    def write(self, final: Path, body: bytes) -> None:
        """``body`` at ``final``, complete or not at all."""
        self.directory.mkdir(parents=True, exist_ok=True)
        # The temporary name starts like the final one, so that forget_patient finds it too.
        temp = final.with_name(f"{final.name}.{uuid.uuid4().hex}.part")
        try:
            with open(temp, "wb") as fh:
                fh.write(body)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(temp, final)
        finally:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()

    def forget_patient(self, patient_id: int) -> int:
        """Remove every file of the patient (an erasure); returns how many."""
        self.check_id("patient_id", patient_id)
        return self._remove(self.directory.glob(f"{patient_id}-*"))

    def clear(self) -> int:
        """Remove every file (a restored backup: the files are another database's)."""
        if not self.directory.is_dir():
            return 0
        return self._remove(p for p in self.directory.iterdir() if p.is_file())

    def files(self) -> list[Path]:
        """The kept files, in no particular order."""
        if not self.directory.is_dir():
            return []
        return [p for p in self.directory.glob(f"*{self.suffix}") if p.is_file()]

    # ------------------------------------------------------------------ bounds

    @staticmethod
    def _remove(paths: Iterable[Path]) -> int:
        removed = 0
        for path in paths:
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            removed += 1
        return removed

    @staticmethod
    def _mtimes(paths: list[Path]) -> list[tuple[float, int, Path]]:
        """(mtime, size, path) of each path still there."""
        out = []
        for path in paths:
            try:
                stat = path.stat()
            except FileNotFoundError:
                continue
            out.append((stat.st_mtime, stat.st_size, path))
        return out

    def keep_newest(self, pattern: str, keep: int) -> None:
        """Of the files matching ``pattern``, remove all but the ``keep`` most recently used."""
        kept = sorted(
            self._mtimes(list(self.directory.glob(pattern))),
            key=lambda entry: entry[0],
            reverse=True,
        )
        self._remove(path for _, _, path in kept[keep:])

    def trim(self) -> None:
        """Remove temporary files left by crashed writers, then, past ``max_bytes``, the
        least recently used files."""
        now = time.time()
        parts = self._mtimes(list(self.directory.glob("*.part")))
        self._remove(path for mtime, _, path in parts if now - mtime > _STALE_PART_S)
        entries = sorted(self._mtimes(self.files()), key=lambda entry: entry[0])
        total = sum(size for _, size, _ in entries)
        doomed = []
        for _, size, path in entries:
            if total <= self.max_bytes:
                break
            doomed.append(path)
            total -= size
        self._remove(doomed)


__all__ = ["PatientFileCache"]
