"""Sensitivity of the scattering fit to reflectance and AOI noise (paper section 4; figures: report.sensitivity).

A Monte Carlo of surffin's own per-pixel fit (:func:`surffin.method.scattering.fit_scattering`, the code that runs
on data): every draw of one configuration is one "pixel" of a single call. Truth R0 = 1, n = 1 (:data:`TRUTH`), so
bias, std and rmse are also relative errors; the noise levels are the paper's Table 3 (:data:`NOISE_LEVELS`), each
noise type applied alone:

- ``reflectance``: additive Gaussian noise of standard deviation sigma on the reflectance R, absolute and the same
  at every AOI (the paper's "absolute reflectance noise levels": the empirical standard deviations of the
  calibrated reflectance); with R0 = 1 it is also the noise relative to R0.
- ``aoi``: Gaussian noise of standard deviation sigma (degrees) on the AOI given to the fit, the reflectance made
  from the true AOI. The model is even in the AOI, so a noisy AOI below zero fits as its absolute value (the AOI
  estimator's arccos |v . n| is never negative).

Two cases: ``separation``, two views, one at 45 deg and the other at 44 down to 0 deg (separation 1..45 deg);
``views``, K = 2..10 views equally spaced over 0..45 deg. The fits use ``min_spread=0``, to cover the small
separations that the workflow's default minimum AOI spread (10 deg) leaves unfitted.

Each configuration draws from its own generator (:func:`configuration_rng`, seeded by the run's seed and the
configuration), so it is reproducible alone, whatever else is run, and a run with fewer draws uses the first draws
of a longer one (the noise is one (draw, view) array, drawn row by row). Statistics are over the fits that
succeeded (status 0); ``failed`` counts the others, whose optimum lies at a bound of n (status 3; under reflectance
noise the lower bound, so the successful fits of a configuration with failures are biased towards larger n and
R0). Beside them, the linearised prediction: the covariance of the least-squares estimate at the truth
(:func:`linearised_covariance`: ``sigma_R^2 (J^T J)^-1``, J the Jacobian of R in (R0, n), or its AOI analogue).
"""

from __future__ import annotations

import numbers

import numpy as np
import pandas as pd
import xarray as xr

from surffin.method.scattering import fit_scattering, scattering_model
from surffin.paper import SLOPES as PAPER_SLOPES

__all__ = [
    "TRUTH",
    "NOISE_LEVELS",
    "NOISE_UNITS",
    "CASES",
    "FIXED_VIEW_DEG",
    "SEPARATIONS_DEG",
    "SPAN_DEG",
    "VIEW_COUNTS",
    "THRESHOLD",
    "DEFAULT_DRAWS",
    "jacobian",
    "aoi_derivative",
    "linearised_covariance",
    "configuration_rng",
    "draw_fits",
    "sensitivity_table",
    "views_slopes",
    "separation_summary",
    "table_frame",
]

#: Parameters of the simulated surface (paper section 4).
TRUTH = {"R0": 1.0, "n": 1.0}
#: Paper Table 3: noise type -> level -> standard deviation (reflectance units; AOI in degrees).
NOISE_LEVELS = {"reflectance": {"min": 0.015, "max": 0.040}, "aoi": {"min": 0.27, "max": 1.70}}
#: Units of the standard deviations of :data:`NOISE_LEVELS`.
NOISE_UNITS = {"reflectance": "1", "aoi": "deg"}
#: The two cases, in the order of their seed index.
CASES = ("separation", "views")
#: AOI of the fixed view of the two-view case, degrees.
FIXED_VIEW_DEG = 45.0
#: Angular separations of the two-view case, degrees (second view at 44 .. 0 deg).
SEPARATIONS_DEG = tuple(range(1, 46))
#: AOI span of the K-view case (views equally spaced over 0 .. SPAN_DEG), degrees.
SPAN_DEG = 45.0
#: Numbers of views of the K-view case.
VIEW_COUNTS = tuple(range(2, 11))
#: Relative standard deviation asked of both parameters (the paper's "10 %").
THRESHOLD = 0.1

#: Draws per configuration unless told.
DEFAULT_DRAWS = 500

_PARAMETERS = tuple(TRUTH)
# Standard errors of the std estimate within which the Monte Carlo "agrees" with
# the linearised prediction (see separation_summary).
_AGREEMENT_ERRORS = 3.0


# --- linearised prediction ---------------------------------------------------------------------


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and bool(np.isfinite(value))


