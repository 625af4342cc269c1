"""Figures of the calibration diagnostics (:mod:`surffin.analysis.diagnostics`).

:func:`plot_correlation` draws correlation matrices of the calibration
coefficients side by side (paper Table 2), :func:`plot_repeatability` the
estimates with one calibration against those with another;
:func:`calibration_figures` draws both for a
:class:`~surffin.analysis.diagnostics.CalibrationReport`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from surffin.analysis.diagnostics import CalibrationReport, coefficients, relative_difference
from surffin.method.calibration import TERMS
from surffin.report.canvas import colormap, figure, message, save, subsample

if TYPE_CHECKING:
    from surffin.grid import Roi

__all__ = [
    "CORRELATION_FIGURE",
    "REPEATABILITY_FIGURE",
    "plot_correlation",
    "plot_repeatability",
    "calibration_figures",
]

#: File names of the figures of :func:`calibration_figures` in its folder.
CORRELATION_FIGURE = "calibration_correlation.png"
REPEATABILITY_FIGURE = "calibration_repeatability.png"
# Most points drawn per scatter panel.
_MAX_POINTS = 4000


def plot_correlation(tables: Mapping[str, Mapping], path: str | os.PathLike) -> Path:
    """Heat maps of correlation matrices of the calibration coefficients (paper Table 2), side by side.

    Parameters
    ----------
    tables : mapping
        Panel title -> ``{"terms": [...], "matrix": [[...]]}``; terms absent
        from a matrix (E in the gauge E = 1) are drawn grey.
    path : path-like
        The image to write.

    Returns
    -------
    Path
    """
    # A fixed layout, in inches (the constrained one took about a third of this figure's time): the colour bar
    # in the right margin
    width, height = 3.9 * len(tables) + 1.2, 4.6
    fig = figure(width, height, layout=None)
    margins = {"left": 0.35 / width, "right": 1 - 1.2 / width, "bottom": 0.4 / height, "top": 1 - 0.75 / height}
    axes = fig.subplots(1, len(tables), squeeze=False, gridspec_kw={**margins, "wspace": 0.1})[0]
    for ax, (title, table) in zip(axes, tables.items()):
        full = np.full((len(TERMS), len(TERMS)), np.nan)
        index = [TERMS.index(term) for term in table["terms"]]
        full[np.ix_(index, index)] = np.asarray(table["matrix"], dtype=np.float64)
        shown = ax.imshow(full, cmap=colormap("RdBu_r"), vmin=-1.0, vmax=1.0)
        for (row, column), value in np.ndenumerate(full):
            if np.isfinite(value):
                colour = "white" if abs(value) > 0.6 else "black"
                ax.text(column, row, f"{value:.2f}", ha="center", va="center", fontsize=9, color=colour)
        ax.set_xticks(range(len(TERMS)), TERMS)
        ax.set_yticks(range(len(TERMS)), TERMS)
        ax.set_title(title, fontsize=10)
    box = axes[-1].get_position()
    bar = fig.add_axes((box.x1 + 0.3 / width, box.y0 + 0.075 * box.height, 0.18 / width, 0.85 * box.height))
    fig.colorbar(shown, cax=bar, label="correlation across pixels")
    fig.suptitle(
        "Correlation of the calibration coefficients of f = (A + B/d²)(Cθ² + Dθ + E) (paper Table 2; "
        "grey: E = 1 does not vary)"
    )
    return save(fig, path)


def _scatter_panel(ax, title: str, groups: Mapping[str, tuple], names: tuple[str, str], scale=None) -> None:
    """Second estimates against first of each group (subsampled), a 1:1 line, the pooled median |difference|.

    ``scale`` as in :func:`surffin.analysis.diagnostics.relative_difference`.
    """
    x_all = np.concatenate([np.ravel(x) for x, _ in groups.values()])
    y_all = np.concatenate([np.ravel(y) for _, y in groups.values()])
    for label, (x, y) in groups.items():
        x, y = np.ravel(x), np.ravel(y)
        finite = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
        shown = finite[subsample(finite.size, _MAX_POINTS // len(groups))]
        ax.scatter(x[shown], y[shown], s=4, alpha=0.4, label=label)
    finite = np.isfinite(x_all) & np.isfinite(y_all)
    if finite.any():
        low, high = np.percentile(np.concatenate([x_all[finite], y_all[finite]]), (0.5, 99.5))
        ax.plot([low, high], [low, high], color="red", linewidth=1)
        ax.set_xlim(low, high)
        ax.set_ylim(low, high)
    median = relative_difference(x_all, y_all, scale)["median_abs_percent"]
    ax.set_title(title if median is None else f"{title}\nmedian |relative difference| {median:.3g} %", fontsize=10)
    ax.set_xlabel(f"with the {names[0]} calibration")
    ax.set_ylabel(f"with the {names[1]} calibration")
    ax.grid(True, alpha=0.3)
    if len(groups) > 1:
        ax.legend(fontsize=8, markerscale=3)


def plot_repeatability(
    first: xr.Dataset,
    second: xr.Dataset,
    specimens: Mapping[str, Mapping[str, xr.Dataset]],
    names: tuple[str, str],
    path: str | os.PathLike,
    *,
    region: Roi | None = None,
) -> Path:
    """Plot the second calibration's estimates against the first's: coefficients A..D and the specimens' R0, n.

    Parameters
    ----------
    first, second : Dataset
        The two calibrations (``coef``).
    specimens : mapping
        Of :func:`surffin.analysis.diagnostics.process_specimens`, with both calibrations.
    names : (str, str)
        Keys of the two calibrations in ``specimens``.
    path : path-like
    region : Roi, optional
        Sensor pixels of the coefficients drawn; default: all.

    Returns
    -------
    Path
    """
    # A fixed layout (the constrained one took about half of this figure's time): room for tick labels of up to
    # 6 characters left of each panel, and for the two-line titles
    fig = figure(15.0, 9.5, layout=None)
    margins = {"left": 0.06, "right": 0.983, "bottom": 0.053, "top": 0.92, "wspace": 0.25, "hspace": 0.27}
    axes = fig.subplots(2, 3, gridspec_kw=margins).ravel()
    a, b = coefficients(first, region), coefficients(second, region)
    for index, term in enumerate(TERMS[:4]):
        scale = 0.5 * (np.nanmean(a[index]) + np.nanmean(b[index]))
        _scatter_panel(axes[index], f"coefficient {term}, per pixel", {"pixels": (a[index], b[index])}, names, scale)
    for ax, feature in zip(axes[4:], ("R0", "n")):
        if not specimens:
            ax.set_axis_off()
            ax.text(0.5, 0.5, f"no specimens: no {feature} to compare", ha="center", va="center")
            continue
        groups = {
            item: (runs[names[0]][feature].values, runs[names[1]][feature].values) for item, runs in specimens.items()
        }
        _scatter_panel(ax, f"specimens' {feature} (smoothed, roi pixels)", groups, names)
    fig.suptitle(
        f"Repeatability: estimates with the {names[1]} calibration against those with the {names[0]} (red: equal)"
    )
    return save(fig, path)


def calibration_figures(diagnostics: CalibrationReport, folder: str | os.PathLike) -> list[Path]:
    """Draw the figures of calibration diagnostics in a folder.

    Parameters
    ----------
    diagnostics : CalibrationReport
        Of :func:`surffin.analysis.diagnostics.calibration_report`.
    folder : path-like
        Where :data:`CORRELATION_FIGURE` (heat maps: the calibration, the
        repeat, the truth, the paper) and :data:`REPEATABILITY_FIGURE` (scatter
        plots, or a note saying why there are none) are written.

    Returns
    -------
    list of Path
        The two figures.
    """
    folder = Path(folder)
    written = [plot_correlation(diagnostics.correlations, folder / CORRELATION_FIGURE)]
    if "repeat" not in diagnostics.calibrations:
        written.append(
            message(
                folder / REPEATABILITY_FIGURE,
                "Repeatability of the calibration",
                f"no repeatability: {diagnostics.report['repeatability']['reason']}",
            )
        )
    else:
        written.append(
            plot_repeatability(
                diagnostics.calibrations["first"],
                diagnostics.calibrations["repeat"],
                diagnostics.specimens,
                ("first", "repeat"),
                folder / REPEATABILITY_FIGURE,
                region=diagnostics.region,
            )
        )
    return written
