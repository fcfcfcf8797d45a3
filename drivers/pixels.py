"""Pixel formats (GenICam PFNC names) → (H, W, C) arrays at full bit depth.

Pure functions over raw payload bytes, so they are tested without a camera. Packed 10/12-bit
formats, which SDKs sometimes hand over as empty or undecoded components, are unpacked here.
Bayer mosaics are demosaiced with OpenCV (and a warning: interpolated colour ruins
per-pixel ratios at edges). Monochrome is refused: ranging needs colour channels.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.drivers.base import ConfigurationError, CorruptFrame

# name → (channels, bits, order) for unpacked formats.
UNPACKED = {
    "RGB8": (3, 8, "RGB"), "BGR8": (3, 8, "BGR"), "RGBa8": (4, 8, "RGB"), "BGRa8": (4, 8, "BGR"),
    "RGB10": (3, 10, "RGB"), "RGB12": (3, 12, "RGB"), "RGB16": (3, 16, "RGB"),
    "BGR10": (3, 10, "BGR"), "BGR12": (3, 12, "BGR"), "BGR16": (3, 16, "BGR"),
    "RGBa10": (4, 10, "RGB"), "RGBa12": (4, 12, "RGB"), "RGBa16": (4, 16, "RGB"),
}
MONO = {"Mono8", "Mono10", "Mono12", "Mono14", "Mono16", "Mono10p", "Mono12p", "Mono10Packed", "Mono12Packed"}
PACKED_RGB = {"RGB10p": 10, "RGB12p": 12}
BAYER_CODES = {  # OpenCV names the pattern by the 2nd row: its BayerXY means PFNC BayerYX
    "BayerRG": cv2.COLOR_BayerBG2RGB, "BayerBG": cv2.COLOR_BayerRG2RGB,
    "BayerGR": cv2.COLOR_BayerGB2RGB, "BayerGB": cv2.COLOR_BayerGR2RGB,
}


class BayerWarning(UserWarning):
    """Colour from a Bayer mosaic is interpolated: per-pixel ratios are unreliable at edges."""


def unpack_10p(raw: NDArray[np.uint8], count: int) -> NDArray[np.uint16]:
    """PFNC 10p (LSB-first): 4 values in 5 bytes."""
    need = (count * 10 + 7) // 8
    if raw.size < need:
        raise CorruptFrame(f"10-bit packed payload has {raw.size} bytes, needs {need}")
    b = raw[: (count // 4) * 5].reshape(-1, 5).astype(np.uint16)
    out = np.empty((b.shape[0], 4), np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x03) << 8)
    out[:, 1] = (b[:, 1] >> 2) | ((b[:, 2] & 0x0F) << 6)
    out[:, 2] = (b[:, 2] >> 4) | ((b[:, 3] & 0x3F) << 4)
    out[:, 3] = (b[:, 3] >> 6) | (b[:, 4] << 2)
    return out.reshape(-1)[:count]


def unpack_12p(raw: NDArray[np.uint8], count: int) -> NDArray[np.uint16]:
    """PFNC 12p (LSB-first): 2 values in 3 bytes."""
    need = (count * 12 + 7) // 8
    if raw.size < need:
        raise CorruptFrame(f"12-bit packed payload has {raw.size} bytes, needs {need}")
    b = raw[: ((count + 1) // 2) * 3].reshape(-1, 3).astype(np.uint16)
    out = np.empty((b.shape[0], 2), np.uint16)
    out[:, 0] = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
    out[:, 1] = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return out.reshape(-1)[:count]


def refuse_monochrome(pixel_format: str) -> None:
    """ConfigurationError for a monochrome format, naming what to choose instead."""
    if pixel_format in MONO or pixel_format.startswith("Mono"):
        raise ConfigurationError(
            f"pixel format {pixel_format} is monochrome; ranging needs two or more colour channels: choose an RGB "
            "format (e.g. RGB8, RGB12p) or a 3-chip/multi-band camera that delivers one component per channel"
        )


def decode(pixel_format: str, raw: NDArray, width: int, height: int) -> tuple[NDArray, int]:
    """(H, W, C) image and its bit depth from a component's bytes or values.

    ``raw`` may be the SDK's decoded array or the payload bytes (uint8) for packed formats.
    """
    refuse_monochrome(pixel_format)
    n = width * height
    if pixel_format in UNPACKED:
        channels, bits, order = UNPACKED[pixel_format]
        dtype = np.uint8 if bits == 8 else np.uint16
        values = raw.view(dtype) if raw.dtype == np.uint8 and dtype == np.uint16 else raw
        if values.size < n * channels:
            raise CorruptFrame(f"{pixel_format} payload has {values.size} values, needs {n * channels} for {width}×{height}")
        img = values[: n * channels].reshape(height, width, channels)[:, :, :3]
        return (img[:, :, ::-1] if order == "BGR" else img), bits
    if pixel_format in PACKED_RGB:
        bits = PACKED_RGB[pixel_format]
        raw8 = np.ascontiguousarray(raw).view(np.uint8).reshape(-1)
        values = (unpack_10p if bits == 10 else unpack_12p)(raw8, n * 3)
        return values.reshape(height, width, 3), bits
    for name, code in BAYER_CODES.items():
        if pixel_format.startswith(name):
            bits = int(pixel_format[len(name):].rstrip("p") or 8)
            if pixel_format.endswith("p"):
                raw8 = np.ascontiguousarray(raw).view(np.uint8).reshape(-1)
                mosaic = (unpack_10p if bits == 10 else unpack_12p)(raw8, n).reshape(height, width)
            else:
                dtype = np.uint8 if bits == 8 else np.uint16
                values = raw.view(dtype) if raw.dtype == np.uint8 and dtype == np.uint16 else raw
                if values.size < n:
                    raise CorruptFrame(f"{pixel_format} payload has {values.size} values, needs {n}")
                mosaic = values[:n].reshape(height, width)
            warnings.warn(f"{pixel_format} is a Bayer mosaic: demosaiced colour makes range ratios unreliable at edges",
                          BayerWarning, stacklevel=2)
            return cv2.cvtColor(np.ascontiguousarray(mosaic), code), bits
    raise ConfigurationError(f"pixel format {pixel_format} is not supported; use an RGB, packed RGB or Bayer format")


def assemble_components(parts: list[NDArray]) -> NDArray:
    """One registered (H, W, C) frame from one mono component per sensor (3-chip cameras)."""
    shapes = {p.shape[:2] for p in parts}
    if len(shapes) != 1:
        raise CorruptFrame(f"components of one frame differ in size: {sorted(shapes)}")
    return np.stack([p if p.ndim == 2 else p[:, :, 0] for p in parts], axis=-1)
