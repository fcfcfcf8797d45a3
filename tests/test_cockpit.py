"""uwcam as Cockpit finds it through BlueOS, judged by Cockpit's own rules.

Cockpit's discovery of external widgets and actions, ported line by line from its source so that
uwcam is checked against what Cockpit does rather than against uwcam's idea of it:

* bluerobotics/cockpit, commit aa40c07ce72f4499bc63988503f4467ebafe35ac (2026-07-10):
  - src/libs/blueos.ts: ``blueOsServiceUrl`` (the extension's base URL), ``getExtrasJsonFromBlueOsService``
    (``baseUrl + service.metadata.extras.cockpit``: no slash added), ``getWidgetsFromBlueOS``
    (``iframeUrl`` used as given unless ``useExtensionPathAsBaseUrl``, then the base URL's path
    is prepended; the icon is ``iconUrl ?? iframeIcon``, prefixed by the whole base URL then);
  - src/libs/blueos/schemas.ts: ``ServiceSchema`` (keys camelCased first) and ``ExtrasJsonSchema``
    (keys taken as they are: commit 31b62fd20, 2026-04-15, "Remove preprocessCamelCase from
    ExtrasJsonSchema");
  - src/libs/actions/http-request.ts: ``getHttpRequestActionCallback`` (``new URL(action.url)``,
    which throws on a relative URL; ``urlParams`` merged into the query; headers sent as given).
* bluerobotics/BlueOS, commit 8e16119ea52340fd9dbb596fbc0f7a49090871d3: core/services/helper/main.py
  (the helper reads ``/register_service`` from 127.0.0.1:<port>, ``sanitized_name``, the nginx
  route that tests/blueos_proxy.py reproduces).
"""

from __future__ import annotations

import json
import re
from urllib.parse import urlencode, urljoin, urlsplit, urlunsplit

import httpx
import pytest

from tests.blueos_proxy import blueos_nginx
from tests.served import Server
from tests.test_api import small_config
from tests.waiting import wait_for
from uwcam.api.web import public_base_url

pytestmark = pytest.mark.slow
HTTP_METHODS = {"GET", "POST", "PUT", "DELETE", "PATCH"}  # cockpit src/types/cockpit-actions.ts HttpRequestMethod
ACTION_TYPES = {"http-request", "mavlink-message", "javascript"}  # customActionTypes


# --- Cockpit's rules, ported ------------------------------------------------------------------

def camelcase_keys(value):
    """npm camelcase-keys with ``deep: true``, as ServiceSchema's preprocessing applies it."""
    if isinstance(value, dict):
        return {re.sub(r"[_\-\s]+(.)", lambda m: m.group(1).upper(), k): camelcase_keys(v) for k, v in value.items()}
    if isinstance(value, list):
        return [camelcase_keys(v) for v in value]
    return value


def blueos_service_url(protocol: str, vehicle_address: str, service: dict) -> str:
    """blueos.ts ``blueOsServiceUrl``."""
    metadata = service.get("metadata") or {}
    if metadata.get("worksInRelativePaths"):
        return f"{protocol}//{vehicle_address}/extensionv2/{metadata.get('sanitizedName')}"
    return f"{protocol}//{vehicle_address}:{service.get('port')}"


class Rejected(Exception):
    """What zod's ``parse`` throws: Cockpit then skips the extension's widgets and actions."""


def _need(ok: bool, what: str) -> None:
    if not ok:
        raise Rejected(what)


def _optional(data: dict, key: str, kind) -> None:
    _need(key not in data or isinstance(data[key], kind), f"{key} must be {kind}")


