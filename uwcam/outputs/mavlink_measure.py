"""What the MAVLink output sends, computed from a published frame (pure functions): the range
statistic of a region with its covariance and quality, the obstacle sectors, the distance limits
the profile can measure. Field semantics: :mod:`uwcam.outputs.mavlink`."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.config import MavlinkConfig
from uwcam.optics.geometry import Intrinsics, camera_range_from_path_length, pixel_rays
from uwcam.optics.orientation import measurable_range_m
from uwcam.optics.validity import Reason
from uwcam.runtime.published import Published

log = logging.getLogger(__name__)

UINT8_MAX = 255
UINT16_MAX = 65535
MAX_DISTANCE_CM = 32767
"""ArduPilot holds rangefinder limits as int16 centimetres."""
SECTORS = 72
"""OBSTACLE_DISTANCE's sector count (MAVLink common.xml)."""


@dataclass(frozen=True)
class Measurement:
    """What one processed frame says to the autopilot. Distances in metres, angles in degrees."""

    frame_number: int
    capture_monotonic_ns: int
    wall_time: float
    distance_m: float | None
    """None when the frame gives no trustworthy distance (``reason`` says why)."""
    variance_m2: float | None
    valid_fraction: float
    reason: str
    min_distance_m: float
    max_distance_m: float
    horizontal_fov_rad: float = 0.0
    vertical_fov_rad: float = 0.0
    sectors_cm: NDArray[np.uint16] | None = None
    """(72,) OBSTACLE_DISTANCE distances, or None when not computed."""
    sector_increment_deg: float = 0.0
    sector_offset_deg: float = 0.0


def distance_bounds(path_length_bounds: tuple[float, float], lamp_position_m) -> tuple[float, float]:
    """Camera range on the optical axis (m) at the processing path-length bounds; a bound too
    short to reach past the lamp gives 0."""
    near, far = camera_range_from_path_length(np.array(path_length_bounds, dtype=np.float64), lamp_position_m)
    return (0.0 if not np.isfinite(near) else max(0.0, float(near))), (0.0 if not np.isfinite(far) else float(far))


