"""Waiting for background threads in tests: poll a condition until a deadline."""

import time


def wait_for(predicate, timeout_s: float = 10.0, interval_s: float = 0.02) -> bool:
    """True as soon as ``predicate()`` holds, False if it never did within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return False