def parse_extras(raw) -> dict:
    """schemas.ts ``ExtrasJsonSchema.parse`` (zod objects drop keys they do not know)."""
    _need(isinstance(raw, dict), "not an object")
    _need(isinstance(raw.get("targetCockpitApiVersion"), str), "targetCockpitApiVersion: string required")
    _need(isinstance(raw.get("targetSystem"), str), "targetSystem: string required")
    widgets = raw.get("widgets", [])
    actions = raw.get("actions", [])
    _need(isinstance(widgets, list) and isinstance(actions, list), "widgets and actions are arrays")
    for w in widgets:
        _need(isinstance(w, dict) and isinstance(w.get("name"), str) and isinstance(w.get("iframeUrl"), str),
              "widget: name and iframeUrl strings required")
        for key in ("iconUrl", "iframeIcon", "collapsibleContainerName", "version"):
            _optional(w, key, str)
        for key in ("startCollapsed", "useExtensionPathAsBaseUrl", "scaleContentWithWidget"):
            _optional(w, key, bool)
        _need("iconUrl" in w or "iframeIcon" in w, "Either iconUrl or iframeIcon must be provided")
    for a in actions:
        _need(isinstance(a, dict) and isinstance(a.get("id"), str) and isinstance(a.get("name"), str),
              "action: id and name required")
        _need(a.get("type") in ACTION_TYPES, "action: unknown type")
        c = a.get("config")
        _need(isinstance(c, dict), "action: config required")
        if a["type"] == "http-request":
            _need(isinstance(c.get("name"), str) and isinstance(c.get("url"), str) and isinstance(c.get("body"), str),
                  "http-request config: name, url and body strings required")
            _need(c.get("method") in HTTP_METHODS, "http-request config: unknown method")
            for key in ("headers", "urlParams"):
                _need(isinstance(c.get(key, {}), dict) and all(isinstance(v, str) for v in c.get(key, {}).values()),
                      f"{key}: a record of strings")
            _need("headers" in c, "headers required")
    return {"widgets": widgets, "actions": actions}


def resolve_widget(widget: dict, base_url: str) -> tuple[str, str]:
    """blueos.ts ``getWidgetsFromBlueOS``: the widget's iframe URL and icon URL as Cockpit uses them."""
    use_ext_path = widget.get("useExtensionPathAsBaseUrl") or False
    icon = widget.get("iconUrl") or widget.get("iframeIcon") or ""
    extension_path = urlsplit(base_url).path or "/"  # new URL(baseUrl).pathname
    return (extension_path + widget["iframeUrl"] if use_ext_path else widget["iframeUrl"],
            base_url + icon if use_ext_path else icon)


def action_request(config: dict) -> tuple[str, str, dict, str | None]:
    """http-request.ts ``getHttpRequestActionCallback``: method, URL, headers and body of the fetch."""
    parts = urlsplit(config["url"])
    if not (parts.scheme and parts.netloc):
        raise Rejected(f"TypeError: Failed to construct 'URL': Invalid URL {config['url']!r}")
    query = dict(p.split("=", 1) for p in parts.query.split("&") if p) | config.get("urlParams", {})
    url = urlunsplit((parts.scheme, parts.netloc, parts.path, urlencode(query), ""))
    return config["method"], url, dict(config["headers"]), None if config["method"] == "GET" else config["body"]


def blueos_service(port: int) -> dict:
    """What BlueOS's helper lists for uwcam (``/helper/v1.0/web_services``), as Cockpit parses it:
    the helper reads /register_service from 127.0.0.1:<port> and adds ``sanitized_name``."""
    metadata = httpx.get(f"http://127.0.0.1:{port}/register_service", timeout=10).json()
    metadata["sanitized_name"] = re.sub(r"[^a-z0-9]", "", metadata["name"].lower())
    return camelcase_keys({"port": port, "metadata": metadata})


# --- uwcam against them -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def vehicle(tmp_path_factory):
    """uwcam with a token and the BlueOS setting that lets Cockpit's actions carry it, behind BlueOS's nginx."""
    config = small_config(token="s3cret")
    config.api.cockpit_actions_token = True
    with Server(config) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 60.0)
        with blueos_nginx(tmp_path_factory.mktemp("nginx"), s.port) as proxy:
            yield s, proxy


