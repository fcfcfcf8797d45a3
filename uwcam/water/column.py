"""The lamp-lit water column along each pixel's ray: how much of the water's light comes from
closer than a depth, and what an open-water frame's shape across the view tells of the column
(its attenuation and the lamp's beam), with how far to trust that (:class:`ColumnFit`).

Each ray's column: ∫ exp(−k(1 − cos θ)) (r/(d_s + r))² exp(−c (d_s + t)) dt, with d_s the lamp's
distance to the point at t along the ray, θ its angle off the lamp's axis, r the lamp's effective
radius (docs/physics.md). :mod:`uwcam.water.backscatter` builds the model of the water's light on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.optics.geometry import pixel_rays
from uwcam.optics.lens_shading import shading_basis

# Depth samples of the physical model.
_DEPTH_SAMPLES = 96
_PORT = 0.05  # water starts at the camera port, metres

# The column's attenuation and the lamp's beam, fitted to an open-water frame: the grids searched.
_FIT_ATTENUATIONS = np.geomspace(0.01, 2.0, 64)  # 1/m
_FIT_BEAM_SCALES = np.linspace(0.0, 8.0, 33)  # k in the beam pattern exp(−k·(1 − cos θ))
_FIT_DEPTH_SAMPLES = 160
FIT_TOLERANCE = 0.002
"""rms in log level (0.2 %) within which column shapes are not told apart: the model's own
simplifications (one c for the light's way out and back, forward scatter folded into it) depart
from real columns by about that much."""


def _column_geometry(rays: NDArray, lamp: NDArray, radius: float, z: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Along each ray (P, 3) at depths z (Z,): the light path ds + t (m), the cosine of the angle
    off the beam's axis (camera z) as seen from the lamp, and the spreading × dt (P, Z) each."""
    t = z[None, :] / rays[:, 2:3]  # (P, Z) distance along each ray
    offset = t[..., None] * rays[:, None, :] - lamp
    ds = np.linalg.norm(offset, axis=-1)
    # Irradiance falls as (r/(d_s + r))²: up to the constant r², which no use of the column's shape
    # keeps, 1/(d_s + r)², so a point lamp (r = 0) spreads as 1/d_s² instead of vanishing.
    spread = np.gradient(t, axis=1) / np.maximum(ds + radius, 1e-3) ** 2
    return ds + t, offset[..., 2] / np.maximum(ds, 1e-12), spread


@dataclass(frozen=True)
class ColumnFit:
    """What :func:`fit_column` found in an open-water frame's shape across the view, and how far to
    trust it. All (N,) per channel."""

    attenuation: NDArray[np.float64]
    """c picked (1/m): within :data:`FIT_TOLERANCE` of the best fit, nearest the prior."""
    beam: NDArray[np.float64]
    """k of the beam exp(−k(1 − cos θ)) that goes best with it."""
    attenuation_range: NDArray[np.float64]
    """(N, 2) the smallest and largest c the shape does not tell from the best (1/m)."""
    at_grid_edge: NDArray[np.bool_]
    """The best fit lies at the end of the searched c (:data:`_FIT_ATTENUATIONS`): the shape wants a c
    the grid does not hold, so no c of it is the water's."""
    residual: NDArray[np.float64]
    """rms (in ln) of the shape the best fit leaves across the view."""
    noise: NDArray[np.float64]
    """rms (in ln) of the level's own noise at the rays fitted: the part of ``residual`` no model removes."""
    shading: NDArray[np.float64]
    """(N, 2) the lens shading's (a, b) of ln V fitted with it (:mod:`uwcam.optics.lens_shading`);
    zeros where the shading was known and taken out before."""


def fit_column(level: NDArray, rays: NDArray, lamp: NDArray, radius: float,
               prior: NDArray | None = None, estimate_shading: bool = False,
               noise: NDArray | None = None) -> ColumnFit:
    """The column attenuation c (1/m) and beam k of :func:`_column_shares` that best give the
    open-water backscatter's shape across the view (:class:`ColumnFit`).

    level: (P, N) smoothed open-water backscatter (DN) along rays (P, 3), with the lens's shading
    taken out where it is known. The open-water level of a ray is ∫ exp(−k(1 − cos θ)) (r/(d_s + r))²
    exp(−c (d_s + t)) dt: how it changes across the view (toward the lamp and away from it, toward the
    beam's edge) depends on c and k, its scale not. Least squares in log level, up to a constant per
    channel, over grids of c and k. With ``estimate_shading`` the lens's unknown shading, radial about
    the axis (ln V = a·ln(1 + ρ²) + b·ρ⁴), is fitted with them: what is radial about the image's centre is then
    not read as c, and only the rest of the shape (the lamp's side, the beam's place) tells c. Where the
    shape does not tell c (a lamp at the camera: every ray's column is lit alike), every c whose best fit
    is within :data:`FIT_TOLERANCE` of the best is as good: then the one nearest (in log) to ``prior``
    (N,), the calibration's c. noise: (N,) rms in ln of the level's noise at the rays (0 where not given).
    """
    z = np.geomspace(_PORT, 200.0, _FIT_DEPTH_SAMPLES)
    path, cos_beam, spread = _column_geometry(rays, lamp, radius, z)
    decay = np.exp(-_FIT_ATTENUATIONS[:, None, None] * path[None])  # (C, P, Z)
    target = np.log(np.maximum(level, 1e-30))  # (P, N)
    n_rays = rays.shape[0]
    # Residuals are taken orthogonal to a constant per channel and, with estimate_shading, to the
    # shading's terms: the projection that removes them.
    basis = np.ones((n_rays, 1))
    if estimate_shading:
        basis = np.concatenate([basis, shading_basis(rays)], axis=1)
    q, _ = np.linalg.qr(basis)
    project = np.eye(n_rays) - q @ q.T  # (P, P)
    target_left = project @ target
    costs = []
    for k in _FIT_BEAM_SCALES:
        model = np.log(np.einsum("cpz,pz->cp", decay, spread * np.exp(-k * (1.0 - cos_beam))))  # (C, P)
        model_left = model @ project
        costs.append(((model_left[:, :, None] - target_left[None]) ** 2).mean(axis=1))  # (C, N)
    cost = np.array(costs)  # (K, C, N)
    profile = cost.min(axis=0)  # (C, N): each c with its best beam
    n = level.shape[1]
    best = profile.argmin(axis=0)
    allowed = profile <= profile.min(axis=0) + FIT_TOLERANCE**2
    if prior is None:
        pick = best
    else:
        distance = np.abs(np.log(_FIT_ATTENUATIONS)[:, None] - np.log(np.maximum(np.asarray(prior, np.float64), _FIT_ATTENUATIONS[0])))
        pick = np.where(allowed, distance, np.inf).argmin(axis=0)
    channels = np.arange(n)
    beam = cost[:, pick, channels].argmin(axis=0)
    c_grid = _FIT_ATTENUATIONS[:, None] * np.ones((1, n))
    span = np.stack([np.where(allowed, c_grid, np.inf).min(axis=0), np.where(allowed, c_grid, -np.inf).max(axis=0)], axis=1)
    edge = (best == 0) | (best == len(_FIT_ATTENUATIONS) - 1)
    shading = np.zeros((n, 2))
    if estimate_shading:
        # The shading that goes with the pick: the radial part of what its model leaves.
        for j in range(n):
            model = np.log(np.einsum("pz,pz->p", np.exp(-_FIT_ATTENUATIONS[pick[j]] * path),
                                     spread * np.exp(-_FIT_BEAM_SCALES[beam[j]] * (1.0 - cos_beam))))
            coef, *_ = np.linalg.lstsq(basis, target[:, j] - model, rcond=None)
            shading[j] = coef[1:]
    noise = np.zeros(n) if noise is None else np.asarray(noise, np.float64)
    return ColumnFit(_FIT_ATTENUATIONS[pick], _FIT_BEAM_SCALES[beam], span, edge,
                     np.sqrt(profile[best, channels]), noise, shading)


FIT_PRIOR_AGREEMENT = 20.0
"""Factor within which the c's that the open-water fit cannot tell apart must take in the
calibration's c (each way) for the fit to be used: beyond it the two disagree about which water it
is, and one of them saw something the model does not hold (a lens's shading, a light in the view).
It is wide because the calibration's absolute c is that of the plate's light, which a lamp beside
the camera biases low, and the column's shape is not the model's in every water: in uwcam's
simulator, Jerlov II with the lamp 0.6 m aside (the grey plate, 160×120), 0.38/0.052/0.022 1/m
against the fit's 0.52/0.21/0.17, whose share of the water's light in front of a seabed at 5 m is
the simulator's within 0.7 %; in the independent forward model (`bench/independent_world.py`:
Jerlov II-like, single scattering with a Henyey–Greenstein phase, a 30° Gaussian beam), the
calibration's 0.34/0.013/0.0 against the fit's 0.73/0.27/0.31 (the truth 0.40/0.075/0.055), whose
ranges at 7 m read within 0.1 % where the calibration's c put them 4 % short."""

FIT_ATTENUATION_FLOOR = 0.03
"""1/m below which c's are not told apart in that comparison: over the few metres of water a view
holds, the open water's shape barely changes below it, and the calibration's absolute c of the
clearest channels (blue in Jerlov I and IB) comes out 0–0.01 against a fit's 0.02–0.03."""

FIT_MAX_RESIDUAL = 0.02
"""rms (in ln) of the open-water frame's shape that the fitted column may leave beyond the level's
own noise: 2 %, ten times :data:`FIT_TOLERANCE`. More is structure across the view that no column of
the model makes."""


def column_fit_agrees(fit: ColumnFit, prior: NDArray) -> NDArray[np.bool_]:
    """(N,) whether each channel's column fit can be used: the c's it cannot tell apart take in the
    calibration's ``prior`` (N,) 1/m within :data:`FIT_PRIOR_AGREEMENT` (all below
    :data:`FIT_ATTENUATION_FLOOR` alike), its best c is not at the edge of the searched grid unless
    they take in the prior itself, and it leaves no more than :data:`FIT_MAX_RESIDUAL` of the shape
    beyond the level's noise."""
    prior = np.maximum(np.asarray(prior, np.float64), FIT_ATTENUATION_FLOOR)
    low = np.maximum(fit.attenuation_range[:, 0], FIT_ATTENUATION_FLOOR)
    high = np.maximum(fit.attenuation_range[:, 1], FIT_ATTENUATION_FLOOR)
    agrees = (prior <= high * FIT_PRIOR_AGREEMENT) & (prior >= low / FIT_PRIOR_AGREEMENT)
    edge = fit.at_grid_edge & ~((prior >= low) & (prior <= high))
    structure = np.sqrt(np.maximum(fit.residual**2 - fit.noise**2, 0.0))
    return agrees & ~edge & (structure <= FIT_MAX_RESIDUAL)


_TAIL_DEPTHS = np.geomspace(0.5, 20.0, 24)
"""Depths (m) at which two columns' shares beyond a surface are compared."""


def _tail_disagreement(intr, shape: tuple[int, int], lamp: NDArray, radius: float,
                       used: tuple[NDArray, NDArray], other: tuple[NDArray, NDArray]) -> NDArray[np.float64]:
    """(N,) how far the share of the open water's light beyond a surface, 1 − F, of the column
    ``other`` (c, k: (N,) each) departs from that of the column ``used``, relative to the latter: the
    largest |(1 − F_other) − (1 − F_used)| / (1 − F_used) over a coarse grid of the view and surfaces at
    0.5–20 m, counted only where either column leaves 0.1 % of the light or more beyond the surface."""
    h, w = shape
    rows = np.linspace(0, h - 1, 5).round().astype(int)
    cols = np.linspace(0, w - 1, 7).round().astype(int)
    rays = pixel_rays(intr, h, w)[np.ix_(rows, cols)].reshape(-1, 3)
    tail_used = 1.0 - _column_shares(rays, lamp, radius, used[0], _TAIL_DEPTHS, used[1])  # (P, T, N)
    tail_other = 1.0 - _column_shares(rays, lamp, radius, other[0], _TAIL_DEPTHS, other[1])
    meaningful = np.maximum(tail_used, tail_other) >= 1e-3
    ratio = np.abs(tail_other - tail_used) / np.maximum(tail_used, 1e-6)
    return np.where(meaningful, ratio, 0.0).max(axis=(0, 1))


def _column_shares(rays: NDArray, lamp: NDArray, radius: float, attenuation: NDArray, depths: NDArray,
                   beam: NDArray | None = None) -> NDArray:
    """(P, T, N) share of each ray's lit-column backscatter closer than each depth (T,); beam: (N,)
    k of the beam pattern exp(−k(1 − cos θ)) per channel (None: an even beam)."""
    z = np.geomspace(_PORT, max(depths[-1], _PORT * 2), _DEPTH_SAMPLES * 4)
    path, cos_beam, spread = _column_geometry(rays, lamp, radius, z)
    shares = []
    for j, c in enumerate(attenuation):
        f = spread * np.exp(-c * path)
        if beam is not None:
            f = f * np.exp(-beam[j] * (1.0 - cos_beam))
        cum = np.cumsum(f, axis=1)
        cum /= cum[:, -1:]
        shares.append(np.stack([np.interp(depths, z, row) for row in cum]))
    return np.stack(shares, axis=-1)


def _column_totals(rays: NDArray, lamp: NDArray, radius: float, attenuation: NDArray) -> NDArray:
    """(P, N) each ray's whole lit-column backscatter ∫ exp(−c(d_s + t))/(d_s + r)² dt, up to a
    constant, with an even beam: how open water's light changes across the view with the lamp's
    place (brighter toward the lamp's side)."""
    z = np.geomspace(_PORT, 200.0, _DEPTH_SAMPLES * 4)
    path, _, spread = _column_geometry(rays, lamp, radius, z)
    return np.stack([np.sum(spread * np.exp(-c * path), axis=1) for c in attenuation], axis=-1)
