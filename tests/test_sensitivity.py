"""The sensitivity Monte Carlo (paper section 4): statistics, linearised prediction, slopes, outputs.

Tolerances come from the sampling error of a standard deviation estimated from
N draws: its relative standard error is ~1/sqrt(2(N - 1)) for normal errors
(3.2 % at N = 500). Statistical checks use the paper's 500 draws so that a
4-standard-error band (13 %) is still tight enough to catch a wrong prediction;
the determinism and output tests check no statistics and use few draws.
"""

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from matplotlib.image import imread
from scipy.optimize import least_squares
from scipy.stats import chi2

from surffin.analysis.sensitivity import (
    NOISE_LEVELS,
    VIEW_COUNTS,
    aoi_derivative,
    configuration_rng,
    draw_fits,
    jacobian,
    linearised_covariance,
    sensitivity_table,
    separation_summary,
    views_slopes,
)
from surffin.cli import main
from surffin.io.store import open_store
from surffin.pipeline.analyses import run_sensitivity
from surffin.report.sensitivity import OUTPUTS

DRAWS = 500
# Band of the statistical checks, in standard errors of the estimate.
BAND = 4.0
STD_ERROR = 1.0 / np.sqrt(2.0 * (DRAWS - 1))


@pytest.fixture(scope="module")
def dataset():
    return sensitivity_table(draws=DRAWS, seed=0)


@pytest.fixture(scope="module")
def table(dataset):
    return dataset.to_dataframe()


def rows(frame, **conditions):
    selected = frame
    for column, value in conditions.items():
        selected = selected[selected[column] == value]
    return selected


# --- linearised prediction against independent computations --------------------------------------


@pytest.mark.parametrize(("r0", "n"), [(1.0, 1.0), (0.7, 2.5), (1.2, 0.8)])
def test_derivatives_match_finite_differences(r0, n):
    theta = np.radians([0.0, 10.0, 25.0, 40.0])
    step = 1e-6

    def model(theta, r0, n):
        return r0 * np.cos((2.0 - 1.0 / n) * theta) ** n

    numeric = np.column_stack(
        [
            (model(theta, r0 + step, n) - model(theta, r0 - step, n)) / (2 * step),
            (model(theta, r0, n + step) - model(theta, r0, n - step)) / (2 * step),
        ]
    )
    np.testing.assert_allclose(jacobian(theta, r0, n), numeric, rtol=1e-7, atol=1e-10)
    numeric_aoi = (model(theta + step, r0, n) - model(theta - step, r0, n)) / (2 * step)
    np.testing.assert_allclose(aoi_derivative(theta, r0, n), numeric_aoi, rtol=1e-7, atol=1e-10)


def fit_exactly(reflectance, theta):
    """(R0, n) by scipy's least squares on the model written out here, started at the truth."""

    def residual(p):
        return p[0] * np.cos((2.0 - 1.0 / p[1]) * theta) ** p[1] - reflectance

    return least_squares(residual, [1.0, 1.0], xtol=1e-15, ftol=1e-15, gtol=1e-15).x


@pytest.mark.parametrize("theta_deg", [[45.0, 20.0], [45.0, 1.0], [0.0, 15.0, 30.0, 45.0], [0.0, 5.0, 45.0]])
@pytest.mark.parametrize("noise", ["reflectance", "aoi"])
def test_prediction_matches_brute_force(theta_deg, noise):
    """The covariance propagated through the fit by central differences of an independent fitter."""
    theta = np.radians(theta_deg)
    truth = np.cos(theta)
    sigma, step = 0.01, 1e-5
    gain = np.empty((2, theta.size))
    for view in range(theta.size):
        delta = np.zeros(theta.size)
        delta[view] = step
        if noise == "reflectance":
            plus, minus = fit_exactly(truth + delta, theta), fit_exactly(truth - delta, theta)
        else:
            plus, minus = fit_exactly(truth, theta + delta), fit_exactly(truth, theta - delta)
        gain[:, view] = (plus - minus) / (2 * step)
    brute = sigma**2 * gain @ gain.T
    np.testing.assert_allclose(linearised_covariance(theta, noise, sigma), brute, rtol=1e-5, atol=1e-14)


def test_aoi_prediction_is_zero_for_r0_with_a_view_at_normal_incidence():
    """Two views, one at 0 deg: that view fixes R0 and has dR/dtheta = 0, so R0's first-order std is 0."""
    covariance = linearised_covariance(np.radians([45.0, 0.0]), "aoi", np.radians(1.7))
    assert covariance[0, 0] == 0.0
    assert covariance[1, 1] > 0.0


# --- Monte Carlo against the prediction -------------------------------------------------------------


