"""Surface orientation: incidence angles per pixel block (docs/physics.md §9)."""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.config import OrientationConfig
from uwcam.optics.geometry import Intrinsics, pixel_rays
from uwcam.optics.orientation import beam_pattern, block_irradiance, block_means, incidence_from_blocks
from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.result import RangeResult
from uwcam.runtime.stages.reflectance import ReflectanceCorrector


@dataclass
class OrientationEstimator:
    """Incidence angles per pixel block by Kirlin's Gauss–Newton step (docs/physics.md §9), seeded
    with the fused range, from the profile's absolute attenuations and the absolute scale that the
    reflectance corrector measures at the rangefinder's footprint."""

    config: OrientationConfig
    profile: CalibrationProfile
    state: str = "no frame yet"
    valid_fraction: float | None = None
    ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=100))

    def __post_init__(self) -> None:
        attenuation = [c.attenuation for c in self.profile.channels]
        self.attenuation = None if any(a is None for a in attenuation) else np.array(attenuation, np.float64)
        self._beam: tuple[tuple[int, int], NDArray] | None = None

    def unavailable(self, corrector: ReflectanceCorrector | None) -> str | None:
        """Why no incidence can be had with this profile and corrector, or None."""
        if self.attenuation is None:
            return (f"unavailable: the calibration profile '{self.profile.name}' has no absolute attenuations "
                    "(calibrate with the lamp's effective radius, docs/calibration.md)")
        if corrector is None:
            return ("unavailable: needs the surface's absolute scale from the rangefinder "
                    "(configure processing.reflectance with its footprint)")
        if self.config.beam_half_angle_deg is not None and self.profile.camera_intrinsics() is None:
            return "unavailable: a beam pattern needs camera intrinsics in the calibration profile"
        if corrector.scale is None:
            return f"waiting for an absolute scale at the rangefinder's footprint ({corrector.state})"
        return None

    def beam(self, shape: tuple[int, int]) -> NDArray:
        """The lamp's relative intensity toward the centre of every block, (bh, bw)."""
        if self._beam is None or self._beam[0] != shape:
            intr = self.profile.camera_intrinsics()
            if intr is None or self.config.beam_half_angle_deg is None:
                values = np.ones(shape)
            else:
                b = self.config.block
                # Block (i, j) is centred on pixel (j·b + (b − 1)/2, i·b + (b − 1)/2).
                centres = Intrinsics(intr.fx / b, intr.fy / b, (intr.cx - (b - 1) / 2) / b, (intr.cy - (b - 1) / 2) / b)
                values = beam_pattern(pixel_rays(centres, *shape), self.config.beam_half_angle_deg)
            self._beam = (shape, values)
        return self._beam[1]

    def estimate(self, data: NDArray, result: RangeResult, corrector: ReflectanceCorrector | None,
                 background: NDArray | None = None, exposure_shift: NDArray | None = None) -> NDArray[np.float32] | None:
        """(H // block, W // block) incidence in degrees for this frame, or None (``state`` says why);
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's):
        the scale, measured in the calibration's exposure, is taken to the frame's raw counts."""
        why = self.unavailable(corrector)
        if why is not None:
            self.state = why
            return None
        started = time.perf_counter()
        p = self.profile
        b = self.config.block
        if data.shape[0] < b or data.shape[1] < b:
            self.state = f"unavailable: the image is smaller than one block of {b} pixels"
            return None
        irradiance, share, usable = block_irradiance(data, result.range, p.array("dark_level"), p.array("noise_floor"),
                                                     p.saturation_level, b, background)
        maps = [np.asarray(m, np.float32) for m in (result.range, result.variance, result.common_variance) if m is not None]
        means = block_means(cv2.merge(maps), usable, b)  # one pass over the three maps
        seed, variance = means[..., 0], means[..., 1]
        common = means[..., 2] if means.shape[-1] > 2 else 0.0
        count = share * (b * b)
        # Variances of the block means: the camera's noise model per pixel over the pixels averaged,
        # and the fused range's own (its common part, the calibration's and the backscatter model's, is not averaged down).
        with np.errstate(invalid="ignore", divide="ignore"):
            pixel_var = (p.array("read_noise") ** 2 + p.array("shot_gain") * irradiance
                         + (p.array("fixed_pattern") * irradiance) ** 2 + p.quantisation_step**2 / 12.0)
            irradiance_var = pixel_var / count[..., None]
            range_var = (variance - common) / count + common
        scale = corrector.scale * self.beam(seed.shape)[..., None]
        if exposure_shift is not None:
            scale = scale * np.exp(np.asarray(exposure_shift, np.float64))
        _, incidence = incidence_from_blocks(irradiance, seed, self.attenuation, scale, p.lamp_radius_m or 0.0,
                                             self.config.iterations, irradiance_variance=irradiance_var,
                                             range_variance=range_var)
        self.ms.append((time.perf_counter() - started) * 1e3)
        found = np.isfinite(incidence)
        self.valid_fraction = float(found.mean())
        self.state = "estimating"
        return incidence.astype(np.float32)

    def status(self) -> dict:
        ms = list(self.ms)
        return {"enabled": True, "state": self.state, "block": self.config.block,
                "ms_per_frame": round(float(np.median(ms)), 2) if ms else None,
                "blocks_with_angle": None if self.valid_fraction is None else round(self.valid_fraction, 4)}
