"""The simulated camera: auto-exposure, shot noise, dark current, read noise, fixed-pattern
gain, quantisation and saturation, reproducible with a seed.

Noise is drawn by a compiled, counter-based generator: the normal deviate of pixel p in
frame f comes from a SplitMix64 hash of (seed, f, p) and a tabulated inverse normal CDF
(16-bit index, linear interpolation on 16 more bits, Acklam's rational formula in the two
extreme bins). Frames are therefore identical whatever the thread count, and a
1280×720×3 frame costs about 10 ms rather than numpy's ~40 ms. Without numba, a numpy twin
(:func:`digitise_numpy`) draws exactly the same deviates, more slowly. Shot noise is Gaussian
with variance equal to the mean electron count, exact in mean and variance and a close
approximation to Poisson above a few tens of electrons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from statistics import NormalDist

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.compute.jit import HAVE_NUMBA, njit, prange

if HAVE_NUMBA:
    from numba import uint64
else:  # pragma: no cover
    uint64 = np.uint64

# Auto-exposure target: the brightest pixel's expected value (DN) for each bit depth.
TARGET_CODE = {8: 226.0, 12: 4077.0, 16: 65250.0}


@dataclass(frozen=True)
class CameraModel:
    """Sensor noise and digitisation. Electrons (e⁻) and digital numbers (DN)."""

    bits: int = 16
    """Bit depth of the output codes: 8, 12 or 16."""
    full_well_e: float = 20000.0
    """Electrons at the top code: sets DN per electron."""
    read_noise_e: float = 5.0
    """Rms of the readout's Gaussian noise, e⁻."""
    dark_current_e: float = 40.0
    """Mean dark electrons per exposure (non-zero mean, with its own shot noise)."""
    prnu: float = 0.01
    """Relative rms of the fixed-pattern gain map (photo-response non-uniformity)."""
    fixed_pattern_seed: int = 7
    """Seed of the gain map: a property of the sensor, not of the frame."""
    peak_code: float | None = None
    """Auto-exposure target for the brightest pixel's expected value, DN (None: TARGET_CODE)."""
    response: str = "linear"
    """Tone curve applied to the sensor's linear signal before it is quantised: linear, srgb or
    rec709 (an ordinary USB camera's 8-bit output; see uwcam.imaging.response)."""
    jpeg_quality: int | None = None
    """JPEG-compress each frame at this quality (1–100), as an MJPEG camera or stream does; None: not."""

    def __post_init__(self) -> None:
        if self.bits not in TARGET_CODE:
            raise UserInputError(f"bit depth must be one of {sorted(TARGET_CODE)}, got {self.bits}")
        if self.response not in ("linear", "srgb", "rec709"):
            raise UserInputError(f"unknown camera response '{self.response}'; known: linear, srgb, rec709")
        if (self.response != "linear" or self.jpeg_quality is not None) and self.bits != 8:
            raise UserInputError("a tone curve or JPEG applies to 8-bit cameras here: use --bits 8")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise UserInputError(f"JPEG quality must be 1 to 100, got {self.jpeg_quality}")
        if self.peak_code is not None and not 0 < self.peak_code <= self.max_code:
            raise UserInputError(f"the exposure peak must lie between 0 and {self.max_code} DN, got {self.peak_code}")

    @property
    def max_code(self) -> int:
        return 2**self.bits - 1

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bits == 8 else np.uint16)

    @property
    def gain_dn_per_e(self) -> float:
        return self.max_code / self.full_well_e

    @property
    def dark_level_dn(self) -> float:
        """Mean dark signal in DN, the level a dark frame averages to."""
        return self.dark_current_e * self.gain_dn_per_e

    def gain_map(self, shape: tuple[int, ...]) -> NDArray[np.float64]:
        return 1.0 + self.prnu * np.random.default_rng(self.fixed_pattern_seed).standard_normal(shape)

    def exposure_for(self, radiance: NDArray) -> float:
        """Electrons per unit radiance so the brightest pixel's expected value sits at the target code."""
        peak = float(np.max(radiance * self.gain_map(radiance.shape)))  # the sensor's own response, fixed pattern included
        if not peak > 0:
            raise UserInputError("the scene is black: nothing lit in view (is the lamp on and the scene in range?)")
        peak_dn = TARGET_CODE[self.bits] if self.peak_code is None else self.peak_code
        target_e = peak_dn / self.gain_dn_per_e - self.dark_current_e
        return target_e / peak

    def expected(self, radiance: NDArray, exposure: float) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Mean and standard deviation (DN, float32) of each pixel before quantisation and clipping."""
        electrons = radiance * exposure * self.gain_map(radiance.shape)
        g = self.gain_dn_per_e
        mean = (np.maximum(electrons, 0.0) + self.dark_current_e) * g
        std = np.sqrt(mean * g + (self.read_noise_e * g) ** 2)
        return mean.astype(np.float32), std.astype(np.float32)

    def digitise(self, mean: NDArray[np.float32], std: NDArray[np.float32], seed: int, frame_index: int,
                 out: NDArray | None = None) -> NDArray:
        """One noisy frame: mean + std·N(0, 1), rounded and clipped to [0, max_code]."""
        if out is None:
            out = np.empty(mean.shape, dtype=self.dtype)
        kernel = _digitise if HAVE_NUMBA else digitise_numpy
        if self.response == "linear" and self.jpeg_quality is None:
            kernel(mean.reshape(-1), std.reshape(-1), _frame_key(seed, frame_index), float(self.max_code),
                   _inverse_normal_table(), out.reshape(-1))
            return out
        # An ordinary camera: the noisy linear signal (drawn at 1/256 DN, the same deviates) goes
        # through the tone curve, is quantised to 8 bits, and optionally JPEG-compressed.
        fine = np.empty(mean.shape, np.uint16)
        kernel((mean * 256.0).reshape(-1), (std * 256.0).reshape(-1), _frame_key(seed, frame_index),
               float(self.max_code * 256), _inverse_normal_table(), fine.reshape(-1))
        linear = fine.astype(np.float64) / 256.0
        if self.response == "linear":
            coded = np.rint(linear).astype(np.uint8)
        else:
            from uwcam.imaging.response import encode

            coded = encode(linear, self.response, 8)
        if self.jpeg_quality is not None:
            coded = jpeg_roundtrip(coded, self.jpeg_quality)
        out[...] = coded
        return out


def jpeg_roundtrip(rgb: NDArray[np.uint8], quality: int) -> NDArray[np.uint8]:
    """An 8-bit RGB frame compressed to JPEG at ``quality`` and decoded again (4:2:0, as cameras do)."""
    import cv2

    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise UserInputError("JPEG compression needs three-channel frames")
    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise UserInputError("OpenCV could not JPEG-encode the frame")
    return cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1]


@njit(cache=True, inline="always")
def splitmix(x):
    """SplitMix64 of a uint64 (wrapping arithmetic): the simulator's counter-based noise."""
    x = x + uint64(0x9E3779B97F4A7C15)
    z = (x ^ (x >> uint64(30))) * uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> uint64(27))) * uint64(0x94D049BB133111EB)
    return z ^ (z >> uint64(31))


