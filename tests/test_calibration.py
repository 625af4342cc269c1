"""Radiometric calibration: the sufficient-statistics fit, the scale k, reflectance, diagnostics."""

import dataclasses
import logging
import tempfile

import dask.array as da
import numpy as np
import pytest
import scipy.ndimage
import xarray as xr
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator
from scipy.optimize import least_squares

import surffin
import surffin.method.calibration
from surffin.errors import CalibrationError
from surffin.grid import Roi
from surffin.io.store import open_store, write_store
from surffin.io.viewfile import write_view
from surffin.method.calibration import (
    CALIBRATION_STATUS,
    CORRECTION_DIMS,
    TERMS,
    Observation,
    WallStatistics,
    calibrate,
    calibration_diagnostics,
    correction_factor,
    fit_calibration,
    fit_correction,
    instrument_function,
    reference_scale,
    reflectance,
)
from surffin.simulate import PRESETS, Material

STATUS = {name: code for code, name in CALIBRATION_STATUS.items()}
TINY = PRESETS["tiny"]
# Noise-free and a wall without texture: the wall's I / cos(theta) is then exactly g rho f.
CLEAN = dataclasses.replace(
    TINY, depth_noise=0.0, intensity_noise=0.0, dropout=0.0, wall=Material("wall", TINY.wall.R0, 1.0)
)
HELD_OUT = "w005"  # 0.55 m, 10 deg tilt: inside the calibrated range of distance and AOI


def realistic_coefficients(rng, shape):
    """Coefficients (5, *shape) in the gauge E = 1, in the range the simulator's paper camera has."""
    return np.stack(
        [
            rng.uniform(50.0, 70.0, shape),
            rng.uniform(180.0, 220.0, shape),
            rng.uniform(-0.30, -0.20, shape),
            rng.uniform(0.04, 0.06, shape),
            np.ones(shape),
        ]
    )


def wall_observations(rng, coef, n_views, noise, shape):
    """n_views of (intensity, distance, aoi) (n_views, *shape) of a Lambertian wall, relative intensity noise."""
    distance = rng.uniform(0.3, 1.0, (n_views, *shape))
    aoi = rng.uniform(0.0, 0.9, (n_views, *shape))
    signal = instrument_function(coef, distance, aoi) * np.cos(aoi)
    return signal * (1.0 + noise * rng.standard_normal(signal.shape)), distance, aoi


def accumulate(intensity, distance, aoi, valid=None):
    stats = WallStatistics(intensity.shape[1:])
    valid = np.ones(intensity.shape, dtype=bool) if valid is None else valid
    for view in zip(intensity, distance, aoi, valid):
        stats.add(*view)
    return stats


# --- the model ------------------------------------------------------------------------------


def test_instrument_function_numpy_and_xarray_agree():
    rng = np.random.default_rng(0)
    coef = realistic_coefficients(rng, (3, 4))
    distance, aoi = rng.uniform(0.3, 1.0, (2, 3, 4)), rng.uniform(0.0, 1.0, (2, 3, 4))
    expected = (coef[0] + coef[1] / distance**2) * (coef[2] * aoi**2 + coef[3] * aoi + coef[4])
    np.testing.assert_allclose(instrument_function(coef, distance, aoi), expected, rtol=1e-14)
    dims = ("view", "y", "x")
    # the term order of a DataArray comes from its coordinate, not its position
    coef_da = xr.DataArray(coef[::-1], dims=("term", "y", "x"), coords={"term": list(TERMS[::-1])})
    f = instrument_function(coef_da, xr.DataArray(distance, dims=dims), xr.DataArray(aoi, dims=dims))
    np.testing.assert_allclose(f.transpose(*dims).values, expected, rtol=1e-14)


def test_simulator_and_method_agree_on_eq3_and_eq5():
    # The simulator writes eq. 3 and eq. 5 itself (its truth must not be made by the code it
    # checks, tests/test_simulate.py keeps it free of such imports): both versions must agree.
    from surffin.method.scattering import scattering_model
    from surffin.simulate import instrument as simulator

    rng = np.random.default_rng(7)
    shape = (4, 500)
    coef = np.stack(
        [
            rng.uniform(-5.0, 100.0, shape),
            rng.uniform(0.0, 300.0, shape),
            rng.uniform(-1.0, 1.0, shape),
            rng.uniform(-1.0, 1.0, shape),
            rng.uniform(0.2, 2.0, shape),
        ]
    )
    distance, aoi = rng.uniform(0.1, 3.0, shape), rng.uniform(0.0, 1.5, shape)
    f = instrument_function(coef, distance, aoi)
    # the two evaluate the angular factor in other orders: compare on the scale of f
    atol = 1e-13 * np.abs(f).max()
    np.testing.assert_allclose(simulator.instrument_function(coef, distance, aoi), f, rtol=1e-12, atol=atol)
    assert simulator.TERMS == TERMS
    # eq. 3 from near n = 0.5 to specular, up to grazing incidence: zero beyond the lobe in both
    theta, R0, n = rng.uniform(0.0, np.pi / 2, shape), rng.uniform(0.05, 1.2, shape), rng.uniform(0.55, 20.0, shape)
    ours, method = simulator.scattering(theta, R0, n), scattering_model(theta, R0, n)
    beyond = (2.0 - 1.0 / n) * theta >= np.pi / 2
    assert 0.2 < beyond.mean() < 0.8
    assert (ours[beyond] == 0.0).all() and (method[beyond] == 0.0).all()
    assert (ours[~beyond] > 0.0).all()
    # near the lobe's edge cos^n is tiny and its relative rounding large: an absolute floor
    np.testing.assert_allclose(ours, method, rtol=1e-12, atol=1e-14)


# --- the fit --------------------------------------------------------------------------------


