"""A vehicle surveying a varied seabed, rendered fast enough to stream (scene ``survey``).

The seabed is a periodic height map with reflectance, built once from a seed: a gently
sloping, undulating sandy bottom with ripples, sandstone rocks, a brick partly buried,
a pipe across the track with sand banked against it, a docking ring and a ball. The camera
looks straight down from a vehicle moving along the track at constant speed while its
altitude rises and falls slowly; the lamp rides on the vehicle beside the camera, and the
calibration patch with its ArUco marker sits on a bracket in view, fixed in the image.

Each frame follows the same physics as :func:`uwcam.simulation.render` (Jaffe–McGlamery):

* every pixel's ray is intersected with the height map by Newton steps on
  g(z) = D(X0 + z·px, Y0 + z·py) − Z0 − z (D the seabed depth, (px, py) the pixel's
  normalised image coordinates, z the camera-frame depth), starting from the smooth base
  under the vehicle; the normal comes from the height map's gradient;
* surface light: I_k · ρ_k · beam(θ) · (r/(d_s + r))² · cos γ / π · exp(−c_k d_s) ·
  exp(−G_k d_c), which is the direct term exp(−c_k d_c) plus the forward-scattered term
  exp(−G_k d_c) − exp(−c_k d_c), here unblurred (the forward blur spans about 2 pixels at
  3 m in Jerlov water and conserves light on smooth surfaces);
* backscatter: the slab model's integral along each ray up to the surface, tabulated once
  (the lamp rides with the camera, so the water column in front of it never changes) on a
  coarse pixel grid against log depth, and interpolated per pixel;
* camera: fixed exposure, gain map, dark current, shot and read noise (normal deviates from a
  pool drawn once with the static scenes' counter-based generator, two independent runs of it
  summed per block of pixels: see ``_expose``), quantisation and saturation.

Geometry and light are computed on a grid of every ``step``-th pixel (4: the height map's
1 cm cells span 3 pixels at 4 m) and interpolated bilinearly to the full image, where
exposure and noise are per pixel: a 1280×720 frame costs about 11 ms of rendering and a few ms
of noise on one core (``bench/bench_simulator.py``). Each kernel has a numpy twin, used
where numba is missing.
"""

from __future__ import annotations

import math
from functools import lru_cache
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics
from uwcam.rig import resolve_reflectance
from uwcam.jit import HAVE_NUMBA, njit, prange
from uwcam.simulation.camera import CameraModel, frame_key, inverse_normal_table
from uwcam.simulation.render import PORT_DISTANCE, Ambient, Lamp, KERNELS, slab_edges
from uwcam.simulation.scene import (
    MARKER_CENTRE_M,
    MARKER_ID,
    MARKER_SIDE_M,
    MATERIALS,
    PATCH_CENTRE_M,
    PATCH_DISTANCE_M,
    PATCH_SIZE_M,
    Plane,
    Scene,
    marker_plate,
)
from uwcam.simulation.water import Water

if HAVE_NUMBA:
    from numba import uint64
else:  # pragma: no cover
    uint64 = np.uint64

# Height-map cell (m) and extent (m): periodic in both directions.
CELL_M = 0.01
TRACK_LENGTH_M = 30.0
STRIP_WIDTH_M = 6.0
# Newton steps of the ray/height-map intersection, and the smallest denominator 1 − ∇D·p
# allowed (grazing slopes facing away would otherwise throw a step far off).
NEWTON_STEPS = 4
# Along a row of the shading grid, a seabed node's intersection starts from its left neighbour's
# (a few millimetres off) and needs fewer steps; the first of a row, which has no neighbour,
# takes more. The intersection was ~75 % of the render's CPU.
WARM_NEWTON_STEPS = 2
FIRST_NEWTON_STEPS = NEWTON_STEPS + 2
MIN_SLOPE_DENOMINATOR = 0.25
MIN_DEPTH_M = 0.05
# Backscatter table: every this many pixels, and this many slabs from the port to the farthest depth.
BACKSCATTER_NODE_PX = 16
BACKSCATTER_SLABS = 48
BACKSCATTER_FAR_M = 12.0


@dataclass(frozen=True)
class SurveyMotion:
    """The vehicle's track: along −Y (toward the top of the image) at ``speed`` m/s, altitude above
    the smooth seabed between ``altitude`` (min, max) m, one cycle every ``altitude_period`` s,
    starting at the lowest; a slow sway of ``sway`` m across the track."""

    speed: float = 0.4
    altitude: tuple[float, float] = (1.5, 4.0)
    altitude_period: float = 120.0
    sway: float = 0.3
    sway_period: float = 47.0

    def position(self, t: float) -> tuple[float, float, float]:
        """World X, Y of the camera (m) and its altitude above the smooth seabed (m) at time t (s)."""
        lo, hi = self.altitude
        phase = 2.0 * math.pi * t / self.altitude_period
        altitude = lo + (hi - lo) * 0.5 * (1.0 - math.cos(phase))
        y = (TRACK_LENGTH_M - self.speed * t) % TRACK_LENGTH_M
        x = self.sway * math.sin(2.0 * math.pi * t / self.sway_period)
        return x, y, altitude


def _base_depth(x: NDArray | float, y: NDArray | float) -> NDArray | float:
    """The smooth seabed (m, positive down): a bank rising and falling along the track, a gentle
    cross-slope; periodic over the track length and strip width. Slopes up to about 0.3."""
    ky, kx = 2 * np.pi / TRACK_LENGTH_M, 2 * np.pi / STRIP_WIDTH_M
    return (0.8 * np.sin(ky * y) + 0.3 * np.sin(2 * ky * y + 1.0) + 0.15 * np.sin(3 * ky * y + 2.5)
            + 0.2 * np.sin(kx * x + 0.4 * np.sin(ky * y)))


def _upsample_periodic(coarse: NDArray, factor: int) -> NDArray[np.float32]:
    """Bilinear interpolation of a periodic grid to ``factor`` times its size, node (i, j) of the
    coarse grid at cell (i·factor, j·factor); stays periodic."""
    cy, cx = coarse.shape
    padded = np.pad(coarse.astype(np.float32), ((0, 1), (0, 1)), mode="wrap")
    a = (np.arange(cx * factor) % factor / factor).astype(np.float32)
    j0 = np.arange(cx * factor) // factor
    rows = padded[:, j0] * (1 - a) + padded[:, j0 + 1] * a
    b = (np.arange(cy * factor) % factor / factor).astype(np.float32)[:, None]
    i0 = np.arange(cy * factor) // factor
    return rows[i0] * (1 - b) + rows[i0 + 1] * b


