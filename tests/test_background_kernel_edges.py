"""The compiled kernel for frames with a background, at the edges of its per-value terms: a value
exactly at the noise floor, at the open-water level or at 3σ; a noise model of 0 or below 1 DN²;
signals below 1 DN; a background below 0 (an ambient frame's dark-corrected noise).

The reference is the estimator's numpy terms (``channel_terms`` → ``pack_pairs`` → the numpy
fusion), which tests/test_backscatter_terms.py and tests/test_estimator.py check against the
noise model written out; each case also asserts the state that makes it an edge.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.synthetic import RGB_ATTENUATION, make_profile
from uwcam.optics import ChannelState, Reason, kernels
from uwcam.ranging.estimator import RangeEstimator

B = np.log([0.7, 1.0, 0.8])
D = 3.0  # path length of the surface (m); the lamp is at the camera


def surface(scale):
    """Per-channel light (DN) of a surface at path length D: scale·exp(b_k − c_k·D)."""
    return scale * np.exp(B - RGB_ATTENUATION * D)


# name: (noise model, estimator options, signal v = raw − dark − background (W, 3), background,
#        the value on the edge, its state). raw = v + background + dark.
CASES = {
    # G exactly at the floor of 20 DN: below it, so R alone is usable (the second pixel: G 1 DN above).
    "at the floor": (dict(read_noise=1.0, dark_level=10.0, noise_floor=20.0), {},
                     [[500.0, 20.0, -1.0], [500.0, 21.0, -1.0]], 0.0, (0, 0, 1), ChannelState.BELOW_NOISE_FLOOR),
    # G exactly 3σ above a background of 10 DN (σ = 2 DN): not usable, backscatter only.
    "at 3 sigma": (dict(read_noise=2.0, quantisation_step=0.0), {},
                   [[500.0, 6.0, 1.0], [500.0, 6.5, 1.0]], 10.0, (0, 0, 1), ChannelState.BACKSCATTER_ONLY),
    # G exactly at the open-water level: backscatter only.
    "at the open-water level": (dict(read_noise=1.0, quantisation_step=0.0), dict(backscatter_level=[50.0, 50.0, 50.0]),
                                [[500.0, 50.0, -1.0], [500.0, 50.5, -1.0]], 0.0, (0, 0, 1), ChannelState.BACKSCATTER_ONLY),
    # No noise model at all: σ² = 0 counts as 1 DN².
    "no noise model": (dict(quantisation_step=0.0), {}, [surface(400.0)], 0.0, (0, 0, 2), ChannelState.USABLE),
    # σ² = 0.25 DN²: used as it is.
    "noise below 1 DN": (dict(read_noise=0.5, quantisation_step=0.0), {}, [surface(400.0)], 0.0,
                         (0, 0, 2), ChannelState.USABLE),
    # Signals of a fraction of a DN with a noise model to match: shot noise of a total below 1, ln E < 0.
    "signals below 1 DN": (dict(read_noise=0.01, shot_gain=0.01, quantisation_step=0.0), {},
                           [surface(1.2)], 0.0, (0, 0, 0), ChannelState.USABLE),
    # R: 0.5 DN under the dark level with a background of −3 DN, so v = 2.5 DN: the shot noise
    # of a negative total light is 0 (σ = 0.1 DN), not negative.
    "background below 0": (dict(read_noise=0.1, shot_gain=1.0, dark_level=10.0, quantisation_step=0.0), {},
                           [surface(2.5 / surface(1.0)[0])], -3.0, (0, 0, 0), ChannelState.USABLE),
}


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled background kernel")
@pytest.mark.parametrize("case", list(CASES))
def test_the_compiled_background_kernel_equals_the_numpy_terms_at_the_edges(case):
    noise, options, signal, background, edge, state = CASES[case]
    profile = make_profile(RGB_ATTENUATION, B, **noise)
    est = RangeEstimator(profile, calibration_variance=False, **options)
    v = np.asarray(signal, np.float64)[None]
    bg = np.full(v.shape, background, np.float32)
    raw = v + bg + profile.array("dark_level")
    y, weight, states = est.channel_terms(raw, bg.astype(np.float64))
    assert states[edge] == state  # the premise: this value sits on the edge
    got = est(raw, background=bg)
    pairs = kernels.pack_pairs(y, weight, states, ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
    h, w = raw.shape[:2]
    ref = [np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.uint8)]
    kernels.fuse_arrays_numpy(pairs, est._c, (0.0,) * 3, est._cv, est._geo, est.bounds, *ref)
    np.testing.assert_array_equal(got.reasons, ref[2])
    np.testing.assert_allclose(got.range, ref[0], rtol=2e-6, equal_nan=True)
    np.testing.assert_allclose(got.variance, ref[1], rtol=2e-5, equal_nan=True)
    if state == ChannelState.USABLE:
        assert ref[2][0, 0] == Reason.VALID


@pytest.mark.skipif(kernels.fuse_background is None, reason="numba is not installed: no compiled background kernel")
def test_the_compiled_background_kernel_takes_the_noise_of_means_as_the_numpy_terms_do():
    """Values that are means of several (smoothing before the transform, temporal fusion): their
    noise variance is the single value's over their count, in the kernel as in the numpy terms."""
    profile = make_profile(RGB_ATTENUATION, B, read_noise=2.0, shot_gain=0.5, quantisation_step=0.0)
    est = RangeEstimator(profile, calibration_variance=False)
    rng = np.random.default_rng(3)
    v = surface(400.0) * rng.uniform(0.8, 1.2, (4, 5, 3))
    bg = np.full(v.shape, 5.0, np.float32)
    raw = (v + bg + profile.array("dark_level")).astype(np.float32)
    samples = rng.integers(2, 10, v.shape).astype(np.float32)
    y, weight, states = est.channel_terms(raw, bg.astype(np.float64), samples)
    got = est(raw, background=bg, samples=samples)
    pairs = kernels.pack_pairs(y, weight, states, ChannelState.SATURATED, ChannelState.BACKSCATTER_ONLY)
    ref = [np.empty(v.shape[:2], np.float32), np.empty(v.shape[:2], np.float32), np.empty(v.shape[:2], np.uint8)]
    kernels.fuse_arrays_numpy(pairs, est._c, (0.0,) * 3, est._cv, est._geo, est.bounds, *ref)
    assert (ref[2] == Reason.VALID).all()
    np.testing.assert_allclose(got.range, ref[0], rtol=2e-6)
    np.testing.assert_allclose(got.variance, ref[1], rtol=2e-5)
    single = est(raw, background=bg)  # the same values taken as single pixels: noisier
    assert (got.variance < single.variance).all()
