"""Lens shading (vignetting): how much less light a lens passes to a pixel off its axis.

Every real lens passes less light toward the edge of its view: the natural fall-off goes as cos⁴ of
the ray's angle θ off the optical axis, and apertures and ports take more at the corners. The
factor V(p) multiplies every channel alike (achromatic), so it cancels in the colour ratios that
give the range; it does not cancel where the spatial shape of absolute light is modelled: the water's
own light across the view (:mod:`uwcam.water.backscatter`), a black patch's ring of plate, or a
surface's reflectance from the rangefinder's range.

uwcam models it radially about the principal point, in log:

    ln V(ρ) = a·ln(1 + ρ²) + b·ρ⁴,   ρ = tan θ = sqrt(x² + y²) / z of the pixel's ray,

where a = −2, b = 0 is the natural fall-off cos⁴θ = (1 + ρ²)⁻² exactly, and b takes the steeper or
gentler edges of real lenses and ports. V = 1 on the axis. Two numbers (a, b), stored in the calibration
profile's ``lens_shading`` and measured from frames of a uniformly lit field (a diffuser over the
port, an evenly lit white target filling the view: ``uwcam calibrate --flat-field``), or estimated
with the water's light from open-water frames where the profile has none.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays

MAX_SHADING_LOSS = 0.95
"""The most light a lens may lose at a pixel (V ≥ 0.05): a model that takes more in the image is not
a lens's shading but a mistaken measurement (a target not evenly lit, a hand in the view)."""


def tan_squared(rays: NDArray) -> NDArray[np.float64]:
    """ρ² = tan²θ of unit rays (..., 3): (x² + y²)/z²."""
    r = np.asarray(rays, np.float64)
    return (r[..., 0] ** 2 + r[..., 1] ** 2) / r[..., 2] ** 2


def shading_basis(rays: NDArray) -> NDArray[np.float64]:
    """(..., 2) the terms ln(1 + ρ²), ρ⁴ of ln V at rays (..., 3)."""
    t2 = tan_squared(rays)
    return np.stack([np.log1p(t2), t2 * t2], axis=-1)


def shading_at_rays(coefficients: NDArray | tuple[float, float], rays: NDArray) -> NDArray[np.float64]:
    """V at unit rays (..., 3) for ln V = a·ln(1 + ρ²) + b·ρ⁴ with ``coefficients`` (a, b): (...,)."""
    return np.exp(shading_basis(rays) @ np.asarray(coefficients, np.float64))


def shading_map(coefficients: NDArray | tuple[float, float], intrinsics: Intrinsics, height: int,
                width: int) -> NDArray[np.float64]:
    """(H, W) V of every pixel of a ``height`` × ``width`` image with ``intrinsics``."""
    return shading_at_rays(coefficients, pixel_rays(intrinsics, height, width))


def fit_shading(frames: NDArray, intrinsics: Intrinsics, dark_level: NDArray | float = 0.0,
                full_scale: float | None = None) -> tuple[NDArray[np.float64], float]:
    """(a, b) of ln V and the rms (in ln) of what the radial model leaves, from frames of a
    uniformly lit field.

    frames: (H, W, N) or (K, H, W, N) raw DN of one evenly lit, featureless view (a diffuser over the
    port, a white target filling the view, lit evenly); dark_level: (N,) or scalar DN taken off
    first; full_scale: the sensor's largest value (pixels within 2 % of it are clipped and left out).
    Every channel holds the same shading: the fit is to ln of each channel's light relative to its
    own level, all channels at once, by least squares on a sample of pixels.

    Raises UserInputError where the frames cannot hold a shading: non-finite values, too little
    light, a view too unevenly lit for a lens (the model leaves more than 5 % rms, or takes more
    than :data:`MAX_SHADING_LOSS` anywhere in the view).
    """
    data = np.asarray(frames, np.float64)
    if data.ndim == 3:
        data = data[None]
    if data.ndim != 4:
        raise UserInputError(f"flat-field frames must be (H, W, channels) images, got shape {np.shape(frames)}")
    if not np.isfinite(data).all():
        raise UserInputError("a flat-field frame holds non-finite pixel values (NaN or inf): take it again")
    k, h, w, n = data.shape
    mean = data.mean(axis=0) - np.asarray(dark_level, np.float64)
    rays = pixel_rays(intrinsics, h, w)
    step = max(1, min(h, w) // 60)
    sample = mean[::step, ::step].reshape(-1, n)
    basis = shading_basis(rays[::step, ::step]).reshape(-1, 2)
    usable = np.all(sample > 0, axis=1)
    if full_scale is not None:
        usable &= np.all(data.max(axis=0)[::step, ::step].reshape(-1, n) < 0.98 * full_scale, axis=1)
    if usable.mean() < 0.5:
        raise UserInputError(
            f"the flat-field frames have light in only {usable.mean():.0%} of the view (the rest dark or clipped): "
            "fill the view with an evenly lit target or a diffuser over the port, exposed below saturation")
    logs = np.log(sample[usable])  # (P, N)
    x = basis[usable]
    # ln E_k = ln L_k + a·ρ² + b·ρ⁴: one shading, a level per channel.
    design = np.concatenate([np.repeat(x, n, axis=0), np.tile(np.eye(n), (x.shape[0], 1))], axis=1)
    solution, *_ = np.linalg.lstsq(design, logs.reshape(-1), rcond=None)
    coefficients = solution[:2]
    rms = float(np.sqrt(np.mean((design @ solution - logs.reshape(-1)) ** 2)))
    corner = shading_at_rays(coefficients, rays[[0, 0, -1, -1], [0, -1, 0, -1]])
    if rms > 0.05 or corner.min() < 1.0 - MAX_SHADING_LOSS or corner.max() > 1.5:
        raise UserInputError(
            f"the flat-field frames do not look like an evenly lit view through a lens (the radial shading model "
            f"leaves {rms:.1%} rms, corners at {corner.min():.2f}–{corner.max():.2f} of the centre's light): "
            "light the target evenly, or put a diffuser over the port, and take them again")
    return coefficients, rms
