"""Figures and tables of a processed campaign, after the paper's.

One function per figure, each taking opened stores (Datasets) or dicts and writing one image file (PNG unless
the path names another format that matplotlib writes):

| function | paper | from |
| --- | --- | --- |
| :func:`plot_calibration_fit` | Fig. 9 | calibration ``sample_obs``, ``coef`` |
| :func:`plot_r2_map` | section 3.3 | calibration ``r2``, ``status`` |
| :func:`parameter_table` | Table 2 | calibration diagnostics |
| :func:`plot_wall_reflectance` | Fig. 10 | calibration ``wall_image``, ``wall_obs`` |
| :func:`plot_features` | Fig. 13 | an item's features and registered stores |
| :func:`plot_feature_space` | Fig. 14 | the training set |
| :func:`plot_labels` | Fig. 15 | a scene's labels and ingest stores |
| :func:`accuracy_table` | section 5.2 | ``summary.json`` |

Tables are pandas DataFrames; :func:`write_table` writes one as HTML or CSV. :func:`write_figures` opens the
stores and writes the files a workflow rule asks for (its job: :func:`surffin.pipeline.analyses.run_figures`).
Figures are drawn on the canvas of :mod:`surffin.report.canvas`: matplotlib Figures without pyplot, matplotlib
imported only when a figure is drawn.

Class colours are the same in every figure: the i-th class of the sorted class list (the label order of
:mod:`surffin.method.classify`) takes the i-th colour of matplotlib's ``tab10`` cycle.
"""

from __future__ import annotations

import functools
import html
import json
import logging
import os
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from surffin.grid import Roi
from surffin.method.calibration import TERMS, calibration_diagnostics, instrument_function
from surffin.method.classify import FEATURES, UNCLASSIFIED
from surffin.method.features import UNCERTAINTY, select_roi, smooth
from surffin.method.scattering import scattering_model
from surffin.paper import MEAN_R2 as PAPER_MEAN_R2
from surffin.paper import VARIABILITY_PERCENT as PAPER_VARIABILITY
from surffin.report.canvas import collector_paused, colormap, figure, message, save, subsample

__all__ = [
    "FIGURE_INPUTS",
    "FIGURE_KINDS",
    "class_colours",
    "label_overlay",
    "reference_view",
    "plot_calibration_fit",
    "plot_r2_map",
    "parameter_table",
    "plot_wall_reflectance",
    "plot_features",
    "plot_feature_space",
    "plot_labels",
    "plot_roughness",
    "accuracy_table",
    "write_table",
    "write_figures",
]

log = logging.getLogger("surffin")

#: The inputs :func:`write_figures` opens, by name.
FIGURE_INPUTS = ("calibration", "training", "summary", "features", "registered", "labels", "ingest", "roughness")
#: What :func:`write_figures` can write: output kind -> the inputs it needs.
FIGURE_KINDS = {
    "calibration_fit": ("calibration",),
    "calibration_r2": ("calibration",),
    "calibration_table": ("calibration",),
    "wall_reflectance": ("calibration",),
    "feature_space": ("training",),
    "accuracy_table": ("summary",),
    "features": ("features", "registered"),
    "labels": ("labels", "ingest"),
    "roughness": ("roughness",),
}

# Most points drawn per scatter (per class in the feature space): enough to show the
# distribution, few enough for a light PNG.
_MAX_POINTS = 4000
# Opacity of the class colours over the intensity image.
_LABEL_ALPHA = 0.6
# Colour of unclassified pixels over the intensity image (RGBA): dark, the intensity faintly visible.
_UNCLASSIFIED_COLOUR = (0.0, 0.0, 0.0, 0.8)
# Percentiles of the colour range of feature images and of the intensity background.
_RANGE = (2, 98)
# Resolution of the feature figure, dots per inch: its images 400 px wide. At the canvas's 120 dpi (480 px, a
# pixel of the paper's items each) it cost 15 % more, most of it compressing those pixels.
_FEATURE_DPI = 100
# Ticks made ahead in the feature figure's copied Axes (:func:`_empty_feature_figure`): what the colour bars'
# and the coordinates' locators give, about 4 to 8.
_TICKS_AHEAD = 8


# --- helpers ----------------------------------------------------------------------------------


def class_colours(classes: Sequence[str]) -> dict[str, tuple]:
    """Class name -> RGBA, in the order of ``classes`` (the label order)."""
    import matplotlib

    cycle = matplotlib.colormaps["tab10"]
    return {name: cycle(index % cycle.N) for index, name in enumerate(classes)}


def label_overlay(label: np.ndarray, classes: Sequence[str]) -> np.ndarray:
    """RGBA (H, W, 4) of a label image to draw over the intensity: class colours, unclassified dark, the rest clear."""
    colours = class_colours(classes)
    overlay = np.zeros((*label.shape, 4))
    overlay[label == UNCLASSIFIED] = _UNCLASSIFIED_COLOUR
    for index, name in enumerate(classes):
        overlay[label == index] = (*colours[name][:3], _LABEL_ALPHA)
    return overlay


