"""The compiled frame estimator equals the readable numpy reference, pixel by pixel."""

import numpy as np
import pytest

from tests.synthetic import make_profile
from uwcam.fileio import UserInputError
from uwcam.optics import (
    ChannelState,
    Intrinsics,
    Reason,
    camera_range_derivative,
    camera_range_from_path_length,
    channel_states,
    fused_path_length,
    pixel_reasons,
    pixel_rays,
    signal_variance,
)
from uwcam.ranging.estimator import RangeEstimator


def reference(profile, frame, backscatter=None, bounds=(0.0, np.inf), active=None):
    """Compose the pure optics functions the long way round."""
    dark = profile.array("dark_level")
    e = frame.astype(np.float64) - dark
    states = channel_states(frame, e, profile.array("noise_floor"), profile.saturation_level, backscatter)
    if active is not None:
        states = states.copy()
        states[..., ~active] = 255  # neither usable nor counted
    var = signal_variance(e, profile.array("read_noise"), profile.array("shot_gain"), profile.quantisation_step)
    usable = states == ChannelState.USABLE
    path, path_var = fused_path_length(e, profile.array("attenuation_difference"), profile.array("log_constant"), var, usable)
    lamp = np.array(profile.lamp_position_m)
    intr = profile.camera_intrinsics()
    rays = pixel_rays(intr, *frame.shape[:2]) if intr is not None else None
    reasons = pixel_reasons(states, path, bounds[0], bounds[1])
    reachable = path > np.linalg.norm(lamp)
    reasons[(reasons == Reason.VALID) & ~reachable] = Reason.PATH_OUT_OF_BOUNDS
    valid = reasons == Reason.VALID
    rng = np.where(valid, camera_range_from_path_length(path, lamp, rays), np.nan)
    rvar = np.where(valid, camera_range_derivative(path, lamp, rays) ** 2 * path_var, np.nan)
    return rng, rvar, reasons


def random_frame(rng, shape, n, dtype, saturation):
    if dtype in (np.uint8, np.uint16):
        frame = rng.integers(0, np.iinfo(dtype).max + 1, size=(*shape, n))
    elif np.issubdtype(dtype, np.integer):
        frame = rng.integers(-5, 4000, size=(*shape, n))
    else:
        frame = rng.uniform(-5, 4000, (*shape, n))
    frame = frame.astype(dtype)
    frame[rng.random(shape) < 0.05, :3] = saturation  # some pixels clipped in most channels
    return frame


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64, np.int32])
@pytest.mark.parametrize("geometry", ["equidistant", "axis", "rays"])
def test_estimator_matches_reference(dtype, geometry):
    rng = np.random.default_rng(7)
    n = 4
    shape = (37, 53)
    sat = {np.uint8: 250, np.uint16: 60000}.get(dtype, 3900.0)
    lamp = (0.0, 0.0, 0.0) if geometry == "equidistant" else (0.25, -0.1, 0.05)
    intr = Intrinsics.from_fov(shape[1], shape[0], 70) if geometry == "rays" else None
    floor = np.array([3.0, 5.0, 2.0, 8.0]) * (1 if dtype == np.uint8 else 40)
    profile = make_profile(
        [0.46, 0.11, 0.06, 0.3], [0.2, -0.1, 0.4, 0.0], names=["R", "G", "B", "N"],
        read_noise=[2.0, 3.0, 2.5, 1.0], shot_gain=[0.5, 0.3, 0.2, 1.0], noise_floor=floor,
        dark_level=[1.0, 2.0, 0.0, 3.0], saturation_level=sat, lamp=lamp, intrinsics=intr,
        quantisation_step=0.0 if np.issubdtype(dtype, np.floating) else 1.0,
    )
    frame = random_frame(rng, shape, n, dtype, sat)
    backscatter = floor * 1.5
    bounds = (0.5, 40.0)
    est = RangeEstimator(profile, backscatter_level=backscatter, path_length_bounds=bounds)
    got = est(frame)
    want = reference(profile, frame, backscatter, bounds)
    np.testing.assert_array_equal(got.reasons, want[2])
    assert set(np.unique(got.reasons)) >= {Reason.VALID, Reason.SATURATED, Reason.PATH_OUT_OF_BOUNDS}
    # Lookup tables hold ln E in float32: ~1e-6 absolute in y, divided by Δc.
    np.testing.assert_allclose(got.range, want[0], rtol=2e-5, atol=2e-4, equal_nan=True)
    np.testing.assert_allclose(got.variance, want[1], rtol=2e-4, equal_nan=True)
    assert got.range.dtype == np.float32 and got.variance.dtype == np.float32 and got.reasons.dtype == np.uint8


def test_pair_uses_only_its_channels():
    rng = np.random.default_rng(3)
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5], read_noise=2.0, shot_gain=0.2)
    frame = rng.integers(100, 20000, size=(20, 30, 3)).astype(np.uint16)
    frame[0, 0, 0] = 65535  # R saturated: irrelevant to the G,B pair
    got = RangeEstimator(profile, pair=("G", "B"))(frame)
    want = reference(profile, frame, active=np.array([False, True, True]))
    np.testing.assert_allclose(got.range, want[0], rtol=2e-5, atol=2e-4, equal_nan=True)
    assert got.reasons[0, 0] == Reason.VALID


def test_strided_and_padded_views_match_contiguous_copies():
    rng = np.random.default_rng(5)
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5], read_noise=2.0, shot_gain=0.2)
    padded = rng.integers(50, 40000, size=(40, 64, 4)).astype(np.uint16)  # e.g. RGBA with row padding
    view = padded[3:35, 5:60:2, :3]
    est = RangeEstimator(profile)
    a, b = est(view), est(np.ascontiguousarray(view))
    np.testing.assert_array_equal(a.range, b.range)
    np.testing.assert_array_equal(a.reasons, b.reasons)


def test_surface_reflectance_shifts_constants_by_hue_only():
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5])
    grey = RangeEstimator(profile, surface_reflectance=[0.4, 0.4, 0.4])
    plain = RangeEstimator(profile)
    np.testing.assert_allclose(grey.log_constant - grey.log_constant[0], plain.log_constant - plain.log_constant[0])
    reddish = RangeEstimator(profile, surface_reflectance=[0.6, 0.3, 0.3])
    assert reddish.log_constant[0] - reddish.log_constant[1] == pytest.approx(
        plain.log_constant[0] - plain.log_constant[1] + np.log(2.0))


def test_output_arrays_are_reused():
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5])
    est = RangeEstimator(profile)
    frame = np.full((8, 9, 3), 1000, np.uint16)
    first = est(frame)
    second = est(frame, out=first)
    assert second.range is first.range


def test_bad_frames_and_options_are_explained():
    profile = make_profile([0.46, 0.11, 0.06], [0.0, 0.3, 0.5])
    est = RangeEstimator(profile)
    with pytest.raises(UserInputError, match=r"the image has 4 channel\(s\) but the calibration profile has 3 \(R,G,B\)"):
        est(np.zeros((4, 4, 4), np.uint16))
    with pytest.raises(UserInputError, match="--pair needs two different channel names from R,G,B"):
        RangeEstimator(profile, pair=("R", "X"))
    with pytest.raises(UserInputError, match="surface reflectance needs 3 positive values"):
        RangeEstimator(profile, surface_reflectance=[0.1, 0.2])
