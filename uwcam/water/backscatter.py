"""Backscatter compensation: subtract the water's own light before ranging, iteratively.

Backscatter adds light that never reached the surface, more of it the farther the surface
(the lit water column in front of it is longer) and most where lamp beam and view overlap.
Its spectrum is not the surface's, so it biases the colour ratio toward the water's colour.

Model:
  bs_k(p, z) = S_k(p) · F_k(p, z)
* F_k(p, z): the share of pixel p's open-water backscatter that comes from water closer than
  depth z. When the profile knows the absolute attenuation c_k and the lamp's effective radius
  r (calibrate with --lamp-radius), F follows the physics of the lit column along the pixel's
  ray: ∫ (r/(d_s + r))² exp(−c_k (d_s + t)) dt up to z, over the same integral to infinity
  (the beam pattern is taken as even across the view; its shape is in S). Otherwise F is
  interpolated between the backscatter measured at the calibration plate's black patch at
  each plate distance (0 at the camera) and held beyond the last.
* S_k(p): the open-water backscatter, from a lamp-lit frame of open water (nothing in range)
  smoothed; without one, the patch measurements scaled by F. Given several open-water frames,
  also each pixel's own response relative to its neighbours (the sensor's photo-response
  non-uniformity, 1 % or so, which a smoothed pattern loses: 1 % of a backscatter twenty times the
  surface's light is a fifth of that light), estimated from their mean and shrunk by the noise
  that their spread shows (see :func:`pixel_response`).

Ranging then iterates: range → backscatter at that range → subtract → range, starting from the
uncompensated range. Pixels still without a range use the open-water (or plateau) level.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import pixel_rays
from uwcam.optics.lens_shading import shading_map
from uwcam.water.column import (_DEPTH_SAMPLES, _PORT, ColumnFit, _column_shares, _column_totals, _tail_disagreement,
                                column_fit_agrees, fit_column)
from uwcam.optics.noise import signal_variance
from uwcam.calibration.profile import CalibrationProfile
from uwcam.compute.jit import HAVE_NUMBA, njit


def _interpolate_table_py(flat, index, spatial, i0, f, out):
    """out[p, k] = Σ_q spatial[q, p] · ((1 − f[p]) · flat[index[q, p] + i0[p], k] + f[p] · flat[… + 1, k]):
    F of :meth:`BackscatterModel.fraction` for P pixels, four grid nodes each (compiled: one pass,
    no temporaries; the numpy gather it replaces cost ~2 ms per 720p frame, twice a frame)."""
    for p in range(out.shape[0]):
        g = f[p]
        for k in range(out.shape[1]):
            acc = 0.0
            for q in range(4):
                row = index[q, p] + i0[p]
                acc += spatial[q, p] * ((1.0 - g) * flat[row, k] + g * flat[row + 1, k])
            out[p, k] = acc


_interpolate_table = njit(cache=True, nogil=True)(_interpolate_table_py) if HAVE_NUMBA else None

# Side of the box average that takes the noise out of an open-water frame (pixels).
OPEN_WATER_SMOOTHING = 15


# The coarse pixel grid the physical model is evaluated on.
_GRID_STEP = 16


def pixel_response(frames: NDArray, smooth: NDArray) -> NDArray[np.float64]:
    """Each pixel's response relative to the smoothed level, from K ≥ 2 frames of a smooth scene.

    frames: (K, H, W, N) dark-corrected DN; smooth: (H, W, N) the smoothed mean. The relative
    residual q = mean/smooth − 1 of each pixel holds its response g − 1 (variance σ_g², one value
    per channel) and the noise of a K-frame mean (variance σ_n²/K, from the frames' spread about
    their mean); the estimate is the shrunk q · σ_g²/(σ_g² + σ_n²/K) (the Wiener weight, with
    σ_g² = var q − σ_n²/K, 0 when negative). Returns (H, W, N) g ≥ 0, 1 on average.
    """
    return pixel_response_estimate(frames, smooth).response


@dataclass(frozen=True)
class ResponseEstimate:
    """Each pixel's response estimated from open water (:func:`pixel_response`), and how well."""

    response: NDArray[np.float64]
    """(H, W, N) ĝ = 1 + w·q, ≥ 0."""
    weight: NDArray[np.float64]
    """(N,) w, the Wiener weight each channel's relative residual q was shrunk by (0–1)."""
    noise: NDArray[np.float64]
    """(N,) σ_n²/K, the relative variance of q's noise (the mean of the frames' noise over the view)."""

    def residual_fixed_pattern(self, fixed_pattern: NDArray) -> NDArray[np.float64]:
        """(N,) relative rms of the fixed pattern a background multiplied by ``response`` still
        carries, for a sensor whose fixed pattern has rms ``fixed_pattern`` (N,) (the noise model's).

        With g − 1 of variance f² and ĝ − 1 = w·(g − 1 + noise), what a pixel's background b keeps
        of it is g − ĝ, of variance R = f²(1 − w)² + w²σ_n²/K, and its covariance with the pixel's
        own g − 1 (which multiplies the surface's light v too) is C = f²(1 − w). The variance of
        the surface's light left after subtracting ĝ·b is then f²v² + R·b² + 2C·v·b, which
        (f² − r²)·v² + r²·(v + b)² with r² = max(R, C) covers (exactly where the weight is the
        optimal one, R = C). No response estimated (w = 0): r = f, the pattern counted whole."""
        f2 = np.asarray(fixed_pattern, np.float64) ** 2
        w = self.weight
        covariance = f2 * (1.0 - w)
        residual = f2 * (1.0 - w) ** 2 + w**2 * self.noise
        return np.sqrt(np.maximum(residual, covariance))


