"""Simulated serial devices that speak the real protocols on a pseudo-terminal.

Each device owns a pty pair and exposes a stable path (a symlink, as udev gives real
devices) that the real serial drivers open; so the simulated default and the tests run the
same serial code as a rig. Faults can be injected: garbage bytes, a truncated reply, a
disconnect (the pty closes, the path dangles) and a reconnect (a new pty behind the same
path). Devices read the shared :class:`uwcam.drivers.sim.SimulatedRig`.
"""

from __future__ import annotations

import logging
import math
import os
import select
import tempfile
import termios
import threading
import time
import tty
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from uwcam.drivers.threads import SelectThread
from uwcam.drivers.sim import SimulatedRig

log = logging.getLogger(__name__)


FOLDER_PREFIX = "uwcam-pty-"
"""Then the owning process's id and a random part: a folder whose owner is gone (killed, so it
could not clean up) is removed by the next simulated device that starts."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_stale_folders(folder: str | None = None, min_age_s: float = 60.0) -> list[str]:
    """Remove the pty folders that simulated devices of dead processes left in the temporary
    folder (a process killed with SIGKILL cannot remove its own); returns what was removed. A
    folder is stale when its owner's process is gone, or, for folders without an owner in their
    name, when it holds nothing but links to ptys that no longer exist and is ``min_age_s`` old."""
    import time

    removed = []
    for path in Path(folder or tempfile.gettempdir()).glob(f"{FOLDER_PREFIX}*"):
        try:
            owner = path.name[len(FOLDER_PREFIX):].split("-", 1)[0]
            entries = list(path.iterdir())
            if owner.isdigit():
                stale = int(owner) != os.getpid() and not _alive(int(owner))
            else:
                stale = time.time() - path.stat().st_mtime > min_age_s and all(
                    e.is_symlink() and not e.exists() for e in entries)
            if not stale or any(not e.is_symlink() for e in entries):
                continue  # not ours to judge, or something else was put there: leave it
            for e in entries:
                e.unlink()
            path.rmdir()
            removed.append(str(path))
        except OSError:  # another process removed it meanwhile, or it is not ours
            continue
    return removed


class PtyDevice:
    """A device on the master side of a pty, serving the slave side at ``path``."""

    name = "device"

    def __init__(self, rig: SimulatedRig | None = None, folder: str | None = None) -> None:
        self.rig = rig or SimulatedRig()
        self._own_folder = folder is None  # made here, so removed here when the device stops
        if folder is None:
            remove_stale_folders()
        self._folder = Path(folder or tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{os.getpid()}-"))
        self.path = str(self._folder / self.name)
        self._lock = threading.Lock()
        self._loop = SelectThread(self._run, f"pty-{self.name}")
        self._wake_r, self._wake_w = os.pipe()  # wakes the loop when the pty is replaced
        self._master: int | None = None
        self._slave: int | None = None
        self._truncate_next = False

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> "PtyDevice":
        self._plug()
        self._loop.start()
        return self

    def stop(self) -> None:
        self._loop.stop()
        self._unplug()
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        if self._own_folder:
            try:
                self._folder.rmdir()
            except OSError:  # something else was put there: leave it
                pass

    def __enter__(self) -> "PtyDevice":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        with self._lock:
            self._master, self._slave = master, slave
        tmp = self.path + ".new"
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.path)
        os.write(self._wake_w, b"p")

    def _unplug(self) -> None:
        with self._lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None
        os.write(self._wake_w, b"u")

    # -- fault injection ---------------------------------------------------------------
    def disconnect(self) -> None:
        """The device vanishes: the pty closes and the path points nowhere."""
        self._unplug()

    def reconnect(self) -> None:
        """The device returns on a new pty behind the same path."""
        self._plug()

    def send_garbage(self, data: bytes = b"\x00\xff\x13garbage\xfe\r\n") -> None:
        self.send(data)

    def truncate_next_reply(self) -> None:
        self._truncate_next = True

    # -- I/O -----------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        if self._truncate_next and len(data) > 2:
            self._truncate_next = False
            data = data[: len(data) // 2]
        with self._lock:
            if self._master is not None:
                try:
                    os.write(self._master, data)
                except OSError:
                    pass

    def _run(self) -> None:
        while True:
            with self._lock:
                master = self._master
            fds = [self._loop.stop_fd, self._wake_r] + ([master] if master is not None else [])
            try:
                ready, _, _ = select.select(fds, [], [], self.tick_s())
            except OSError:  # disconnect() closed the pty while we waited on it: look again
                continue
            if self._loop.stop_fd in ready:
                return
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
                continue
            if master is not None and master in ready:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = b""
                if data:
                    self.received(data)
            self.tick()

    def tick_s(self) -> float | None:
        """How long to wait for input before calling :meth:`tick` (None: only on input)."""
        return None

    def tick(self) -> None:
        """Called after input or a tick interval; streaming devices send here."""

    def received(self, data: bytes) -> None:
        """Handle bytes from the host."""


class SimulatedLampDevice(PtyDevice):
    """Speaks drivers/lamp_protocols/generic-dimmable-led.yaml and drives the rig's lamp."""

    name = "lamp"

    def __init__(self, rig: SimulatedRig | None = None, folder: str | None = None, temperature_c: float = 21.5) -> None:
        super().__init__(rig, folder)
        self._buffer = b""
        self.temperature_c = temperature_c
        self.fault: str | None = None
        self.percent = 100

    def received(self, data: bytes) -> None:
        self._buffer += data
        while b"\r\n" in self._buffer:
            line, self._buffer = self._buffer.split(b"\r\n", 1)
            self.send(self.answer(line.decode(errors="replace").strip()).encode() + b"\r\n")

    def answer(self, command: str) -> str:
        rig = self.rig
        if command in ("ON", "OFF"):
            if command == "ON":
                rig.set_lamp(on=True, intensity=self.percent / 100)
            else:
                rig.set_lamp(on=False)
            # The device's own word, as a real lamp's indicator would show it.
            log.info("simulated lamp: %s", command)
            return "OK"
        if command.startswith("PWM "):
            try:
                value = int(command[4:])
            except ValueError:
                return "ERR bad number"
            if not 0 <= value <= 100:
                return "ERR out of range"
            self.percent = value
            rig.set_lamp(intensity=value / 100)
            return "OK"
        if command == "STATUS?":
            fault = f" FAULT={self.fault}" if self.fault else ""
            return f"STATUS {'ON' if rig.lamp_on else 'OFF'} {self.percent} T={self.temperature_c:.1f}{fault}"
        return "ERR unknown command"


