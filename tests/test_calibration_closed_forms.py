"""Small pieces of the calibration against published numbers and textbook closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from uwcam.calibration.line_fit import chi2_upper, fit_attenuation_differences, fit_lines
from uwcam.calibration.noise_fit import variance_floor


@pytest.mark.parametrize("dof, chi2_95", [(5, 11.070), (10, 18.307), (20, 31.410), (30, 43.773), (100, 124.342)])
def test_reduced_chi2_bound_matches_the_published_95_percent_points(dof, chi2_95):
    """χ²₀.₉₅(k) from the standard tables, divided by k (Wilson–Hilferty is good to ~0.3 % here)."""
    assert chi2_upper(dof) == pytest.approx(chi2_95 / dof, rel=3e-3)


def test_variance_floor_is_a_quantisation_step_or_a_float32_rounding():
    np.testing.assert_allclose(variance_floor([0.0, 10.0, 5000.0], 4.0), [16 / 12] * 3, rtol=1e-15)
    e = np.array([1.0, 3.0e4])
    np.testing.assert_allclose(variance_floor(e, 0.0), (e * 2.0**-23) ** 2 / 12, rtol=1e-15)


def test_two_point_weighted_line_has_the_uncertainty_of_its_stated_variances():
    x = np.array([1.0, 3.0])
    y = np.array([[2.0], [5.0]])
    var = np.array([[0.04], [0.09]])
    fit = fit_lines(x, y, var)
    w = 1 / var[:, 0]
    det = w.sum() * (w * x**2).sum() - (w * x).sum() ** 2
    assert fit.slope[0] == pytest.approx(1.5) and fit.intercept[0] == pytest.approx(0.5)
    assert fit.slope_std[0] == pytest.approx(np.sqrt(w.sum() / det), rel=1e-12)
    assert fit.intercept_std[0] == pytest.approx(np.sqrt((w * x**2).sum() / det), rel=1e-12)
    assert np.all(np.isnan(fit_lines(x, y).slope_std))  # equal weights, no spare degree: unknown


def test_unweighted_fit_over_three_distances_has_the_ordinary_least_squares_errors():
    """With no stated variances the scatter sets the uncertainty: s² = RSS/(n − 2),
    Var(V) = s²/Σ(d − d̄)², Var(b) = s²·Σd²/(n·Σ(d − d̄)²), for ln(E_1/E_0) = b − V·d."""
    d = np.array([2.0, 4.0, 7.0])
    ratio = np.array([-0.31, -0.93, -1.78])  # ln(E_1/E_0): scattered about a line
    ln_e = np.stack([np.zeros(3), ratio], axis=1)
    fit = fit_attenuation_differences(ln_e, d)
    slope, intercept = np.polyfit(d, ratio, 1)
    rss = np.sum((ratio - (intercept + slope * d)) ** 2)
    s2 = rss / (len(d) - 2)
    sxx = np.sum((d - d.mean()) ** 2)
    assert fit.attenuation_difference[1] == pytest.approx(-slope, rel=1e-10)
    assert fit.log_constant[1] == pytest.approx(intercept, rel=1e-10)
    assert fit.attenuation_difference_std[1] == pytest.approx(np.sqrt(s2 / sxx), rel=1e-9)
    assert fit.log_constant_std[1] == pytest.approx(np.sqrt(s2 * np.sum(d**2) / (len(d) * sxx)), rel=1e-9)


def test_stated_variances_are_scaled_only_when_the_scatter_is_significantly_larger():
    d = np.array([2.0, 4.0, 7.0, 9.0])
    line = -0.3 * d + 0.1
    sigma2 = 1e-4  # each ln E; the ratio then has 2σ²
    lv = np.full((4, 2), sigma2)
    sxx = np.sum((d - d.mean()) ** 2)
    honest = fit_attenuation_differences(np.stack([np.zeros(4), line + [0.01, -0.012, 0.008, -0.006]], 1), d, log_variance=lv)
    assert honest.attenuation_difference_std[1] == pytest.approx(np.sqrt(2 * sigma2 / sxx), rel=1e-9)
    bad = line + [0.2, -0.25, 0.15, -0.1]  # far more scatter than 2σ² allows
    fit = fit_attenuation_differences(np.stack([np.zeros(4), bad], 1), d, log_variance=lv)
    slope, intercept = np.polyfit(d, bad, 1)
    chi2 = np.sum((bad - (intercept + slope * d)) ** 2) / (2 * sigma2) / (len(d) - 2)
    assert chi2 > chi2_upper(2)
    assert fit.attenuation_difference_std[1] == pytest.approx(np.sqrt(2 * sigma2 / sxx * chi2), rel=1e-9)
