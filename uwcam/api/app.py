"""The application factory: assembles one router per resource and the services they share.

The API reads the frame loop's published state and never blocks it: the loop calls back with
each published frame, the callback only records "newest" and sets an asyncio event thread-safely,
and every WebSocket client sends the newest frame when it can. Authorisation of every route is
declared once, in :mod:`uwcam.api.security`.
"""

from __future__ import annotations

import asyncio
import logging
import math
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from uwcam import __version__
from uwcam.api import lamp, metrics, profiles, session, settings, snapshots, status, stream
from uwcam.api.common import Broadcaster
from uwcam.api.security import Guard, required_token
from uwcam.config import DaemonConfig
from uwcam.daemon import Daemon
from uwcam.fileio import UserInputError

ROUTERS = (status.router, snapshots.router, settings.router, profiles.router, lamp.router, session.router,
           stream.router, metrics.router)


def json_safe(value: Any) -> Any:
    """``value`` with every NaN or infinity replaced by its name: an error message quoting a
    user's ``NaN`` must still be valid JSON (strict JSON has no such numbers)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def create_app(config: DaemonConfig, daemon: Daemon | None = None) -> FastAPI:
    guard = Guard(required_token(config), tuple(config.api.allowed_hosts))

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        d = daemon or Daemon(config)
        await asyncio.to_thread(d.start)
        app.state.daemon = d
        app.state.broadcaster = Broadcaster(asyncio.get_running_loop())
        d.pipeline.subscribe(app.state.broadcaster.publish)
        try:
            yield
        finally:
            d.pipeline.unsubscribe(app.state.broadcaster.publish)
            await asyncio.to_thread(d.stop)

    app = FastAPI(title="uwcam", version=__version__, lifespan=lifespan, dependencies=[Depends(guard)],
                  description="Underwater ranging camera: range maps from colour attenuation, live.")
    app.state.config = config
    app.state.guard = guard

    @app.exception_handler(UserInputError)
    async def _user_error(request: Request, exc: UserInputError):
        return JSONResponse(status_code=400, content={"error": str(exc)})

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError):
        return JSONResponse(status_code=422, content={"detail": json_safe(jsonable_encoder(exc.errors()))})

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException):
        exc.detail = json_safe(exc.detail)
        return await http_exception_handler(request, exc)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        # A clear JSON message, never a stack trace; the trace goes to the daemon's log.
        logging.getLogger("uwcam.api").exception("unexpected error in %s %s", request.method, request.url.path)
        return JSONResponse(status_code=500, content={"error": f"internal error ({type(exc).__name__}); see the daemon log"})

    for router in ROUTERS:
        app.include_router(router)
    return app
