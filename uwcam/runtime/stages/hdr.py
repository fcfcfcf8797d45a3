"""High dynamic range for cameras with one exposure: alternate exposures, merge per channel.

A camera that exposes all channels alike cannot keep red (weak, far) and blue (strong) both in
range. The exposure controller (:mod:`uwcam.runtime.stages.exposure`) then alternates a short exposure (the
strongest channel does not saturate) and a long one (the weakest is lifted above its floor),
and :func:`merge_exposures` builds one frame from consecutive frames: each channel is taken
whole from the longest exposure in which it is not saturated, keeping the sensor's own
counts, and the merged frame carries each channel's exposure. The estimator then corrects
each channel for its exposure exactly and evaluates the noise on those counts, as for a
3-chip camera (docs/exposure.md).

Taking whole channels (rather than mixing exposures pixel by pixel) keeps one exposure per
channel, which is what the transform's per-channel correction needs; a channel saturated in
every frame of the bracket takes the shortest exposure and its clipped pixels stay marked as
saturated.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from uwcam.drivers.base import Frame

# A channel counts as saturated in a frame when more than this fraction of its pixels are clipped.
SATURATED_FRACTION = 0.001


def merge_exposures(frames: Sequence[NDArray], exposure_us: Sequence[Sequence[float]], saturation_level: float,
                    saturated_fraction: float = SATURATED_FRACTION) -> tuple[NDArray, tuple[float, ...], list[int]]:
    """One frame (H, W, N) from frames of the same scene at different exposures.

    frames: each (H, W, N), same shape and type; exposure_us: each frame's exposure per channel
    (µs, (N,)). Channel k is copied from the frame with the longest exposure of channel k in
    which at most ``saturated_fraction`` of its pixels reach ``saturation_level``, or from the
    shortest when it saturates in all. Returns the merged frame (the frames' type, raw counts),
    each channel's exposure (µs) and the index of the frame each channel came from.
    """
    if not frames or len(frames) != len(exposure_us):
        raise ValueError("need one exposure per frame, and at least one frame")
    first = np.asarray(frames[0])
    if any(np.shape(f) != first.shape for f in frames) or first.ndim != 3:
        raise ValueError("frames to merge must all be (H, W, N) of the same size")
    n = first.shape[-1]
    t = np.asarray(exposure_us, dtype=np.float64)
    if t.shape != (len(frames), n) or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"need {n} positive exposures per frame, got {t.tolist()}")
    merged = np.empty_like(first)
    chosen: list[int] = []
    for k in range(n):
        order = np.argsort(-t[:, k], kind="stable")  # longest first
        pick = int(order[-1])
        for i in order:
            if np.mean(np.asarray(frames[i])[..., k] >= saturation_level) <= saturated_fraction:
                pick = int(i)
                break
        merged[..., k] = np.asarray(frames[pick])[..., k]
        chosen.append(pick)
    return merged, tuple(float(t[chosen[k], k]) for k in range(n)), chosen


class HdrMerger:
    """Merges each frame with the one before it when their exposures differ (a bracket of two,
    alternating), so one merged frame comes out per frame in: the frame rate is kept."""

    def __init__(self, saturation_level: float, max_gap: int = 1) -> None:
        """max_gap: frames further apart in sequence number than this are not merged (a dropped
        frame in between: the scene may have moved)."""
        self.saturation_level = float(saturation_level)
        self.max_gap = max_gap
        self._previous: Frame | None = None
        self.merged = 0

    def __call__(self, frame: Frame) -> Frame:
        """The merged frame (a new Frame with per-channel exposure), or ``frame`` itself when there is
        nothing to merge it with (the first, a gap, a lamp change, equal or unknown exposures)."""
        previous, self._previous = self._previous, frame
        exposure = frame.exposures()[0]
        if previous is None or exposure is None:
            return frame
        before = previous.exposures()[0]
        if (before is None or before == exposure or previous.data.shape != frame.data.shape
                or previous.lamp_on != frame.lamp_on or not 0 < frame.sequence - previous.sequence <= self.max_gap):
            return frame
        data, merged_exposure, chosen = merge_exposures([previous.data, frame.data], [before, exposure], self.saturation_level)
        self.merged += 1
        gains = [previous.exposures()[1], frame.exposures()[1]]
        gain = None if None in gains else tuple(gains[i][k] for k, i in enumerate(chosen))
        return replace(frame, data=data, exposure_us=None, gain_db=None, channel_exposure_us=merged_exposure,
                       channel_gain_db=gain)
