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
    common_variance: NDArray[np.float32] | None = None
    """The part of ``variance`` that neighbouring pixels share and that no average over pixels or
    frames reduces (m²): the calibration's uncertainty and, where the water's light was subtracted,
    the backscatter model's; None when neither was added."""
