"""POST/DELETE /api/v1/session: a browser exchanges the token for a session cookie.

A page in an iframe (BlueOS, Cockpit) cannot attach a bearer header to its requests; it signs in
once with the token and then sends the HttpOnly, SameSite=Strict cookie plus the CSRF token this
call returns (``X-CSRF-Token``) with every state change. See :mod:`uwcam.api.security`.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.security import SESSION_COOKIE, Guard

router = APIRouter(prefix="/api/v1/session", tags=["session"])


class SignIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    token: str = Field(max_length=4096)


@router.get("")
def session_state(request: Request) -> dict:
    """Whether state changes need signing in, and whether this browser is signed in."""
    guard: Guard = request.app.state.guard
    session = request.cookies.get(SESSION_COOKIE)
    return {"token_required": guard.token is not None,
            "signed_in": guard.token is None or (session is not None and guard.sessions.csrf_for(session) is not None)}


@router.post("")
def sign_in(body: SignIn, request: Request, response: Response) -> dict:
    """Exchange the token for a session cookie; returns the CSRF token to send as X-CSRF-Token."""
    guard: Guard = request.app.state.guard
    if not guard.check_token(body.token):
        raise HTTPException(status_code=401, detail="wrong token")
    session, csrf = guard.sessions.open()
    response.set_cookie(SESSION_COOKIE, session, httponly=True, samesite="strict", path="/",
                        secure=request.url.scheme == "https")
    return {"csrf_token": csrf, "token_required": guard.token is not None}


@router.delete("")
def sign_out(request: Request, response: Response) -> dict:
    guard: Guard = request.app.state.guard
    session = request.cookies.get(SESSION_COOKIE)
    if session:
        guard.sessions.close(session)
    response.delete_cookie(SESSION_COOKIE, path="/")
    return {"signed_in": False}