def test_cockpit_finds_the_widget_icon_and_actions_under_blueos_prefix_and_the_actions_work(vehicle):
    server, proxy = vehicle
    protocol, vehicle_address = "http:", urlsplit(proxy).netloc
    cockpit_page = f"{proxy}/cockpit.html"  # Cockpit served by the same BlueOS (same origin)
    service = blueos_service(server.port)
    base = blueos_service_url(protocol, vehicle_address, service)
    assert base == f"{proxy}/extensionv2/uwcam"

    fetched = httpx.get(base + service["metadata"]["extras"]["cockpit"], timeout=10)
    assert fetched.status_code == 200, fetched.url
    extras = parse_extras(fetched.json())
    assert len(extras["widgets"]) == 1 and len(extras["actions"]) == 2

    iframe, icon = resolve_widget(extras["widgets"][0], base)
    page = httpx.get(urljoin(cockpit_page, iframe), timeout=10)
    assert page.status_code == 200 and "<html" in page.text.lower() and str(page.url).startswith(base + "/")
    drawn = httpx.get(urljoin(cockpit_page, icon), timeout=10)
    assert drawn.status_code == 200 and drawn.headers["content-type"].startswith("image/svg")

    origin = proxy  # the Origin a page of Cockpit on this BlueOS sends
    for action in sorted(extras["actions"], key=lambda a: a["id"]):  # "…-off" first: the simulated lamp starts on
        method, url, headers, body = action_request(action["config"])
        assert url.startswith(base + "/")
        expected = json.loads(body)["on"]
        answer = httpx.request(method, url, headers={**headers, "Origin": origin}, content=body, timeout=10)
        assert answer.status_code == 200, answer.text
        assert wait_for(lambda: server.daemon.lamp.last_status.on is expected, 10.0), action["id"]
        # Without the token the same request is refused: the token is what made it work.
        bare = {k: v for k, v in headers.items() if k.lower() != "authorization"}
        assert httpx.request(method, url, headers={**bare, "Origin": origin}, content=body, timeout=10).status_code == 401


def test_the_join_rule_rejects_what_uwcam_used_to_serve(vehicle):
    """The ported rules can fail: the old document's relative paths and snake_case keys."""
    server, proxy = vehicle
    base = blueos_service_url("http:", urlsplit(proxy).netloc, blueos_service(server.port))
    assert httpx.get(base + "cockpit_extras.json", timeout=10).status_code == 404  # …/extensionv2/uwcamcockpit_extras.json
    old = {"target_system": "Cockpit", "target_cockpit_api_version": "1.0.0",
           "widgets": [{"name": "uwcam range", "iframe_url": "widget", "iframe_icon": "static/favicon.svg"}]}
    with pytest.raises(Rejected):
        parse_extras(old)
    with pytest.raises(Rejected):
        action_request({"url": "api/v1/lamp", "method": "PUT", "headers": {}, "urlParams": {}, "body": "{}"})
    # A relative widget resolves against Cockpit's own address, not the extension's.
    assert not urljoin(f"{proxy}/cockpit.html", "widget").startswith(base)


def test_reached_directly_the_urls_are_the_daemons_own_and_no_token_is_published():
    with Server(small_config(token="s3cret")) as s:
        extras = parse_extras(s.http.get("/cockpit_extras.json").json())
        iframe, icon = resolve_widget(extras["widgets"][0], s.url)
        assert iframe == f"{s.url}/widget" and httpx.get(icon, timeout=10).status_code == 200
        method, url, headers, body = action_request(extras["actions"][0]["config"])
        assert url == f"{s.url}/api/v1/lamp" and "s3cret" not in json.dumps(extras)
        assert httpx.request(method, url, headers=headers, content=body, timeout=10).status_code == 401
        authorised = httpx.request(method, url, headers={**headers, "Authorization": "Bearer s3cret"}, content=body,
                                   timeout=10)
        assert authorised.status_code == 200


@pytest.mark.parametrize(("headers", "expected"), [
    ({"host": "127.0.0.1:6480"}, "http://127.0.0.1:6480"),
    # BlueOS's nginx: Host without its port, X-Forwarded-Proto, no prefix header.
    ({"host": "blueos.local", "x-forwarded-for": "10.0.0.2", "x-forwarded-proto": "http"},
     "http://blueos.local/extensionv2/uwcam"),
    ({"host": "blueos.local", "x-forwarded-proto": "https"}, "https://blueos.local/extensionv2/uwcam"),
    ({"host": "boat.local", "x-forwarded-for": "1.2.3.4", "x-forwarded-port": "8000"},
     "http://boat.local:8000/extensionv2/uwcam"),
    ({"host": "boat.local", "x-forwarded-for": "1.2.3.4", "x-forwarded-prefix": "/cam/"}, "http://boat.local/cam"),
    # A prefix that is not a plain path is ignored rather than written into URLs.
    ({"host": "boat.local", "x-forwarded-for": "1.2.3.4", "x-forwarded-prefix": "//evil.example"},
     "http://boat.local/extensionv2/uwcam"),
])
def test_public_base_url(headers, expected):
    assert public_base_url(headers, "http") == expected
