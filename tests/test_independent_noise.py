"""The camera noise model against its formula written out: σ² = read² + gain·max(E, 0) + step²/12."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.optics import NoiseModel, signal_variance


@pytest.mark.parametrize("e, read, gain, step", [
    (0.0, 0.0, 0.0, 1.0), (100.0, 3.0, 0.0, 1.0), (100.0, 0.0, 0.25, 0.0), (2500.0, 12.0, 0.5, 2.0), (7.0, 0.5, 2.0, 4.0),
])
def test_variance_is_read_squared_plus_shot_plus_quantisation(e, read, gain, step):
    expected = read * read + gain * e + step * step / 12.0
    assert signal_variance(e, read, gain, step) == pytest.approx(expected, rel=1e-15)
    assert NoiseModel(read, gain, step).variance(e) == pytest.approx(expected, rel=1e-15)


def test_read_noise_is_squared_not_linear():
    # 12 DN rms of read noise is 144 DN² of variance; nothing else here.
    assert signal_variance(0.0, 12.0, 0.0, 0.0) == 144.0
    assert signal_variance(0.0, 0.5, 0.0, 0.0) == 0.25


def test_default_step_is_one_code_and_negative_signal_adds_no_shot_noise():
    assert signal_variance(10.0, 2.0, 0.5) == pytest.approx(4.0 + 5.0 + 1.0 / 12.0)
    assert NoiseModel(2.0, 0.5).variance(10.0) == pytest.approx(4.0 + 5.0 + 1.0 / 12.0)
    assert signal_variance(-50.0, 2.0, 0.5, 0.0) == pytest.approx(4.0)  # below dark: clipped at 0


def test_per_channel_parameters_broadcast_on_the_last_axis():
    e = np.array([[100.0, 200.0, 300.0], [0.0, 10.0, -5.0]])
    read, gain, step = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 4.0])
    got = signal_variance(e, read, gain, step)
    for i in range(2):
        for k in range(3):
            assert got[i, k] == pytest.approx(read[k] ** 2 + gain[k] * max(e[i, k], 0.0) + step[k] ** 2 / 12.0)
    assert got.dtype == np.float64


def test_noise_model_is_an_immutable_value():
    import dataclasses

    model = NoiseModel(2.0, 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.read_noise = 3.0  # shared between channels and threads: never changed in place
    assert model == NoiseModel(2.0, 0.5, 1.0) and hash(model) == hash(NoiseModel(2.0, 0.5, 1.0))