def pixel_response_estimate(frames: NDArray, smooth: NDArray) -> ResponseEstimate:
    """:func:`pixel_response` with its weights and noise (:class:`ResponseEstimate`)."""
    k = frames.shape[0]
    return response_of_mean_estimate(frames.mean(axis=0), smooth, frames.var(axis=0, ddof=1) / k)


MAX_FRAMES_AVERAGED = 100_000
"""The most open-water frames a capture's mean is taken to be made of."""


def frames_averaged_count(value: object) -> int | None:
    """``value`` as the count of frames an open-water frame is the mean of: an int from 1 to
    :data:`MAX_FRAMES_AVERAGED`; None where it is not one (a state file or record from elsewhere)."""
    if isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_FRAMES_AVERAGED:
        return value
    return None


def response_of_mean(mean: NDArray, smooth: NDArray, noise: NDArray) -> NDArray[np.float64]:
    """:func:`pixel_response` from the mean of the frames alone: mean (H, W, N) dark-corrected DN,
    smooth (H, W, N) its smoothed level, noise (H, W, N) the variance (DN²) of the mean's noise
    (the frames' spread over K, or the camera's noise model over K where only the mean was kept)."""
    return response_of_mean_estimate(mean, smooth, noise).response


def response_of_mean_estimate(mean: NDArray, smooth: NDArray, noise: NDArray) -> ResponseEstimate:
    """:func:`response_of_mean` with its weights and noise (:class:`ResponseEstimate`)."""
    safe = np.where(smooth > 0, smooth, 1.0)
    q = np.where(smooth > 0, mean / safe - 1.0, 0.0)
    relative = np.where(smooth > 0, noise / safe**2, 0.0)  # (H, W, N) variance of q's noise
    noise_var = relative.reshape(-1, relative.shape[-1]).mean(axis=0)
    total_var = (q**2).reshape(-1, q.shape[-1]).mean(axis=0)
    response_var = np.maximum(total_var - noise_var, 0.0)
    weight = np.where(total_var > 0, response_var / np.where(total_var > 0, total_var, 1.0), 0.0)
    return ResponseEstimate(np.maximum(1.0 + q * weight, 0.0), weight, noise_var)


_FIT_MARGIN = 2 * OPEN_WATER_SMOOTHING  # pixels of the open-water frame kept clear of its border (the smoothing's edge)
_PATTERN_STEP = 8  # pixels between the rays the physical open-water pattern is evaluated on


