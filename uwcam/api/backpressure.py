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
