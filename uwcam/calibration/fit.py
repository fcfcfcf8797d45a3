"""In-situ calibration from a target imaged at known distances (docs/physics.md §4).

The fitting functions are pure and work on per-image region statistics; :func:`calibrate`
measures those statistics on frames and assembles a :class:`CalibrationProfile`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range
from uwcam.optics.noise import signal_variance
from uwcam.calibration.profile import (
    BackscatterSamples,
    CalibrationCovariance,
    CalibrationProfile,
    ChannelCalibration,
    Provenance,
    now_iso,
)
from uwcam.calibration.black_patch import (EDGE, BackscatterEstimate, backscatter_at_black_patch, dilate_mask,
                                          locate_black_patch)
from uwcam.calibration.line_fit import (
    SMOOTHING,
    AttenuationFit,
    absolute_attenuation,
    common_pixel_means,
    fit_attenuation_differences,
    log_mean_variance,
    mean_weights,
    smoothed_log_signal,
    spreading_log,
)
from uwcam.calibration.noise_fit import (
    NOISE_BINS,
    NoiseFit,
    NoisePoint,
    dim_noise_points,
    fit_noise,
    mask_interior,
    noise_point,
    signal_variance_temporal,
    variance_floor,
)

# A target region with more clipped pixels than this is refused rather than averaged.
MAX_SATURATED_FRACTION = 0.01
# Noise floor = backscatter at the black patch + this many σ of its pixel noise.
FLOOR_SIGMAS = 3.0
# Backscatter more than this many σ from 0 at any distance counts as measured (see calibrate_with_details);
# at 5σ clean water is almost never taken for murky (6 tests per calibration: ~4e-6).
BACKSCATTER_SIGMAS = 5.0
BACKSCATTER_FRACTION = 1e-3

Box = tuple[int, int, int, int]  # x, y, width, height in pixels


def project_plate_box(centre_m: tuple[float, float], size_m: tuple[float, float], distance: float, intrinsics: Intrinsics) -> Box:
    """Pixel box of a rectangle on a plate square to the optical axis at ``distance`` (m), centred on the axis."""
    x0 = intrinsics.cx + intrinsics.fx * (centre_m[0] - size_m[0] / 2) / distance
    x1 = intrinsics.cx + intrinsics.fx * (centre_m[0] + size_m[0] / 2) / distance
    y0 = intrinsics.cy + intrinsics.fy * (centre_m[1] - size_m[1] / 2) / distance
    y1 = intrinsics.cy + intrinsics.fy * (centre_m[1] + size_m[1] / 2) / distance
    xa, ya = int(np.ceil(x0)), int(np.ceil(y0))
    return xa, ya, int(np.floor(x1)) - xa + 1, int(np.floor(y1)) - ya + 1


def box_mask(shape: tuple[int, int], box: Box | None, what: str) -> NDArray[np.bool_]:
    """Boolean (H, W) mask of a pixel box; the whole image for None. Errors if it misses the image."""
    h, w = shape
    if box is None:
        return np.ones((h, w), dtype=bool)
    x, y, bw, bh = box
    if bw <= 0 or bh <= 0 or x < 0 or y < 0 or x + bw > w or y + bh > h:
        raise UserInputError(f"{what} {x},{y},{bw},{bh} (x,y,width,height) does not lie inside the {w}×{h} image")
    m = np.zeros((h, w), dtype=bool)
    m[y : y + bh, x : x + bw] = True
    return m


@dataclass(frozen=True)
class CalibrationInputs:
    """What a calibration needs besides the frames and distances; units in each name."""

    channel_names: list[str]
    wavelengths_nm: list[float | None]
    target_reflectance: NDArray[np.float64]  # (N,)
    black_reflectance: NDArray[np.float64] | None = None  # (N,), if the target has a black patch
    target_box: Box | None = None  # one box for all images, or per-image boxes below
    target_boxes: list[Box] | None = None
    black_boxes: list[Box] | None = None
    lamp_position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intrinsics: Intrinsics | None = None
    lamp_radius_m: float | None = None
    dark_level: NDArray[np.float64] | None = None  # (N,) DN
    saturation_level: float = 65535.0
    quantisation_step: float = 1.0
    reference: int = 0
    name: str = "uwcam calibration"
    target_description: str = "spectrally flat target"
    image_names: list[str] | None = None


@dataclass(frozen=True)
class DistanceGroup:
    """The frames taken at one distance and what was measured on their average."""

    distance_m: float
    images: list[str]
    mean_frame: NDArray[np.float64]
    """(H, W, N) average of the frames, dark-corrected, DN."""
    target: NDArray[np.bool_]
    """(H, W) plate pixels used for the fit."""
    black: NDArray[np.bool_] | None
    path_length_m: float = 0.0
    log_signal: NDArray[np.float64] | None = None
    log_variance: NDArray[np.float64] | None = None
    backscatter: BackscatterEstimate | None = None
    fit_pixels: NDArray[np.bool_] | None = None
    """(H, W) the pixels whose light entered the fit."""


@dataclass(frozen=True)
class CalibrationDetails:
    """Everything measured on the way to a profile: for reports and plots."""

    profile: CalibrationProfile
    groups: list[DistanceGroup]
    noise_points: list[tuple[str, NoisePoint]]
    noise: NoiseFit
    fit: AttenuationFit


def calibrate(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs) -> CalibrationProfile:
    """Calibration profile from frames (H, W, N) of the target at camera distances (m, along the axis).

    Frames given the same distance are averaged; see :func:`calibrate_with_details`."""
    return calibrate_with_details(frames, distances_m, inputs).profile


def _check_frames(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs, names: list[str]) -> None:
    n_img = len(frames)
    if len(distances_m) != n_img:
        raise UserInputError(f"got {n_img} images but {len(distances_m)} --distance values; give one distance per image, in order")
    if any(not (np.isfinite(d) and d > 0) for d in distances_m):
        raise UserInputError(f"distances must be positive metres, got {list(distances_m)}")
    if len(set(float(d) for d in distances_m)) < 2:
        raise UserInputError(f"calibration needs images at two or more different distances, got {sorted(set(distances_m))} m")
    n_ch = len(inputs.channel_names)
    for frame, label in zip(frames, names):
        if frame.ndim != 3 or frame.shape[-1] != n_ch:
            got = frame.shape[-1] if frame.ndim == 3 else 1
            raise UserInputError(f"{label} has {got} channel(s) but calibration expects {n_ch} ({','.join(inputs.channel_names)})")
    shape = frames[0].shape[:2]
    for frame, label in zip(frames, names):
        if frame.shape[:2] != shape:
            raise UserInputError(f"{label} is {frame.shape[1]}×{frame.shape[0]} but the first image is {shape[1]}×{shape[0]}; use images of one size")


def calibrate_with_details(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs) -> CalibrationDetails:
    """Calibration profile and what was measured, from frames (H, W, N) at camera distances (m).

    Several frames at one distance (the same distance given repeatedly) are averaged for the
    fit, and their differences give the temporal noise; the spatial spread beyond it is the
    fixed pattern. With one frame per distance the noise model comes from the spatial spread
    of a region clear of the plate's edges and of the black patch. The variance of every
    distance's mean log signal follows from that model, and the fit's joint covariance of
    attenuation differences and log constants is stored in the profile.
    """
    n_img = len(frames)
    names = inputs.image_names or [f"image {i + 1}" for i in range(n_img)]
    if n_img < 2:
        raise UserInputError(f"calibration needs images at two or more distances, got {n_img}")
    _check_frames(frames, distances_m, inputs, names)
    n_ch = len(inputs.channel_names)
    shape = frames[0].shape[:2]
    dark = np.zeros(n_ch) if inputs.dark_level is None else np.asarray(inputs.dark_level, dtype=np.float64)
    lamp = np.asarray(inputs.lamp_position_m, dtype=np.float64)
    rays = pixel_rays(inputs.intrinsics, *shape) if inputs.intrinsics is not None else None
    step = float(inputs.quantisation_step)
    has_black = bool(inputs.black_boxes) and inputs.black_reflectance is not None

    # Group by distance, in order of first appearance.
    order: list[float] = []
    members: dict[float, list[int]] = {}
    for i, d in enumerate(distances_m):
        key = float(d)
        if key not in members:
            order.append(key)
            members[key] = []
        members[key].append(i)

    groups: list[DistanceGroup] = []
    noise_points: list[tuple[str, NoisePoint]] = []
    for distance in order:
        idx = members[distance]
        first = idx[0]
        label = names[first] if len(idx) == 1 else f"{len(idx)} images at {distance:g} m"
        box = inputs.target_boxes[first] if inputs.target_boxes else inputs.target_box
        target = box_mask(shape, box, f"target region of {names[first]}")
        black = None
        if inputs.black_boxes:
            black = box_mask(shape, inputs.black_boxes[first], f"black patch region of {names[first]}")
            target &= ~black
        for i in idx:
            frac = (np.asarray(frames[i])[target] >= inputs.saturation_level).mean(axis=0)
            if frac.max() > MAX_SATURATED_FRACTION:
                k = int(frac.argmax())
                raise UserInputError(
                    f"{frac[k]:.0%} of the target region of {names[i]} is saturated in channel {inputs.channel_names[k]}; "
                    "lower the exposure, gain or lamp intensity and capture it again"
                )
        stack = [np.asarray(frames[i]) for i in idx]
        clipped = np.any([np.any(f >= inputs.saturation_level, axis=-1) for f in stack], axis=0)
        mean_frame = np.mean([f.astype(np.float64) for f in stack], axis=0) - dark
        if black is not None:  # where the image shows the patch: the pose's projection may be pixels off
            black = locate_black_patch(mean_frame, black, target)
            target &= ~black
        usable = target & ~clipped
        # Noise region: away from the plate's edges and from the black patch (and from anything,
        # like markers, outside the target region); on a plate only a few pixels across, as close as it takes.
        away = np.zeros(shape, bool) if black is None else black
        candidates = [mask_interior(usable, EDGE) & ~dilate_mask(away, EDGE + SMOOTHING), mask_interior(usable, 1) & ~dilate_mask(away, 1),
                      usable & ~away]
        region = next((r for r in candidates if (r[:, 2:] & r[:, 1:-1] & r[:, :-2]).sum() >= 2), None)
        if region is None:
            raise UserInputError(f"the target region of {label} is too small to measure its noise; check the regions")
        # The plate's light falls off toward its edges: bins of brightness give the noise model
        # several signal levels per distance.
        brightness = cv2.blur(mean_frame.sum(axis=-1), (SMOOTHING, SMOOTHING))
        edges = np.quantile(brightness[region], np.linspace(0, 1, NOISE_BINS + 1))
        before = len(noise_points)
        for j in range(NOISE_BINS):
            part = region & (brightness >= edges[j]) & (brightness <= edges[j + 1])
            if part.sum() >= 64:
                noise_points.append((f"plate {distance:g} m, level {j + 1}", noise_point(stack, part, dark)))
        if len(noise_points) == before:
            noise_points.append((f"plate {distance:g} m", noise_point(stack, region, dark)))
        if black is not None:
            patch = mask_interior(black, EDGE)
            triples = patch[:, 2:] & patch[:, 1:-1] & patch[:, :-2]
            if triples.sum() >= 2:  # a patch too small to measure its noise still gives backscatter
                noise_points.append((f"black patch {distance:g} m", noise_point(stack, patch, dark)))
        if len(stack) >= 2:
            noise_points += dim_noise_points(stack, brightness, target if black is None else target | black,
                                             clipped, dark, brightness[region].min(), distance)
        groups.append(DistanceGroup(distance, [names[i] for i in idx], mean_frame, usable, black))

    noise = fit_noise([p for _, p in noise_points], step)

    def pixel_variance(signal: NDArray, frames_averaged: int) -> NDArray:
        # Temporal noise averages down over the frames; the fixed pattern does not.
        temporal = signal_variance_temporal(signal, noise) / frames_averaged
        return np.maximum(temporal + (noise.fixed_pattern * np.maximum(signal, 0)) ** 2, variance_floor(signal, step))

    estimates: list[BackscatterEstimate | None] = []
    for g in groups:
        estimate = None
        if has_black and g.black is not None:
            estimate = backscatter_at_black_patch(g.mean_frame, g.black, g.target, inputs.black_reflectance,
                                                  inputs.target_reflectance, pixel_variance(g.mean_frame, len(g.images)))
        estimates.append(estimate)
    # Backscatter is not uniform over a plate (it follows the lamp's beam through the water), so a
    # level measured at the patch cannot be subtracted from the whole plate. Where backscatter is
    # measurable, the fit uses the plate's own light at the patch, which is free of it pixel by
    # pixel; where it is not (clean water, a tank), the whole plate, which has many more pixels.
    # Measured: more than 5σ from 0 and more than 0.1 % of the plate's light (below that its unevenness
    # over the plate moves ln E by less than 1e-4; noise-free frames have σ ≈ 0).
    patch_local = has_black and any(
        np.any((np.abs(e.level) > BACKSCATTER_SIGMAS * np.sqrt(e.variance))
               & (np.abs(e.level) > BACKSCATTER_FRACTION * np.exp(e.plate_log)))
        for e in estimates if e is not None)

    fitted: list[DistanceGroup] = []
    log_signal, log_variance, path_lengths, log_spread_corrected = [], [], [], []
    weights: list[NDArray | None] = []  # each distance's pixel weights in its mean (None: patch-local)
    for g, estimate in zip(groups, estimates):
        m = len(g.images)
        if patch_local:
            pixels = estimate.pixels
            ln_mean = estimate.plate_log
            lv = estimate.plate_log_variance
            ln_e = np.broadcast_to(ln_mean, (int(pixels.sum()), n_ch))
        else:
            if np.any(g.mean_frame[g.target].mean(axis=0) <= 0):
                k = int(np.argmin(g.mean_frame[g.target].mean(axis=0)))
                raise UserInputError(
                    f"the target region at {g.distance_m:g} m has no signal in channel {inputs.channel_names[k]} after dark "
                    "correction; check the lamp, the exposure and that the target is in the region"
                )
            ln_e, pixels = smoothed_log_signal(g.mean_frame, g.target)
            # Each pixel's expected signal, smoothed within the region only (a box reaching past the
            # plate's edge or into the black patch would make its pixels look dark and noisy).
            inside = g.target.astype(np.float64)
            weight = cv2.blur(inside, (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_CONSTANT)
            smooth = cv2.blur(g.mean_frame * inside[..., None], (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_CONSTANT)
            smooth = smooth / np.maximum(weight, 1e-12)[..., None]
            lv = log_mean_variance(pixels, np.maximum(smooth, 1e-30), pixel_variance(smooth, m))
            weights.append(mean_weights(pixels))
            ln_mean = ln_e.mean(axis=0)
        lv = np.maximum(lv, variance_floor(np.exp(ln_mean), step) / np.exp(ln_mean) ** 2)
        u = rays[pixels] if rays is not None else np.array([[0.0, 0.0, 1.0]])
        dc = plane_camera_range(g.distance_m, u)
        ds = np.linalg.norm(dc[:, None] * u - lamp, axis=-1)
        path = float(np.mean(dc + ds))
        log_signal.append(ln_mean)
        log_variance.append(lv)
        path_lengths.append(path)
        if inputs.lamp_radius_m is not None:
            # The plate (normal along −z) is lit at the angle θ from its normal: cos θ = (z − S_z)/d_s.
            lit = np.clip((dc * u[:, 2] - lamp[2]) / ds, 1e-6, 1.0)
            spread = spreading_log(ds, inputs.lamp_radius_m) - np.log(lit)
            log_spread_corrected.append((pixels, ln_e + spread[:, None], dc + ds))
        fitted.append(replace(g, path_length_m=path, log_signal=log_signal[-1], log_variance=lv, backscatter=estimate,
                              fit_pixels=pixels))

    ref = inputs.reference
    # The fixed pattern of pixels that two distances share is the same in both means: it cancels in
    # their difference (the attenuation differences), and counted as independent it would inflate
    # their σ several times. Its covariance between distances i and j: f_k²·Σ_p a_p(i)·a_p(j).
    covariance = None
    if not patch_local and np.any(noise.fixed_pattern > 0):
        cross = np.array([[float(np.sum(a * b)) for b in weights] for a in weights])
        covariance = cross[:, :, None] * np.asarray(noise.fixed_pattern, np.float64) ** 2
    fit = fit_attenuation_differences(np.array(log_signal), path_lengths, ref, np.array(log_variance), covariance)

    backscatter_samples = None
    floor = np.zeros(n_ch)
    if has_black:
        levels = np.array([g.backscatter.level for g in fitted])
        blacks = np.array([g.backscatter.black_mean for g in fitted])
        # The floor is for single frames: the black patch's signal plus 3σ of one pixel's noise.
        sigma = np.sqrt(np.maximum(signal_variance(blacks, noise.read_noise, noise.shot_gain, step, noise.fixed_pattern),
                                   variance_floor(blacks, step)))
        floor = np.max(np.maximum(levels, 0.0) + FLOOR_SIGMAS * sigma, axis=0)
        centres = [(x + w / 2 - 0.5, y + h / 2 - 0.5) for x, y, w, h in
                   (inputs.black_boxes[members[g.distance_m][0]] for g in fitted)]
        backscatter_samples = BackscatterSamples(
            distances_m=[g.distance_m for g in fitted],
            patch_pixels=centres,
            levels={inputs.channel_names[k]: [float(max(v, 0.0)) for v in levels[:, k]] for k in range(n_ch)},
            noise_sigma={inputs.channel_names[k]: float(np.max(sigma[:, k])) for k in range(n_ch)},
            level_std={inputs.channel_names[k]: [float(np.sqrt(max(g.backscatter.variance[k], 0.0))) for g in fitted]
                       for k in range(n_ch)},
        )
    absolute: tuple[NDArray, NDArray] | None = None
    if inputs.lamp_radius_m is not None:
        absolute = absolute_attenuation(*common_pixel_means(log_spread_corrected, path_lengths), np.array(log_variance))

    channels = [
        ChannelCalibration(
            name=inputs.channel_names[k],
            wavelength_nm=inputs.wavelengths_nm[k],
            attenuation_difference=float(fit.attenuation_difference[k]),
            attenuation_difference_std=float(fit.attenuation_difference_std[k]),
            log_constant=float(fit.log_constant[k]),
            log_constant_std=float(fit.log_constant_std[k]),
            attenuation=None if absolute is None else float(max(absolute[0][k], 0.0)),
            target_reflectance=float(inputs.target_reflectance[k]),
            dark_level=float(dark[k]),
            read_noise=float(noise.read_noise[k]),
            shot_gain=float(noise.shot_gain[k]),
            fixed_pattern=float(noise.fixed_pattern[k]),
            noise_floor=float(floor[k]),
        )
        for k in range(n_ch)
    ]
    others = [inputs.channel_names[k] for k in range(n_ch) if k != ref]
    covariance = CalibrationCovariance(parameters=[f"V:{c}" for c in others] + [f"b:{c}" for c in others],
                                       matrix=fit.covariance.tolist())
    residuals = {inputs.channel_names[k]: [float(r) for r in fit.residuals[:, k]] for k in range(n_ch)}
    provenance = Provenance(
        created=now_iso(),
        method=f"{fit.method}; {'plate light at the black patch (backscatter measured)' if patch_local else 'whole plate'}; "
               f"noise: {noise.method}",
        distances_m=[g.distance_m for g in fitted],
        frames_per_distance=[len(g.images) for g in fitted],
        path_lengths_m=path_lengths,
        images=list(names),
        target=inputs.target_description,
        roi=list(inputs.target_box) if inputs.target_box else None,
        residuals=residuals,
        rms_residual=float(np.sqrt(np.mean(fit.residuals**2))),
    )
    intr = inputs.intrinsics
    profile = CalibrationProfile(
        name=inputs.name,
        reference_channel=inputs.channel_names[ref],
        channels=channels,
        saturation_level=float(inputs.saturation_level),
        quantisation_step=float(inputs.quantisation_step),
        lamp_position_m=tuple(float(v) for v in lamp),
        lamp_radius_m=inputs.lamp_radius_m,
        intrinsics=None if intr is None else {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        backscatter=backscatter_samples,
        covariance=covariance,
        provenance=provenance,
    )
    return CalibrationDetails(profile, fitted, noise_points, noise, fit)


