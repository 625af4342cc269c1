"""Feature images (surffin.method.features) against brute-force loops and analytic surfaces."""

import dask.array as dask_array
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

from surffin.grid import Roi
from surffin.method.features import (
    QUALITY,
    features,
    first_available,
    gaussian_sigma,
    local_std,
    residual_correlation,
    select_roi,
    smooth,
    smooth_uncertainty,
    variability,
    variance_inflation,
    views_by_incidence,
)
from surffin.method.registration import warp
from surffin.method.scattering import fit_scattering, scattering_model
from surffin.method.stages import features_stage

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


def gaussian_kernel(size, sigma):
    """An independently built, normalised 2-D Gaussian (size, size)."""
    offsets = np.arange(size) - size // 2
    kernel = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma**2))
    return kernel / kernel.sum()


def brute_smooth(image, size, sigma, min_weight):
    """Normalised convolution pixel by pixel with an independently built 2-D Gaussian."""
    kernel = gaussian_kernel(size, sigma)
    out = np.full(image.shape, np.nan)
    win = windows(image, size)
    for i, j in np.ndindex(image.shape):
        w = win[i, j]
        ok = np.isfinite(w)
        mass = kernel[ok].sum()
        if np.isfinite(image[i, j]) and mass >= min_weight:
            out[i, j] = (kernel[ok] * w[ok]).sum() / mass
    return out


def brute_uncertainty(image, uncertainty, size, min_weight, inflation):
    """The propagated uncertainty of the normalised convolution, pixel by pixel (smooth_uncertainty's formula)."""
    kernel = gaussian_kernel(size, gaussian_sigma(size))
    out = np.full(image.shape, np.nan)
    values, sigmas = windows(image, size), windows(uncertainty, size)
    for i, j in np.ndindex(image.shape):
        ok = np.isfinite(values[i, j])
        known = ok & np.isfinite(sigmas[i, j])
        if not (np.isfinite(image[i, j]) and kernel[ok].sum() >= min_weight and known.any()):
            continue
        s, w = sigmas[i, j][known], kernel[known]
        bound = (w * s).sum() / w.sum()
        variance = (w**2 * s**2).sum() / (w**2).sum()
        independent = np.sqrt(inflation * variance * (kernel[ok] ** 2).sum()) / kernel[ok].sum()
        out[i, j] = min(bound, independent)
    return out


def holey_uncertainty(image, seed=0):
    """Per-pixel uncertainties 0.01..0.05 of ``image``, unknown (NaN) on a few of its finite pixels."""
    rng = np.random.default_rng(seed)
    sigma = np.where(np.isfinite(image), rng.uniform(0.01, 0.05, image.shape), np.nan)
    sigma[rng.integers(0, image.shape[0], 15), rng.integers(0, image.shape[1], 15)] = np.nan
    return sigma


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
    sigma = grid(holey_uncertainty(image.values, seed=size))
    for func, args in ((smooth, ()), (local_std, ()), (smooth_uncertainty, (sigma,))):
        expected = func(image, *args, size=size).values
        # the uncertainties in other chunks than the values: cut into the values' chunks
        out = func(lazy, *(arg.chunk({"x": 7}) for arg in args), size=size)
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


def test_views_by_incidence():
    rng = np.random.default_rng(1)
    aoi = np.deg2rad(np.stack([np.full((10, 12), 30.0), np.full((10, 12), 10.0), np.full((10, 12), 20.0)]))
    aoi += rng.normal(0, 0.01, aoi.shape)
    # view "b" is grazing on the right half, where view "c" is the most perpendicular
    aoi[1, :, 6:] = np.deg2rad(60.0)
    aoi[0, :3] = np.nan
    cube = grid(aoi, view=["a", "b", "c"])
    assert views_by_incidence(cube) == ["c", "a", "b"]  # medians over all pixels: 20, 30, 35 deg
    assert views_by_incidence(cube, Roi((Y0, Y0 + 10), (X0, X0 + 6))) == ["b", "c", "a"]
    # a view missing everywhere comes last
    cube[2] = np.nan
    assert views_by_incidence(cube, Roi((Y0, Y0 + 10), (X0 + 6, X0 + 12))) == ["a", "b", "c"]
    with pytest.raises(ValueError, match="no view"):
        views_by_incidence(cube * np.nan)


