"""Per-channel usability and per-pixel validity reasons (docs/physics.md §7)."""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray


class ChannelState(IntEnum):
    """Why one channel of one pixel may or may not be used."""

    USABLE = 0
    BELOW_NOISE_FLOOR = 1
    SATURATED = 2
    BACKSCATTER_ONLY = 3


class Reason(IntEnum):
    """Why a pixel has, or has no, range. Stored as uint8 in reason maps."""

    VALID = 0
    BELOW_NOISE_FLOOR = 1
    SATURATED = 2
    BACKSCATTER_ONLY = 3
    TOO_FEW_CHANNELS = 4
    PATH_OUT_OF_BOUNDS = 5
    VEHICLE = 6
    """The vehicle itself is in view here (processing.vehicle_mask): not a surface to range."""

    @classmethod
    def describe(cls) -> dict[int, str]:
        """Code → human-readable name, for legends and API documentation."""
        return {int(r): r.name.lower().replace("_", " ") for r in cls}


def channel_states(
    raw: ArrayLike,
    signal: ArrayLike,
    noise_floor: ArrayLike,
    saturation_level: float,
    backscatter_level: ArrayLike | None = None,
) -> NDArray[np.uint8]:
    """ChannelState per pixel and channel, shape (..., N).

    raw: values as read from the sensor (saturation is judged on these).
    signal: dark-corrected values E (floors are judged on these), same shape.
    noise_floor: (N,) E at or below which a channel carries no signal.
    saturation_level: raw value at or above which a channel is clipped.
    backscatter_level: optional (N,) E at or below which only water light arrives.
    """
    raw = np.asarray(raw)
    e = np.asarray(signal, dtype=np.float64)
    state = np.zeros(e.shape, dtype=np.uint8)
    if backscatter_level is not None:
        state[e <= np.asarray(backscatter_level, dtype=np.float64)] = ChannelState.BACKSCATTER_ONLY
    state[(e <= np.asarray(noise_floor, dtype=np.float64)) | ~np.isfinite(e)] = ChannelState.BELOW_NOISE_FLOOR
    state[raw >= saturation_level] = ChannelState.SATURATED
    return state


def pixel_reasons(
    states: ArrayLike,
    path_length: ArrayLike,
    min_path_length: float = 0.0,
    max_path_length: float = np.inf,
) -> NDArray[np.uint8]:
    """Reason per pixel from channel states (..., N) and the computed path length (...).

    A pixel with two or more usable channels and a path length is VALID, or PATH_OUT_OF_BOUNDS
    outside [min_path_length, max_path_length]. Without a path length (fewer than two usable
    channels, or usable channels that do not clearly differ in attenuation: NaN) the most telling
    cause wins: SATURATED (a channel clipped), then BACKSCATTER_ONLY (a channel above the floor but
    not above the water's own light, with enough such and usable channels to have ranged), then
    TOO_FEW_CHANNELS (a usable channel), then BELOW_NOISE_FLOOR.
    """
    s = np.asarray(states)
    d = np.asarray(path_length, dtype=np.float64)
    n_usable = (s == ChannelState.USABLE).sum(axis=-1)
    n_saturated = (s == ChannelState.SATURATED).sum(axis=-1)
    n_backscatter = (s == ChannelState.BACKSCATTER_ONLY).sum(axis=-1)
    reasons = np.full(d.shape, Reason.VALID, dtype=np.uint8)
    ranged = (n_usable >= 2) & ~np.isnan(d)
    with np.errstate(invalid="ignore"):
        in_bounds = (d >= min_path_length) & (d <= max_path_length)
    reasons[ranged & ~in_bounds] = Reason.PATH_OUT_OF_BOUNDS
    none = ~ranged
    reasons[none] = Reason.BELOW_NOISE_FLOOR
    reasons[none & (n_usable >= 1)] = Reason.TOO_FEW_CHANNELS
    reasons[none & (n_usable + n_backscatter >= 2) & (n_backscatter > 0)] = Reason.BACKSCATTER_ONLY
    reasons[none & (n_saturated > 0)] = Reason.SATURATED
    return reasons
