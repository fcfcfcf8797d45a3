"""Lamp commands off the frame loop's critical path.

A serial lamp answers in milliseconds, or, when it does not answer, only after its reply
timeout and a retry (about a second). The frame loop must never wait for that: it *asks* for
the lamp on or off and carries on; this commander's own thread sends the command, retries a
failed one with exponential backoff, and tells the loop when the lamp has acknowledged.
"""

from __future__ import annotations

import logging
import threading
import time

from uwcam.drivers.threads import StoppableThread

log = logging.getLogger(__name__)


class LampCommander:
    """Drives ``lamp.on()``/``lamp.off()`` in a thread of its own; the newest request wins.

    With no command to send for ``poll_s`` seconds, it asks the lamp for its status, so that a
    lamp which falls silent while nothing is commanded shows as not answering within about
    ``poll_s`` plus the lamp's reply timeout (its health, in /api/v1/status and on the page),
    as the camera's watchdog and the rangefinder's readings do for theirs."""

    def __init__(self, lamp: object, backoff_s: tuple[float, float] = (0.25, 10.0), poll_s: float = 2.0) -> None:
        self.lamp = lamp
        self.backoff_s = backoff_s
        self.poll_s = poll_s
        self._polls = 0
        self._cond = threading.Condition()
        self._want: bool | None = None  # guarded by _cond
        self._requested = 0
        self._completed = 0
        self._acknowledged_ns = 0
        self._failures = 0
        self._last_error: str | None = None
        self._retry_at: float | None = None
        self._worker = StoppableThread(self._run, "lamp-commander", wake=self._cond)

    def request(self, on: bool) -> int:
        """Ask for the lamp on or off; returns a ticket for :meth:`done`. Never blocks."""
        with self._cond:
            self._requested += 1
            self._want = on
            self._cond.notify_all()
            return self._requested

    def done(self, ticket: int) -> bool:
        """True once the request ``ticket`` (or a later one) has been acknowledged by the lamp."""
        with self._cond:
            return self._completed >= ticket

    @property
    def acknowledged_ns(self) -> int:
        """time.monotonic_ns() when the lamp last acknowledged a command."""
        with self._cond:
            return self._acknowledged_ns

    @property
    def failing(self) -> bool:
        """True while the last attempt at a command failed."""
        with self._cond:
            return self._failures > 0

    def status(self) -> dict:
        with self._cond:
            return {"pending": None if self._want is None else ("on" if self._want else "off"),
                    "consecutive_failures": self._failures, "last_error": self._last_error,
                    "retry_in_s": None if self._retry_at is None else round(max(0.0, self._retry_at - time.monotonic()), 2)}

    def start(self) -> None:
        self._worker.start()

    def stop(self) -> None:
        self._worker.stop()

    @property
    def polls(self) -> int:
        """Status queries made while no command was due."""
        with self._cond:
            return self._polls

    def _poll(self) -> None:
        """Ask the lamp for its status; its driver records in its health whether it answered."""
        try:
            self.lamp.status()
        except Exception as exc:  # the driver's health says so; the loop goes on
            log.debug("lamp status query failed: %s", exc)
        with self._cond:
            self._polls += 1

    def _run(self) -> None:
        delay = self.backoff_s[0]
        while not self._worker.stopping.is_set():
            with self._cond:
                self._cond.wait_for(lambda: self._want is not None or self._worker.stopping.is_set(), timeout=self.poll_s)
                if self._worker.stopping.is_set():
                    return
                want, ticket = self._want, self._requested
            if want is None:
                self._poll()
                continue
            try:
                self.lamp.on() if want else self.lamp.off()
            except Exception as exc:  # not answering, unplugged, refusing: retry later, loop unaffected
                with self._cond:
                    self._failures += 1
                    self._last_error = f"{type(exc).__name__}: {exc}"
                    self._retry_at = time.monotonic() + delay
                if self._failures == 1:
                    log.warning("lamp did not take 'switch %s': %s; retrying with backoff", "on" if want else "off", exc)
                self._worker.stopping.wait(delay)
                delay = min(delay * 2, self.backoff_s[1])
                continue
            delay = self.backoff_s[0]
            with self._cond:
                self._completed = max(self._completed, ticket)
                self._acknowledged_ns = time.monotonic_ns()
                if self._requested == ticket:
                    self._want = None
                if self._failures:
                    log.info("lamp answers again after %d failed attempt(s)", self._failures)
                self._failures, self._last_error, self._retry_at = 0, None, None
