"""Authorisation of every state-changing route, enumerated from the live application.

A real uvicorn server on an ephemeral port runs the real daemon on simulated devices. The routes
are taken from the application object, so a route added later is covered without touching this
file. Each one is tried with no token, wrong tokens, the right token, and the browser path
(session cookie from ``POST /api/v1/session`` plus its CSRF header), and from a foreign page.
"""

from __future__ import annotations

import asyncio
import re

import httpx
import pytest
import websockets
from fastapi.routing import APIRoute
from starlette.routing import Mount

from tests.served import Server
from uwcam.api.app import ROUTERS
from uwcam.api.security import required_token
from uwcam.config import ApiConfig, CameraConfig, DaemonConfig, DeviceConfig
from uwcam.fileio import UserInputError

COOKIE = "uwcam_session_8080"  # uwcam_session_<api.port> (cookies ignore ports): the configured port, 8080
TOKEN = "s3cret-Tok3n"
SESSION_PATH = "/api/v1/session"
SAFE = {"GET", "HEAD", "OPTIONS"}
WRONG = [
    "Bearer wrong",
    "Bearer",
    f"Bearer {TOKEN[:-1]}",  # a prefix of the token
    f"Bearer {TOKEN}x",  # the token and more
    f"Bearer {TOKEN.upper()}",
    TOKEN,  # no scheme
    f"Basic {TOKEN}",
    f"Token {TOKEN}",
]


def config(token: str | None, **api) -> DaemonConfig:
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 10.0, "serial_number": "SIM-AUTH"}, watchdog_s=1.0),
        lamp=DeviceConfig(driver="sim"),
        simulation={"scene": "seabed", "distance": 2.0, "size": [64, 48], "water": "jerlov-IB"},
        api=ApiConfig(token=token, **api),
    )


@pytest.fixture(scope="module")
def server():
    with Server(config(TOKEN)) as s:
        yield s


def state_changing(app) -> list[tuple[str, str]]:
    """(method, concrete path) of every route that may change state; path parameters filled in.

    From the OpenAPI schema (every documented route, however it was added) and from the route
    objects of the app and of its routers (also those left out of the schema)."""
    found: set[tuple[str, str]] = set()
    for path, operations in app.openapi()["paths"].items():
        found |= {(m.upper(), path) for m in operations if m.upper() not in SAFE}
    for route in [*app.routes, *(r for router in ROUTERS for r in router.routes)]:
        if isinstance(route, APIRoute):
            found |= {(m, route.path) for m in route.methods - SAFE}
    return sorted({(m, re.sub(r"\{[^}]+\}", "auth-probe", p)) for m, p in found})


def request(s: Server, method: str, path: str, **kw) -> httpx.Response:
    kw.setdefault("json", {})
    return s.http.request(method, path, **kw)


def routes(s: Server) -> list[tuple[str, str]]:
    r = [mp for mp in state_changing(s.app) if mp[1] != SESSION_PATH]
    assert len(r) >= 5, r  # lamp, config (2), profiles (2) at least
    return r


def test_the_route_table_has_the_known_state_changing_routes(server):
    found = set(state_changing(server.app))
    for expected in [("PUT", "/api/v1/lamp"), ("PATCH", "/api/v1/config"), ("POST", "/api/v1/config/restore"),
                     ("PUT", "/api/v1/calibration/profiles/auth-probe"),
                     ("POST", "/api/v1/calibration/profiles/auth-probe/activate"),
                     ("POST", SESSION_PATH), ("DELETE", SESSION_PATH)]:
        assert expected in found
    # Anything mounted (static files) must not take state changes.
    for route in server.app.routes:
        if isinstance(route, Mount):
            assert request(server, "POST", route.path.rstrip("/") + "/x").status_code in (401, 403, 404, 405)


def test_every_state_change_without_a_token_is_refused(server):
    for method, path in routes(server):
        r = request(server, method, path)
        assert r.status_code == 401, (method, path, r.status_code, r.text)
        assert "Authorization: Bearer" in r.json()["detail"]


@pytest.mark.parametrize("header", WRONG)
def test_every_state_change_with_a_wrong_token_is_refused(server, header):
    for method, path in routes(server):
        r = request(server, method, path, headers={"Authorization": header})
        assert r.status_code == 401, (method, path, header, r.status_code)


