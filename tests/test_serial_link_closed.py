"""A serial port closed under a call (a disconnect handled in another thread) is a lost device,
not an unexpected error: seen as a 500 from GET /api/v1/lamp in the fault-injection soak."""

from __future__ import annotations

import os
import termios

import pytest

from uwcam.drivers.base import DeviceLost, HealthState
from uwcam.drivers.serial_link import SerialLink


@pytest.fixture
def link():
    controller, device = os.openpty()  # a real pseudo-terminal for pyserial to open
    link = SerialLink(os.ttyname(device), timeout_s=0.1)
    yield link
    link.close()
    os.close(controller)
    os.close(device)


def test_a_port_closed_during_the_call_is_a_lost_device(link):
    def closed_midway(port):
        port.close()  # what the other thread does between pyserial's is_open check and its use of the fd
        termios.tcflush(port.fd, termios.TCIFLUSH)  # pyserial's reset_input_buffer, fd now None: TypeError

    with pytest.raises(DeviceLost, match="closed during the call"):
        link._io("write to", closed_midway)
    assert link.health.current.state == HealthState.RECOVERING
    link.write(b"again\r")  # reopened on the next use


def test_a_mistake_in_the_call_on_an_open_port_is_not_taken_for_a_lost_device(link):
    with pytest.raises(TypeError):
        link._io("write to", lambda port: port.write("text"))  # str, not bytes: a programming error
