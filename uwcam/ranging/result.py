"""What ranging gives for one frame: range, variance and reason maps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class RangeResult:
    """Outputs for one frame, each (H, W)."""

    range: NDArray[np.float32]
    """Camera range d_c in metres along each pixel's ray; NaN where invalid."""
    variance: NDArray[np.float32]
    """Variance of ``range`` in m²; NaN where invalid."""
    reasons: NDArray[np.uint8]
    """:class:`uwcam.optics.validity.Reason` code per pixel."""
    calibration_variance: NDArray[np.float32] | None = None
    """The part of ``variance`` that comes from the calibration (m²), the same in every frame and
    correlated between pixels; None when not added."""