def test_views_by_incidence_takes_the_median_of_an_even_count_halfway():
    # medians 20, 21, 19 and 22 deg: "a" would go last on its upper middle value, first on its lower one
    aoi = np.deg2rad(np.array([[10.0, 30, np.nan, np.nan], [21, 21, 21, 21], [19, 18, 20, 19], [5, 50, 22, np.nan]]))
    assert views_by_incidence(grid(aoi[:, None, :], view=["a", "b", "c", "d"])) == ["c", "a", "b", "d"]


def test_first_available_takes_each_pixel_from_the_first_view_that_has_it():
    rng = np.random.default_rng(2)
    data = rng.random((3, 10, 12))
    data[rng.random(data.shape) < 0.5] = np.nan
    cube = grid(data, view=["a", "b", "c"])
    for chunks in (None, {"y": 3, "x": 5}):
        values, source = first_available(cube if chunks is None else cube.chunk(chunks))
        for y, x in np.ndindex(10, 12):
            finite = np.flatnonzero(np.isfinite(data[:, y, x]))
            assert source.values[y, x] == (finite[0] if finite.size else -1)
            if finite.size:
                assert values.values[y, x] == data[finite[0], y, x]
            else:
                assert np.isnan(values.values[y, x])


def views_of_an_item(shape=(18, 22), seed=3):
    """Three views of a textured plane on their own grids, and maps onto the first view's, with holes.

    The first view misses a block and scattered pixels, the second part of that block (and maps
    off its grid at the left edge), the third part of that part: pixels take their value from
    each of the three views, and some from none.
    """
    rng = np.random.default_rng(seed)
    view = ["a", "b", "c"]
    aoi = np.deg2rad(np.array([10.0, 25.0, 40.0]))[:, None, None] + rng.normal(0, 0.02, (3, *shape))
    reflectance = 0.7 * np.cos(aoi) * (1 + 0.05 * rng.standard_normal((3, *shape)))
    reflectance[0, 5:11, 6:14] = np.nan
    reflectance[0, rng.integers(0, shape[0], 15), rng.integers(0, shape[1], 15)] = np.nan
    reflectance[1, 5:9, 6:10] = np.nan
    reflectance[2, 4:9, 5:11] = np.nan
    aoi[2, 14:, :] = np.nan
    noise = np.full((3, *shape), 0.01)
    y, x = np.mgrid[Y0 : Y0 + shape[0], X0 : X0 + shape[1]].astype(np.float32)
    map_x = np.stack([x, x - 1.25, x + 0.4])
    map_y = np.stack([y, y + 0.5, y - 0.3])
    own = xr.Dataset(
        {
            "reflectance": grid(reflectance, view=view),
            "reflectance_noise": grid(noise, view=view),
            "aoi": grid(aoi, view=view),
        }
    )
    maps = xr.Dataset({"map_x": grid(map_x, view=view), "map_y": grid(map_y, view=view)})
    registered = xr.Dataset(
        {"reflectance": warp(own["reflectance"], maps), "aoi": warp(own["aoi"], maps), **maps.data_vars}
    )
    return registered, own[["reflectance", "reflectance_noise"]], own[["aoi"]]


