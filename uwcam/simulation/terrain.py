"""The survey scene's seabed: a periodic height map with reflectance, built once from a seed,
and the vehicle's track over it (see :mod:`uwcam.simulation.survey`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.calibration.rig import resolve_reflectance
from uwcam.simulation.scene import MATERIALS


# Height-map cell (m) and extent (m): periodic in both directions.
CELL_M = 0.01
TRACK_LENGTH_M = 30.0
STRIP_WIDTH_M = 6.0


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

