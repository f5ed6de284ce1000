"""Running a streamed-upload use case from an async route."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from fastapi import Request
from starlette.concurrency import run_in_threadpool

from app.uploads import receive_multipart

T = TypeVar("T")


def multipart_body(
    properties: dict[str, dict[str, Any]], required: list[str], description: str
) -> dict[str, Any]:
    """``openapi_extra`` documenting a multipart body that the route parses itself."""
    return {
        "requestBody": {
            "required": True,
            "description": description,
            "content": {
                "multipart/form-data": {
                    "schema": {"type": "object", "properties": properties, "required": required}
                }
            },
        }
    }


BINARY = {"type": "string", "format": "binary"}


async def run_upload(
    request: Request,
    *,
    file_fields: dict[str, str],
    text_fields: frozenset[str],
    check: Callable[[], Any],
    use_case: Callable[..., T],
) -> T:
    """Run ``check()`` (e.g. the target exists: a 404 before the body is read), stream the
    body into storage, run ``use_case(upload)`` in the thread pool, clean up."""
    await run_in_threadpool(check)
    settings = request.app.state.settings
    upload = await receive_multipart(
        request,
        storage=request.app.state.storage,
        file_fields=file_fields,
        text_fields=text_fields,
        max_file_bytes=int(settings.max_upload_bytes),
    )
    try:
        return await run_in_threadpool(use_case, upload)
    except BaseException:
        upload.discard()
        raise
    finally:
        upload.close()