@pytest.mark.parametrize("chunks", [None, {"y": 7, "x": 9}])
@pytest.mark.parametrize(
    ("roi", "blind"), [(None, None), (Roi((Y0 + 4, Y0 + 12), (X0 + 3, X0 + 15)), None), (None, "b"), (None, "c")]
)
def test_features_stage_takes_the_variability_from_the_first_view_that_has_it(chunks, roi, blind):
    registered, reflectance, aoi = views_of_an_item()
    if blind:  # a view whose maps send no pixel anywhere
        registered["map_x"].loc[{"view": blind}] = np.nan
    order = views_by_incidence(aoi["aoi"], roi)
    assert order == ["a", "b", "c"]
    own = xr.concat(
        [
            variability(
                reflectance["reflectance"].sel(view=v),
                aoi["aoi"].sel(view=v),
                size=5,
                relative_noise=reflectance["reflectance_noise"].sel(view=v),
            )
            for v in order
        ],
        dim="view",
    )
    maps = registered[["map_x", "map_y"]].sel(view=order)
    if roi is not None:
        maps = select_roi(maps, roi.grown(2))
    expected, source = first_available(warp(own, maps))
    assert set(np.unique(source.values)) == {-1, 0, 1, 2} - {order.index(blind) if blind else None}
    if chunks:
        registered, reflectance, aoi = (ds.chunk(chunks) for ds in (registered, reflectance, aoi))
    ds = features_stage(registered, reflectance, aoi, roi=roi, size=5, variability_size=5).compute()
    np.testing.assert_array_equal(ds["variability"].values, expected.values.astype(np.float32))
    np.testing.assert_array_equal(ds["variability_view"].values, source.values)
    assert ds["variability"].attrs["noise_corrected"] == 1
    assert ds.attrs["variability_views"] == order


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