def _robust_range(values, percentiles=_RANGE) -> tuple[float, float] | tuple[None, None]:
    """Colour limits from percentiles of the finite values (None, None when there are none)."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return None, None
    low, high = np.percentile(finite, percentiles)
    return float(low), float(high if high > low else low + 1e-12)


def _extent(da: xr.DataArray) -> tuple[float, float, float, float]:
    """Imshow extent of a (y, x) image in sensor coordinates (pixel centres on integers)."""
    x, y = da["x"].values, da["y"].values
    return x[0] - 0.5, x[-1] + 0.5, y[-1] + 0.5, y[0] - 0.5


def _linear(values: np.ndarray, norm) -> tuple:
    """Return values and a linear norm that colour them as ``values`` under ``norm``: under a LogNorm, log10.

    The same pixels (drawn nearest, the data resampled before colouring) in half the time of matplotlib's
    LogNorm. Values not positive become NaN: LogNorm masks them.
    """
    from matplotlib.colors import LogNorm, Normalize

    if not isinstance(norm, LogNorm):
        return values, norm
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(values > 0, np.log10(values), np.nan), Normalize(np.log10(norm.vmin), np.log10(norm.vmax))


def _image(
    ax,
    da: xr.DataArray,
    title: str,
    label: str,
    cmap: str,
    limits=None,
    *,
    log_scale: bool = False,
    coordinates: bool = True,
    cax=None,
):
    """Draw a (y, x) DataArray in sensor coordinates with a colour bar (logarithmic if asked and possible).

    The title notes a logarithmic scale. Without ``coordinates`` the x and y axes are hidden, their ticks and
    labels not drawn (with them they cost about 1.5 ms each, the image about 4); hidden, matplotlib does not
    even lay out their empty tick lists. The colour bar is drawn in ``cax`` if given, else in room taken from
    ``ax``.
    """
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LogNorm, Normalize

    low, high = limits if limits is not None else _robust_range(da.values)
    log_scale = log_scale and low is not None and low > 0
    norm, cmap = LogNorm(low, high) if log_scale else Normalize(low, high), colormap(cmap)
    values, linear = _linear(da.transpose("y", "x").values, norm)
    ax.imshow(
        values,
        cmap=cmap,
        norm=linear,
        extent=_extent(da),
        interpolation="nearest",
        interpolation_stage="data",  # the same pixels as colouring first, in less than half the time
    )
    # A set title position: matplotlib then does not lay out the tick labels to find the axes' top.
    ax.set_title(f"{title} (log scale)" if log_scale else title, y=1.0)
    if coordinates:
        ax.set_xlabel("sensor column x (px)")
        ax.set_ylabel("sensor row y (px)")
    else:
        ax.xaxis.set_visible(False)
        ax.yaxis.set_visible(False)
    _colorbar(ax, ScalarMappable(norm, cmap), label, cax)


def _scale_ticks(norm):
    """Return the locator and formatter of a colour scale: a few plain values (a log scale's are many, mathtext).

    Within a decade plain steps; 1 and 3 of each of a few decades; every few decades of many. The formatter
    is None for a linear scale: matplotlib's default.
    """
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FormatStrFormatter, LogLocator, MaxNLocator

    low, high = norm.vmin, norm.vmax
    if not isinstance(norm, LogNorm):
        return MaxNLocator(5), None
    if high <= 10 * low:
        locator = MaxNLocator(4)
    else:
        locator = LogLocator(subs=(1.0, 3.0)) if high <= 1000 * low else LogLocator(numticks=5)
    return locator, FormatStrFormatter("%.2g")


def _colorbar(ax, shown, label: str, cax=None) -> None:
    """Add matplotlib's colour bar of ``shown`` (a mappable) with the ticks of :func:`_scale_ticks`.

    In ``cax`` if given, else in room taken from ``ax``.
    """
    bar = ax.figure.colorbar(shown, ax=ax, cax=cax, label=label, shrink=0.9)
    locator, formatter = _scale_ticks(shown.norm)
    bar.set_ticks(locator)
    # The short axis has no ticks nor label: hidden, matplotlib does not lay out its empty tick lists.
    (bar.ax.xaxis if bar.orientation == "vertical" else bar.ax.yaxis).set_visible(False)
    if formatter is not None:
        bar.formatter = formatter
        bar.minorticks_off()


def _roi_box(ax, roi: Roi | None) -> None:
    """Outline a roi (sensor coordinates), dashed white."""
    if roi is None:
        return
    from matplotlib.patches import Rectangle

    (top, bottom), (left, right) = roi.y, roi.x
    ax.add_patch(
        Rectangle(
            (left - 0.5, top - 0.5),
            right - left,
            bottom - top,
            fill=False,
            edgecolor="white",
            linewidth=1.2,
            linestyle="--",
        )
    )


def _polar_xy(theta, radius) -> tuple:
    """Position on :func:`_polar_quadrant`'s axes of angle ``theta`` (rad, from up, clockwise) and ``radius``."""
    return radius * np.sin(theta), radius * np.cos(theta)


def _polar_quadrant(ax, r_max: float, title: str) -> None:
    """Make Cartesian axes a polar quadrant, titled: AOI 0 (up) to 90 deg (right), radius = reflectance.

    Draw the data first, at :func:`_polar_xy`: they are clipped to the quarter disc. Matplotlib's polar
    axes cost about 30 ms more per figure (a tenth of the feature figure).
    """
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Wedge
    from matplotlib.ticker import MaxNLocator

    disc = Wedge((0.0, 0.0), r_max, 0.0, 90.0, facecolor="none", edgecolor="black", linewidth=1.0)
    ax.add_patch(disc)
    for artist in (*ax.lines, *ax.collections):
        artist.set_clip_path(disc)
    radii = MaxNLocator(5, steps=[1, 2, 2.5, 5, 10]).tick_values(0.0, r_max)
    radii = radii[radii < r_max]
    arc = np.radians(np.linspace(0.0, 90.0, 91))
    angles = np.radians(np.arange(0, 91, 15))
    grid = [np.column_stack(_polar_xy(arc, radius)) for radius in radii[1:]]
    grid += [np.column_stack(_polar_xy(angle, np.array([0.0, r_max]))) for angle in angles[1:-1]]
    ax.add_collection(LineCollection(grid, colors="0.8", linewidths=0.8, zorder=0.5))
    # Labels as texts, not ticks (a tick costs about 2 ms, a text 1): the angles every 30 deg, the radii up the
    # 0 deg line.
    for angle in angles[::2]:
        ax.annotate(
            f"{np.degrees(angle):.0f}°",
            _polar_xy(angle, r_max),
            xytext=_polar_xy(angle, 12.0),
            textcoords="offset points",
            ha="center",
            va="center",
        )
    for radius in radii:
        ax.annotate(
            f"{radius:g}", (0.0, radius), xytext=(-4.0, 0.0), textcoords="offset points", ha="right", va="center"
        )
    ax.set(xlim=(0.0, r_max), ylim=(0.0, r_max), aspect="equal", xticks=[], yticks=[])
    ax.spines[:].set_visible(False)
    ax.yaxis.set_visible(False)  # no ticks nor label (the x axis has its label)
    ax.set_xlabel("reflectance R (radius) at angle of incidence θ", labelpad=8)
    ax.set_title(title, y=1.0, pad=24)  # above the label of 0 deg


def _calibration_samples(calibration: xr.Dataset, variable: str) -> bool:
    return variable in calibration and "quantity" in calibration.coords


_NO_SAMPLES = (
    "this calibration store holds no raw wall observations ({variable}); calibrations fitted by "
    "surffin since the report figures were added keep them: refit the calibration to draw this figure"
)


# --- calibration ------------------------------------------------------------------------------


def plot_calibration_fit(calibration: xr.Dataset, path: str | os.PathLike) -> Path:
    """Paper Fig. 9: the calibration fit of a few pixels.

    The fitted instrument function is a product ``f = g(d) h(theta)`` with
    ``g = A + B / d^2`` and ``h = C theta^2 + D theta + E`` (E = 1). Panels:
    the Lambert-corrected intensity ``y = I / cos(theta)`` of every wall view of
    the first sample pixel over (d, theta) with the fitted surface f (the
    paper's figure); then, for every sample pixel, each factor against its
    variable with the data divided by the other factor (``y / h`` against d,
    ``y / g`` against theta), which shows both effects and how they vary
    across the sensor.

    Parameters
    ----------
    calibration : Dataset
        A calibration store (``coef``, ``r2``, ``sample_obs`` with
        ``sample_y``/``sample_x``).
    path : path-like
        The image to write.

    Returns
    -------
    Path
        ``path``.
    """
    if not _calibration_samples(calibration, "sample_obs"):
        return message(path, "Calibration fit of sample pixels", _NO_SAMPLES.format(variable="sample_obs"))
    obs = calibration["sample_obs"].load()
    rows, columns = obs["sample_y"].values, obs["sample_x"].values
    pixels = {"y": xr.DataArray(rows, dims="sample_pixel"), "x": xr.DataArray(columns, dims="sample_pixel")}
    coef = calibration["coef"].sel(pixels).transpose("term", "sample_pixel").values
    r2 = calibration["r2"].sel(pixels).values
    distance = obs.sel(quantity="distance").values
    aoi = obs.sel(quantity="aoi").values
    corrected = obs.sel(quantity="intensity").values / np.cos(aoi)
    ok = np.isfinite(corrected)
    d_grid = np.linspace(np.nanmin(distance) * 0.97, np.nanmax(distance) * 1.03, 60)
    t_grid = np.linspace(0.0, np.nanmax(aoi) * 1.03, 60)
    fig = figure(18.0, 5.8)
    surface = fig.add_subplot(1, 3, 1, projection="3d")
    surface.set_box_aspect(None, zoom=0.82)
    first = ok[0]
    d_mesh, t_mesh = np.meshgrid(d_grid, t_grid)
    surface.plot_surface(
        d_mesh,
        np.degrees(t_mesh),
        instrument_function(coef[:, 0], d_mesh, t_mesh),
        cmap="viridis",
        alpha=0.55,
        linewidth=0,
    )
    surface.scatter(
        distance[0, first],
        np.degrees(aoi[0, first]),
        corrected[0, first],
        color="red",
        s=18,
        depthshade=False,
        label="wall views",
    )
    surface.set_xlabel("distance d (m)")
    surface.set_ylabel("AOI θ (deg)")
    surface.set_zlabel("I / cos θ (camera units)", labelpad=10)
    surface.set_title(
        f"pixel 1 (y {rows[0]}, x {columns[0]}): data and fitted f(d, θ), R² = {float(r2[0]):.4f}", fontsize=10
    )
    surface.legend(loc="upper right", fontsize=9)
    by_distance, by_angle = fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    for index in range(obs.sizes["sample_pixel"]):
        A, B, C, D, E = coef[:, index]
        g = A + B / distance[index] ** 2
        h = (C * aoi[index] + D) * aoi[index] + E
        label = f"{index + 1}: (y {rows[index]}, x {columns[index]}), R² {float(r2[index]):.4f}"
        line = by_distance.plot(d_grid, A + B / d_grid**2, linewidth=1.2, label=label)[0]
        by_distance.scatter(distance[index], corrected[index] / h, s=10, alpha=0.6, color=line.get_color())
        by_angle.plot(np.degrees(t_grid), (C * t_grid + D) * t_grid + E, linewidth=1.2, color=line.get_color())
        by_angle.scatter(np.degrees(aoi[index]), corrected[index] / g, s=10, alpha=0.6, color=line.get_color())
    by_distance.set_xlabel("distance d (m)")
    by_distance.set_ylabel("(I / cos θ) / h(θ) (camera units)")
    by_distance.set_title("distance factor g(d) = A + B/d² (lines) and data / h(θ)", fontsize=10)
    by_distance.legend(title="sample pixel", fontsize=8)
    by_angle.set_xlabel("angle of incidence θ (deg)")
    by_angle.set_ylabel("(I / cos θ) / g(d)")
    by_angle.set_title("angular factor h(θ) = Cθ² + Dθ + E (lines, E = 1) and data / g(d)", fontsize=10)
    for ax in (by_distance, by_angle):
        ax.grid(True, alpha=0.3)
    fig.suptitle("Calibration fit (eq. 5) of sample pixels to the Lambert-corrected wall intensity I / cos θ")
    return save(fig, path)


def plot_r2_map(calibration: xr.Dataset, path: str | os.PathLike) -> Path:
    """Draw the calibration's coefficient of determination per pixel, with the sample pixels of Fig. 9.

    Parameters
    ----------
    calibration : Dataset
        A calibration store (``r2``, ``status``; ``sample_y``/``sample_x`` when present).
    path : path-like

    Returns
    -------
    Path
    """
    r2 = calibration["r2"].load()
    fitted = (calibration["status"] == 0).values
    values = r2.values[fitted]
    low = float(np.percentile(values, 1)) if values.size else 0.0
    fig = figure(8.5, 6.0)
    ax = fig.add_subplot()
    mean = f"{values.mean():.4f}" if values.size else "n/a"
    _image(
        ax,
        r2,
        f"Calibration fit: R² per pixel (mean {mean}, paper {PAPER_MEAN_R2:g}; {values.size} of {fitted.size} "
        "pixels fitted, grey: none)",
        "coefficient of determination R²",
        "viridis",
        (low, 1.0),
    )
    if "sample_y" in calibration.coords:
        ys, xs = calibration["sample_y"].values, calibration["sample_x"].values
        ax.scatter(xs, ys, marker="o", s=60, facecolors="none", edgecolors="red", linewidths=1.5)
        for index, (y, x) in enumerate(zip(ys, xs)):
            ax.annotate(
                str(index + 1),
                (x, y),
                xytext=(5, 5),
                textcoords="offset points",
                color="red",
                fontsize=11,
                fontweight="bold",
            )
    ax.title.set_fontsize(10)
    return save(fig, path)


def parameter_table(calibration: xr.Dataset) -> pd.DataFrame:
    """Paper Table 2: correlation of the calibration coefficients across pixels, and their variability.

    Parameters
    ----------
    calibration : Dataset
        A calibration store (``coef``, ``r2``, ``status``).

    Returns
    -------
    DataFrame
        Rows A..E: the correlation matrix (NaN for a coefficient that does not
        vary: E in the gauge E = 1); then ``variability (%)`` (100 std / |mean|
        across the fitted pixels) and ``paper variability (%)``
        (:data:`PAPER_VARIABILITY`, in the paper's unstated gauge).
    """
    diagnostics = calibration_diagnostics(calibration[["coef", "r2", "status"]].load())
    table = pd.DataFrame(np.nan, index=[*TERMS, "variability (%)", "paper variability (%)"], columns=list(TERMS))
    varying = diagnostics["correlation_terms"]
    table.loc[varying, varying] = np.asarray(diagnostics["correlation"])
    table.loc["variability (%)"] = [diagnostics["variability_percent"][term] for term in TERMS]
    table.loc["paper variability (%)"] = [PAPER_VARIABILITY[term] for term in TERMS]
    table.index.name = "coefficient"
    table.attrs = {
        "title": "Calibration coefficients: correlation across pixels and variability (paper Table 2)",
        "notes": [
            f"{diagnostics['n_fitted']} of {diagnostics['n_pixels']} pixels fitted; mean R² "
            f"{diagnostics['mean_r2']:.4f}, median {diagnostics['median_r2']:.4f} (paper: mean {PAPER_MEAN_R2:g}).",
            "f = (A + B/d²)(C θ² + D θ + E), d in m, θ in rad, gauge E = 1: E does not vary, so its "
            "correlations are undefined (blank) and its variability is 0.",
        ],
    }
    return table


def plot_wall_reflectance(calibration: xr.Dataset, path: str | os.PathLike) -> Path:
    """Paper Fig. 10: the calibrated reflectance of the wall against the ideal Lambertian scatterer.

    Left: the deviation of the reflectance of the most perpendicular wall view
    from ``rho_wall cos(theta)`` per pixel, with ``rho_wall = 1 / scale_k`` (the
    wall's reflectance in the calibration's gauge): what the calibration
    leaves uncompensated; below it, the same smoothed with a Gaussian window
    of about 1/20 of the image, which averages the noise and leaves the
    residual systematics. Right: reflectance against AOI of random wall pixels
    of all views, on a polar plot, with ``rho_wall cos(theta)`` in red.

    Parameters
    ----------
    calibration : Dataset
        A calibration store (``wall_image``, ``wall_obs``, attr ``scale_k``).
    path : path-like

    Returns
    -------
    Path
    """
    if not (_calibration_samples(calibration, "wall_obs") and "wall_image" in calibration):
        return message(path, "Reflectance of the calibration wall", _NO_SAMPLES.format(variable="wall_obs"))
    rho = 1.0 / float(calibration.attrs["scale_k"])
    image = calibration["wall_image"].astype(np.float64).load()
    deviation = 100.0 * (image.sel(quantity="reflectance") / (rho * np.cos(image.sel(quantity="aoi"))) - 1.0)
    size = 2 * (min(deviation.shape) // 40) + 1
    fig = figure(15.0, 9.0)
    grid = fig.add_gridspec(2, 2, width_ratios=(1.0, 0.9))
    view = image.attrs.get("view", "")
    for row, (shown, title) in enumerate(
        (
            (deviation, f"wall view {view}: deviation from Lambertian, R / (ρ_wall cos θ) − 1"),
            (smooth(deviation, size), f"the same, Gaussian-smoothed {size}x{size} px: residual systematics"),
        )
    ):
        low, high = _robust_range(shown.values, (1, 99))
        limit = max(abs(low or 0.0), abs(high or 0.0)) or 1.0
        _image(fig.add_subplot(grid[row, 0]), shown, title, "deviation (%)", "RdBu_r", (-limit, limit))
    obs = calibration["wall_obs"].load()
    aoi, reflectance = obs.sel(quantity="aoi").values, obs.sel(quantity="reflectance").values
    ok = np.isfinite(aoi) & np.isfinite(reflectance)
    chosen = np.flatnonzero(ok)[subsample(int(ok.sum()), _MAX_POINTS)]
    polar = fig.add_subplot(grid[:, 1])
    polar.scatter(
        *_polar_xy(aoi[chosen], reflectance[chosen]),
        s=4,
        alpha=0.35,
        color="tab:blue",
        label=f"wall pixels ({chosen.size} of {obs.sizes['wall_sample']} samples, "
        f"{np.unique(obs['wall_view'].values).size} views)",
    )
    theta = np.radians(np.linspace(0.0, 90.0, 181))
    polar.plot(
        *_polar_xy(theta, rho * np.cos(theta)),
        color="red",
        linewidth=2,
        label=f"ideal Lambertian ρ_wall cos θ, ρ_wall = 1/k = {rho:.3f}",
    )
    top = max(rho, float(np.percentile(reflectance[chosen], 99.5)) if chosen.size else rho)
    _polar_quadrant(polar, 1.1 * top, "reflectance vs angle of incidence θ (deg) of the calibration wall")
    polar.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), fontsize=9, markerscale=4)
    fig.suptitle("Calibrated reflectance of the calibration wall against an ideal Lambertian surface")
    return save(fig, path)


