import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares

from surffin.method.scattering import FIT_STATUS, fit_scattering, fit_scattering_arrays, scattering_model


def noisy_pixels(npix, nview=5, sigma=0.02, seed=0):
    rng = np.random.default_rng(seed)
    theta = np.abs(np.deg2rad(np.linspace(0, 40, nview)) + rng.normal(0, np.deg2rad(3), (npix, nview)))
    r0 = rng.uniform(0.5, 1.0, npix)
    n = rng.uniform(0.7, 2.0, npix)
    r = scattering_model(theta, r0[:, None], n[:, None]) + rng.normal(0, sigma, (npix, nview))
    return r, theta, r0, n


def scipy_fit(r, theta):
    """Global least-squares optimum from several starts (the independent reference)."""

    def resid(p):
        return scattering_model(theta, p[0], p[1]) - r

    fits = [
        least_squares(resid, [r.max(), n0], bounds=([0, 0.5 + 1e-9], [np.inf, 50]), xtol=1e-15, ftol=1e-15, gtol=1e-15)
        for n0 in (0.6, 1.0, 2.0, 5.0)
    ]
    return min(fits, key=lambda f: f.cost).x


def test_model_closed_forms():
    theta = np.linspace(0, 1.2, 7)
    np.testing.assert_allclose(scattering_model(theta, 0.7, 1.0), 0.7 * np.cos(theta), rtol=1e-14)
    np.testing.assert_allclose(scattering_model(theta[:-1], 1.0, 2.0), np.cos(1.5 * theta[:-1]) ** 2, rtol=1e-12)
    # no return beyond (2 - 1/n) theta = pi/2
    assert scattering_model(1.2, 1.0, 10.0) == 0.0


def test_matches_scipy_least_squares():
    r, theta, _, _ = noisy_pixels(150, seed=3)
    out = fit_scattering_arrays(r, theta)
    assert (out["status"] == 0).all()
    for i in range(r.shape[0]):
        np.testing.assert_allclose([out["R0"][i], out["n"][i]], scipy_fit(r[i], theta[i]), rtol=1e-6)


def test_recovers_truth_without_noise():
    r, theta, r0, n = noisy_pixels(500, sigma=0.0, seed=1)
    out = fit_scattering_arrays(r, theta)
    np.testing.assert_allclose(out["R0"], r0, rtol=1e-8)
    np.testing.assert_allclose(out["n"], n, rtol=1e-8)
    assert out["converged"].all()
    assert np.nanmax(out["rms"]) < 1e-10


@settings(max_examples=60, deadline=None)
@given(
    r0=st.floats(0.05, 1.0),
    n=st.floats(0.55, 8.0),
    angles=st.lists(st.floats(0.0, 60.0), min_size=3, max_size=8, unique=True),
)
def test_noise_free_fit_is_exact(r0, n, angles):
    theta = np.deg2rad(np.array(angles))
    if np.ptp(theta) < np.deg2rad(10) or np.any((2 - 1 / n) * theta >= 0.99 * np.pi / 2):
        return
    out = fit_scattering_arrays(scattering_model(theta, r0, n)[None], theta[None])
    assert out["status"][0] == 0
    np.testing.assert_allclose([out["R0"][0], out["n"][0]], [r0, n], rtol=1e-6)


def test_uncertainty_matches_scatter_of_repeated_fits():
    rng = np.random.default_rng(7)
    npix, sigma = 20000, 0.02
    theta = np.broadcast_to(np.deg2rad(np.linspace(0, 40, 5)), (npix, 5))
    r = scattering_model(theta, 0.8, 1.2) + rng.normal(0, sigma, (npix, 5))
    out = fit_scattering_arrays(r, theta)
    # the median reported sigma agrees with the empirical spread within 15 %
    assert np.nanmedian(out["n_sigma"]) == pytest.approx(np.nanstd(out["n"]), rel=0.15)
    assert np.nanmedian(out["R0_sigma"]) == pytest.approx(np.nanstd(out["R0"]), rel=0.15)


def test_status_codes_never_garbage():
    theta = np.deg2rad(np.array([[0, 20, 40], [10, np.nan, np.nan], [20, 21, 22], [0, 20, 40]], float))
    r = np.array([[0.8, 0.75, 0.6], [0.8, 0.7, 0.6], [0.7, 0.7, 0.7], [-0.8, -0.75, -0.6]])
    out = fit_scattering_arrays(r, theta)
    assert list(out["status"]) == [0, 1, 2, 4]
    assert list(out["n_views"]) == [3, 1, 3, 3]
    for key in ("R0", "n", "R0_sigma", "n_sigma", "rms"):
        assert np.isfinite(out[key][0]) and np.isnan(out[key][1:]).all()
    assert set(np.unique(out["status"])) <= set(FIT_STATUS)


