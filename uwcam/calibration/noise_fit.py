"""The camera's noise model from a calibration: per-channel read noise, shot gain and fixed pattern,
fitted to the plate's pixels frame to frame (docs/physics.md §4)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError


# Brightness bins of the plate, each a point of the noise-model fit.
NOISE_BINS = 4


@dataclass(frozen=True)
class NoisePoint:
    """Noise observed in one region of one distance's frames, per channel (DN, dark-corrected)."""

    mean: NDArray[np.float64]
    """(N,) mean signal E over the region."""
    mean_square: NDArray[np.float64]
    """(N,) mean of E² over the region (the fixed-pattern term goes with E², not with Ē²)."""
    spatial_variance: NDArray[np.float64]
    """(N,) pixel-to-pixel variance of the frames' average (second differences along rows:
    smooth illumination cancels): fixed pattern + temporal/frames."""
    temporal_variance: NDArray[np.float64] | None
    """(N,) frame-to-frame variance from the differences between frames; None with one frame."""
    frames: int
    count: int
    shows_fixed_pattern: bool = True
    """Whether its spatial variance counts in the fixed-pattern fit: not for light that is not the
    plate's (the water beside it varies from pixel to pixel by more than the sensor's pattern)."""


def mask_interior(mask: NDArray[np.bool_], margin: int) -> NDArray[np.bool_]:
    if margin <= 0:
        return mask
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def noise_point(frames: list[NDArray] | NDArray, mask: ArrayLike, dark_level: ArrayLike = 0.0,
                shows_fixed_pattern: bool = True) -> NoisePoint:
    """Noise statistics of ``frames`` (m frames (H, W, N) of one static scene) inside ``mask`` (H, W).

    Temporal variance: per pixel, the unbiased variance over the m frames, averaged over the
    region. Spatial variance: of the frames' average, from second differences along rows,
    x[i−1] − 2x[i] + x[i+1], whose variance is 6σ² for independent pixel noise while a
    linear gradient of illumination cancels exactly.
    """
    stack = np.asarray(frames, dtype=np.float64)
    if stack.ndim == 3:
        stack = stack[None]
    m_frames = stack.shape[0]
    x = stack.mean(axis=0) - np.asarray(dark_level, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    triple = m[:, 2:] & m[:, 1:-1] & m[:, :-2]
    count = int(triple.sum())
    if count < 2:
        raise UserInputError("a noise region holds fewer than 2 usable pixels; check the target and black patch regions")
    centre = x[:, 1:-1][triple]
    second = (x[:, :-2] - 2.0 * x[:, 1:-1] + x[:, 2:])[triple]
    spatial = second.var(axis=0) / 6.0
    temporal = None
    if m_frames >= 2:
        temporal = stack[:, :, 1:-1][:, triple].var(axis=0, ddof=1).mean(axis=0)
    return NoisePoint(centre.mean(axis=0), (centre**2).mean(axis=0), spatial, temporal, m_frames, count,
                      shows_fixed_pattern)


DIM_BINS = 2
"""Brightness bins of the light beside the plate dimmer than the plate, each a point of the noise fit."""


def dim_noise_points(stack: list[NDArray], brightness: NDArray, occupied: NDArray[np.bool_], clipped: NDArray[np.bool_],
                     dark_level: ArrayLike, plate_floor: float, distance: float,
                     margin: int = 7) -> list[tuple[str, NoisePoint]]:
    """Noise points of the light beside the target (``occupied``: the plate's and black patch's
    regions, (H, W)) dimmer than the plate's dimmest (``plate_floor``, of ``brightness``: the (H, W)
    box mean of the channels' sum, dark-corrected, that the plate's bins are made of): the water or
    tank beside it, frame to frame.

    The plate's bins hold thousands of DN, where read noise is a few percent of the variance: fitted
    from those and a small black patch over 2-4 frames, it came out 0-50 DN for a true 26. Light of
    a few hundred DN pins it. Frame to frame only (``shows_fixed_pattern`` False): the water's light
    varies from pixel to pixel by more than the sensor's pattern. Light that moves (particles, fish)
    only adds temporal variance: the read noise can only come out larger, σ with it. ``stack``: the
    frames of one distance (at least 2); ``clipped``: pixels saturated in any frame."""
    beside = mask_interior(~occupied & ~clipped, margin)
    dim = beside & (brightness < plate_floor)
    triples = dim[:, 2:] & dim[:, 1:-1] & dim[:, :-2]
    if triples.sum() < 64 * DIM_BINS:
        return []
    edges = np.quantile(brightness[dim], np.linspace(0, 1, DIM_BINS + 1))
    points = []
    for j in range(DIM_BINS):
        part = dim & (brightness >= edges[j]) & (brightness <= edges[j + 1])
        points.append((f"beside the plate {distance:g} m, level {j + 1}",
                       noise_point(stack, part, dark_level, shows_fixed_pattern=False)))
    return points


def _nonnegative_least_squares(a: NDArray, y: NDArray, w: NDArray) -> NDArray:
    """argmin Σ w (a·p − y)² over p ≥ 0, by trying every set of free parameters (few columns)."""
    n_par = a.shape[1]
    best, best_cost = np.zeros(n_par), float(np.sum(w * y**2))
    sw = np.sqrt(w)
    for subset in range(1, 2**n_par):
        cols = [j for j in range(n_par) if subset >> j & 1]
        sol, *_ = np.linalg.lstsq(a[:, cols] * sw[:, None], y * sw, rcond=None)
        if np.all(sol >= 0):
            p = np.zeros(n_par)
            p[cols] = sol
            cost = float(np.sum(w * (a @ p - y) ** 2))
            if cost < best_cost - 1e-12 * abs(best_cost):
                best, best_cost = p, cost
    return best


@dataclass(frozen=True)
class NoiseFit:
    """Per-channel noise model: σ² = read² + shot_gain·E + (fixed_pattern·E)² + step²/12."""

    read_noise: NDArray[np.float64]
    """(N,) DN rms."""
    shot_gain: NDArray[np.float64]
    """(N,) DN per photo-electron."""
    fixed_pattern: NDArray[np.float64]
    """(N,) relative rms of the pixel response non-uniformity."""
    method: str


def fit_noise(points: list[NoisePoint], quantisation_step: float = 1.0) -> NoiseFit:
    """Read noise, shot gain and fixed pattern per channel from region noise points.

    With repeated frames, the temporal variances give read and shot noise
    (t − step²/12 = read² + gain·E) and the spatial variance beyond temporal/frames gives the
    fixed pattern (s − t/m = fpn²·mean(E²)). With single frames, the spatial variances alone
    are fitted with all three terms. Every term is kept non-negative; a variance of 0 (noise-free
    frames) gives all terms 0, and users of the model fall back to the quantisation floor.
    Weights are 1/variance², so every point counts by its relative error.
    """
    if not points:
        raise ValueError("fit_noise needs at least one noise point")
    n = points[0].mean.shape[0]
    q = quantisation_step**2 / 12.0
    read2, gain, fpn2 = np.zeros(n), np.zeros(n), np.zeros(n)
    temporal = [p for p in points if p.temporal_variance is not None]
    for k in range(n):
        if temporal:
            e = np.array([p.mean[k] for p in temporal])
            t = np.array([p.temporal_variance[k] for p in temporal])
            w = 1.0 / np.maximum(t, q + 1e-12) ** 2
            read2[k], gain[k] = _nonnegative_least_squares(np.stack([np.ones_like(e), e], 1), t - q, w)
            patterned = [p for p in temporal if p.shows_fixed_pattern] or temporal
            e = np.array([p.mean[k] for p in patterned])
            e2 = np.array([p.mean_square[k] for p in patterned])
            s = np.array([p.spatial_variance[k] for p in patterned])
            t_model = read2[k] + gain[k] * np.maximum(e, 0) + q
            m = np.array([p.frames for p in patterned], dtype=np.float64)
            ws = 1.0 / np.maximum(s, q + 1e-12) ** 2
            fpn2[k] = _nonnegative_least_squares(e2[:, None], s - t_model / m, ws)[0]
        else:
            e = np.array([p.mean[k] for p in points])
            e2 = np.array([p.mean_square[k] for p in points])
            s = np.array([p.spatial_variance[k] for p in points])
            w = 1.0 / np.maximum(s, q + 1e-12) ** 2
            read2[k], gain[k], fpn2[k] = _nonnegative_least_squares(np.stack([np.ones_like(e), e, e2], 1), s - q, w)
    method = "temporal from repeated frames, fixed pattern beyond it" if temporal else "spatial spread of single frames"
    return NoiseFit(np.sqrt(read2), gain, np.sqrt(fpn2), method)


def fit_noise_model(
    means: ArrayLike, noise_variances: ArrayLike, quantisation_step: float = 1.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read noise (DN rms) and shot gain (DN/e⁻) per channel from (mean, temporal variance) pairs (n, N).

    σ² − step²/12 = read² + gain·E by weighted non-negative least squares (see :func:`fit_noise`).
    """
    mu = np.asarray(means, dtype=np.float64)
    var = np.asarray(noise_variances, dtype=np.float64)
    pts = [NoisePoint(mu[i], mu[i] ** 2, var[i], var[i], 1, 2) for i in range(mu.shape[0]) if np.all(np.isfinite(var[i]))]
    if not pts:
        return np.zeros(mu.shape[1]), np.zeros(mu.shape[1])
    fit = fit_noise(pts, quantisation_step)
    return fit.read_noise, fit.shot_gain


def variance_floor(signal: ArrayLike, quantisation_step: float) -> NDArray[np.float64]:
    """The least variance (DN²) a value can have: its quantisation, step²/12, or for float data
    (step 0) the float32 rounding of the value itself (relative step 2⁻²³). Never 0 for E > 0."""
    e = np.abs(np.asarray(signal, dtype=np.float64))
    step = np.where(quantisation_step > 0, quantisation_step, np.maximum(e, 1e-30) * 2.0**-23)
    return step**2 / 12.0


def signal_variance_temporal(signal: NDArray, noise: NoiseFit) -> NDArray:
    """Frame-to-frame variance (DN²) of ``signal`` (…, N) under a fitted noise model, quantisation excluded
    (it is added by the floor)."""
    return noise.read_noise**2 + noise.shot_gain * np.maximum(signal, 0.0)
