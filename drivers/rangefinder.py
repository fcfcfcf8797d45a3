"""Rangefinders on a serial line, read continuously in a background thread.

* ``ascii``: NMEA depth sentences ($--DPT, $--DBT, checksums verified) and the ``R####``
  millimetre lines of common ultrasonic rangers.
* ``ping1d``: the Blue Robotics Ping1D sonar, binary ping protocol (message encoding and
  parsing from ``bluerobotics-ping``; uwcam drives the port itself with blocking reads), on a
  serial port or bridged over UDP (``udp:HOST:PORT``, e.g. by BlueOS's ping service).

Every reading carries range (m), confidence (0–1 from the device's own figure, None where
the device gives none), monotonic and wall timestamps. Speed of sound is configurable
(fresh 1435 m/s, salt 1500 m/s): ASCII devices compute range with their own assumed speed,
which is rescaled; the Ping1D is told the speed. Readings outside [min, max] or below the
confidence threshold are rejected and counted; garbage and checksum errors are counted,
never fatal.
"""

from __future__ import annotations

import math
import re
import threading
import time
from dataclasses import dataclass
from typing import Annotated

from pydantic import Field

from uwcam.drivers.options import DriverOptions, Real, Whole
from uwcam.drivers.base import ConfigurationError, DeviceLost, Health, HealthState
from uwcam.drivers.serial_link import SerialLink
from uwcam.drivers.threads import StoppableThread
from uwcam.drivers.udp_link import SCHEME as UDP_SCHEME, UdpLink

FRESH_WATER = 1435.0
SALT_WATER = 1500.0


@dataclass(frozen=True)
class RangeReading:
    range_m: float
    confidence: float | None
    monotonic_ns: int
    wall_time: float

    @property
    def age_s(self) -> float:
        return (time.monotonic_ns() - self.monotonic_ns) / 1e9


@dataclass
class RangefinderStats:
    readings: int = 0
    rejected: int = 0
    """Valid messages outside the range limits or below the confidence threshold."""
    garbage: int = 0
    """Lines or packets that could not be parsed, or failed their checksum."""


@dataclass
class RangefinderConfig:
    speed_of_sound: float = SALT_WATER
    min_range_m: float = 0.1
    max_range_m: float = 100.0
    min_confidence: float = 0.0
    stale_after_s: float = 2.0
    lost_after_s: float = 10.0
    """Without a valid reading for this long the rangefinder counts as lost, not recovering."""

    def __post_init__(self) -> None:
        if not 1300 <= self.speed_of_sound <= 1700:
            raise ConfigurationError(f"speed of sound {self.speed_of_sound} m/s is not water's (fresh ~1435, salt ~1500)")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ConfigurationError(f"need 0 ≤ min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")
        if not 0 <= self.min_confidence <= 1:
            raise ConfigurationError(f"min_confidence must be 0–1, got {self.min_confidence}")
        if not (0 < self.stale_after_s < self.lost_after_s < float("inf")):
            raise ConfigurationError(f"need 0 < stale_after_s < lost_after_s, got {self.stale_after_s}, {self.lost_after_s}")


