"""The noise model's terms one at a time, from its definition (docs/physics.md):
σ² = read² + shot_gain·E + (fixed_pattern·E)² + step²/12 with E clipped at 0; the temporal
part leaves out the fixed pattern; the quantisation step is 1 DN unless given."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.optics.noise import NoiseModel, signal_variance, temporal_variance


def test_the_fixed_pattern_adds_its_square_and_only_to_the_total():
    e = np.array([0.0, 1000.0, 4000.0])
    read, gain, step, fp = 3.0, 0.5, 1.0, 0.01
    temporal = read**2 + gain * e + step**2 / 12
    np.testing.assert_allclose(signal_variance(e, read, gain, step, fp), temporal + (fp * e) ** 2, rtol=1e-12)
    np.testing.assert_allclose(temporal_variance(e, read, gain, step), temporal, rtol=1e-12)
    model = NoiseModel(read, gain, step, fp)
    assert model.variance(1000.0) == pytest.approx(9.0 + 500.0 + 1 / 12 + 100.0, rel=1e-12)
    assert model.temporal(1000.0) == pytest.approx(9.0 + 500.0 + 1 / 12, rel=1e-12)


def test_a_negative_signal_counts_as_no_light():
    """Dark-corrected values below 0 (noise around the dark level) carry no shot noise or fixed
    pattern: σ² is the read and quantisation noise alone."""
    e = np.array([-0.5, -5.0, -300.0])
    floor = 2.0**2 + 1.0 / 12
    np.testing.assert_allclose(signal_variance(e, 2.0, 0.8, 1.0, 0.02), floor, rtol=1e-12)
    np.testing.assert_allclose(temporal_variance(e, 2.0, 0.8, 1.0), floor, rtol=1e-12)


def test_the_quantisation_step_is_one_dn_unless_given():
    assert temporal_variance(100.0, 2.0, 0.5) == pytest.approx(4.0 + 50.0 + 1 / 12, rel=1e-12)
    assert signal_variance(100.0, 2.0, 0.5) == pytest.approx(4.0 + 50.0 + 1 / 12, rel=1e-12)
