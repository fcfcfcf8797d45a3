"""The Foxglove gateway's handshake rewriting, on the bytes of real opening handshakes (RFC 6455 §1.2)."""

from uwcam.outputs.foxglove_gateway import (LEGACY_PROTOCOL, SDK_PROTOCOL, offered_protocols, rewrite_protocol,
                                            upstream_request)

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
