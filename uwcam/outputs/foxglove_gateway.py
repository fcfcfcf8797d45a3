"""The Foxglove port: both WebSocket subprotocol names in front of the Foxglove SDK's server.

The SDK (foxglove-sdk 0.30) accepts only ``foxglove.sdk.v1``; Lichtblick and Foxglove before the
SDK ask for ``foxglove.websocket.v1``, the same protocol under its older name, and get HTTP 400.
This gateway listens on the configured port and passes every connection through to the SDK's
server (on an ephemeral loopback port), rewriting only the subprotocol name in the opening
handshake: the client's ``foxglove.websocket.v1`` goes upstream as ``foxglove.sdk.v1`` and the
server's answer comes back under the name the client asked for. ``Sec-WebSocket-Accept`` depends
on the key alone, so it stays valid; after the handshake the bytes are copied unchanged both
ways (extensions such as permessage-deflate are negotiated end to end).

It runs on an asyncio loop in a thread of its own, apart from the API's and the frame loop.
"""

from __future__ import annotations

import asyncio
import logging
import threading

log = logging.getLogger(__name__)

SDK_PROTOCOL = "foxglove.sdk.v1"
LEGACY_PROTOCOL = "foxglove.websocket.v1"
MAX_HEAD_BYTES = 16384
"""An opening handshake longer than this is refused (a browser's is under 2 kB)."""
HANDSHAKE_TIMEOUT_S = 10.0


def offered_protocols(head: bytes) -> list[str]:
    """The subprotocols a WebSocket opening request offers, in its order."""
    offered: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            offered += [p.strip() for p in value.decode("latin-1").split(",") if p.strip()]
    return offered


def rewrite_protocol(head: bytes, protocols: str) -> bytes:
    """``head`` (request or response, ending in a blank line) with every Sec-WebSocket-Protocol
    header replaced by one carrying ``protocols``."""
    lines = head.split(b"\r\n")
    kept = [line for line in lines[:-2] if line.partition(b":")[0].strip().lower() != b"sec-websocket-protocol"]
    return b"\r\n".join(kept + [b"Sec-WebSocket-Protocol: " + protocols.encode("latin-1"), b"", b""])


def upstream_request(head: bytes) -> tuple[bytes, str | None]:
    """The request to send to the SDK's server, and the legacy name to answer with (None: as is).
    A client offering the SDK's name keeps it; one offering only the legacy name is translated."""
    offered = offered_protocols(head)
    if SDK_PROTOCOL in offered or LEGACY_PROTOCOL not in offered:
        return head, None
    return rewrite_protocol(head, SDK_PROTOCOL), LEGACY_PROTOCOL


async def _read_head(reader: asyncio.StreamReader) -> bytes:
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT_S)
    if len(head) > MAX_HEAD_BYTES:
        raise ValueError("handshake too long")
    return head


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while data := await reader.read(1 << 16):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, asyncio.IncompleteReadError):
        pass
    finally:
        writer.close()


class FoxgloveGateway:
    """Listens on ``host:port`` (0: any free port) and passes connections to ``upstream_port``."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self.host, self.requested_port, self.upstream_port = host, port, upstream_port
        self.port: int | None = None
        self.clients = 0
        """Connections open now, whichever the protocol name."""
        self.by_protocol = {SDK_PROTOCOL: 0, LEGACY_PROTOCOL: 0}
        """Handshakes passed through since the start, by the name the client got."""
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.base_events.Server | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def start(self) -> None:
        """Bind (in the caller's thread's time: an error here is raised here) and serve."""
        self._thread = threading.Thread(target=self._run, name="foxglove-gateway", daemon=True)
        self._thread.start()
        self._started.wait(30.0)
        if self._error is not None:
            raise self._error
        if self.port is None:
            raise OSError(f"the Foxglove gateway did not start on {self.host}:{self.requested_port}")

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        self._loop = loop
        try:
            self._server = loop.run_until_complete(asyncio.start_server(self._handle, self.host, self.requested_port))
            self.port = self._server.sockets[0].getsockname()[1]
        except BaseException as exc:  # reported to start()
            self._error = exc
            loop.close()  # before start() hears of it: a stop() right after finds nothing left to stop
            self._started.set()
            return
        self._started.set()
        try:
            loop.run_forever()
        finally:
            self._server.close()
            tasks = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for task in tasks:
                task.cancel()
            loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            loop.run_until_complete(self._server.wait_closed())
            loop.close()

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None and thread.is_alive() and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(loop.stop)
            except RuntimeError:  # closed since: it never served (a failed bind), nothing to stop
                pass
        if thread is not None:
            thread.join(timeout=10.0)
        self._thread = None

    async def _handle(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        upstream_writer = None
        try:
            head = await _read_head(client_reader)
            request, answer_as = upstream_request(head)
            upstream_reader, upstream_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
            upstream_writer.write(request)
            await upstream_writer.drain()
            response = await _read_head(upstream_reader)
            upgraded = response.split(b"\r\n", 1)[0].split(b" ")[1:2] == [b"101"]
            if upgraded and answer_as is not None:
                response = rewrite_protocol(response, answer_as)
            client_writer.write(response)
            await client_writer.drain()
            if not upgraded:
                return
            got = answer_as or SDK_PROTOCOL
            with self._lock:
                self.clients += 1
                self.by_protocol[got] = self.by_protocol.get(got, 0) + 1
            try:
                await asyncio.gather(_pipe(client_reader, upstream_writer), _pipe(upstream_reader, client_writer))
            finally:
                with self._lock:
                    self.clients -= 1
        except (asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError,
                ConnectionError, OSError) as exc:
            log.debug("Foxglove connection closed during the handshake: %s", exc)
        finally:
            if upstream_writer is not None:
                upstream_writer.close()
            client_writer.close()

    def status(self) -> dict:
        with self._lock:
            return {"clients": self.clients, "connections_by_protocol": dict(self.by_protocol)}
