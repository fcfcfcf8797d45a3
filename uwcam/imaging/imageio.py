"""Reading frames and writing maps: .npy, .tif/.tiff (tifffile) and .png (OpenCV).

Frames come back as (H, W, C) arrays in stored channel order (R, G, B for PNG/TIFF
colour images) at their full bit depth. Writes are atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError, atomic_write

IMAGE_SUFFIXES = (".npy", ".tif", ".tiff", ".png")
MAP_SUFFIXES = (".npy", ".tif", ".tiff")


def _suffix(path: Path, allowed: tuple[str, ...], what: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in allowed:
        raise UserInputError(f"{what} {path} has an unknown extension; use one of {', '.join(allowed)}")
    return suffix


def read_frame(path: str | os.PathLike[str]) -> NDArray:
    """An image as (H, W, C), C ≥ 2, with its stored dtype; UserInputError if unreadable."""
    p = Path(path)
    suffix = _suffix(p, IMAGE_SUFFIXES, "image")
    if not p.is_file():
        raise UserInputError(f"image {p} does not exist")
    try:
        if suffix == ".npy":
            frame = np.load(p, allow_pickle=False)
        elif suffix in (".tif", ".tiff"):
            import tifffile  # only when a TIFF is read or written: ~2 MB of the daemon's memory
            frame = tifffile.imread(p)
            # Planar TIFFs store (C, H, W); a small leading axis with a larger last one is planar.
            if frame.ndim == 3 and frame.shape[0] <= 16 and frame.shape[-1] > 16:
                frame = np.moveaxis(frame, 0, -1)
        else:
            frame = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if frame is None:
                raise ValueError("OpenCV could not decode it")
            if frame.ndim == 3:
                # OpenCV stores BGR(A); give channels back in the file's R, G, B(, A) order.
                frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2RGBA if frame.shape[-1] == 4 else cv2.COLOR_BGR2RGB)
    except UserInputError:
        raise
    except Exception as exc:  # each reader raises its own types; all mean "not a readable image"
        raise UserInputError(f"cannot read image {p}: {exc}") from None
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[-1] < 2:
        channels = 1 if frame.ndim == 2 else (frame.shape[-1] if frame.ndim == 3 else "?")
        raise UserInputError(
            f"image {p} has shape {frame.shape} ({channels} channel(s)); ranging needs a colour image of shape H×W×C with C ≥ 2"
        )
    if not (np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating)):
        raise UserInputError(f"image {p} has pixel type {frame.dtype}; use integer or float pixels")
    return frame


def write_map(path: str | os.PathLike[str], data: NDArray) -> None:
    """Write a 2-D map (range, variance, reasons) as .npy or .tif atomically."""
    p = Path(path)
    suffix = _suffix(p, MAP_SUFFIXES, "output")
    if not p.parent.exists():
        raise UserInputError(f"output folder {p.parent} does not exist")
    with atomic_write(p) as fh:
        if suffix == ".npy":
            np.save(fh, data, allow_pickle=False)
        else:
            import tifffile  # only when a TIFF is read or written: ~2 MB of the daemon's memory
            tifffile.imwrite(fh, data)


def write_frame(path: str | os.PathLike[str], frame: NDArray) -> None:
    """Write an (H, W, C) frame as .npy, .tif (any C) or .png (C = 3 or 4, uint8/uint16) atomically."""
    p = Path(path)
    suffix = _suffix(p, IMAGE_SUFFIXES, "output")
    if not p.parent.exists():
        raise UserInputError(f"output folder {p.parent} does not exist")
    if suffix == ".png":
        if frame.dtype not in (np.uint8, np.uint16) or frame.ndim != 3 or frame.shape[-1] not in (3, 4):
            raise UserInputError("PNG holds 3 or 4 channels of uint8 or uint16; use .tif or .npy for other frames")
        code = cv2.COLOR_RGBA2BGRA if frame.shape[-1] == 4 else cv2.COLOR_RGB2BGR
        ok, buf = cv2.imencode(".png", cv2.cvtColor(frame, code))
        if not ok:
            raise UserInputError(f"OpenCV could not encode {p} as PNG")
        with atomic_write(p) as fh:
            fh.write(buf.tobytes())
    else:
        write_map(p, frame)