def test_two_views_fit_exactly_with_unknown_uncertainty():
    theta = np.deg2rad(np.array([[5.0, 45.0]]))
    out = fit_scattering_arrays(scattering_model(theta, 0.9, 1.3), theta)
    np.testing.assert_allclose([out["R0"][0], out["n"][0]], [0.9, 1.3], rtol=1e-8)
    assert np.isnan(out["n_sigma"][0])


def cube(ny=23, nx=31, nview=5):
    r, theta, _, _ = noisy_pixels(ny * nx, nview, seed=5)
    r[::7, 1] = np.nan
    dims = ("view", "y", "x")
    coords = {"view": [f"v{i}" for i in range(nview)], "y": np.arange(ny), "x": np.arange(nx)}
    return tuple(xr.DataArray(a.T.reshape(nview, ny, nx), dims=dims, coords=coords) for a in (r, theta))


def test_dask_equals_numpy_with_uneven_chunks():
    r, theta = cube()
    eager = fit_scattering(r, theta)
    lazy = fit_scattering(r.chunk({"view": -1, "y": 10, "x": 13}), theta.chunk({"view": -1, "y": 10, "x": 13}))
    assert lazy["R0"].chunks is not None
    xr.testing.assert_identical(lazy.compute(), eager)
    assert eager["R0"].dims == ("y", "x")
    assert eager["R0"].attrs["units"] == "1"


def test_view_must_be_one_chunk():
    r, theta = cube()
    with pytest.raises(ValueError, match="rechunk"):
        fit_scattering(r.chunk({"view": 2}), theta.chunk({"view": 2}))


@pytest.mark.parametrize("n", [3.0, 5.0])
def test_the_fit_stays_where_every_view_is_lit(n):
    # found by test_noise_free_fit_is_exact: the views at 49 deg return 0.3 % of R0, and above
    # n = 6.13 the model returns nothing there, a flat F(n) the fit used to stop on (n = 15.8)
    theta = np.deg2rad(np.array([0.0, 49.0, 48.75]))
    out = fit_scattering_arrays(scattering_model(theta, 1.0, n)[None], theta[None])
    assert out["status"][0] == 0
    np.testing.assert_allclose([out["R0"][0], out["n"][0]], [1.0, n], rtol=1e-6)


def test_inputs_of_any_layout_and_float_type_fit_alike_and_are_left_alone():
    r, theta, _, _ = noisy_pixels(300, seed=4)
    r[::9, 2] = np.nan
    r32, theta32 = r.astype(np.float32), theta.astype(np.float32)
    expected = fit_scattering_arrays(r32.astype(np.float64), theta32.astype(np.float64))
    # (y, x, view) views of (view, y, x) cubes, as fit_scattering hands them over: the view axis is the slowest
    view_major = [np.ascontiguousarray(a.T).T.reshape(20, 15, 5) for a in (r32, theta32)]
    assert not view_major[0].flags.c_contiguous
    for args in ([r32, theta32], view_major, [a.astype(np.float64) for a in view_major]):
        before = [a.copy() for a in args]
        out = fit_scattering_arrays(*args)
        for key, value in expected.items():
            np.testing.assert_array_equal(out[key].reshape(-1), value, err_msg=key)
        for a, b in zip(args, before):
            np.testing.assert_array_equal(a, b)  # NaN and all: the inputs are not written to


@pytest.mark.parametrize("nview", [5, 20])
def test_a_pixels_fit_does_not_depend_on_the_pixels_fitted_with_it(nview):
    # the kernel works on blocks of pixels, their size set by the number of views: a pixel's fit is its own, to
    # the bit (but for a pixel alone in a block, whose views einsum sums in another order)
    r, theta, _, _ = noisy_pixels(20000, nview, seed=5)
    r[::7, 1] = np.nan
    whole = fit_scattering_arrays(r, theta)
    for part in (slice(0, 2), slice(3, 780), slice(780, None)):
        alone = fit_scattering_arrays(r[part], theta[part])
        for key, value in whole.items():
            np.testing.assert_array_equal(alone[key], value[part], err_msg=key)


def test_high_incidence_pixels_match_scipy_least_squares():
    # views at 50-67 deg: 4 of the 10 start values of n (above 1.6) light none of them and are not tried
    rng = np.random.default_rng(8)
    theta = np.deg2rad(np.array([51.0, 55, 60, 65]) + rng.normal(0, 1, (40, 4)))
    n = rng.uniform(0.6, 1.0, 40)
    r = scattering_model(theta, 0.7, n[:, None]) + rng.normal(0, 0.002, theta.shape)
    out = fit_scattering_arrays(r, theta)
    for i in np.flatnonzero(out["status"] == 0):
        np.testing.assert_allclose([out["R0"][i], out["n"][i]], scipy_fit(r[i], theta[i]), rtol=1e-6)
    assert (out["status"] == 0).mean() > 0.8
