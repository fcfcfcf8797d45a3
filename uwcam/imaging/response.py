"""Camera response curves: from a gamma-encoded camera's codes back to linear light.

uwcam's physics needs values proportional to the light on the sensor. A scientific camera gives
them; an ordinary one (USB, 8-bit, MJPEG/H.264) sends codes through a tone curve, often sRGB or
Rec. 709, which turns every intensity ratio into the wrong one. A response curve maps each code
back to linear light, per channel, as a table over every code ("linear DN": scaled so the top
code stays the top value, so saturation levels and noise in DN keep their meaning).

Curves come from a standard (``srgb``, ``rec709``: IEC 61966-2-1 and ITU-R BT.709 transfer
functions) or are recovered from frames of a still scene at several known exposures
(``uwcam response``: OpenCV's Debevec or Robertson calibration).

Linearising widens the codes unevenly: near the top of an sRGB curve one code spans ~2.3 linear
DN, near the bottom ~0.08. :meth:`ResponseCurve.quantisation_variance` gives each linear value
the variance of the code it came from (width²/12), which ranging uses as the least variance a
value can have.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError

STANDARDS = ("srgb", "rec709")


def srgb_to_linear(v: ArrayLike) -> NDArray[np.float64]:
    """IEC 61966-2-1 inverse transfer function: encoded value in [0, 1] → linear light in [0, 1]."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: ArrayLike) -> NDArray[np.float64]:
    """IEC 61966-2-1 transfer function: linear light in [0, 1] → encoded value in [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def rec709_to_linear(v: ArrayLike) -> NDArray[np.float64]:
    """ITU-R BT.709 inverse OETF: encoded value in [0, 1] → linear light in [0, 1]."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v < 0.081, v / 4.5, ((v + 0.099) / 1.099) ** (1 / 0.45))


def linear_to_rec709(x: ArrayLike) -> NDArray[np.float64]:
    """ITU-R BT.709 OETF: linear light in [0, 1] → encoded value in [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x < 0.018, 4.5 * x, 1.099 * x**0.45 - 0.099)


DECODE = {"srgb": srgb_to_linear, "rec709": rec709_to_linear}
ENCODE = {"srgb": linear_to_srgb, "rec709": linear_to_rec709}


def encode(linear_dn: ArrayLike, kind: str, bits: int) -> NDArray:
    """Linear DN (0 … 2^bits − 1) → codes of a camera with a standard tone curve, rounded and clipped."""
    top = 2**bits - 1
    codes = np.rint(ENCODE[kind](np.asarray(linear_dn, dtype=np.float64) / top) * top)
    return codes.astype(np.uint8 if bits == 8 else np.uint16)


class ResponseCurve:
    """Per-channel tables code → linear DN, for every code of a ``bits``-bit camera."""

    def __init__(self, table: ArrayLike, kind: str = "table", method: str = "") -> None:
        t = np.asarray(table, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] not in (256, 1024, 4096, 65536):
            raise UserInputError(f"a response table needs one row per channel of 2^bits values, got shape {t.shape}")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t, axis=1) < 0):
            raise UserInputError("a response table must be finite and non-decreasing in every channel")
        self.table = t
        self.kind = kind
        self.method = method
        self.bits = int(np.log2(t.shape[1]))
        top = t.shape[1] - 1
        # Width in linear DN of each code (half the distance to its neighbours), for the quantisation term.
        padded = np.concatenate([t[:, :1], t, t[:, -1:]], axis=1)
        self.width = (padded[:, 2:] - padded[:, :-2]) / np.where((np.arange(t.shape[1]) % top) == 0, 1.0, 2.0)
        self._lut = [np.ascontiguousarray(row, dtype=np.float32) for row in t]

    @property
    def channels(self) -> int:
        return self.table.shape[0]

    @classmethod
    def standard(cls, kind: str, bits: int, channels: int) -> "ResponseCurve":
        """A standard curve (``srgb``, ``rec709``) for every channel."""
        if kind not in DECODE:
            raise UserInputError(f"unknown response curve '{kind}'; known: {', '.join(STANDARDS)} (or a response file)")
        top = 2**bits - 1
        row = DECODE[kind](np.arange(top + 1) / top) * top
        return cls(np.repeat(row[None, :], channels, axis=0), kind=kind, method=f"{kind} standard")

    def linearise(self, frame: NDArray) -> NDArray[np.float32]:
        """(H, W, N) integer codes → (H, W, N) linear DN, float32."""
        if not np.issubdtype(frame.dtype, np.integer):
            raise UserInputError(f"a response curve applies to camera codes (integers), got {frame.dtype} values")
        if frame.shape[-1] != self.channels:
            raise UserInputError(f"the frame has {frame.shape[-1]} channels, the response curve {self.channels}")
        if int(frame.max(initial=0)) >= self.table.shape[1]:
            raise UserInputError(f"the frame has codes above {self.table.shape[1] - 1}: its response curve is for "
                                 f"{self.bits}-bit codes")
        out = np.empty(frame.shape, np.float32)
        for k, lut in enumerate(self._lut):
            np.take(lut, frame[..., k], out=out[..., k])
        return out

    def quantisation_variance(self, linear: ArrayLike) -> NDArray[np.float64]:
        """Variance (linear DN²) of one code's width at each linear value (…, N): width²/12."""
        x = np.asarray(linear, dtype=np.float64)
        out = np.empty(np.broadcast_shapes(x.shape, (self.channels,)))
        for k in range(self.channels):
            out[..., k] = np.interp(x[..., k], self.table[k], self.width[k]) ** 2 / 12.0
        return out

    # -- the profile's record ---------------------------------------------------------------
    def to_record(self) -> dict:
        record: dict = {"kind": self.kind, "bits": self.bits, "method": self.method}
        if self.kind == "table":
            record["table"] = [[round(float(v), 6) for v in row] for row in self.table]
        return record

    @classmethod
    def from_record(cls, record, channels: int) -> "ResponseCurve":
        kind, bits = record.kind, record.bits
        if kind in DECODE:
            return cls.standard(kind, bits, channels)
        curve = cls(record.table, kind="table", method=record.method)
        if curve.channels != channels or curve.bits != bits:
            raise UserInputError(f"the profile's response table has {curve.channels} channels of {curve.bits}-bit codes; "
                                 f"expected {channels} channels of {bits}-bit codes")
        return curve


