"""The rangefinder's line parser against a table of real-world sentences.

Checksums are computed here by a naive XOR written apart from the driver, and that reference is
itself pinned by two sentences whose checksums are published (the classic GGA and RMC examples
of the NMEA 0183 literature), so a parser that compares only one nibble, or accepts sentences
without ``*hh``, cannot agree with it.
"""

from __future__ import annotations

import math
import os
import tty

import pytest

from tests.waiting import wait_for
from uwcam.drivers.rangefinder import AsciiRangefinder, nmea_checksum_ok, parse_ascii_range

# Published examples (e.g. "NMEA data" pages of gpsinformation.org): body and checksum.
GGA = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"
RMC = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"


def xor_checksum(body: str) -> int:
    """NMEA 0183 checksum: XOR of every character between '$' and '*'."""
    value = 0
    for ch in body:
        value ^= ord(ch)
    return value


def sentence(body: str, checksum: int | None = None) -> str:
    """``$body*HH`` with the right checksum, or with ``checksum`` given instead."""
    c = xor_checksum(body) if checksum is None else checksum
    return f"${body}*{c:02X}"


def test_the_reference_checksum_matches_published_sentences():
    for s in (GGA, RMC):
        body, given = s[1:].split("*")
        assert xor_checksum(body) == int(given, 16)


GOOD = [
    (sentence("SDDPT,12.5,0.0"), 12.5),
    (sentence("SDDPT,3.25,0.5,100.0"), 3.25),
    (sentence("SDDPT,4.5"), 4.5),  # a simple sounder that leaves out the offset  # NMEA 3.0 adds the maximum range field
    (sentence("IIDPT,0.75,-0.2"), 0.75),  # integrated-instrumentation talker, keel offset
    (sentence("SDDBT,41.0,f,12.50,M,6.8,F"), 12.5),
    (sentence("YXDBT,8.2,f,2.50,M,1.4,F"), 2.5),  # transducer talker
    (sentence("SDDBT,41.0,f,12.50,M"), 12.5),  # fathoms left out
    (sentence("SDDPT,12.5,0.0").lower().replace("$sddpt", "$SDDPT"), 12.5),  # lower-case hex digits
    ("R1234", 1.234),
    ("R0100", 0.1),
    ("  R2000\r", 2.0),  # line noise around a good reading
]


@pytest.mark.parametrize("line, metres", GOOD, ids=[g[0] for g in GOOD])
def test_good_sentences_give_their_range(line, metres):
    assert nmea_checksum_ok(line.strip()) or line.strip().startswith("R")
    assert parse_ascii_range(line) == pytest.approx(metres, abs=1e-12)


def _bad_checksums() -> list[str]:
    body = "SDDPT,12.5,0.0"
    right = xor_checksum(body)
    return [
        sentence(body, right ^ 0x10),  # high nibble wrong, low nibble right
        sentence(body, right ^ 0x80),
        sentence(body, right ^ 0x01),  # low nibble wrong
        sentence(body, right ^ 0xFF),
        sentence("SDDBT,41.0,f,12.50,M,6.8,F", xor_checksum("SDDBT,41.0,f,12.50,M,6.8,F") ^ 0x20),
        sentence("SDDPT,12.5,0.0")[:-2] + "G1",  # not hexadecimal
        sentence(body) + "7",  # three checksum digits
        sentence(body) + "XYZ",  # junk after the checksum
        "$" + "SDDPT,13.5,0.0" + sentence(body)[len(body) + 1:],  # one digit of the body changed
    ]


@pytest.mark.parametrize("line", _bad_checksums())
def test_bad_checksums_are_refused(line):
    assert not nmea_checksum_ok(line)
    assert parse_ascii_range(line) is None


MISSING = [
    "$SDDPT,12.5,0.0",
    "$SDDPT,12.5,0.0*",
    "$SDDBT,41.0,f,12.50,M,6.8,F",
    "SDDPT,12.5,0.0*" + f"{xor_checksum('SDDPT,12.5,0.0'):02X}",  # no '$'
]


@pytest.mark.parametrize("line", MISSING)
def test_sentences_without_a_checksum_are_refused(line):
    assert not nmea_checksum_ok(line)
    assert parse_ascii_range(line) is None