def _row_medians(values: NDArray) -> tuple[NDArray, NDArray]:
    """Median of the finite entries of each row of (n, k) ``values`` and their count, without
    numpy's nanmedian (which falls back to a Python loop per row when NaNs are present)."""
    ordered = np.sort(np.where(np.isfinite(values), values, np.inf), axis=1)
    count = np.isfinite(values).sum(axis=1)
    rows = np.arange(values.shape[0])
    lo = ordered[rows, np.maximum(count - 1, 0) // 2]
    hi = ordered[rows, np.maximum(count, 1) // 2 - (count == 0)]
    with np.errstate(invalid="ignore"):  # rows without a finite entry: NaN, on purpose
        return np.where(count > 0, 0.5 * (lo + hi), np.nan), count


def tile_medians(values: NDArray, variance: NDArray, rows: int, cols: int) -> tuple[NDArray, NDArray]:
    """Median value and median variance of each rows×cols tile with at least half its pixels
    valid (finite); tiles at the edges may be smaller. Returns two 1-D arrays, one entry per
    such tile."""
    h, w = values.shape
    hb, wb = -(-h // rows), -(-w // cols)
    padded = np.full((hb * rows, wb * cols), np.nan, dtype=np.float64)
    padded[:h, :w] = values
    pvar = np.full_like(padded, np.nan)
    pvar[:h, :w] = variance
    tiles = padded.reshape(hb, rows, wb, cols).transpose(0, 2, 1, 3).reshape(hb * wb, rows * cols)
    sizes = np.minimum(rows, h - np.arange(hb) * rows)[:, None] * np.minimum(cols, w - np.arange(wb) * cols)[None, :]
    medians, count = _row_medians(tiles)
    good = count * 2 >= sizes.ravel()
    if not good.any():
        return np.empty(0), np.empty(0)
    tvar = pvar.reshape(hb, rows, wb, cols).transpose(0, 2, 1, 3).reshape(hb * wb, rows * cols)[good]
    tvar = np.where(np.isfinite(tiles[good]), tvar, np.nan)  # the variances of the valid pixels only
    return medians[good], _row_medians(tvar)[0]


def region_statistic(distance: NDArray, variance: NDArray, statistic: str, block: int) -> tuple[float | None, float | None, float]:
    """(distance, its per-pixel variance, valid fraction) over one region.

    distance, variance: (h, w) metres and m², NaN where invalid. median: the median of the
    valid pixels, with their median variance. minimum: the smallest median over block×block
    tiles (so that no single noisy pixel sets it), with that tile's median variance.
    """
    ok = np.isfinite(distance)
    n = int(ok.sum())
    fraction = n / distance.size if distance.size else 0.0
    if n == 0:
        return None, None, fraction
    if statistic == "median":
        v = variance[ok][::4]  # a describing figure: every 4th valid pixel's variance is plenty
        v = v[np.isfinite(v)]
        return float(np.median(distance[ok])), (float(np.median(v)) if v.size else None), fraction
    medians, variances = tile_medians(distance, variance, block, block)
    if medians.size == 0:
        return None, None, fraction
    i = int(np.argmin(medians))
    return float(medians[i]), (float(variances[i]) if np.isfinite(variances[i]) else None), fraction


def covariance_cm2(variance_m2: float | None) -> int:
    """DISTANCE_SENSOR covariance: cm², rounded up; UINT8_MAX when unknown or above 254 cm²."""
    if variance_m2 is None or not np.isfinite(variance_m2) or variance_m2 < 0:
        return UINT8_MAX
    cm2 = math.ceil(variance_m2 * 1e4)
    return cm2 if cm2 < UINT8_MAX else UINT8_MAX


def signal_quality(valid_fraction: float) -> int:
    """Valid fraction as MAVLink's signal quality: percent, 2–100 for a reading that is sent
    (0 would mean unknown and 1 invalid)."""
    return int(min(100, max(2, round(100 * valid_fraction))))


def sector_layout(intrinsics: Intrinsics, width: int, yaw_deg: float = 0.0) -> tuple[NDArray[np.int64], float, float]:
    """Which of the 72 sectors each image column falls in, the sector width and sector 0's centre.

    Returns (sector index per column (width,), increment in degrees, angle of sector 0's centre
    in degrees, clockwise positive from the vehicle's front, with the camera's yaw added).
    """
    left = math.degrees(math.atan2(-0.5 - intrinsics.cx, intrinsics.fx))
    right = math.degrees(math.atan2(width - 0.5 - intrinsics.cx, intrinsics.fx))
    increment = (right - left) / SECTORS
    columns = np.degrees(np.arctan2(np.arange(width) - intrinsics.cx, intrinsics.fx))
    index = np.clip(((columns - left) / increment).astype(np.int64), 0, SECTORS - 1)
    centre = left + increment / 2 + yaw_deg
    return index, increment, (centre + 180.0) % 360.0 - 180.0


def sector_distances(horizontal: NDArray, reasons: NDArray, column_sector: NDArray, min_cm: int, max_cm: int,
                     block: int) -> NDArray[np.uint16]:
    """OBSTACLE_DISTANCE ``distances``: per sector the robust minimum horizontal distance (cm).

    horizontal: (h, w) metres, NaN where invalid; reasons: (h, w) :class:`Reason` codes;
    column_sector: (w,) sector of each column. A sector's distance is the smallest median over
    tiles of ``block`` rows × the sector's columns. A sector without such a tile is
    ``max_cm + 1`` (no obstacle) when most of its pixels saw only lit water, else UINT16_MAX
    (unknown).
    """
    out = np.full(SECTORS, UINT16_MAX, dtype=np.uint16)
    for s in np.unique(column_sector):
        cols = column_sector == s
        d = horizontal[:, cols]
        medians, _ = tile_medians(d, np.zeros_like(d), block, d.shape[1])
        if medians.size:
            out[s] = int(np.clip(round(float(medians.min()) * 100), min_cm, max_cm))
        elif np.mean(reasons[:, cols] == Reason.BACKSCATTER_ONLY) >= 0.5:
            out[s] = max_cm + 1
    return out


class PixelRays:
    """Unit rays for the current intrinsics and image size, recomputed only when they change."""

    def __init__(self) -> None:
        self.key = None
        self.rays: NDArray | None = None

    def get(self, intrinsics: Intrinsics | None, height: int, width: int) -> NDArray | None:
        key = (intrinsics, height, width)
        if key != self.key:
            self.key = key
            self.rays = None if intrinsics is None else pixel_rays(intrinsics, height, width).astype(np.float32)
        return self.rays


def reach_of(profile, corrector) -> tuple[float | None, str]:
    """The range (m) the profile can measure on the surface the rangefinder sees, and where the
    maximum distance comes from; None when it cannot be known (then the path-length bound holds)."""
    if corrector is None or getattr(corrector, "attenuation", None) is None:
        return None, "processing.path_length_bounds (the profile has no absolute attenuations)"
    if corrector.scale is None:
        return None, "processing.path_length_bounds (no surface scale yet: it needs a rangefinder reading)"
    floor = profile.array("noise_floor")
    if not np.any(floor > 0):
        return None, "processing.path_length_bounds (the profile has no noise floor)"
    reach = measurable_range_m(corrector.attenuation, corrector.scale, floor, profile.lamp_radius_m or 0.0)
    if not math.isfinite(reach):
        return None, "processing.path_length_bounds (the noise floor limits fewer than two channels)"
    return reach, "the profile's noise floor and attenuations, on the surface the rangefinder measured"


def measure(published: Published, config: MavlinkConfig, profile, path_length_bounds: tuple[float, float],
            rays_cache: PixelRays | None = None, reach_m: float | None = None) -> Measurement:
    """Reduce one published frame to a :class:`Measurement` (runs in the output's thread);
    ``reach_m``: the range the profile can measure (:func:`reach_of`), a lower maximum distance."""
    result, frame = published.result, published.frame
    h, w = result.range.shape
    intrinsics = profile.camera_intrinsics()
    rays = (rays_cache or PixelRays()).get(intrinsics, h, w)
    near, far = distance_bounds(path_length_bounds, profile.lamp_position_m)
    if reach_m is not None and near < reach_m < far:
        far = reach_m
    base = dict(frame_number=published.number, capture_monotonic_ns=frame.host_monotonic_ns,
                wall_time=frame.wall_time, min_distance_m=near, max_distance_m=far)
    x, y, rw, rh = config.region if config.region is not None else (0, 0, w, h)
    x1, y1 = min(x + rw, w), min(y + rh, h)
    if x >= w or y >= h:
        return Measurement(distance_m=None, variance_m2=None, valid_fraction=0.0,
                           reason=f"region {config.region} lies outside the {w}×{h} image", **base)
    r = result.range[y:y1, x:x1]
    var = result.variance[y:y1, x:x1]
    hfov = vfov = 0.0
    if rays is not None:
        # Distance along the optical axis: what a rangefinder looking along it reports for a
        # surface square to it, and the altitude over a flat seabed whatever the pixel.
        uz = rays[y:y1, x:x1, 2]
        r, var = r * uz, var * uz * uz
        hfov = math.atan2(x1 - 0.5 - intrinsics.cx, intrinsics.fx) - math.atan2(x - 0.5 - intrinsics.cx, intrinsics.fx)
        vfov = math.atan2(y1 - 0.5 - intrinsics.cy, intrinsics.fy) - math.atan2(y - 0.5 - intrinsics.cy, intrinsics.fy)
    distance, variance, fraction = region_statistic(r, var, config.statistic, config.minimum_block)
    reason = ""
    if fraction < config.min_valid_fraction:
        reason = f"{100 * fraction:.1f} % of the region's pixels have a range (needs {100 * config.min_valid_fraction:g} %)"
        distance = None
    sectors = None
    increment = offset = 0.0
    if config.obstacle_distance and rays is not None:
        yaw = 45.0 * config.orientation_value  # NONE = 0, YAW_45 = 1, … YAW_315 = 7
        column_sector, increment, offset = sector_layout(intrinsics, w, yaw)
        band = rays[y:y1, :]
        horizontal = result.range[y:y1, :] * np.sqrt(band[..., 0] ** 2 + band[..., 2] ** 2)
        min_cm, max_cm = distance_limits_cm(near, far)
        sectors = sector_distances(horizontal, result.reasons[y:y1, :], column_sector, min_cm, max_cm,
                                   config.minimum_block)
    return Measurement(distance_m=distance, variance_m2=variance, valid_fraction=fraction, reason=reason,
                       horizontal_fov_rad=hfov, vertical_fov_rad=vfov, sectors_cm=sectors,
                       sector_increment_deg=increment, sector_offset_deg=offset, **base)


def distance_limits_cm(near_m: float, far_m: float) -> tuple[int, int]:
    """min_distance and max_distance in cm: rounded outward, the far one at most MAX_DISTANCE_CM."""
    return int(math.floor(near_m * 100)), int(min(MAX_DISTANCE_CM, math.ceil(far_m * 100)))


# -- the output -----------------------------------------------------------------------------------
