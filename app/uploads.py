"""Uploads: stream multipart bodies to disk, check videos by decoding them.

An upload goes through three steps, and a rejected one leaves nothing behind:

1. :func:`receive_multipart` (run by :func:`run_upload`, the one upload
   runner of the API and the pages) streams the request body, chunk by chunk, into
   temporary files of the storage (``data_dir/tmp``, the same file system as
   the stored files, so publishing is an atomic rename), computing each file's
   SHA-256 on the fly and stopping at the size limit (HTTP 413).
2. :mod:`app.upload_checks` decides whether a file really is a usable video
   by decoding it, never by its name or declared content type, and reads
   timestamps and rig files.
3. The use case publishes the accepted files (:meth:`ParsedUpload.publish`)
   and commits the rows that reference them; if anything fails it calls
   :meth:`ParsedUpload.discard`, and :meth:`ParsedUpload.close` always.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

from app.errors import (
    AppError,
    InvalidRequestError,
    PayloadTooLargeError,
    UnsupportedMediaError,
    http_status_for,
)
from app.storage import IncomingFile, Storage, StoredFile
from core.errors import BradyscopeError

T = TypeVar("T")

MAX_FIELD_BYTES = 64 * 1024  # a plain form field (hand, board, ...), not a file
MAX_PARTS = 16
IGNORED_FIELDS = frozenset({"csrf_token"})
"""Parts read and dropped where a route does not take them: a browser's CSRF token (the
API reads it from the ``X-CSRF-Token`` header). Any other unknown part refuses the upload."""
_AUDITED_BY_USE_CASE = frozenset({401, 403, 404})
# After a body was refused for its size, keep reading (and dropping) at most
# this much so that the client can still read the 413 answer.
_DRAIN_LIMIT_BYTES = 256 * 1024 * 1024


class UploadError(AppError):
    """The uploaded body is malformed or incomplete (HTTP 400)."""

    http_status = 400


class UnsupportedUpload(UnsupportedMediaError):
    """The body is not ``multipart/form-data``, or a file is not a readable video (HTTP 415)."""

    http_status = 415


class InvalidUpload(InvalidRequestError):
    """A well-formed upload whose content is unusable: missing field, bad rig file (HTTP 422)."""


_VIDEO_SUFFIXES = frozenset({".mp4", ".mkv", ".avi", ".mov", ".m4v", ".webm"})


def stored_suffix(filename: str, *, default: str) -> str:
    """A cosmetic suffix for the stored file: the client's if it is a known video suffix.

    The suffix decides nothing (content is checked by decoding); it only makes
    the stored file easier to open by hand.
    """
    suffix = Path(filename).suffix.lower()
    return suffix if suffix in _VIDEO_SUFFIXES else default


@dataclass
class StagedFile:
    """One uploaded file, fully received (hashed, size-checked) but not yet published.

    Attributes
    ----------
    field : str
        The form field name (``left_video``, ``rig_json``, ...).
    filename : str
        The client's file name, kept for display only; it decides nothing.
    incoming : IncomingFile
        The storage's receiving file; ``incoming.temp_path`` holds the bytes
        until :meth:`publish` moves them to their server-generated path.
    """

    field: str
    filename: str
    incoming: IncomingFile

    @property
    def path(self) -> Path:
        """Where the received bytes are now (before publishing)."""
        return self.incoming.temp_path

    @property
    def size_bytes(self) -> int:
        return self.incoming.size_bytes

    def publish(self) -> StoredFile:
        """fsync and atomically move the file to its final path in storage."""
        return self.incoming.commit()


@dataclass
class ParsedUpload:
    """Form fields and received files of one multipart request."""

    storage: Storage
    fields: dict[str, str] = field(default_factory=dict)
    files: dict[str, StagedFile] = field(default_factory=dict)
    labels: dict[str, str] = field(default_factory=dict)
    """The form's own labels of its parts (a page's form): messages name them instead."""
    unknown: list[str] = field(default_factory=list)
    """Parts the route does not take (dropped unread), in the order they came."""
    accepted: frozenset[str] = frozenset()
    """The parts the route takes (files and fields)."""
    _published: list[str] = field(default_factory=list)

    def label(self, name: str) -> str:
        """How a message names the part ``name``: the form's label, else the field name."""
        return f"“{self.labels[name]}”" if name in self.labels else repr(name)

    def publish(self, name: str) -> StoredFile:
        """Publish one file; remembered so that :meth:`discard` can remove it again."""
        stored = self.files[name].publish()
        self._published.append(stored.path)
        return stored

    def discard(self) -> None:
        """Remove everything of this upload: temporary files and files already published.

        Call it when the use case fails (its transaction was rolled back).
        """
        for staged in self.files.values():
            staged.incoming.abort()
        for path in self._published:
            self.storage.delete(path)
        self._published.clear()

    def close(self) -> None:
        """Remove the temporary files that were not published (always call it at the end)."""
        for staged in self.files.values():
            staged.incoming.abort()

    def refuse_unknown_fields(self) -> None:
        """Refuse (422, naming each) parts the route does not take, as the JSON routes refuse
        fields they do not know: a misspelt ``takeid`` or ``offset_frame`` is not dropped."""
        if not self.unknown:
            return
        names = list(dict.fromkeys(self.unknown))
        raise InvalidUpload(
            f"The upload has {'a field' if len(names) == 1 else 'fields'} this route does not"
            f" take: {', '.join(repr(n) for n in names)}; remove {'it' if len(names) == 1 else 'them'}"
            f" or correct the name (the fields are {', '.join(sorted(self.accepted))}).",
            issues=[
                {
                    "loc": ["body", n],
                    "msg": "Extra inputs are not permitted",
                    "type": "extra_forbidden",
                }
                for n in names
            ],
        )

    def require_file(self, name: str) -> StagedFile:
        if name not in self.files:
            raise InvalidUpload(
                f"The upload lacks the file {self.label(name)}; attach it and retry.",
                field=name,
                kind="missing",
            )
        return self.files[name]

    def require_field(self, name: str) -> str:
        value = self.fields.get(name)
        if value is None or value.strip() == "":
            if name in self.labels:
                raise InvalidUpload(
                    f"Fill in {self.label(name)} and send the form again.",
                    field=name,
                    kind="missing",
                )
            raise InvalidUpload(
                f"The upload lacks the form field {name!r}; fill it in and retry.",
                field=name,
                kind="missing",
            )
        return value.strip()