def test_monte_carlo_std_agrees_with_prediction_when_well_separated(table):
    """Separations >= 20 deg and all K under reflectance noise: every fit succeeds and the std is the
    linearised one within the band.

    Left out: R0 under AOI noise where the prediction is zero (a view at 0 deg,
    see test_second_order_where_the_prediction_is_zero) and R0 under the high
    AOI noise, whose second-order terms (1.7 deg) are not negligible (next test).
    """
    separated = table[(table["case"] == "separation") & (table["separation_deg"] >= 20)]
    aoi_r0 = (separated["noise"] == "aoi") & (separated["parameter"] == "R0")
    left_out = aoi_r0 & ((separated["level"] == "max") | (separated["predicted_std"] == 0))
    assert (separated["failed"] == 0).all()
    assert np.abs(separated.loc[~left_out, "std_ratio"] - 1.0).max() < BAND * STD_ERROR
    views = rows(table, case="views", noise="reflectance")
    assert np.abs(views["std_ratio"] - 1.0).max() < BAND * STD_ERROR


def test_linearisation_underestimates_r0_under_high_aoi_noise(table):
    """R0, AOI noise 1.7 deg, separations >= 14 deg: the Monte Carlo std is never below the linearised
    one (beyond the band) and exceeds it by more than the band somewhere: the prediction is optimistic."""
    high = rows(table, case="separation", noise="aoi", level="max", parameter="R0")
    ratio = high.loc[high["separation_deg"] >= 14, "std_ratio"]
    assert ratio.min() > 1.0 - BAND * STD_ERROR
    assert ratio.max() > 1.0 + BAND * STD_ERROR


@pytest.mark.parametrize("level", ["min", "max"])
def test_second_order_where_the_prediction_is_zero(table, level):
    """Views at 45 and 0 deg, AOI noise e: R0 = 1 / cos(e) ~ 1 + e^2 / 2, so bias sigma^2/2, std sigma^2/sqrt(2).

    e^2 is chi-square with 1 dof (kurtosis 15): the relative standard error of
    its sample std is sqrt((15 - 1) / (4 N)), 8.4 % at N = 500.
    """
    sigma = np.radians(NOISE_LEVELS["aoi"][level])
    row = rows(table, case="separation", noise="aoi", level=level, parameter="R0", separation_deg=45.0).iloc[0]
    assert row["predicted_std"] == 0.0 and row["std_ratio"] == np.inf
    error = np.sqrt(14.0 / (4 * DRAWS))
    assert row["std"] == pytest.approx(sigma**2 / np.sqrt(2.0), rel=BAND * error)
    assert row["bias"] == pytest.approx(sigma**2 / 2.0, rel=BAND * np.sqrt(2.0 / DRAWS))


def test_small_separations_fail(table):
    """Separations <= 3 deg at the high noise levels: over 10 % of the fits fail (n at its bounds), the
    std of both parameters exceeds 20 % (the paper: "tens of %"), and under reflectance noise the
    successful fits are biased upwards far beyond their standard error (the bound on n censors them)."""
    close = rows(table, case="separation", level="max")
    close = close[close["separation_deg"] <= 3]
    assert (close["failed"] > 0.1 * DRAWS).all()
    assert (close["std"] > 0.2).all()
    reflectance = rows(close, noise="reflectance")
    standard_error = reflectance["std"] / np.sqrt(reflectance["draws"] - reflectance["failed"])
    assert (reflectance["bias"] > BAND * standard_error).all()


@pytest.mark.parametrize("count", [5, 8, 10])
def test_fit_sigma_matches_prediction(table, count):
    """Reflectance noise, K views: s^2 ~ sigma^2 chi2(K - 2)/(K - 2), so the median fit sigma is the
    predicted std times sqrt(median chi2 / dof); the sample median of s has a relative standard
    error below ~1.25 / sqrt(2 dof N) (<= 2.1 % here)."""
    dof = count - 2
    expected = np.sqrt(chi2.median(dof) / dof)
    for _, row in rows(table, case="views", noise="reflectance", n_views=count).iterrows():
        assert row["fit_sigma_median"] / row["predicted_std"] == pytest.approx(
            expected, rel=BAND * 1.25 / np.sqrt(2 * dof * DRAWS)
        )


def test_fit_sigma_undefined_with_two_views(table):
    assert rows(table, n_views=2)["fit_sigma_median"].isna().all()
    assert rows(table, case="views")[lambda f: f["n_views"] > 2]["fit_sigma_median"].notna().all()


# --- slopes and summary ------------------------------------------------------------------------------


def slope_error(draws=DRAWS):
    """Standard error of the log-log slope from independent log std's (each 1/sqrt(2(N - 1)))."""
    x = np.log(np.array(VIEW_COUNTS, dtype=float))
    return 1.0 / np.sqrt(2.0 * (draws - 1)) / np.sqrt(np.sum((x - x.mean()) ** 2))


