"""How much more light a frame gathered than the light the model of the water's light came from.

The modelled backscatter is in the counts of that light (an open-water frame, or the calibration's
black-patch measurements): it is scaled by each channel's exposure × gain ratio before it is
subtracted (docs/exposure.md)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.estimator import RangeEstimator


def light_scale(profile: CalibrationProfile, estimator: RangeEstimator, gathered: NDArray | None,
                from_open_water: bool, open_water_exposure: NDArray | list[float] | None = None) -> NDArray | None:
    """(N,) the frame's exposure × gain over that of the light the backscatter model came from
    (None: taken as 1): ``gathered`` the frame's light gathered per channel (None: unknown);
    ``from_open_water``: the model came from an open-water frame, taken at ``open_water_exposure``
    (None: unknown), else from the calibration, whose exposure the estimator's shift is relative to."""
    if gathered is None:
        return None
    if from_open_water:
        if open_water_exposure is None or len(open_water_exposure) != np.size(gathered):
            return None
        return gathered / np.asarray(open_water_exposure, dtype=np.float64)
    if profile.calibration_exposure()[0] is not None:
        return np.exp(estimator.exposure_shift)
    return None
