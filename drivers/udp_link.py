"""A device reached over UDP (``udp:HOST:PORT``), with the same interface as :class:`SerialLink`.

BlueOS's ping service owns a Ping sonar's serial port and bridges it to UDP (port 9090 for the
first Ping1D): every datagram sent to it goes to the sonar, and what the sonar answers goes to
every client heard from. A driver written against :class:`uwcam.drivers.serial_link.SerialLink`
reads the bridged device through this class unchanged, so uwcam and BlueOS share one sonar.

The socket is connected to the peer, so only its datagrams are read and a peer that has gone
(nothing listens on the port any more) shows up as "connection refused" from the kernel.
Reads wait on the socket with the link's timeout; no sleep-polling.
"""

from __future__ import annotations

import select
import socket
import threading
import time

from uwcam.drivers.base import ConfigurationError, DeviceLost, HealthState, HealthTracker
from uwcam.drivers.serial_link import OpenBackoff

SCHEME = "udp:"


def parse_udp_address(text: str) -> tuple[str, int]:
    """``udp:HOST:PORT`` (``udp:[::1]:9090`` for IPv6) → (host, port); ConfigurationError otherwise."""
    host, sep, port = text.removeprefix(SCHEME).rpartition(":")
    host = host.strip("[]")
    if not text.startswith(SCHEME) or not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigurationError(f"'{text}' is not udp:HOST:PORT (e.g. udp:127.0.0.1:9090 for BlueOS's first Ping1D)")
    return host, int(port)


class UdpLink:
    """One UDP peer, (re)opened lazily; reads come from a buffer of received datagrams."""

    def __init__(self, address: str, timeout_s: float = 0.5, retry_s: tuple[float, float] = (0.1, 5.0)) -> None:
        self.port = address  # what error messages and status call the device
        self.host, self.udp_port = parse_udp_address(address)
        self.timeout_s = float(timeout_s)
        self.retry_s = retry_s
        self.health = HealthTracker()
        self.lock = threading.RLock()  # one transaction (command + reply) at a time
        self._sock: socket.socket | None = None
        self._buffer = bytearray()
        self._backoff = OpenBackoff(self.port, retry_s, self.health)

    def _address(self):
        try:
            return socket.getaddrinfo(self.host, self.udp_port, type=socket.SOCK_DGRAM)[0]
        except socket.gaierror as exc:
            raise ConfigurationError(f"cannot resolve {self.host} in {self.port}: {exc}; check the address") from None

    def check_exists(self) -> None:
        """ConfigurationError at start when the address cannot exist (an unknown host name)."""
        self._address()

    def _ensure_open(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        now = self._backoff.check()
        try:
            family, kind, proto, _, address = self._address()
            sock = socket.socket(family, kind, proto)
            sock.connect(address)
        except (OSError, ConfigurationError) as exc:
            raise self._backoff.failed(now, exc) from None
        self._sock = sock
        self._backoff.opened()
        return sock

    def fail(self, reason: str) -> None:
        """Close after a failure; the next use reopens (under the transaction lock, so never
        under another thread's transaction)."""
        with self.lock:
            self.health.set(HealthState.RECOVERING, reason)
            self._close_socket()

    def _close_socket(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._buffer.clear()

    def _lost(self, what: str, exc: OSError) -> DeviceLost:
        reason = (f"nothing answers at {self.port} (connection refused): is the bridge (BlueOS's ping service) running?"
                  if isinstance(exc, ConnectionRefusedError) else f"{what} {self.port} failed: {exc}")
        self.fail(reason)
        return DeviceLost(reason)

    def _receive(self, sock: socket.socket, wait_s: float) -> bool:
        """Append one datagram to the buffer if one arrives within ``wait_s``."""
        ready, _, _ = select.select([sock], [], [], wait_s)
        if not ready:
            return False
        try:
            self._buffer += sock.recv(65536)
        except OSError as exc:
            raise self._lost("read from", exc) from None
        return True

    def write(self, data: bytes) -> None:
        """Send ``data`` as one datagram, dropping what arrived before (each command waits for its own reply)."""
        sock = self._ensure_open()
        while self._receive(sock, 0.0):
            pass
        self._buffer.clear()
        try:
            sock.send(data)
        except OSError as exc:
            raise self._lost("write to", exc) from None

    def read(self, size: int) -> bytes:
        """Up to ``size`` bytes, waiting at most the link's timeout for a datagram (b"" on timeout)."""
        sock = self._ensure_open()
        if not self._buffer:
            self._receive(sock, self.timeout_s)
        out = bytes(self._buffer[:size])
        del self._buffer[:size]
        return out

    def read_until(self, terminator: bytes, limit: int = 512) -> bytes:
        """Bytes up to and including ``terminator``, or what came before the timeout."""
        sock = self._ensure_open()
        deadline = time.monotonic() + self.timeout_s
        while terminator not in self._buffer and len(self._buffer) < limit:
            if not self._receive(sock, max(0.0, deadline - time.monotonic())):
                break
        end = self._buffer.find(terminator)
        n = min(limit, len(self._buffer) if end < 0 else end + len(terminator))
        out = bytes(self._buffer[:n])
        del self._buffer[:n]
        return out

    def close(self) -> None:
        with self.lock:
            self._close_socket()