def test_r0_slope_under_reflectance_noise(dataset):
    """~1/sqrt(K) as the paper says: within the band of the linearised slope, which is near -1/2."""
    slopes = views_slopes(dataset).to_dataframe()
    for _, row in rows(slopes, noise="reflectance", parameter="R0").iterrows():
        assert row["predicted_slope"] == pytest.approx(-0.5, abs=0.05)
        assert abs(row["slope"] - row["predicted_slope"]) < BAND * slope_error()


def test_n_slope_is_not_one_over_k(dataset):
    """The paper's 1/K for n is not what the fit does: the slope is near the linearised -0.25."""
    slopes = views_slopes(dataset).to_dataframe()
    for _, row in rows(slopes, noise="reflectance", parameter="n").iterrows():
        assert abs(row["slope"] - row["predicted_slope"]) < BAND * slope_error()
        assert row["slope"] - row["paper_slope"] > 10 * slope_error()


def test_separation_summary_orders_noise_levels(dataset):
    summary = separation_summary(dataset).to_dataframe()
    needed = summary.set_index(["noise", "level", "parameter"])["required_separation_deg"]
    for noise in NOISE_LEVELS:
        for parameter in ("R0", "n"):
            assert needed[(noise, "min", parameter)] < needed[(noise, "max", parameter)]
    assert 10 <= needed[("reflectance", "max", "n")] <= 25
    assert summary["linear_from_deg"].notna().all()


# --- determinism ---------------------------------------------------------------------------------------


def test_same_seed_same_table():
    first, again, other = (sensitivity_table(draws=50, seed=seed) for seed in (7, 7, 8))
    xr.testing.assert_identical(first, again)
    assert not np.array_equal(first["std"].values, other["std"].values)


def test_each_configuration_reproducible_alone():
    """A row of the table is reproduced from its own generator, whatever else was run."""
    table = sensitivity_table(draws=50, seed=3).to_dataframe()
    row = rows(table, case="separation", noise="aoi", level="max", separation_deg=20.0, parameter="n").iloc[0]
    fits = draw_fits(
        np.radians([45.0, 25.0]), "aoi", np.radians(1.7), 50, configuration_rng(3, "separation", "aoi", "max", 20)
    )
    assert row["std"] == np.std(fits["n"].values - 1.0, ddof=1)
    shorter = draw_fits(
        np.radians([45.0, 25.0]), "aoi", np.radians(1.7), 20, configuration_rng(3, "separation", "aoi", "max", 20)
    )
    np.testing.assert_array_equal(shorter["n"].values, fits["n"].values[:20])


# --- outputs and errors --------------------------------------------------------------------------------


def test_cli_writes_the_files(tmp_path, capsys):
    out = tmp_path / "sensitivity"
    assert main(["sensitivity", "--out", str(out), "--draws", "20", "--seed", "1"]) == 0
    printed = capsys.readouterr().out
    assert "K^slope" in printed and "std < 10 %" in printed
    for name in OUTPUTS.values():
        assert (out / name).exists(), name
    stored = open_store(out / OUTPUTS["store"], stage="sensitivity").load()
    assert stored.attrs["surffin_parameters"] == {"draws": 20, "seed": 1}
    csv = pd.read_csv(out / OUTPUTS["table"])
    assert len(csv) == stored.sizes["row"] == 2 * 2 * 2 * (45 + len(VIEW_COUNTS))
    np.testing.assert_allclose(csv["std"], stored["std"].values, rtol=1e-5)
    assert set(pd.read_csv(out / OUTPUTS["slopes"])["parameter"]) == {"R0", "n"}
    for key in ("separation_figure", "views_figure"):
        assert imread(out / OUTPUTS[key]).shape[:2] == (1020, 1440)
    assert not list(out.glob(".*")), "temporary files left behind"


def test_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["sensitivity", "--out", str(tmp_path), "--draws", "1"])
    assert "minimum 2" in capsys.readouterr().err
    with pytest.raises(ValueError, match="draws"):
        run_sensitivity(tmp_path / "never", draws=1)
    assert not (tmp_path / "never").exists()
    with pytest.raises(ValueError, match="seed"):
        sensitivity_table(draws=10, seed=-1)
    with pytest.raises(ValueError, match="unknown noise"):
        linearised_covariance(np.radians([10.0, 40.0]), "intensity", 0.01)
    with pytest.raises(ValueError, match="do not determine"):
        linearised_covariance(np.radians([30.0, 30.0]), "reflectance", 0.01)
    with pytest.raises(ValueError, match="n > 0.5"):
        jacobian(np.radians([10.0, 40.0]), n=0.4)
    with pytest.raises(ValueError, match="unknown level"):
        configuration_rng(0, "views", "aoi", "medium", 3)
