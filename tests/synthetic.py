"""Noise-free forward model E_k = K_k ρ_k g exp(−c_k d_T) (docs/physics.md §2) for tests.

Deliberately independent of uwcam's own code apart from the pinhole ray helper,
so that inverting these frames checks uwcam against the physics, not itself.
"""

from __future__ import annotations

import numpy as np

from uwcam.optics.geometry import Intrinsics, pixel_rays

RGB_ATTENUATION = np.array([0.46, 0.11, 0.06])  # Jerlov II at 675/575/475 nm, 1/m


def plate_frame(
    distance: float,
    attenuation: np.ndarray,
    constant: np.ndarray,
    reflectance: np.ndarray,
    shape: tuple[int, int] = (96, 128),
    lamp: np.ndarray = np.zeros(3),
    lamp_radius: float = 0.15,
    fov_deg: float = 50.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A plate square to the axis at ``distance`` m: (frame (H, W, N) float64, camera range (H, W))."""
    h, w = shape
    rays = pixel_rays(Intrinsics.from_fov(w, h, fov_deg), h, w)
    dc = distance / rays[..., 2]
    ds = np.linalg.norm(dc[..., None] * rays - lamp, axis=-1)
    # Spreading × cos of the lamp's incidence on the plate (normal along −z), as the simulator has it.
    g = (lamp_radius / (ds + lamp_radius)) ** 2 * (distance - lamp[2]) / ds
    frame = constant * reflectance * g[..., None] * np.exp(-attenuation * (dc + ds)[..., None])
    return frame, dc


def to_counts(frame: np.ndarray, peak: float, dtype=np.uint16) -> np.ndarray:
    """Scale so the brightest value is ``peak`` and round to integer codes."""
    return np.clip(np.rint(frame * (peak / frame.max())), 0, np.iinfo(dtype).max).astype(dtype)


def make_profile(
    attenuation,
    log_constant,
    *,
    names=None,
    read_noise=0.0,
    shot_gain=0.0,
    noise_floor=0.0,
    dark_level=0.0,
    saturation_level=65535.0,
    quantisation_step=1.0,
    lamp=(0.0, 0.0, 0.0),
    intrinsics=None,
    reference=0,
):
    """A CalibrationProfile with the given per-channel truths (scalars broadcast)."""
    from uwcam.calibration.profile import CalibrationProfile, ChannelCalibration, Provenance

    c = np.asarray(attenuation, dtype=float)
    b = np.asarray(log_constant, dtype=float)
    n = len(c)
    names = names or (["R", "G", "B"] if n == 3 else [f"ch{k}" for k in range(n)])

    def per(value, k):
        return float(np.broadcast_to(np.asarray(value, dtype=float), (n,))[k])

    channels = [
        ChannelCalibration(
            name=names[k],
            attenuation_difference=float(c[k] - c[reference]),
            log_constant=float(b[k] - b[reference]),
            read_noise=per(read_noise, k),
            shot_gain=per(shot_gain, k),
            noise_floor=per(noise_floor, k),
            dark_level=per(dark_level, k),
        )
        for k in range(n)
    ]
    intr = None if intrinsics is None else {"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy}
    return CalibrationProfile(
        name="test",
        reference_channel=names[reference],
        channels=channels,
        saturation_level=saturation_level,
        quantisation_step=quantisation_step,
        lamp_position_m=tuple(float(v) for v in lamp),
        intrinsics=intr,
        provenance=Provenance(created="2026-01-01T00:00:00+00:00", method="synthetic"),
    )
