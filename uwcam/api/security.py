"""Who may change state, declared once for every route.

Every request passes :func:`guard`, installed as a dependency of the whole application, so a new
route cannot forget it:

* reads (GET, HEAD, OPTIONS) are open to anyone who can reach the daemon;
* everything else (POST, PUT, PATCH, DELETE) needs, when a token is set, either
  ``Authorization: Bearer <token>`` (tools, scripts) or the session cookie that
  ``POST /api/v1/session`` hands to a browser in exchange for the token, together with the
  ``X-CSRF-Token`` header that the same call returns (a page inside an iframe, such as BlueOS's or
  Cockpit's, cannot send a bearer header of its own);
* a state change whose ``Origin`` is not this daemon's own is refused, token or not, so that a web
  page the operator happens to visit cannot drive the lamp through the operator's browser.

Tokens are compared as bytes in constant time, so non-ASCII input is simply a wrong token.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import secrets
import threading
import time
from urllib.parse import urlsplit

from fastapi import HTTPException, WebSocketException, status
from starlette.requests import HTTPConnection

from uwcam.config import DaemonConfig
from uwcam.fileio import UserInputError

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SESSION_PATH = "/api/v1/session"
"""Checks the token itself: exchanging it for a session, and ending one."""
SESSION_COOKIE = "uwcam_session"
CSRF_HEADER = "x-csrf-token"


def is_loopback(host: str) -> bool:
    """True only for explicit loopback addresses and the name ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def required_token(config: DaemonConfig) -> str | None:
    """The token for state-changing requests; UserInputError if one is needed and missing."""
    token = config.api.token or os.environ.get("UWCAM_TOKEN")
    if not is_loopback(config.api.host) and not token:
        raise UserInputError(
            f"refusing to listen on {config.api.host} without a token: set the UWCAM_TOKEN environment variable "
            "(the systemd unit reads it from /etc/uwcam/token.env; see docs/deployment.md) or api.token"
        )
    return token or None


def _utf8(text: str) -> bytes:
    """The text's bytes: an environment variable's undecodable bytes come back as they were, and
    any other lone surrogate (only a wrong token can hold one) is encoded rather than raised on."""
    try:
        return text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:
        return text.encode("utf-8", "surrogatepass")


def _same(given: bytes, expected: bytes) -> bool:
    return hmac.compare_digest(given, expected)


def _header_bytes(value: str) -> bytes:
    """The header's bytes as sent: HTTP headers are bytes, which Starlette decodes as Latin-1."""
    return value.encode("latin-1", "replace")


class Sessions:
    """Browser sessions: an opaque id (HttpOnly cookie) bound to a CSRF token (sent as a header).

    A session ends after ``idle_s`` without use or ``lifetime_s`` in all; at most ``limit`` are
    kept (the oldest forgotten first). Sign-in routes run in a thread pool: a lock guards the table."""

    def __init__(self, limit: int = 256, idle_s: float = 12 * 3600.0, lifetime_s: float = 7 * 24 * 3600.0) -> None:
        self._table: dict[str, tuple[str, float, float]] = {}  # id → (csrf, opened, last used), monotonic s
        self._limit, self._idle_s, self._lifetime_s = limit, idle_s, lifetime_s
        self._lock = threading.Lock()

    def open(self) -> tuple[str, str]:
        session, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        now = time.monotonic()
        with self._lock:
            while len(self._table) >= self._limit:
                self._table.pop(next(iter(self._table)))
            self._table[session] = (csrf, now, now)
        return session, csrf

    def close(self, session: str) -> None:
        with self._lock:
            self._table.pop(session, None)

    def csrf_for(self, session: str) -> str | None:
        """The session's CSRF token while it is valid (and marks it used); None otherwise."""
        now = time.monotonic()
        with self._lock:
            entry = self._table.get(session)
            if entry is None:
                return None
            csrf, opened, used = entry
            if now - used > self._idle_s or now - opened > self._lifetime_s:
                del self._table[session]
                return None
            self._table[session] = (csrf, opened, now)
            return csrf


class SignInThrottle:
    """Wrong sign-ins, per client address: every wrong token in a row from an address makes that
    address wait longer before its next wrong token is answered 401 (``step_s`` more each time, at
    most ``most_s``); a right token clears the address's count.

    The wait is not spent holding a request: a wrong token that comes too early is refused at once
    (429, with the seconds left), so a flood of wrong sign-ins costs neither a worker thread nor the
    time of anyone else; a right token is never refused (see :func:`uwcam.api.session.sign_in`).
    At most ``addresses`` addresses are remembered (the longest unused forgotten first), so a
    flood from many addresses costs bounded memory."""

    def __init__(self, step_s: float = 0.25, most_s: float = 5.0, addresses: int = 4096) -> None:
        self._table: dict[str, tuple[int, float]] = {}  # address → (wrong tokens in a row, last one, monotonic s)
        self._step_s, self._most_s, self._limit = step_s, most_s, addresses
        self._lock = threading.Lock()

    def delay_s(self, address: str = "") -> float:
        """The wait (s) that ``address``'s wrong tokens in a row impose after the last of them."""
        with self._lock:
            failures = self._table.get(address, (0, 0.0))[0]
        return min(failures * self._step_s, self._most_s)

    def wait_s(self, address: str = "") -> float:
        """Seconds ``address`` must still wait before its next attempt; 0 when it may try now."""
        with self._lock:
            failures, last = self._table.get(address, (0, 0.0))
        if failures == 0:
            return 0.0
        return max(0.0, last + min(failures * self._step_s, self._most_s) - time.monotonic())

    def record(self, ok: bool, address: str = "") -> None:
        with self._lock:
            if ok:
                self._table.pop(address, None)
                return
            failures = self._table.pop(address, (0, 0.0))[0]  # re-inserted last: the table stays in order of use
            while len(self._table) >= self._limit:
                self._table.pop(next(iter(self._table)))
            self._table[address] = (failures + 1, time.monotonic())


