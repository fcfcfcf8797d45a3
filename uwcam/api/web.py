"""The operator page, the Cockpit widget, offline API docs and BlueOS service discovery.

Everything ships inside the package (uwcam/web/, the Swagger UI assets of fastapi-offline):
no CDN, no build step. Every URL the pages use is relative, so they work unchanged behind a
reverse proxy that serves uwcam under a path prefix, as BlueOS does (``/extensionv2/<name>/``).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from importlib import resources
from urllib.parse import urlsplit

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse

from uwcam import __version__

router = APIRouter(tags=["page"])
WEB = resources.files("uwcam") / "web"


FRAME_ANCESTORS = "'self' http://localhost:* http://127.0.0.1:* http://*.local http://*.local:*"
"""Who may show uwcam's pages in a frame: BlueOS and Cockpit on the vehicle (mDNS names) or on
this computer, plus ``api.allowed_origins``; any other site framing them could trick clicks."""


def _page(name: str, request: Request) -> HTMLResponse:
    ancestors = " ".join([FRAME_ANCESTORS, *request.app.state.config.api.allowed_origins])
    policy = ("default-src 'self'; img-src 'self' blob: data:; style-src 'self' 'unsafe-inline'; "
              f"connect-src 'self' ws: wss:; frame-ancestors {ancestors}")
    # No caching of the HTML: a new uwcam version must not run against an old page.
    return HTMLResponse((WEB / name).read_text(encoding="utf-8"),
                        headers={"Cache-Control": "no-cache", "Content-Security-Policy": policy})


@router.get("/", include_in_schema=False)
def index(request: Request) -> HTMLResponse:
    """The operator page."""
    return _page("index.html", request)


@router.get("/widget", include_in_schema=False)
def widget(request: Request) -> HTMLResponse:
    """A compact range view for Cockpit: centre and minimum range, a false-colour strip."""
    return _page("widget.html", request)


@router.get("/docs", include_in_schema=False)
def docs() -> HTMLResponse:
    """Swagger UI from the package's own copy of its assets (works offline and under a prefix)."""
    return get_swagger_ui_html(openapi_url="openapi.json", title="uwcam API",
                               swagger_js_url="static/docs/swagger-ui-bundle.js",
                               swagger_css_url="static/docs/swagger-ui.css",
                               swagger_favicon_url="static/favicon.svg")


SERVICE_NAME = "uwcam"
DOCS_URL = "https://github.com/uwcam/uwcam/blob/main/docs/blueos.md"
"""The daemon's own documentation (its BlueOS page), which BlueOS links as the service's webpage."""

BLUEOS_EXTENSION_ROUTE = "/extensionv2/"
"""Where BlueOS's nginx serves an extension that works in relative paths (BlueOS
core/services/helper/main.py, ``setup_nginx_route``: ``location /extensionv2/{name}/``)."""

_PREFIX = re.compile(r"^(/[A-Za-z0-9._~-]+)*/?$")


def blueos_sanitized_name(name: str) -> str:
    """BlueOS's ``sanitized_name`` of a service (core/services/helper/main.py): lower case, only a-z and 0-9."""
    return re.sub(r"[^a-z0-9]", "", name.lower())