def test_fit_equals_least_squares_on_raw_observations():
    rng = np.random.default_rng(1)
    shape = (5, 10)  # 50 pixels
    coef = realistic_coefficients(rng, shape)
    intensity, distance, aoi = wall_observations(rng, coef, 60, 0.02, shape)
    fit = fit_calibration(accumulate(intensity, distance, aoi), angular_smoothing=0)
    assert (fit.status == STATUS["converged"]).all()
    for y, x in np.ndindex(shape):
        d, theta = distance[:, y, x], aoi[:, y, x]
        target = intensity[:, y, x] / np.cos(theta)

        def residual(p, d=d, theta=theta, target=target):
            return instrument_function(np.append(p, 1.0), d, theta) - target

        # an independent start: the middle of the coefficient range, not our fit
        reference = least_squares(
            residual, [60.0, 200.0, -0.25, 0.05], method="lm", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15
        )
        ours = fit.coef.values[:, y, x]
        # D is often near zero (its noise exceeds its value): compare it on the scale of C,
        # since D theta and C theta^2 are of similar size over 0-0.9 rad; C and D are correlated
        # (-0.99): LAPACK builds differ by up to 3e-6 of C between the dependency floors and the newest
        np.testing.assert_allclose(ours[:4], reference.x, rtol=1e-5, atol=1e-5 * abs(reference.x[2]))
        fitted_f = instrument_function(ours, d, theta)
        np.testing.assert_allclose(fitted_f, instrument_function(np.append(reference.x, 1.0), d, theta), rtol=1e-6)
        assert ours[4] == 1.0
        ssr = np.sum(reference.fun**2)
        sst = np.sum((target - target.mean()) ** 2)
        assert fit.r2.values[y, x] == pytest.approx(1.0 - ssr / sst, rel=1e-9)
    np.testing.assert_array_equal(fit.n_obs, 60)