@pytest.mark.parametrize("chunks", [None, {"y": 7, "x": 11}])
def test_variability_is_the_local_std_of_the_corrected_reflectance(chunks):
    reflectance, aoi = lambertian_view(shape=(30, 40), texture=0.02)
    aoi = aoi.where(aoi["x"] != aoi["x"][5])
    noise = xr.full_like(reflectance, 0.01).where(reflectance["y"] != reflectance["y"][3])
    corrected = (reflectance / np.cos(aoi)).where(np.cos(aoi) > 0)
    expected = local_std(corrected, noise_variance=(corrected * noise) ** 2)
    if chunks:
        reflectance, aoi, noise = (a.chunk(chunks) for a in (reflectance, aoi, noise))
    out = variability(reflectance, aoi, relative_noise=noise)
    assert out.attrs["noise_corrected"] == 1
    assert out.attrs["min_count"] == expected.attrs["min_count"]
    np.testing.assert_allclose(out.values, expected.values, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("chunks", [None, {"y": 9, "x": 11}])
@pytest.mark.parametrize(
    "region",
    [
        Roi((Y0 + 5, Y0 + 17), (X0 + 20, X0 + 31)),
        Roi((Y0 - 4, Y0 + 3), (X0 + 30, X0 + 60)),
        Roi((Y0 + 10, Y0 + 11), (X0 + 7, X0 + 8)),
        Roi((Y0, Y0 + 30), (X0, X0 + 40)),
        Roi((Y0 + 6, Y0 + 6), (X0, X0 + 40)),
        Roi((0, 10), (0, 10)),
    ],
)
def test_variability_in_a_region_is_that_of_the_whole_grid(chunks, region):
    # a bright gradient: the sums of squares are centred on the whole image's mean, which a part's would change
    reflectance, aoi = lambertian_view(shape=(30, 40), rho=50.0, texture=0.5)
    reflectance = (reflectance * (1 + 0.1 * reflectance["x"])).where(holey_image((30, 40), holes=60) > 0)
    noise = xr.full_like(reflectance, 0.01).where(reflectance["y"] != reflectance["y"][12])
    if chunks:
        reflectance, aoi, noise = (a.chunk(chunks) for a in (reflectance, aoi, noise))
    whole = variability(reflectance, aoi, relative_noise=noise).values
    out = variability(reflectance, aoi, relative_noise=noise, region=region)
    y, x = np.meshgrid(reflectance["y"], reflectance["x"], indexing="ij")
    inside = (y >= region.y[0]) & (y < region.y[1]) & (x >= region.x[0]) & (x < region.x[1])
    np.testing.assert_array_equal(out.values, np.where(inside, whole, np.nan))
    assert out.attrs == variability(reflectance, aoi, relative_noise=noise).attrs


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
    assert set(ds.data_vars) == {
        "R0",
        "n",
        "variability",
        "R0_uncertainty",
        "n_uncertainty",
        "R0_fit",
        "n_fit",
        *QUALITY,
    }
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
    with pytest.raises(ValueError, match="n_sigma"):
        features(fit.drop_vars("n_sigma"), var)


def test_features_propagate_the_fit_sigma(fit):
    var = grid(np.full((16, 20), 0.01))
    # without a measured correlation: the fully correlated bound
    bound = features(fit, var)
    assert bound.attrs["uncertainty_propagation"].startswith("fully correlated")
    assert "uncertainty_inflation" not in bound.attrs
    np.testing.assert_array_equal(bound["n_uncertainty"].values, smooth_uncertainty(fit["n"], fit["n_sigma"]).values)
    correlation = xr.DataArray(
        np.zeros((13, 13)), dims=("lag_y", "lag_x"), coords={"lag_y": np.arange(-6, 7), "lag_x": np.arange(-6, 7)}
    )
    correlation[6, 6] = 1.0
    ds = features(fit, var, error_correlation=correlation)
    assert ds.attrs["uncertainty_inflation"] == pytest.approx(1.0)
    assert ds.attrs["uncertainty_effective_pixels"] == pytest.approx(variance_inflation(correlation * 0 + 1), rel=1e-12)
    for name in ("R0", "n"):
        expected = smooth_uncertainty(fit[name], fit[f"{name}_sigma"], inflation=ds.attrs["uncertainty_inflation"])
        np.testing.assert_array_equal(ds[f"{name}_uncertainty"].values, expected.values)
        assert ds[f"{name}_uncertainty"].attrs["units"] == "1"
        assert f"{name}_sigma" in ds[f"{name}_uncertainty"].attrs["long_name"]
        # independent errors average down; the bound does not
        assert np.nanmedian(ds[f"{name}_uncertainty"]) < 0.3 * np.nanmedian(bound[f"{name}_uncertainty"])
    # a correlation without residuals (NaN) falls back to the bound
    assert (
        features(fit, var, error_correlation=correlation * np.nan).attrs["uncertainty_propagation"].startswith("fully")
    )


def test_features_stay_lazy(fit):
    var = grid(np.full((16, 20), 0.01)).chunk({"y": 7})
    ds = features(fit.chunk({"y": 5, "x": 9}), var)
    eager = features(fit, var.compute())
    for name in ("R0", "n", "R0_uncertainty", "n_uncertainty"):
        assert isinstance(ds[name].data, dask_array.Array), name
        np.testing.assert_allclose(ds[name].values, eager[name].values, rtol=1e-12)


# --- propagation of the per-pixel uncertainties -------------------------------------------------


@pytest.mark.parametrize(("size", "min_weight", "inflation"), [(7, 0.25, 1.0), (5, 0.5, 7.5), (3, 0.25, np.inf)])
def test_uncertainty_matches_brute_force(size, min_weight, inflation):
    image = holey_image(seed=4)
    sigma = holey_uncertainty(image)
    out = smooth_uncertainty(grid(image), grid(sigma), size, min_weight=min_weight, inflation=inflation)
    expected = brute_uncertainty(image, sigma, size, min_weight, inflation)
    np.testing.assert_array_equal(np.isnan(out.values), np.isnan(expected))
    np.testing.assert_allclose(out.values, expected, rtol=1e-12)
    # exactly where the smoothed value is, but for windows without a known uncertainty
    assert not (np.isfinite(out.values) & np.isnan(smooth(grid(image), size, min_weight=min_weight).values)).any()


def test_constant_uncertainty_has_the_closed_form():
    shape, s = (15, 17), 0.02
    kernel = gaussian_kernel(7, 1.4)
    out = smooth_uncertainty(grid(np.ones(shape)), grid(np.full(shape, s)), 7, inflation=1.0).values
    # inside: s sqrt(sum w^2) / sum w
    np.testing.assert_allclose(out[3:-3, 3:-3], s * np.sqrt((kernel**2).sum()), rtol=1e-13)
    # in a corner only a quarter of the kernel is in the image
    quarter = kernel[3:, 3:]
    assert out[0, 0] == pytest.approx(s * np.sqrt((quarter**2).sum()) / quarter.sum(), rel=1e-13)
    # fully correlated: s everywhere
    np.testing.assert_allclose(smooth_uncertainty(grid(np.ones(shape)), grid(np.full(shape, s))).values, s, rtol=1e-13)
    # an unknown uncertainty takes the mean variance of its window: nothing changes here
    unknown = np.full(shape, s)
    unknown[5:7, 8] = np.nan
    np.testing.assert_allclose(
        smooth_uncertainty(grid(np.ones(shape)), grid(unknown), inflation=1.0).values, out, rtol=1e-13
    )
    # a window without any known uncertainty has none
    hole = np.full(shape, np.nan)
    hole[0, 0] = s
    assert np.isnan(smooth_uncertainty(grid(np.ones(shape)), grid(hole)).values[10, 10])


def test_independent_errors_monte_carlo():
    image = holey_image(seed=6)
    sigma = holey_uncertainty(image, seed=6)
    sigma = np.where(np.isfinite(image), np.where(np.isnan(sigma), 0.03, sigma), np.nan)
    rng = np.random.default_rng(7)
    draws = image + sigma * rng.standard_normal((4000, *image.shape))
    spread = smooth(grid(draws, draw=np.arange(4000)), 7).std("draw").values
    propagated = smooth_uncertainty(grid(image), grid(sigma), 7, inflation=1.0).values
    np.testing.assert_array_equal(np.isnan(spread), np.isnan(propagated))
    np.testing.assert_allclose(spread, propagated, rtol=0.06, equal_nan=True)


def correlated_noise(rng, shape, radius=6, length=1.5):
    """Unit-variance noise correlated by a Gaussian filter of sd ``length``, and its exact correlation."""
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / length) ** 2)
    taps /= np.sqrt((taps**2).sum())
    white = rng.standard_normal((*shape[:-2], shape[-2] + 2 * radius, shape[-1] + 2 * radius))
    noise = np.apply_along_axis(np.convolve, -1, white, taps, "valid")
    noise = np.apply_along_axis(np.convolve, -2, noise, taps, "valid")
    lag = np.correlate(taps, taps, "full")[radius : 3 * radius + 1]
    lags = np.arange(-radius, radius + 1)
    correlation = xr.DataArray(np.outer(lag, lag), dims=("lag_y", "lag_x"), coords={"lag_y": lags, "lag_x": lags})
    return noise, correlation


