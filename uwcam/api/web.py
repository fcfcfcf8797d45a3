"""The operator page, the Cockpit widget, offline API docs and BlueOS service discovery.

Everything ships inside the package (uwcam/web/, the Swagger UI assets of fastapi-offline):
no CDN, no build step. Every URL the pages use is relative, so they work unchanged behind a
reverse proxy that serves uwcam under a path prefix, as BlueOS does (``/extensionv2/<name>/``).
"""

from __future__ import annotations

from importlib import resources

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


@router.get("/register_service")
def register_service(request: Request) -> JSONResponse:
    """Service metadata that BlueOS reads to list uwcam in its menu (paths relative to uwcam's root)."""
    return JSONResponse({
        "name": "uwcam",
        "description": "Range from colour: a per-pixel range map, its uncertainty and live camera health",
        "icon": "mdi-camera-metering-spot",
        "company": "uwcam",
        "version": __version__,
        "webpage": "https://pypi.org/project/uwcam/",
        "api": "docs",
        "route": "",
        "new_page": False,
        "works_in_relative_paths": True,
        "extras": {"cockpit": "cockpit_extras.json"},
    })


@router.get("/cockpit_extras.json")
def cockpit_extras() -> JSONResponse:
    """Cockpit extras: the compact range widget (an iframe) and lamp actions."""
    def lamp_action(name: str, on: bool) -> dict:
        return {"id": f"uwcam-lamp-{'on' if on else 'off'}", "name": name, "type": "http-request",
                "config": {"name": name, "url": "api/v1/lamp", "method": "PUT",
                           "headers": {"Content-Type": "application/json"}, "urlParams": {},
                           "body": f'{{"on": {"true" if on else "false"}}}'}}

    return JSONResponse({
        "target_system": "Cockpit",
        "target_cockpit_api_version": "1.0.0",
        "widgets": [{"name": "uwcam range", "config_iframe_url": None, "iframe_url": "widget",
                     "iframe_icon": "static/favicon.svg", "version": __version__}],
        "actions": [lamp_action("uwcam lamp on", True), lamp_action("uwcam lamp off", False)],
    })