class _Receiver:
    """python-multipart callbacks writing file parts straight into storage's temporary files."""

    def __init__(
        self,
        storage: Storage,
        *,
        file_fields: dict[str, str],
        text_fields: frozenset[str],
        max_file_bytes: int,
    ) -> None:
        self.storage = storage
        self.file_fields = file_fields
        self.text_fields = text_fields
        self.max_file_bytes = max_file_bytes
        self.result = ParsedUpload(storage, accepted=frozenset(file_fields) | text_fields)
        self._parts = 0
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._name = ""
        self._filename = ""
        self._text = bytearray()
        self._incoming: IncomingFile | None = None
        self._skip = False

    # -- python-multipart callbacks ------------------------------------
    def on_part_begin(self) -> None:
        self._parts += 1
        if self._parts > MAX_PARTS:
            raise UploadError(f"The upload has more than {MAX_PARTS} parts; send only the form.")
        self._disposition = b""
        self._name = ""
        self._filename = ""
        self._text = bytearray()
        self._incoming = None
        self._skip = False

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        if b"name" not in options:
            raise UploadError("A part of the upload has no field name; send a regular HTML form.")
        self._name = options[b"name"].decode("utf-8", "replace")
        if self._name in self.result.files or self._name in self.result.fields:
            raise UploadError(f"The field {self._name!r} appears twice in the upload.")
        self._filename = options.get(b"filename", b"").decode("utf-8", "replace")
        if self._name in self.file_fields:
            # Server-generated path: the client's file name never reaches the file system.
            suffix = stored_suffix(self._filename, default=self.file_fields[self._name])
            category = "rigs" if self._name == "rig_json" else "videos"
            self._incoming = self.storage.receive(category, suffix, max_bytes=self.max_file_bytes)
            self.result.files[self._name] = StagedFile(self._name, self._filename, self._incoming)
        elif self._name not in self.text_fields:
            self._skip = True  # read and dropped; refused after the body (all are named)
            if self._name not in IGNORED_FIELDS:
                self.result.unknown.append(self._name)

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self._skip:
            return
        chunk = data[start:end]
        if self._incoming is not None:
            try:
                self._incoming.write(chunk)
            except PayloadTooLargeError as exc:
                raise PayloadTooLargeError(f"{_label(self._name)}: {exc}") from exc
        else:
            if len(self._text) + len(chunk) > MAX_FIELD_BYTES:
                raise UploadError(f"The form field {self._name!r} is too long.")
            self._text.extend(chunk)

    def on_part_end(self) -> None:
        if self._skip:
            return
        if self._incoming is not None:
            # Complete: make the bytes readable at temp_path for the checks; the
            # use case publishes (fsync + rename) the accepted ones.
            self._incoming.flush()
            self._incoming = None
        else:
            self.result.fields[self._name] = self._text.decode("utf-8", "replace")

    def callbacks(self) -> Any:  # python_multipart.MultipartCallbacks
        return {
            "on_part_begin": self.on_part_begin,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
        }


