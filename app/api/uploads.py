"""The API's uploads: their OpenAPI description, and the route side of :func:`app.uploads.run_upload`."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from fastapi import Request
from starlette.concurrency import run_in_threadpool

from app.uploads import ParsedUpload, run_upload

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
                    "schema": {
                        "type": "object",
                        "properties": properties,
                        "required": required,
                        "additionalProperties": False,  # another field is refused (422)
                    }
                }
            },
        }
    }


BINARY = {"type": "string", "format": "binary"}


async def run_api_upload(
    request: Request,
    *,
    file_fields: Mapping[str, str],
    text_fields: frozenset[str],
    check: Callable[[], object],
    use_case: Callable[[ParsedUpload], T],
    on_rejected: Callable[[BaseException], None] | None = None,
) -> T:
    """Run ``check()`` (e.g. the target exists: a 404 before the body is read), then the
    upload (:func:`app.uploads.run_upload`); errors go to the app's exception handler,
    after ``on_rejected(exc)`` audited a refused upload."""
    await run_in_threadpool(check)
    return await run_upload(
        request,
        storage=request.app.state.storage,
        max_file_bytes=int(request.app.state.settings.max_upload_bytes),
        file_fields=file_fields,
        text_fields=text_fields,
        use_case=use_case,
        on_rejected=on_rejected,
    )
