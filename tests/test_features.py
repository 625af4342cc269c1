"""Feature images (surffin.features) against brute-force loops and analytic surfaces."""

import dask.array as dask_array
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from surffin.campaign import Roi
from surffin.features import (
    QUALITY,
    features,
    gaussian_sigma,
    local_std,
    most_perpendicular_view,
    select_roi,
    smooth,
    variability,
)
from surffin.scattering import fit_scattering, scattering_model

Y0, X0 = 40, 70
"""Sensor position of the crops' top-left pixel: grids never start at 0."""


def grid(values, y0=Y0, x0=X0, **dims):
    """A DataArray (..., y, x) with integer sensor coordinates starting at (y0, x0)."""
    values = np.asarray(values)
    names = (*dims, "y", "x")
    coords = {"y": np.arange(y0, y0 + values.shape[-2]), "x": np.arange(x0, x0 + values.shape[-1]), **dims}
    return xr.DataArray(values, dims=names, coords=coords)


def holey_image(shape=(23, 31), seed=0, holes=40):
    """Random image with scattered NaN pixels, a NaN block and a NaN border run."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.2, 1.0, shape)
    image[rng.integers(0, shape[0], holes), rng.integers(0, shape[1], holes)] = np.nan
    image[8:12, 14:19] = np.nan
    image[0, :6] = np.nan
    return image


def windows(image, size):
    """Every pixel's size x size window (H, W, size, size), NaN outside the image."""
    r = size // 2
    padded = np.pad(image, r, constant_values=np.nan)
    return np.lib.stride_tricks.sliding_window_view(padded, (size, size))


def brute_smooth(image, size, sigma, min_weight):
    """Normalised convolution pixel by pixel with an independently built 2-D Gaussian."""
    offsets = np.arange(size) - size // 2
    kernel = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma**2))
    kernel /= kernel.sum()
    out = np.full(image.shape, np.nan)
    win = windows(image, size)
    for i, j in np.ndindex(image.shape):
        w = win[i, j]
        ok = np.isfinite(w)
        mass = kernel[ok].sum()
        if np.isfinite(image[i, j]) and mass >= min_weight:
            out[i, j] = (kernel[ok] * w[ok]).sum() / mass
    return out


def brute_std(image, size, ddof, min_count):
    out = np.full(image.shape, np.nan)
    win = windows(image, size)
    for i, j in np.ndindex(image.shape):
        count = np.isfinite(win[i, j]).sum()
        if np.isfinite(image[i, j]) and count >= max(min_count, ddof + 1):
            out[i, j] = np.nanstd(win[i, j], ddof=ddof)
    return out


def test_sigma_rule_is_opencvs():
    assert gaussian_sigma(7) == pytest.approx(1.4)
    assert gaussian_sigma(3) == pytest.approx(0.8)
    with pytest.raises(ValueError, match="odd"):
        gaussian_sigma(6)


@pytest.mark.parametrize(("size", "sigma", "min_weight"), [(7, None, 0.25), (5, 2.0, 0.5), (3, None, 0.9)])
def test_smooth_matches_brute_force(size, sigma, min_weight):
    image = holey_image()
    out = smooth(grid(image), size, sigma=sigma, min_weight=min_weight)
    expected = brute_smooth(image, size, gaussian_sigma(size) if sigma is None else sigma, min_weight)
    np.testing.assert_array_equal(np.isnan(out.values), np.isnan(expected))
    np.testing.assert_allclose(out.values, expected, rtol=1e-13, atol=1e-15)
    assert out.dims == ("y", "x") and out["y"][0] == Y0 and out.dtype == np.float64


def test_delta_gives_the_normalised_kernel():
    image = np.zeros((15, 15))
    image[7, 7] = 1.0
    out = smooth(grid(image), 7).values
    g = np.exp(-0.5 * (np.arange(-3, 4) / 1.4) ** 2)
    g /= g.sum()
    np.testing.assert_allclose(out[4:11, 4:11], np.outer(g, g), rtol=1e-13, atol=1e-17)
    assert out.sum() == pytest.approx(1.0, rel=1e-13)
    assert (out[:4] == 0).all() and (out[:, 11:] == 0).all()


