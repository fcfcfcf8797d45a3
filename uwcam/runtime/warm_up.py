"""Compile the frame loop's kernels before a frame needs them.

numba compiles a kernel for each combination of argument types the first time it meets it
(or loads it from its on-disk cache): a 3×3 mean before the transform hands the estimator float
means with sample counts, temporal fusion float means, the water's light a threshold of means.
Met first in the frame loop, a combination stalls it for seconds (16 s for a switch to
smoothing before the transform on the 2-core test machine with an empty cache). So the loop's
settings are rehearsed on a small synthetic frame, in the caller's thread, before the loop sees
them: at start-up, on a settings change (the API request's thread), and in full by
``uwcam warmup`` at install time, which fills numba's cache for every combination so that
later ones only load.
"""

from __future__ import annotations

import numpy as np

from uwcam.config import ProcessingConfig, TemporalConfig
from uwcam.ranging.estimator import RangeEstimator, range_frame
from uwcam.runtime.stages.temporal import TemporalFuser
from uwcam.water.water_light import WaterLight

SMOOTHINGS: tuple[tuple[str, str], ...] = (
    ("none", "after"), ("mean", "before"), ("median", "before"), ("mean", "after"), ("median", "after"),
    ("adaptive", "after"),
)
"""Every (smoothing, smoothing_stage) the processing settings accept that takes its own path."""

_SIZE = (24, 32)  # rows, columns: large enough for adaptive windows to grow, small enough to be instant


def _frames(estimator: RangeEstimator, dtypes: tuple[type, ...], read_only: tuple[bool, ...]) -> list[np.ndarray]:
    """Synthetic frames (H, W, N) of these pixel types, writable and read-only, whose light spans
    dark to bright, so that pixels take every branch that matters for types (valid, too dark,
    windows grown)."""
    if estimator.response is not None:  # a gamma camera: codes of its depth, and linear light
        dtypes = tuple(d for d in dtypes if np.dtype(d).itemsize * 8 == estimator.response.bits) + (np.float32,)
    h, w = _SIZE
    n = estimator.n_channels
    top = float(estimator.profile.saturation_level)
    ramp = np.linspace(0.0, 0.6, h * w * n).reshape(h, w, n)
    frames = []
    for dtype in dict.fromkeys(dtypes):
        ceiling = min(top, float(np.iinfo(dtype).max)) if np.issubdtype(dtype, np.integer) else top
        for fixed in read_only:  # a driver may hand over its buffer read-only (numba compiles for those apart)
            frame = (ramp * ceiling).astype(dtype)
            frame.flags.writeable = not fixed
            frames.append(frame)
    return frames


def warm_up_ranging(estimator: RangeEstimator, processing: ProcessingConfig | None = None,
                    dtypes: tuple[type, ...] = (np.uint8, np.uint16), read_only: tuple[bool, ...] = (False, True)) -> None:
    """Range small synthetic frames of these pixel types the ways ``processing`` can range them
    (its smoothing; with light not from the lamp when it takes lamp-off frames or subtracts
    backscatter; temporal means when it fuses
    frames; judged against the water's light, which the loop may use whenever an open-water frame
    or a backscatter model is at hand), so that numba compiles or loads each kernel now. None:
    every way the settings allow (``uwcam warmup``). read_only: frames writable (False), read-only
    (True) or both, as the camera's driver hands them over. Leaves ``estimator`` as it was."""
    smoothings = SMOOTHINGS if processing is None else ((processing.smoothing, processing.smoothing_stage),)
    # Light not from the lamp beside the frame: ambient (lamp-off frames) or backscatter subtracted.
    ambient = processing is None or bool(processing.lamp_off_interval) or processing.backscatter is not None
    temporal = processing is None or processing.temporal is not None
    frames = _frames(estimator, dtypes, read_only)
    shape = frames[0].shape
    water = WaterLight(np.full(shape, 0.05 * float(estimator.profile.saturation_level), np.float32), 0.05, "warm-up")
    lights = (None, np.zeros(shape, np.float32)) if ambient else (None,)
    inputs = [(frame, None) for frame in frames]
    if temporal:
        fuser = TemporalFuser(processing.temporal if processing is not None and processing.temporal else TemporalConfig())
        for frame in frames:
            fuser.reset("warm-up")
            fuser.update(frame, (None,), estimator)
            inputs.append(fuser.update(frame, (None,), estimator))  # the second frame takes the compiled path
    for smoothing, stage in smoothings:
        for data, samples in inputs:
            for light in lights:
                for judge in (None, water):
                    range_frame(estimator, data, smoothing, stage, light, (), None, judge, None, samples)


def warm_up_everything(estimator: RangeEstimator, first: ProcessingConfig | None = None) -> None:
    """Every kernel ranging with ``estimator``'s channels can need, in the order a first start needs
    them (:mod:`uwcam.runtime.background_warm_up`): 16-bit frames ranged with the settings ``first``
    (the daemon's; default settings when None), then with a background (backscatter compensation),
    then float frames with a background (its coarse passes), then the same for 8-bit frames, then
    every other setting, pixel type and layout."""
    first = first or ProcessingConfig()
    for dtype in (np.uint16, np.uint8):
        warm_up_ranging(estimator, first, dtypes=(dtype,), read_only=(False,))
        estimator.warm_up(dtypes=(dtype,), background=True, strided=False)
        if dtype == np.uint16:  # float means with a background: the coarse passes, whatever the camera's type
            estimator.warm_up(dtypes=(), background=True)
    warm_up_ranging(estimator)
    estimator.warm_up(dtypes=(np.uint8, np.uint16, np.float32))