def test_every_state_change_with_the_token_reaches_its_handler(server):
    for method, path in routes(server):
        r = request(server, method, path, headers={"Authorization": f"Bearer {TOKEN}"})
        assert r.status_code not in (401, 403), (method, path, r.status_code, r.text)


def test_a_refused_request_changes_nothing(server):
    before = server.http.get("/api/v1/lamp").json()
    assert before["on"] is True
    assert server.http.put("/api/v1/lamp", json={"on": False, "intensity": 10}).status_code == 401
    assert server.http.put("/api/v1/lamp", json={"on": False}, headers={"Authorization": "Bearer nope"}).status_code == 401
    after = server.http.get("/api/v1/lamp").json()
    assert after["on"] is True and after["intensity"] == before["intensity"]
    config = server.http.get("/api/v1/config").json()
    assert server.http.patch("/api/v1/config", json={"smoothing": "median"}).status_code == 401
    assert server.http.get("/api/v1/config").json() == config


def test_reading_stays_open(server):
    for path in ("/api/v1/status", "/api/v1/config", "/api/v1/lamp", "/api/v1/calibration/profiles", SESSION_PATH):
        assert server.http.get(path).status_code == 200, path


def sign_in(s: Server) -> tuple[str, str]:
    r = s.http.post(SESSION_PATH, json={"token": TOKEN})
    assert r.status_code == 200, r.text
    cookie = r.cookies.get(COOKIE)
    set_cookie = r.headers["set-cookie"].lower()
    assert cookie and "httponly" in set_cookie and "samesite=strict" in set_cookie and "path=/" in set_cookie
    assert "secure" not in set_cookie  # plain http here: a Secure cookie would never come back
    assert r.json()["token_required"] is True
    s.http.cookies.clear()  # each request below says exactly what it sends
    return cookie, r.json()["csrf_token"]


def test_the_session_cookie_lasts_as_long_as_a_session_may(server):
    """docs/api.md: a session ends after 12 hours without use or 7 days in all. The daemon ends
    idle sessions itself; the cookie must not end first, or a browser in use would lose its
    session 12 hours after signing in."""
    r = server.http.post(SESSION_PATH, json={"token": TOKEN})
    server.http.cookies.clear()
    assert r.status_code == 200, r.text
    max_age = re.search(r"max-age=(\d+)", r.headers["set-cookie"].lower())
    assert max_age and int(max_age.group(1)) == 7 * 24 * 3600