def recover(frames: Sequence[NDArray], exposures_s: Sequence[float], method: str = "debevec",
            samples: int = 200, smoothness: float = 10.0) -> ResponseCurve:
    """The response of an 8-bit camera from frames of a still scene at several exposures (s).

    OpenCV's ``CalibrateDebevec`` (least squares on log exposure with a smoothness term) or
    ``CalibrateRobertson`` (iterative); each channel is then made non-decreasing and scaled so
    its top code is 255 linear DN (the absolute scale per channel is the calibration's business).
    """
    import cv2

    if len(frames) < 2 or len(frames) != len(exposures_s):
        raise UserInputError(f"response recovery needs two or more frames with one exposure each, "
                             f"got {len(frames)} frames and {len(exposures_s)} exposures")
    times = np.asarray(exposures_s, dtype=np.float32)
    if not np.all(np.isfinite(times)) or np.any(times <= 0):
        raise UserInputError(f"exposures must be positive numbers, got {list(exposures_s)}")
    if len(set(np.round(times, 9))) < 2:
        raise UserInputError("the frames need at least two different exposures")
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise UserInputError(f"bracket frames differ in size: {sorted(shapes)}")
    first = frames[0]
    if first.dtype != np.uint8 or first.ndim != 3 or first.shape[-1] != 3:
        raise UserInputError("response recovery takes 8-bit frames with three channels (OpenCV's calibration); "
                             f"got {first.dtype} frames of shape {first.shape}")
    images = [np.ascontiguousarray(f) for f in frames]  # channel order is kept: OpenCV treats them alike
    if method == "debevec":
        tool = cv2.createCalibrateDebevec(samples=samples, lambda_=smoothness)
    elif method == "robertson":
        tool = cv2.createCalibrateRobertson()
    else:
        raise UserInputError(f"unknown response method '{method}'; known: debevec, robertson")
    curve = tool.process(images, times).reshape(256, 3).T.astype(np.float64)
    curve = np.maximum.accumulate(np.maximum(curve, 0.0), axis=1)
    curve = curve / curve[:, -1:] * 255.0
    curve[:, 0] = 0.0  # code 0 is no light (anything darker is clipped there)
    return ResponseCurve(curve, kind="table", method=f"{method} from {len(frames)} frames at "
                                                        f"{', '.join(f'{t * 1e3:g}' for t in times)} ms")


RESPONSE_FORMAT = "uwcam-response"


def save_response(curve: ResponseCurve, path) -> None:
    """Write a response curve as YAML (written atomically)."""
    import yaml

    from uwcam.fileio import atomic_write

    with atomic_write(path, "w") as fh:
        yaml.safe_dump({"format": RESPONSE_FORMAT, "version": 1, **curve.to_record()}, fh, sort_keys=False, width=200)


def load_response(name_or_path: str, channels: int, bits: int = 8) -> ResponseCurve:
    """``srgb``, ``rec709`` or a response file written by ``uwcam response``."""
    if name_or_path in DECODE:
        return ResponseCurve.standard(name_or_path, bits, channels)
    from pathlib import Path

    from pydantic import ValidationError

    from uwcam.fileio import explain_validation_error, load_yaml_mapping
    from uwcam.calibration.profile import ResponseRecord

    path = Path(name_or_path)
    if not path.is_file():
        raise UserInputError(f"--response must be srgb, rec709 or a response file from 'uwcam response'; "
                             f"{name_or_path} is none of these")
    data = load_yaml_mapping(path, "response file")
    if data.get("format") != RESPONSE_FORMAT:
        raise UserInputError(f"{path} is not a response file (its format is {data.get('format')!r}, "
                             f"expected {RESPONSE_FORMAT!r})")
    try:  # the key at fault and what it may hold, as for a profile
        record = ResponseRecord.model_validate({k: v for k, v in data.items() if k not in ("format", "version")})
    except ValidationError as exc:
        raise UserInputError(explain_validation_error(exc, f"response file {path}")) from None
    return ResponseCurve.from_record(record, channels)
