"""Reason codes are a file format (reason maps saved by `uwcam range`, recorded, served by the
API): each code means what the documentation's table says."""

from __future__ import annotations

import re
from pathlib import Path

from uwcam.optics import Reason

DOCS = Path(__file__).resolve().parent.parent / "docs" / "recording.md"


def test_every_reason_code_is_the_documented_one():
    row = next(line for line in DOCS.read_text().splitlines() if line.startswith("| `/uwcam/reasons`"))
    documented = dict(re.findall(r"(\d) ([a-z ]+?)(?=,| \|)", row))
    assert sorted(int(code) for code in documented) == sorted(int(r) for r in Reason)
    for code, words in documented.items():
        name = Reason(int(code)).name.lower().replace("_", " ")
        assert name in words, (code, name, words)