# --- items and the training set ----------------------------------------------------------------


def plot_features(
    features: xr.Dataset, registered: xr.Dataset, path: str | os.PathLike, *, roi: Roi | None = None
) -> Path:
    """Paper Fig. 13: an item's feature images, their uncertainties and the reflectance samples.

    Panels: R0, n and variability on the item's reference grid (sensor
    coordinates; a specimen's roi, dashed, and its margin); the standard uncertainties of the smoothed R0
    and n (logarithmic colour scale); and the registered reflectance of all
    views against their AOI on a polar plot (pixels of the roi, or of the whole
    image), with the scattering model (eq. 3) at the median R0 and n.

    Parameters
    ----------
    features : Dataset (y, x)
        A features store (``R0``, ``n``, ``variability``, ``R0_uncertainty``,
        ``n_uncertainty``; attrs ``item``, ``kind``, ``class``). A store
        without the uncertainties (an older surffin) gets a note in their place.
    registered : Dataset (view, y, x)
        The item's registered store (``reflectance``, ``aoi``).
    path : path-like
    roi : Roi, optional
        The item's pixels (a specimen's roi).

    Returns
    -------
    Path
    """
    from matplotlib.lines import Line2D

    uncertainties = [f"{name}_uncertainty" for name in UNCERTAINTY]
    features = features[[*FEATURES, *(name for name in uncertainties if name in features)]].load()
    region = features if roi is None else select_roi(features, roi)
    panels = (
        ("R0", "R0: reflectance at normal incidence", "viridis", _RANGE, False),
        ("n", "n: scattering coefficient", "cividis", _RANGE, False),
        ("variability", "spatial reflectance variability", "inferno", (2, 99.5), True),
        *(
            (name, f"uncertainty of the smoothed {name.split('_')[0]}", "magma", (1, 99.5), True)
            for name in uncertainties
        ),
    )
    fig, boxes, axes, polar = _feature_layout(
        features.sizes["y"] / features.sizes["x"], tuple(panel[0] in features for panel in panels)
    )
    for index, ((name, title, cmap, percentiles, log_scale), (image, _), made) in enumerate(zip(panels, boxes, axes)):
        if made is None:
            left, bottom, width, height = image
            fig.text(
                left + width / 2,
                bottom + height / 2,
                f"no {name} in this features store:\nrecompute it with this surffin",
                ha="center",
                va="center",
                fontsize=11,
            )
            continue
        ax, bar = made
        _image(
            ax,
            features[name],
            title,
            f"{name} (1)",
            cmap,
            _robust_range(region[name].values, percentiles),
            log_scale=log_scale,
            coordinates=not index,  # on the first panel only: the panels share its grid
            cax=bar,
        )
        _roi_box(ax, roi)
    both = registered[["reflectance", "aoi"]]
    both = (both if roi is None else select_roi(both, roi)).load()
    # Each view's pixels by position: xarray's sel took about 0.1 ms a view and variable.
    aois, reflectances = (both[name].transpose("view", ...).values for name in ("aoi", "reflectance"))
    r_max, handles = 0.0, []
    for index, view in enumerate(both["view"].values):
        aoi, reflectance = aois[index].ravel(), reflectances[index].ravel()
        ok = np.flatnonzero(np.isfinite(aoi) & np.isfinite(reflectance))
        chosen = ok[subsample(ok.size, _MAX_POINTS // both.sizes["view"], seed=index)]
        (line,) = polar.plot(*_polar_xy(aoi[chosen], reflectance[chosen]), "o", ms=3, mew=0, alpha=0.3)
        # A marker of its own in the legend: its copies of the plotted lines (their markers deep-copied) cost
        # about 1 ms an entry.
        handles.append(
            Line2D([], [], ls="", marker="o", ms=7, mew=0, alpha=0.3, color=line.get_color(), label=f"view {view}")
        )
        if chosen.size:
            r_max = max(r_max, float(np.percentile(reflectance[chosen], 99.5)))
    r0, n = (float(np.nanmedian(region[name].values)) for name in ("R0", "n"))
    if np.isfinite(r0) and np.isfinite(n):
        theta = np.radians(np.linspace(0.0, 90.0, 181))
        handles += polar.plot(
            *_polar_xy(theta, scattering_model(theta, r0, n)),
            color="black",
            linewidth=2,
            label=f"model at median R0 = {r0:.3f},\nn = {n:.3f}",
        )
        r_max = max(r_max, r0)
    _polar_quadrant(polar, 1.1 * r_max if r_max > 0 else 1.0, "registered reflectance vs angle of incidence θ (deg)")
    polar.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.1, 1.0), fontsize=8)
    attrs = features.attrs
    what = f"specimen of class {attrs['class']}" if attrs.get("kind") == "specimen" else attrs.get("kind", "item")
    title = f"{attrs.get('item', '')} ({what}): features, smoothed {attrs.get('smoothing_size', '?')} px"
    if "uncertainty_effective_pixels" in attrs:
        title += (
            f"; uncertainties for {attrs['uncertainty_effective_pixels']:.1f} effectively independent px per window"
        )
    fig.suptitle(title)
    return save(fig, path, dpi=_FEATURE_DPI)


