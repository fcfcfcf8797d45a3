"""Ranging images offline (``uwcam range``), through the frame loop's own path.

The frame loop, ``uwcam reprocess`` and this module all range through
:func:`uwcam.ranging.estimator.range_frame` with the same pieces: a :class:`~uwcam.ranging.estimator.RangeEstimator`,
the backscatter compensation of :class:`~uwcam.water.frame_compensator.BackscatterCompensator` (with its
model's uncertainty) when asked for, and the open water's light that every pixel is judged against
(:mod:`uwcam.water.water_light`). So one frame with one profile and the same settings gives the same
range, variance and reasons, bit for bit, whichever way it is ranged.

Several frames of one static scene are fused before ranging: their per-pixel mean, whose noise is
that of the noise model with the temporal part (read, shot, quantisation) divided by the number of
frames and the fixed pattern (each pixel's own response, the same in every frame) not.

The frames' exposure (:class:`Exposure`) is used as the frame loop uses each frame's: the estimator
ranges at it (:meth:`~uwcam.ranging.estimator.RangeEstimator.set_exposure`) and the modelled
backscatter is scaled to it (:func:`uwcam.water.light_scale.light_scale`); where it cannot be
related to the light the backscatter model came from, the frames are refused (:func:`relate_exposures`).
Several open-water frames are taken as the daemon takes its capture (:func:`open_water_mean`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.noise import signal_variance, temporal_variance
from uwcam.calibration.profile import CalibrationProfile
from uwcam.ranging.result import RangeResult
from uwcam.ranging.estimator import DEFAULT_SMOOTHING_TARGET, RangeEstimator, range_frame


@dataclass(frozen=True)
class Exposure:
    """How a set of frames was exposed, per channel, as a frame says it
    (:meth:`uwcam.drivers.base.Frame.exposures`): exposure_us (µs, (N,)) and gain_db (dB, (N,)),
    each None where not stated."""

    exposure_us: NDArray | None = None
    gain_db: NDArray | None = None

    def light_gathered(self) -> NDArray[np.float64] | None:
        """Per channel, exposure × linear gain (µs), as :meth:`uwcam.drivers.base.Frame.light_gathered`:
        None without an exposure time (a gain not stated counts as 0 dB)."""
        if self.exposure_us is None:
            return None
        gain = 0.0 if self.gain_db is None else self.gain_db
        return np.asarray(self.exposure_us, dtype=np.float64) * 10.0 ** (np.asarray(gain, dtype=np.float64) / 20.0)


def _values(values: NDArray) -> str:
    return ",".join(f"{v:g}" for v in values)


def relate_exposures(profile: CalibrationProfile, exposure: Exposure, open_water: Exposure | None) -> None:
    """UserInputError unless the backscatter model can be scaled to frames exposed ``exposure``.

    The model is in the counts of the light it came from: the open-water frames (exposed
    ``open_water``) or, without them (None), the calibration's black-patch measurements (the
    profile's recorded exposure). Each of exposure time and gain must be stated for the frames
    and for that light alike, or for neither (then both are taken as alike, as before exposures
    were recorded); and the gain only with the time (the light gathered is exposure × gain)."""
    for exp, prefix in ((exposure, ""), (open_water, "open-water-")):
        if exp is not None and exp.gain_db is not None and exp.exposure_us is None:
            raise UserInputError(f"--{prefix}gain-db needs --{prefix}exposure-us: the backscatter is scaled by the "
                                 "light gathered, exposure × gain")
    if open_water is not None:
        for flag, ours, theirs in (("exposure-us", exposure.exposure_us, open_water.exposure_us),
                                   ("gain-db", exposure.gain_db, open_water.gain_db)):
            if (ours is None) != (theirs is None):
                given, missing = (f"--{flag}", f"--open-water-{flag}") if theirs is None else (f"--open-water-{flag}", f"--{flag}")
                raise UserInputError(f"{given} is given but not {missing}: the open-water frames' backscatter is scaled "
                                     "by the frames' exposure over theirs; give both (the same where they were taken "
                                     "alike) or neither")
        return
    cal_t, cal_g = profile.calibration_exposure()
    for flag, what, ours, cal in (("exposure-us", "exposure (µs)", exposure.exposure_us, cal_t),
                                  ("gain-db", "gain (dB)", exposure.gain_db, cal_g)):
        if ours is not None and cal is None:
            raise UserInputError(f"--{flag} is given but the profile records no calibration {what}, and without "
                                 "--open-water the backscatter subtracted is the calibration's, in its counts; give "
                                 f"--open-water frames of this water (with --open-water-{flag}) or a profile "
                                 f"calibrated with --{flag}")
        if ours is None and cal is not None:
            raise UserInputError(f"the profile was calibrated at {what} {_values(cal)}, and without --open-water the "
                                 f"backscatter subtracted is in those counts; give the frames' --{flag}")


def check_alike(frames: Sequence[NDArray], label: str, advice: str) -> None:
    """UserInputError unless every frame has the first's shape and pixel type, naming the first that
    differs as ``label`` k (counted from 1) and ending with ``advice``."""
    def size(f: NDArray) -> str:
        return f"{f.shape[1]}×{f.shape[0]}×{f.shape[2] if f.ndim == 3 else 1} {f.dtype}"

    first = frames[0]
    for k, f in enumerate(frames[1:], start=2):
        if f.shape != first.shape or f.dtype != first.dtype:
            raise UserInputError(f"{label} {k} is {size(f)} but {label} 1 is {size(first)}; {advice}")


def open_water_mean(profile: CalibrationProfile, frames: Sequence[NDArray]) -> NDArray[np.float32]:
    """The open-water frame the daemon keeps of a capture of K lamp-lit frames (H, W, N) raw, taken
    at one exposure: their mean, summed in float32 in order as
    :meth:`uwcam.runtime.stages.compensation.CompensationStage._take_open_water` sums them (a gamma
    camera's codes linearised first, as the frame loop does every frame). Ranged with
    ``open_water_frames=K``, each pixel's response is estimated from it with the noise model's
    noise over K (:meth:`uwcam.water.backscatter.BackscatterModel.from_profile`), as in the daemon."""
    check_alike(frames, "open-water image", "take them with one camera and its settings")
    curve = profile.response_curve()
    total = None
    for f in frames:
        light = (curve.linearise(f) if curve is not None and np.issubdtype(f.dtype, np.integer) else f).astype(np.float32)
        total = light if total is None else total + light
    return total / len(frames)


def fuse_frames(estimator: RangeEstimator, frames: Sequence[NDArray]) -> tuple[NDArray, NDArray | None]:
    """(the frame to range, samples) for K frames (H, W, N) of one static scene: one frame as it is
    (samples None); several, their mean (float32) and, per value, the number of single-pixel
    noises its variance is equal to: σ²(E) / (σ_t²(E)/K + (f·E)²), σ_t² the temporal variance and
    f the fixed pattern of the noise model (see :meth:`RangeEstimator.channel_terms`'s ``samples``)."""
    if len(frames) == 0:
        raise UserInputError("give at least one image to range")
    check_alike(frames, "image", "fuse only frames of one camera and scene")
    first = frames[0]
    if len(frames) == 1:
        return first, None
    k = len(frames)
    response = getattr(estimator, "response", None)
    if response is not None and np.issubdtype(first.dtype, np.integer):
        frames = [response.linearise(f) for f in frames]  # a gamma camera: average light, not codes
    mean = np.mean(np.stack(frames).astype(np.float64), axis=0)
    # A saturated mean stays at or above the level: the estimator marks it as it would one frame.
    return mean.astype(np.float32), samples_of_mean(estimator, mean - estimator.dark, 1.0 / k)


def samples_of_mean(estimator: RangeEstimator, signal: NDArray, weight_squares: float | NDArray) -> NDArray[np.float32]:
    """Per value, the number of single-pixel noises the variance of a weighted mean of frames equals:
    σ²(E) / (σ_t²(E)·Σw² + (f·E)²). signal: (H, W, N) the mean's dark-corrected signal E (DN);
    weight_squares: Σw² of the frames' weights (they sum to 1), 1/K for K equal frames, a scalar or
    (H, W, 1); σ_t² the temporal part of the noise model (read, shot, quantisation), which averages
    down, f its fixed pattern, which is the same in every frame and does not."""
    q = estimator.profile.quantisation_step
    total = signal_variance(signal, estimator.read_noise, estimator.shot_gain, q, estimator.fixed_pattern)
    fused = (temporal_variance(signal, estimator.read_noise, estimator.shot_gain, q) * weight_squares
             + (estimator.fixed_pattern * np.maximum(signal, 0.0)) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        samples = np.where(fused > 0, total / fused, 1.0 / np.asarray(weight_squares, np.float64))
    return samples.astype(np.float32)


def range_images(
    profile: CalibrationProfile,
    frames: Sequence[NDArray],
    *,
    pair: tuple[str, str] | None = None,
    surface_reflectance: Sequence[float] | None = None,
    path_length_bounds: tuple[float, float] = (0.0, np.inf),
    smoothing: str = "none",
    smoothing_target: float = DEFAULT_SMOOTHING_TARGET,
    compensate: bool = False,
    iterations: int = 2,
    open_water: NDArray | None = None,
    open_water_frames: int = 1,
    exposure: Exposure | None = None,
    open_water_exposure: Exposure = Exposure(),
) -> RangeResult:
    """Range, variance and reasons of a static scene seen in ``frames`` (K ≥ 1 raw frames (H, W, N)).

    compensate: subtract modelled backscatter (``iterations`` passes, as the frame loop's
    ``backscatter.iterations``); it is subtracted all the same wherever the profile has backscatter
    measurements (:func:`uwcam.water.frame_compensator.compensation_iterations`: a range with the water's
    light left in reads short), so the flag only refuses a profile without them; open_water: a lamp-lit frame of open water (H, W, N) raw, or several
    (K, H, W, N), for the backscatter's pattern and the per-pixel open-water light. Whenever the
    profile has backscatter measurements, a pixel not clearly above the open water's light has no
    range (reason 3). smoothing: "none", "mean" or "median", of the range map (as the loop's
    smoothing stage "after"), or "adaptive", windows reaching ``smoothing_target`` (σ/range) as the
    loop's ``processing.smoothing_target``. open_water_frames: how many frames the one open-water
    frame (H, W, N) is the mean of (:func:`open_water_mean`: the daemon's capture).
    exposure: the frames' own, as stated (the estimator ranges at it and the backscatter is scaled to
    it); UserInputError where the backscatter subtracted cannot be related to it
    (:func:`relate_exposures`); None: the calibration's, unchecked (as
    :meth:`~uwcam.ranging.estimator.RangeEstimator.set_exposure`'s None). open_water_exposure: the
    open-water frames'."""
    from uwcam.water.frame_compensator import BackscatterCompensator, compensation, compensation_iterations
    from uwcam.water.light_scale import light_scale

    options = dict(pair=pair, surface_reflectance=surface_reflectance, path_length_bounds=path_length_bounds)
    estimator = RangeEstimator(profile, **options)
    try:  # as the frame loop, every frame
        estimator.set_exposure(*((None, None) if exposure is None else (exposure.exposure_us, exposure.gain_db)))
    except ValueError as exc:
        raise UserInputError(f"the frames' exposure: {exc}") from None
    frame, samples = fuse_frames(estimator, list(frames))
    if frame.ndim != 3 or frame.shape[-1] != len(profile.channels):
        got = frame.shape[-1] if frame.ndim == 3 else 1
        raise UserInputError(f"the image has {got} channel(s) but the calibration profile has {len(profile.channels)} "
                             f"({','.join(profile.channel_names)}); use a profile made with this camera")
    if open_water is not None and open_water.shape[-3:] != frame.shape:
        raise UserInputError(f"the open-water frame is {open_water.shape[-2]}×{open_water.shape[-3]}×{open_water.shape[-1]} "
                             f"but the image is {frame.shape[1]}×{frame.shape[0]}×{frame.shape[2]}; "
                             "take it with the same camera and settings")
    shape = frame.shape[:2]
    transform, water = None, None
    passes = compensation_iterations(iterations if compensate else None, profile)
    if compensate or passes is not None:
        if exposure is not None:
            relate_exposures(profile, exposure, None if open_water is None else open_water_exposure)
        comp = BackscatterCompensator(profile, shape, passes or iterations, open_water,
                                      open_water_frames=open_water_frames, **options)
        # The modelled backscatter is in the counts of the light it came from: scaled to the frames' exposure.
        scale = light_scale(profile, estimator, None if exposure is None else exposure.light_gathered(), comp.open_water,
                            open_water_exposure.light_gathered())
        transform, water = compensation(comp, estimator, None, scale), comp.water
    return range_frame(estimator, frame, smoothing, "after", None, (), transform, water, None, samples,
                       smoothing_target)
