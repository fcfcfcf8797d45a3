"""A serial port that survives: reopens with backoff after the device goes away.

pyserial does the I/O; reads block with the port's own timeout (no sleep-polling). The
port path should be a stable name (udev symlink, see deploy/): a device that comes back
under the same name is found again.
"""

from __future__ import annotations

import termios
import threading
import time

import serial

from uwcam.drivers.base import ConfigurationError, DeviceLost, HealthState, HealthTracker

# What pyserial raises when a port breaks: its own error, the OS's, and termios errors from
# flushes on a vanished tty (seen with USB adapters pulled and ptys closed).
PORT_ERRORS = (serial.SerialException, OSError, termios.error)


def close_quietly(port: serial.Serial | None) -> None:
    """Close ``port`` (None: nothing to close); a port that vanished closes as best it can, without an error."""
    if port is not None:
        try:
            port.close()
        except Exception:  # closing a vanished port is best effort
            pass


class OpenBackoff:
    """When a lazily opened link may next try to open its device: a failed open waits
    ``retry_s[0]`` seconds before the next try, doubling up to ``retry_s[1]``; an open that works
    resets the wait. Failures set ``health`` to RECOVERING; ``port`` names the device in messages."""

    def __init__(self, port: str, retry_s: tuple[float, float], health: HealthTracker) -> None:
        self.port, self.retry_s, self.health = port, retry_s, health
        self._next_try = 0.0
        self._delay = retry_s[0]

    def check(self) -> float:
        """The monotonic time now; DeviceLost while the wait after a failed open lasts."""
        now = time.monotonic()
        if now < self._next_try:
            raise DeviceLost(f"{self.port} is unavailable; retrying in {self._next_try - now:.1f} s")
        return now

    def failed(self, now: float, exc: Exception) -> DeviceLost:
        """Record a failed open tried at ``now``; the DeviceLost to raise."""
        self._next_try = now + self._delay
        self._delay = min(self._delay * 2, self.retry_s[1])
        self.health.set(HealthState.RECOVERING, f"cannot open {self.port}: {exc}")
        return DeviceLost(f"cannot open {self.port}: {exc}")

    def opened(self) -> None:
        self._delay = self.retry_s[0]


class SerialLink:
    """One serial port, opened lazily and reopened after failures (at most every ``retry_s``)."""

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 0.5, retry_s: tuple[float, float] = (0.1, 5.0)) -> None:
        self.port, self.baud, self.timeout_s = port, int(baud), float(timeout_s)
        self.retry_s = retry_s
        self.health = HealthTracker()
        self.lock = threading.RLock()  # one transaction (command + reply) at a time
        self._serial: serial.Serial | None = None
        self._backoff = OpenBackoff(self.port, retry_s, self.health)

    def check_exists(self) -> None:
        """ConfigurationError at start when the port cannot exist at all (wrong name)."""
        try:
            serial.Serial(self.port, self.baud, timeout=self.timeout_s).close()
        except serial.SerialException as exc:
            raise ConfigurationError(f"cannot open serial port {self.port}: {exc}; check the device name and udev rules") from None

    def _ensure_open(self) -> serial.Serial:
        if self._serial is not None:
            return self._serial
        now = self._backoff.check()
        try:
            self._serial = serial.Serial(self.port, self.baud, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except PORT_ERRORS as exc:
            raise self._backoff.failed(now, exc) from None
        self._backoff.opened()
        return self._serial

    def _close_port(self) -> None:
        close_quietly(self._serial)
        self._serial = None

    def fail(self, reason: str) -> None:
        """Close after an I/O failure; the next use reopens.

        Takes the transaction lock: a failure seen in one thread must not close the port under
        another thread's transaction (pyserial clears the descriptor before it clears ``is_open``,
        so a call in flight would see an open port without a descriptor).
        """
        with self.lock:
            self.health.set(HealthState.RECOVERING, reason)
            self._close_port()

    def _io(self, what: str, call):
        """Run ``call(port)``; a port error closes the port and becomes DeviceLost naming ``what``."""
        port = self._ensure_open()
        try:
            return call(port)
        except PORT_ERRORS as exc:
            self.fail(f"{what} {self.port} failed: {exc}")
            raise DeviceLost(f"{what} {self.port} failed: {exc}") from None
        except (TypeError, AttributeError) as exc:
            if port.is_open and getattr(port, "fd", 0) is not None:
                raise  # a mistake in the call itself, not the port
            # Closed under the call (a disconnect handled in another thread): pyserial checks
            # is_open first, then uses the descriptor it no longer has (TypeError from tcflush);
            # its close() clears the descriptor before is_open, so either may be seen first.
            self.fail(f"{what} {self.port} failed: the port was closed")
            raise DeviceLost(f"{what} {self.port} failed: the port was closed during the call ({exc})") from None

    def write(self, data: bytes) -> None:
        """Send ``data``, dropping any stale input first (each command waits for its own reply)."""
        def send(port):
            port.reset_input_buffer()
            port.write(data)
            port.flush()

        self._io("write to", send)

    def read_until(self, terminator: bytes, limit: int = 512) -> bytes:
        """Bytes up to and including ``terminator``, or what came before the timeout."""
        return self._io("read from", lambda port: port.read_until(terminator, limit))

    def read(self, size: int) -> bytes:
        return self._io("read from", lambda port: port.read(size))

    def close(self) -> None:
        with self.lock:
            self._close_port()
