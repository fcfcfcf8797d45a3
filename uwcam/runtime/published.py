"""What the frame loop publishes for each processed frame: the frame, its range maps and the
values the loop ranged it with. Immutable once published; every output reads it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.drivers.base import Frame
from uwcam.ranging.result import RangeResult


@dataclass(frozen=True)
class Published:
    """One processed frame. Arrays are never modified after publication."""

    number: int
    frame: Frame
    result: RangeResult
    publish_monotonic_ns: int
    attenuation_differences: tuple[float, ...]
    log_constants: tuple[float, ...] = ()
    """The log constants b_k this frame was ranged with (the calibration's, or the surface's)."""
    ambient: NDArray[np.float32] | None = None
    """(H, W, C) light not from the lamp (DN, dark-corrected) subtracted from this frame, or None."""
    incidence: NDArray[np.float32] | None = None
    """(H // block, W // block) incidence angle γ in degrees per pixel block (Kirlin), NaN where
    none was found; None when orientation is off or unavailable."""
    incidence_block: int = 0
    """Side of the pixel blocks of ``incidence``."""
    water_source: str | None = None
    """What the open-water light this frame was judged against came from (uwcam.water.water_light), or None."""
    light_scale: tuple[float, ...] | None = None
    """Per channel, this frame's exposure × gain over that of the backscatter model's light (None: 1)."""
    open_water: NDArray[np.float32] | None = None
    """The open-water frame the backscatter model was made with, when it was (raw DN less ambient)."""
    frames: NDArray[np.uint16] | None = None
    """(H, W) frames each pixel's range is built from under temporal fusion (0: no range); None
    when fusion is off (every range from its own frame alone)."""
    open_water_frames: int = 1
    """How many frames ``open_water`` is the mean of (its pixels' own response is found from it
    when 2 or more: :meth:`uwcam.water.backscatter.BackscatterModel.from_profile`)."""

    @property
    def latency_s(self) -> float:
        return (self.publish_monotonic_ns - self.frame.host_monotonic_ns) / 1e9