def test_variance_inflation_of_correlated_errors_monte_carlo():
    rng = np.random.default_rng(8)
    noise, correlation = correlated_noise(rng, (3000, 9, 9))
    inflation = variance_inflation(correlation, 7)
    assert 1 < inflation < 23.6
    spread = smooth(grid(0.5 + 0.02 * noise, draw=np.arange(3000)), 7).std("draw").values[4, 4]
    propagated = smooth_uncertainty(grid(np.ones((9, 9))), grid(np.full((9, 9), 0.02)), 7, inflation=inflation)
    assert spread == pytest.approx(propagated.values[4, 4], rel=0.05)


def test_variance_inflation_limits():
    lags = np.arange(-6, 7)
    coords = {"lag_y": lags, "lag_x": lags}
    delta = xr.DataArray(
        np.where(np.add.outer(lags**2, lags**2) == 0, 1.0, 0.0), dims=("lag_y", "lag_x"), coords=coords
    )
    assert variance_inflation(delta, 7) == pytest.approx(1.0, rel=1e-14)
    kernel = gaussian_kernel(7, 1.4)
    assert variance_inflation(delta * 0 + 1, 7) == pytest.approx(1 / (kernel**2).sum(), rel=1e-12)
    assert variance_inflation(delta * 0 + 1, 7) == pytest.approx(23.6, abs=0.05)
    # a larger correlation table is cut to the kernel's lags; a smaller one is an error
    assert variance_inflation(delta, 5) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="lags -6..6"):
        variance_inflation(delta.isel(lag_y=slice(1, -1), lag_x=slice(1, -1)), 7)


