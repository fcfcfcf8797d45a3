"""The survey renderer's compiled kernels and their numpy twins (used where numba is missing):
ray/height-map intersection, shading with backscatter, interpolation and exposure with noise.
The physics is described in :mod:`uwcam.simulation.survey`."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from uwcam.compute.jit import HAVE_NUMBA, njit, prange
from uwcam.simulation.camera import frame_key, inverse_normal_table, splitmix

if HAVE_NUMBA:
    from numba import uint64
else:  # pragma: no cover
    uint64 = np.uint64

from uwcam.simulation.terrain import Terrain

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


NOISE_POOL_SIZE = 1 << 20
"""Standard normal deviates drawn once for the survey's noise (float32, 4 MB)."""
NOISE_BLOCK = 4096
"""Samples that take their deviates from one pair of places in the pool."""
SQRT_HALF = math.sqrt(0.5)


@njit(cache=True, inline="always")
def _pool_offsets(key, block, size):
    """The two places in the pool (distinct, each < size) that block ``block`` of a frame reads from."""
    r = splitmix(key + uint64(block))
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