def test_constant_stays_constant_near_holes_and_borders():
    image = np.where(np.isnan(holey_image()), np.nan, 0.731)
    out = smooth(grid(image), 7).values
    finite = np.isfinite(image)
    # every valid pixel keeps the constant, holes are not filled
    np.testing.assert_allclose(out[finite], 0.731, rtol=1e-14)
    assert np.isnan(out[~finite]).all()
    # the corner sees about a third of the kernel mass: kept at 0.25, dropped at 0.5
    assert np.isfinite(smooth(grid(np.ones((9, 9))), 7, min_weight=0.25).values[0, 0])
    assert np.isnan(smooth(grid(np.ones((9, 9))), 7, min_weight=0.5).values[0, 0])


def test_pixel_in_a_sea_of_nan_is_dropped():
    image = np.full((9, 9), np.nan)
    image[4, 4] = 1.0
    assert np.isnan(smooth(grid(image), 7).values).all()
    # alone it carries ~10 % of the kernel mass
    assert smooth(grid(image), 7, min_weight=0.05).values[4, 4] == 1.0


@settings(max_examples=25, deadline=None)
@given(
    y_cuts=st.lists(st.integers(1, 22), max_size=4, unique=True),
    x_cuts=st.lists(st.integers(1, 30), max_size=4, unique=True),
    size=st.sampled_from([3, 5, 7]),
)
def test_dask_equals_numpy_for_any_chunks(y_cuts, x_cuts, size):
    image = grid(holey_image(seed=size))

    def chunks(cuts, n):
        bounds = [0, *sorted(cuts), n]
        return tuple(b - a for a, b in zip(bounds[:-1], bounds[1:]))

    lazy = image.chunk({"y": chunks(y_cuts, 23), "x": chunks(x_cuts, 31)})
    for func in (smooth, local_std):
        expected = func(image, size).values
        out = func(lazy, size)
        assert isinstance(out.data, dask_array.Array)
        got = out.values
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-15)


def test_other_dims_are_looped_and_kept_in_place():
    stack = np.stack([holey_image(seed=s) for s in range(3)])
    cube = grid(stack, view=["a", "b", "c"])
    for func in (smooth, local_std):
        out = func(cube.transpose("y", "view", "x"), 5)
        assert out.dims == ("y", "view", "x")
        for k, view in enumerate("abc"):
            np.testing.assert_array_equal(out.sel(view=view).values, func(grid(stack[k]), 5).values)


@pytest.mark.parametrize(("ddof", "min_count"), [(1, None), (0, 5), (1, 40)])
def test_local_std_matches_nanstd(ddof, min_count):
    image = holey_image(seed=3)
    out = local_std(grid(image), 7, ddof=ddof, min_count=min_count)
    expected = brute_std(image, 7, ddof, 13 if min_count is None else min_count)
    np.testing.assert_array_equal(np.isnan(out.values), np.isnan(expected))
    np.testing.assert_allclose(out.values, expected, rtol=1e-11, atol=1e-15)
    assert out.attrs["ddof"] == ddof


def test_local_std_does_not_cancel_on_a_large_offset():
    rng = np.random.default_rng(5)
    image = 1e6 + 1e-3 * rng.standard_normal((20, 20))
    image[10, 10] = np.nan
    out = local_std(grid(image), 5).values
    np.testing.assert_allclose(out, brute_std(image, 5, 1, 7), rtol=1e-7)


def test_select_roi_uses_sensor_coordinates():
    image = grid(np.arange(20 * 30.0).reshape(20, 30))
    part = select_roi(image, Roi((Y0 + 2, Y0 + 5), (X0 + 10, X0 + 14)))
    assert part.shape == (3, 4)
    assert part["y"].values.tolist() == [Y0 + 2, Y0 + 3, Y0 + 4]
    assert part.values[0, 0] == 2 * 30 + 10
    with pytest.raises(ValueError, match="holds no pixel"):
        select_roi(image, Roi((0, 10), (X0, X0 + 5)))


