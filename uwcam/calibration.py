"""In-situ calibration from a target imaged at known distances (DESIGN.md §4).

The fitting functions are pure and work on per-image region statistics; :func:`calibrate`
measures those statistics on frames and assembles a :class:`CalibrationProfile`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays, plane_camera_range
from uwcam.profile import BackscatterSamples, CalibrationProfile, ChannelCalibration, Provenance, now_iso

# A target region with more clipped pixels than this is refused rather than averaged.
MAX_SATURATED_FRACTION = 0.01
# Noise floor = backscatter at the black patch + this many σ of its pixel noise.
FLOOR_SIGMAS = 3.0
# Side of the box average applied before taking logs of the target (pixels).
SMOOTHING = 5

Box = tuple[int, int, int, int]  # x, y, width, height in pixels


@dataclass(frozen=True)
class RegionStatistics:
    """Statistics of one image region, per channel, after dark correction."""

    mean: NDArray[np.float64]
    """(N,) mean signal E, DN."""
    noise_variance: NDArray[np.float64]
    """(N,) pixel noise variance, DN², from horizontal neighbour differences (gradients cancel)."""
    count: int
    """Number of pixels used."""


@dataclass(frozen=True)
class LineFit:
    """y = intercept + slope·x fitted per channel, with standard uncertainties."""

    intercept: NDArray[np.float64]
    slope: NDArray[np.float64]
    intercept_std: NDArray[np.float64]
    slope_std: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (n, N)


@dataclass(frozen=True)
class AttenuationFit:
    """Relative calibration: y_k = ln(E_k/E_ref) = b_k − V_k·d_T."""

    attenuation_difference: NDArray[np.float64]  # V_k = c_k − c_ref, 1/m
    attenuation_difference_std: NDArray[np.float64]
    log_constant: NDArray[np.float64]  # b_k
    log_constant_std: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (n, N), natural-log units
    method: str


def region_statistics(frame: ArrayLike, mask: ArrayLike, dark_level: ArrayLike = 0.0) -> RegionStatistics:
    """Mean and pixel noise variance of ``frame`` (H, W, N) inside boolean ``mask`` (H, W)."""
    x = np.asarray(frame, dtype=np.float64) - np.asarray(dark_level, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    count = int(m.sum())
    if count == 0:
        raise UserInputError("the target region holds no usable pixels; check --roi and the rig's regions")
    mean = x[m].mean(axis=0)
    pairs = m[:, 1:] & m[:, :-1]
    if pairs.sum() >= 2:
        diff = (x[:, 1:] - x[:, :-1])[pairs]
        noise_variance = diff.var(axis=0) / 2.0
    else:
        noise_variance = np.full(x.shape[-1], np.nan)
    return RegionStatistics(mean=mean, noise_variance=noise_variance, count=count)


def smoothed_log_signal(frame: ArrayLike, mask: ArrayLike, dark_level: ArrayLike = 0.0) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """ln E per pixel of a region after a 5×5 box average, and the (H, W) mask of pixels used.

    Averaging ln E per pixel keeps the calibration exactly linear in each pixel's own
    path length, however much d_T varies over a large target. The box average first
    divides the noise variance by 25, which makes the log's small-signal bias
    (−σ²/2E²) negligible; only pixels whose whole 5×5 box lies in the region are used,
    so nothing from outside it leaks in.
    """
    m = np.asarray(mask, dtype=bool)
    x = np.asarray(frame, dtype=np.float64) - np.asarray(dark_level, dtype=np.float64)
    kernel = np.ones((SMOOTHING, SMOOTHING), np.uint8)
    interior = cv2.erode(m.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    if not interior.any():
        interior = m  # a region thinner than the box: use it unsmoothed
        smooth = x
    else:
        smooth = cv2.blur(x, (SMOOTHING, SMOOTHING), borderType=cv2.BORDER_REFLECT)
    values = smooth[interior]
    positive = np.all(values > 0, axis=-1)
    if not positive.any():
        raise UserInputError("the target region has no pixel with signal in every channel; check the lamp and the region")
    pixels = interior.copy()
    pixels[interior] = positive
    return np.log(values[positive]), pixels


def fit_lines(x: ArrayLike, y: ArrayLike, variance: ArrayLike | None = None) -> LineFit:
    """Weighted least squares y[:, k] = a_k + s_k·x per column k.

    x: (n,), y: (n, N), variance: (n, N) of y or None (equal weights). With n = 2 the
    fit is exact and uncertainties come from ``variance`` alone; with n ≥ 3 they are
    scaled up by the reduced χ² when the scatter exceeds the stated variances, so a
    bad distance or scattering shows up as uncertainty, not false confidence.
    """
    xv = np.asarray(x, dtype=np.float64)
    yv = np.asarray(y, dtype=np.float64)
    n = xv.shape[0]
    var = np.ones_like(yv) if variance is None else np.asarray(variance, dtype=np.float64)
    w = 1.0 / var
    sw, swx, swxx = w.sum(0), (w * xv[:, None]).sum(0), (w * xv[:, None] ** 2).sum(0)
    swy, swxy = (w * yv).sum(0), (w * xv[:, None] * yv).sum(0)
    det = sw * swxx - swx**2
    slope = (sw * swxy - swx * swy) / det
    intercept = (swxx * swy - swx * swxy) / det
    residuals = yv - (intercept + slope * xv[:, None])
    var_slope, var_intercept = sw / det, swxx / det
    dof = n - 2
    if dof > 0:
        chi2 = (w * residuals**2).sum(0) / dof
        scale = chi2 if variance is None else np.maximum(1.0, chi2)
    else:
        scale = np.full(yv.shape[1], np.nan if variance is None else 1.0)
    return LineFit(intercept, slope, np.sqrt(var_intercept * scale), np.sqrt(var_slope * scale), residuals)


def fit_attenuation_differences(
    log_signal: ArrayLike,
    path_lengths: ArrayLike,
    reference: int = 0,
    log_variance: ArrayLike | None = None,
) -> AttenuationFit:
    """Attenuation differences V_k = c_k − c_ref (1/m) and log constants b_k from n ≥ 2 distances.

    log_signal: (n, N) mean of ln E_k over the target in each image; path_lengths: (n,)
    mean d_T over the same pixels, metres; log_variance: (n, N) variance of each
    log_signal entry, if known. Two distances use the closed form of DESIGN.md §4,
    more use weighted least squares on ln(E_k/E_ref) = b_k − V_k·d_T.
    """
    ln_e = np.asarray(log_signal, dtype=np.float64)
    d = np.asarray(path_lengths, dtype=np.float64)
    if ln_e.ndim != 2 or ln_e.shape[0] != d.shape[0] or ln_e.shape[0] < 2:
        raise ValueError(f"need log_signal (n, N) and path_lengths (n,) with n ≥ 2, got {ln_e.shape} and {d.shape}")
    if np.ptp(d) <= 0:
        raise UserInputError("all path lengths are equal; image the target at two or more different distances")
    log_ratio = ln_e - ln_e[:, reference : reference + 1]
    ratio_var = None
    if log_variance is not None:
        lv = np.asarray(log_variance, dtype=np.float64)
        ratio_var = lv + lv[:, reference : reference + 1]
        ratio_var[:, reference] = 1.0  # the reference's own ratio is identically 0; any weight will do
    fit = fit_lines(d, log_ratio, ratio_var)
    if ln_e.shape[0] == 2:
        # Closed form (DESIGN.md §4): V = ln((E_ref1/E_ref2)/(E_k1/E_k2)) / (d1 − d2),
        # b = ln(E_k1/E_ref1) + V·d1. Identical to the fit, stated as the design states it.
        v = ((ln_e[0, reference] - ln_e[1, reference]) - (ln_e[0] - ln_e[1])) / (d[0] - d[1])
        b = log_ratio[0] + v * d[0]
        method = "two-distance closed form"
    else:
        v, b = -fit.slope, fit.intercept
        method = f"weighted least squares over {ln_e.shape[0]} distances"
    v[reference] = 0.0
    b[reference] = 0.0
    v_std, b_std = fit.slope_std.copy(), fit.intercept_std.copy()
    v_std[reference] = b_std[reference] = 0.0
    return AttenuationFit(v, v_std, b, b_std, fit.residuals, method)


def absolute_attenuation(
    spread_corrected_log_signal: ArrayLike,
    path_lengths: ArrayLike,
    log_variance: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Absolute beam attenuation c_k (1/m) and its uncertainty, given the lamp spreading model.

    Irradiance from a lamp of effective radius r = sqrt(A0/Ω) falls as (r/(d_s + r))²
    (r = 0: a point source), so y_k = ln E_k + 2 ln(d_s + r) = a_k − c_k·d_T.
    spread_corrected_log_signal: (n, N) mean of y_k over the target per image (see
    :func:`spreading_log`); path_lengths: (n,) mean d_T in metres. With two distances
    this is c_k = [ln(E_k1/E_k2) − 2 ln((d_s2 + r)/(d_s1 + r))] / (d_T2 − d_T1).
    """
    fit = fit_lines(path_lengths, spread_corrected_log_signal, log_variance)
    return -fit.slope, fit.slope_std


