"""Paper Figs. 11 and 12 and the files of a sensitivity run (:mod:`surffin.analysis.sensitivity`).

:func:`write_sensitivity` runs the Monte Carlo and writes its table (CSV and zarr store), the slopes
against the number of views and both figures into one folder (:data:`OUTPUTS`), each file atomically.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from surffin.analysis.sensitivity import (
    DEFAULT_DRAWS,
    NOISE_LEVELS,
    NOISE_UNITS,
    SEPARATIONS_DEG,
    SPAN_DEG,
    THRESHOLD,
    TRUTH,
    VIEW_COUNTS,
    sensitivity_table,
    table_frame,
    views_slopes,
)
from surffin.io.files import write_atomically
from surffin.io.store import provenance, write_store
from surffin.report.canvas import figure, save

__all__ = ["OUTPUTS", "plot_separation", "plot_views", "write_sensitivity"]

log = logging.getLogger("surffin")

_LEVEL_COLOURS = {"min": "tab:blue", "max": "tab:red"}
# The paper clips Fig. 11 at 50 %: beyond it the features are useless for classification.
_SEPARATION_YLIM = (-10.0, 50.0)


def _noise_title(noise: str) -> str:
    return "reflectance noise (AOI exact)" if noise == "reflectance" else "AOI noise (reflectance exact)"


def _level_label(noise: str, level: str, sigma: float) -> str:
    unit = "" if NOISE_UNITS[noise] == "1" else " deg"
    return f"{level} σ = {sigma:g}{unit}"


def _legend(ax, noise: str, frame: pd.DataFrame, styles: dict[str, dict], loc: str) -> None:
    """One legend entry per noise level (colour) and per drawn quantity (black line style)."""
    from matplotlib.lines import Line2D

    sigmas = frame[frame["noise"] == noise].groupby("level")["sigma"].first()
    handles = [
        Line2D([], [], color=_LEVEL_COLOURS[level], linewidth=2, label=_level_label(noise, level, sigma))
        for level, sigma in sigmas.items()
    ]
    handles += [Line2D([], [], label=label, **{"color": "black", **style}) for label, style in styles.items()]
    ax.legend(handles=handles, fontsize=8, loc=loc)


def _panels(table: xr.Dataset, case: str, abscissa: str, xlabel: str, styles: dict[str, dict], loc: str):
    """Draw a 2 x 2 figure (rows: noise types, columns: parameters) of one case's rows.

    Returns the figure, the case's rows and, per panel, ``(ax, noise, parameter,
    {level: rows sorted by abscissa})``; the panels are labelled, titled by
    letter, noise and parameter, and carry the legend of ``styles``.
    """
    frame = table_frame(table)
    frame = frame[frame["case"] == case]
    fig = figure(12.0, 8.5)
    axes = fig.subplots(2, 2, sharex=True)
    panels = []
    for row, noise in enumerate(NOISE_LEVELS):
        for column, parameter in enumerate(TRUTH):
            ax = axes[row, column]
            rows = frame[(frame["noise"] == noise) & (frame["parameter"] == parameter)]
            groups = {level: group.sort_values(abscissa) for level, group in rows.groupby("level")}
            ax.set_title(f"({'abcd'[2 * row + column]}) {parameter}, {_noise_title(noise)}", fontsize=10)
            ax.set_ylabel(f"error of {parameter} (% of truth)")
            if row == 1:
                ax.set_xlabel(xlabel)
            _legend(ax, noise, frame, styles, loc)
            panels.append((ax, noise, parameter, groups))
    return fig, frame, panels


def _draws(frame: pd.DataFrame) -> int:
    return int(frame["draws"].max()) if not frame.empty else 0


_SEPARATION_STYLES = {
    "SD (Monte Carlo)": {"linestyle": "-", "marker": "o", "markersize": 3},
    "bias": {"linestyle": "--", "linewidth": 1},
    "linearised SD": {"linestyle": ":", "linewidth": 1.8},
    "failed fits (% of draws)": {"linestyle": "-.", "linewidth": 0.8},
}
_VIEWS_STYLES = {
    "SD (Monte Carlo)": {"linestyle": "-", "marker": "o", "markersize": 4},
    "linearised SD": {"linestyle": ":", "linewidth": 1.8},
    "|bias|": {"linestyle": "none", "marker": "x", "markersize": 5},
    "K^-1/2 through K = 10": {"linestyle": (0, (4, 2)), "linewidth": 0.8, "color": "0.55"},
    "K^-1 through K = 10": {"linestyle": (0, (1, 2)), "linewidth": 0.8, "color": "0.55"},
}


def plot_separation(table: xr.Dataset, path: str | os.PathLike) -> Path:
    """Paper Fig. 11: bias and std of R0 and n against the separation of two views.

    Rows: reflectance noise, AOI noise; columns: R0, n. Per noise level the
    Monte Carlo std, bias, linearised std and the share of failed fits, all in
    % of the truth, clipped to -10..50 % (the paper clips at 50 %).

    Parameters
    ----------
    table : Dataset
        A :func:`~surffin.analysis.sensitivity.sensitivity_table`.
    path : path-like
        The image to write (written atomically).

    Returns
    -------
    Path
    """
    fig, frame, panels = _panels(
        table,
        "separation",
        "separation_deg",
        "angular separation of the two views (deg); one view at 45 deg",
        _SEPARATION_STYLES,
        "upper right",
    )
    styles = list(_SEPARATION_STYLES.values())
    for ax, _, _, groups in panels:
        for level, group in groups.items():
            x = group["separation_deg"]
            curves = (group["std"], group["bias"], group["predicted_std"], group["failed"] / group["draws"])
            for values, style in zip(curves, styles):
                ax.plot(x, 100 * values, color=_LEVEL_COLOURS[level], **style)
        ax.axhline(100 * THRESHOLD, color="0.3", linewidth=0.8)
        ax.axhline(0.0, color="0.6", linewidth=0.5)
        ax.set_ylim(*_SEPARATION_YLIM)
        ax.set_xlim(0, max(SEPARATIONS_DEG) + 1)
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"Two views: errors against separation ({_draws(frame)} draws, truth R0 = n = 1; grey line: 10 %)")
    return save(fig, path)


def plot_views(table: xr.Dataset, path: str | os.PathLike) -> Path:
    """Paper Fig. 12: std and |bias| of R0 and n against the number of views K, log-log.

    Rows: reflectance noise, AOI noise; columns: R0, n. Per noise level the
    Monte Carlo std, the linearised std (where not zero), |bias| (where within
    the axis range, which follows the std) and reference slopes K^-1/2 and K^-1
    through the Monte Carlo std at K = 10; the titles give the fitted slopes.

    Parameters
    ----------
    table : Dataset
        A :func:`~surffin.analysis.sensitivity.sensitivity_table`.
    path : path-like
        The image to write (written atomically).

    Returns
    -------
    Path
    """
    slopes = table_frame(views_slopes(table)).set_index(["noise", "level", "parameter"])["slope"]
    fig, frame, panels = _panels(
        table, "views", "n_views", f"number of views K over 0..{SPAN_DEG:g} deg", _VIEWS_STYLES, "best"
    )
    line, predicted_style, bias_style, *references = _VIEWS_STYLES.values()
    for ax, noise, parameter, groups in panels:
        for level, group in groups.items():
            colour = _LEVEL_COLOURS[level]
            k = group["n_views"].to_numpy(dtype=float)
            std = 100 * group["std"].to_numpy()
            predicted = 100 * group["predicted_std"].to_numpy()
            ax.plot(k, std, color=colour, **line)
            ax.plot(k[predicted > 0], predicted[predicted > 0], color=colour, **predicted_style)
            ax.plot(k, 100 * np.abs(group["bias"].to_numpy()), color=colour, **bias_style)
            for exponent, style in zip((-0.5, -1.0), references):
                ax.plot(k, std[-1] * (k / k[-1]) ** exponent, **style)
        shown = np.concatenate([100 * group["std"].to_numpy() for group in groups.values()])
        ax.set_ylim(0.5 * shown.min(), 2.0 * shown.max())
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(list(VIEW_COUNTS), [str(k) for k in VIEW_COUNTS])
        ax.minorticks_off()
        ax.grid(True, which="both", alpha=0.3)
        fitted = ", ".join(f"{level} {slopes[(noise, level, parameter)]:+.2f}" for level in groups)
        ax.set_title(f"{ax.get_title()}; slope {fitted}", fontsize=10)
    fig.suptitle(f"K views equally spaced over 0..45 deg: errors ({_draws(frame)} draws, truth R0 = n = 1; log-log)")
    return save(fig, path)


#: Files :func:`write_sensitivity` writes in its output folder: key -> file name.
OUTPUTS = {
    "table": "sensitivity.csv",
    "store": "sensitivity.zarr",
    "slopes": "slopes.csv",
    "separation_figure": "separation.png",
    "views_figure": "views.png",
}


def _write_csv(frame: pd.DataFrame, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, frame.to_csv(index=False, float_format="%.6g").encode("utf-8"))
    return path


def write_sensitivity(
    out_dir: str | os.PathLike, *, draws: int = DEFAULT_DRAWS, seed: int = 0, code_version: int | None = None
) -> dict[str, Path]:
    """Run the Monte Carlo and write the table, its store, the slopes and both figures.

    The workflow's job is :func:`surffin.pipeline.analyses.run_sensitivity`.

    Parameters
    ----------
    out_dir : path-like
        Output folder; the files are :data:`OUTPUTS`, each written atomically.
    draws : int >= 2
        Draws per configuration.
    seed : int >= 0
        Seed of the run (see :func:`~surffin.analysis.sensitivity.configuration_rng`).
    code_version : int, optional
        Recorded in the store's provenance (the stage table's version of the stage).

    Returns
    -------
    dict of str to Path
        The written files by the keys of :data:`OUTPUTS`.
    """
    out = Path(out_dir)
    paths = {key: out / name for key, name in OUTPUTS.items()}
    start = time.perf_counter()
    table = sensitivity_table(draws, seed)
    log.info(
        "sensitivity: %d rows (%d draws per configuration) in %.2f s",
        table.sizes["row"],
        draws,
        time.perf_counter() - start,
    )
    slopes = views_slopes(table)
    _write_csv(table_frame(table), paths["table"])
    table.attrs |= provenance("sensitivity", {"draws": draws, "seed": seed}, version=code_version)
    write_store(table, paths["store"])
    _write_csv(table_frame(slopes), paths["slopes"])
    plot_separation(table, paths["separation_figure"])
    plot_views(table, paths["views_figure"])
    log.info(
        "sensitivity: wrote %s in %s; done in %.2f s", ", ".join(OUTPUTS.values()), out, time.perf_counter() - start
    )
    return paths
