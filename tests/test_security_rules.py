"""The API's session expiry, sign-in throttle and same-origin rule, against the numbers
docs/api.md states (12 h idle, 7 days in all; 0.25 s more per wrong token, at most 5 s) and the
URL rules of RFC 6454 (a missing port is the scheme's default: 80 for http, 443 for https)."""

from __future__ import annotations

import pytest

from uwcam.api import security
from uwcam.api.security import Sessions, SignInThrottle, same_origin

HOUR = 3600.0


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(security.time, "monotonic", c)
    return c


def test_a_session_lasts_twelve_hours_without_use_and_no_longer(clock):
    sessions = Sessions()
    session, csrf = sessions.open()
    clock.now += 12 * HOUR  # exactly 12 h idle: still valid, and used again now
    assert sessions.csrf_for(session) == csrf
    clock.now += 12 * HOUR + 1.0
    assert sessions.csrf_for(session) is None
    assert sessions.csrf_for(session) is None  # forgotten, not revived


def test_a_session_in_use_lasts_seven_days_in_all(clock):
    sessions = Sessions()
    session, csrf = sessions.open()
    for _ in range(7 * 24):
        clock.now += HOUR
        assert sessions.csrf_for(session) == csrf
    clock.now += 1.0  # 7 days and a second after it opened, used a second ago
    assert sessions.csrf_for(session) is None


def test_sessions_expire_on_their_own_clock(clock):
    sessions = Sessions(idle_s=10.0, lifetime_s=100.0)
    first, csrf = sessions.open()
    clock.now += 5.0
    second, _ = sessions.open()
    clock.now += 6.0  # first used 11 s ago, second 6 s ago
    assert sessions.csrf_for(first) is None
    assert sessions.csrf_for(second) is not None


def test_each_wrong_token_in_a_row_adds_a_quarter_second_up_to_five():
    throttle = SignInThrottle()
    assert throttle.delay_s() == 0.0
    waits = []
    for _ in range(25):
        throttle.record(False)
        waits.append(throttle.delay_s())
    assert waits[:4] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert waits[19] == pytest.approx(5.0) and max(waits) == pytest.approx(5.0)
    assert waits[18] == pytest.approx(4.75)
    throttle.record(True)
    assert throttle.delay_s() == 0.0


@pytest.mark.parametrize("origin, host, forwarded, same", [
    ("http://boat.local", "boat.local", None, True),
    ("http://boat.local:80", "boat.local", None, True),  # explicit default port
    ("https://boat.local:443", "boat.local", None, True),
    ("https://boat.local", "boat.local", None, True),
    ("http://boat.local:81", "boat.local", None, False),
    ("https://boat.local:444", "boat.local", None, False),
    ("http://boat.local:8080", "boat.local:8080", None, True),
    ("http://boat.local:8080", "boat.local", "8080", True),  # behind a proxy that names its port
    ("http://boat.local", "boat.local", "8080", False),
    ("http://boat.local:8080", "boat.local", None, False),
    ("http://other.local", "boat.local", None, False),
    ("http://boat.local", "boat.local", "eighty", False),
])
def test_same_origin_follows_the_default_ports(origin, host, forwarded, same):
    assert same_origin(origin, host, forwarded) is same