_MASK64 = (1 << 64) - 1


def _splitmix_int(x: int) -> int:
    """SplitMix64 on a Python int (the same function as the compiled ``splitmix``)."""
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    z = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _frame_key(seed: int, frame_index: int) -> np.uint64:
    key = _splitmix_int(seed & _MASK64)
    return np.uint64(_splitmix_int((key ^ (frame_index * 0xD1B54A32D192ED03)) & _MASK64))


def frame_key(seed: int, frame_index: int) -> np.uint64:
    """The noise key of frame ``frame_index`` of a sensor seeded ``seed`` (for fused kernels)."""
    return _frame_key(seed, frame_index)


def inverse_normal_table() -> NDArray[np.float64]:
    """Φ⁻¹ at 65,537 equally spaced probabilities (ends 0: the tails are computed)."""
    return _inverse_normal_table()


@lru_cache(maxsize=1)
def _inverse_normal_table() -> NDArray[np.float64]:
    nd = NormalDist()
    return np.array([0.0] + [nd.inv_cdf(i / 65536.0) for i in range(1, 65536)] + [0.0], dtype=np.float64)


def _acklam_lower_tail(q):
    """Φ⁻¹(p) for p < 0.02425 from q = √(−2 ln p) (Acklam's rational approximation, relative error
    < 1.2e-9). Plain arithmetic: the same function serves the kernel's scalars and the twin's arrays."""
    num = ((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838) * q
            - 2.549732539343734) * q + 4.374664141464968) * q + 2.938163982698783
    den = (((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996) * q
           + 3.754408661907416) * q + 1.0
    return num / den


_acklam_lower_tail_compiled = njit(cache=True, inline="always")(_acklam_lower_tail)


@njit(cache=True, inline="always")
def _lower_tail(p):
    """Φ⁻¹(p) for p < 0.02425."""
    return _acklam_lower_tail_compiled(math.sqrt(-2.0 * math.log(p)))


@njit(cache=True, inline="always")
def _normal(bits32, table):
    idx = bits32 >> 16
    frac = (bits32 & 0xFFFF) * (1.0 / 65536.0) + 0.5 / 65536.0
    if idx == 0:
        return _lower_tail(frac / 65536.0)
    if idx == 65535:
        return -_lower_tail((1.0 - frac) / 65536.0)
    return table[idx] + (frac - 0.5 / 65536.0) * (table[idx + 1] - table[idx])


@njit(parallel=True, cache=True, nogil=True)
def _digitise(mean, std, key, top, table, out):
    n = mean.shape[0]
    for p in prange((n + 1) // 2):
        r = splitmix(key + uint64(p))
        i = 2 * p
        v = mean[i] + std[i] * _normal(np.int64(r >> uint64(32)), table)
        out[i] = min(max(round(v), 0.0), top)
        if i + 1 < n:
            v = mean[i + 1] + std[i + 1] * _normal(np.int64(r & uint64(0xFFFFFFFF)), table)
            out[i + 1] = min(max(round(v), 0.0), top)


# numpy twins: the same arithmetic, in the same order, on whole arrays -------------------

def splitmix_numpy(x: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64 of each element (uint64 arithmetic wraps modulo 2⁶⁴, as in the kernel)."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    z = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _lower_tail_numpy(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return _acklam_lower_tail(np.sqrt(-2.0 * np.log(p)))


def normal_numpy(bits32: NDArray[np.int64], table: NDArray[np.float64]) -> NDArray[np.float64]:
    """Standard normal deviates from 32 random bits each (the kernel's ``_normal``)."""
    idx = bits32 >> 16
    frac = (bits32 & 0xFFFF) * (1.0 / 65536.0) + 0.5 / 65536.0
    value = table[idx] + (frac - 0.5 / 65536.0) * (table[np.minimum(idx + 1, 65536)] - table[idx])
    low, high = idx == 0, idx == 65535
    if low.any():
        value[low] = _lower_tail_numpy(frac[low] / 65536.0)
    if high.any():
        value[high] = -_lower_tail_numpy((1.0 - frac[high]) / 65536.0)
    return value


def deviates_numpy(key: np.uint64, start: int, count: int, table: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normal deviates of samples ``start … start+count−1`` of the frame with noise key ``key``:
    sample s takes the high (s even) or low (s odd) 32 bits of SplitMix64(key + s // 2)."""
    first, last = start // 2, (start + count - 1) // 2
    r = splitmix_numpy(np.uint64(key) + np.arange(first, last + 1, dtype=np.uint64))
    bits = np.empty(2 * r.size, dtype=np.int64)
    bits[0::2] = (r >> np.uint64(32)).astype(np.int64)
    bits[1::2] = (r & np.uint64(0xFFFFFFFF)).astype(np.int64)
    offset = start - 2 * first
    return normal_numpy(bits[offset : offset + count], table)


def digitise_numpy(mean: NDArray[np.float32], std: NDArray[np.float32], key: np.uint64, top: float,
                   table: NDArray[np.float64], out: NDArray, chunk: int = 1 << 20) -> None:
    """numpy twin of the compiled ``_digitise`` (flat arrays), in chunks to bound memory."""
    n = mean.shape[0]
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        v = mean[start:stop].astype(np.float64) + std[start:stop].astype(np.float64) * deviates_numpy(key, start, stop - start, table)
        out[start:stop] = np.minimum(np.maximum(np.rint(v), 0.0), top)
