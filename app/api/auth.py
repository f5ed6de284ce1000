"""``/auth``: browser login/logout for the pages' JavaScript, and who-am-I for any caller."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Request, Response, status
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool

from app.api.responses import AUTH, errors
from app.auth import CurrentActor, CurrentUser, SessionDep
from app.login import login_from_request, logout_from_request
from app.schemas import LoginRequest, LoginResponse

router = APIRouter(prefix="/auth", tags=["auth"])


class WhoAmI(BaseModel):
    type: Literal["api_client", "user"]
    id: int
    name: str
    scopes: list[str]
    role: str | None


@router.post(
    "/login",
    response_model=LoginResponse,
    responses=errors(401, 422, 429, 400, 413),
    summary="Log a browser in (sets the HttpOnly session cookie)",
)
async def login(
    data: LoginRequest, request: Request, response: Response, db: SessionDep
) -> LoginResponse:
    result = await run_in_threadpool(
        login_from_request, db, request, response, email=data.email, password=data.password
    )
    return LoginResponse(
        user_id=result.user.id,
        email=result.user.email,
        role=result.user.role,
        csrf_token=result.csrf_token,
    )


@router.post(
    "/logout",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=errors(*AUTH),
    summary="End the browser session (needs the X-CSRF-Token header)",
)
def logout(request: Request, user: CurrentUser, db: SessionDep) -> Response:
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    logout_from_request(db, request, response)
    return response


@router.get("/me", response_model=WhoAmI, responses=errors(*AUTH), summary="Who is calling")
def whoami(actor: CurrentActor) -> WhoAmI:
    return WhoAmI(
        type=actor.type, id=actor.id, name=actor.name, scopes=sorted(actor.scopes), role=actor.role
    )