DEFAULT_HOST_NAMES = ("localhost", "*.localhost", "*.local")
"""Names accepted in ``Host`` besides IP literals: loopback and mDNS names (BlueOS answers as
blueos.local). A DNS-rebinding attack needs a public name that resolves to the vehicle; such a name
is refused unless configured in ``api.allowed_hosts``."""


def host_allowed(host_header: str, allowed: tuple[str, ...]) -> bool:
    host = urlsplit(f"//{host_header}").hostname or ""
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    host = host.lower().rstrip(".")
    for pattern in (*DEFAULT_HOST_NAMES, *allowed):
        pattern = pattern.lower()
        if host == pattern or (pattern.startswith("*.") and host.endswith(pattern[1:])):
            return True
    return False


def same_origin(origin: str, host_header: str, forwarded_port: str | None = None) -> bool:
    """Whether a page at ``origin`` belongs to the daemon reached as ``host_header``.

    A reverse proxy may pass on the host name without its port (BlueOS's nginx sets
    ``Host $host``): then the page's port must be the one the proxy says it received the request
    on (``X-Forwarded-Port``), or else the scheme's default port (BlueOS serves on port 80)."""
    page = urlsplit(origin)
    host = urlsplit(f"//{host_header}")
    try:
        page_port, host_port = page.port, host.port
        proxied_port = int(forwarded_port) if forwarded_port else None
    except ValueError:
        return False
    if (page.hostname or "").lower() != (host.hostname or "").lower():
        return False
    default = {"http": 80, "https": 443}.get(page.scheme)
    expected = host_port or proxied_port or default
    return (page_port or default) == expected


class Guard:
    """The application-wide dependency: Host and Origin checks, and authorisation of state changes."""

    def __init__(self, token: str | None, allowed_hosts: tuple[str, ...] = (), allowed_origins: tuple[str, ...] = (),
                 cookie: str = SESSION_COOKIE) -> None:
        self.token = token
        self.allowed_hosts = allowed_hosts
        self.allowed_origins = tuple(o.rstrip("/").lower() for o in allowed_origins)
        self.cookie = cookie
        """Session cookie name: one per daemon port, since cookies ignore ports."""
        self.sessions = Sessions()
        self.throttle = SignInThrottle()

    def authenticated(self, conn: HTTPConnection) -> bool:
        """A valid bearer token, or a valid session cookie with its CSRF token."""
        if self.token is None:
            return True
        scheme, _, given = conn.headers.get("authorization", "").partition(" ")
        # The scheme is case-insensitive; a token with non-ASCII characters travels as its UTF-8 bytes.
        if scheme.lower() == "bearer" and _same(_header_bytes(given.strip()), _utf8(self.token)):
            return True
        session = conn.cookies.get(self.cookie)
        csrf = self.sessions.csrf_for(session) if session else None
        return csrf is not None and _same(_header_bytes(conn.headers.get(CSRF_HEADER, "")), _utf8(csrf))

    def check_origin(self, conn: HTTPConnection) -> None:
        """Refuse a request from a page of another origin (a browser always sends Origin on those)."""
        origin = conn.headers.get("origin")
        if origin is None:
            return  # not from a browser page, or a same-origin GET
        if origin.rstrip("/").lower() in self.allowed_origins:
            return  # configured, e.g. Cockpit served from another port
        if origin == "null" or not same_origin(origin, conn.headers.get("host", ""), conn.headers.get("x-forwarded-port")):
            raise HTTPException(status_code=403, detail=f"requests from the page at {origin} may not change this daemon's "
                                                        "state; use uwcam's own page")

    async def __call__(self, conn: HTTPConnection) -> None:
        if conn.scope["type"] == "websocket":
            try:
                self._check(conn, "WEBSOCKET")
            except HTTPException as exc:
                raise WebSocketException(code=status.WS_1008_POLICY_VIOLATION, reason=str(exc.detail)[:120]) from None
        else:
            self._check(conn, conn.scope["method"])

    def _check(self, conn: HTTPConnection, method: str) -> None:
        host = conn.headers.get("host", "")
        if not host_allowed(host, self.allowed_hosts):
            raise HTTPException(status_code=421, detail=f"unknown host name {host!r}: add it to api.allowed_hosts "
                                                        "if uwcam is reached through it")
        if method in SAFE_METHODS:
            return
        self.check_origin(conn)
        if method == "WEBSOCKET" or getattr(conn.scope.get("route"), "path", None) == SESSION_PATH:
            return  # streams only read; the exchange of a token for a session checks the token itself
        if not self.authenticated(conn):
            raise HTTPException(status_code=401, detail="this request changes state: send 'Authorization: Bearer <token>', "
                                                        "or sign in on the page")

    def check_token(self, given: str) -> bool:
        return self.token is None or _same(_utf8(given), _utf8(self.token))