TRUNCATED = [
    sentence("SDDPT,12.5,0.0")[:-1],  # one checksum digit lost
    "$SDDPT,12.",
    "$SD",
    "$",
    "",
    sentence("SDDPT,"),  # checksummed, but the depth field is empty
    sentence("SDDPT"),
    sentence("SDDBT,41.0,f,12.50"),  # checksummed, the metres unit missing
    sentence("SDDBT,41.0,f,12.50,"),
    sentence("SDDBT,41.0,f,,M,6.8,F"),
    sentence("SDDBT,41.0,f,12.50,F,6.8,F"),  # the metres field is not in metres
    "R",
    "R12a4",
    "R-123",
    "r1234",
    "R\u0661\u0662\u0663",  # Arabic-Indic digits are digits to Python, not to a ranger
    "R\u06612",
    "RA123",
    "R 123",
]


@pytest.mark.parametrize("line", TRUNCATED)
def test_truncated_or_incomplete_sentences_give_no_range(line):
    assert parse_ascii_range(line) is None


FOREIGN = [
    GGA,  # a GPS on the same line: valid checksum, not a depth
    RMC,
    sentence("SDMTW,11.2,C"),  # the sounder's water temperature
    sentence("SDVHW,,T,,M,3.5,N,6.5,K"),
    sentence("DPT,12.5,0.0"),  # no talker: not a valid address
    sentence("XDPT,12.5,0.0"),
    sentence("SDXDPT,12.5,0.0"),  # six-character address
    sentence("SDDPT,nan,0.0"),  # well-formed, but not a finite number
    sentence("SDDPT,inf,0.0"),
    sentence("SDDBT,41.0,f,NaN,M,6.8,F"),
    sentence("SDDPT,1e999,0.0"),
    "hello",
    "\x00\xff\x13garbage\xfe",
]


@pytest.mark.parametrize("line", FOREIGN)
def test_foreign_or_meaningless_sentences_give_no_range(line):
    value = parse_ascii_range(line)
    assert value is None, value


def test_every_good_value_is_finite():
    for line, _ in GOOD:
        assert math.isfinite(parse_ascii_range(line))


class RecordingRangefinder(AsciiRangefinder):
    """The real driver, noting every value it is about to accept (in the driver's thread)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.values: list[float] = []

    def _accept(self, range_m: float, confidence: float | None) -> None:
        self.values.append(range_m)
        super()._accept(range_m, confidence)


def test_the_driver_counts_bad_lines_as_garbage_over_a_real_pty():
    """The whole read path on a pseudo-terminal: bad lines never become readings."""
    master, slave = os.openpty()
    tty.setraw(slave)
    rf = RecordingRangefinder(os.ttyname(slave), device_speed_of_sound=1500.0, speed_of_sound=1435.0, stale_after_s=60.0,
                              lost_after_s=120.0)
    scale = 1435.0 / 1500.0
    try:
        rf.start()

        def seen(metres: float) -> bool:
            latest = rf.latest()
            return latest is not None and latest.range_m == pytest.approx(metres * scale, abs=1e-9)

        # The driver opens the port lazily, and opening flushes what was sent before: repeat
        # the first line until it arrives, then send a distinct marker so that everything
        # before it is known to have been read.
        assert wait_for(lambda: os.write(master, b"R0400\r\n") > 0 and seen(0.4), 30.0)
        os.write(master, b"R0450\r\n")
        assert wait_for(lambda: seen(0.45))
        garbage, first = rf.stats.garbage, len(rf.values)
        bad = _bad_checksums() + MISSING + FOREIGN[:4]
        payload = "".join(f"{line}\r\n" for line in bad).encode("ascii")
        # A lone CR also ends a line: garbage and a reading may share one read.
        os.write(master, payload + b"garbage\r" + sentence("SDDPT,7.25,0.0").encode() + b"\r\n")
        assert wait_for(lambda: seen(7.25), 10.0)
        assert rf.values[first:] == [pytest.approx(7.25 * scale, abs=1e-9)]
        assert rf.stats.garbage == garbage + len(bad) + 1
    finally:
        rf.stop()
        os.close(master)
        os.close(slave)