def patch_disagreement(model: "BackscatterModel", profile: CalibrationProfile) -> float:
    """How far the black-patch measurements stray from ``model`` (one built from them alone, scaled
    to the farthest): the largest |measured − modelled| / modelled, over channels and the other
    plate distances, of what the measurements' own noise (3σ of both) leaves unexplained; 0 with
    one distance or where the modelled level is within its noise of 0.

    The model extrapolates the lamp's whole lit column from the patch; where the water's light at
    the patch is not that (a range-gated camera sees the slab of water around the plate, and the
    plate's own light blurred into the patch, both falling as the plate recedes, where the column's
    rises), the nearer plate shows it: the model's error beyond the plate is then at least that large.
    """
    bs = profile.backscatter
    if bs is None or len(bs.distances_m) < 2:
        return 0.0
    names = profile.channel_names
    order = np.argsort(bs.distances_m)
    depths = np.asarray(bs.distances_m, np.float64)[order]
    pixels = np.asarray(bs.patch_pixels, np.float64)[order]
    levels = np.array([bs.levels[k] for k in names], np.float64).T[order]  # (n, N)
    stds = (np.array([bs.level_std[k] for k in names], np.float64).T[order] if bs.level_std
            else np.zeros_like(levels))

    anchor = model.level_at_pixel(depths[-1], *pixels[-1])
    worst = 0.0
    for i in range(len(depths) - 1):
        predicted = model.level_at_pixel(depths[i], *pixels[i])
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(anchor > 0, predicted / anchor, 0.0)
        noise = 3.0 * np.sqrt(stds[i] ** 2 + (scale * stds[-1]) ** 2)
        meaningful = predicted > noise
        if meaningful.any():
            excess = np.maximum(np.abs(levels[i] - predicted) - noise, 0.0)[meaningful] / predicted[meaningful]
            worst = max(worst, float(excess.max()))
    return worst


