"""How much of what we sent a WebSocket client has not taken yet: so that a slow client gets the
newest frame, never a queue of old ones.

Frames waiting in the kernel's send buffer reach a slow client seconds or minutes late. Before
each message the stream asks the kernel how many bytes of the connection are still unsent or
unacknowledged (``SIOCOUTQ``); while any are, the client has not taken the last message and
newer frames are skipped, not queued.

The connection's socket is found by :class:`ConnectionSocket`, the outermost middleware, which
sees the server's own ``send`` (uvicorn's protocol object, whose transport holds the socket) and
records the socket in the scope. Servers that hide it leave ``None``: the stream then only
avoids queueing in the process itself (one send in flight per client).
"""

from __future__ import annotations

import fcntl
import math
import socket
import struct
import termios

from starlette.types import ASGIApp, Receive, Scope, Send

SCOPE_KEY = "uwcam.socket"


class ConnectionSocket:
    """Puts the WebSocket connection's socket (or None) into ``scope["uwcam.socket"]``."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            transport = getattr(getattr(send, "__self__", None), "transport", None)
            sock = transport.get_extra_info("socket") if transport is not None else None
            scope[SCOPE_KEY] = (transport, sock) if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6) else None
        await self.app(scope, receive, send)


def unsent_bytes(connection: tuple | None) -> int | None:
    """Bytes written to the connection that the peer has not acknowledged yet (our buffer plus
    the kernel's); None when unknown."""
    if connection is None:
        return None
    transport, sock = connection
    try:
        kernel = struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0"))[0]  # SIOCOUTQ
    except (OSError, ValueError):
        return None
    return kernel + transport.get_write_buffer_size()


class Pace:
    """The rate (Hz) at which a client is sent range maps, learnt from how fast it takes them.

    Skipping frames while the last message is unsent bounds what waits on our side, but not what
    waits on the client's: its kernel acknowledges whatever fits its receive buffer (megabytes)
    whether or not the client reads, so a client that reads every few seconds would find its
    buffer filled with the frames of the first part of the interval, and the newest it takes
    would be seconds old. So the rate follows the client's: a message not taken within
    ``STALL_S`` (the client's buffers were full) sets the rate to ``BACK_OFF`` times the maps it
    took since the last such stall, spread over that time; while messages are taken at once the
    rate grows by ``GROWTH_PER_S`` of itself plus ``STEP_HZ_PER_S`` a second, up to the rate the
    client asked for. Growth is slow so that the rate outgrows a slow reader's by little before
    the next stall: its buffers then fill only shortly before it reads, and the newest map it
    finds is still young. A client that
    reads at any pace then finds maps spread over the time since it last read, the newest fresh.
    A client on a link too slow for one map in ``STALL_S`` is sent ``BACK_OFF`` of what it takes.
    """

    STALL_S = 1.0
    """A message not taken within this time (s) means the client's buffers are full."""
    BACK_OFF = 0.75
    GROWTH_PER_S = 0.02
    STEP_HZ_PER_S = 0.02
    LEAST_HZ = 0.1

    def __init__(self, most_hz: float, now_s: float) -> None:
        self.most_hz = most_hz
        self.hz = most_hz
        self._since_s = self._last_s = now_s  # the last stall's end; the last message taken (monotonic s)
        self._maps = 0  # maps sent since the last stall

    @property
    def period_s(self) -> float:
        return 1.0 / self.hz

    def sent_map(self) -> None:
        self._maps += 1

    def taken(self, delay_s: float, now_s: float) -> None:
        """The last message was taken by the client ``delay_s`` after it was sent, at ``now_s``."""
        if delay_s > self.STALL_S:
            took_hz = self._maps / max(now_s - self._since_s, 1e-3)
            self.hz = min(max(self.BACK_OFF * took_hz, min(self.LEAST_HZ, self.most_hz)), self.most_hz)
            self._since_s, self._maps = now_s, 0
        else:
            dt_s = now_s - self._last_s
            self.hz = min(self.hz * math.exp(self.GROWTH_PER_S * dt_s) + self.STEP_HZ_PER_S * dt_s, self.most_hz)
        self._last_s = now_s