def _periodic_noise(rng: np.random.Generator, shape: tuple[int, int], scale_cells: float) -> NDArray[np.float32]:
    """Smooth periodic noise, zero mean, unit rms, features about ``scale_cells`` cells across:
    Gaussian-filtered white noise, drawn on a grid about scale/3 coarser and interpolated."""
    factor = max(f for f in range(1, max(1, int(scale_cells / 3)) + 1) if shape[0] % f == 0 and shape[1] % f == 0)
    small = (shape[0] // factor, shape[1] // factor)
    white = rng.standard_normal(small)
    fy = np.fft.fftfreq(small[0])[:, None]
    fx = np.fft.rfftfreq(small[1])[None, :]
    spectrum = np.fft.rfft2(white) * np.exp(-0.5 * (np.hypot(fx, fy) * scale_cells / factor * 2.0) ** 2)
    out = np.fft.irfft2(spectrum, s=small)
    out = out / (out.std() or 1.0)
    return out.astype(np.float32) if factor == 1 else _upsample_periodic(out, factor)


@dataclass
class Terrain:
    """The seabed as a periodic grid: ``data`` (ny, nx, 3 + N) float32 holds, per cell centre, the
    depth D (m, positive down), ∂D/∂X, ∂D/∂Y and the reflectance per channel. Cell (i, j) lies at
    X = x0 + j·cell, Y = i·cell."""

    data: NDArray[np.float32]
    cell: float
    x0: float

    def __post_init__(self) -> None:
        # One more row and column repeating the first: interpolation never wraps an index.
        self.padded = np.ascontiguousarray(np.pad(self.data, ((0, 1), (0, 1), (0, 0)), mode="wrap"))

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape[0], self.data.shape[1]

    def sample(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Bilinear interpolation of every layer at world points (x, y), wrapping: (..., 3 + N)."""
        ny, nx = self.shape
        fx = (np.asarray(x, dtype=np.float64) - self.x0) * (1.0 / self.cell)
        fy = np.asarray(y, dtype=np.float64) * (1.0 / self.cell)
        fx = fx - nx * np.floor(fx / nx)
        fy = fy - ny * np.floor(fy / ny)
        j0, i0 = np.minimum(fx.astype(np.int64), nx - 1), np.minimum(fy.astype(np.int64), ny - 1)
        ax, ay = (fx - j0)[..., None], (fy - i0)[..., None]
        d = self.padded
        return ((1 - ay) * ((1 - ax) * d[i0, j0] + ax * d[i0, j0 + 1]) + ay * ((1 - ax) * d[i0 + 1, j0] + ax * d[i0 + 1, j0 + 1]))


def build_terrain(seed: int, channel_names: list[str], wavelengths_nm: list[float], material: str | None = None) -> Terrain:
    """The survey's seabed (see the module docstring); ``material`` gives every surface one material."""
    rng = np.random.default_rng(seed)
    nx, ny = int(round(STRIP_WIDTH_M / CELL_M)), int(round(TRACK_LENGTH_M / CELL_M))
    x0 = -STRIP_WIDTH_M / 2
    xs = x0 + np.arange(nx) * CELL_M
    ys = np.arange(ny) * CELL_M
    X, Y = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    # The smooth base on a 10 cm grid (its wavelengths are metres), interpolated.
    coarse = 10
    cx_, cy_ = np.meshgrid(xs[::coarse], ys[::coarse])
    depth = _upsample_periodic(_base_depth(cx_, cy_), coarse) + 0.03 * _periodic_noise(rng, (ny, nx), 40.0)
    # Sand ripples, 8–14 cm crests, fading in and out.
    # (Whole numbers of crests across the strip and along the track keep the ripples periodic.)
    ripple_dir = rng.uniform(0, np.pi)
    cycles_x = round(STRIP_WIDTH_M * np.cos(ripple_dir) / 0.11)
    cycles_y = round(TRACK_LENGTH_M * np.sin(ripple_dir) / 0.11)
    wobble = 0.6 * _periodic_noise(rng, (ny, nx), 30.0)
    ripples = np.sin(2 * np.pi * (cycles_x * X / STRIP_WIDTH_M + cycles_y * Y / TRACK_LENGTH_M) + wobble)
    depth += 0.006 * ripples * np.clip(0.6 + 0.5 * _periodic_noise(rng, (ny, nx), 150.0), 0.0, 1.0)

    names = ["sand", "rock", "brick", "pipe", "ring", "ball"]
    proud = np.zeros((ny, nx))  # height above the sand of whatever stands on it
    owner = np.zeros((ny, nx), dtype=np.int8)  # index into names

    def place(height: NDArray, name: str, where: tuple[slice, slice]) -> None:
        region = proud[where]
        higher = height > region
        region[higher] = height[higher]
        owner[where][higher] = names.index(name)

    def window(xc: float, yc: float, half: float) -> tuple[tuple[slice, slice], NDArray, NDArray]:
        """A block of cells around (xc, yc), offsets from the centre in metres (no wrap needed:
        objects sit away from the strip's edges and the track's ends)."""
        j0, j1 = int((xc - half - x0) / CELL_M), int((xc + half - x0) / CELL_M) + 1
        i0, i1 = int((yc - half) / CELL_M), int((yc + half) / CELL_M) + 1
        sl = (slice(max(i0, 0), min(i1, ny)), slice(max(j0, 0), min(j1, nx)))
        return sl, X[sl] - xc, Y[sl] - yc

    # Rocks: two fields and a few strays; sandstone, the sand's hue but darker and varied.
    rock_tone = np.ones((ny, nx))
    centres = ([(rng.uniform(-1.5, 1.5), rng.uniform(19.0, 25.0)) for _ in range(22)]
               + [(rng.uniform(-1.2, 1.2), rng.uniform(2.0, 4.5)) for _ in range(10)]
               + [(rng.uniform(-2.0, 2.0), rng.uniform(8.0, 16.0)) for _ in range(6)])
    bumps = _periodic_noise(rng, (ny, nx), 6.0)
    for xc, yc in centres:
        a, b = rng.uniform(0.06, 0.3), rng.uniform(0.05, 0.25)
        height = rng.uniform(0.04, 0.3) * min(1.0, 1.2 * min(a, b) / 0.15)
        angle = rng.uniform(0, np.pi)
        sl, dx, dy = window(xc, yc, max(a, b) * 1.1)
        u = (np.cos(angle) * dx + np.sin(angle) * dy) / a
        v = (-np.sin(angle) * dx + np.cos(angle) * dy) / b
        rr = u * u + v * v
        h = height * np.clip(1.0 - rr, 0.0, None) ** 0.45 * (1.0 + 0.08 * bumps[sl])
        place(np.where(rr < 1.0, h, 0.0), "rock", sl)
        rock_tone[sl] = np.where(rr < 1.0, rng.uniform(0.6, 1.1), rock_tone[sl])

    # The brick, 0.215 × 0.1025 m, 0.10 m proud, turned 25°, edges rounded over 1.5 cm.
    sl, dx, dy = window(0.15, 6.0, 0.2)
    a = np.radians(25.0)
    u, v = np.cos(a) * dx + np.sin(a) * dy, -np.sin(a) * dx + np.cos(a) * dy
    inside = np.minimum(0.1075 - np.abs(u), 0.05125 - np.abs(v))
    place(0.10 * np.clip(inside / 0.015 + 0.5, 0.0, 1.0), "brick", sl)

    # The pipe, 0.26 m across, 4 cm buried, lying across the track, with sand banked on both sides.
    r, bury, pipe_y = 0.13, 0.04, 11.0
    rows = slice(int((pipe_y - 0.4) / CELL_M), int((pipe_y + 0.4) / CELL_M))
    dyp = Y[rows] - pipe_y
    top = (r - bury) + np.sqrt(np.clip(r * r - dyp * dyp, 0.0, None))
    pipe = np.where(np.abs(dyp) < r, top, 0.0)
    berm = (r - bury) * np.clip(1.0 - (np.abs(dyp) - 0.8 * r) / 0.18, 0.0, 1.0)
    place(np.where(berm > pipe, 0.0, pipe), "pipe", (rows, slice(None)))
    place(np.where(berm > pipe, berm, 0.0), "sand", (rows, slice(None)))

    # The docking ring, 0.115 m across, a 12 mm tube lying on the sand; and an 11 cm ball.
    tube, major = 0.012, 0.115 / 2 - 0.012
    sl, dx, dy = window(-0.25, 15.0, 0.1)
    rho = np.hypot(dx, dy)
    place(np.where(np.abs(rho - major) < tube, tube + np.sqrt(np.clip(tube * tube - (rho - major) ** 2, 0.0, None)), 0.0),
          "ring", sl)
    sl, dx, dy = window(0.4, 16.5, 0.08)
    rb = 0.055
    rr = dx * dx + dy * dy
    place(np.where(rr < rb * rb, rb + np.sqrt(np.clip(rb * rb - rr, 0.0, None)), 0.0), "ball", sl)

    depth = depth - proud
    grad_y = (np.roll(depth, -1, axis=0) - np.roll(depth, 1, axis=0)) / (2 * CELL_M)
    grad_x = (np.roll(depth, -1, axis=1) - np.roll(depth, 1, axis=1)) / (2 * CELL_M)

    sand = MATERIALS["sand"]
    materials = {**MATERIALS, "rock": sand.model_copy(update={"reflectance": [0.7 * v for v in sand.reflectance]})}
    n = len(channel_names)
    table = np.empty((len(names), n))
    for k, name in enumerate(names):
        chosen = material or name
        spec = materials.get(chosen)
        if spec is None:
            raise UserInputError(f"unknown material '{chosen}'; known: {', '.join(MATERIALS)}")
        table[k] = resolve_reflectance(spec, channel_names, wavelengths_nm, f"material {chosen}")
    # Spectrally flat brightness: patches of coarser and finer sand, grains, rock tones.
    tone = 1.0 + 0.12 * _periodic_noise(rng, (ny, nx), 60.0) + 0.06 * _periodic_noise(rng, (ny, nx), 1.5)
    tone = np.where(owner == names.index("rock"), rock_tone * (1.0 + 0.1 * bumps), tone)
    tone = np.where(owner >= names.index("brick"), 1.0, tone)
    reflectance = table[owner] * np.clip(tone, 0.2, 2.0)[..., None]

    data = np.empty((ny, nx, 3 + n), dtype=np.float32)
    data[..., 0], data[..., 1], data[..., 2] = depth, grad_x, grad_y
    data[..., 3:] = reflectance
    return Terrain(data, CELL_M, x0)


def bracket_scene() -> Scene:
    """The calibration patch and its ArUco marker on a bracket, in the camera frame (as in the
    ``seabed-patch`` scene, without the seabed)."""
    x, y, d, half = PATCH_CENTRE_M[0], PATCH_CENTRE_M[1], PATCH_DISTANCE_M, PATCH_SIZE_M / 2
    patch = Plane((x, y, d), (0.0, 0.0, -1.0), "grey", half_size=(half, half))
    return Scene("bracket", (patch, marker_plate(MARKER_CENTRE_M, MARKER_SIDE_M, d, MARKER_ID)), textured=())


# Kernels -----------------------------------------------------------------------------
# fastmath without the no-NaN/no-inf assumptions: reassociation and fused multiply-adds only.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, inline="always", fastmath=_FAST)
def _bilinear(data, layer, x, y, x0, inv_cell, out):
    """Bilinear interpolation of ``layer`` layers of the periodic grid at world (x, y) into out;
    ``data`` is padded with a copy of its first row and column, so no index wraps."""
    ny, nx = data.shape[0] - 1, data.shape[1] - 1
    fx = (x - x0) * inv_cell
    fy = y * inv_cell
    fx -= nx * math.floor(fx * (1.0 / nx))
    fy -= ny * math.floor(fy * (1.0 / ny))
    j0, i0 = min(int(fx), nx - 1), min(int(fy), ny - 1)
    ax, ay = fx - j0, fy - i0
    for m in range(layer):
        out[m] = ((1 - ay) * ((1 - ax) * data[i0, j0, m] + ax * data[i0, j0 + 1, m])
                  + ay * ((1 - ax) * data[i0 + 1, j0, m] + ax * data[i0 + 1, j0 + 1, m]))


@njit(cache=True, inline="always", fastmath=_FAST)
def _intersect(data, x0, inv_cell, qx, qy, x0w, y0w, z0w, z_start, steps, sample):
    """Camera-frame depth z where the ray of normalised image point (qx, qy) meets the height
    map: ``steps`` Newton steps from z_start on g(z) = D(x0w + z·qx, y0w + z·qy) − z0w − z,
    g′ = ∇D·(qx, qy) − 1."""
    z = z_start
    for _ in range(steps):
        _bilinear(data, 3, x0w + z * qx, y0w + z * qy, x0, inv_cell, sample)
        den = max(1.0 - sample[1] * qx - sample[2] * qy, MIN_SLOPE_DENOMINATOR)
        z = max(z + (sample[0] - z0w - z) / den, MIN_DEPTH_M)
    return z


@njit(cache=True, nogil=True, fastmath=_FAST)
def _node_backscatter(nqx, nqy, node_fg_z, x0w, y0w, z0w, z_start, data, x0, inv_cell, table, log_z0, inv_dlog, out):
    """Backscatter (relative radiance, (gh, gw, N)) along each coarse-grid ray up to its own surface:
    the tabulated cumulative integral interpolated linearly in log depth."""
    gh, gw, n_levels, n = table.shape
    sample = np.empty(3)
    for gi in range(gh):
        for gj in range(gw):
            z = node_fg_z[gi, gj]
            if z <= 0.0:
                z = _intersect(data, x0, inv_cell, nqx[gj], nqy[gi], x0w, y0w, z0w, z_start, NEWTON_STEPS, sample)
            lv = min(max((math.log(z) - log_z0) * inv_dlog, 0.0), n_levels - 1.000001)
            l0 = int(lv)
            fl = lv - l0
            for k in range(n):
                out[gi, gj, k] = table[gi, gj, l0, k] + fl * (table[gi, gj, l0 + 1, k] - table[gi, gj, l0, k])


@njit(cache=True, nogil=True, parallel=True, fastmath=_FAST)
def _shade(px, py, x0w, y0w, z0w, z_start, data, x0, inv_cell, fg_range, fg_normal, fg_refl, lamp, lamp_r, beam_scale,
           intensity, c, g, back, node_px, step, amb, amb_fraction, lamp_out, amb_out, range_out):
    """Geometry and light on the shading grid: lamp light (surface + backscatter) and ambient light
    per channel (hs, ws, N), and the camera range (hs, ws). fg_range ≤ 0: no bracket there."""
    hs, ws = range_out.shape
    n = c.shape[0]
    n_layers = data.shape[2]
    gh, gw, _ = back.shape
    with_ambient = amb_fraction > 0.0 or amb.max() > 0.0
    for i in prange(hs):
        sample = np.empty(n_layers)
        z_prev = -1.0  # the row's last seabed node: the next one starts from it
        qy = py[i]
        gy = (i * step + 0.5 * (step - 1)) / node_px
        gi = min(int(gy), gh - 2)
        fy = min(gy - gi, 1.0)
        for j in range(ws):
            qx = px[j]
            norm = math.sqrt(qx * qx + qy * qy + 1.0)
            if fg_range[i, j] > 0.0:
                d = fg_range[i, j]
                z = d / norm
                nxv, nyv, nzv = fg_normal[i, j, 0], fg_normal[i, j, 1], fg_normal[i, j, 2]
                for k in range(n):
                    sample[3 + k] = fg_refl[i, j, k]
            else:
                if z_prev > 0.0:
                    z = _intersect(data, x0, inv_cell, qx, qy, x0w, y0w, z0w, z_prev, WARM_NEWTON_STEPS, sample)
                else:
                    z = _intersect(data, x0, inv_cell, qx, qy, x0w, y0w, z0w, z_start, FIRST_NEWTON_STEPS, sample)
                z_prev = z
                _bilinear(data, n_layers, x0w + z * qx, y0w + z * qy, x0, inv_cell, sample)
                gn = math.sqrt(sample[1] * sample[1] + sample[2] * sample[2] + 1.0)
                nxv, nyv, nzv = sample[1] / gn, sample[2] / gn, -1.0 / gn
                d = z * norm
            range_out[i, j] = d
            lx, ly, lz = lamp[0] - z * qx, lamp[1] - z * qy, lamp[2] - z
            ds = math.sqrt(lx * lx + ly * ly + lz * lz)
            cos_g = max((nxv * lx + nyv * ly + nzv * lz) / ds, 0.0)
            spread = lamp_r / (ds + lamp_r)
            geo = math.exp(-beam_scale * (1.0 + lz / ds)) * spread * spread * cos_g / math.pi
            gx = (j * step + 0.5 * (step - 1)) / node_px
            gj = min(int(gx), gw - 2)
            fx = min(gx - gj, 1.0)
            up = max(-nzv, 0.0)
            for k in range(n):
                b = ((1 - fy) * ((1 - fx) * back[gi, gj, k] + fx * back[gi, gj + 1, k])
                     + fy * ((1 - fx) * back[gi + 1, gj, k] + fx * back[gi + 1, gj + 1, k]))
                rho = sample[3 + k]
                lamp_out[i, j, k] = intensity[k] * rho * geo * math.exp(-c[k] * ds - g[k] * d) + b
                if with_ambient:
                    e_cd = math.exp(-c[k] * d)
                    amb_out[i, j, k] = amb[k] * rho * up / math.pi * e_cd + amb[k] * amb_fraction * (1.0 - e_cd)
                else:
                    amb_out[i, j, k] = 0.0


@njit(cache=True, inline="always")
def _splitmix(x):
    x = x + uint64(0x9E3779B97F4A7C15)
    z = (x ^ (x >> uint64(30))) * uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> uint64(27))) * uint64(0x94D049BB133111EB)
    return z ^ (z >> uint64(31))