class SerialRangefinder:
    """Common part: thread, latest reading, health, limits. Subclasses implement ``_poll``."""

    kind = ""

    def __init__(self, port: str, baud: int, config: RangefinderConfig | None = None, timeout_s: float = 0.5,
                 link: SerialLink | UdpLink | None = None) -> None:
        self.config = config or RangefinderConfig()
        self.link = link or SerialLink(port, baud, timeout_s)
        self.stats = RangefinderStats()
        self._latest: RangeReading | None = None
        self._lock = threading.Lock()
        self._worker = StoppableThread(self._run, f"rangefinder-{self.kind}")
        self._last_good = time.monotonic()

    @property
    def health(self) -> Health:
        h = self.link.health.current
        latest = self.latest()
        silent_s = time.monotonic() - self._last_good
        if h.state in (HealthState.OK, HealthState.RECOVERING) and silent_s > self.config.lost_after_s:
            why = "no valid range" if h.state == HealthState.OK else h.reason
            return Health(HealthState.LOST, f"{why}; nothing valid for {silent_s:.1f} s")
        if h.state == HealthState.OK and (latest is None or latest.age_s > self.config.stale_after_s):
            return Health(HealthState.RECOVERING, f"no valid range for {silent_s:.1f} s")
        return h

    def latest(self) -> RangeReading | None:
        with self._lock:
            return self._latest

    def fresh(self) -> RangeReading | None:
        """The latest reading if younger than ``stale_after_s``, else None."""
        r = self.latest()
        return r if r is not None and r.age_s <= self.config.stale_after_s else None

    def _accept(self, range_m: float, confidence: float | None) -> None:
        c = self.config
        if not (c.min_range_m <= range_m <= c.max_range_m) or (confidence is not None and confidence < c.min_confidence):
            self.stats.rejected += 1
            return
        reading = RangeReading(range_m, confidence, time.monotonic_ns(), time.time())
        with self._lock:
            self._latest = reading
        self.stats.readings += 1
        self._last_good = time.monotonic()
        self.link.health.set(HealthState.OK, "reading")

    def start(self) -> None:
        self.link.check_exists()
        self._setup()
        self._worker.start()

    def _setup(self) -> None:
        """Configure the device (e.g. speed of sound); failures are retried by the thread."""

    def _run(self) -> None:
        configured = True
        while not self._worker.stopping.is_set():
            try:
                if not configured:
                    self._setup()
                    configured = True
                self._poll()
            except DeviceLost as exc:
                configured = False
                self.link.health.set(HealthState.RECOVERING, str(exc))
                self._worker.stopping.wait(self.link.timeout_s)
            except Exception as exc:  # never let a device kill the reader: report and retry
                configured = False
                self.link.fail(f"{type(exc).__name__}: {exc}")
                self._worker.stopping.wait(self.link.timeout_s)

    def _poll(self) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        self._worker.stop(timeout_s=5.0)
        self.link.close()
        self.link.health.set(HealthState.STOPPED, "stopped")

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


# An NMEA 0183 sentence: '$', a five-letter address (two-letter talker, three-letter type), the
# fields, '*' and exactly two hexadecimal checksum digits, nothing after them.
_NMEA = re.compile(r"\$(?P<body>(?P<talker>[A-Z]{2})(?P<type>[A-Z]{3})(?:,[^*$]*)?)\*(?P<checksum>[0-9A-Fa-f]{2})")


def nmea_checksum_ok(sentence: str) -> bool:
    """True for a well-formed sentence whose checksum (XOR of the characters between '$' and '*')
    matches its two hex digits; sentences without a checksum are refused."""
    m = _NMEA.fullmatch(sentence)
    if m is None:
        return False
    calc = 0
    for ch in m["body"]:
        calc ^= ord(ch)
    return calc == int(m["checksum"], 16)