def _feature_layout(aspect: float, shown: tuple[bool, ...]) -> tuple:
    """Return the feature figure for images of ``aspect`` (rows / columns) before its content.

    A fixed layout (the constrained one took 0.7 of this figure's ~2 s, and the figure is drawn for every
    item), its Axes a copy of :func:`_empty_feature_figure`'s. ``shown``: whether each of the five images has
    Axes. Returns the figure, the (image, colour bar) boxes of :func:`_feature_boxes`, the (image, colour bar)
    Axes of each image (None where not shown) and the polar plot's Axes.
    """
    boxes, polar_box, size = _feature_boxes(aspect)
    fig = pickle.loads(_empty_feature_figure(shown))
    fig.set_size_inches(size)
    shown_boxes = [box for pair, show in zip(boxes, shown) if show for box in pair]
    for ax, box in zip(fig.axes, [polar_box, *shown_boxes], strict=True):
        ax.set_position(box)
    polar, *made = fig.axes
    pairs = zip(made[::2], made[1::2])
    return fig, boxes, [next(pairs) if show else None for show in shown], polar


def _feature_boxes(aspect: float) -> tuple:
    """Return the feature figure's boxes (left, bottom, width, height in figure fractions) and size (in).

    Two rows of three columns 5.15 in apart, each an image of at most 4 x 2.7 in with its colour bar right
    of it; the last a square, the polar plot, right of the radii's labels, its legend right of it. Returns the
    (image, colour bar) boxes of the five images (row by row), the polar plot's box and the figure's size.
    """
    pitch, left, bottom, gap = 5.15, 0.8, 0.5, 0.85  # inches: columns apart, margins, between the rows
    width = min(4.0, 2.7 / aspect)
    height = width * aspect
    side = min(width, height)
    size = (left + 3 * pitch + 0.6, bottom + 2 * height + gap + 0.8)
    corners = [(left + column * pitch, bottom + height + gap) for column in range(3)]
    corners += [(left + column * pitch, bottom) for column in range(2)]

    def box(x, y, w, h):
        return x / size[0], y / size[1], w / size[0], h / size[1]

    boxes = [(box(x, y, width, height), box(x + width + 0.1, y, 0.14, height)) for x, y in corners]
    return boxes, box(left + 2 * pitch + 0.45, bottom, side, side), size