def test_variance_inflation_is_the_double_sum_over_the_kernel():
    lags = np.arange(-6, 7)
    rho = np.random.default_rng(3).uniform(-0.2, 1.0, (13, 13))
    correlation = xr.DataArray(rho, dims=("lag_y", "lag_x"), coords={"lag_y": lags, "lag_x": lags})
    kernel = gaussian_kernel(7, 1.4)
    pixels = [(i, j) for i in range(7) for j in range(7)]
    double_sum = sum(kernel[p] * kernel[q] * rho[p[0] - q[0] + 6, p[1] - q[1] + 6] for p in pixels for q in pixels)
    assert variance_inflation(correlation, 7) == pytest.approx(double_sum / (kernel**2).sum(), rel=1e-12)


def views_of(noise, shape):
    """Registered reflectance and AOI (view, y, x) of 5 views of R0 = 0.8, n = 1.3 plus ``noise``."""
    theta = np.deg2rad(np.array([0.0, 12, 24, 36, 48]))[:, None, None] + np.zeros((5, *shape))
    reflectance = scattering_model(theta, 0.8, 1.3) + noise
    view = [f"v{k}" for k in range(5)]
    return grid(reflectance, view=view), grid(theta, view=view)


@pytest.mark.parametrize("correlated", [False, True])
def test_residual_correlation_measures_the_error_correlation(correlated):
    rng = np.random.default_rng(9)
    shape = (120, 150)
    if correlated:
        noise, expected = correlated_noise(rng, (5, *shape))
    else:
        noise, expected = rng.standard_normal((5, *shape)), None
    reflectance, aoi = views_of(0.01 * noise, shape)
    reflectance[2, 10:14, 20:24] += 0.5  # outliers are left out
    fit = fit_scattering(reflectance, aoi)
    out = residual_correlation(reflectance, aoi, fit, max_lag=6)
    assert out.dims == ("lag_y", "lag_x") and out.sel(lag_y=0, lag_x=0) == 1.0
    np.testing.assert_allclose(out.values, out.values[::-1, ::-1], rtol=1e-10)
    if correlated:
        np.testing.assert_allclose(out.values, expected.values, atol=0.04)
        assert variance_inflation(out) == pytest.approx(variance_inflation(expected), rel=0.1)
    else:
        off_centre = np.abs(out.values[np.arange(13) != 6])
        assert off_centre.max() < 0.03
        assert variance_inflation(out) == pytest.approx(1.0, abs=0.1)
    # lags beyond a small image are zero-padded, not an error
    small = residual_correlation(reflectance.isel(y=slice(0, 4)), aoi.isel(y=slice(0, 4)), fit.isel(y=slice(0, 4)))
    assert small.shape == (13, 13) and np.isnan(small.values[0]).all()


def test_residual_correlation_without_residuals_is_nan():
    reflectance, aoi = views_of(0.0, (10, 12))
    reflectance[2:] = np.nan  # two views: fitted exactly, no residual degrees of freedom
    fit = fit_scattering(reflectance, aoi)
    assert (fit["status"] == 0).all()
    assert np.isnan(residual_correlation(reflectance, aoi, fit).values).all()
    with pytest.raises(ValueError, match="one grid"):
        residual_correlation(reflectance, aoi, fit.isel(x=slice(1, None)))
    with pytest.raises(ValueError, match="max_lag"):
        residual_correlation(reflectance, aoi, fit, max_lag=-1)


def test_uncertainty_errors():
    image = grid(holey_image())
    with pytest.raises(ValueError, match="inflation"):
        smooth_uncertainty(image, image, inflation=0)
    with pytest.raises(ValueError, match="one grid"):
        smooth_uncertainty(image, image.isel(x=slice(1, None)))