def spreading_log(lamp_distance: ArrayLike, lamp_radius: float) -> NDArray[np.float64]:
    """2·ln(d_s + r): the log of the inverse lamp spreading factor, up to a constant."""
    return 2.0 * np.log(np.asarray(lamp_distance, dtype=np.float64) + lamp_radius)


def fit_noise_model(
    means: ArrayLike, noise_variances: ArrayLike, quantisation_step: float = 1.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read noise (DN rms) and shot gain (DN/e⁻) per channel from (mean, variance) pairs.

    Fits σ² − step²/12 = read² + gain·E by least squares over the n images, keeping both
    terms non-negative: a negative intercept means no measurable read noise, a negative
    slope no measurable shot noise.
    """
    mu = np.asarray(means, dtype=np.float64)
    s2 = np.asarray(noise_variances, dtype=np.float64) - quantisation_step**2 / 12.0
    read2 = np.zeros(mu.shape[1])
    gain = np.zeros(mu.shape[1])
    for k in range(mu.shape[1]):
        x, y = mu[:, k], s2[:, k]
        ok = np.isfinite(x) & np.isfinite(y)
        x, y = x[ok], y[ok]
        if x.size == 0:
            continue
        if x.size >= 2 and np.ptp(x) > 0:
            slope, intercept = np.polyfit(x, y, 1)
        else:
            slope, intercept = -1.0, -1.0
        if slope >= 0 and intercept >= 0:
            read2[k], gain[k] = intercept, slope
        elif np.dot(x, x) > 0 and np.dot(x, y) > 0 and (slope >= 0 or x.size == 1):
            read2[k], gain[k] = 0.0, np.dot(x, y) / np.dot(x, x)
        else:
            read2[k], gain[k] = max(float(np.mean(y)), 0.0), 0.0
    return np.sqrt(read2), gain


def backscatter_at_black_patch(
    black_mean: ArrayLike, surround_mean: ArrayLike, black_reflectance: ArrayLike, plate_reflectance: ArrayLike
) -> NDArray[np.float64]:
    """Backscatter (DN, dark-corrected) in front of a plate, per channel, from its black patch.

    The patch and the plate right around it see the same water and the same lamp light X:
    black = bs + ρ_black·X and surround = bs + ρ_plate·X, so X = (surround − black)/(ρ_plate − ρ_black)
    and bs = black − ρ_black·X. Clipped at 0.
    """
    black = np.asarray(black_mean, dtype=np.float64)
    surround = np.asarray(surround_mean, dtype=np.float64)
    rho_b = np.asarray(black_reflectance, dtype=np.float64)
    rho_p = np.asarray(plate_reflectance, dtype=np.float64)
    lit = (surround - black) / (rho_p - rho_b)
    return np.maximum(black - rho_b * lit, 0.0)


def noise_floor_from_black_patch(backscatter: ArrayLike, black_noise_variance: ArrayLike) -> NDArray[np.float64]:
    """Noise floor per channel (DN, dark-corrected): backscatter + FLOOR_SIGMAS·σ of the black patch,
    the largest over the images (n, N) (the farthest plate sees the most backscatter)."""
    bs = np.asarray(backscatter, dtype=np.float64)
    sigma = np.sqrt(np.nan_to_num(np.asarray(black_noise_variance, dtype=np.float64)))
    return np.max(bs + FLOOR_SIGMAS * sigma, axis=0)


def surrounding_box(box: Box, shape: tuple[int, int]) -> Box:
    """The box grown by half its size on every side, clipped to the image."""
    x, y, w, h = box
    x0, y0 = max(x - w // 2, 0), max(y - h // 2, 0)
    x1, y1 = min(x + w + w // 2, shape[1]), min(y + h + h // 2, shape[0])
    return x0, y0, x1 - x0, y1 - y0


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


def calibrate(frames: list[NDArray], distances_m: list[float], inputs: CalibrationInputs) -> CalibrationProfile:
    """Calibration profile from frames (H, W, N) of the target at camera distances (m, along the axis)."""
    n_img = len(frames)
    if n_img < 2:
        raise UserInputError(f"calibration needs images at two or more distances, got {n_img}")
    if len(distances_m) != n_img:
        raise UserInputError(f"got {n_img} images but {len(distances_m)} --distance values; give one distance per image, in order")
    if any(not (np.isfinite(d) and d > 0) for d in distances_m):
        raise UserInputError(f"distances must be positive metres, got {list(distances_m)}")
    names = inputs.image_names or [f"image {i + 1}" for i in range(n_img)]
    n_ch = len(inputs.channel_names)
    for frame, label in zip(frames, names):
        if frame.ndim != 3 or frame.shape[-1] != n_ch:
            got = frame.shape[-1] if frame.ndim == 3 else 1
            raise UserInputError(f"{label} has {got} channel(s) but calibration expects {n_ch} ({','.join(inputs.channel_names)})")
    shape = frames[0].shape[:2]
    for frame, label in zip(frames, names):
        if frame.shape[:2] != shape:
            raise UserInputError(f"{label} is {frame.shape[1]}×{frame.shape[0]} but the first image is {shape[1]}×{shape[0]}; use images of one size")
    dark = np.zeros(n_ch) if inputs.dark_level is None else np.asarray(inputs.dark_level, dtype=np.float64)
    lamp = np.asarray(inputs.lamp_position_m, dtype=np.float64)
    rays = pixel_rays(inputs.intrinsics, *shape) if inputs.intrinsics is not None else None

    target_stats, black_stats, black_surround, backscatters = [], [], [], []
    log_signal, log_spread_corrected, path_lengths = [], [], []
    for i, (frame, distance, label) in enumerate(zip(frames, distances_m, names)):
        box = inputs.target_boxes[i] if inputs.target_boxes else inputs.target_box
        target = box_mask(shape, box, f"target region of {label}")
        backscatter = np.zeros(n_ch)
        if inputs.black_boxes:
            black = box_mask(shape, inputs.black_boxes[i], f"black patch region of {label}")
            target &= ~black
            black_stats.append(region_statistics(frame, black, dark))
            surround = box_mask(shape, surrounding_box(inputs.black_boxes[i], shape), "") & target
            if not surround.any():
                raise UserInputError(f"the black patch of {label} is not surrounded by target pixels; check the regions")
            black_surround.append(region_statistics(frame, surround, dark).mean)
            if inputs.black_reflectance is not None:
                backscatter = backscatter_at_black_patch(black_stats[-1].mean, black_surround[-1],
                                                         inputs.black_reflectance, inputs.target_reflectance)
        backscatters.append(backscatter)
        clipped = np.any(np.asarray(frame) >= inputs.saturation_level, axis=-1)
        frac = (np.asarray(frame)[target] >= inputs.saturation_level).mean(axis=0)
        if frac.max() > MAX_SATURATED_FRACTION:
            k = int(frac.argmax())
            raise UserInputError(
                f"{frac[k]:.0%} of the target region of {label} is saturated in channel {inputs.channel_names[k]}; "
                "lower the exposure, gain or lamp intensity and capture it again"
            )
        usable = target & ~clipped
        stats = region_statistics(frame, usable, dark)
        if np.any(stats.mean <= 0):
            k = int(np.argmin(stats.mean))
            raise UserInputError(
                f"the target region of {label} has no signal in channel {inputs.channel_names[k]} after dark correction; "
                "check the lamp, the exposure and that the target is in the region"
            )
        target_stats.append(stats)
        # The plate's own light only: the water in front of it adds the same backscatter to
        # plate and patch (taken as uniform over the plate).
        ln_e, pixels = smoothed_log_signal(frame, usable, dark + backscatter)
        # Path length per pixel: plate square to the axis at `distance`.
        u = rays[pixels] if rays is not None else np.array([[0.0, 0.0, 1.0]])
        dc = plane_camera_range(distance, u)
        ds = np.linalg.norm(dc[:, None] * u - lamp, axis=-1)
        log_signal.append(ln_e.mean(axis=0))
        path_lengths.append(float(np.mean(dc + ds)))
        if inputs.lamp_radius_m is not None:
            spread = spreading_log(ds, inputs.lamp_radius_m)
            log_spread_corrected.append((ln_e + spread[:, None]).mean(axis=0))

    means = np.array([s.mean for s in target_stats])
    noise = np.array([s.noise_variance for s in target_stats])
    counts = np.array([s.count for s in target_stats], dtype=np.float64)[:, None]
    ref = inputs.reference
    # Variance of a region's mean ln E_k from pixel noise.
    log_var = noise / (counts * means**2)
    fit = fit_attenuation_differences(np.array(log_signal), path_lengths, ref, log_var)

    # b_k was measured on the target; store the target's reflectance so a surface of another
    # hue can be corrected later (DESIGN.md §3).
    read_noise, shot_gain = fit_noise_model(means, noise, inputs.quantisation_step)
    backscatter_samples = None
    if inputs.black_boxes and inputs.black_reflectance is not None:
        black_var = np.array([b.noise_variance for b in black_stats])
        floor = noise_floor_from_black_patch(backscatters, black_var)
        centres = [(x + w / 2 - 0.5, y + h / 2 - 0.5) for x, y, w, h in inputs.black_boxes]
        backscatter_samples = BackscatterSamples(
            distances_m=[float(d) for d in distances_m],
            patch_pixels=centres,
            levels={inputs.channel_names[k]: [float(b[k]) for b in backscatters] for k in range(n_ch)},
            noise_sigma={inputs.channel_names[k]: float(np.sqrt(np.nanmax(black_var[:, k]))) for k in range(n_ch)},
        )
    else:
        floor = np.zeros(n_ch)
    absolute: tuple[NDArray, NDArray] | None = None
    if inputs.lamp_radius_m is not None:
        absolute = absolute_attenuation(np.array(log_spread_corrected), path_lengths, log_var)

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
            read_noise=float(read_noise[k]),
            shot_gain=float(shot_gain[k]),
            noise_floor=float(floor[k]),
        )
        for k in range(n_ch)
    ]
    residuals = {inputs.channel_names[k]: [float(r) for r in fit.residuals[:, k]] for k in range(n_ch)}
    provenance = Provenance(
        created=now_iso(),
        method=fit.method,
        distances_m=[float(d) for d in distances_m],
        path_lengths_m=path_lengths,
        images=list(names),
        target=inputs.target_description,
        roi=list(inputs.target_box) if inputs.target_box else None,
        residuals=residuals,
        rms_residual=float(np.sqrt(np.mean(fit.residuals**2))),
    )
    intr = inputs.intrinsics
    return CalibrationProfile(
        name=inputs.name,
        reference_channel=inputs.channel_names[ref],
        channels=channels,
        saturation_level=float(inputs.saturation_level),
        quantisation_step=float(inputs.quantisation_step),
        lamp_position_m=tuple(float(v) for v in lamp),
        lamp_radius_m=inputs.lamp_radius_m,
        intrinsics=None if intr is None else {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        backscatter=backscatter_samples,
        provenance=provenance,
    )
