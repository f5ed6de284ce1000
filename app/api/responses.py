"""What the routes share: documented error answers (OpenAPI ``responses=``), path
and paging parameters, and building a :class:`~app.schemas.Page`."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated, Any, TypeVar

from fastapi import Query, Request
from fastapi.responses import Response
from pydantic import BaseModel

from app.schemas import ErrorResponse, Page
from app.schemas import IdPath as IdPath  # the API's routes import it from here

S = TypeVar("S", bound=BaseModel)

_TEXT = {
    400: "The request body is malformed.",
    401: "No valid API key or browser session.",
    403: "The key lacks the scope, or the browser request lacks its CSRF token.",
    404: "No such resource (or it was deleted).",
    409: "Conflicts with the current state (duplicate, or not ready yet).",
    413: "An uploaded file, or a JSON body above 1 MiB, is larger than the limit.",
    415: "The upload is not multipart/form-data, or a file is not a readable video.",
    422: "The request is well-formed but its content is invalid.",
    429: "Too many attempts; wait and retry.",
    503: "The database is not reachable, or the server's storage refuses writes; retry later.",
    507: "The server's storage is full; nothing was saved.",
}


def errors(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries for the given error statuses, all ``ErrorResponse``."""
    return {s: {"model": ErrorResponse, "description": _TEXT[s]} for s in statuses}


def json_errors(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """Like :func:`errors`, for routes whose success is not JSON (HTML, PDF, CSV, FHIR).

    FastAPI would document a ``model`` in the route's own media type; errors
    are always ``application/json``, so the content is spelled out.
    """
    schema = {"$ref": "#/components/schemas/ErrorResponse"}
    return {
        s: {"description": _TEXT[s], "content": {"application/json": {"schema": schema}}}
        for s in statuses
    }


# Every authenticated route can answer these.
AUTH = (401, 403, 422)

Limit = Annotated[int, Query(ge=1, le=200, description="Items per page.")]
Offset = Annotated[int, Query(ge=0, le=10_000_000, description="Items to skip.")]


def page(schema: type[S], rows: Iterable[Any], total: int, *, limit: int, offset: int) -> Page[S]:
    """One page of ``rows`` (ORM objects), each read as ``schema``."""
    return Page[schema](  # type: ignore[valid-type]
        items=[schema.model_validate(row) for row in rows], total=total, limit=limit, offset=offset
    )


def not_modified(request: Request, etag: str) -> bool:
    """Whether the request's ``If-None-Match`` names ``etag`` (or is ``*``): the client holds
    this version, answer 304 (RFC 9110: weak comparison, ``W/`` ignored)."""
    sent = request.headers.get("if-none-match")
    if not sent:
        return False
    tags = {tag.strip().removeprefix("W/") for tag in sent.split(",")}
    return "*" in tags or etag.removeprefix("W/") in tags


def attachment(body: bytes, media_type: str, filename: str, **headers: str) -> Response:
    """``body`` as a download named ``filename`` (``Content-Disposition: attachment``)."""
    disposition = {"Content-Disposition": f'attachment; filename="{filename}"'}
    return Response(body, media_type=media_type, headers={**disposition, **headers})


def head_attachment(kept: bytes | None, media_type: str, filename: str) -> Response:
    """A HEAD's answer for a file that is made on demand: the kept file's headers, or, when it
    is not made yet, its type and name without the Content-Length that only making it could
    tell (RFC 9110 9.3.2 lets a HEAD leave out what only generating the content determines)."""
    response = attachment(b"" if kept is None else kept, media_type, filename)
    if kept is None:
        del response.headers["content-length"]
    return response


def file_responses(media_type: str, description: str) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route answering a file of ``media_type``, with its errors."""
    return {
        200: {"content": {media_type: {"schema": {"type": "string"}}}, "description": description},
        **json_errors(*AUTH, 404, 409),
    }
