"""Sensor frames from the Mitsuba 3 renders cached in tests/data/mitsuba (a helper for tests, not a test).

bench/mitsuba_world.py rendered the mean radiance of each scene once (Mitsuba 3, multiple scattering);
this module turns a render into raw 16-bit frames of a simulated sensor, in numpy, so that the tests
need no Mitsuba. The sensor (one per water: one calibration, one fixed pattern):

* exposure: one for every frame of a water, the calibration's: the brightest pixel (any channel) of
  the 1 m plate render at 60 % of the range above the dark level, ``exposure = 0.6 (65535 − 256) / max L``
  DN per unit radiance. The seabed and open-water frames are taken at that same exposure (so
  ``uwcam range`` needs no exposure options), which leaves the 7 m seabed at a few hundred DN in
  green and blue and the red near the noise floor;
* cos⁴ vignetting (optional, off by default): cos⁴ of each pixel centre's ray angle off the axis,
  from the Mitsuba camera's intrinsics (60° horizontal field of view, 160×120);
* photo-response non-uniformity: a fixed per-pixel, per-channel gain 1 + 0.01·N(0, 1), seeded
  (``prnu_seed``), the same in every frame of the sensor;
* shot noise: Poisson in electrons at 4 e⁻/DN; read noise: Gaussian, 3 DN rms;
* a dark level of 256 DN, rounding and clipping to 0 … 65535 (uint16).

Frames are (H, W, 3) uint16, channels R, G, B.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(ROOT, "tests", "data", "mitsuba")
sys.path.insert(0, os.path.join(ROOT, "bench"))

import mitsuba_world as mw  # noqa: E402  (the scene list and intrinsics; imports no Mitsuba)

FULL_SCALE = 65535


@dataclass(frozen=True)
class Sensor:
    gain_e_per_dn: float = 4.0
    read_noise_dn: float = 3.0
    dark_level_dn: float = 256.0
    prnu: float = 0.01
    prnu_seed: int = 7
    vignetting: bool = False
    peak_fraction: float = 0.6


@lru_cache(maxsize=None)
def load(name: str) -> dict:
    """A cached render <water>_<scene> as a dict: radiance (H, W, 3) float64 and its metadata."""
    with np.load(os.path.join(DATA, f"{name}.npz")) as z:
        out = {k: z[k] for k in z.files}
    out["radiance"] = out["radiance"].astype(np.float64)
    return out


def intrinsics() -> tuple[float, float, float, float]:
    return mw.intrinsics()


def ray_cos() -> np.ndarray:
    """cos of each pixel centre's ray angle off the optical axis, (H, W)."""
    return mw.pixel_rays()[..., 2]


def true_range(distance_m: float) -> np.ndarray:
    """Camera range along each pixel's ray to a plane square to the axis at ``distance_m``, (H, W), m."""
    return distance_m / ray_cos()


def vignetting(sensor: Sensor) -> np.ndarray:
    return ray_cos() ** 4 if sensor.vignetting else np.ones((mw.HEIGHT, mw.WIDTH))


def prnu_map(sensor: Sensor) -> np.ndarray:
    rng = np.random.default_rng(sensor.prnu_seed)
    return 1.0 + sensor.prnu * rng.standard_normal((mw.HEIGHT, mw.WIDTH, 3))


def calibration_exposure(water: str, sensor: Sensor) -> float:
    """DN per unit radiance putting the 1 m plate's brightest (vignetted) pixel at ``peak_fraction`` of the
    range above the dark level."""
    plate = load(f"{water}_plate-1m")["radiance"] * vignetting(sensor)[..., None]
    return sensor.peak_fraction * (FULL_SCALE - sensor.dark_level_dn) / float(plate.max())


def mean_dn(name: str, sensor: Sensor, exposure: float) -> np.ndarray:
    """Noise-free expected raw values of render ``name``, (H, W, 3) float DN, unclipped."""
    signal = exposure * load(name)["radiance"] * vignetting(sensor)[..., None] * prnu_map(sensor)
    return sensor.dark_level_dn + signal


def frames(name: str, sensor: Sensor, exposure: float, count: int, seed: int) -> list[np.ndarray]:
    """``count`` noisy uint16 frames (H, W, 3) of render ``name``: Poisson electrons, read noise, clipping."""
    rng = np.random.default_rng(seed)
    mean = mean_dn(name, sensor, exposure)
    electrons = np.clip((mean - sensor.dark_level_dn) * sensor.gain_e_per_dn, 0.0, None)
    out = []
    for _ in range(count):
        dn = rng.poisson(electrons) / sensor.gain_e_per_dn + sensor.dark_level_dn
        dn = dn + sensor.read_noise_dn * rng.standard_normal(mean.shape)
        out.append(np.clip(np.rint(dn), 0, FULL_SCALE).astype(np.uint16))
    return out
