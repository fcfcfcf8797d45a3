"""A serial port closed under a call (a disconnect handled in another thread) is a lost device,
not an unexpected error: seen as a 500 from GET /api/v1/lamp in the fault-injection soak."""

from __future__ import annotations

import os
import socket
import termios
import threading

import pytest

from uwcam.drivers.base import DeviceLost, HealthState
from uwcam.drivers.lamp import SerialLamp
from uwcam.drivers.serial_link import SerialLink
from uwcam.drivers.udp_link import UdpLink


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


def test_a_port_whose_descriptor_went_before_its_open_flag_is_a_lost_device(link):
    """pyserial's close() clears ``fd`` before ``is_open``: a call in that window sees an open port
    with no descriptor (CI seed of stop 38: TypeError from tcflush, a reset connection on GET /lamp)."""
    def closing_midway(port):
        os.close(port.fd)
        port.fd = None  # the first half of Serial.close(), as another thread would leave it
        assert port.is_open
        termios.tcflush(port.fd, termios.TCIFLUSH)

    with pytest.raises(DeviceLost, match="closed during the call"):
        link._io("write to", closing_midway)
    assert link.health.current.state == HealthState.RECOVERING
    link.write(b"again\r")


def _closes_only_after_the_transaction(link, port_of) -> None:
    holding, release = threading.Event(), threading.Event()

    def transaction():
        with link.lock:
            holding.set()
            release.wait(5.0)

    owner = threading.Thread(target=transaction)
    owner.start()
    assert holding.wait(5.0)
    opened = port_of(link)
    failer = threading.Thread(target=link.fail, args=("seen by another caller",))
    failer.start()
    failer.join(0.3)
    still_open = failer.is_alive() and port_of(link) is opened
    release.set()
    owner.join(5.0)
    failer.join(5.0)
    assert still_open, "fail() closed the port under another thread's transaction"
    assert port_of(link) is None and not failer.is_alive()


def test_a_failure_in_one_thread_waits_for_the_transaction_of_another(link):
    link.write(b"open\r")
    _closes_only_after_the_transaction(link, lambda l: l._serial)


def test_a_udp_failure_in_one_thread_waits_for_the_transaction_of_another():
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    udp = UdpLink(f"udp:127.0.0.1:{peer.getsockname()[1]}", timeout_s=0.1)
    try:
        udp.write(b"open\r")
        _closes_only_after_the_transaction(udp, lambda l: l._sock)
    finally:
        udp.close()
        peer.close()


def test_the_lamp_closes_its_port_inside_its_own_transaction():
    """A lamp that gives up on a reply closes the port while it still holds the link's lock."""
    controller, device = os.openpty()
    lamp = SerialLamp(os.ttyname(device))
    lamp.link.timeout_s = 0.05
    held_when_failing = []
    original = lamp.link.fail
    lamp.link.fail = lambda reason: (held_when_failing.append(lamp.link.lock._is_owned()), original(reason))
    try:
        with pytest.raises(DeviceLost, match="no complete reply"):
            lamp.status()  # nobody answers on the pty
        assert held_when_failing == [True]
    finally:
        lamp.close()
        os.close(controller)
        os.close(device)