def public_base_url(headers: Mapping[str, str], scheme: str, name: str = SERVICE_NAME) -> str:
    """The absolute URL of uwcam's root as the browser that sent ``headers`` reaches it, without a
    trailing slash.

    Cockpit uses an extension's action URLs and (unless told otherwise) widget URLs as given, so
    they must be absolute. Reached directly, that is the request's own scheme and Host. Behind a
    proxy (``X-Forwarded-For`` or ``X-Forwarded-Proto`` present), the scheme is the proxy's, the
    port is ``X-Forwarded-Port`` when Host names none (BlueOS's nginx passes ``Host $host``,
    without a port), and the path prefix is ``X-Forwarded-Prefix`` or, when the proxy sends none,
    BlueOS's ``/extensionv2/<sanitized name>``.
    """
    proxied = "x-forwarded-for" in headers or "x-forwarded-proto" in headers
    proto = headers.get("x-forwarded-proto", "").split(",")[0].strip().lower() if proxied else ""
    proto = proto if proto in ("http", "https") else scheme
    host = headers.get("host", "") or "localhost"
    parts = urlsplit(f"//{host}")
    try:
        port = parts.port
    except ValueError:
        port = None
    forwarded_port = headers.get("x-forwarded-port", "").strip()
    if proxied and port is None and forwarded_port.isdigit() and int(forwarded_port) != {"http": 80, "https": 443}[proto]:
        host = f"{host}:{int(forwarded_port)}"
    prefix = ""
    if proxied:
        given = headers.get("x-forwarded-prefix", "").strip()
        prefix = given if given and _PREFIX.match(given) else BLUEOS_EXTENSION_ROUTE + blueos_sanitized_name(name)
    return f"{proto}://{host}{prefix.rstrip('/')}"


@router.get("/register_service")
def register_service(request: Request) -> JSONResponse:
    """Service metadata that BlueOS reads to list uwcam in its menu and that Cockpit reads to find
    its extras. Cockpit joins the extras path to the extension's URL with no slash between them
    (cockpit src/libs/blueos.ts: ``baseUrl + service.metadata.extras.cockpit``), so it starts with one."""
    return JSONResponse({
        "name": SERVICE_NAME,
        "description": "Range from colour: a per-pixel range map, its uncertainty and live camera health",
        "icon": "mdi-camera-metering-spot",
        "company": "uwcam",
        "version": __version__,
        "webpage": DOCS_URL,
        "api": "docs",
        "route": "",
        "new_page": False,
        "works_in_relative_paths": True,
        "extras": {"cockpit": "/cockpit_extras.json"},
    })


@router.get("/cockpit_extras.json")
def cockpit_extras(request: Request) -> JSONResponse:
    """Cockpit extras: the compact range widget (an iframe) and lamp actions.

    In Cockpit's own schema (src/libs/blueos/schemas.ts, ``ExtrasJsonSchema``): camelCase keys,
    which Cockpit no longer converts from snake_case. Every URL is absolute, built from how the
    request reached uwcam (:func:`public_base_url`): Cockpit uses action URLs as given (``new
    URL(url)``) and widget URLs as given when ``useExtensionPathAsBaseUrl`` is false. The actions
    carry the API token only when ``api.cockpit_actions_token`` is set, since anyone who can reach
    the daemon can read this document."""
    base = public_base_url(request.headers, request.url.scheme)
    token = request.app.state.guard.token
    headers = {"Content-Type": "application/json"}
    if token is not None and request.app.state.config.api.cockpit_actions_token:
        headers["Authorization"] = f"Bearer {token}"

    def lamp_action(name: str, on: bool) -> dict:
        return {"id": f"uwcam-lamp-{'on' if on else 'off'}", "name": name, "type": "http-request",
                "version": __version__,
                "config": {"name": name, "url": f"{base}/api/v1/lamp", "method": "PUT", "headers": headers,
                           "urlParams": {}, "body": json.dumps({"on": on})}}

    icon = f"{base}/static/favicon.svg"
    return JSONResponse({
        "targetSystem": "Cockpit",
        "targetCockpitApiVersion": "1.0.0",
        # iconUrl for Cockpit since March 2026, iframeIcon for the versions before it.
        "widgets": [{"name": "uwcam range", "iframeUrl": f"{base}/widget", "iconUrl": icon, "iframeIcon": icon,
                     "useExtensionPathAsBaseUrl": False, "version": __version__}],
        "actions": [lamp_action("uwcam lamp on", True), lamp_action("uwcam lamp off", False)],
    }, headers={"Cache-Control": "no-store"})
