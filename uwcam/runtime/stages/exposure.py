"""Radiometric exposure control: every channel in range (docs/exposure.md).

The camera's own auto-exposure meters a brightness it chooses and changes the exposure when
it likes, which breaks intensity ratios; it stays off. This controller meters the lamp-lit
frame per channel instead and sets each channel's exposure time so that its brightest useful
pixels (a high percentile) sit at a target fraction of the saturation level: the strongest
channel does not clip, and the weakest gets all the light it can, which keeps it above its
noise floor as far as physics allows. A camera that exposes channels apart (3-chip, a
multi-device rig) takes one exposure per channel; a camera with one exposure takes the
shortest of them, so that no channel saturates, and the controller says which channel then
falls below its floor (:mod:`uwcam.runtime.stages.hdr` merges alternating exposures for those).

Every frame carries the exposure it was taken with and the estimator corrects for it
(:meth:`uwcam.ranging.estimator.RangeEstimator.set_exposure`), so changing the exposure never changes
the range. Steps are bounded (at most ``max_step`` times per frame) and there is a dead band
(``tolerance``) so the exposure does not hunt.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.config import ExposureConfig

# Meter on every this-many-th pixel in each direction: percentiles need no more.
METER_STRIDE = 4


@dataclass(frozen=True)
class Metering:
    """What one lit frame says about each channel, (N,) each, in the sensor's own counts."""

    high: NDArray[np.float64]
    """The high percentile of the raw values (DN)."""
    low: NDArray[np.float64]
    """The low percentile of the dark-corrected values (DN): the weak end of the useful pixels."""


def meter(data: NDArray, dark: NDArray, config: ExposureConfig) -> Metering:
    """Robust per-channel levels of a frame (H, W, N), on a subsample of its pixels."""
    sample = np.asarray(data[::METER_STRIDE, ::METER_STRIDE], dtype=np.float64).reshape(-1, data.shape[-1])
    high, low = np.percentile(sample, [config.high_percentile, config.low_percentile], axis=0)
    return Metering(high=high, low=low - np.asarray(dark, dtype=np.float64))


def next_exposure(metering: Metering, exposure_us: NDArray, dark: NDArray, floor: NDArray, saturation_level: float,
                  config: ExposureConfig, per_channel: bool = True) -> tuple[NDArray[np.float64], list[str]]:
    """Exposure times (µs, (N,)) for the next frames and each channel's state.

    Each channel's wanted factor brings its high percentile to ``target`` × the saturation level
    (a saturated percentile: the largest step down), bounded to [1/max_step, max_step] and
    kept at 1 within the dead band; the exposure is then clipped to the configured limits.
    With one exposure for all channels (``per_channel`` False), all take the smallest factor:
    the strongest channel does not saturate. States: "ok", "saturated", "below floor" (its
    low percentile, at the new exposure, is not above the floor), "longest exposure" (it
    wants more than the limit allows) or "held back" (one exposure: another channel limits it).
    """
    t = np.asarray(exposure_us, dtype=np.float64)
    dark = np.asarray(dark, dtype=np.float64)
    signal = metering.high - dark
    top = config.target * saturation_level - dark
    saturated = metering.high >= saturation_level
    with np.errstate(divide="ignore", invalid="ignore"):
        want = np.where(saturated, 1.0 / config.max_step, top / np.maximum(signal, 1.0))
    step = np.clip(want, 1.0 / config.max_step, config.max_step)
    step = np.where(np.abs(np.log(step)) <= np.log1p(config.tolerance), 1.0, step)
    if not per_channel:
        step = np.full_like(step, float(np.min(step)))
    new = np.clip(t * step, config.min_exposure_us, config.max_exposure_us)
    if not per_channel:  # one exposure: the limits may differ from the channels' common value only by rounding
        new = np.full_like(new, float(np.min(new)))
    states = []
    for k in range(t.size):
        low_after = metering.low[k] * new[k] / t[k]
        if saturated[k] and new[k] >= t[k]:
            states.append("saturated")
        elif low_after <= floor[k]:
            states.append("longest exposure" if new[k] >= config.max_exposure_us
                          else "held back" if not per_channel and want[k] > float(np.min(want)) else "below floor")
        else:
            states.append("ok")
    return new, states


@dataclass
class ExposureController:
    """Per-frame exposure control for one camera; called from the frame loop's thread only."""

    config: ExposureConfig
    channel_names: tuple[str, ...]
    control: str
    """The camera's exposure control: "per-channel" or "common"."""
    adjustments: int = 0
    frames: int = 0
    state: str = "no frame yet"
    last: dict = field(default_factory=dict)
    bracket: tuple[float, ...] | None = None
    """Bracketing: the exposures (µs) alternated, short then long (one: no bracket needed)."""

    @property
    def bracketing(self) -> bool:
        """True on a camera with one exposure when alternating exposures are merged (uwcam.runtime.stages.hdr)."""
        return self.control == "common" and self.config.hdr

    def update(self, data: NDArray, exposure_us: tuple[float, ...] | None, lamp_on: bool | None, dark: NDArray,
               floor: NDArray, saturation_level: float,
               raw_exposure_us: tuple[float, ...] | None = None) -> tuple[float, ...] | None:
        """The exposure (µs per channel) to ask the camera for after this frame, or None to keep it.

        data, exposure_us: the frame as ranged (merged from a bracket where the camera has one
        exposure) and each channel's exposure in it; floor: each channel's floor in its counts
        (the estimator's); raw_exposure_us: the exposure of the frame as the camera took it,
        when it was merged (None: ``exposure_us``)."""
        if lamp_on is False:
            self.state = "waiting for a lamp-lit frame"
            return None
        if exposure_us is None:
            self.state = "paused: the camera does not report its exposure"
            return None
        self.frames += 1
        t = np.asarray(exposure_us, dtype=np.float64)
        metering = meter(data, dark, self.config)
        per_channel = self.control == "per-channel" or self.bracketing
        new, states = next_exposure(metering, t, dark, floor, saturation_level, self.config, per_channel=per_channel)
        self.last = {name: {"exposure_us": round(float(t[k]), 3), "next_exposure_us": round(float(new[k]), 3),
                            "high_dn": round(float(metering.high[k]), 1), "low_dn": round(float(metering.low[k]), 1),
                            "floor_dn": round(float(floor[k]), 1), "state": states[k]}
                     for k, name in enumerate(self.channel_names)}
        self.state = "all channels in range" if all(s == "ok" for s in states) else "out of range: " + ", ".join(
            f"{n} ({s})" for n, s in zip(self.channel_names, states) if s != "ok")
        taken = t if raw_exposure_us is None else np.asarray(raw_exposure_us, dtype=np.float64)
        if self.bracketing:
            # Alternate the bracket's ends: the strongest channel's exposure and the weakest's.
            short, long = float(np.min(new)), float(np.max(new))
            single = long <= short * (1.0 + self.config.tolerance)
            self.bracket = (short,) if single else (short, long)
            target = short if single or abs(np.log(taken[0] / long)) < abs(np.log(taken[0] / short)) else long
            new = np.full_like(new, target)
        if np.allclose(new, taken, rtol=1e-9, atol=0.0):
            return None
        self.adjustments += 1
        return tuple(float(v) for v in new)

    def status(self) -> dict:
        return {"enabled": True, "control": self.control, "state": self.state, "frames_metered": self.frames,
                "adjustments": self.adjustments, "channels": self.last or None,
                "bracket_us": None if self.bracket is None else [round(v, 3) for v in self.bracket]}
