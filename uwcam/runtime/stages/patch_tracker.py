"""Live tracking of the attenuation differences from a calibration patch in view (docs/physics.md §6)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.config import PatchConfig
from uwcam.calibration.profile import CalibrationProfile
from uwcam.imaging.markers import find_markers


@dataclass
class PatchTracker:
    """Re-estimates c_k − c_ref every frame from a patch of known path length (docs/physics.md §6):
    ln(E_k/E_ref) = b_k − V_k·d_T^p, so V_k = (b_k − ln(E_k/E_ref)) / d_T^p; smoothed by an EMA,
    with frames rejected when the patch is saturated, too dark or the estimate jumps."""

    config: PatchConfig
    profile: CalibrationProfile
    tracked: NDArray[np.float64] = field(init=False)
    accepted: int = 0
    rejected: int = 0
    last_reason: str = "no frame yet"

    def __post_init__(self) -> None:
        self.region = self.config.region
        self.calibrated = self.profile.array("attenuation_difference")
        self.tracked = self.calibrated.copy()
        self.log_constant = self.profile.array("log_constant")
        self.dark = self.profile.array("dark_level")
        self.floor = self.profile.array("noise_floor")
        self.ref = self.profile.reference_index

    def locate(self, data: NDArray) -> tuple[int, int, int, int] | None:
        """The patch region in pixels: fixed, or placed beside the marker found in this frame."""
        if self.config.marker is None:
            return self.config.region
        m = self.config.marker
        corners, ids = find_markers(data, m.dictionary)
        if m.id not in ids:
            return None
        c = corners[ids.index(m.id)]
        side = float(np.mean([np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0])]))
        x, y = c[0] + np.array(m.offset) * side
        w, h = np.array(m.size) * side
        x0, y0 = max(int(round(x)), 0), max(int(round(y)), 0)
        return x0, y0, max(int(round(w)), 1), max(int(round(h)), 1)

    def update(self, data: NDArray, background: NDArray | None = None, exposure_shift: NDArray | None = None) -> bool:
        """background: light (DN) not from the lamp, e.g. the ambient frame, subtracted first;
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's)."""
        region = self.locate(data)
        if region is None:
            self.last_reason = f"marker {self.config.marker.id} not found (occluded, dark or out of view?)"
            self.rejected += 1
            return False
        self.region = region
        x, y, w, h = region
        patch = data[y : y + h, x : x + w]
        if patch.size == 0:
            self.last_reason = "patch region lies outside the image"
            self.rejected += 1
            return False
        if np.any(patch >= self.profile.saturation_level):
            self.last_reason = "patch saturated"
            self.rejected += 1
            return False
        e = patch.reshape(-1, patch.shape[-1]).astype(np.float64).mean(axis=0) - self.dark
        if background is not None:
            e = e - background[y : y + h, x : x + w].reshape(-1, patch.shape[-1]).mean(axis=0)
        if np.any(e <= np.maximum(self.floor, 0.0)) or np.any(e <= 0):
            self.last_reason = "patch below the noise floor (occluded or lamp off?)"
            self.rejected += 1
            return False
        if exposure_shift is not None:
            e = e * np.exp(-np.asarray(exposure_shift))  # as if at the calibration's exposure
        estimate = (self.log_constant - (np.log(e) - np.log(e[self.ref]))) / self.config.path_length_m
        estimate[self.ref] = 0.0
        if self.accepted and np.max(np.abs(estimate - self.tracked)) > self.config.max_step:
            self.last_reason = f"estimate jumped by {np.max(np.abs(estimate - self.tracked)):.3f} 1/m (outlier)"
            self.rejected += 1
            return False
        a = 1.0 if self.accepted == 0 else self.config.smoothing
        self.tracked = (1 - a) * self.tracked + a * estimate
        self.accepted += 1
        self.last_reason = "tracking"
        return True

    def status(self) -> dict:
        names = self.profile.channel_names
        return {
            "attenuation_differences": dict(zip(names, map(float, self.tracked))),
            "drift": dict(zip(names, map(float, self.tracked - self.calibrated))),
            # The calibration's own uncertainty of each difference (1/m; 0: not known): a drift
            # within a few of these is the calibration's noise, beyond them the water has changed.
            "drift_std": dict(zip(names, map(float, self.profile.array("attenuation_difference_std")))),
            "accepted": self.accepted,
            "rejected": self.rejected,
            "state": self.last_reason,
            "region": None if self.region is None else list(self.region),
        }