@dataclass(frozen=True)
class BackscatterModel:
    """bs_k(p, z) = pattern[p, k] · F_k(p, z); F tabulated over depths on a coarse grid.

    Attributes:
        depths: (T,) depth samples, metres.
        shares: (gh, gw, T, N) F at the grid points, or (1, 1, T, N) when uniform over the image.
        pattern: (H, W, N) open-water backscatter in DN, smoothed, or (1, 1, N).
        grid_step: pixels between the grid points of ``shares``; 0 when uniform over the image.
        response_estimate: each pixel's response relative to the smoothed pattern (from several
            open-water frames) and how well it is known, or None (1 everywhere).
    """

    depths: NDArray[np.float64]
    shares: NDArray[np.float64]
    pattern: NDArray[np.float64]
    grid_step: int
    response_estimate: ResponseEstimate | None = None
    column_fit: ColumnFit | None = None
    """What the open-water frame's shape told of the column (None: no open-water frame, or no
    physics of the column in the profile)."""
    tail_uncertainty: NDArray[np.float64] | None = None
    """(N,) relative uncertainty of the modelled share of the open water's light beyond a surface,
    where the column fit was not used (:func:`column_fit_agrees`): how far the fit's column and the
    calibration's part on it; 0 where the fit was used; None where every channel's was."""
    spread_doubt: NDArray[np.float64] | None = None
    """(H, W) relative uncertainty of the level at each pixel where no open-water frame measured the
    water's light across the view: the black patch measured it at the patch's pixel, and the lamp's
    beam and the lens's shading, which the patch cannot see, move it elsewhere by up to 1 − cos⁴ of
    the angle between that pixel's ray and the patch's (a 30° Gaussian beam 25° off its axis passes
    71 % of its light there, cos⁴ 25° is 67 %). None with an open-water frame or without intrinsics."""

    @property
    def response(self) -> NDArray[np.float64] | None:
        """(H, W, N) each pixel's response relative to the smoothed pattern, or None (1 everywhere)."""
        return None if self.response_estimate is None else self.response_estimate.response

    @classmethod
    def from_profile(cls, profile: CalibrationProfile, open_water: NDArray | None = None,
                     shape: tuple[int, int] | None = None, frames_averaged: int = 1) -> "BackscatterModel":
        """From the profile's backscatter measurements and an optional lamp-lit open-water frame (H, W, N) raw,
        or several of them (K, H, W, N): their mean is the frame, and with K ≥ 2 each pixel's own response
        is estimated too (:func:`pixel_response`). frames_averaged: the one frame (H, W, N) is the mean
        of this many (the daemon keeps only the mean of its capture): with 2 or more the response is
        estimated from it, its noise taken from the profile's noise model. shape: (H, W) of the
        frames to be ranged, when no open-water frame gives it."""
        if profile.backscatter is None:
            raise UserInputError(
                "the calibration profile has no backscatter measurements; calibrate with a rig that has a black patch "
                "(e.g. --rig grey-plate) to compensate backscatter"
            )
        bs = profile.backscatter
        if open_water is not None and profile.response is not None and np.issubdtype(np.asarray(open_water).dtype,
                                                                                      np.integer):
            open_water = profile.response_curve().linearise(np.asarray(open_water))  # a gamma camera's codes
        names = profile.channel_names
        n = len(names)
        measured_depths = np.array(bs.distances_m)
        levels = np.array([bs.levels[k] for k in names]).T  # (n, N)
        order = np.argsort(measured_depths)
        measured_depths, levels = measured_depths[order], levels[order]
        patches = np.array(bs.patch_pixels)[order]
        c = profile.array("attenuation") if all(ch.attenuation is not None for ch in profile.channels) else None
        intr = profile.camera_intrinsics()
        physical = c is not None and profile.lamp_radius_m is not None and intr is not None
        if open_water is not None:
            if open_water.ndim not in (3, 4) or open_water.shape[-1] != n or open_water.shape[0] == 0:
                raise UserInputError(f"the open-water frame must have {n} channels like the profile")
            shape = open_water.shape[-3:-1]
        depths = np.geomspace(_PORT, 200.0, _DEPTH_SAMPLES)
        pattern = None
        if open_water is not None:
            frames = open_water.astype(np.float64).reshape(-1, *open_water.shape[-3:]) - profile.array("dark_level")
            water = frames.mean(axis=0)
            pattern = np.maximum(cv2.blur(water, (OPEN_WATER_SMOOTHING, OPEN_WATER_SMOOTHING), borderType=cv2.BORDER_REFLECT), 0.0)
        beam = None
        column_fit = None
        tail_uncertainty = None
        if physical and pattern is not None:
            # The open-water frame's shape across the view gives the column's attenuation and the
            # beam (the calibration's c is that of the plate's light, which a lamp beside the
            # camera biases: each pixel sees the plate at another angle off the beam at each distance).
            h, w = shape
            m = min(_FIT_MARGIN, (h - 1) // 2, (w - 1) // 2)
            fy = np.unique(np.linspace(m, h - 1 - m, 12).round().astype(int))
            fx = np.unique(np.linspace(m, w - 1 - m, 16).round().astype(int))
            fit_rays = pixel_rays(intr, h, w)[np.ix_(fy, fx)].reshape(-1, 3)
            fit_level = pattern[np.ix_(fy, fx)].reshape(-1, n)
            if profile.lens_shading is not None:
                fit_level = fit_level / shading_map(profile.lens_shading.coefficients, intr, h, w)[np.ix_(fy, fx)].reshape(-1, 1)
            usable = np.all(fit_level > 0, axis=0)
            if usable.any():
                # The smoothed level's noise, in ln at the rays fitted: the frames' spread (or the
                # camera's noise model) over the frames and the smoothing's box.
                if frames.shape[0] >= 2:
                    spread = frames.var(axis=0, ddof=1).reshape(-1, n).mean(axis=0) / frames.shape[0]
                else:
                    spread = signal_variance(water, profile.array("read_noise"), profile.array("shot_gain"),
                                             profile.quantisation_step).reshape(-1, n).mean(axis=0) / max(frames_averaged, 1)
                relative = spread / OPEN_WATER_SMOOTHING**2 / np.maximum(pattern[np.ix_(fy, fx)].reshape(-1, n), 1e-30) ** 2
                column = (fit_level[:, usable], fit_rays, np.array(profile.lamp_position_m), profile.lamp_radius_m)
                noise = np.sqrt(relative.mean(axis=0))[usable]
                column_fit = fit_column(*column, prior=c[usable], noise=noise)
                trusted = column_fit_agrees(column_fit, c[usable])
                if profile.lens_shading is None and not trusted.all():
                    # A lens's unmeasured shading reads as a column of almost no attenuation (its fall-off
                    # toward the edge, like a long column's): fitted with the column, it is told apart by
                    # all that is not radial about the centre. Only then: where the view's radial shape is
                    # the column's, it tells c better than the calibration (a lamp far aside).
                    shaded = fit_column(*column, prior=c[usable], estimate_shading=True, noise=noise)
                    shaded_trusted = column_fit_agrees(shaded, c[usable])
                    if shaded_trusted.sum() > trusted.sum():
                        column_fit, trusted = shaded, shaded_trusted
                fitted = c.copy()
                fitted[usable] = column_fit.attenuation
                chosen = c.copy()
                chosen[usable] = np.where(trusted, column_fit.attenuation, c[usable])
                fitted_beam = np.zeros(n)
                fitted_beam[usable] = column_fit.beam
                beam = np.zeros(n)
                beam[usable] = np.where(trusted, column_fit.beam, 0.0)
                if not trusted.all():
                    # The fit and the calibration tell different columns: the share beyond a surface is
                    # then known only as well as the two agree on it.
                    doubted = np.zeros(n, bool)
                    doubted[np.flatnonzero(usable)[~trusted]] = True
                    tail_uncertainty = np.where(doubted, _tail_disagreement(
                        intr, shape, np.array(profile.lamp_position_m), profile.lamp_radius_m,
                        (chosen, beam), (fitted, fitted_beam)), 0.0)
                c = chosen
        if physical:
            h, w = shape if shape is not None else (int(2 * intr.cy + 1), int(2 * intr.cx + 1))
            gy = np.minimum(np.arange(0, h + _GRID_STEP, _GRID_STEP), h - 1)
            gx = np.minimum(np.arange(0, w + _GRID_STEP, _GRID_STEP), w - 1)
            rays = pixel_rays(intr, h, w)[np.ix_(gy, gx)].reshape(-1, 3)
            lamp = np.array(profile.lamp_position_m)
            shares = _column_shares(rays, lamp, profile.lamp_radius_m, c, depths, beam).reshape(len(gy), len(gx), len(depths), n)
            step = _GRID_STEP
        else:
            at = np.concatenate([[0.0], measured_depths])
            shares = np.stack([np.interp(depths, at, np.concatenate([[0.0], levels[:, k] / levels[-1, k]]))
                               if levels[-1, k] > 0 else np.zeros_like(depths) for k in range(n)], axis=-1)[None, None]
            step = 0
        if pattern is not None:
            estimate = None
            if frames.shape[0] >= 2:
                estimate = pixel_response_estimate(frames, pattern)
            elif frames_averaged >= 2:
                q = profile.quantisation_step
                noise = signal_variance(water, profile.array("read_noise"), profile.array("shot_gain"), q) / frames_averaged
                estimate = response_of_mean_estimate(water, pattern, noise)
            return cls(depths, shares, pattern, step, estimate, column_fit, tail_uncertainty)
        # No open-water frame: scale F so the model meets the last patch measurement; uniform in
        # space, or, with the physics of the column, following the lamp's place across the view.
        shape_across = np.ones((1, 1, n))
        if physical:
            h, w = shape if shape is not None else (int(2 * intr.cy + 1), int(2 * intr.cx + 1))
            gh, gw = max(h // _PATTERN_STEP, 2), max(w // _PATTERN_STEP, 2)
            rows = np.linspace(0, h - 1, gh).round().astype(int)
            cols = np.linspace(0, w - 1, gw).round().astype(int)
            rays = pixel_rays(intr, h, w)[np.ix_(rows, cols)].reshape(-1, 3)
            totals = _column_totals(rays, np.array(profile.lamp_position_m), profile.lamp_radius_m, c).reshape(gh, gw, n)
            totals = totals / totals.max(axis=(0, 1))
            shape_across = cv2.resize(totals.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, n)
        if intr is not None and profile.lens_shading is not None:
            # The lens passes less of the water's light toward the edge of the view, as it does the plate's.
            h, w = shape if shape is not None else (int(2 * intr.cy + 1), int(2 * intr.cx + 1))
            lens = shading_map(profile.lens_shading.coefficients, intr, h, w)[..., None]
            shape_across = np.broadcast_to(shape_across, (h, w, n)) * lens
        spread_doubt = None
        if intr is not None:
            h, w = shape if shape is not None else (int(2 * intr.cy + 1), int(2 * intr.cx + 1))
            rays = pixel_rays(intr, h, w)
            x, y = patches[-1]
            at_patch = rays[int(round(min(max(y, 0), h - 1))), int(round(min(max(x, 0), w - 1)))]
            spread_doubt = 1.0 - np.clip(rays @ at_patch, 0.0, 1.0) ** 4
        at_patch = cls(depths, shares, shape_across, step).level_at_pixel(measured_depths[-1], *patches[-1])
        scale = np.where(at_patch > 0, levels[-1] / np.where(at_patch > 0, at_patch, 1.0), 0.0)
        return cls(depths, shares, (shape_across * scale).astype(np.float64), step, spread_doubt=spread_doubt)

    def corners(self, rows: NDArray, cols: NDArray) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """For pixels at (rows, cols) (any shape S, full-resolution coordinates): the rows of the
        flattened table ``shares.reshape(-1, N)`` at the first depth sample of the four grid nodes
        around each pixel, and their bilinear weights; (4, *S) each. They do not depend on depth:
        a caller that asks for F at the same pixels again and again computes them once
        (:meth:`fraction`'s ``corners``). Only for a model with a grid (grid_step > 0)."""
        gh, gw, n_depths, _ = self.shares.shape
        gy, gx = np.asarray(rows, np.float64) / self.grid_step, np.asarray(cols, np.float64) / self.grid_step
        y0 = np.minimum(gy.astype(int), gh - 2)
        x0 = np.minimum(gx.astype(int), gw - 2)
        fy, fx = gy - y0, gx - x0
        index = np.stack([((y0 + dy) * gw + (x0 + dx)) * n_depths for dy in (0, 1) for dx in (0, 1)])
        weight = np.stack([wy * wx for wy in (1 - fy, fy) for wx in (1 - fx, fx)])
        return index.astype(np.int64), weight

    def fraction(self, depth: NDArray, rows: NDArray | None = None, cols: NDArray | None = None,
                 corners: tuple[NDArray, NDArray] | None = None) -> NDArray[np.float64]:
        """F at surface depths (H, W) metres → (H, W, N); NaN depth (no range) counts as open water.
        rows, cols: the pixels' full-resolution coordinates (default: the pixel grid of ``depth``);
        corners: :meth:`corners` of those pixels, computed beforehand (then rows and cols are not read)."""
        z = np.asarray(depth, dtype=np.float64)
        z = np.where(np.isnan(z), self.depths[-1], np.clip(z, self.depths[0], self.depths[-1]))
        pos = np.interp(np.log(z), np.log(self.depths), np.arange(len(self.depths)))
        i0 = np.minimum(pos.astype(int), len(self.depths) - 2)
        f = pos - i0
        if self.grid_step == 0:
            table = self.shares[0, 0]
            return table[i0] * (1 - f)[..., None] + table[i0 + 1] * f[..., None]
        if corners is None:
            if rows is None:
                rows, cols = np.mgrid[0:z.shape[0], 0:z.shape[1]]
            corners = self.corners(rows, cols)
        index, spatial = corners
        flat = self.shares.reshape(-1, self.shares.shape[-1])
        if _interpolate_table is not None:
            out = np.empty(z.shape + (flat.shape[1],))
            _interpolate_table(np.ascontiguousarray(flat), index.reshape(4, -1), spatial.reshape(4, -1),
                               i0.reshape(-1), f.reshape(-1), out.reshape(-1, flat.shape[1]))
            return out
        # Bilinear in the pixel grid, linear in log depth: eight table rows per pixel, taken in one
        # gather (one numpy call rather than eight: the grid is small, the calls were the cost).
        rows_at = index + i0
        both = np.concatenate([rows_at, rows_at + 1])
        weight = np.concatenate([spatial * (1 - f), spatial * f])
        return np.einsum("q...,q...n->...n", weight, flat[both])

    def level_at_pixel(self, depth: float, x: float, y: float) -> NDArray[np.float64]:
        """(N,) backscatter (DN) at one pixel (x, y), full-resolution coordinates (the pattern's
        nearest pixel, clamped to it), for a surface at ``depth`` metres: a patch measurement's twin."""
        f = self.fraction(np.array([[depth]]), np.array([[y]]), np.array([[x]]))[0, 0]
        p = self.pattern
        row = int(round(min(max(y, 0), p.shape[0] - 1)))
        col = int(round(min(max(x, 0), p.shape[1] - 1)))
        level = p[row, col] * f
        return level if self.response is None else level * self.response[row, col]

    def open_water_level(self, shape: tuple[int, int]) -> NDArray[np.float64]:
        """(H, W, N) backscatter (DN, dark-corrected) of open water, nothing in range, at every pixel of
        frames of ``shape`` (H, W): the light a pixel must be clearly above to carry a surface's."""
        return self.level(np.full(shape, np.nan))

    def level(self, depth: NDArray) -> NDArray[np.float64]:
        """Backscatter (DN, dark-corrected) for surfaces at ``depth`` (H, W) metres → (H, W, N)."""
        level = self.pattern * self.fraction(depth)
        return level if self.response is None else level * self.response