class SimulatedAsciiRanger(PtyDevice):
    """Streams the rig's true range as NMEA $SDDPT sentences or R#### lines at ``rate_hz``."""

    name = "ranger"

    def __init__(self, rig: SimulatedRig | None = None, folder: str | None = None, style: str = "nmea",
                 rate_hz: float = 10.0, speed_of_sound: float = 1500.0, water_speed_of_sound: float = 1500.0) -> None:
        super().__init__(rig, folder)
        if style not in ("nmea", "mm"):
            raise ValueError("style must be 'nmea' or 'mm'")
        self.style, self.period = style, 1.0 / rate_hz
        # The device assumes ``speed_of_sound``; the water has ``water_speed_of_sound``.
        self.scale = speed_of_sound / water_speed_of_sound
        self._next = time.monotonic()
        self.silent = False

    def tick_s(self) -> float:
        return max(0.0, self._next - time.monotonic())

    def tick(self) -> None:
        if time.monotonic() < self._next:
            return
        self._next += self.period
        if self.silent:
            return
        reported = self.rig.true_range() * self.scale
        if not math.isfinite(reported):  # nothing in range (open water): a sounder sends no depth
            return
        if self.style == "mm":
            self.send(f"R{int(round(reported * 1000)):04d}\r".encode())
        else:
            body = f"SDDPT,{reported:.3f},0.0"
            checksum = 0
            for ch in body:
                checksum ^= ord(ch)
            self.send(f"${body}*{checksum:02X}\r\n".encode())