def _check_theta(theta) -> np.ndarray:
    theta = np.asarray(theta, dtype=np.float64)
    if theta.ndim != 1 or theta.size < 2 or not np.all(np.isfinite(theta)):
        raise ValueError(f"theta must be a 1-D array of at least 2 finite AOIs (radians), got {theta!r}")
    return theta


def _check_point(theta, r0, n) -> np.ndarray:
    """Theta as a checked array; R0 > 0, n > 0.5 and every view lit ((2 - 1/n) theta < 90 deg)."""
    theta = _check_theta(theta)
    if not (_is_real(r0) and r0 > 0 and _is_real(n) and n > 0.5):
        raise ValueError(f"the model needs R0 > 0 and n > 0.5, got R0 = {r0!r}, n = {n!r}")
    if np.any(np.abs((2.0 - 1.0 / n) * theta) >= 0.5 * np.pi):
        raise ValueError(f"AOIs {np.degrees(theta)} deg: (2 - 1/n) theta reaches 90 deg (no return) at n = {n}")
    return theta


def jacobian(theta, r0: float = TRUTH["R0"], n: float = TRUTH["n"]) -> np.ndarray:
    """Differentiate R = R0 cos(a theta)^n, a = 2 - 1/n, with respect to (R0, n).

    Parameters
    ----------
    theta : (view,) array, radians
    r0, n : float
        The point of the linearisation (R0 > 0, n > 0.5, every (2 - 1/n) theta
        below 90 deg).

    Returns
    -------
    (view, 2) array
        Columns dR/dR0 = cos(a theta)^n and dR/dn = R dlog/dn with
        dlog/dn = log cos(a theta) - theta tan(a theta) / n.
    """
    theta = _check_point(theta, r0, n)
    angle = (2.0 - 1.0 / n) * theta
    g = np.cos(angle) ** n
    dlog_dn = np.log(np.cos(angle)) - theta * np.tan(angle) / n
    return np.column_stack([g, r0 * g * dlog_dn])


def aoi_derivative(theta, r0: float = TRUTH["R0"], n: float = TRUTH["n"]) -> np.ndarray:
    """dR/dtheta of R = R0 cos(a theta)^n, a = 2 - 1/n.

    Parameters
    ----------
    theta : (view,) array, radians
    r0, n : float

    Returns
    -------
    (view,) array
        ``-R0 n a cos(a theta)^(n - 1) sin(a theta)``, reflectance per radian.
    """
    theta = _check_point(theta, r0, n)
    a = 2.0 - 1.0 / n
    return -r0 * n * a * np.cos(a * theta) ** (n - 1.0) * np.sin(a * theta)


def _check_noise(noise: str) -> None:
    if noise not in NOISE_LEVELS:
        raise ValueError(f"unknown noise type {noise!r}; known: {sorted(NOISE_LEVELS)}")


