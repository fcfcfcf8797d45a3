"""Image formation after Jaffe and McGlamery, per channel.

All quantities are radiometrically relative (the camera's auto-exposure fixes the scale):

* irradiance on a surface point: I_k · beam(θ) · (r/(d_s + r))² · exp(−c_k d_s)
* surface radiance: irradiance · ρ_k · cos γ / π
* direct: radiance · exp(−c_k d_c)
* forward scatter: radiance · (exp(−G_k d_c) − exp(−c_k d_c)), blurred by the OTF
  exp(−B · d · f), f in cycles/rad
* backscatter: the water column in slabs parallel to the image plane; a slab returns
  β_k · (lamp irradiance on it) · thickness, attenuated (direct) and forward-scattered
  (blurred) like the surface term; both parts make up the backscatter component. Range
  gating keeps only the water within ``gate_width`` in front of the surface.
* ambient: optional daylight from above, independent of the lamp.

Blur by range: every forward-scattered contribution is split between the two nearest of
a few geometrically spaced range bins; each bin is Fourier transformed once, multiplied by
its OTF, and the bins are summed before one inverse transform per channel.

The per-pixel kernels are compiled with numba when it is installed; each has a numpy twin
(``*_numpy``) computing the same values, used where numba is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.optics.geometry import Intrinsics
from uwcam.compute.jit import HAVE_NUMBA, njit, prange
from uwcam.simulation.scene import Hit
from uwcam.simulation.water import Water

_LN2 = math.log(2.0)
# Water starts at the camera's port, not at its centre of projection (m).
PORT_DISTANCE = 0.05
# Backscatter is smooth across the image: slabs are evaluated every this many pixels and
# interpolated; only the cut-off at each pixel's own surface is computed per pixel.
BACKSCATTER_GRID_STEP = 4
# Sub-slabs across a range gate.
GATE_STEPS = 4


@dataclass(frozen=True)
class Lamp:
    """A directional lamp beside the camera, its beam along the camera's z axis."""

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Camera frame, metres (x right, y down, z forward)."""
    intensity: tuple[float, ...] | None = None
    """Relative spectral intensity per channel (None: equal)."""
    beam_half_angle_deg: float = 50.0
    """Angle off the beam axis at which intensity halves; the pattern is exp(−k·(1 − cos θ))."""
    lens_area_m2: float = 0.003
    """Front lens area A0."""
    on: bool = True

    @property
    def solid_angle(self) -> float:
        """Beam solid angle Ω (sr) of the cone at the half angle."""
        return 2.0 * math.pi * (1.0 - math.cos(math.radians(self.beam_half_angle_deg)))

    @property
    def effective_radius(self) -> float:
        """r = sqrt(A0/Ω) in metres: irradiance falls as (r/(d_s + r))²."""
        return math.sqrt(self.lens_area_m2 / self.solid_angle)

    @property
    def beam_scale(self) -> float:
        """k in the beam pattern exp(−k·(1 − cos θ)): half power at the half angle."""
        return _LN2 / (1.0 - math.cos(math.radians(self.beam_half_angle_deg)))

    def intensities(self, n: int) -> NDArray[np.float64]:
        return np.ones(n) if self.intensity is None else np.asarray(self.intensity, dtype=np.float64)


@dataclass(frozen=True)
class Ambient:
    """Daylight from above: irradiance per channel on an up-facing surface, and the fraction of
    it that the water column scatters toward the camera over a long path."""

    irradiance: tuple[float, ...]
    path_fraction: float = 0.05


@dataclass
class Components:
    """Image components (H, W, N) in relative radiance; ``total`` is their sum."""

    direct: NDArray[np.float64]
    forward: NDArray[np.float64]
    backscatter: NDArray[np.float64]
    ambient: NDArray[np.float64]
    extra: dict[str, NDArray[np.float64]] = field(default_factory=dict)

    @property
    def total(self) -> NDArray[np.float64]:
        return self.direct + self.forward + self.backscatter + self.ambient


@njit(cache=True, inline="always")
def _beam(cos_theta, beam_scale):
    """Lamp beam pattern: exp(−ln2·(1 − cos θ)/(1 − cos θ½)), half power at the half angle."""
    return math.exp(-beam_scale * (1.0 - cos_theta))


@njit(cache=True, inline="always")
def _slab_source(ux, uy, uz, t, dt, lamp, lamp_r, beam_scale):
    """Lamp irradiance × thickness at distance t along ray u (channel-independent part), and d_s."""
    px, py, pz = t * ux - lamp[0], t * uy - lamp[1], t * uz - lamp[2]
    ds = math.sqrt(px * px + py * py + pz * pz)
    return _beam(pz / ds, beam_scale) * (lamp_r / (ds + lamp_r)) ** 2 * dt, ds


@njit(parallel=True, cache=True, nogil=True)
def _slab_contributions(inv_f, centre, step, edges, lamp, lamp_r, beam_scale, intensity, c, g, beta, direct_out, forward_out):
    """Backscatter of each whole slab on a coarse pixel grid: (gh, gw, S, N) direct and
    forward-scattered parts. Pixel (gi·step, gj·step), clamped to the image, is the sample."""
    gh, gw, n_slabs, n = direct_out.shape
    h, w = int(centre[2]), int(centre[3])
    for gi in prange(gh):
        y = min(gi * step, h - 1)
        for gj in range(gw):
            x = min(gj * step, w - 1)
            ux, uy = (x - centre[0]) * inv_f[0], (y - centre[1]) * inv_f[1]
            norm = math.sqrt(ux * ux + uy * uy + 1.0)
            ux, uy, uz = ux / norm, uy / norm, 1.0 / norm
            for s in range(n_slabs):
                t0, t1 = edges[s] / uz, edges[s + 1] / uz
                t = 0.5 * (t0 + t1)
                geometric, ds = _slab_source(ux, uy, uz, t, t1 - t0, lamp, lamp_r, beam_scale)
                for k in range(n):
                    source = beta[k] * intensity[k] * geometric * math.exp(-c[k] * ds)
                    e_ct = math.exp(-c[k] * t)
                    direct_out[gi, gj, s, k] = source * e_ct
                    forward_out[gi, gj, s, k] = source * (math.exp(-g[k] * t) - e_ct)


@njit(cache=True, inline="always")
def _bin_position(log_t, log_r_min, log_span, n_bins):
    x = (log_t - log_r_min) / log_span * (n_bins - 1)
    x = min(max(x, 0.0), n_bins - 1.0)
    b0 = int(x)
    return b0, x - b0


@njit(parallel=True, cache=True, nogil=True)
def _backscatter_column(rays, surface_range, step, log_edges, slab_direct, slab_forward, open_end_z, log_r_min,
                        log_span, direct_out, bins_out):
    """Per pixel: the coarse per-slab contributions, interpolated bilinearly to the pixel and
    summed up to the pixel's own surface (the last slab in proportion, in log depth)."""
    h, w, _ = rays.shape
    gh, gw, n_slabs, n = slab_direct.shape
    n_bins = bins_out.shape[0]
    for i in prange(h):
        gy = i / step
        gi = min(int(gy), gh - 2)
        fy = min(gy - gi, 1.0)
        for j in range(w):
            gx = j / step
            gj = min(int(gx), gw - 2)
            fx = min(gx - gj, 1.0)
            uz = rays[i, j, 2]
            d = surface_range[i, j]
            z_end = d * uz if math.isfinite(d) else open_end_z
            log_z_end = math.log(z_end)
            log_uz = math.log(uz)
            w00, w01, w10, w11 = (1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx
            for s in range(n_slabs):
                if log_edges[s] >= log_z_end:
                    break
                share = 1.0
                if log_edges[s + 1] > log_z_end:
                    share = (log_z_end - log_edges[s]) / (log_edges[s + 1] - log_edges[s])
                b0, f = _bin_position(0.5 * (log_edges[s] + log_edges[s + 1]) - log_uz, log_r_min, log_span, n_bins)
                for k in range(n):
                    dv = (w00 * slab_direct[gi, gj, s, k] + w01 * slab_direct[gi, gj + 1, s, k]
                          + w10 * slab_direct[gi + 1, gj, s, k] + w11 * slab_direct[gi + 1, gj + 1, s, k])
                    fv = (w00 * slab_forward[gi, gj, s, k] + w01 * slab_forward[gi, gj + 1, s, k]
                          + w10 * slab_forward[gi + 1, gj, s, k] + w11 * slab_forward[gi + 1, gj + 1, s, k])
                    direct_out[i, j, k] += share * dv
                    bins_out[b0, i, j, k] += share * fv * (1.0 - f)
                    if b0 + 1 < n_bins:
                        bins_out[b0 + 1, i, j, k] += share * fv * f


@njit(parallel=True, cache=True, nogil=True)
def _backscatter_gated(rays, surface_range, gate_width, steps, open_gate_end, lamp, lamp_r, beam_scale, intensity,
                       c, g, beta, log_r_min, log_span, direct_out, bins_out):
    """Range-gated backscatter: only [d − gate_width, d] in front of each pixel's surface (or of
    open_gate_end for open water), integrated directly in ``steps`` sub-slabs per pixel."""
    h, w, _ = rays.shape
    n = c.shape[0]
    n_bins = bins_out.shape[0]
    for i in prange(h):
        for j in range(w):
            ux, uy, uz = rays[i, j, 0], rays[i, j, 1], rays[i, j, 2]
            d = surface_range[i, j]
            end = d if math.isfinite(d) else open_gate_end
            start = max(end - gate_width, 0.0)
            dt = (end - start) / steps
            for s in range(steps):
                t = start + (s + 0.5) * dt
                geometric, ds = _slab_source(ux, uy, uz, t, dt, lamp, lamp_r, beam_scale)
                b0, f = _bin_position(math.log(t), log_r_min, log_span, n_bins)
                for k in range(n):
                    source = beta[k] * intensity[k] * geometric * math.exp(-c[k] * ds)
                    e_ct = math.exp(-c[k] * t)
                    direct_out[i, j, k] += source * e_ct
                    fv = source * (math.exp(-g[k] * t) - e_ct)
                    bins_out[b0, i, j, k] += fv * (1.0 - f)
                    if b0 + 1 < n_bins:
                        bins_out[b0 + 1, i, j, k] += fv * f


@njit(parallel=True, cache=True, nogil=True)
def _bin_surface(source, ranges, log_r_min, log_span, bins_out):
    """Split each pixel's forward-scattered surface light between the two nearest range bins."""
    h, w, n = source.shape
    n_bins = bins_out.shape[0]
    for i in prange(h):
        for j in range(w):
            r = ranges[i, j]
            if not math.isfinite(r):
                continue
            b0, f = _bin_position(math.log(r), log_r_min, log_span, n_bins)
            for k in range(n):
                bins_out[b0, i, j, k] += source[i, j, k] * (1.0 - f)
                if b0 + 1 < n_bins:
                    bins_out[b0 + 1, i, j, k] += source[i, j, k] * f


# numpy twins of the kernels above: the same arithmetic on whole arrays ------------------

def _bin_position_numpy(log_t, log_r_min, log_span, n_bins):
    x = (log_t - log_r_min) / log_span * (n_bins - 1)
    x = np.minimum(np.maximum(x, 0.0), n_bins - 1.0)
    b0 = x.astype(np.int64)
    return b0, x - b0


def _add_to_bins(bins_out, b0, f, values, rows, cols):
    """bins_out[b0] += values·(1 − f), bins_out[b0 + 1] += values·f at (rows, cols); values (M, N)."""
    n_bins = bins_out.shape[0]
    for b in range(n_bins):
        sel = b0 == b
        if sel.any():
            bins_out[b, rows[sel], cols[sel]] += values[sel] * (1.0 - f[sel])[:, None]
        sel = (b0 + 1 == b)
        if sel.any():
            bins_out[b, rows[sel], cols[sel]] += values[sel] * f[sel][:, None]


def slab_contributions_numpy(inv_f, centre, step, edges, lamp, lamp_r, beam_scale, intensity, c, g, beta,
                             direct_out, forward_out):
    """numpy twin of ``_slab_contributions``."""
    gh, gw, n_slabs, n = direct_out.shape
    h, w = int(centre[2]), int(centre[3])
    y = np.minimum(np.arange(gh) * step, h - 1).astype(np.float64)
    x = np.minimum(np.arange(gw) * step, w - 1).astype(np.float64)
    ux, uy = np.meshgrid((x - centre[0]) * inv_f[0], (y - centre[1]) * inv_f[1])
    norm = np.sqrt(ux * ux + uy * uy + 1.0)
    ux, uy, uz = (ux / norm)[..., None], (uy / norm)[..., None], (1.0 / norm)[..., None]
    t0, t1 = edges[None, None, :-1] / uz, edges[None, None, 1:] / uz
    t = 0.5 * (t0 + t1)
    px, py, pz = t * ux - lamp[0], t * uy - lamp[1], t * uz - lamp[2]
    ds = np.sqrt(px * px + py * py + pz * pz)
    geometric = (np.exp(-beam_scale * (1.0 - pz / ds)) * (lamp_r / (ds + lamp_r)) ** 2 * (t1 - t0))[..., None]
    source = beta * intensity * geometric * np.exp(-c * ds[..., None])
    e_ct = np.exp(-c * t[..., None])
    direct_out[:] = source * e_ct
    forward_out[:] = source * (np.exp(-g * t[..., None]) - e_ct)


def backscatter_column_numpy(rays, surface_range, step, log_edges, slab_direct, slab_forward, open_end_z, log_r_min,
                             log_span, direct_out, bins_out):
    """numpy twin of ``_backscatter_column``."""
    h, w, _ = rays.shape
    gh, gw, n_slabs, n = slab_direct.shape
    n_bins = bins_out.shape[0]
    gy = np.arange(h) / step
    gi = np.minimum(gy.astype(np.int64), gh - 2)
    fy = np.minimum(gy - gi, 1.0)[:, None]
    gx = np.arange(w) / step
    gj = np.minimum(gx.astype(np.int64), gw - 2)
    fx = np.minimum(gx - gj, 1.0)[None, :]
    uz = rays[..., 2]
    z_end = np.where(np.isfinite(surface_range), surface_range * uz, open_end_z)
    log_z_end, log_uz = np.log(z_end), np.log(uz)
    w00, w01, w10, w11 = ((1 - fy) * (1 - fx))[..., None], ((1 - fy) * fx)[..., None], (fy * (1 - fx))[..., None], (fy * fx)[..., None]
    rows, cols = np.indices((h, w))
    rows, cols = rows.ravel(), cols.ravel()
    r0, r1, c0, c1 = gi[:, None], gi[:, None] + 1, gj[None, :], gj[None, :] + 1
    for s in range(n_slabs):
        active = log_edges[s] < log_z_end
        if not active.any():
            break
        share = np.where(log_edges[s + 1] > log_z_end, (log_z_end - log_edges[s]) / (log_edges[s + 1] - log_edges[s]), 1.0)
        share = np.where(active, share, 0.0)[..., None]
        b0, f = _bin_position_numpy(0.5 * (log_edges[s] + log_edges[s + 1]) - log_uz, log_r_min, log_span, n_bins)
        sd, sf = slab_direct[:, :, s], slab_forward[:, :, s]
        dv = w00 * sd[r0, c0] + w01 * sd[r0, c1] + w10 * sd[r1, c0] + w11 * sd[r1, c1]
        fv = w00 * sf[r0, c0] + w01 * sf[r0, c1] + w10 * sf[r1, c0] + w11 * sf[r1, c1]
        direct_out += share * dv
        _add_to_bins(bins_out, b0.ravel(), f.ravel(), (share * fv).reshape(-1, n), rows, cols)


def backscatter_gated_numpy(rays, surface_range, gate_width, steps, open_gate_end, lamp, lamp_r, beam_scale, intensity,
                            c, g, beta, log_r_min, log_span, direct_out, bins_out):
    """numpy twin of ``_backscatter_gated``."""
    h, w, _ = rays.shape
    n = c.shape[0]
    n_bins = bins_out.shape[0]
    ux, uy, uz = rays[..., 0], rays[..., 1], rays[..., 2]
    end = np.where(np.isfinite(surface_range), surface_range, open_gate_end)
    start = np.maximum(end - gate_width, 0.0)
    dt = (end - start) / steps
    rows, cols = np.indices((h, w))
    rows, cols = rows.ravel(), cols.ravel()
    for s in range(steps):
        t = start + (s + 0.5) * dt
        px, py, pz = t * ux - lamp[0], t * uy - lamp[1], t * uz - lamp[2]
        ds = np.sqrt(px * px + py * py + pz * pz)
        geometric = np.exp(-beam_scale * (1.0 - pz / ds)) * (lamp_r / (ds + lamp_r)) ** 2 * dt
        b0, f = _bin_position_numpy(np.log(t), log_r_min, log_span, n_bins)
        source = beta * intensity * geometric[..., None] * np.exp(-c * ds[..., None])
        e_ct = np.exp(-c * t[..., None])
        direct_out += source * e_ct
        fv = source * (np.exp(-g * t[..., None]) - e_ct)
        _add_to_bins(bins_out, b0.ravel(), f.ravel(), fv.reshape(-1, n), rows, cols)


def bin_surface_numpy(source, ranges, log_r_min, log_span, bins_out):
    """numpy twin of ``_bin_surface``."""
    rows, cols = np.nonzero(np.isfinite(ranges))
    b0, f = _bin_position_numpy(np.log(ranges[rows, cols]), log_r_min, log_span, bins_out.shape[0])
    _add_to_bins(bins_out, b0, f, source[rows, cols], rows, cols)


# The kernels render() calls: compiled, or their numpy twins without numba.
if HAVE_NUMBA:
    KERNELS = {"slab_contributions": _slab_contributions, "backscatter_column": _backscatter_column,
               "backscatter_gated": _backscatter_gated, "bin_surface": _bin_surface}
else:  # pragma: no cover
    KERNELS = {"slab_contributions": slab_contributions_numpy, "backscatter_column": backscatter_column_numpy,
               "backscatter_gated": backscatter_gated_numpy, "bin_surface": bin_surface_numpy}


def blur_by_range(bins: NDArray, bin_ranges: NDArray, forward_blur: float, intrinsics: Intrinsics) -> NDArray[np.float64]:
    """Sum over range bins of each bin blurred by the OTF exp(−B·r·f), f in cycles/rad. (H, W, N).

    The OTF exp(−a·f) is the Fourier transform of a 2-D Poisson kernel of scale a/2π rad;
    the image is padded (mirrored) by three such scales of the farthest bin in use so
    that light does not wrap around the edges.
    """
    n_bins, h, w, n = bins.shape
    used = [b for b in range(n_bins) if bins[b].any()]
    if forward_blur == 0 or not used:
        return bins.sum(axis=0)
    scale_px = forward_blur * bin_ranges[max(used)] / (2 * np.pi) * max(intrinsics.fx, intrinsics.fy)
    pad = int(min(max(h, w) // 2, 3 * scale_px + 4))
    hp, wp = cv2.getOptimalDFTSize(h + 2 * pad), cv2.getOptimalDFTSize(w + 2 * pad)
    fy = np.fft.fftfreq(hp)[:, None] * intrinsics.fy  # cycles/pixel × pixels/rad = cycles/rad
    fx = np.fft.rfftfreq(wp)[None, :] * intrinsics.fx
    f = np.hypot(fx, fy).astype(np.float32)
    out = np.zeros((h, w, n))
    for k in range(n):
        spectrum = np.zeros((hp, wp // 2 + 1), dtype=np.complex64)
        for b in used:
            plane = bins[b, :, :, k].astype(np.float32)
            padded = cv2.copyMakeBorder(plane, pad, hp - h - pad, pad, wp - w - pad, cv2.BORDER_REFLECT)
            spectrum += np.fft.rfft2(padded) * np.exp(np.float32(-forward_blur * bin_ranges[b]) * f)
        out[..., k] = np.fft.irfft2(spectrum, s=(hp, wp))[pad : pad + h, pad : pad + w]
    return np.maximum(out, 0.0)


def slab_edges(z_near: float, z_far: float, slabs: int) -> NDArray[np.float64]:
    """Geometrically spaced slab boundaries along camera z: thin near the lamp, where
    backscatter changes fastest, thicker far away."""
    return np.geomspace(z_near, z_far, slabs + 1)


def render(
    hit: Hit,
    reflectance: NDArray,
    rays: NDArray,
    intrinsics: Intrinsics,
    water: Water,
    lamp: Lamp,
    ambient: Ambient | None = None,
    slabs: int = 32,
    gate_width: float | None = None,
    blur_bins: int = 10,
    kernels: dict | None = None,
) -> Components:
    """Render the image components of a ray-cast scene. Shapes: rays (H, W, 3), reflectance (H, W, N).

    kernels: per-pixel kernels by name (default :data:`KERNELS`; tests pass the numpy twins)."""
    k_ = KERNELS if kernels is None else kernels
    h, w, n = reflectance.shape
    c, g, beta = water.attenuation, water.scatter_attenuation, water.backscatter
    d_c = hit.range
    surface = np.isfinite(d_c)
    zeros = np.zeros((h, w, n))
    direct, forward, back, amb = zeros.copy(), zeros.copy(), zeros.copy(), zeros.copy()
    finite = d_c[surface]
    z_far_surface = float((d_c * rays[..., 2])[surface].max()) if surface.any() else 0.0
    # Open water: integrate until the round trip has dimmed every channel a thousandfold.
    open_water_far = 3.5 / max(float(c.min()), 1e-3)
    z_far = max(z_far_surface, open_water_far if (~surface).any() else z_far_surface, 0.1)
    r_min = 0.05
    r_max = max(float(finite.max()) if finite.size else 0.0, z_far / float(rays[..., 2].min()))
    log_span = math.log(max(r_max, r_min * 1.01) / r_min)
    bins = np.zeros((blur_bins, h, w, n), dtype=np.float64)  # surface light, forward-scattered
    back_bins = np.zeros_like(bins)  # backscattered light, forward-scattered on its way back

    if lamp.on:
        s = np.asarray(lamp.position, dtype=np.float64)
        intensity = lamp.intensities(n)
        dc = np.where(surface, d_c, 0.0)
        to_lamp = s - dc[..., None] * rays
        d_s = np.linalg.norm(to_lamp, axis=-1)
        d_s_safe = np.where(d_s > 0, d_s, 1.0)
        cos_gamma = np.clip(np.einsum("...i,...i", hit.normal, to_lamp) / d_s_safe, 0.0, 1.0)
        beam_scale = lamp.beam_scale
        beam = np.exp(-beam_scale * (1.0 + to_lamp[..., 2] / d_s_safe))  # cos θ = −to_lamp_z / d_s
        r = lamp.effective_radius
        geometric = np.where(surface, beam * (r / (d_s + r)) ** 2 * cos_gamma / math.pi, 0.0)
        radiance = intensity * reflectance * geometric[..., None] * np.exp(-c * d_s[..., None])
        att_c = np.exp(-c * dc[..., None])
        direct = np.where(surface[..., None], radiance * att_c, 0.0)
        forward_source = np.where(surface[..., None], radiance * (np.exp(-g * dc[..., None]) - att_c), 0.0)
        k_["bin_surface"](forward_source, d_c, math.log(r_min), log_span, bins)
        if np.any(beta > 0):
            args = (s, r, beam_scale, intensity, c, g, beta)
            if gate_width:
                open_gate_end = float(np.median(finite)) if finite.size else 1.0
                k_["backscatter_gated"](np.ascontiguousarray(rays), np.ascontiguousarray(d_c), float(gate_width), GATE_STEPS,
                                   open_gate_end, *args, math.log(r_min), log_span, back, back_bins)
            else:
                edges = slab_edges(PORT_DISTANCE, z_far, slabs)
                step = BACKSCATTER_GRID_STEP
                gh, gw = -(-(h - 1) // step) + 1, -(-(w - 1) // step) + 1
                slab_direct = np.zeros((gh, gw, slabs, n))
                slab_forward = np.zeros((gh, gw, slabs, n))
                inv_f = np.array([1.0 / intrinsics.fx, 1.0 / intrinsics.fy])
                centre = np.array([intrinsics.cx, intrinsics.cy, h, w], dtype=np.float64)
                k_["slab_contributions"](inv_f, centre, step, edges, *args, slab_direct, slab_forward)
                k_["backscatter_column"](np.ascontiguousarray(rays), np.ascontiguousarray(d_c), step, np.log(edges), slab_direct,
                                    slab_forward, z_far, math.log(r_min), log_span, back, back_bins)
    bin_ranges = r_min * np.exp(np.linspace(0.0, log_span, blur_bins))
    forward = blur_by_range(bins, bin_ranges, water.forward_blur, intrinsics)
    if back_bins.any():
        back += blur_by_range(back_bins, bin_ranges, water.forward_blur, intrinsics)

    if ambient is not None:
        a = np.asarray(ambient.irradiance, dtype=np.float64)
        up = np.clip(-hit.normal[..., 2], 0.0, 1.0)  # the camera looks down: up is −z
        dc = np.where(surface, d_c, np.inf)
        amb = np.where(surface[..., None], a * reflectance * up[..., None] / math.pi * np.exp(-c * np.where(surface, d_c, 0.0)[..., None]), 0.0)
        amb += a * ambient.path_fraction * (1.0 - np.exp(-c * dc[..., None]))
    return Components(direct, forward, back, amb)
