"""Reading the command line's arguments: numbers, boxes, channels and output paths checked before any work."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uwcam.fileio import UserInputError


DEFAULT_RGB = ["R", "G", "B"]


def parse_floats(text: str, what: str, count: int | None = None) -> list[float]:
    """'1,2,3' → [1.0, 2.0, 3.0]; UserInputError saying what was expected."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UserInputError(f"{what} must be comma-separated numbers, got '{text}'") from None
    if count is not None and len(values) != count:
        raise UserInputError(f"{what} needs {count} comma-separated numbers, got {len(values)} in '{text}'")
    if not all(np.isfinite(values)):
        raise UserInputError(f"{what} must be finite numbers, got '{text}'")
    return values


def parse_box(text: str, what: str) -> tuple[int, int, int, int]:
    values = parse_floats(text, what, 4)
    if any(v != int(v) for v in values) or values[2] <= 0 or values[3] <= 0 or values[0] < 0 or values[1] < 0:
        raise UserInputError(f"{what} must be X,Y,WIDTH,HEIGHT in whole pixels with positive size, got '{text}'")
    x, y, w, h = (int(v) for v in values)
    return x, y, w, h


def parse_channels(text: str | None, n: int) -> tuple[list[str], list[float | None]]:
    """--channels R:675,G:575,B:475 or R,G,B → names and optional wavelengths (nm)."""
    if text is None:
        names = DEFAULT_RGB if n == 3 else [f"ch{k}" for k in range(n)]
        return names, [None] * n
    names, wavelengths = [], []
    for item in text.split(","):
        name, _, nm = item.partition(":")
        names.append(name.strip())
        if nm:
            wl = parse_floats(nm, f"wavelength of channel {name}", 1)[0]
            if wl <= 0:
                raise UserInputError(f"wavelength of channel {name} must be positive nanometres, got {nm}")
            wavelengths.append(wl)
        else:
            wavelengths.append(None)
    if len(names) != n:
        raise UserInputError(f"--channels names {len(names)} channels but the images have {n}")
    if len(set(names)) != n or not all(names):
        raise UserInputError(f"--channels needs {n} different, non-empty names, got '{text}'")
    return names, wavelengths


def parse_per_channel(text: str | None, what: str, n: int) -> np.ndarray | None:
    """One number for every channel, or N comma-separated numbers."""
    if text is None:
        return None
    values = parse_floats(text, what)
    if len(values) not in (1, n):
        raise UserInputError(f"{what} takes one value or {n} comma-separated values (one per channel), got '{text}'")
    if any(v < 0 for v in values):
        raise UserInputError(f"{what} must not be negative, got '{text}'")
    return np.broadcast_to(np.array(values), (n,)).copy()


def checked_output(path: str | Path, suffixes: tuple[str, ...], wrong_suffix: str, flag: str | None = None) -> Path:
    """An output file's path, checked before any work is done: it ends in one of ``suffixes``
    (else UserInputError ``wrong_suffix`` with ``{path}`` filled in) and its folder exists."""
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise UserInputError(wrong_suffix.format(path=p))
    if not p.parent.exists():
        raise UserInputError(f"output folder {p.parent}{f' of {flag}' if flag else ''} does not exist")
    return p


def resolve_rig_path(text: str) -> Path:
    """A rig file path, or the name of a rig shipped with uwcam (e.g. grey-plate)."""
    from uwcam.calibration.rig import builtin_rig_path

    path = Path(text)
    if path.exists() or path.suffix in (".yaml", ".yml") or "/" in text:
        return path
    return builtin_rig_path(text)


MAX_EXPOSURE_US = 1e9
"""The longest exposure time a profile holds (µs)."""

MAX_GAIN_DB = 100.0
"""The largest analogue gain, either way, a profile holds (dB)."""


def parse_exposure(text: str | None, what: str, names: list[str], gain: bool = False) -> np.ndarray | None:
    """Per channel, in channel order: one value for every channel ('5000'), one per channel
    ('5000,4000,8000'), or every channel by name ('R=5000,G=4000,B=8000'); None where not given.
    Exposure times (``gain`` False) are microseconds, positive, at most :data:`MAX_EXPOSURE_US`;
    gains are decibels from −:data:`MAX_GAIN_DB` to :data:`MAX_GAIN_DB`. UserInputError names ``what``."""
    if text is None:
        return None
    items = [s.strip() for s in text.split(",")]
    if any("=" in s for s in items):
        given: dict[str, float] = {}
        for item in items:
            name, _, value = (s.strip() for s in item.partition("="))
            if name not in names or name in given:
                raise UserInputError(f"{what} takes NAME=VALUE once for each of the channels {','.join(names)}, "
                                     f"got '{text}'")
            given[name] = parse_floats(value, f"{what} of channel {name}", 1)[0]
        missing = [n for n in names if n not in given]
        if missing:
            raise UserInputError(f"{what} gives no value for channel(s) {','.join(missing)} in '{text}'")
        values = [given[n] for n in names]
    else:
        values = parse_floats(text, what)
        if len(values) not in (1, len(names)):
            raise UserInputError(f"{what} takes one value, {len(names)} comma-separated values or NAME=VALUE for the "
                                 f"channels {','.join(names)}, got '{text}'")
    out = np.broadcast_to(np.array(values, dtype=np.float64), (len(names),)).copy()
    if gain and np.any(np.abs(out) > MAX_GAIN_DB):
        raise UserInputError(f"{what} must be decibels from −{MAX_GAIN_DB:g} to {MAX_GAIN_DB:g}, got '{text}'")
    if not gain and (np.any(out <= 0) or np.any(out > MAX_EXPOSURE_US)):
        raise UserInputError(f"{what} must be positive microseconds, at most {MAX_EXPOSURE_US:g}, got '{text}'")
    return out