@functools.cache
def _empty_feature_figure(shown: tuple[bool, ...]) -> bytes:
    """Return the feature figure with its empty Axes, pickled: each figure is a copy, sized and its Axes placed.

    Unpickling the figure takes a quarter of the time of making its 11 Axes (most of it their ticks), and
    the figure is drawn for every item. Made for square images: the items' grids differ a little in shape,
    and placing the copy's Axes costs next to nothing. The Axes: the polar plot's, then each shown image's and
    its colour bar's, in the order of the boxes of :func:`_feature_boxes`. The axes that show values (the colour bars'
    and the first image's) have :data:`_TICKS_AHEAD` ticks: matplotlib makes those it lacks when it draws, at
    about 0.5 ms each (copies of the first), and a tick's unpickling takes a seventh of that. Made with the
    matplotlib settings of the first figure: surffin changes them only while it draws
    (:data:`~surffin.report.canvas.DRAWING`).
    """
    boxes, polar, size = _feature_boxes(1.0)
    fig = figure(*size, layout=None)
    fig.add_axes(polar)
    for (image, bar), show in zip(boxes, shown):
        if show:
            fig.add_axes(image)
            fig.add_axes(bar).yaxis.get_major_ticks(_TICKS_AHEAD)
    fig.axes[1].xaxis.get_major_ticks(_TICKS_AHEAD)  # the first image's: the only one with coordinates
    fig.axes[1].yaxis.get_major_ticks(_TICKS_AHEAD)
    return pickle.dumps(fig, pickle.HIGHEST_PROTOCOL)


