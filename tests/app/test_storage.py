"""Stored files: server-generated paths, atomic publication, size limit, no leftovers."""

from __future__ import annotations

import hashlib

import pytest

from app.errors import PayloadTooLargeError
from app.storage import Storage, file_sha256


def _leftovers(storage: Storage) -> list:
    return sorted(p for p in storage.tmp_dir.rglob("*") if p.is_file())


def test_received_file_is_published_with_size_and_checksum(storage):
    chunks = [b"a" * 1000, b"b" * 24, b""]
    with storage.receive("videos", ".MP4", max_bytes=2000) as incoming:
        for chunk in chunks:
            incoming.write(chunk)
        assert incoming.temp_path.is_file() and not storage.exists(incoming.path)
        stored = incoming.commit()
    data = b"".join(chunks)
    assert stored.size_bytes == len(data)
    assert stored.sha256 == hashlib.sha256(data).hexdigest()
    assert stored.path.startswith("files/videos/") and stored.path.endswith(".mp4")
    assert storage.absolute(stored.path).read_bytes() == data
    assert file_sha256(storage.absolute(stored.path)) == stored.sha256
    assert _leftovers(storage) == []


def test_flush_makes_received_bytes_readable_before_commit(storage):
    with storage.receive("videos", ".mp4") as incoming:
        incoming.write(b"frame-bytes")
        incoming.flush()
        assert incoming.temp_path.read_bytes() == b"frame-bytes"
        assert not storage.exists(incoming.path)
        incoming.commit()
        incoming.flush()  # harmless once the file is closed
    assert _leftovers(storage) == []


def test_oversized_upload_leaves_nothing(storage):
    with pytest.raises(PayloadTooLargeError, match="larger than the limit"):
        with storage.receive("videos", ".mp4", max_bytes=100) as incoming:
            incoming.write(b"x" * 60)
            incoming.write(b"x" * 60)
    assert _leftovers(storage) == []
    assert not any(p.is_file() for p in storage.files_dir.rglob("*"))


def test_rejected_after_commit_removes_the_published_file(storage):
    with pytest.raises(RuntimeError):
        with storage.receive("videos", ".mp4") as incoming:
            incoming.write(b"data")
            stored = incoming.commit()
            raise RuntimeError("the database insert failed")
    assert not storage.exists(stored.path)
    assert _leftovers(storage) == []


def test_block_left_without_commit_discards_the_file(storage):
    with storage.receive("videos", ".mp4") as incoming:
        incoming.write(b"data")
    assert not storage.exists(incoming.path) and _leftovers(storage) == []


def test_writing_publishes_only_complete_files(storage):
    with storage.writing("results", ".csv") as (tmp, path):
        tmp.write_text("frame,time_s\n")
        assert not storage.exists(path)
    assert storage.absolute(path).read_text() == "frame,time_s\n"
    with pytest.raises(ValueError, match="boom"):
        with storage.writing("results", ".csv") as (tmp, failed_path):
            tmp.write_text("half")
            raise ValueError("boom")
    assert not storage.exists(failed_path) and _leftovers(storage) == []


def test_paths_are_unique_and_server_generated(storage):
    paths = {storage.new_path("videos", ".mp4") for _ in range(1000)}
    assert len(paths) == 1000
    for bad in ("../x", "Videos", "a/b"):
        with pytest.raises(ValueError):
            storage.new_path(bad, ".mp4")
    for bad_suffix in ("mp4", ".mp4/../../x", "./"):
        with pytest.raises(ValueError):
            storage.new_path("videos", bad_suffix)


@pytest.mark.parametrize(
    "path", ["/etc/passwd", "../outside.mp4", "files/../../outside", "bradyscope.sqlite3", ""]
)
def test_absolute_refuses_paths_outside_the_files_dir(storage, path):
    with pytest.raises(ValueError):
        storage.absolute(path)


def test_delete_is_idempotent(storage):
    stored = storage.write_bytes("rigs", ".json", b"{}")
    storage.delete(stored.path)
    storage.delete(stored.path)
    storage.delete(None)
    assert not storage.exists(stored.path)


def test_cleanup_tmp_removes_only_old_files(storage):
    import os

    old = storage.tmp_dir / "old.part"
    new = storage.tmp_dir / "new.part"
    old.write_bytes(b"x")
    new.write_bytes(b"x")
    os.utime(old, (0, 0))
    assert storage.cleanup_tmp(older_than_s=3600) == 1
    assert not old.exists() and new.exists()
    # the default: an hour unchanged (a crash loop left .part files for a day before)
    import time

    os.utime(new, (time.time() - 3700, time.time() - 3700))
    assert storage.cleanup_tmp() == 1 and not new.exists()
