"""The MAVLink output's serial transport on a real pseudo-terminal: bytes go both ways, and
closing is safe to repeat and safe after the other end has gone."""

from __future__ import annotations

import os
import select

import pytest

from uwcam.config import MavlinkConfig
from uwcam.outputs.mavlink_links import LinkDown, open_transport


def read_within(fd: int, size: int, timeout_s: float = 5.0) -> bytes:
    """Up to ``size`` bytes from ``fd``, waiting at most ``timeout_s`` for them to arrive."""
    ready, _, _ = select.select([fd], [], [], timeout_s)
    return os.read(fd, size) if ready else b""


def test_the_serial_transport_carries_bytes_both_ways_and_closes_quietly():
    controller, device = os.openpty()  # the autopilot's end, and the device uwcam opens by path
    try:
        link = open_transport(MavlinkConfig(connection=os.ttyname(device), baud=57600))
        link.open()
        link.send(b"\xfd\x09heartbeat")
        assert read_within(controller, 64) == b"\xfd\x09heartbeat"
        os.write(controller, b"\xfe\x02ok")
        assert select.select([link.port.fileno()], [], [], 5.0)[0], "the reply never reached the port"
        assert link.receive() == b"\xfe\x02ok"
        link.close()
        assert link.port is None
        link.close()  # nothing left to close: no error
    finally:
        os.close(controller)
        os.close(device)


def test_a_vanished_device_is_a_link_down_and_still_closes():
    controller, device = os.openpty()
    path = os.ttyname(device)
    link = open_transport(MavlinkConfig(connection=path, baud=57600))
    link.open()
    os.close(controller)  # the other end goes: reads fail
    os.close(device)
    with pytest.raises(LinkDown, match=f"reading from {path} failed"):
        link.receive()
    link.close()  # best effort, never an error
    assert link.port is None
