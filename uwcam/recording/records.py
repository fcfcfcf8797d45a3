"""What a recording says about each frame besides its images: the frame's metadata, its ranging
record, the summary of a frame left out, and range turned into depth."""

from __future__ import annotations

import numpy as np

from uwcam.drivers.base import Frame
from uwcam.runtime.published import Published
from uwcam.calibration.profile import CalibrationProfile

BUDGET = "decimated to fit recording.budget_mb_s"
"""Why a frame's raw image is left out of a recording: it did not fit the disk budget."""


def summary_of(item: tuple, why: str) -> dict:
    """A queued raw item reduced to what is kept of a frame without its raw image: its metadata
    (``raw_left_out``: ``why``), its ranging record, and its preview if one was due (only when
    decimated: a recorder behind sheds the pixels of previews too)."""
    if item[0] == "ranged":
        _, published, profile, processing, preview = item
        frame, ranging = published.frame, ranging_record(published, profile, processing)
        metadata = frame_metadata(frame, "ranged", published.number, why)
    else:
        _, frame, ranged, preview = item
        ranging, metadata = None, frame_metadata(frame, ranged, None, why)
    return {"t": int(frame.wall_time * 1e9), "metadata": metadata, "ranging": ranging,
            "preview": frame.data if preview and why == BUDGET else None}


def frame_metadata(frame: Frame, ranged: str, number: int | None, raw_left_out: str | None = None) -> dict:
    """A frame's /uwcam/image/metadata record; ``raw_left_out``: why its raw image is not in the
    file (None: it is), ``raw_kept`` the same as a flag."""
    exposure, gain = frame.exposures()  # per channel: one value each, alike where the camera has one
    return {"sequence": frame.sequence, "device_timestamp_ns": frame.device_timestamp_ns,
            "host_monotonic_ns": frame.host_monotonic_ns, "wall_time": frame.wall_time,
            "exposure_us": None if exposure is None else list(exposure), "gain_db": None if gain is None else list(gain),
            "lamp_on": frame.lamp_on, "channel_names": list(frame.channel_names), "bit_depth": frame.bit_depth,
            "dtype": frame.data.dtype.name, "ranged": ranged, "number": number, "raw_kept": raw_left_out is None,
            "raw_left_out": raw_left_out}


def ranging_record(p: Published, profile: CalibrationProfile, processing) -> dict:
    """What a frame was ranged with: enough to range its raw frame again the same way."""
    return {"number": p.number, "sequence": p.frame.sequence, "profile": profile.name,
            "channel_names": profile.channel_names,
            "attenuation_differences": list(p.attenuation_differences), "log_constants": list(p.log_constants),
            "ambient_subtracted": p.ambient is not None,
            "processing": {"pair": processing.pair, "smoothing": processing.smoothing,
                           "smoothing_stage": processing.smoothing_stage,
                           "smoothing_target": processing.smoothing_target,
                           "path_length_bounds": list(processing.path_length_bounds),
                           "vehicle_mask": [list(box) for box in processing.vehicle_mask],
                           "backscatter": None if processing.backscatter is None else processing.backscatter.iterations,
                           # Fused frames are reprocessed as single frames (docs/physics.md §11).
                           "temporal": None if processing.temporal is None else processing.temporal.model_dump()},
            "water": p.water_source, "light_scale": None if p.light_scale is None else list(p.light_scale),
            "open_water_frames": p.open_water_frames if p.open_water is not None else None,
            "depth": "metres along the optical axis (range along the pixel ray times u_z)"}


def to_depth(range_m: np.ndarray, variance: np.ndarray, uz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range along each pixel's ray → depth along the optical axis (REP 118), and its variance (m²)."""
    depth = (range_m * uz).astype(np.float32)
    return depth, (variance * (uz * uz)).astype(np.float32)