class SimulatedPing1D(PtyDevice):
    """Answers ping-protocol requests for distance like a Ping1D, from the rig's true range."""

    name = "ping1d"

    def __init__(self, rig: SimulatedRig | None = None, folder: str | None = None, confidence: int = 97,
                 water_speed_of_sound: float = 1500.0) -> None:
        super().__init__(rig, folder)
        from brping import PingParser

        self._parser = PingParser()
        self.confidence = confidence
        self.water_speed_of_sound = water_speed_of_sound
        self.speed_of_sound = 1500.0  # the device's own setting until told otherwise
        self.ping_number = 0

    def received(self, data: bytes) -> None:
        from brping import PingMessage, PingParser, definitions

        for byte in data:
            if self._parser.parse_byte(byte) != PingParser.NEW_MESSAGE:
                continue
            msg = self._parser.rx_msg
            if msg.message_id == definitions.PING1D_SET_SPEED_OF_SOUND:
                self.speed_of_sound = msg.sos_mm_per_sec / 1000.0
            elif msg.message_id == definitions.COMMON_GENERAL_REQUEST and msg.requested_id == definitions.PING1D_DISTANCE:
                self.ping_number += 1
                echo_time = 2 * self.rig.true_range() / self.water_speed_of_sound
                reply = PingMessage(definitions.PING1D_DISTANCE)
                # Nothing in range (open water): no echo, which a Ping1D reports as confidence 0.
                found = math.isfinite(echo_time)
                reply.distance = int(round(echo_time * self.speed_of_sound / 2 * 1000)) if found else 0
                reply.confidence = self.confidence if found else 0
                reply.transmit_duration = 100
                reply.ping_number = self.ping_number
                reply.scan_start = 0
                reply.scan_length = 30000
                reply.gain_setting = 3
                reply.pack_msg_data()
                self.send(bytes(reply.msg_data))


# Registry entries: the real serial drivers, each talking to its own simulated device.
def _options():
    from uwcam.drivers import options

    return options


def _serial_classes():
    from uwcam.drivers.lamp import SerialLamp
    from uwcam.drivers.rangefinder import AsciiRangefinder, Ping1DRangefinder

    return SerialLamp, AsciiRangefinder, Ping1DRangefinder


class SimulatedSerialLamp(_serial_classes()[0]):
    """Registry name ``sim``: the serial lamp driver talking to a simulated lamp on a pty."""

    kind = "sim"

    class Options(_options().DriverOptions):
        protocol: str = "generic-dimmable-led"

    def __init__(self, rig: SimulatedRig | None = None, protocol: str = "generic-dimmable-led") -> None:
        self.device = SimulatedLampDevice(rig).start()
        super().__init__(self.device.path, protocol)

    def close(self) -> None:
        super().close()
        self.device.stop()


class _OwnsDevice:
    """Starts the simulated device before the driver, stops it after."""

    device: PtyDevice

    def start(self) -> None:
        self.device.start()
        super().start()  # type: ignore[misc]

    def stop(self) -> None:
        super().stop()  # type: ignore[misc]
        self.device.stop()


class SimulatedAsciiRangefinder(_OwnsDevice, _serial_classes()[1]):
    """Registry name ``sim-ascii``: the ASCII rangefinder driver reading a simulated ranger."""

    kind = "sim-ascii"

    class Options(_serial_classes()[1].Options):
        port: None = None  # the simulated ranger's own pty
        style: Literal["nmea", "mm"] = "nmea"
        rate_hz: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = 10.0

    def __init__(self, rig: SimulatedRig | None = None, style: str = "nmea", rate_hz: float = 10.0, **config) -> None:
        self.device = SimulatedAsciiRanger(rig, style=style, rate_hz=rate_hz)
        super().__init__(self.device.path, **config)


class SimulatedPing1DRangefinder(_OwnsDevice, _serial_classes()[2]):
    """Registry name ``sim-ping1d``: the Ping1D driver talking to a simulated Ping1D."""

    kind = "sim-ping1d"

    class Options(_serial_classes()[2].Options):
        port: None = None  # the simulated sonar's own pty
        confidence: Annotated[int, Field(ge=0, le=100)] = 97
        """Confidence (percent) the simulated sonar reports."""

    def __init__(self, rig: SimulatedRig | None = None, confidence: int = 97, **config) -> None:
        self.device = SimulatedPing1D(rig, confidence=confidence)
        super().__init__(self.device.path, **config)
