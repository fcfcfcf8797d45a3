"""What the API's routers share: the daemon and the newest published frame."""

from __future__ import annotations

import asyncio

from fastapi import HTTPException, Request
from starlette.requests import HTTPConnection

from uwcam.runtime.daemon import Daemon
from uwcam.runtime.published import Published


def get_daemon(conn: HTTPConnection) -> Daemon:
    return conn.app.state.daemon


def latest(d: Daemon) -> Published:
    """The newest processed frame; 503 before the first."""
    published = d.pipeline.latest if d.pipeline else None
    if published is None:
        raise HTTPException(status_code=503, detail="no frame processed yet; see /api/v1/status")
    return published


class Broadcaster:
    """Newest published frame, handed from the loop's thread to the event loop without blocking.

    Each client waits on an event of its own (:meth:`listen`), so that one client clearing its
    event never hides a new frame from another."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.latest: Published | None = None
        self.changed = asyncio.Event()
        self._listeners: set[asyncio.Event] = {self.changed}

    def listen(self) -> asyncio.Event:
        event = asyncio.Event()
        self._listeners.add(event)
        return event

    def forget(self, event: asyncio.Event) -> None:
        self._listeners.discard(event)

    def _notify(self) -> None:
        for event in self._listeners:
            event.set()

    def publish(self, published: Published) -> None:  # called in the processing thread
        self.latest = published
        self.loop.call_soon_threadsafe(self._notify)


__all__ = ["Broadcaster", "Request", "get_daemon", "latest"]