def plot_feature_space(training: xr.Dataset, path: str | os.PathLike) -> Path:
    """Paper Fig. 14: the training samples in feature space, coloured by class.

    Three panels: R0 against n (the paper's middle panel), and each against
    the variability (its right panel, as two projections). At most a few
    thousand samples per class are drawn; class medians are marked.

    Parameters
    ----------
    training : Dataset
        A training store (``features (sample, feature)``, ``class (sample)``, attr ``classes``).
    path : path-like

    Returns
    -------
    Path
    """
    training = training[["features", "class"]].load()
    classes = list(training.attrs.get("classes") or sorted(set(training["class"].values.tolist())))
    colours = class_colours(classes)
    values = training["features"].transpose("sample", "feature").values
    column = {name: index for index, name in enumerate(training["feature"].values.tolist())}
    labels = np.asarray(training["class"].values.tolist())
    pairs = (("n", "R0"), ("variability", "R0"), ("variability", "n"))
    names = {
        "R0": "R0 (reflectance at normal incidence)",
        "n": "n (scattering coefficient)",
        "variability": "spatial reflectance variability",
    }
    fig = figure(16.0, 5.4)
    axes = fig.subplots(1, 3)
    for seed, name in enumerate(classes):
        members = np.flatnonzero(labels == name)
        chosen = members[subsample(members.size, _MAX_POINTS, seed=seed)]
        for ax, (x_name, y_name) in zip(axes, pairs):
            x, y = values[chosen, column[x_name]], values[chosen, column[y_name]]
            ax.scatter(x, y, s=3, alpha=0.25, color=colours[name], rasterized=True)
            ax.scatter(
                np.median(values[members, column[x_name]]),
                np.median(values[members, column[y_name]]),
                s=120,
                marker="X",
                color=colours[name],
                edgecolors="black",
                linewidths=1.0,
                label=f"{name} ({members.size} px)",
            )
    for ax, (x_name, y_name) in zip(axes, pairs):
        ax.set_xlabel(names[x_name])
        ax.set_ylabel(names[y_name])
        ax.grid(True, alpha=0.3)
    axes[0].legend(title="class (median ✕)", fontsize=9)
    fig.suptitle(f"Feature space of the training specimens ({', '.join(training.attrs.get('items', []))})")
    return save(fig, path)


# --- scenes ------------------------------------------------------------------------------------


def reference_view(ds: xr.Dataset, grid: xr.DataArray) -> tuple[xr.Dataset, str]:
    """Select the reference view of a (view, y, x) store on the (y, x) pixels of ``grid``; return it and its stem."""
    view = ds.attrs.get("reference_view", ds["view"].values[0])
    return ds.sel(view=view, y=grid["y"], x=grid["x"]), str(view)


def _intensity_background(ingest: xr.Dataset, grid: xr.DataArray) -> tuple[xr.DataArray, str]:
    """Return the reference view's intensity on the pixels of ``grid``, NaN where invalid, and the view's stem."""
    reference, view = reference_view(ingest, grid)
    intensity = reference["intensity"]
    if "valid" in reference:
        intensity = intensity.where(reference["valid"])
    return intensity.astype(np.float64).load(), view


