"""POST/DELETE /api/v1/session: a browser exchanges the token for a session cookie.

A page in an iframe (BlueOS, Cockpit) cannot attach a bearer header to its requests; it signs in
once with the token and then sends the HttpOnly, SameSite=Strict cookie plus the CSRF token this
call returns (``X-CSRF-Token``) with every state change. See :mod:`uwcam.api.security`.
"""

from __future__ import annotations

import math

from fastapi import APIRouter, HTTPException, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.security import SESSION_PATH, Guard

router = APIRouter(prefix=SESSION_PATH, tags=["session"])
# The cookie lasts as long as a session may (Sessions' lifetime, 7 days); the daemon itself ends a
# session after 12 h without use. A cookie of 12 h from sign-in would end a session in use.
COOKIE_MAX_AGE_S = 7 * 24 * 3600


class SignIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    token: str = Field(max_length=4096)


@router.get("")
def session_state(request: Request) -> dict:
    """Whether state changes need signing in, and whether this browser is signed in; a signed-in
    browser gets its CSRF token again (a second tab has none of its own). Pages of other origins
    cannot read this answer: uwcam sends no CORS headers for it."""
    guard: Guard = request.app.state.guard
    session = request.cookies.get(guard.cookie)
    csrf = guard.sessions.csrf_for(session) if session else None
    return {"token_required": guard.token is not None, "signed_in": guard.token is None or csrf is not None,
            "csrf_token": csrf}


@router.post("")
async def sign_in(body: SignIn, request: Request, response: Response) -> dict:
    """Exchange the token for a session cookie; returns the CSRF token to send as X-CSRF-Token.

    The token is checked first (in constant time), so a right token is accepted at once, whatever
    wrong tokens came before it from the same address. After a wrong token an address must wait
    before its next one is answered 401: a wrong token that comes earlier is answered 429 (with the
    seconds left) and does not lengthen the wait. Runs on the event loop (checking a token takes
    microseconds): no attempt, right or wrong, holds a worker thread or waits for another.

    The wait does not limit how fast tokens can be guessed (a bearer header on any state change is
    checked at once too): that rests on the token being long and random, see docs/api.md."""
    guard: Guard = request.app.state.guard
    address = request.client.host if request.client else ""
    if guard.check_token(body.token):
        guard.throttle.record(True, address)
    else:
        wait = guard.throttle.wait_s(address)
        if wait > 0:
            raise HTTPException(status_code=429, headers={"Retry-After": str(math.ceil(wait))},
                                detail=f"too many wrong tokens from {address}: try again in {wait:.1f} s")
        guard.throttle.record(False, address)
        raise HTTPException(status_code=401, detail="wrong token")
    session, csrf = guard.sessions.open()
    response.set_cookie(guard.cookie, session, httponly=True, samesite="strict", path="/", max_age=COOKIE_MAX_AGE_S,
                        secure=request.url.scheme == "https")
    return {"csrf_token": csrf, "token_required": guard.token is not None}


@router.delete("")
def sign_out(request: Request, response: Response) -> dict:
    """End this browser's session (its cookie no longer signs in)."""
    guard: Guard = request.app.state.guard
    session = request.cookies.get(guard.cookie)
    if session:
        guard.sessions.close(session)
    response.delete_cookie(guard.cookie, path="/")
    return {"signed_in": False}
