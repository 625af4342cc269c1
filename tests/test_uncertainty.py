"""Calibration check of uncertainties (surffin.analysis.uncertainty) on synthetic fits with known truth."""

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from surffin.analysis.uncertainty import NORMAL_COVERAGE, coverage
from surffin.method.features import features, residual_correlation
from surffin.method.scattering import fit_scattering, scattering_model

Y0, X0 = 30, 50
"""Sensor position of the features' top-left pixel; the truth covers a larger sensor area."""
SHAPE = (150, 160)


def grid(values, y0=Y0, x0=X0, **dims):
    values = np.asarray(values)
    coords = {"y": np.arange(y0, y0 + values.shape[-2]), "x": np.arange(x0, x0 + values.shape[-1]), **dims}
    return xr.DataArray(values, dims=(*dims, "y", "x"), coords=coords)


@pytest.fixture(scope="module")
def item():
    """Features of 5 noisy views of a textured surface, and its truth on a larger sensor grid."""
    rng = np.random.default_rng(3)
    truth_shape = (SHAPE[0] + 20, SHAPE[1] + 30)
    truth = xr.Dataset(
        {
            "R0": grid(0.8 * (1 + 0.03 * rng.standard_normal(truth_shape)), y0=Y0 - 10, x0=X0 - 5),
            "n": grid(1.3 + 0.05 * rng.standard_normal(truth_shape), y0=Y0 - 10, x0=X0 - 5),
        }
    )
    local = truth.sel(y=slice(Y0, Y0 + SHAPE[0] - 1), x=slice(X0, X0 + SHAPE[1] - 1))
    view = [f"v{k}" for k in range(5)]
    theta = grid(np.deg2rad(np.array([0.0, 12, 24, 36, 48]))[:, None, None] + np.zeros((5, *SHAPE)), view=view)
    clean = scattering_model(theta.values, local["R0"].values[None], local["n"].values[None])
    reflectance = grid(clean + 0.01 * rng.standard_normal(theta.shape), view=view)
    fit = fit_scattering(reflectance, theta)
    correlation = residual_correlation(reflectance, theta, fit)
    return features(fit, grid(np.full(SHAPE, 0.01)), error_correlation=correlation), truth


def test_calibrated_uncertainties_cover_as_a_normal(item):
    feats, truth = item
    result = coverage(feats, truth)
    assert set(result) == {"R0", "n"}
    for name, entry in result.items():
        assert entry["n_pixels"] == SHAPE[0] * SHAPE[1]
        assert (entry["expected_1"], entry["expected_2"]) == pytest.approx(NORMAL_COVERAGE)
        assert NORMAL_COVERAGE == pytest.approx((0.6827, 0.9545), abs=1e-4)
        # the window pools the 3-degree-of-freedom variances of ~24 pixels into ~37 degrees of
        # freedom: Student's t with 37 covers 0.676 and 0.947
        assert entry["within_1"] == pytest.approx(0.676, abs=0.025), name
        assert entry["within_2"] == pytest.approx(0.947, abs=0.015), name
        assert entry["z_scale"] == pytest.approx(1.0, abs=0.08), name
    # the reference is the truth smoothed like the features: the texture (3 % of R0) is far
    # above the uncertainty and would otherwise count as error
    assert float(feats["R0_uncertainty"].median()) < 0.2 * 0.03 * 0.8


@pytest.mark.parametrize(("scale", "within"), [(0.5, (0.383, 0.683)), (2.0, (0.954, 1.0))])
def test_miscalibrated_uncertainties_are_exposed(item, scale, within):
    feats, truth = item
    scaled = feats.assign(R0_uncertainty=feats["R0_uncertainty"] * scale, n_uncertainty=feats["n_uncertainty"] * scale)
    for name, entry in coverage(scaled, truth).items():
        assert (entry["within_1"], entry["within_2"]) == pytest.approx(within, abs=0.03), name
        assert entry["z_scale"] == pytest.approx(1 / scale, rel=0.1), name


def test_fit_sigma_covers_as_student_t(item):
    feats, truth = item
    t3 = (2 * stats.t.cdf(1, 3) - 1, 2 * stats.t.cdf(2, 3) - 1)
    for name, entry in coverage(feats, truth, unsmoothed=True).items():
        assert (entry["expected_1"], entry["expected_2"]) == pytest.approx(t3)
        assert (entry["within_1"], entry["within_2"]) == pytest.approx(t3, abs=0.015), name


def test_mask_selects_sensor_pixels(item):
    feats, truth = item
    mask = xr.zeros_like(truth["R0"], dtype=bool)
    mask.loc[{"y": slice(Y0, Y0 + 9), "x": slice(X0 + 100, X0 + 119)}] = True
    result = coverage(feats, truth, mask=mask)
    assert result["n"]["n_pixels"] == 10 * 20
    empty = coverage(feats, truth, mask=mask & False)
    assert empty["R0"] == {
        "n_pixels": 0,
        "within_1": None,
        "within_2": None,
        "expected_1": None,
        "expected_2": None,
        "z_scale": None,
    }


def test_coverage_errors(item):
    feats, truth = item
    with pytest.raises(ValueError, match="n_uncertainty"):
        coverage(feats.drop_vars("n_uncertainty"), truth)
    with pytest.raises(ValueError, match="n_views"):
        coverage(feats.drop_vars("n_views"), truth, unsmoothed=True)
    with pytest.raises(ValueError, match="truth lacks"):
        coverage(feats, truth.drop_vars("n"))
    with pytest.raises(ValueError, match="truth does not cover"):
        coverage(feats, truth.isel(y=slice(20, None)))