def plot_labels(
    labels: xr.Dataset, ingest: xr.Dataset, path: str | os.PathLike, *, scores: Mapping | None = None
) -> Path:
    """Paper Fig. 15: a scene's class labels over its intensity image, before and after filtering.

    Unclassified pixels (no feature, too uncertain, or unlike every class) are
    dark; the count per reason (attr ``unclassified`` of ``label``) is noted.

    Parameters
    ----------
    labels : Dataset (y, x)
        A labels store (``label``, ``label_filtered`` with CF ``flag_meanings``).
    ingest : Dataset (view, y, x)
        The scene's ingest store: the reference view's intensity is the background.
    path : path-like
    scores : mapping, optional
        The scene's entry of ``summary.json`` (``accuracy`` per variable), shown in the titles.

    Returns
    -------
    Path
    """
    from matplotlib.patches import Patch

    labels = labels[["label", "label_filtered"]].load()
    classes = labels["label"].attrs["flag_meanings"].split()
    colours = class_colours(classes)
    background, view = _intensity_background(ingest, labels["label"])
    low, high = _robust_range(background.values, (1, 99))
    accuracy = (scores or {}).get("accuracy", {})
    filtered = labels["label_filtered"].attrs
    size = filtered.get("filter_size", "?")
    titles = {
        "label": "k-NN labels",
        "label_filtered": f"after the {filtered.get('filter', '')} filter ({size}x{size} px)",
    }
    # A fixed layout: the constrained one took about a third of this figure's time.
    fig = figure(14.0, 4.6, layout=None)
    axes = fig.subplots(1, 2, gridspec_kw={"left": 0.05, "right": 0.87, "top": 0.86, "bottom": 0.14, "wspace": 0.12})
    for ax, variable in zip(axes, ("label", "label_filtered")):
        label = labels[variable]
        ax.imshow(
            background.values,
            cmap=colormap("gray", bad="black"),
            vmin=low,
            vmax=high,
            extent=_extent(label),
            interpolation="nearest",
            interpolation_stage="data",
        )
        ax.imshow(label_overlay(label.values, classes), extent=_extent(label), interpolation="nearest")
        title = titles[variable]
        if variable in accuracy:
            title += f": accuracy {100 * accuracy[variable]['accuracy']:.1f} % of {accuracy[variable]['n_scored']} px"
        ax.set_title(title, y=1.0)
    # Sensor coordinates on the first panel only: the second has its grid.
    axes[0].set_xlabel("sensor column x (px)")
    axes[0].set_ylabel("sensor row y (px)")
    axes[1].set_xticks([])
    axes[1].set_yticks([])
    handles = [Patch(facecolor=colours[name], alpha=_LABEL_ALPHA, label=name) for name in classes]
    handles.append(Patch(facecolor=_UNCLASSIFIED_COLOUR, label=f"unclassified ({UNCLASSIFIED})"))
    fig.legend(handles=handles, loc="center right", title="class")
    fig.suptitle(f"Scene {labels.attrs.get('item', '')}: class labels over the intensity of view {view}")
    reasons = labels["label"].attrs.get("unclassified")
    if reasons:
        counts = ", ".join(f"{reason.replace('_', ' ')} {count}" for reason, count in reasons.items())
        total = int((labels["label"].values == UNCLASSIFIED).sum())
        fig.supxlabel(
            f"unclassified pixels (both panels, black): {total} of {labels['label'].size}: {counts}", fontsize=9
        )
    return save(fig, path)


def plot_roughness(roughness: xr.Dataset, path: str | os.PathLike) -> Path:
    """Draw a scene's indicative roughness map beside the specimens' relation of mean n and roughness.

    Parameters
    ----------
    roughness : Dataset (y, x)
        A roughness store (:func:`surffin.method.stages.roughness_stage`); the relation
        is the one recorded in its parameters.
    path : path-like

    Returns
    -------
    Path
    """
    roughness = roughness.load()
    relation = roughness.attrs["surffin_parameters"]["relation"]
    fig = figure(13.0, 4.8)
    left, right = fig.subplots(1, 2, width_ratios=(1.6, 1))
    inside = roughness["roughness"].where(~roughness["extrapolated"])
    limits = _robust_range(inside.values)
    _image(
        left,
        inside,
        "indicative roughness (grey: outside the specimens' range of n)",
        "roughness (mm)",
        "viridis",
        limits,
    )
    left.set_xlabel("sensor column x (px)")
    left.set_ylabel("sensor row y (px)")
    specimens = relation["specimens"]
    r = np.array([v["roughness_mm"] for v in specimens.values()])
    n = np.array([v["mean_n"] for v in specimens.values()])
    right.plot(r, n, "o", color="C0")
    for name, x, y in zip(specimens, r, n):
        right.annotate(name, (x, y), textcoords="offset points", xytext=(5, 3))
    line = np.linspace(0.0, 1.1 * r.max(), 50)
    right.plot(
        line,
        relation["intercept"] + relation["slope"] * line,
        color="C3",
        label=f"n = {relation['intercept']:.3f} {relation['slope']:+.3f} r, R² {relation['r2']:.3f}",
    )
    right.set_xlabel("reference roughness r (mm)")
    right.set_ylabel("mean n of the specimen")
    right.set_title("specimens' relation (least squares)")
    right.legend(loc="best", fontsize=8)
    right.grid(alpha=0.3)
    fig.suptitle(f"Scene {roughness.attrs.get('item', '')}: roughness from n (indicative, not a measurement)")
    return save(fig, path)


