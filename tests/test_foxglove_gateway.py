"""The Foxglove gateway's handshake rewriting, on the bytes of real opening handshakes (RFC 6455 §1.2),
and its start and stop on a port that is taken."""

import asyncio
import socket
import time

import pytest

from uwcam.outputs.foxglove_gateway import (LEGACY_PROTOCOL, SDK_PROTOCOL, FoxgloveGateway, offered_protocols,
                                            rewrite_protocol, upstream_request)

LICHTBLICK = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
              b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n")
ACCEPTED = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nsec-websocket-protocol: foxglove.sdk.v1\r\n\r\n")


def test_a_legacy_client_is_translated_and_answered_under_its_own_name():
    request, answer_as = upstream_request(LICHTBLICK)
    assert answer_as == LEGACY_PROTOCOL and offered_protocols(request) == [SDK_PROTOCOL]
    assert request.count(b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n") == 1 and request.endswith(b"\r\n\r\n")
    answer = rewrite_protocol(ACCEPTED, answer_as)
    assert offered_protocols(answer) == [LEGACY_PROTOCOL]
    assert b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n" in answer and answer.startswith(b"HTTP/1.1 101 ")


def test_a_client_offering_the_sdk_name_or_none_passes_unchanged():
    both = LICHTBLICK.replace(b"foxglove.websocket.v1", b"foxglove.websocket.v1, foxglove.sdk.v1")
    assert upstream_request(both) == (both, None)
    plain = LICHTBLICK.replace(b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n", b"")
    assert upstream_request(plain) == (plain, None) and offered_protocols(plain) == []


def test_a_port_that_is_taken_fails_the_start_and_the_stop_after_it_is_quiet(monkeypatch):
    """The daemon stops everything it started when an output cannot start: the gateway's stop right
    after its failed start must neither raise nor leave its thread. Its thread used to report the
    failure before closing its loop, so a stop in between met a loop closed under it ("Event loop
    is closed", seen in CI under load, which hid the message about the port and left the devices'
    threads running). Here the loop lingers after closing, as a loaded machine makes it."""
    real_new_loop = asyncio.new_event_loop

    def lingering_loop():
        loop = real_new_loop()
        close = loop.close

        def close_then_linger():
            close()
            time.sleep(0.3)

        loop.close = close_then_linger
        return loop

    monkeypatch.setattr(asyncio, "new_event_loop", lingering_loop)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        gateway = FoxgloveGateway("127.0.0.1", taken.getsockname()[1], upstream_port=1)
        thread_started = []
        with pytest.raises(OSError):
            try:
                gateway.start()
            finally:
                thread_started.append(gateway._thread)
        time.sleep(0.1)  # the loop is closed by now; its thread may still be lingering
        gateway.stop()
        assert not thread_started[0].is_alive()