def _check_positive(name: str, value) -> float:
    if not _is_real(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def linearised_covariance(
    theta, noise: str, sigma: float, *, r0: float = TRUTH["R0"], n: float = TRUTH["n"]
) -> np.ndarray:
    """Covariance of (R0, n) of the least-squares fit, linearised at the truth.

    Parameters
    ----------
    theta : (view,) array, radians
        True AOI of the views (at least 2 different ones).
    noise : {"reflectance", "aoi"}
    sigma : float
        Standard deviation of the noise: reflectance units, or radians for ``aoi``.
    r0, n : float
        The truth.

    Returns
    -------
    (2, 2) array
        ``sigma^2 (J^T J)^-1`` for reflectance noise; for AOI noise each view's
        reflectance error is ``dR/dtheta * sigma`` (first order), so
        ``(J^T J)^-1 J^T diag((dR/dtheta sigma)^2) J (J^T J)^-1``.
    """
    _check_noise(noise)
    sigma = _check_positive("sigma", sigma)
    jac = jacobian(theta, r0, n)
    normal = jac.T @ jac
    if np.linalg.cond(normal) > 1e14:
        raise ValueError(f"the AOIs {np.degrees(theta)} deg do not determine R0 and n (J^T J is singular)")
    if noise == "reflectance":
        return sigma**2 * np.linalg.inv(normal)
    gain = np.linalg.solve(normal, jac.T)
    # Where the exact gain has zeros (two views, one at normal incidence: that view,
    # whose dR/dtheta is 0, alone fixes R0), solve leaves rounding (~1e-17): clear it,
    # so that a first-order std of zero comes out as zero.
    gain[np.abs(gain) < 1e-12 * np.abs(gain).max()] = 0.0
    errors = aoi_derivative(theta, r0, n) * sigma
    return (gain * errors**2) @ gain.T


# --- Monte Carlo ---------------------------------------------------------------------------------


def _check_count(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def configuration_rng(seed: int, case: str, noise: str, level: str, abscissa: int) -> np.random.Generator:
    """Return the random generator of one configuration's draws.

    Parameters
    ----------
    seed : int >= 0
        The run's seed.
    case : {"separation", "views"}
    noise : {"reflectance", "aoi"}
    level : {"min", "max"}
    abscissa : int
        Separation in degrees (``separation``) or number of views (``views``).

    Returns
    -------
    numpy.random.Generator
        ``default_rng([seed, case index, noise index, level index, abscissa])``,
        indices in the order of :data:`CASES`, :data:`NOISE_LEVELS` and its levels.
    """
    seed = _check_count("seed", seed, 0)
    if case not in CASES:
        raise ValueError(f"unknown case {case!r}; known: {list(CASES)}")
    _check_noise(noise)
    levels = list(NOISE_LEVELS[noise])
    if level not in levels:
        raise ValueError(f"unknown level {level!r} of {noise} noise; known: {levels}")
    abscissa = _check_count("abscissa", abscissa, 0)
    return np.random.default_rng(
        [seed, CASES.index(case), list(NOISE_LEVELS).index(noise), levels.index(level), abscissa]
    )


def draw_fits(theta, noise: str, sigma: float, draws: int, rng: np.random.Generator) -> xr.Dataset:
    """Fit ``draws`` noisy copies of the truth at AOIs ``theta`` with surffin's fit.

    Parameters
    ----------
    theta : (view,) array, radians
        True AOI of the views.
    noise : {"reflectance", "aoi"}
    sigma : float
        Noise standard deviation: reflectance units, or radians for ``aoi``.
    draws : int >= 1
    rng : numpy.random.Generator
        Source of the noise, drawn as one standard normal (draw, view) array.

    Returns
    -------
    Dataset
        The output of :func:`~surffin.method.scattering.fit_scattering` over dimension
        ``draw`` (min_views 2, min_spread 0).
    """
    theta = _check_theta(theta)
    _check_noise(noise)
    sigma = _check_positive("sigma", sigma)
    draws = _check_count("draws", draws, 1)
    unit = rng.standard_normal((draws, theta.size))
    reflectance = np.broadcast_to(scattering_model(theta, TRUTH["R0"], TRUTH["n"]), unit.shape)
    aoi = np.broadcast_to(theta, unit.shape)
    if noise == "reflectance":
        reflectance = reflectance + sigma * unit
    else:
        aoi = aoi + sigma * unit
    dims = ("draw", "view")
    return fit_scattering(
        xr.DataArray(reflectance, dims=dims), xr.DataArray(aoi, dims=dims), min_views=2, min_spread=0.0
    )


def _statistics(fits: xr.Dataset, theta: np.ndarray, noise: str, sigma_rad: float) -> list[dict]:
    """One row per parameter: Monte Carlo statistics, linearised prediction, fit's own sigma."""
    ok = fits["status"].values == 0
    predicted = np.sqrt(np.diag(linearised_covariance(theta, noise, sigma_rad)))
    rows = []
    for index, name in enumerate(_PARAMETERS):
        error = fits[name].values[ok] - TRUTH[name]
        sigmas = fits[f"{name}_sigma"].values[ok]
        std = float(np.std(error, ddof=1)) if error.size > 1 else np.nan
        rows.append(
            {
                "parameter": name,
                "truth": TRUTH[name],
                "bias": float(error.mean()) if error.size else np.nan,
                "std": std,
                "rmse": float(np.sqrt(np.mean(error**2))) if error.size else np.nan,
                "predicted_std": float(predicted[index]),
                "std_ratio": std / predicted[index] if predicted[index] > 0 else np.inf,
                # Two views leave no residual degree of freedom: the fit reports no sigma.
                "fit_sigma_median": float(np.median(sigmas)) if theta.size > 2 and sigmas.size else np.nan,
                "draws": int(ok.size),
                "failed": int((~ok).sum()),
            }
        )
    return rows


def _configurations():
    """(case, abscissa, separation_deg, AOIs in degrees) of every configuration."""
    for separation in SEPARATIONS_DEG:
        yield "separation", separation, float(separation), np.array([FIXED_VIEW_DEG, FIXED_VIEW_DEG - separation])
    for count in VIEW_COUNTS:
        yield "views", count, SPAN_DEG, np.linspace(0.0, SPAN_DEG, count)


_COLUMN_ATTRS = {
    "case": "separation: two views, one at 45 deg; views: K views equally spaced over 0..45 deg",
    "noise": "noise type applied alone: reflectance (absolute, on R) or aoi (added to the fit's AOI)",
    "level": "paper Table 3 level: min or max",
    "sigma": "noise standard deviation (reflectance units, or degrees for aoi; see sigma_units)",
    "sigma_units": "units of sigma",
    "separation_deg": "AOI separation of the two views, or span of the K views, degrees",
    "n_views": "number of views",
    "parameter": "fitted parameter: R0 or n",
    "truth": "true value of the parameter",
    "bias": "mean error of the successful fits",
    "std": "standard deviation (ddof 1) of the successful fits",
    "rmse": "root mean square error of the successful fits",
    "predicted_std": "linearised standard deviation from the fit covariance at the truth",
    "std_ratio": "std / predicted_std (inf where the first-order prediction is zero)",
    "fit_sigma_median": "median of the fit's own standard uncertainty (NaN with 2 views: no residual dof)",
    "draws": "Monte Carlo draws",
    "failed": "draws whose fit failed (status != 0), left out of the statistics",
}


def sensitivity_table(draws: int = DEFAULT_DRAWS, seed: int = 0) -> xr.Dataset:
    """Run the Monte Carlo of both cases, both noise types and both levels, as a tidy table.

    Parameters
    ----------
    draws : int >= 2
        Draws per configuration (the paper: 500).
    seed : int >= 0
        Seed of the run; see :func:`configuration_rng`.

    Returns
    -------
    Dataset
        One ``row`` per case x noise x level x abscissa x parameter, with the
        columns as variables (``case``, ``noise``,
        ``level``, ``sigma``, ``sigma_units``, ``separation_deg``, ``n_views``,
        ``parameter``, ``truth``, ``bias``, ``std``, ``rmse``, ``predicted_std``,
        ``std_ratio``, ``fit_sigma_median``, ``draws``, ``failed``), each with a
        ``description`` attribute.
    """
    draws = _check_count("draws", draws, 2)
    seed = _check_count("seed", seed, 0)
    rows = []
    for case, abscissa, separation, theta_deg in _configurations():
        theta = np.radians(theta_deg)
        for noise, levels in NOISE_LEVELS.items():
            for level, sigma in levels.items():
                sigma_rad = float(np.radians(sigma)) if noise == "aoi" else sigma
                rng = configuration_rng(seed, case, noise, level, abscissa)
                fits = draw_fits(theta, noise, sigma_rad, draws, rng)
                head = {
                    "case": case,
                    "noise": noise,
                    "level": level,
                    "sigma": sigma,
                    "sigma_units": NOISE_UNITS[noise],
                    "separation_deg": separation,
                    "n_views": theta.size,
                }
                rows += [head | stats for stats in _statistics(fits, theta, noise, sigma_rad)]
    table = xr.Dataset.from_dataframe(pd.DataFrame(rows).rename_axis("row"))
    for name, description in _COLUMN_ATTRS.items():
        table[name].attrs["description"] = description
    table.attrs = {
        "title": "Sensitivity of the scattering fit to reflectance and AOI noise (paper section 4)",
        "truth": dict(TRUTH),
        "seeding": "numpy.random.default_rng([seed, case, noise, level, abscissa]) per configuration",
        "fit": "surffin.method.scattering.fit_scattering, min_views 2, min_spread 0; "
        "failed: status != 0 (surffin.method.scattering.FIT_STATUS)",
    }
    return table


def table_frame(table: xr.Dataset) -> pd.DataFrame:
    """Return a table of :func:`sensitivity_table` (or :func:`views_slopes`) as a pandas DataFrame, a row each."""
    return table.to_dataframe().reset_index(drop=True)


def _loglog_slope(counts: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of log(values) on log(counts) and its standard error (NaN if undefined)."""
    if values.size < 3 or not np.all(np.isfinite(values) & (values > 0)):
        return np.nan, np.nan
    x, y = np.log(counts), np.log(values)
    (slope, _), residual, *_ = np.polyfit(x, y, 1, full=True)
    spread = np.sum((x - x.mean()) ** 2)
    stderr = np.sqrt(residual[0] / (x.size - 2) / spread) if residual.size else 0.0
    return float(slope), float(stderr)


def views_slopes(table: xr.Dataset) -> xr.Dataset:
    """Log-log slope of the std against the number of views K (case ``views``).

    Parameters
    ----------
    table : Dataset
        A :func:`sensitivity_table`.

    Returns
    -------
    Dataset
        One ``row`` per noise x level x parameter: ``slope`` and ``slope_stderr``
        (least squares of log std on log K over all K, and its standard error
        from the residuals), ``slope_from_3`` (the same over K >= 3: with two
        views one sits at 0 deg, where R has no first-order AOI sensitivity),
        ``predicted_slope`` (the same for the linearised std; NaN where it is
        zero), ``paper_slope`` (the paper's statement: -1/2 for R0, -1 for n).
    """
    frame = table_frame(table)
    frame = frame[frame["case"] == "views"]
    if frame.empty:
        raise ValueError("views_slopes: the table has no rows of case 'views'")
    rows = []
    for (noise, level, parameter), group in frame.groupby(["noise", "level", "parameter"], sort=False):
        group = group.sort_values("n_views")
        counts = group["n_views"].to_numpy(dtype=float)
        slope, stderr = _loglog_slope(counts, group["std"].to_numpy())
        from_3 = counts >= 3
        rows.append(
            {
                "noise": noise,
                "level": level,
                "sigma": group["sigma"].iloc[0],
                "parameter": parameter,
                "slope": slope,
                "slope_stderr": stderr,
                "slope_from_3": _loglog_slope(counts[from_3], group["std"].to_numpy()[from_3])[0],
                "predicted_slope": _loglog_slope(counts, group["predicted_std"].to_numpy())[0],
                "paper_slope": PAPER_SLOPES[parameter],
            }
        )
    slopes = xr.Dataset.from_dataframe(pd.DataFrame(rows).rename_axis("row"))
    slopes.attrs["title"] = "std proportional to K^slope, K = number of views over a 45 deg span"
    return slopes


def _first_of_last_run(separations: np.ndarray, good: np.ndarray) -> float:
    """Smallest separation from which ``good`` holds at every larger one (NaN if not at the largest)."""
    if not good[-1]:
        return np.nan
    bad = np.flatnonzero(~good)
    return float(separations[bad[-1] + 1] if bad.size else separations[0])


def separation_summary(table: xr.Dataset, threshold: float = THRESHOLD) -> xr.Dataset:
    """Per noise configuration and parameter: the separation needed, and where linearisation holds.

    Parameters
    ----------
    table : Dataset
        A :func:`sensitivity_table`.
    threshold : float
        Relative standard deviation asked for (default 10 %).

    Returns
    -------
    Dataset
        One ``row`` per noise x level x parameter of case ``separation``:
        ``required_separation_deg``, the smallest separation from which the
        Monte Carlo std stays below ``threshold`` at every larger separation;
        ``linear_from_deg`` / ``linear_to_deg``, the longest run of separations
        over which the Monte Carlo std agrees with the linearised one within
        3 standard errors of a std estimate (relative error 1/sqrt(2(N-1)),
        N the successful draws) and no fit failed (NaN when there is none);
        ``no_failures_from_deg``, the smallest separation from which no fit
        fails at any larger separation (failed fits are left out of the std).
    """
    threshold = _check_positive("threshold", threshold)
    frame = table_frame(table)
    frame = frame[frame["case"] == "separation"]
    if frame.empty:
        raise ValueError("separation_summary: the table has no rows of case 'separation'")
    rows = []
    for (noise, level, parameter), group in frame.groupby(["noise", "level", "parameter"], sort=False):
        group = group.sort_values("separation_deg")
        separations = group["separation_deg"].to_numpy()
        successes = (group["draws"] - group["failed"]).to_numpy()
        tolerance = _AGREEMENT_ERRORS / np.sqrt(2.0 * np.maximum(successes - 1, 1))
        agrees = (np.abs(group["std_ratio"].to_numpy() - 1.0) <= tolerance) & (group["failed"].to_numpy() == 0)
        low, high = _longest_run(agrees)
        rows.append(
            {
                "noise": noise,
                "level": level,
                "sigma": group["sigma"].iloc[0],
                "parameter": parameter,
                "required_separation_deg": _first_of_last_run(separations, group["std"].to_numpy() < threshold),
                "linear_from_deg": separations[low] if high >= low else np.nan,
                "linear_to_deg": separations[high] if high >= low else np.nan,
                "no_failures_from_deg": _first_of_last_run(separations, group["failed"].to_numpy() == 0),
            }
        )
    summary = xr.Dataset.from_dataframe(pd.DataFrame(rows).rename_axis("row"))
    summary.attrs["threshold"] = threshold
    return summary


def _longest_run(flags: np.ndarray) -> tuple[int, int]:
    """First and last index of the longest run of True in ``flags`` ((0, -1) when there is none)."""
    best, start = (0, -1), None
    for index, flag in enumerate([*flags, False]):
        if flag and start is None:
            start = index
        elif not flag and start is not None:
            if index - 1 - start > best[1] - best[0]:
                best = (start, index - 1)
            start = None
    return best