def accuracy_table(summary: Mapping) -> pd.DataFrame:
    """Per scene and label variant: accuracy against the truth and the share of each class.

    Parameters
    ----------
    summary : mapping
        The content of ``summary.json``.

    Returns
    -------
    DataFrame
        Index (scene, labels) with labels ``label`` / ``label_filtered``;
        columns ``accuracy (%)`` and ``scored pixels`` (NaN without truth),
        ``<class> (%)`` for every class, ``unclassified (%)``, ``pixels``.
    """
    rows, classes = {}, []
    for scene, entry in summary.get("scenes", {}).items():
        for variable, fractions in entry["class_fractions"].items():
            score = entry.get("accuracy", {}).get(variable, {})
            classes += [name for name in fractions["fractions"] if name not in classes]
            rows[(scene, variable)] = {
                "accuracy (%)": 100.0 * score["accuracy"] if score else np.nan,
                "scored pixels": score.get("n_scored", np.nan),
                **{f"{name} (%)": 100.0 * share for name, share in fractions["fractions"].items()},
                "unclassified (%)": 100.0 * fractions["unclassified"],
                "pixels": fractions["n_pixels"],
            }
    columns = ["accuracy (%)", "scored pixels", *(f"{name} (%)" for name in classes), "unclassified (%)", "pixels"]
    table = pd.DataFrame.from_dict(rows, orient="index", columns=columns)
    table.index = pd.MultiIndex.from_tuples(list(rows), names=["scene", "labels"])
    table.attrs = {
        "title": "Classification of the scenes: accuracy and class fractions",
        "notes": [
            "accuracy: share of the pixels with a truth label whose predicted class is that label "
            "(unclassified counts as wrong); class fractions over all pixels of the scene's image.",
        ],
    }
    return table


def write_table(table: pd.DataFrame, path: str | os.PathLike) -> Path:
    """Write a table of this module as a small HTML page (``.html``) or as CSV (any other suffix).

    The HTML page carries the table's ``attrs["title"]`` and ``attrs["notes"]``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() not in (".html", ".htm"):
        table.to_csv(path, float_format="%.6g")
        return path
    title = html.escape(table.attrs.get("title", ""))
    notes = "".join(f"<p>{html.escape(note)}</p>" for note in table.attrs.get("notes", []))
    body = table.to_html(float_format=lambda value: f"{value:.2f}", na_rep="", border=0, classes="table")
    style = (
        "body{font-family:sans-serif;margin:1em}table{border-collapse:collapse}"
        "th,td{padding:4px 10px;text-align:right;border-bottom:1px solid #ddd}th{background:#f4f4f4}"
    )
    page = (
        f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{title}</title><style>{style}</style></head>'
        f"<body><h3>{title}</h3>{body}{notes}</body></html>\n"
    )
    path.write_text(page, encoding="utf-8")
    return path


# --- the requested files --------------------------------------------------------------------------


def _paths(value) -> list[str]:
    """One path or several (a snakemake named output with a list)."""
    return [value] if isinstance(value, str | os.PathLike) else [str(v) for v in value]


def write_figures(
    outputs: Mapping[str, str | os.PathLike | Sequence[str | os.PathLike]],
    inputs: Mapping[str, str | os.PathLike | None],
    *,
    roi: Roi | Mapping | None = None,
) -> list[Path]:
    """Open the stores and write the requested figures and tables.

    The workflow's job is :func:`surffin.pipeline.analyses.run_figures`. Each file is made with Python's garbage
    collector paused (:func:`~surffin.report.canvas.collector_paused`).

    Parameters
    ----------
    outputs : mapping
        Kind (a key of :data:`FIGURE_KINDS`) -> one path or a list of paths.
        Figures take the image format of each path's suffix (PNG); tables are
        written as HTML for ``.html`` and as CSV otherwise.
    inputs : mapping
        Name (of :data:`FIGURE_INPUTS`) -> path, None or left out where not
        given: ``calibration``, ``training`` (the stores), ``summary``
        (``summary.json``); ``features``, ``registered`` (one item's stores,
        kind ``features``); ``labels``, ``ingest`` (one scene's stores, kind
        ``labels``; with ``summary``, the accuracy appears in the titles);
        ``roughness`` (one scene's roughness store, kind ``roughness``).
    roi : Roi or {"y": [a, b], "x": [c, d]}, optional
        The item's roi (kind ``features``).

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ValueError
        An unknown kind or input, or a kind whose inputs are not given.
    """
    from surffin.io.store import load_store

    if unknown := set(inputs) - set(FIGURE_INPUTS):
        raise ValueError(f"unknown figure inputs {sorted(unknown)}; known: {list(FIGURE_INPUTS)}")
    given = {name: inputs.get(name) for name in FIGURE_INPUTS}
    for kind in outputs:
        if kind not in FIGURE_KINDS:
            raise ValueError(f"unknown figure kind {kind!r}; known: {sorted(FIGURE_KINDS)}")
        missing = [name for name in FIGURE_KINDS[kind] if given[name] is None]
        if missing:
            raise ValueError(f"figure {kind!r} needs {missing}")
    # Loaded whole, without dask: the figures read small stores or most of them, and dask's tasks cost
    # more than the reads.
    opened = {name: load_store(path) for name, path in given.items() if path is not None and name != "summary"}
    if given["summary"] is not None:
        opened["summary"] = json.loads(Path(given["summary"]).read_text())
    scene = opened["labels"].attrs.get("item") if "labels" in opened else None
    makers = {
        "calibration_fit": lambda path: plot_calibration_fit(opened["calibration"], path),
        "calibration_r2": lambda path: plot_r2_map(opened["calibration"], path),
        "calibration_table": lambda path: write_table(parameter_table(opened["calibration"]), path),
        "wall_reflectance": lambda path: plot_wall_reflectance(opened["calibration"], path),
        "feature_space": lambda path: plot_feature_space(opened["training"], path),
        "accuracy_table": lambda path: write_table(accuracy_table(opened["summary"]), path),
        "features": lambda path: plot_features(
            opened["features"], opened["registered"], path, roi=Roi.from_mapping(roi)
        ),
        "labels": lambda path: plot_labels(
            opened["labels"], opened["ingest"], path, scores=opened.get("summary", {}).get("scenes", {}).get(scene)
        ),
        "roughness": lambda path: plot_roughness(opened["roughness"], path),
    }
    written = []
    for kind, value in outputs.items():
        for path in _paths(value):
            with collector_paused():  # each figure apart: one figure's garbage at most waits for the collector
                written.append(makers[kind](path))
            log.info("figures: wrote %s (%s)", path, kind)
    return written
