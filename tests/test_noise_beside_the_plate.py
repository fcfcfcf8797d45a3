"""The noise points of the light beside the plate (``dim_noise_points``) and how the noise fit
uses them: which pixels they hold, how many levels, when there are too few, and that they pin
read noise and shot gain while the fixed pattern comes from the plate alone.

Expected values are written out from the layouts below (rows or columns of one brightness each),
not computed by the code under test."""

import numpy as np
import pytest

from uwcam.calibration.noise_fit import NoisePoint, dim_noise_points, fit_noise, noise_point

CHANNELS = np.array([1.0, 2.0, 3.0])


def frames_of(brightness: np.ndarray) -> list[np.ndarray]:
    """Two frames whose mean is ``brightness`` times each channel's factor (±1 DN frame to frame)."""
    base = brightness[..., None] * CHANNELS
    return [base + 1.0, base - 1.0]


def test_two_levels_of_the_dim_light_beside_the_plate_and_nothing_else():
    # Rows, each of one brightness (the channels' sum); 40 columns, so 38 triples per row.
    # Only the rows at 100, 200, 300 and 400 are dim light beside the plate: the others are the
    # plate's or patch's region (150), clipped (350), brighter than the plate's floor (1000), or
    # exactly at it (500).
    values = [150, 100, 350, 200, 1000, 300, 500, 400]
    brightness = np.repeat(np.array(values, float)[:, None], 40, axis=1)
    occupied = np.zeros_like(brightness, bool)
    occupied[0] = True
    clipped = np.zeros_like(brightness, bool)
    clipped[2] = True
    points = dim_noise_points(frames_of(brightness), brightness, occupied, clipped, dark_level=0.0,
                              plate_floor=500.0, distance=1.5, margin=0)
    # 4 × 40 dim pixels; their median is 250: level 1 holds 100 and 200, level 2 300 and 400.
    assert [label for label, _ in points] == ["beside the plate 1.5 m, level 1", "beside the plate 1.5 m, level 2"]
    (_, low), (_, high) = points
    np.testing.assert_allclose(low.mean, 150.0 * CHANNELS, rtol=1e-12)
    np.testing.assert_allclose(high.mean, 350.0 * CHANNELS, rtol=1e-12)
    assert low.count == high.count == 2 * 38
    assert not low.shows_fixed_pattern and not high.shows_fixed_pattern  # the water's spread is not the sensor's
    np.testing.assert_allclose(low.temporal_variance, [2.0] * 3, rtol=1e-12)  # (+1, −1): variance 2 (ddof 1)


@pytest.mark.parametrize("pixels, levels", [(130, 2), (129, 0)])
def test_at_least_128_triples_of_dim_pixels_make_points(pixels, levels):
    # One row of dim light: `pixels` of them hold pixels − 2 triples (128 is 64 per level).
    brightness = np.full((1, 140), 5000.0)
    brightness[0, :pixels] = np.where(np.arange(pixels) < pixels // 2, 100.0, 200.0)
    none = np.zeros_like(brightness, bool)
    points = dim_noise_points(frames_of(brightness), brightness, none, none, 0.0, plate_floor=1000.0,
                              distance=2.0, margin=0)
    assert len(points) == levels


def test_dim_pixels_that_never_stand_three_in_a_row_make_no_points():
    # Stripes two pixels wide: hundreds of dim pixels, not one triple along a row.
    brightness = np.full((20, 60), 5000.0)
    stripes = (np.arange(60) % 3) != 2
    brightness[:, stripes] = np.where(np.arange(20) < 10, 100.0, 200.0)[:, None]
    none = np.zeros_like(brightness, bool)
    assert dim_noise_points(frames_of(brightness), brightness, none, none, 0.0, plate_floor=1000.0,
                            distance=2.0, margin=0) == []


def test_the_default_margin_keeps_pixels_8_or_more_from_the_plate_and_the_edge():
    # 40 × 100; the plate's region is columns 0-19. A margin of 7 keeps rows 7-32 and columns 27-92.
    # Columns below 60 are at 100, the others at 200: level 1 is columns 27-59, level 2 60-92,
    # 33 columns each, 31 triples in each of 26 rows.
    brightness = np.where(np.arange(100) < 60, 100.0, 200.0)[None, :].repeat(40, axis=0)
    occupied = np.zeros_like(brightness, bool)
    occupied[:, :20] = True
    none = np.zeros_like(brightness, bool)
    points = dim_noise_points(frames_of(brightness), brightness, occupied, none, 0.0, plate_floor=1000.0, distance=3.0)
    assert [p.count for _, p in points] == [26 * 31, 26 * 31]
    np.testing.assert_allclose([p.mean[0] for _, p in points], [100.0, 200.0], rtol=1e-12)


def test_the_plates_points_count_in_the_fixed_pattern():
    frame = np.full((8, 20, 3), 300.0)
    assert noise_point([frame, frame + 2.0], np.ones((8, 20), bool)).shows_fixed_pattern


def test_the_water_beside_the_plate_pins_read_noise_and_gain_but_not_the_fixed_pattern():
    # Camera: read noise 5 DN, gain 2 DN/e⁻, fixed pattern 1 %, 4 frames, step 1 DN.
    read, gain, fpn, frames, q = 5.0, 2.0, 0.01, 4, 1.0 / 12.0

    def temporal(e):
        return read**2 + gain * e + q

    plate = [NoisePoint(np.array([e]), np.array([e * e]), np.array([(fpn * e) ** 2 + temporal(e) / frames]),
                        np.array([temporal(e)]), frames, 1000) for e in (1000.0, 2000.0, 4000.0)]
    # The water varies from pixel to pixel as a 5 % pattern would: five times the sensor's.
    water = [NoisePoint(np.array([e]), np.array([e * e]), np.array([(0.05 * e) ** 2 + temporal(e) / frames]),
                        np.array([temporal(e)]), frames, 1000, shows_fixed_pattern=False) for e in (100.0, 200.0)]
    fit = fit_noise(plate + water, quantisation_step=1.0)
    np.testing.assert_allclose(fit.read_noise, [read], rtol=1e-6)
    np.testing.assert_allclose(fit.shot_gain, [gain], rtol=1e-6)
    np.testing.assert_allclose(fit.fixed_pattern, [fpn], rtol=1e-6)
    # Counted in the pattern, the water's spread would have moved it: by 2 % here, where the plate's
    # points, relatively far more exact, outweigh the water's.
    as_pattern = [NoisePoint(p.mean, p.mean_square, p.spatial_variance, p.temporal_variance, frames, 1000)
                  for p in water]
    assert fit_noise(plate + as_pattern, quantisation_step=1.0).fixed_pattern[0] > 1.01 * fpn
