"""Reflectance correction: surface log constants from the rangefinder's readings at the beam's
footprint (docs/physics.md §8)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.config import ReflectanceConfig
from uwcam.drivers.base import Frame
from uwcam.optics.geometry import Intrinsics, path_length_from_camera_range, pixel_rays
from uwcam.optics.orientation import beam_pattern, plane_normal, surface_scale
from uwcam.optics.reflectance import surface_log_constant
from uwcam.calibration.profile import CalibrationProfile


@dataclass
class ReflectanceCorrector:
    """Surface log constants b_k from rangefinder readings at the beam's footprint (docs/physics.md §8),
    and, when the profile has absolute attenuations, the surface's absolute scale s_k of Kirlin's
    model (§9), the light a surface facing the lamp squarely would return at that range.

    The reading is taken as the camera range along the ray through the footprint's centre. Where
    the surface there is tilted, each footprint pixel looks at it from another range, and an
    absolute scale divides by the cosine of the incidence angle: both come from the surface normal
    at the footprint, estimated from the previous frame's range map (:meth:`observe`).

    A reading is used only if it is fresh relative to the frame's capture time and the
    rangefinder is healthy; otherwise the correction pauses (the last estimate stays in use)
    and :meth:`status` says why.
    """

    config: ReflectanceConfig
    profile: CalibrationProfile
    rangefinder: object
    beam_half_angle_deg: float | None = None
    """The lamp's beam pattern (see :func:`uwcam.optics.orientation.beam_pattern`), for the scale."""
    log_constant: NDArray[np.float64] | None = None
    scale: NDArray[np.float64] | None = None
    """(N,) absolute scale s_k (DN, at the calibration's exposure) of the surface at the footprint, or None."""
    normal: NDArray[np.float64] | None = None
    """(3,) unit surface normal at the footprint (camera frame), from the range map; None: unknown."""
    incidence_deg: float | None = None
    """Incidence angle at the footprint's centre from ``normal``, degrees."""
    used: int = 0
    state: str = "no reading yet"

    def __post_init__(self) -> None:
        attenuation = [c.attenuation for c in self.profile.channels]
        self.attenuation = None if any(a is None for a in attenuation) else np.array(attenuation, np.float64)

    def observe(self, range_map: NDArray) -> None:
        """The surface normal at the footprint from a range map (H, W), metres: the least-squares
        plane (:func:`plane_normal`) through the surface points of the footprint and a margin
        around it, smoothed over frames as the log constants are (``config.smoothing``); None
        where too few pixels there have a range."""
        intr = self.profile.camera_intrinsics()
        if intr is None:
            return
        x, y, w, h = self.config.footprint
        margin = 8  # pixels around the footprint: a single frame's range is noisy pixel to pixel
        x0, y0 = max(x - margin, 0), max(y - margin, 0)
        x1, y1 = min(x + w + margin, range_map.shape[1]), min(y + h + margin, range_map.shape[0])
        crop = np.asarray(range_map[y0:y1, x0:x1], dtype=np.float64)
        valid = np.isfinite(crop)
        if valid.sum() < max(16, crop.size // 4):
            self.normal = None
            return
        rays = pixel_rays(Intrinsics(intr.fx, intr.fy, intr.cx - x0, intr.cy - y0), *crop.shape)
        normal = plane_normal(crop[valid], rays[valid])
        if normal is None:
            self.normal = None
            return
        if self.normal is not None:
            a = self.config.smoothing
            normal = (1 - a) * self.normal + a * normal
            normal /= np.linalg.norm(normal)
        self.normal = normal

    def update(self, frame: Frame, attenuation_differences: NDArray, background: NDArray | None = None,
               exposure_shift: NDArray | None = None) -> NDArray[np.float64] | None:
        """background: light (DN) not from the lamp, e.g. the ambient frame, subtracted first: of
        the frame's size (H, W, N), or of the footprint's (clipped to the frame) alone;
        exposure_shift: ln m_k of the frame's exposure against the calibration's (the estimator's)."""
        rf = self.rangefinder
        health = rf.health
        reading = rf.latest()
        if health.state.value != "ok":
            self.state = f"paused: rangefinder {health.state.value} ({health.reason})"
            return self.log_constant
        if reading is None:
            self.state = "paused: no valid reading yet"
            return self.log_constant
        skew = abs(reading.monotonic_ns - frame.host_monotonic_ns) / 1e9
        if skew > self.config.max_age_s:
            self.state = f"paused: reading {skew:.2f} s from the frame (limit {self.config.max_age_s:g} s)"
            return self.log_constant
        x, y, w, h = self.config.footprint
        pixels = frame.data[y : y + h, x : x + w].reshape(-1, frame.data.shape[-1]).astype(np.float64)
        e = pixels - self.profile.array("dark_level")
        if background is not None:
            if background.shape[:2] == frame.data.shape[:2]:
                background = background[y : y + h, x : x + w]
            e = e - background.reshape(-1, frame.data.shape[-1])
        ok = np.all((e > self.profile.array("noise_floor")) & (pixels < self.profile.saturation_level), axis=1)
        if ok.sum() < max(4, pixels.shape[0] // 4):
            self.state = "paused: footprint too dark or saturated"
            return self.log_constant
        intr = self.profile.camera_intrinsics()
        rays = None
        camera_range = np.full(int(ok.sum()), reading.range_m)
        cos = np.ones(int(ok.sum()))
        if intr is not None:  # rays of the footprint only: the principal point shifted into it
            window = Intrinsics(intr.fx, intr.fy, intr.cx - x, intr.cy - y)
            rays = pixel_rays(window, pixels.shape[0] // w, w).reshape(-1, 3)[ok]
            if self.normal is not None:
                # The reading lies on the ray through the footprint's centre; every other footprint
                # pixel meets the tilted surface (the plane of the normal) at its own range.
                centre = pixel_rays(Intrinsics(intr.fx, intr.fy, intr.cx - x - (w - 1) / 2, intr.cy - y - (h - 1) / 2), 1, 1)[0, 0]
                facing = rays @ self.normal
                camera_range = reading.range_m * float(centre @ self.normal) / facing
                cos = np.abs(facing)
                self.incidence_deg = float(np.degrees(np.arccos(min(abs(float(centre @ self.normal)), 1.0))))
        path = path_length_from_camera_range(camera_range, self.profile.lamp_position_m, rays)
        # The light at the calibration's exposure: estimates from frames at any exposure agree.
        light = e[ok] if exposure_shift is None else e[ok] * np.exp(-np.asarray(exposure_shift))
        estimate = surface_log_constant(light, path, attenuation_differences, self.profile.reference_index)
        a = 1.0 if self.log_constant is None else self.config.smoothing
        self.log_constant = estimate if self.log_constant is None else (1 - a) * self.log_constant + a * estimate
        if self.attenuation is not None and rays is not None and self.normal is not None:
            # Only with the surface's normal: an absolute scale divides by cos γ.
            beam = beam_pattern(rays, self.beam_half_angle_deg)
            log_scale = np.log(surface_scale(light, camera_range, self.attenuation, cos, self.profile.lamp_radius_m or 0.0, beam))
            self.scale = np.exp(log_scale if self.scale is None else (1 - a) * np.log(self.scale) + a * log_scale)
        self.used += 1
        self.state = "correcting"
        return self.log_constant

    def status(self) -> dict:
        names = self.profile.channel_names
        target = self.profile.array("log_constant")
        ratio = None if self.log_constant is None else dict(zip(names, map(float, np.exp(self.log_constant - target))))
        return {"state": self.state, "readings_used": self.used, "reflectance_ratio_to_target": ratio,
                "incidence_deg": None if self.incidence_deg is None or self.normal is None else round(self.incidence_deg, 2),
                "scale": None if self.scale is None else dict(zip(names, map(float, self.scale)))}
