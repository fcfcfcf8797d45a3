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
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from uwcam import __version__
from uwcam.api import (alerts, backscatter, calibration_session, lamp, metrics, profiles, recordings, session,
                       settings, simulation, snapshots, status, stream, view, web)
from uwcam.api.backpressure import ConnectionSocket
from uwcam.api.common import Broadcaster
from uwcam.api.limits import BodyLimit
from uwcam.api.security import SAFE_METHODS, SESSION_COOKIE, SESSION_PATH, Guard, required_token
from uwcam.api.view import ViewEncoder
from uwcam.config import DaemonConfig
from uwcam.runtime.daemon import Daemon
from uwcam.fileio import UserInputError

def openapi_with_bearer(app: FastAPI) -> dict:
    """The OpenAPI document, declaring the bearer token on every state-changing operation so that
    the Swagger UI at /docs offers to authorise (the guard, not this, enforces it)."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes,
                             servers=app.servers)
        schema.setdefault("components", {})["securitySchemes"] = {
            "bearer": {"type": "http", "scheme": "bearer",
                       "description": "api.token or UWCAM_TOKEN; needed for state changes when one is set"}}
        for path in schema["paths"].values():
            for method, operation in path.items():
                if method.upper() not in SAFE_METHODS and path is not schema["paths"].get(SESSION_PATH):
                    operation["security"] = [{"bearer": []}]
        app.openapi_schema = schema
    return app.openapi_schema


ROUTERS = (status.router, alerts.router, snapshots.router, settings.router, profiles.router, lamp.router, backscatter.router, session.router,
           stream.router, view.router, metrics.router, recordings.router, calibration_session.router, simulation.router, web.router)


def json_safe(value: Any) -> Any:
    """``value`` as something strict JSON in UTF-8 can always hold: an error message quotes the
    user's input, and that input may hold NaN or infinity (no such numbers in strict JSON), lone
    surrogates from ``"\\ud800"`` escapes (no UTF-8 for them: written as ``\\ud800``), or objects
    JSON has no form for (written as their ``repr``)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, dict):
        return {json_safe(str(k)): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if value is None or isinstance(value, (int, bool)):
        return value
    if isinstance(value, bytes):
        return value.decode("utf-8", "backslashreplace")
    return json_safe(str(value) if isinstance(value, BaseException) else repr(value))


def create_app(config: DaemonConfig, daemon: Daemon | None = None) -> FastAPI:
    guard = Guard(required_token(config), tuple(config.api.allowed_hosts), tuple(config.api.allowed_origins),
                  cookie=f"{SESSION_COOKIE}_{config.api.port}")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        d = daemon or Daemon(config)
        if d.pipeline is None:  # `uwcam run` starts its daemon before serving, to report errors plainly
            await asyncio.to_thread(d.start)
        app.state.daemon = d
        app.state.broadcaster = Broadcaster(asyncio.get_running_loop())
        app.state.view_encoder = ViewEncoder()
        d.pipeline.subscribe(app.state.broadcaster.publish)
        app.state.metrics = metrics.Metrics(d, app.state)
        try:
            yield
        finally:
            app.state.metrics.close()
            d.pipeline.unsubscribe(app.state.broadcaster.publish)
            await asyncio.to_thread(d.stop)

    # docs_url=None: /docs is served from the package's own Swagger UI copy (uwcam.api.web), and
    # "." as the server makes "Try it out" work under a reverse proxy's path prefix.
    app = FastAPI(title="uwcam", version=__version__, lifespan=lifespan, dependencies=[Depends(guard)],
                  docs_url=None, redoc_url=None, servers=[{"url": "."}],
                  description="Underwater ranging camera: range maps from colour attenuation, live.")
    app.state.config = config
    app.state.guard = guard

    app.add_middleware(BodyLimit, limits={profiles.router.prefix + "/": (profiles.MAX_PROFILE_BYTES, profiles.TOO_LARGE_HINT)})
    app.add_middleware(ConnectionSocket)  # outermost: it must see the server's own send

    @app.exception_handler(UserInputError)
    async def _user_error(request: Request, exc: UserInputError):
        return JSONResponse(status_code=400, content={"error": json_safe(str(exc))})

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError):
        # The errors quote the input, which may hold what JSON cannot: see json_safe.
        return JSONResponse(status_code=422, content={"detail": json_safe(exc.errors())})

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
    if config.api.allowed_origins:
        # Pages of these origins (e.g. Cockpit on another port) may call the API from the browser;
        # the guard admits their state changes. No other origin gets CORS headers.
        app.add_middleware(CORSMiddleware, allow_origins=list(config.api.allowed_origins), allow_credentials=True,
                           allow_methods=["GET", "PUT", "PATCH", "POST", "DELETE"],
                           allow_headers=["Content-Type", "Authorization", "X-CSRF-Token"])
    app.openapi = lambda: openapi_with_bearer(app)
    app.mount("/static/docs", StaticFiles(packages=[("fastapi_offline", "static")]), name="docs-assets")
    app.mount("/static", StaticFiles(packages=[("uwcam", "web")]), name="static")
    return app