def _finite(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def parse_ascii_range(line: str) -> float | None:
    """Range in metres at the device's own speed of sound, or None if the line is not a range
    (not a depth sentence, bad or missing checksum, empty or non-finite depth)."""
    line = line.strip()
    if line.startswith("R") and line[1:].isdigit() and line[1:].isascii():
        return int(line[1:]) / 1000.0
    m = _NMEA.fullmatch(line)
    if m is None or not nmea_checksum_ok(line):
        return None
    fields = m["body"].split(",")
    if m["type"] == "DPT" and len(fields) > 1:
        return _finite(fields[1])
    if m["type"] == "DBT" and len(fields) > 4 and fields[4] == "M":
        return _finite(fields[3])
    return None


class RangefinderOptions(DriverOptions):
    """What every serial rangefinder takes (:class:`RangefinderConfig`)."""

    speed_of_sound: Annotated[Real, Field(ge=1300, le=1700)] = SALT_WATER
    """Metres per second in the water dived in (fresh ~1435, salt ~1500)."""
    min_range_m: Annotated[Real, Field(ge=0, le=10000)] = 0.1
    max_range_m: Annotated[Real, Field(gt=0, le=10000)] = 100.0
    min_confidence: Annotated[Real, Field(ge=0, le=1)] = 0.0
    stale_after_s: Annotated[Real, Field(gt=0, le=3600)] = 2.0


class AsciiRangefinder(SerialRangefinder):
    """NMEA DPT/DBT or R#### (mm) lines."""

    kind = "ascii"

    class Options(RangefinderOptions):
        port: str
        baud: Annotated[Whole, Field(gt=0, le=10_000_000)] = 9600
        device_speed_of_sound: Annotated[Real, Field(ge=1300, le=1700)] = SALT_WATER
        """The speed of sound the device itself assumes; its ranges are rescaled to the water's."""

    def __init__(self, port: str, baud: int = 9600, device_speed_of_sound: float = SALT_WATER, **config) -> None:
        super().__init__(port, baud, RangefinderConfig(**config))
        self.device_speed_of_sound = float(device_speed_of_sound)

    def _poll(self) -> None:
        raw = self.link.read_until(b"\n")
        if not raw:
            return  # timeout: the thread goes on; health turns stale by itself
        line = raw.decode("ascii", errors="replace").replace("\r", "\n").strip()
        for part in filter(None, line.split("\n")):
            value = parse_ascii_range(part)
            if value is None:
                self.stats.garbage += 1
                continue
            self._accept(value * self.config.speed_of_sound / self.device_speed_of_sound, None)


class Ping1DRangefinder(SerialRangefinder):
    """Blue Robotics Ping1D: requests a distance message per poll.

    ``port``: a serial device, or ``udp:HOST:PORT`` for a Ping bridged over UDP (BlueOS's ping
    service serves its first Ping1D at udp:127.0.0.1:9090 on the vehicle). Through a bridge other
    clients' requests are answered to every client, so any message carrying a distance counts.
    """

    kind = "ping1d"

    class Options(RangefinderOptions):
        port: str
        baud: Annotated[Whole, Field(gt=0, le=10_000_000)] = 115200
        rate_hz: Annotated[Real, Field(gt=0, le=50)] = 10.0
        """Distance requests per second."""

    def __init__(self, port: str, baud: int = 115200, rate_hz: float = 10.0, **config) -> None:
        link = UdpLink(port) if port.startswith(UDP_SCHEME) else None
        super().__init__(port, baud, RangefinderConfig(**config), link=link)
        from brping import PingParser

        if not 0 < rate_hz <= 50:
            raise ConfigurationError(f"Ping1D poll rate must be 0–50 Hz, got {rate_hz}")
        self.period_s = 1.0 / rate_hz
        self._parser = PingParser()

    def _message(self, message_id: int, **fields) -> bytes:
        from brping import PingMessage

        msg = PingMessage(message_id)
        for name, value in fields.items():
            setattr(msg, name, value)
        msg.pack_msg_data()
        return bytes(msg.msg_data)

    def _setup(self) -> None:
        from brping import definitions

        with self.link.lock:
            self.link.write(self._message(definitions.PING1D_SET_SPEED_OF_SOUND, sos_mm_per_sec=int(self.config.speed_of_sound * 1000)))

    def _read_message(self):
        from brping import PingParser

        deadline = time.monotonic() + self.link.timeout_s
        while time.monotonic() < deadline:
            chunk = self.link.read(1)
            if not chunk:
                return None
            state = self._parser.parse_byte(chunk[0])
            if state == PingParser.NEW_MESSAGE:
                return self._parser.rx_msg
            if state == PingParser.ERROR:
                self.stats.garbage += 1
        return None

    def _poll(self) -> None:
        from brping import definitions

        with self.link.lock:
            self.link.write(self._message(definitions.COMMON_GENERAL_REQUEST, requested_id=definitions.PING1D_DISTANCE))
            msg = self._read_message()
        if msg is not None and msg.message_id in (definitions.PING1D_DISTANCE, definitions.PING1D_DISTANCE_SIMPLE,
                                                  definitions.PING1D_PROFILE):
            self._accept(msg.distance / 1000.0, msg.confidence / 100.0)
        self._worker.stopping.wait(self.period_s)
