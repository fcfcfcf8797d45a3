"""The water's own light at the calibration plate's black patch: backscatter level and its
variance, and the plate's own light beside it (docs/physics.md §7)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError

from uwcam.calibration.noise_fit import mask_interior

# Pixels kept clear of a region's edges (blur, partial pixels) when measuring noise or backscatter.
EDGE = 2
# The plate within this many patch widths of the black patch carries its light across the patch:
# the sensor's fixed pattern averages over the ring (half a width left the attenuation differences
# twice as scattered by sensor), and a wider one follows a steep lamp field less well.
RING_REACH = 1


def dilate_mask(mask: NDArray[np.bool_], radius: int) -> NDArray[np.bool_]:
    if radius <= 0:
        return mask
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def locate_black_patch(signal: NDArray, black_mask: NDArray[np.bool_], plate_mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The black patch's pixels as the image shows them, near where the plate's pose put them.

    signal: (H, W, N) dark-corrected light; black_mask: (H, W) the patch projected from the pose;
    plate_mask: (H, W) plate pixels (the target region). A pose from a few markers can put the
    projected patch a few pixels off (the simulated tank at 1 m, four markers in view: 4 px, the
    patch's box reaching over the grey plate), and grey plate in the "black" reads as backscatter
    (565 DN where 1.5 DN is true, which also switched the fit to patch-local). Pixels within a
    margin of the projected box (a quarter of its smaller side, at least 5 px) darker, in the sum of
    the channels, than halfway between the box's median and the surrounding plate's median are
    the patch: the connected dark region overlapping the box most. The projected mask is kept
    where the image cannot tell (too little contrast, too few plate pixels around, or a dark
    region of implausible size)."""
    if not black_mask.any():
        return black_mask
    light = np.asarray(signal, np.float64).sum(axis=-1)
    ys, xs = np.nonzero(black_mask)
    size = int(min(np.ptp(ys), np.ptp(xs)) + 1)
    margin = max(5, size // 4)
    search = dilate_mask(black_mask, margin)
    surround = dilate_mask(black_mask, 2 * margin + 2) & ~dilate_mask(black_mask, margin + 1) & plate_mask
    if surround.sum() < 16:
        return black_mask
    dark, plate = float(np.median(light[black_mask])), float(np.median(light[surround]))
    if not plate > 1.5 * max(dark, 0.0) + 1e-9 or not np.isfinite(plate):
        return black_mask  # the patch does not stand out (no lit plate): nothing to locate it by
    candidates = (search & (light < (dark + plate) / 2)).astype(np.uint8)
    count, labels = cv2.connectedComponents(candidates, connectivity=4)
    if count < 2:
        return black_mask
    overlap = np.bincount(labels[black_mask], minlength=count)
    overlap[0] = 0
    found = labels == int(overlap.argmax())
    if not 0.5 * black_mask.sum() <= found.sum() <= 1.6 * black_mask.sum():
        return black_mask
    return found


@dataclass(frozen=True)
class BackscatterEstimate:
    """The water's light and the plate's at the black patch, at one distance.

    Attributes:
        level: (N,) backscatter in DN (dark-corrected) at the black patch; may be slightly
            negative from noise.
        variance: (N,) its variance from pixel noise, DN².
        black_mean: (N,) mean signal of the black patch, DN.
        plate_log: (N,) ln of the plate's own light (backscatter excluded pixel by pixel) at the
            patch's pixels.
        plate_log_variance: (N,) its variance from pixel noise.
        pixels: (H, W) the patch pixels used.
    """

    level: NDArray[np.float64]
    variance: NDArray[np.float64]
    black_mean: NDArray[np.float64]
    plate_log: NDArray[np.float64]
    plate_log_variance: NDArray[np.float64]
    pixels: NDArray[np.bool_]


def backscatter_at_black_patch(
    signal: NDArray,
    black_mask: NDArray[np.bool_],
    plate_mask: NDArray[np.bool_],
    black_reflectance: ArrayLike,
    plate_reflectance: ArrayLike,
    pixel_variance: NDArray | None = None,
) -> BackscatterEstimate:
    """Backscatter (DN, dark-corrected) in front of a plate, per channel, from its black patch.

    signal: (H, W, N) dark-corrected average of the distance's frames; masks (H, W). At each patch
    pixel, black = bs + ρ_black·X and the plate would read bs + ρ_plate·X, where X (lamp light ×
    geometry) is *that pixel's own*: the lamp lights patch and surrounding plate differently
    (spreading, beam pattern, incidence), so X is not the surround's mean. The plate's signal is
    interpolated across the patch by a smooth surface (cubic; quadratic or a plane on few pixels)
    fitted to the plate within RING_REACH patch widths of it, then X = (plate − black)/(ρ_plate −
    ρ_black) and bs = black − ρ_black·X per pixel, averaged (docs/calibration.md, "Backscatter at
    the black patch").
    Edge pixels of patch and plate are left out (blur, partial pixels). ``pixel_variance``
    (H, W, N): each pixel's noise variance, for the estimate's variance (0 without it).
    """
    rho_b = np.asarray(black_reflectance, dtype=np.float64)
    rho_p = np.asarray(plate_reflectance, dtype=np.float64)
    if not black_mask.any():
        raise UserInputError("the black patch region holds no pixels; check the regions")
    patch = mask_interior(black_mask, EDGE)
    edge = EDGE
    if patch.sum() < 4:
        patch, edge = black_mask, 0  # a patch a few pixels wide (small or far): keep every pixel of it
    ys, xs = np.nonzero(black_mask)
    size = max(int(min(np.ptp(ys), np.ptp(xs)) + 1), 4)
    ring = dilate_mask(black_mask, max(RING_REACH * size, 4)) & ~dilate_mask(black_mask, edge) & mask_interior(plate_mask, edge)
    ring &= ~black_mask
    if ring.sum() < 6:
        raise UserInputError("the black patch is not surrounded by enough plate pixels to interpolate the plate's light across it; "
                             "check the regions (the patch must lie inside the plate, away from its edges)")
    cy, cx, scale = ys.mean(), xs.mean(), float(size)
    degree = 3 if ring.sum() >= 60 else 2 if ring.sum() >= 24 else 1  # a few ring pixels only support a plane

    def design(mask: NDArray[np.bool_]) -> NDArray:
        yy, xx = np.nonzero(mask)
        u, v = (xx - cx) / scale, (yy - cy) / scale
        return np.stack([u ** (d - i) * v**i for d in range(degree + 1) for i in range(d + 1)], axis=1)

    a_ring, a_patch = design(ring), design(patch)
    plate_values = signal[ring]
    coef, *_ = np.linalg.lstsq(a_ring, plate_values, rcond=None)
    plate_at_patch = a_patch @ coef
    black = signal[patch]
    lit = (plate_at_patch - black) / (rho_p - rho_b)
    level = (black - rho_b * lit).mean(axis=0)
    # The plate's own light at these pixels, ρp·X, free of backscatter pixel by pixel whatever
    # its spatial pattern (it cancels in plate − black).
    difference = (plate_at_patch - black).mean(axis=0)
    plate_log = np.log(np.maximum(difference, 1e-30)) + np.log(rho_p / (rho_p - rho_b))
    variance = np.zeros(signal.shape[-1])
    log_variance = np.zeros(signal.shape[-1])
    if pixel_variance is not None:
        # bs = α·mean(black) − β·mean(plate fit), α = ρp/(ρp−ρb), β = ρb/(ρp−ρb).
        alpha, beta = rho_p / (rho_p - rho_b), rho_b / (rho_p - rho_b)
        var_black = pixel_variance[patch].mean(axis=0) / patch.sum()
        mean_row = a_patch.mean(axis=0)
        leverage = float(mean_row @ np.linalg.pinv(a_ring.T @ a_ring) @ mean_row)
        var_plate = pixel_variance[ring].mean(axis=0) * leverage
        variance = alpha**2 * var_black + beta**2 * var_plate
        log_variance = (var_black + var_plate) / np.maximum(difference, 1e-30) ** 2
    return BackscatterEstimate(level, variance, black.mean(axis=0), plate_log, log_variance, patch)
