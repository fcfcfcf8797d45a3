"""The serial lamp driver against a scripted peer on a pseudo-terminal: each command and the reply
it gets, written out (the pymeasure ``expected_protocol`` style), so the commands sent and the
replies parsed are checked exactly."""

from __future__ import annotations

import os
import select
import threading
import tty

import pytest

from uwcam.drivers.base import ConfigurationError, DeviceLost, DriverError, HealthState
from uwcam.drivers.lamp import LampStatus, SerialLamp


class ScriptedPeer:
    """Answers each complete command line with the next scripted reply (raw bytes)."""

    def __init__(self, replies: list[bytes]) -> None:
        self.replies = list(replies)
        self.commands: list[str] = []
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="scripted-lamp", daemon=True)

    def __enter__(self) -> "ScriptedPeer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        os.write(self._wake_w, b"x")
        self._thread.join(5.0)
        for fd in (self.master, self.slave, self._wake_r, self._wake_w):
            os.close(fd)

    def _run(self) -> None:
        buffer = b""
        while True:
            ready, _, _ = select.select([self.master, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            buffer += os.read(self.master, 1024)
            while b"\r\n" in buffer:
                line, buffer = buffer.split(b"\r\n", 1)
                self.commands.append(line.decode())
                if self.replies:
                    os.write(self.master, self.replies.pop(0))


def test_intensity_is_sent_as_a_whole_percent_and_checked_first():
    with ScriptedPeer([b"OK\r\n"] * 4) as peer:
        lamp = SerialLamp(peer.path)
        for percent in (0, 100, 37.4, 99.6):
            lamp.set_intensity(percent)
        assert peer.commands == ["PWM 0", "PWM 100", "PWM 37", "PWM 100"]
        for bad in (-0.001, 100.001, 250, float("nan"), float("inf"), float("-inf")):
            with pytest.raises(ConfigurationError, match="lamp intensity must be 0–100 %"):
                lamp.set_intensity(bad)
        assert len(peer.commands) == 4  # nothing sent for the refused ones
        lamp.close()


def test_last_status_follows_acknowledged_commands():
    with ScriptedPeer([b"OK\r\n"] * 4) as peer:
        lamp = SerialLamp(peer.path)
        assert lamp.last_status is None
        lamp.on()
        assert lamp.last_status == LampStatus(on=True, percent=100)  # full power until told otherwise
        lamp.set_intensity(40)
        assert lamp.last_status == LampStatus(on=True, percent=40)
        lamp.off()
        assert lamp.last_status == LampStatus(on=False, percent=40)
        lamp.on()
        assert lamp.last_status == LampStatus(on=True, percent=40)
        assert peer.commands == ["ON", "PWM 40", "OFF", "ON"]
        lamp.close()
    with ScriptedPeer([b"OK\r\n"]) as peer:
        lamp = SerialLamp(peer.path)
        lamp.set_intensity(15)
        assert lamp.last_status == LampStatus(on=False, percent=15)  # off until switched on
        lamp.close()


def test_status_replies_are_parsed_field_by_field():
    replies = [b"STATUS ON 55 T=31.5 FAULT=OVERHEAT\r\n", b"STATUS OFF 0\r\n", b"STATUS ON 100 T=-2\r\n"]
    with ScriptedPeer(replies) as peer:
        lamp = SerialLamp(peer.path)
        assert lamp.status() == LampStatus(on=True, percent=55, temperature_c=31.5, fault="OVERHEAT")
        assert lamp.health.state == HealthState.RECOVERING and "OVERHEAT" in lamp.health.reason
        assert lamp.status() == LampStatus(on=False, percent=0)
        assert lamp.last_status == LampStatus(on=False, percent=0)
        assert lamp.status() == LampStatus(on=True, percent=100, temperature_c=-2.0)
        assert peer.commands == ["STATUS?"] * 3
        lamp.close()


def test_one_bad_reply_is_retried_and_two_fail_the_command():
    with ScriptedPeer([b"OKAY\r\n", b"OK\r\n", b"NOPE\r\n", b"OK?\r\n", b"OK\r\n"]) as peer:
        lamp = SerialLamp(peer.path)
        lamp.on()  # one unexpected reply: sent again, fine
        assert peer.commands == ["ON", "ON"] and lamp.health.state == HealthState.OK
        with pytest.raises(DeviceLost, match=r"unexpected reply to 'OFF': 'OK\?'"):
            lamp.off()  # two in a row: given up after exactly two tries
        assert peer.commands == ["ON", "ON", "OFF", "OFF"]
        assert lamp.health.state == HealthState.RECOVERING
        assert lamp.last_status == LampStatus(on=True, percent=100)  # the failed switch is not remembered
        lamp.off()  # the lamp answers again
        assert lamp.last_status.on is False and lamp.health.state == HealthState.OK
        lamp.close()


def test_a_refusal_is_reported_at_once_and_a_silent_lamp_is_lost():
    with ScriptedPeer([b"ERR overtemperature\r\n", b"O"]) as peer:
        lamp = SerialLamp(peer.path)
        with pytest.raises(DriverError, match="lamp refused 'ON': overtemperature"):
            lamp.on()
        assert peer.commands == ["ON"]  # a refusal is an answer: not retried
        with pytest.raises(DeviceLost, match="no complete reply to 'OFF' within 0.5 s"):
            lamp.off()
        assert peer.commands == ["ON", "OFF", "OFF"]
        lamp.close()
