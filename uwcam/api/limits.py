"""Request bodies have a size limit, enforced while they stream in.

A pure ASGI middleware: a declared ``Content-Length`` over the limit is refused before a byte of
the body is read, and a chunked body is counted as it arrives and refused (413) the moment it
passes the limit, so an endless upload costs the daemon at most one limit's worth of memory.
"""

from __future__ import annotations

import json

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

DEFAULT_BODY_LIMIT = 64 * 1024
"""Bytes: JSON commands and settings are a few hundred bytes."""


def too_large(limit: int, hint: str = "send less") -> str:
    return f"request body larger than {limit} bytes; {hint}"


class BodyLimit:
    """Caps every HTTP request body: ``limits`` maps path prefixes to their own limit (bytes), or
    to their limit and what the 413 tells the client to do instead."""

    def __init__(self, app: ASGIApp, default: int = DEFAULT_BODY_LIMIT,
                 limits: dict[str, int | tuple[int, str]] | None = None) -> None:
        self.app = app
        self.default = default
        self.limits = sorted(((prefix, rule if isinstance(rule, tuple) else (rule, "send less"))
                              for prefix, rule in (limits or {}).items()), key=lambda item: -len(item[0]))  # longest first

    def rule_for(self, path: str) -> tuple[int, str]:
        return next((rule for prefix, rule in self.limits if path.startswith(prefix)), (self.default, "send less"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit, hint = self.rule_for(scope["path"])
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:
            try:
                declared_size = int(declared)
            except ValueError:
                declared_size = -1
            if declared_size < 0 or declared_size > limit:
                status = 413 if declared_size > limit else 400
                detail = too_large(limit, hint) if status == 413 else "Content-Length is not a byte count"
                await _respond(send, status, detail)
                return
        received = 0

        async def limited() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    # Raised inside the route's body read; FastAPI passes HTTPExceptions through.
                    raise HTTPException(status_code=413, detail=too_large(limit, hint))
            return message

        await self.app(scope, limited, send)


async def _respond(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
