"""Compensated ranges that are no measurement: too uncertain for their length, or alone in their block.

Once the water's light is subtracted, what is left of a surface's light may be within the noise
and the model's doubt; the transform's log of it is then anything. Two rules take such pixels'
ranges (reason 3, "backscatter only"): a standard deviation beyond :data:`MAX_RELATIVE_SD` times
the range, and a block of the backscatter's grid where too few pixels have a range
(:data:`MIN_SUPPORT`). :class:`uwcam.water.frame_compensator.BackscatterCompensator` applies both.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import HAVE_NUMBA, njit
from uwcam.optics.validity import Reason
from uwcam.ranging.result import RangeResult

MAX_RELATIVE_SD = 2.0
"""A compensated range whose standard deviation exceeds this many times the range itself is not
a range: what is left of the surface's light after the subtraction is within the noise and the
model's uncertainty (reason 3), the transform's log of it anything. Murky water then leaves
pixels without a range instead of ranges hundreds of per cent out."""


def _drop_unresolved_py(range_m, variance, reasons, factor2, reason):
    """In place, over flat C-contiguous arrays: where variance > range²·factor2 (float32, as numpy
    computes it), the range and variance become NaN and the reason ``reason``. One pass instead of
    numpy's six over the whole frame."""
    nan = np.float32(np.nan)
    for i in range(range_m.shape[0]):
        r = range_m[i]
        if variance[i] > (r * r) * factor2:
            range_m[i] = nan
            variance[i] = nan
            reasons[i] = reason


_drop_unresolved = njit(cache=True, nogil=True)(_drop_unresolved_py) if HAVE_NUMBA else None


def drop_unresolved(result: RangeResult, max_relative_sd: float = MAX_RELATIVE_SD) -> None:
    """Pixels of ``result`` whose standard deviation exceeds ``max_relative_sd`` times their range
    have no range: reason 3, "backscatter only" (see :data:`MAX_RELATIVE_SD`). In place."""
    factor2 = np.float32(max_relative_sd**2)
    arrays = (result.range, result.variance, result.reasons)
    if _drop_unresolved is not None and all(a.flags.c_contiguous for a in arrays):
        _drop_unresolved(*(a.reshape(-1) for a in arrays), factor2, np.uint8(Reason.BACKSCATTER_ONLY))
        return
    limit = np.multiply(result.range, result.range)
    limit *= factor2
    with np.errstate(invalid="ignore"):
        lost = np.greater(result.variance, limit)
    if lost.any():
        np.copyto(result.range, np.float32(np.nan), where=lost)
        np.copyto(result.variance, np.float32(np.nan), where=lost)
        np.copyto(result.reasons, np.uint8(Reason.BACKSCATTER_ONLY), where=lost)


MIN_SUPPORT = 0.1
"""Share of a block's pixels (:data:`BLOCK` × :data:`BLOCK`: 7 of 64, saturated ones left out)
that must have a range for any of them to keep it, once the water's light is subtracted (counted
on what the compensation ranged, before the judge of the water's light, which after compensation
took no pixel from the water study's Jerlov II cell at 7 m). Where the surface is lost in the
water's light, a few pixels still pass each test of "clearly above it" by chance, and their
ranges are of that noise: Jerlov III at 5 m, 16 frames fused, 9 pixels 62 % short, every one
beyond 3σ, in blocks where nothing else had a range. Isolated like that, a pass is more likely
chance than a surface. The cost where the light is marginal but the ranges right: Jerlov II at
7 m, one frame, 38.8 → 38.3 % of the image keeps a range (a quarter of the block: 37.4 %)."""


def drop_unsupported(result: RangeResult, grid: tuple[int, int]) -> None:
    """In place: the pixels with a range in a block of ``grid`` ((gh, gw) blocks over the frame:
    the backscatter's) where fewer than :data:`MIN_SUPPORT` of the pixels that could have one
    have one lose it (reason 3); a saturated pixel could not, so a highlight beside a surface
    takes no range from it."""
    valid = np.isfinite(result.range).astype(np.float32)
    could = (result.reasons != Reason.SATURATED).astype(np.float32)
    gh, gw = grid
    share = cv2.resize(valid, (gw, gh), interpolation=cv2.INTER_AREA)
    drop_blocks(result, share < MIN_SUPPORT * cv2.resize(could, (gw, gh), interpolation=cv2.INTER_AREA))


def drop_blocks(result: RangeResult, blocks: NDArray[np.bool_]) -> None:
    """In place: the pixels with a range in the blocks marked in ``blocks`` ((gh, gw) over the
    frame, each block its pixels' nearest) lose it: NaN range, variance and common share, reason 3."""
    if not blocks.any():
        return
    h, w = result.range.shape
    lost = cv2.resize(blocks.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    lost &= np.isfinite(result.range)
    if not lost.any():
        return
    result.range[lost] = np.nan
    result.variance[lost] = np.nan
    result.reasons[lost] = Reason.BACKSCATTER_ONLY
    if result.common_variance is not None:
        result.common_variance[lost] = np.nan