def test_most_perpendicular_view():
    rng = np.random.default_rng(1)
    aoi = np.deg2rad(np.stack([np.full((10, 12), 30.0), np.full((10, 12), 10.0), np.full((10, 12), 20.0)]))
    aoi += rng.normal(0, 0.01, aoi.shape)
    # view "b" is grazing on the right half, where view "c" is the most perpendicular
    aoi[1, :, 6:] = np.deg2rad(60.0)
    aoi[0, :3] = np.nan
    cube = grid(aoi, view=["a", "b", "c"])
    assert most_perpendicular_view(cube) == "c"  # median over all pixels: b's is 35 deg
    assert most_perpendicular_view(cube, Roi((Y0, Y0 + 10), (X0, X0 + 6))) == "b"
    # a view missing everywhere but on a few good pixels does not win through them
    cube[2] = np.nan
    assert most_perpendicular_view(cube, Roi((Y0, Y0 + 10), (X0 + 6, X0 + 12))) == "a"
    with pytest.raises(ValueError, match="no view"):
        most_perpendicular_view(cube * np.nan)


def lambertian_view(shape=(30, 40), rho=0.6, texture=0.0, seed=0):
    """Reflectance R = rho cos(theta) of a diffuse surface with AOI 5..55 deg across the image."""
    theta = np.deg2rad(np.linspace(5, 55, shape[1]))[None, :] + np.deg2rad(np.linspace(0, 10, shape[0]))[:, None]
    albedo = rho + texture * np.random.default_rng(seed).standard_normal(shape)
    return grid(albedo * np.cos(theta)), grid(theta)


def test_variability_of_a_lambertian_surface_is_zero():
    reflectance, aoi = lambertian_view()
    out = variability(reflectance, aoi)
    assert out.attrs["units"] == "1"
    assert np.isfinite(out.values).all()
    assert np.nanmax(out.values) < 1e-12
    # without the Lambert correction the AOI gradient would leak in
    assert np.nanmin(local_std(reflectance).values) > 1e-3


def test_variability_measures_the_texture():
    reflectance, aoi = lambertian_view(shape=(120, 160), texture=0.02)
    out = variability(reflectance, aoi).values
    # unbiased variance: its mean over windows is the texture variance
    assert np.sqrt(np.mean(out[3:-3, 3:-3] ** 2)) == pytest.approx(0.02, rel=0.03)


def test_variability_needs_one_grid():
    reflectance, aoi = lambertian_view()
    with pytest.raises(ValueError, match="same"):
        variability(reflectance, aoi.assign_coords(x=aoi["x"] + 1))
    with pytest.raises(ValueError, match="dims"):
        variability(reflectance.expand_dims(view=["a"]), aoi)


@pytest.fixture
def fit():
    """A scattering fit of 5 noisy views of a 16 x 20 grid with a NaN pixel."""
    rng = np.random.default_rng(2)
    theta = np.deg2rad(np.array([0.0, 10, 20, 30, 40]))[:, None, None] + np.zeros((5, 16, 20))
    r = scattering_model(theta, 0.8, 1.3) + rng.normal(0, 0.01, theta.shape)
    r[:, 3, 4] = np.nan
    view = [f"v{k}" for k in range(5)]
    return fit_scattering(grid(r, view=view), grid(theta, view=view))


def test_features(fit):
    var = grid(np.full((16, 20), 0.01))
    ds = features(fit, var, size=5)
    assert set(ds.data_vars) == {"R0", "n", "variability", "R0_fit", "n_fit", *QUALITY}
    np.testing.assert_array_equal(ds["R0"].values, smooth(fit["R0"], 5).values)
    np.testing.assert_array_equal(ds["n_fit"].values, fit["n"].values)
    # smoothing lowers the pixel-to-pixel scatter of the fit
    assert np.nanstd(ds["n"].values) < 0.5 * np.nanstd(fit["n"].values)
    assert np.isnan(ds["R0"].values[3, 4])
    assert ds.attrs["smoothing_size"] == 5 and ds.attrs["smoothing_sigma"] == pytest.approx(1.1)
    for name, arr in ds.data_vars.items():
        assert "long_name" in arr.attrs, name
    assert all(ds[name].attrs["units"] == "1" for name in ("R0", "n", "variability"))
    with pytest.raises(ValueError, match="warp"):
        features(fit, var.isel(x=slice(1, None)))


def test_features_stay_lazy(fit):
    var = grid(np.full((16, 20), 0.01)).chunk({"y": 7})
    ds = features(fit.chunk({"y": 5, "x": 9}), var)
    assert isinstance(ds["R0"].data, dask_array.Array)
    np.testing.assert_allclose(ds["n"].values, features(fit, var.compute())["n"].values, rtol=1e-12)