def test_noise_free_data_give_the_exact_coefficients():
    rng = np.random.default_rng(2)
    shape = (6, 7)
    coef = realistic_coefficients(rng, shape)
    fit = fit_calibration(accumulate(*wall_observations(rng, coef, 20, 0.0, shape)), angular_smoothing=0)
    assert (fit.status == STATUS["converged"]).all()
    np.testing.assert_allclose(fit.coef.values, coef, rtol=1e-8)
    np.testing.assert_allclose(fit.r2.values, 1.0, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(
    level=st.floats(1.0, 1e4),
    ratio=st.floats(0.1, 10.0),
    C=st.floats(-1.0, 0.5),
    D=st.floats(-0.5, 0.5),
    seed=st.integers(0, 2**16),
)
def test_noise_free_fits_recover_any_plausible_instrument(level, ratio, C, D, seed):
    """Any level, distance ratio B/A and angular shape with f > 0 over the views is recovered exactly."""
    rng = np.random.default_rng(seed)
    coef = np.array([level, level * ratio, C, D, 1.0])[:, None, None]
    intensity, distance, aoi = wall_observations(rng, coef, 24, 0.0, (1, 1))
    assume(np.all(intensity > 0))
    fit = fit_calibration(accumulate(intensity, distance, aoi), angular_smoothing=0)
    assert fit.status.item() == STATUS["converged"]
    np.testing.assert_allclose(fit.coef.values[:2], coef[:2], rtol=1e-8)
    np.testing.assert_allclose(fit.coef.values[2:], coef[2:], rtol=0, atol=1e-8)


def test_smoothed_angular_factor_is_the_neighbours_mean_with_exact_levels():
    rng = np.random.default_rng(5)
    shape = (30, 40)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    coef = realistic_coefficients(rng, shape)
    coef[2] = -0.25 + 0.02 * np.cos(xx / 12.0)  # a smooth angular response over the sensor
    coef[3] = 0.05 + 0.003 * np.sin(yy / 9.0)
    intensity, distance, aoi = wall_observations(rng, coef, 40, 0.02, shape)
    stats = accumulate(intensity, distance, aoi)
    own = fit_calibration(stats, angular_smoothing=0)
    smooth = fit_calibration(stats, angular_smoothing=0.04)
    assert smooth.attrs["angular_smoothing"] == 0.04
    # C and D: the Gaussian-weighted mean of the per-pixel fits (sigma 4 % of the diagonal, zero outside)
    sigma = 0.04 * np.hypot(*shape)
    weight = scipy.ndimage.gaussian_filter(np.ones(shape), sigma, mode="constant", truncate=8.0)
    for term in (2, 3):
        expected = scipy.ndimage.gaussian_filter(own.coef.values[term], sigma, mode="constant", truncate=8.0) / weight
        np.testing.assert_allclose(smooth.coef.values[term], expected, rtol=2e-3, atol=1e-5)
    # A and B: the linear least squares of each pixel's observations for its smoothed C and D
    for y, x in ((0, 0), (13, 27), (29, 39)):
        C, D = smooth.coef.values[2:4, y, x]
        theta, w = aoi[:, y, x], 1.0 / distance[:, y, x] ** 2
        g = C * theta**2 + D * theta + 1.0
        design = np.stack([g, w * g], axis=1)
        reference = np.linalg.lstsq(design, intensity[:, y, x] / np.cos(theta), rcond=None)[0]
        np.testing.assert_allclose(smooth.coef.values[:2, y, x], reference, rtol=1e-8)
    # and the instrument function is closer to the truth than the per-pixel fits
    for theta in (0.0, 0.45, 0.9):
        truth = instrument_function(coef, 0.45, theta)
        error_own = np.median(np.abs(instrument_function(own.coef.values, 0.45, theta) / truth - 1))
        error_smooth = np.median(np.abs(instrument_function(smooth.coef.values, 0.45, theta) / truth - 1))
        assert error_smooth < 0.8 * error_own, theta


def test_accumulation_is_order_independent_and_equals_one_shot_sums():
    rng = np.random.default_rng(3)
    shape = (4, 5)
    intensity, distance, aoi = wall_observations(rng, realistic_coefficients(rng, shape), 30, 0.02, shape)
    valid = rng.random(intensity.shape) > 0.2
    aoi[0, 0, 0] = np.nan  # a pixel without an AOI is left out whatever valid says
    forward = accumulate(intensity, distance, aoi, valid)
    order = rng.permutation(30)
    backward = accumulate(intensity[order], distance[order], aoi[order], valid[order])
    split = accumulate(intensity[:11], distance[:11], aoi[:11], valid[:11]).merge(
        accumulate(intensity[11:], distance[11:], aoi[11:], valid[11:])
    )
    # one shot: every moment as a plain sum over the stacked views
    used = valid & np.isfinite(aoi)
    w = np.where(used, 1.0 / distance**2, 0.0)
    theta = np.where(used, aoi, 0.0)
    y = np.where(used, intensity / np.cos(theta), 0.0)
    one = used.astype(float)
    expected = [np.sum(one * w**a * theta**c, axis=0) for a in range(3) for c in range(5)]
    expected += [np.sum(y * w**a * theta**c, axis=0) for a in range(2) for c in range(3)]
    expected.append(np.sum(y * y, axis=0))
    for stats in (forward, backward, split):
        assert stats.n_views == 30
        np.testing.assert_allclose(stats.moments, np.stack(expected), rtol=1e-13)
        np.testing.assert_array_equal(stats.n_obs, used.sum(axis=0))
    # moments equal to rounding give fits equal to the fit's own precision (~1e-6 of a
    # coefficient's standard error, from the stopping rule)
    np.testing.assert_allclose(
        fit_calibration(backward, angular_smoothing=0).coef,
        fit_calibration(forward, angular_smoothing=0).coef,
        rtol=1e-6,
    )


def test_degenerate_pixels_are_nan_with_their_status():
    rng = np.random.default_rng(4)
    shape = (3, 4)
    coef = realistic_coefficients(rng, shape)
    intensity, distance, aoi = wall_observations(rng, coef, 30, 0.01, shape)
    distance[:, 0, 0] = 0.6  # one distance: A and B are not separable
    aoi[:, 0, 1] = 0.4  # one angle: C, D and the level are not separable
    aoi[:, 0, 2] = 0.0  # normal incidence only
    distance[:15, 0, 3] = distance[0, 0, 3]  # two distances only: still fine
    valid = np.ones(intensity.shape, dtype=bool)
    valid[5:, 1, 0] = False  # 5 observations
    valid[:, 1, 1] = False  # none
    fit = fit_calibration(accumulate(intensity, distance, aoi, valid), min_obs=12, angular_smoothing=0)
    expected = np.full(shape, STATUS["converged"])
    expected[0, :3] = STATUS["singular_statistics"]
    expected[1, :2] = STATUS["too_few_observations"]
    np.testing.assert_array_equal(fit.status, expected)
    failed = expected != STATUS["converged"]
    assert np.isnan(fit.coef.values[:, failed]).all() and np.isnan(fit.r2.values[failed]).all()
    assert np.isfinite(fit.coef.values[:, ~failed]).all()
    np.testing.assert_array_equal(fit.n_obs.values[1, :2], [5, 0])
    counts = calibration_diagnostics(fit)["status_counts"]
    assert counts == {"converged": 7, "too_few_observations": 2, "singular_statistics": 3, "not_converged": 0}


def test_fit_leaves_its_inputs_unchanged_and_repeats_bit_for_bit():
    # more pixels than one block of the batched fit (the last one partial), with pixels without a fit in both
    rng = np.random.default_rng(8)
    shape = (131, 127)
    coef = realistic_coefficients(rng, shape)
    intensity, distance, aoi = wall_observations(rng, coef, 14, 0.02, shape)
    valid = rng.random(intensity.shape) > 0.05
    distance[:, 0, :40], valid[:, 0, :40] = 0.6, True  # singular statistics
    valid[:, -1, -40:] = False  # too few observations
    stats = accumulate(intensity, distance, aoi, valid)
    start = fit_calibration(stats).coef.values
    moments, previous = stats.moments.copy(), start.copy()
    fits = [fit_calibration(stats, start=start) for _ in range(2)]
    np.testing.assert_array_equal(stats.moments, moments)
    np.testing.assert_array_equal(start, previous)
    for name in ("coef", "r2", "status"):
        np.testing.assert_array_equal(fits[0][name], fits[1][name])
    status = fits[0].status.values
    assert (status[0, :40] == STATUS["singular_statistics"]).all()
    assert (status[-1, -40:] == STATUS["too_few_observations"]).all()
    assert np.mean(status == STATUS["converged"]) > 0.95


def test_fit_output_layout():
    fit = fit_calibration(WallStatistics((2, 3)))
    assert fit.coef.dims == ("term", "y", "x") and fit.coef.dtype == np.float64
    assert list(fit.term.values) == list(TERMS)
    np.testing.assert_array_equal(fit.y, [0, 1])
    np.testing.assert_array_equal(fit.x, [0, 1, 2])
    assert (fit.status == STATUS["too_few_observations"]).all()
    assert fit.status.attrs["flag_meanings"].split() == list(STATUS)
    for name in ("coef", "r2", "n_obs"):
        assert fit[name].attrs["units"] and fit[name].attrs["long_name"]
    with pytest.raises(ValueError, match="min_obs"):
        fit_calibration(WallStatistics((2, 3)), min_obs=3)
    for smoothing in (-0.1, 1.0, "0.03", True):
        with pytest.raises(ValueError, match="angular_smoothing"):
            fit_calibration(WallStatistics((2, 3)), angular_smoothing=smoothing)
    with pytest.raises(ValueError, match="sensor shape"):
        WallStatistics((2, 3)).add(np.ones((3, 2)), np.ones((2, 3)), np.ones((2, 3)), np.ones((2, 3), bool))


# --- scale k --------------------------------------------------------------------------------


def test_reference_scale_is_the_median_ratio_over_reflectance():
    rng = np.random.default_rng(5)
    coef = realistic_coefficients(rng, (6, 8))
    roi = Roi((1, 5), (2, 7))
    ratio = 1.2  # panel 0.6, wall 0.5
    views = []
    for index in range(3):
        distance = np.full((6, 8), 0.5)
        aoi = rng.uniform(0.0, 0.2, (6, 8))
        intensity = ratio * instrument_function(coef, distance, aoi) * np.cos(aoi)
        intensity[roi.slices] *= 1.0 + 0.01 * rng.standard_normal(roi.shape)
        intensity[0, 0] = 1e9  # outside the roi: ignored
        views.append(Observation(f"r{index}.npz", intensity, distance, aoi, np.ones((6, 8), bool)))
    ratios = [v.intensity / (instrument_function(coef, v.distance, v.aoi) * np.cos(v.aoi)) for v in views]
    samples = np.concatenate([ratio[roi.slices].ravel() for ratio in ratios])
    scale_k, details = reference_scale(coef, iter(views), roi, 0.6)
    assert scale_k == pytest.approx(np.median(samples) / 0.6, rel=1e-12)
    assert details["n_pixels"] == samples.size and details["n_views"] == 3
    assert set(details["per_view"]) == {"r0.npz", "r1.npz", "r2.npz"}
    assert details["relative_spread"] == pytest.approx(0.01, rel=0.3)
    # with a residual correction c (here 1.05 + theta, tabulated), the ratio is I / (f c cos(theta))
    table = correction_table(lambda d, t: 1.05 + t, [0.4, 0.6], [0.0, 0.1, 0.2])
    corrected = np.concatenate([(ratio / (1.05 + v.aoi))[roi.slices].ravel() for ratio, v in zip(ratios, views)])
    scale_k, _ = reference_scale(coef, iter(views), roi, 0.6, table)
    assert scale_k == pytest.approx(np.median(corrected) / 0.6, rel=1e-12)


def test_reference_scale_names_the_view_without_valid_panel_pixels():
    coef = realistic_coefficients(np.random.default_rng(6), (4, 4))
    ones = np.ones((4, 4))
    valid = np.ones((4, 4), bool)
    valid[1:3, 1:3] = False
    views = [
        Observation("good.npz", ones, ones, 0 * ones, np.ones((4, 4), bool)),
        Observation("bad.npz", ones, ones, 0 * ones, valid),
    ]
    with pytest.raises(CalibrationError, match="bad.npz.*no valid pixel"):
        reference_scale(coef, views, Roi((1, 3), (1, 3)), 0.6)


# --- reflectance ----------------------------------------------------------------------------


def reflectance_inputs():
    rng = np.random.default_rng(7)
    coef = realistic_coefficients(rng, (60, 80))
    coef[:2, 12, 15] = -1.0  # f < 0 there
    sensor = {"term": list(TERMS), "y": np.arange(60), "x": np.arange(80)}
    full = xr.DataArray(coef, dims=("term", "y", "x"), coords=sensor)
    dims = ("view", "y", "x")
    coords = {"view": ["a", "b", "c"], "y": np.arange(10, 50), "x": np.arange(10, 70)}
    distance = rng.uniform(0.3, 1.0, (3, 40, 60))
    aoi = rng.uniform(0.0, 0.8, (3, 40, 60))
    intensity = rng.uniform(50.0, 500.0, (3, 40, 60)).astype(np.float32)
    intensity[1, 3, 4] = np.nan
    aoi[2, 5, 6] = np.nan
    arrays = [xr.DataArray(array, dims=dims, coords=coords) for array in (intensity, distance, aoi)]
    return full, arrays


def test_reflectance_is_intensity_over_k_f_on_the_crop():
    coef, (intensity, distance, aoi) = reflectance_inputs()
    out = reflectance(intensity, distance, aoi, coef, 2.0)
    local = coef.values[:, 10:50, 10:70]
    expected = intensity.values / (2.0 * instrument_function(local, distance.values, aoi.values))
    np.testing.assert_allclose(out.values, np.where(expected > 0, expected, np.nan), rtol=1e-12)
    assert out.dims == ("view", "y", "x") and out.attrs["units"] == "1" and out.attrs["long_name"]
    assert np.isnan(out.values[:, 2, 5]).all()  # f < 0 at sensor pixel (12, 15)
    assert np.isnan(out.values[1, 3, 4]) and np.isnan(out.values[2, 5, 6])
    assert np.isfinite(out.values).sum() == out.size - 5


@pytest.mark.parametrize("correction", [False, True])
def test_reflectance_is_the_arithmetic_of_eq_2_on_data_arrays_to_the_bit(correction):
    """As a store holds them: float32 intensity, distance and AOI (d^2 in float32), float64 coefficients."""
    coef, arrays = reflectance_inputs()
    intensity, distance, aoi = (array.astype(np.float32) for array in arrays)
    distance[0, 7, :9] = np.nan
    table = correction_table(
        lambda d, t: 1.0 + 0.2 * d - 0.3 * t * t, np.arange(0.3, 1.01, 0.05), np.arange(0.0, 0.9, 0.1)
    )
    f = instrument_function(coef.sel(y=intensity["y"], x=intensity["x"]), distance, aoi)
    if correction:
        f = f * correction_factor(table, distance, aoi)
    expected = (intensity / (2.0 * f)).where(f > 0).transpose(*intensity.dims)
    out = reflectance(intensity, distance, aoi, coef, 2.0, table if correction else None)
    np.testing.assert_array_equal(out.values, expected.values)
    assert out.dtype == np.float64 and np.isnan(out.values).sum() == 9 + 3 + 2  # d, f < 0 at (12, 15), I and AOI


@pytest.mark.parametrize("scheduler", ["synchronous", "threads"])
def test_reflectance_is_lazy_on_dask_and_equals_numpy(scheduler):
    coef, arrays = reflectance_inputs()
    expected = reflectance(*arrays, coef, 2.0)
    chunks = {"view": 2, "y": 7, "x": 13}  # none divides its dimension
    lazy = reflectance(*(array.chunk(chunks) for array in arrays), coef.chunk({"y": 11, "x": 17}), 2.0)
    assert isinstance(lazy.data, da.Array)
    xr.testing.assert_identical(lazy.compute(scheduler=scheduler), expected)


def test_reflectance_refuses_a_calibration_that_does_not_cover_the_image():
    coef, arrays = reflectance_inputs()
    with pytest.raises(CalibrationError, match="does not cover"):
        reflectance(*arrays, coef.isel(x=slice(0, 40)), 2.0)
    with pytest.raises(CalibrationError, match="scale_k"):
        reflectance(*arrays, coef, 0.0)
    intensity, distance, aoi = arrays
    with pytest.raises(ValueError, match="share their coordinates"):
        reflectance(intensity, distance.assign_coords(y=distance.y + 1), aoi, coef, 2.0)


# --- diagnostics ----------------------------------------------------------------------------


def test_diagnostics_match_direct_numpy():
    rng = np.random.default_rng(8)
    shape = (20, 30)
    coef = realistic_coefficients(rng, shape)
    coef[3] = -0.99 * coef[2] + 0.001 * rng.standard_normal(shape)  # strongly anti-correlated C, D
    status = np.zeros(shape, dtype=np.int8)
    status[:3] = 1
    status[5, :7] = 3
    coef[:, status != 0] = np.nan
    r2 = np.where(status == 0, rng.uniform(0.9, 1.0, shape), np.nan)
    ds = xr.Dataset(
        {"coef": (("term", "y", "x"), coef), "r2": (("y", "x"), r2), "status": (("y", "x"), status)},
        coords={"term": list(TERMS)},
    )
    diag = calibration_diagnostics(ds)
    fitted = coef[:, status == 0]
    assert diag["n_fitted"] == fitted.shape[1] and diag["n_pixels"] == 600
    assert diag["mean_r2"] == pytest.approx(np.mean(r2[status == 0]))
    for k, term in enumerate(TERMS):
        expected = 100 * fitted[k].std() / abs(fitted[k].mean())
        assert diag["variability_percent"][term] == pytest.approx(expected, rel=1e-10, abs=1e-12)
    assert diag["correlation_terms"] == ["A", "B", "C", "D"]  # E = 1 everywhere does not vary
    corr = np.array(diag["correlation"])
    np.testing.assert_allclose(corr, corr.T, atol=1e-15)
    np.testing.assert_allclose(np.diag(corr), 1.0, atol=1e-12)
    np.testing.assert_allclose(corr, np.corrcoef(fitted[:4]), atol=1e-12)
    assert corr[2, 3] < -0.99
    counts = {"converged": 503, "too_few_observations": 90, "singular_statistics": 0, "not_converged": 7}
    assert diag["status_counts"] == counts


# --- the campaign -----------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["noisy", "clean"])
def campaign(request, tmp_path_factory):
    """A tiny synthetic campaign calibrated without its held-out wall view, and its truth."""
    root = tmp_path_factory.mktemp(request.param)
    preset = TINY if request.param == "noisy" else CLEAN
    surffin.simulate_campaign(root / "campaign", preset)
    camp = surffin.read_campaign(root / "campaign")
    calls = []
    # clean: per pixel, exactly (no smoothing of the angular factor, whose truth has a white part)
    smoothing = {"angular_smoothing": 0.0} if request.param == "clean" else {}
    ds = calibrate(camp, exclude=[HELD_OUT], progress=lambda done, total: calls.append((done, total)), **smoothing)
    truth = xr.open_zarr(root / "campaign-truth" / "instrument.zarr").compute()
    return request.param, camp, ds, truth, calls


def held_out(camp, ds):
    """The held-out wall view: its reflectance through the public API, and the truth rho_wall cos(theta)."""
    from surffin.method.geometry import angle_of_incidence

    (path,) = [path for path in camp.calibration.wall if path.stem == HELD_OUT]
    view = camp.read_view(path)
    dims = ("view", "y", "x")
    coords = {"view": [HELD_OUT], "y": np.arange(TINY.camera.height), "x": np.arange(TINY.camera.width)}
    xyz = xr.DataArray(view.xyz[None], dims=(*dims, "axis"), coords=coords)
    geometry = angle_of_incidence(xyz)
    intensity = xr.DataArray(np.where(view.valid, view.intensity, np.nan)[None], dims=dims, coords=coords)
    R = reflectance(intensity, geometry.distance, geometry.aoi, ds.coef, ds.attrs["scale_k"]).values[0]
    normal = view.pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the wall's normal (world Z) in the camera frame
    rays = view.xyz / np.linalg.norm(view.xyz, axis=-1, keepdims=True)
    true_aoi = np.arccos(np.minimum(np.abs(rays @ normal), 1.0))
    return R, TINY.wall.R0 * np.cos(true_aoi), true_aoi, geometry.distance.values[0]


def test_calibrate_recovers_the_truth(campaign):
    name, camp, ds, truth, calls = campaign
    n_pixels = TINY.camera.height * TINY.camera.width
    assert ds.coef.shape == (5, TINY.camera.height, TINY.camera.width)
    assert ds.attrs["reference_reflectance"] == TINY.reference.R0
    assert ds.attrs["surffin_stage"] == "calibration"
    assert ds.attrs["surffin_parameters"]["exclude"] == [HELD_OUT]
    assert not any(HELD_OUT in key for key in ds.attrs["surffin_inputs"])
    wall = len(camp.calibration.wall) - 1
    # the residual correction (the default) reads the wall views twice
    assert calls[-1] == (2 * wall + len(camp.calibration.reference.views),) * 2
    # no spurious residual correction where the data follow eq. 5 (measured: clean 7e-8, noisy 0.19 %)
    c = ds["correction"].values[ds["correction_count"].values >= 10]
    assert np.abs(c - 1.0).max() < (1e-6 if name == "clean" else 0.005)
    fitted = ds.status.values == 0
    R, expected, true_aoi, distance = held_out(camp, ds)
    error = R / expected - 1.0
    error = error[np.isfinite(error)]
    f_fit = instrument_function(ds.coef.values, distance, true_aoi)
    f_err = f_fit / instrument_function(truth.coef.values, distance, true_aoi) - 1.0
    f_err = f_err[np.isfinite(f_err)]
    if name == "clean":
        assert fitted.all()
        # Intensities are stored as float32 (relative rounding 2^-24 = 6e-8) and each pixel has
        # 15 views: the fit amplifies that ~30-fold in A and B and ~100-fold in C and D
        # (~-0.99 correlated). Measured over seeds 0-2: A, B within 1.7e-6, C, D within 6e-6,
        # f and R within 5e-7, k within 9e-8; the bounds leave a 10x margin.
        np.testing.assert_allclose(ds.coef.values[:2], truth.coef.values[:2], rtol=2e-5)
        np.testing.assert_allclose(ds.coef.values[2:], truth.coef.values[2:], rtol=0, atol=6e-5)
        assert ds.attrs["scale_k"] == pytest.approx(truth.attrs["scale_k"], rel=1e-6)
        # f itself, over a view it was not fitted on, and the reflectance of that view
        assert np.max(np.abs(f_err)) < 5e-6
        assert np.max(np.abs(error)) < 5e-6 and error.size == n_pixels
        assert ds.attrs["diagnostics"]["mean_r2"] == pytest.approx(1.0, abs=1e-10)
    else:
        # 15 views with 1.5-4 % intensity noise, 0.9 mm depth noise and a wall with a 0.5 %
        # texture: C and D are poorly determined per pixel (only their combination with A and
        # B matters), and a few border pixels may not converge. f over the held-out view's
        # geometry is good to ~noise * sqrt(4 / 15) ~ 1 % per pixel (measured over seeds 0-2:
        # median |error| 0.9 %, median error within 0.04 %).
        assert fitted.sum() >= 0.99 * n_pixels
        assert np.median(np.abs(f_err)) < 0.015 and abs(np.median(f_err)) < 0.003
        # k: f at the panel's geometry has per-pixel errors of several %, correlated over a few
        # pixels (the wall's 1 cm texture seen by neighbours, shared AOI windows): over the
        # ~1500-pixel roi they leave ~0.2 % (measured -0.08, +0.24, -0.20 % over seeds 0-2).
        assert ds.attrs["scale_k"] == pytest.approx(truth.attrs["scale_k"], rel=0.005)
        # the held-out view: its own 1.5-4 % noise and the fit's ~1 % per pixel (measured median
        # |error| 2.2-2.3 %); its median error is k's (measured within 0.26 %).
        assert np.median(np.abs(error)) < 0.03 and abs(np.median(error)) < 0.005
        assert ds.attrs["diagnostics"]["mean_r2"] > 0.99


def test_plain_calibration_has_no_correction_and_the_same_noise_model(campaign):
    _, camp, ds, _, _ = campaign
    smoothing = ds.attrs["angular_smoothing"]
    plain = calibrate(camp, exclude=[HELD_OUT], residual_correction=False, angular_smoothing=smoothing)
    assert "correction" not in plain and not plain.attrs["surffin_parameters"]["residual_correction"]
    assert ds.attrs["surffin_parameters"]["residual_correction"]
    for name in ("noise_variance", "noise_samples"):
        xr.testing.assert_equal(plain[name], ds[name])


def test_calibration_measures_the_intensity_noise(campaign):
    """The wall's noise model against the simulator's own noise formula (independent of surffin.method.noise)."""
    name, _, ds, _, _ = campaign
    measured = np.sqrt(ds["noise_variance"].values)
    level = ds["noise_intensity"].values
    if name == "clean":
        # no noise, no wall texture: what is left is float32 rounding and the fit's own misfit
        assert np.nanmax(measured) < 1e-4
        return
    # the simulator: relative sigma 1.5 % above 2000 counts, growing as 1/sqrt(I) below, capped at 4 %
    truth = np.clip(
        TINY.intensity_noise * np.sqrt(TINY.noise_reference / level), TINY.intensity_noise, TINY.intensity_noise_max
    )
    # bins between the cap and the floor, where the formula has no kink inside the bin; measured
    # within 6 % (each pixel's fit takes up part of the noise of the 15 views it was fitted on)
    middle = (level > 300) & (level < 1800) & np.isfinite(measured)
    assert middle.sum() >= 6
    np.testing.assert_allclose(measured[middle], truth[middle], rtol=0.12)


def test_calibration_store_round_trip(campaign, tmp_path):
    _, _, ds, _, _ = campaign
    back = open_store(write_store(ds, tmp_path / "calibration.zarr"), stage="calibration").compute()
    xr.testing.assert_identical(back[["coef", "r2", "n_obs", "status"]], ds[["coef", "r2", "n_obs", "status"]])
    assert back.attrs["scale_k"] == ds.attrs["scale_k"]
    assert back.attrs["diagnostics"] == ds.attrs["diagnostics"]
    assert back.attrs["reference"]["per_view"] == ds.attrs["reference"]["per_view"]
    xr.testing.assert_equal(back[["correction", "correction_count"]], ds[["correction", "correction_count"]])
    for key, value in ds["correction"].attrs.items():
        assert np.all(np.asarray(back["correction"].attrs[key]) == np.asarray(value)), key


def test_calibrate_logs_progress_and_refuses_bad_requests(campaign, caplog):
    _, camp, _, _, _ = campaign
    with pytest.raises(CalibrationError, match="no views named \\['nope'\\]"):
        calibrate(camp, exclude=["nope"])
    no_calibration = dataclasses.replace(camp, calibration=None)
    with pytest.raises(CalibrationError, match="no calibration section"):
        calibrate(no_calibration)
    everything = [path.stem for path in camp.calibration.wall]
    with caplog.at_level(logging.INFO, logger="surffin"), pytest.raises(CalibrationError, match="no pixel"):
        calibrate(camp, exclude=everything[2:])
    assert any("calibration: 2/" in message for message in caplog.messages)


def test_calibrate_computes_each_views_geometry_once_and_leaves_no_temporary_files(campaign, monkeypatch, tmp_path):
    """The second pass over the wall takes the first pass's observations back, not a second plane fit."""
    _, camp, ds, _, _ = campaign
    fitted = []
    fit = surffin.method.calibration.frame_angle_of_incidence
    monkeypatch.setattr(
        surffin.method.calibration,
        "frame_angle_of_incidence",
        lambda xyz, *args, **kwargs: fitted.append(xyz.shape) or fit(xyz, *args, **kwargs),
    )
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    again = calibrate(camp, exclude=[HELD_OUT], angular_smoothing=ds.attrs["angular_smoothing"])
    assert len(fitted) == len(camp.calibration.wall) - 1 + len(camp.calibration.reference.views)
    xr.testing.assert_identical(again, ds)
    assert list(tmp_path.iterdir()) == []
    # a failure between the passes leaves nothing behind either
    everything = [path.stem for path in camp.calibration.wall]
    with pytest.raises(CalibrationError, match="no pixel"):
        calibrate(camp, exclude=everything[2:])
    assert list(tmp_path.iterdir()) == []


def test_saturated_pixels_are_left_out_of_the_calibration_and_counted(tmp_path):
    """Wall views clipped at a saturation level, as a camera would: with camera.saturation the fit is exact."""
    surffin.simulate_campaign(tmp_path / "campaign", CLEAN)
    camp = surffin.read_campaign(tmp_path / "campaign")
    level = 2400.0  # the brightest wall views (nearest, most perpendicular) reach ~2600
    clipped = {}
    for path in (*camp.calibration.wall, *camp.calibration.reference.views):
        view = camp.read_view(path)
        clipped[str(path.relative_to(camp.root))] = int((view.valid & (view.intensity >= level)).sum())
        write_view(path, view.xyz, np.minimum(view.intensity, level), pose=view.pose)
    assert sum(count > 0 for count in clipped.values()) >= 3
    truth = xr.open_zarr(tmp_path / "campaign-truth" / "instrument.zarr").compute()
    saturating = dataclasses.replace(camp, camera=dataclasses.replace(camp.camera, saturation=level))

    ds = calibrate(saturating, angular_smoothing=0.0)
    assert ds.attrs["saturated_pixels"] == clipped
    assert ds.attrs["settings"] == dict.fromkeys(clipped, {})
    assert (ds.status.values == 0).all()
    np.testing.assert_allclose(ds.coef.values[:2], truth.coef.values[:2], rtol=2e-5)
    np.testing.assert_allclose(ds.coef.values[2:], truth.coef.values[2:], rtol=0, atol=6e-5)
    assert ds.attrs["scale_k"] == pytest.approx(truth.attrs["scale_k"], rel=1e-6)

    blind = calibrate(camp, angular_smoothing=0.0)  # the clipped intensities taken at face value
    assert (blind.n_obs.values - ds.n_obs.values).sum() == sum(clipped.values())
    assert np.abs(blind.coef.values[:2] / truth.coef.values[:2] - 1).max() > 0.1


# --- the residual correction ------------------------------------------------------------------


def smooth_factor(distance, aoi):
    """A smooth factor outside eq. 5's form (a wave in distance whose phase turns with the AOI), 3 % peak."""
    return 1.0 + 0.03 * np.sin(2.0 * np.pi * distance / 0.35 + 2.0 * aoi)


def correction_table(function, distances, aois):
    """``function`` tabulated on the nodes, in the layout of a calibration's ``correction``."""
    dims = ("correction_distance", "correction_aoi")
    values = np.broadcast_to(
        function(np.asarray(distances)[:, None], np.asarray(aois)[None, :]), (len(distances), len(aois))
    )
    return xr.DataArray(values, dims=dims, coords={dims[0]: distances, dims[1]: aois})


def residual_ratios(factor, noise, seed=0, n_views=60, shape=(24, 32)):
    """Wall observations ``I = f s cos(theta)`` with noise, fitted by eq. 5.

    Returns the ratios ``y / f_fit`` (y = I / cos(theta)), distance, AOI, view index, intensity, the true
    and the fitted coefficients.
    """
    rng = np.random.default_rng(seed)
    coef = realistic_coefficients(rng, shape)
    intensity, distance, aoi = wall_observations(rng, coef, n_views, noise, shape)
    intensity = intensity * factor(distance, aoi)
    fitted = fit_calibration(accumulate(intensity, distance, aoi), angular_smoothing=0.0).coef.values
    ratio = intensity / (np.cos(aoi) * instrument_function(fitted, distance, aoi))
    views = np.broadcast_to(np.arange(n_views)[:, None, None], ratio.shape)
    return ratio, distance, aoi, views, intensity, coef, fitted


def test_correction_recovers_a_smooth_factor_from_noisy_ratios():
    """The smoother alone: ratios that are the factor times 1 % noise give the factor back."""
    rng = np.random.default_rng(3)
    distance = rng.uniform(0.3, 1.0, 200_000)
    aoi = rng.uniform(0.0, 0.9, distance.size)
    ratio = smooth_factor(distance, aoi) * (1.0 + 0.01 * rng.standard_normal(distance.size))
    ds = fit_correction(ratio, distance, aoi, rng.integers(0, 40, distance.size))
    c = ds["correction"]
    assert c.dims == CORRECTION_DIMS and c.attrs["n_samples"] == distance.size
    assert c.attrs["penalty"] in c.attrs["cv_penalties"] and len(c.attrs["cv_scores"]) == len(c.attrs["cv_penalties"])
    # inside the covered range (one node in from its edges): ~200 observations per 1 cm x 1 deg node,
    # 0.07 % noise per node before smoothing; measured max error 0.12 %
    d, t = np.meshgrid(np.linspace(0.31, 0.99, 50), np.linspace(0.02, 0.88, 40), indexing="ij")
    error = correction_factor(c, d, t) / smooth_factor(d, t) - 1.0
    assert np.max(np.abs(error)) < 0.003 and np.median(np.abs(error)) < 0.001
    # the chosen smoothness beats the roughest and the smoothest candidates on held-out views
    scores = c.attrs["cv_scores"]
    assert min(scores) < scores[0] and min(scores) < scores[-1]


def test_correction_times_eq5_recovers_the_instrument_outside_eq5():
    """Per-pixel eq. 5 fits take up part of the factor; f c recovers f s where the wall covers (d, theta).

    :func:`calibrate`'s alternation on arrays: c from the ratios to the plain fit, eq. 5 refitted to
    ``I / c``, c again. The reference is the same noise without the factor: eq. 5's own error.
    """
    ratio, distance, aoi, views, intensity, coef, fitted = residual_ratios(smooth_factor, noise=0.01)
    first = fit_correction(ratio, distance, aoi, views)["correction"]
    stats = accumulate(intensity / correction_factor(first, distance, aoi), distance, aoi)
    refit = fit_calibration(stats, angular_smoothing=0.0).coef.values
    ratio = intensity / (np.cos(aoi) * instrument_function(refit, distance, aoi))
    c = fit_correction(ratio, distance, aoi, views)["correction"]
    baseline = residual_ratios(lambda d, t: 1.0, noise=0.01)[-1]

    d, t = np.meshgrid(np.linspace(0.32, 0.98, 12), np.linspace(0.03, 0.87, 10), indexing="ij")
    d, t = d[:, :, None, None], t[:, :, None, None]
    true = instrument_function(coef, d, t)

    def error(fit, factor):
        return np.median(np.abs(instrument_function(fit, d, t) * factor / (true * smooth_factor(d, t)) - 1.0))

    reference = np.median(np.abs(instrument_function(baseline, d, t) / true - 1.0))
    # measured median errors: eq. 5 alone 1.7 %, c of the plain fit 0.49 %, after the alternation 0.27 %,
    # the reference 0.25 %
    assert error(fitted, 1.0) > 0.01
    assert error(fitted, correction_factor(first, d, t)) < 0.007
    assert error(refit, correction_factor(c, d, t)) < reference + 0.0005


def test_correction_is_one_where_the_data_follow_eq5():
    ratio, distance, aoi, views, *_ = residual_ratios(lambda d, t: 1.0, noise=0.01)
    ds = fit_correction(ratio, distance, aoi, views)
    supported = ds["correction"].values[ds["correction_count"].values >= 10]
    # measured within 0.15 % of 1 (noise of ~12 observations per node, smoothed)
    assert np.max(np.abs(supported - 1.0)) < 0.004


def test_reflectance_with_the_correction_removes_the_factor():
    coef, (_, distance, aoi) = reflectance_inputs()
    local = coef.values[:, 10:50, 10:70]
    R = 0.7
    intensity = 2.0 * instrument_function(local, distance, aoi) * smooth_factor(distance, aoi) * R
    table = correction_table(smooth_factor, np.arange(0.2, 1.1, 0.005), np.deg2rad(np.arange(0.0, 60.0, 0.5)))
    out = reflectance(intensity, distance, aoi, coef, 2.0, table)
    plain = reflectance(intensity, distance, aoi, coef, 2.0)
    good = np.isfinite(out.values)
    assert np.nanmax(np.abs(plain.values / R - 1.0)) > 0.025
    # bilinear interpolation of the tabulated factor: error below (h^2 / 8) |s''| ~ 1e-4
    np.testing.assert_allclose(out.values[good], R, rtol=2e-4)
    assert np.isnan(out.values[2, 5, 6]) and good.sum() == out.size - 4  # NaN AOI; f < 0 at (12, 15)
    lazy = reflectance(*(array.chunk({"y": 7}) for array in (intensity, distance, aoi)), coef, 2.0, table)
    assert isinstance(lazy.data, da.Array)
    xr.testing.assert_allclose(lazy.compute(), out)


def test_correction_never_extrapolates():
    """Beyond the grid the factor is held at the grid's edge; nodes without data take the nearest supported one."""
    ramp = correction_table(lambda d, t: 1.0 + 0.1 * d + 0.2 * t, [0.3, 0.4, 0.5], [0.0, 0.5])
    far = correction_factor(ramp, np.array([0.0, 0.3, 2.0, 2.0, np.nan]), np.array([-1.0, 0.25, 0.0, 3.0, 0.1]))
    np.testing.assert_allclose(far[:4], [1.03, 1.08, 1.05, 1.15], rtol=1e-12)
    assert np.isnan(far[4])
    # data only where d + theta < 1.2, a steep factor there: the empty corner holds the values of its edge
    rng = np.random.default_rng(5)
    distance, aoi = rng.uniform(0.3, 1.0, 100_000), rng.uniform(0.0, 0.9, 100_000)
    inside = distance + aoi < 1.2
    steep = 1.0 + 0.2 * (distance + aoi)
    ds = fit_correction(steep[inside], distance[inside], aoi[inside], rng.integers(0, 20, inside.sum()))
    c, count = ds["correction"].values, ds["correction_count"].values
    supported = count >= 10
    assert supported.mean() < 0.8
    assert c[~supported].min() >= c[supported].min() - 1e-9 and c[~supported].max() <= c[supported].max() + 1e-9
    # the far corner (1.0 m, 0.9 rad) lies where no data are: it gets the values of the support's edge (~1.24)
    corner = float(correction_factor(ds["correction"], 1.0, 0.9))
    assert corner == pytest.approx(1.24, abs=0.01) and ds["correction"].attrs["outside"]
    with pytest.raises(ValueError, match="correction must be a DataArray"):
        correction_factor(ramp.rename(correction_aoi="aoi"), 0.4, 0.1)
    with pytest.raises(CalibrationError, match="at least 2 views"):
        fit_correction(steep, distance, aoi, np.zeros(distance.size, dtype=int))


def test_correction_lookup_matches_scipy_regular_grid_interpolation():
    """Any table, any positions: scipy's RegularGridInterpolator on the clamped positions, NaN where one is NaN."""
    rng = np.random.default_rng(8)
    distances, aois = np.linspace(0.25, 1.15, 13), np.linspace(0.0, 1.2, 9)
    table = correction_table(lambda d, t: 1.0 + 0.05 * rng.standard_normal((d.size, t.size)), distances, aois)
    distance, aoi = rng.uniform(0.1, 1.4, (40, 30)), rng.uniform(-0.2, 1.5, (40, 30))
    distance[3, :4] = aoi[5, 7:9] = np.nan
    got = correction_factor(table, distance, aoi)
    finite = np.isfinite(distance) & np.isfinite(aoi)
    points = np.stack([np.clip(distance, 0.25, 1.15), np.clip(aoi, 0.0, 1.2)], axis=-1)[finite]
    expected = RegularGridInterpolator((distances, aois), table.values)(points)
    np.testing.assert_allclose(got[finite], expected, rtol=1e-12)
    assert np.isnan(got[~finite]).all() and (~finite).sum() == 6


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_correction_lookup_is_scipy_map_coordinates_to_the_bit(dtype):
    """Positions on, between and beyond the nodes, NaN and inf, over several blocks of pixels."""
    rng = np.random.default_rng(11)
    distances, aois = np.linspace(0.25, 1.15, 13), np.linspace(0.0, 1.2, 9)
    table = correction_table(lambda d, t: rng.lognormal(0.0, 0.3, (d.size, t.size)), distances, aois)
    distance, aoi = rng.uniform(0.1, 1.4, (7, 50_000)), rng.uniform(-0.2, 1.5, (7, 50_000))
    distance[1], aoi[2] = rng.choice(distances, 50_000), rng.choice(aois, 50_000)
    distance[3, :100], aoi[3, 100:200], aoi[4, :100] = np.nan, np.inf, -np.inf
    distance, aoi = distance.astype(dtype), aoi.astype(dtype)
    index = [
        (np.clip(values.astype(np.float64), nodes[0], nodes[-1]) - nodes[0]) / (nodes[1] - nodes[0])
        for values, nodes in ((distance, distances), (aoi, aois))
    ]
    finite = np.isfinite(index[0]) & np.isfinite(index[1])
    positions = [np.where(finite, position, 0.0) for position in index]
    expected = scipy.ndimage.map_coordinates(table.values, positions, order=1, mode="nearest", prefilter=False)
    np.testing.assert_array_equal(correction_factor(table, distance, aoi), np.where(finite, expected, np.nan))
    assert (~finite).sum() == 100  # NaN; inf is clamped to the grid


def test_instrument_truth_tabulates_the_rendered_systematics_for_the_correction_lookup():
    """The simulator's truth of residual systematics reads back through correction_factor (the ceiling's c)."""
    instrument = surffin.simulate.draw_instrument(
        TINY.camera, TINY.coef_mean, TINY.coef_variability, TINY.gain, surffin.simulate.keyed_rng(0, "i")
    )
    assert "systematic" not in surffin.simulate.instrument_truth(instrument, TINY)
    truth = surffin.simulate.instrument_truth(instrument, TINY, systematics=0.03)
    rng = np.random.default_rng(2)
    distance, aoi = rng.uniform(0.2, 2.0, 1000), rng.uniform(0.0, 1.4, 1000)
    expected = surffin.simulate.systematic_factor(distance, aoi, 0.03)
    # bilinear on 5 mm x 0.5 deg nodes: within (h^2 / 8) |s''| ~ 5e-5
    np.testing.assert_allclose(correction_factor(truth["systematic"], distance, aoi), expected, rtol=1e-4)
    assert truth.attrs["systematics"] == 0.03


def test_calibration_error_compares_k_f_c_with_the_true_k_f_s():
    """The evaluation's calibration error includes both the fitted correction and the rendered systematics."""
    from surffin.analysis.evaluation import CALIBRATION_CHECK, calibration_error

    rng = np.random.default_rng(4)
    coef = realistic_coefficients(rng, (6, 8))
    nodes = np.arange(0.2, 1.2, 0.005), np.deg2rad(np.arange(0.0, 60.0, 0.5))
    table = correction_table(smooth_factor, *nodes)

    def store(coef, scale_k, **factor):
        variables = {"coef": (("term", "y", "x"), coef), **factor}
        return xr.Dataset(variables, coords={"term": list(TERMS)}, attrs={"scale_k": scale_k})

    truth = store(coef, 2.0, systematic=table)
    crop = Roi((1, 5), (2, 7))
    high = coef * np.array([1.01, 1.01, 1.0, 1.0, 1.0])[:, None, None]  # f 1 % too high everywhere
    assert calibration_error(store(high, 2.0, correction=table), truth, crop) == pytest.approx(0.01, rel=1e-3)
    # without the factor: the worst of |1.01 / s - 1| over the checked angles (one distance: every pixel alike)
    distance, angles = CALIBRATION_CHECK
    expected = max(abs(1.01 / smooth_factor(distance, np.deg2rad(a)) - 1.0) for a in angles)
    assert calibration_error(store(high, 2.0), truth, crop) == pytest.approx(expected, rel=1e-3)