NOISE_POOL_SIZE = 1 << 20
"""Standard normal deviates drawn once for the survey's noise (float32, 4 MB)."""
NOISE_BLOCK = 4096
"""Samples that take their deviates from one pair of places in the pool."""
SQRT_HALF = math.sqrt(0.5)


@njit(cache=True, inline="always")
def _pool_offsets(key, block, size):
    """The two places in the pool (distinct, each < size) that block ``block`` of a frame reads from."""
    r = _splitmix(key + uint64(block))
    a = np.int64(r >> uint64(32)) % size
    b = np.int64(r & uint64(0xFFFFFFFF)) % size
    return a, (b if b != a else (a + size // 2) % size)


@njit(cache=True, nogil=True)
def _expose_block(radiance, gain, exposure, dark_e, g_dn, read_dn2, top, za, zb, out):
    """One block of ``_expose`` on slices of equal length (deviates from the pool's runs za, zb).
    A function of its own, on slices that start at 0, so that LLVM vectorises the loop (written
    inline in the prange loop it stays scalar: 15 against 8.6 ms a 1080p frame on one core)."""
    for t in range(out.shape[0]):
        mean = (max(radiance[t] * exposure * gain[t], 0.0) + dark_e) * g_dn
        std = np.float32(math.sqrt(mean * g_dn + read_dn2))
        z = (np.float64(za[t]) + np.float64(zb[t])) * SQRT_HALF
        v = np.float64(np.float32(mean)) + np.float64(std) * z
        out[t] = min(max(np.rint(v), 0.0), top)  # rint: half to even, as round(), and it vectorises


@njit(cache=True, nogil=True, parallel=True)
def _expose(radiance, gain, exposure, dark_e, g_dn, read_dn2, key, top, pool, out):
    """Flat arrays: radiance → electrons → mean and σ (DN, float32, as CameraModel.expected) →
    mean + σ·z, rounded and clipped to codes. The deviates z: each block of NOISE_BLOCK samples
    adds two runs of the pool (see :func:`noise_pool`) starting at places drawn from the frame's
    key, scaled by √½, so each z is exactly as normal as the pool and independent of the rest
    (two blocks share both runs with probability ~1e-12); the loop is then a stream of loads
    and arithmetic that vectorises, ~4× the speed of drawing each deviate apart."""
    n = radiance.shape[0]
    size = pool.shape[0] - NOISE_BLOCK
    for block in prange((n + NOISE_BLOCK - 1) // NOISE_BLOCK):
        a, b = _pool_offsets(key, block, size)
        start = block * NOISE_BLOCK
        stop = min(start + NOISE_BLOCK, n)
        count = stop - start
        _expose_block(radiance[start:stop], gain[start:stop], exposure, dark_e, g_dn, read_dn2, top,
                      pool[a:a + count], pool[b:b + count], out[start:stop])


# numpy twins -------------------------------------------------------------------------

def intersect_numpy(terrain: Terrain, qx: NDArray, qy: NDArray, x0w: float, y0w: float, z0w: float,
                    z_start: float | NDArray, steps: int | NDArray = NEWTON_STEPS) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """numpy twin of ``_intersect`` for arrays of normalised image points: (z, layers at the hit);
    z_start and steps may differ from point to point (arrays broadcasting with qx, qy)."""
    shape = np.broadcast(qx, qy).shape
    z = np.broadcast_to(np.asarray(z_start, dtype=np.float64), shape).copy()
    steps = np.broadcast_to(steps, shape)
    for k in range(int(steps.max(initial=0))):
        sample = terrain.sample(x0w + z * qx, y0w + z * qy)
        den = np.maximum(1.0 - sample[..., 1] * qx - sample[..., 2] * qy, MIN_SLOPE_DENOMINATOR)
        z = np.where(k < steps, np.maximum(z + (sample[..., 0] - z0w - z) / den, MIN_DEPTH_M), z)
    return z, terrain.sample(x0w + z * qx, y0w + z * qy)


def row_intersect_numpy(terrain: Terrain, qx: NDArray, qy: NDArray, x0w: float, y0w: float, z0w: float,
                        z_start: float, foreground: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """numpy twin of ``_shade``'s intersections on the grid (hs, ws): along each row, a node not
    in the ``foreground`` (hs, ws) starts from the row's last such node (WARM_NEWTON_STEPS), the
    first from z_start (FIRST_NEWTON_STEPS); column by column, every row at once."""
    hs, ws = foreground.shape
    z = np.empty((hs, ws))
    sample = None
    z_prev = np.full(hs, -1.0)
    for j in range(ws):
        warm = z_prev > 0.0
        zj, sj = intersect_numpy(terrain, qx[:, j], qy[:, j], x0w, y0w, z0w, np.where(warm, z_prev, z_start),
                                 np.where(warm, WARM_NEWTON_STEPS, FIRST_NEWTON_STEPS))
        if sample is None:
            sample = np.empty((hs, ws, sj.shape[-1]))
        z[:, j], sample[:, j] = zj, sj
        z_prev = np.where(foreground[:, j], z_prev, zj)
    return z, sample


def node_backscatter_numpy(nqx, nqy, node_fg_z, x0w, y0w, z0w, z_start, terrain: Terrain, table, log_z0, inv_dlog, out):
    """numpy twin of ``_node_backscatter`` (the terrain as a :class:`Terrain`)."""
    gh, gw, n_levels, n = table.shape
    z, _ = intersect_numpy(terrain, nqx[None, :], nqy[:, None], x0w, y0w, z0w, z_start)
    z = np.where(node_fg_z > 0.0, node_fg_z, z)
    lv = np.minimum(np.maximum((np.log(z) - log_z0) * inv_dlog, 0.0), n_levels - 1.000001)
    l0 = lv.astype(np.int64)
    fl = (lv - l0)[..., None]
    gi, gj = np.indices((gh, gw))
    out[:] = table[gi, gj, l0] + fl * (table[gi, gj, l0 + 1] - table[gi, gj, l0])


def shade_numpy(px, py, x0w, y0w, z0w, z_start, terrain: Terrain, fg_range, fg_normal, fg_refl, lamp, lamp_r, beam_scale,
                intensity, c, g, back, node_px, step, amb, amb_fraction, lamp_out, amb_out, range_out):
    """numpy twin of ``_shade`` (same arguments, the terrain as a :class:`Terrain`)."""
    qx, qy = np.broadcast_arrays(px[None, :], py[:, None])
    norm = np.sqrt(qx * qx + qy * qy + 1.0)
    z, sample = row_intersect_numpy(terrain, qx, qy, x0w, y0w, z0w, z_start, fg_range > 0.0)
    gn = np.sqrt(sample[..., 1] ** 2 + sample[..., 2] ** 2 + 1.0)
    normal = np.stack([sample[..., 1] / gn, sample[..., 2] / gn, -1.0 / gn], axis=-1)
    d = z * norm
    rho = sample[..., 3:]
    fg = fg_range > 0.0
    d = np.where(fg, fg_range, d)
    z = np.where(fg, d / norm, z)
    normal = np.where(fg[..., None], fg_normal, normal)
    rho = np.where(fg[..., None], fg_refl, rho)
    range_out[:] = d
    lx, ly, lz = lamp[0] - z * qx, lamp[1] - z * qy, lamp[2] - z
    ds = np.sqrt(lx * lx + ly * ly + lz * lz)
    cos_g = np.maximum((normal[..., 0] * lx + normal[..., 1] * ly + normal[..., 2] * lz) / ds, 0.0)
    spread = lamp_r / (ds + lamp_r)
    geo = np.exp(-beam_scale * (1.0 + lz / ds)) * spread * spread * cos_g / math.pi
    hs, ws = range_out.shape
    gh, gw, _ = back.shape
    gx = (np.arange(ws) * step + 0.5 * (step - 1)) / node_px
    gy = (np.arange(hs) * step + 0.5 * (step - 1)) / node_px
    gj, gi = np.minimum(gx.astype(np.int64), gw - 2), np.minimum(gy.astype(np.int64), gh - 2)
    fx, fy = np.minimum(gx - gj, 1.0)[None, :, None], np.minimum(gy - gi, 1.0)[:, None, None]
    r0, r1, c0, c1 = gi[:, None], gi[:, None] + 1, gj[None, :], gj[None, :] + 1
    b = (1 - fy) * ((1 - fx) * back[r0, c0] + fx * back[r0, c1]) + fy * ((1 - fx) * back[r1, c0] + fx * back[r1, c1])
    lamp_out[:] = intensity * rho * geo[..., None] * np.exp(-c * ds[..., None] - g * d[..., None]) + b
    e_cd = np.exp(-c * d[..., None])
    up = np.maximum(-normal[..., 2], 0.0)[..., None]
    amb_out[:] = amb * rho * up / math.pi * e_cd + amb * amb_fraction * (1.0 - e_cd)


def _source_positions(n_out: int, n_grid: int, step: int) -> tuple[NDArray, NDArray, NDArray]:
    """For each output pixel: the grid points either side and the weight of the second, pixel
    centres mapping as x_grid = (x + 0.5)/step − 0.5; held beyond the outermost points."""
    pos = np.clip((np.arange(n_out) + 0.5) / step - 0.5, 0.0, n_grid - 1.0)
    i0 = np.minimum(pos.astype(np.int64), n_grid - 1)
    return i0, np.minimum(i0 + 1, n_grid - 1), (pos - i0).astype(np.float32)


@njit(cache=True, nogil=True, parallel=True)
def _upsample(grid, y0, y1, fy, x0, x1, fx, out):
    h, w, n = out.shape
    for i in prange(h):
        a, b, f = y0[i], y1[i], fy[i]
        for j in range(w):
            c, d, e = x0[j], x1[j], fx[j]
            for k in range(n):
                out[i, j, k] = ((1 - f) * ((1 - e) * grid[a, c, k] + e * grid[a, d, k])
                                + f * ((1 - e) * grid[b, c, k] + e * grid[b, d, k]))


def upsample_numpy(grid, y0, y1, fy, x0, x1, fx, out) -> None:
    """numpy twin of ``_upsample``."""
    f, e = fy[:, None, None], fx[None, :, None]
    out[:] = ((1 - f) * ((1 - e) * grid[y0][:, x0] + e * grid[y0][:, x1]) + f * ((1 - e) * grid[y1][:, x0] + e * grid[y1][:, x1]))


def upsample(grid: NDArray[np.float32], size: tuple[int, int], step: int, use_numba: bool = HAVE_NUMBA) -> NDArray[np.float32]:
    """Bilinear interpolation of the shading grid (hs, ws, N) to the image (h, w, N) (see
    :func:`_source_positions`)."""
    w, h = size
    if use_numba and grid.shape[0] * step == h and grid.shape[1] * step == w:
        import cv2

        # The grid tiles the image exactly: OpenCV's mapping is the same, and faster.
        out = cv2.resize(np.ascontiguousarray(grid, dtype=np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        return out.reshape(h, w, grid.shape[2])
    out = np.empty((h, w, grid.shape[2]), dtype=np.float32)
    args = (*_source_positions(h, grid.shape[0], step), *_source_positions(w, grid.shape[1], step), out)
    (_upsample if use_numba else upsample_numpy)(np.ascontiguousarray(grid, dtype=np.float32), *args)
    return out


def noise_pool() -> NDArray[np.float32]:
    """NOISE_POOL_SIZE standard normal deviates (float32) for the survey's noise, from the static
    camera's counter-based generator with a fixed key, standardised to mean 0 and standard
    deviation 1 over the pool; the first NOISE_BLOCK repeated at the end so a block's run never
    wraps. Built once (~0.1 s)."""
    return _noise_pool()


@lru_cache(maxsize=1)
def _noise_pool() -> NDArray[np.float32]:
    from uwcam.simulation.camera import deviates_numpy

    z = deviates_numpy(frame_key(0x5EED, 0), 0, NOISE_POOL_SIZE, inverse_normal_table())
    z = (z - z.mean()) / z.std()
    return np.concatenate([z, z[:NOISE_BLOCK]]).astype(np.float32)


def pool_offsets_numpy(key: np.uint64, blocks: NDArray[np.int64], size: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """numpy twin of ``_pool_offsets`` for an array of block numbers."""
    from uwcam.simulation.camera import splitmix_numpy

    r = splitmix_numpy(np.uint64(key) + blocks.astype(np.uint64))
    a = (r >> np.uint64(32)).astype(np.int64) % size
    b = (r & np.uint64(0xFFFFFFFF)).astype(np.int64) % size
    return a, np.where(b != a, b, (a + size // 2) % size)


def expose_numpy(radiance, gain, exposure, dark_e, g_dn, read_dn2, key, top, pool, out, chunk: int = 1 << 20) -> None:
    """numpy twin of ``_expose`` (flat arrays), in chunks (whole noise blocks) to bound memory."""
    n = radiance.shape[0]
    size = pool.shape[0] - NOISE_BLOCK
    chunk = max(NOISE_BLOCK, chunk - chunk % NOISE_BLOCK)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        electrons = radiance[start:stop].astype(np.float64) * exposure * gain[start:stop]
        mean = (np.maximum(electrons, 0.0) + dark_e) * g_dn
        std = np.sqrt(mean * g_dn + read_dn2).astype(np.float32).astype(np.float64)
        i = np.arange(start, stop)
        a, b = pool_offsets_numpy(key, i // NOISE_BLOCK, size)
        t = i % NOISE_BLOCK
        z = (pool[a + t].astype(np.float64) + pool[b + t].astype(np.float64)) * SQRT_HALF
        v = mean.astype(np.float32).astype(np.float64) + std * z
        out[start:stop] = np.minimum(np.maximum(np.rint(v), 0.0), top)


# The world ---------------------------------------------------------------------------

@dataclass
class SurveyWorld:
    """A vehicle surveying the seabed: frames and ground truth at any time t (s) of the survey."""

    size: tuple[int, int] = (1280, 720)
    fov_deg: float = 60.0
    channel_names: tuple[str, ...] = ("R", "G", "B")
    wavelengths_nm: tuple[float, ...] = (675.0, 575.0, 475.0)
    water: Water | None = None
    lamp: Lamp = field(default_factory=lambda: Lamp(position=(0.1, -0.4, 0.0)))
    camera: CameraModel = field(default_factory=CameraModel)
    motion: SurveyMotion = field(default_factory=SurveyMotion)
    ambient: Ambient | None = None
    seed: int = 0
    material: str | None = None
    bracket: bool = True
    """The calibration patch and its marker on a bracket in view."""
    step: int = 4
    """Geometry and light every this many pixels, interpolated between (the height map's 1 cm
    cells span 3 pixels at 4 m altitude, 7 at 1.5 m)."""
    terrain: Terrain | None = None
    """None: :func:`build_terrain` from the seed."""
    use_numba: bool = HAVE_NUMBA

    def __post_init__(self) -> None:
        from uwcam.simulation.water import water_preset

        w, h = self.size
        if w < 2 or h < 2:
            raise UserInputError(f"image size must be at least 2×2 pixels, got {w}×{h}")
        if self.step < 1:
            raise UserInputError("the shading step must be a whole number of pixels ≥ 1")
        if self.water is None:
            self.water = water_preset("jerlov-II", list(self.wavelengths_nm))
        n = len(self.channel_names)
        if self.terrain is None:
            self.terrain = build_terrain(self.seed, list(self.channel_names), list(self.wavelengths_nm), self.material)
        self.intrinsics = Intrinsics.from_fov(w, h, self.fov_deg)
        intr, s = self.intrinsics, self.step
        self.grid_size = (-(-w // s), -(-h // s))
        ws, hs = self.grid_size
        # Shading point j sits at the centre of pixel block j: x = j·s + (s − 1)/2.
        self._px = (np.arange(ws) * s + 0.5 * (s - 1) - intr.cx) / intr.fx
        self._py = (np.arange(hs) * s + 0.5 * (s - 1) - intr.cy) / intr.fy
        self._foreground(n)
        self._backscatter_table(n)
        self._gain = self.camera.gain_map((h, w, n)).astype(np.float32)
        self._exposure: float | None = None

    def _bracket_hits(self, qx: NDArray, qy: NDArray, n: int) -> tuple[NDArray, NDArray, NDArray]:
        """Range (≤ 0 where none), normal and reflectance of the bracket along the rays of normalised
        image points (qx, qy)."""
        qx, qy = np.broadcast_arrays(qx, qy)
        if not self.bracket:
            return np.full(qx.shape, -1.0), np.zeros((*qx.shape, 3)), np.zeros((*qx.shape, n))
        rays = np.stack([qx, qy, np.ones(qx.shape)], axis=-1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        scene = bracket_scene()
        hit = scene.trace(rays)
        refl = scene.reflectance(hit, rays, list(self.channel_names), list(self.wavelengths_nm))
        rng = np.where(np.isfinite(hit.range), hit.range, -1.0)
        return np.ascontiguousarray(rng), np.ascontiguousarray(hit.normal, dtype=np.float64), np.ascontiguousarray(refl)

    def _foreground(self, n: int) -> None:
        """The bracket on the shading grid; where its marker plate is (not metered for exposure)."""
        self._fg_range, self._fg_normal, self._fg_refl = self._bracket_hits(self._px[None, :], self._py[:, None], n)
        patch_half = PATCH_SIZE_M / 2 / PATCH_DISTANCE_M
        in_patch = ((np.abs(self._px[None, :] - PATCH_CENTRE_M[0] / PATCH_DISTANCE_M) <= patch_half)
                    & (np.abs(self._py[:, None] - PATCH_CENTRE_M[1] / PATCH_DISTANCE_M) <= patch_half))
        self._marker_plate = (self._fg_range > 0) & ~in_patch

    def _backscatter_table(self, n: int) -> None:
        """Cumulative backscatter (relative radiance) along the rays of a coarse pixel grid, at
        log-spaced depths from the port: (gh, gw, levels, N). The slab integrand is the static
        renderer's; its forward-scattered part arrives unblurred (exp(−G t) in all). Per frame
        each node's ray is followed to its own surface and the results interpolated between
        nodes (backscatter varies slowly across the image)."""
        from uwcam.simulation.render import slab_contributions_numpy

        w, h = self.size
        node = BACKSCATTER_NODE_PX
        gh, gw = -(-(h - 1) // node) + 1, -(-(w - 1) // node) + 1
        edges = slab_edges(PORT_DISTANCE, BACKSCATTER_FAR_M, BACKSCATTER_SLABS)
        direct = np.zeros((gh, gw, BACKSCATTER_SLABS, n))
        forward = np.zeros_like(direct)
        water, lamp, intr = self.water, self.lamp, self.intrinsics
        kernel = KERNELS["slab_contributions"] if self.use_numba else slab_contributions_numpy
        kernel(np.array([1.0 / intr.fx, 1.0 / intr.fy]), np.array([intr.cx, intr.cy, h, w], dtype=np.float64), node,
               edges, np.asarray(lamp.position, dtype=np.float64), lamp.effective_radius, lamp.beam_scale,
               lamp.intensities(n), water.attenuation, water.scatter_attenuation, water.backscatter, direct, forward)
        table = np.zeros((gh, gw, BACKSCATTER_SLABS + 1, n))
        table[:, :, 1:] = np.cumsum(direct + forward, axis=2)
        self._table = table
        self._log_z0 = math.log(edges[0])
        self._inv_dlog = BACKSCATTER_SLABS / (math.log(edges[-1]) - math.log(edges[0]))
        # The node rays (as _slab_contributions samples them) and where the bracket cuts them short.
        self._nqx = (np.minimum(np.arange(gw) * node, w - 1) - intr.cx) / intr.fx
        self._nqy = (np.minimum(np.arange(gh) * node, h - 1) - intr.cy) / intr.fy
        fg_range = self._bracket_hits(self._nqx[None, :], self._nqy[:, None], n)[0]
        norm = np.sqrt(self._nqx[None, :] ** 2 + self._nqy[:, None] ** 2 + 1.0)
        self._node_fg_z = np.where(fg_range > 0, fg_range / norm, -1.0)

    # Motion and ground truth ---------------------------------------------------------
    def pose(self, t: float) -> tuple[float, float, float]:
        """Camera position in the world (m): X, Y and depth Z (positive down) at time t (s)."""
        x, y, altitude = self.motion.position(t)
        return x, y, float(_base_depth(x, y)) - altitude

    def axis_range(self, t: float) -> float:
        """Range (m) along the optical axis to the seabed at time t: what a rangefinder looking
        straight down beside the camera measures. On the axis (p = 0) the intersection is exact."""
        x, y, z0 = self.pose(t)
        return float(self.terrain.sample(np.array(x), np.array(y))[0]) - z0

    # Rendering -----------------------------------------------------------------------
    def shade(self, t: float) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
        """Lamp light (at full intensity) and ambient light per channel on the shading grid
        (hs, ws, N) in relative radiance, and the camera range (hs, ws) in m, at time t."""
        ws, hs = self.grid_size
        n = len(self.channel_names)
        x, y, z0 = self.pose(t)
        z_start = max(float(_base_depth(x, y)) - z0, MIN_DEPTH_M)
        lamp_out = np.empty((hs, ws, n), dtype=np.float32)
        amb_out = np.empty((hs, ws, n), dtype=np.float32)
        range_out = np.empty((hs, ws))
        back = np.empty(self._table.shape[:2] + (n,))
        amb = np.zeros(n) if self.ambient is None else np.asarray(self.ambient.irradiance, dtype=np.float64)
        fraction = 0.0 if self.ambient is None else self.ambient.path_fraction
        lamp, water, terrain = self.lamp, self.water, self.terrain
        node_args = (self._nqx, self._nqy, self._node_fg_z, x, y, z0, z_start)
        table_args = (self._table, self._log_z0, self._inv_dlog, back)
        args = (self._fg_range, self._fg_normal, self._fg_refl, np.asarray(lamp.position, dtype=np.float64),
                lamp.effective_radius, lamp.beam_scale, lamp.intensities(n), water.attenuation, water.scatter_attenuation,
                back, float(BACKSCATTER_NODE_PX), float(self.step), amb, fraction, lamp_out, amb_out, range_out)
        if self.use_numba:
            _node_backscatter(*node_args, terrain.padded, terrain.x0, 1.0 / terrain.cell, *table_args)
            _shade(self._px, self._py, x, y, z0, z_start, terrain.padded, terrain.x0, 1.0 / terrain.cell, *args)
        else:
            node_backscatter_numpy(*node_args, terrain, *table_args)
            shade_numpy(self._px, self._py, x, y, z0, z_start, terrain, *args)
        return lamp_out, amb_out, range_out

    def camera_range(self, t: float) -> NDArray[np.float64]:
        """Ground truth (H, W): camera range (m) of every pixel at time t, as rendered."""
        return upsample(self.shade(t)[2][..., None].astype(np.float32), self.size, self.step, self.use_numba)[..., 0].astype(np.float64)

    @property
    def exposure(self) -> float:
        """Electrons per unit radiance: auto-exposure on the lamp-lit view at the start (lowest
        altitude, the brightest seabed), metered on the seabed and the calibration patch but not
        the marker's white plate (which may clip: the marker is still found), then held."""
        if self._exposure is None:
            lamp_rad, amb_rad, _ = self.shade(0.0)
            radiance = lamp_rad.astype(np.float64) + amb_rad
            self._exposure = self.camera.exposure_for(np.where(self._marker_plate[..., None], 0.0, radiance))
        return self._exposure

    def frame(self, t: float, index: int, level: float = 1.0, out: NDArray | None = None,
              exposure_scale: NDArray | None = None) -> NDArray:
        """Frame ``index`` (noise counter) at time t (s) with the lamp at ``level`` (0: off), (H, W, N).
        exposure_scale: (N,) each channel's exposure relative to :attr:`exposure` (None: 1)."""
        w, h = self.size
        n = len(self.channel_names)
        lamp_rad, amb_rad, _ = self.shade(t)
        grid = np.float32(level) * lamp_rad + amb_rad
        if exposure_scale is not None:
            grid = grid * np.asarray(exposure_scale, np.float32)  # (hs, ws, N) × (N,): electrons ∝ exposure time
        radiance = upsample(grid, self.size, self.step, self.use_numba).reshape(-1)
        cam = self.camera
        if out is None:
            out = np.empty((h, w, n), dtype=cam.dtype)
        g = cam.gain_dn_per_e
        kernel = _expose if self.use_numba else expose_numpy
        kernel(radiance, self._gain.reshape(-1), self.exposure, cam.dark_current_e, g, (cam.read_noise_e * g) ** 2,
               frame_key(self.seed * 2 + int(level > 0), index), float(cam.max_code), noise_pool(), out.reshape(-1))
        return out