def test_browser_session_with_csrf_header_is_accepted_and_without_it_refused(server):
    cookie, csrf = sign_in(server)
    other_cookie, other_csrf = sign_in(server)
    assert cookie != other_cookie and csrf != other_csrf
    for secret in (cookie, csrf):  # at least 32 random bytes each, URL-safe base64
        assert len(secret) >= 43 and re.fullmatch(r"[A-Za-z0-9_-]+", secret)
    for method, path in routes(server):
        ok = request(server, method, path, headers={"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf})
        assert ok.status_code not in (401, 403), (method, path, ok.status_code, ok.text)
        for headers in ({"Cookie": f"{COOKIE}={cookie}"},  # no CSRF header
                        {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": ""},
                        {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf[:-1]},
                        {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": other_csrf},  # another session's
                        {"X-CSRF-Token": csrf},  # no cookie
                        {"Cookie": f"{COOKIE}={csrf}", "X-CSRF-Token": cookie},  # swapped
                        {"Cookie": f"{COOKIE}=forged", "X-CSRF-Token": csrf}):
            r = request(server, method, path, headers=headers)
            assert r.status_code == 401, (method, path, headers, r.status_code)


def test_signing_out_ends_the_session_and_wrong_tokens_get_none(server, monkeypatch):
    from uwcam.api.security import SignInThrottle

    # Wrong tokens in a row would make this address wait (429; see test_hardening_second): here
    # each one must be checked, and the module's other tests must not inherit a wait.
    monkeypatch.setattr(server.app.state.guard, "throttle", SignInThrottle(step_s=0.0))
    cookie, csrf = sign_in(server)
    headers = {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf}
    assert server.http.get(SESSION_PATH, headers={"Cookie": f"{COOKIE}={cookie}"}).json() == \
        {"token_required": True, "signed_in": True, "csrf_token": csrf}
    assert server.http.get(SESSION_PATH).json() == {"token_required": True, "signed_in": False, "csrf_token": None}
    assert server.http.put("/api/v1/lamp", json={}, headers=headers).status_code == 200
    out = server.http.delete(SESSION_PATH, headers={"Cookie": f"{COOKIE}={cookie}"})
    assert out.status_code == 200 and out.json() == {"signed_in": False}
    server.http.cookies.clear()
    assert server.http.put("/api/v1/lamp", json={}, headers=headers).status_code == 401
    assert server.http.get(SESSION_PATH, headers={"Cookie": f"{COOKIE}={cookie}"}).json()["signed_in"] is False
    for token in ("wrong", "", TOKEN[:-1], TOKEN + " ", f"Bearer {TOKEN}"):
        r = server.http.post(SESSION_PATH, json={"token": token})
        assert r.status_code == 401 and COOKIE not in r.cookies, token
    assert server.http.post(SESSION_PATH, json={}).status_code == 422
    assert server.http.post(SESSION_PATH, json={"token": "x" * 4096}).status_code == 401  # long, but wrong
    assert server.http.post(SESSION_PATH, json={"token": "x" * 4097}).status_code == 422  # too long to consider
    assert server.http.post(SESSION_PATH, json={"token": TOKEN, "extra": 1}).status_code == 422


def test_foreign_pages_may_not_change_state_even_with_credentials(server):
    cookie, csrf = sign_in(server)
    own = f"http://127.0.0.1:{server.port}"
    for method, path in routes(server) + [("POST", SESSION_PATH), ("DELETE", SESSION_PATH)]:
        body = {"token": TOKEN} if path == SESSION_PATH else {}
        for origin in ("http://evil.example", "null", f"http://127.0.0.1:{server.port + 1}", f"https://127.0.0.1:{server.port}x"):
            for creds in ({"Authorization": f"Bearer {TOKEN}"}, {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf}):
                r = request(server, method, path, json=body, headers={"Origin": origin, **creds})
                assert r.status_code == 403, (method, path, origin, r.status_code)
                assert "may not change this daemon's state" in r.json()["detail"]
        r = request(server, method, path, json=body, headers={"Origin": own, "Authorization": f"Bearer {TOKEN}"})
        assert r.status_code not in (401, 403), (method, path, r.status_code, r.text)
    # Reading from a foreign page is not a state change.
    assert server.http.get("/api/v1/status", headers={"Origin": "http://evil.example"}).status_code == 200


@pytest.mark.parametrize("host, allowed", [
    ("127.0.0.1", True), ("[::1]:8080", True), ("10.0.0.7:80", True), ("localhost", True), ("LOCALHOST:1", True),
    ("cam.localhost", True), ("blueos.local", True), ("blueos.local.", True),
    ("evil.example", False), ("evillocalhost", False), ("local", False), ("blueos.local.evil.example", False),
    ("", False),
])
def test_unknown_host_names_are_refused_even_for_reads(server, host, allowed):
    r = server.http.get("/api/v1/status", headers={"Host": host})
    assert (r.status_code == 200) == allowed, (host, r.status_code)
    if not allowed:
        assert r.status_code == 421 and "api.allowed_hosts" in r.json()["detail"]


def test_websocket_from_a_foreign_page_is_refused(server):
    async def connect(origin):
        async with websockets.connect(f"ws://127.0.0.1:{server.port}/api/v1/stream?rate=5",
                                      additional_headers={"Origin": origin}) as ws:
            return await asyncio.wait_for(ws.recv(), 10.0)

    assert "hello" in asyncio.run(connect(f"http://127.0.0.1:{server.port}"))
    with pytest.raises(Exception) as refused:
        asyncio.run(connect("http://evil.example"))
    assert "403" in str(refused.value) or "1008" in str(refused.value)


def test_configured_host_names_and_open_loopback_daemon():
    with Server(config(None, allowed_hosts=["cam.example.org", "*.vehicles.example"])) as s:
        for host, status in [("cam.example.org", 200), ("rov1.vehicles.example", 200), ("vehicles.example", 421),
                             ("other.example.org", 421)]:
            assert s.http.get("/api/v1/status", headers={"Host": host}).status_code == status, host
        # No token on loopback: state changes need no credentials, but foreign pages are still refused.
        assert s.http.put("/api/v1/lamp", json={"on": True}).status_code == 200
        assert s.http.put("/api/v1/lamp", json={}, headers={"Origin": "http://evil.example"}).status_code == 403
        assert s.http.get(SESSION_PATH).json() == {"token_required": False, "signed_in": True, "csrf_token": None}


def test_a_token_is_required_beyond_loopback(monkeypatch):
    monkeypatch.delenv("UWCAM_TOKEN", raising=False)
    for host in ("0.0.0.0", "192.168.2.2", "::", "localhost.evil.example"):
        with pytest.raises(UserInputError, match=f"refusing to listen on {re.escape(host)} without a token"):
            required_token(config(None, host=host))
    for host in ("127.0.0.1", "::1", "localhost", "127.0.0.2"):
        assert required_token(config(None, host=host)) is None
    assert required_token(config("abc", host="0.0.0.0")) == "abc"
    monkeypatch.setenv("UWCAM_TOKEN", "from-env")
    assert required_token(config(None, host="0.0.0.0")) == "from-env"
    assert required_token(config("abc", host="0.0.0.0")) == "abc"  # the configuration wins


def test_a_path_ending_like_the_session_route_gets_no_exemption(server):
    """The token exchange is exempt from the token check; no other route may become so by a path
    parameter that ends in /api/v1/session (slashes encoded)."""
    for method, path in routes(server):
        if "auth-probe" not in path:
            continue
        probe = path.replace("auth-probe", "x%2Fapi%2Fv1%2Fsession")
        r = request(server, method, probe)
        assert r.status_code in (401, 404), (method, probe, r.status_code)
        r = request(server, method, path.replace("auth-probe", "session"))
        assert r.status_code == 401, (method, path, r.status_code)


def test_the_oldest_browser_session_is_forgotten_beyond_256(server):
    first, first_csrf = sign_in(server)
    second, second_csrf = sign_in(server)
    for _ in range(254):  # 256 sessions open now: all valid
        sign_in(server)
    for cookie, csrf in ((first, first_csrf), (second, second_csrf)):
        assert server.http.put("/api/v1/lamp", json={}, headers={"Cookie": f"{COOKIE}={cookie}",
                                                                 "X-CSRF-Token": csrf}).status_code == 200
    sign_in(server)  # the 257th pushes out the oldest
    assert server.http.put("/api/v1/lamp", json={}, headers={"Cookie": f"{COOKIE}={first}",
                                                             "X-CSRF-Token": first_csrf}).status_code == 401
    assert server.http.put("/api/v1/lamp", json={}, headers={"Cookie": f"{COOKIE}={second}",
                                                             "X-CSRF-Token": second_csrf}).status_code == 200


class FixedWait:
    """A sign-in throttle that tells every address to wait ``wait`` s more, and records what it is told."""

    def __init__(self, wait: float) -> None:
        self.wait, self.recorded = wait, []

    def wait_s(self, address: str = "") -> float:
        return self.wait

    def record(self, ok: bool, address: str = "") -> None:
        self.recorded.append(ok)


@pytest.mark.parametrize("wait, status, retry_after", [(0.4, 429, "1"), (2.2, 429, "3"), (0.0, 401, None)])
def test_a_wrong_token_within_the_wait_is_refused_at_once_with_the_seconds_left(server, monkeypatch, wait, status, retry_after):
    """Any wait left, however short, is a 429 saying the whole seconds to wait (a wait under a
    second included); none left, the token is checked, found wrong, and counted."""
    throttle = FixedWait(wait)
    monkeypatch.setattr(server.app.state.guard, "throttle", throttle)
    r = server.http.post(SESSION_PATH, json={"token": "wrong"})
    assert r.status_code == status, r.text
    assert r.headers.get("Retry-After") == retry_after
    assert throttle.recorded == ([] if status == 429 else [False])