def _label(field_name: str) -> str:
    return {
        "left_video": "the left video",
        "right_video": "the right video",
        "rig_json": "the rig file",
        "left_times": "the left timestamps file",
        "right_times": "the right timestamps file",
    }.get(field_name, f"the file {field_name!r}")


def _check_request(request: Request, *, n_files: int, n_fields: int, max_file_bytes: int) -> bytes:
    """The multipart boundary of ``request``, after its declared type and size were checked."""
    content_type = request.headers.get("content-type", "")
    ctype, params = parse_options_header(content_type)
    if ctype != b"multipart/form-data":
        raise UnsupportedUpload(
            "Send the recording as multipart/form-data (an HTML form with file fields)."
        )
    boundary = params.get(b"boundary")
    if not boundary:
        raise UploadError("The multipart upload has no boundary; send a regular HTML form.")
    declared = request.headers.get("content-length", "")
    limit_total = max_file_bytes * n_files + MAX_FIELD_BYTES * (n_fields + 4)
    if declared.isdigit() and int(declared) > limit_total:
        raise PayloadTooLargeError(
            f"The upload is larger than the limit of {max_file_bytes / 1e6:.1f} MB per file;"
            " record a shorter clip or ask the administrator to raise BRADYSCOPE_MAX_UPLOAD_BYTES."
        )
    return bytes(boundary)


UPLOAD_STALL_S = 60.0
"""An upload from which nothing arrives for this long (s) is dropped (400): a stalled
client would hold its partial file and keep the server from shutting down."""


async def receive_multipart(
    request: Request,
    *,
    storage: Storage,
    file_fields: Mapping[str, str],
    text_fields: set[str] | frozenset[str] = frozenset(),
    max_file_bytes: int,
) -> ParsedUpload:
    """Stream a ``multipart/form-data`` request body into storage's temporary files.

    Parameters
    ----------
    request : Request
        The incoming request; its body has not been read yet.
    storage : Storage
        Files are received into ``storage.tmp_dir`` (same file system as the
        stored files, so publishing is an atomic rename).
    file_fields : mapping of str to str
        Accepted file parts, each with the default suffix of its stored file
        (``{"left_video": ".video"}``). Other parts are read and dropped, and named
        in ``ParsedUpload.unknown`` (except :data:`IGNORED_FIELDS`).
    text_fields : set of str
        Accepted plain-text parts.
    max_file_bytes : int
        Size limit of each file part, in bytes.

    Returns
    -------
    ParsedUpload
        The caller owns it: :meth:`ParsedUpload.close` at the end, and
        :meth:`ParsedUpload.discard` if the use case failed.

    Raises
    ------
    UnsupportedUpload, UploadError, PayloadTooLargeError
        Nothing of the upload is left on disk when these are raised.
    """
    boundary = _check_request(
        request, n_files=len(file_fields), n_fields=len(text_fields), max_file_bytes=max_file_bytes
    )
    receiver = _Receiver(
        storage,
        file_fields=dict(file_fields),
        text_fields=frozenset(text_fields),
        max_file_bytes=max_file_bytes,
    )
    stream = request.stream()
    try:
        parser = MultipartParser(boundary, receiver.callbacks())
        while True:
            try:
                chunk = await asyncio.wait_for(anext(stream), UPLOAD_STALL_S)
            except StopAsyncIteration:
                break
            except TimeoutError as exc:
                raise UploadError(
                    f"The upload stalled: nothing arrived for {UPLOAD_STALL_S:.0f} s; check the"
                    " connection and retry."
                ) from exc
            if chunk:
                parser.write(chunk)
        parser.finalize()
        if receiver._incoming is not None or receiver._parts == 0:
            raise UploadError("The upload ended before it was complete; retry the upload.")
    except PayloadTooLargeError:
        receiver.result.discard()
        await _drain(stream)
        raise
    except ClientDisconnect as exc:
        receiver.result.discard()
        raise UploadError("The upload was interrupted before it was complete; retry.") from exc
    except MultipartParseError as exc:
        receiver.result.discard()
        raise UploadError(f"The multipart upload is malformed ({exc}); retry the upload.") from exc
    except BaseException:
        receiver.result.discard()
        raise
    return receiver.result


async def run_upload(
    request: Request,
    *,
    storage: Storage,
    max_file_bytes: int,
    file_fields: Mapping[str, str],
    text_fields: frozenset[str],
    use_case: Callable[[ParsedUpload], T],
    accept: Callable[[ParsedUpload], None] | None = None,
    on_rejected: Callable[[BaseException], None] | None = None,
) -> T:
    """The one way an upload is run, for the API and the pages alike.

    Streams the body into storage (:func:`receive_multipart`), lets
    ``accept(upload)`` check or adjust the received form (e.g. its CSRF
    token), refuses parts the route does not take
    (:meth:`ParsedUpload.refuse_unknown_fields`), then runs ``use_case(upload)`` in
    the thread pool (it publishes the files and commits their rows). Whatever fails, every file of the upload is
    removed again; the temporary files are always cleaned up.

    ``on_rejected(exc)`` (run in the thread pool) records an upload refused for
    its content (a malformed body, too large, not a video, an invalid form...);
    refusals the use case has audited itself (401, 403, 404, and an error raised
    with ``audited=True``) do not reach it.

    Raises
    ------
    AppError, core.errors.BradyscopeError
        From receiving, ``accept`` or the use case; the caller answers them.
    """
    try:
        upload = await receive_multipart(
            request,
            storage=storage,
            file_fields=file_fields,
            text_fields=text_fields,
            max_file_bytes=max_file_bytes,
        )
        try:
            if accept is not None:
                accept(upload)
            upload.refuse_unknown_fields()
            return await run_in_threadpool(use_case, upload)
        except BaseException:
            upload.discard()
            raise
        finally:
            upload.close()
    except (AppError, BradyscopeError) as exc:
        audited = getattr(exc, "audited", False)
        if (
            on_rejected is not None
            and not audited
            and http_status_for(exc) not in _AUDITED_BY_USE_CASE
        ):
            await run_in_threadpool(on_rejected, exc)
        raise


async def _drain(stream: Any) -> None:
    """Read and drop the rest of a refused body (bounded) so the client sees the answer."""
    dropped = 0
    try:
        async for chunk in stream:
            dropped += len(chunk)
            if dropped > _DRAIN_LIMIT_BYTES:
                break
    except (ClientDisconnect, RuntimeError):
        pass  # the client went away or the stream was already consumed: nothing to drain
