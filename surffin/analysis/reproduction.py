"""Every quantitative claim of the paper beside surffin's number for the same quantity.

:func:`comparison` reads what the workflow wrote (``summary.json``, the calibration
diagnostics, the sensitivity analysis, the roughness relation, the scenes' job times)
and returns one row per claim: the paper's value, surffin's, and where
surffin's comes from, and its origin (:data:`ORIGINS`): whether surffin's value
echoes an input the simulator's ``paper`` preset took from the paper, which is no
evidence for the paper's claim, or is measured. :func:`write_comparison`
writes them as a Markdown table (``paper-comparison.md``), the generated half of
``docs/paper-reproduction.md``; the paper's numbers are :mod:`surffin.paper`'s.
Nothing here computes science: it only reads and lines up numbers, so that a
rerun of the workflow regenerates the table.
"""

from __future__ import annotations

import csv
import json
import logging
import os
from collections.abc import Mapping, Sequence
from itertools import pairwise
from pathlib import Path

from surffin.io.files import write_text
from surffin.paper import (
    ACCURACY,
    FEATURE_SPAN_PERCENT,
    RUNTIME_S,
    RUNTIME_VIEWS,
    SEPARATION_DEG,
    SLOPES,
    VARIABILITY_PERCENT,
)

__all__ = ["ORIGINS", "COMPARISON_INPUTS", "comparison", "write_comparison", "to_markdown"]

log = logging.getLogger("surffin")

_BUILT, _MEASURED = "by construction", "measured"
#: What the ``origin`` column of a row says (the table's legend), for the synthetic
#: ``paper`` campaign, the workflow's default; on a real camera's campaign every row is measured.
ORIGINS = {
    _BUILT: (
        "surffin's value recovers what the simulator's `paper` preset put in, and the preset took that input "
        "from the paper (the note names it): agreement shows that the pipeline recovers its input, not that the "
        "paper's claim holds"
    ),
    _MEASURED: (
        "the simulator was given neither the value nor inputs that fix it: it comes out of the pipeline (in the "
        "sensitivity section, out of surffin's fit in a Monte Carlo) under the paper's acquisition design and "
        "noise levels, which the preset copies"
    ),
}
#: The inputs of the ``paper`` preset (``surffin/simulate/presets.py``) that the rows of origin
#: "by construction" echo: taken from the paper, except coef_mean (the paper gives no means).
_PRESET = {
    "n": "n = 1.30 - 2.4 roughness_mm",
    "R0": "R0 = 0.80, 0.86, 0.92, 0.81 for S1..S4",
    "roughness": "roughness_mm of Table 4",
    "variability": (
        f"coef_variability = Table 2's ({', '.join(f'{value:g}' for value in VARIABILITY_PERCENT.values())} %)"
    ),
    "correlation": (
        "coef_variability = Table 2's, coef_mean C < 0 < D; in the fit's gauge E = 1 (A E, B E, C/E, D/E) the "
        "true coefficients share E's variation, which makes them correlate with Table 2's signs and C-D near -1"
    ),
}
_TERMS = ("A", "B", "C", "D", "E")
#: The workflow's outputs :func:`write_comparison` reads, by name.
COMPARISON_INPUTS = ("summary", "diagnostics", "sensitivity", "slopes", "relation")
_SENSITIVITY = "snakemake --cores 2 sensitivity (or: surffin sensitivity --out DIR)"
_DIAGNOSTICS = "snakemake --cores 2 calibration_diagnostics"
_MAIN = "snakemake --cores 2"


def _row(section: str, quantity: str, paper, surffin, source: str, command: str, origin: str, note: str = "") -> dict:
    return {
        "section": section,
        "quantity": quantity,
        "paper": paper,
        "surffin": surffin,
        "source": source,
        "command": command,
        "origin": origin,
        "note": note,
    }


def _note(*parts: str) -> str:
    return "; ".join(part for part in parts if part)


def _preset(*inputs: str) -> str:
    """Return the note naming the ``paper`` preset's inputs (keys of ``_PRESET``) a row echoes."""
    return "preset: " + ", ".join(_PRESET[name] for name in inputs)


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, str):
        return value
    return f"{value:.{digits}g}"


def _calibration_rows(diag: Mapping) -> list[dict]:
    paper = diag["paper"]
    first = diag["calibrations"]["first"]
    src = "diagnostics/calibration.json"
    rows = [
        _row(
            "calibration",
            "mean R² over the crop's pixels",
            paper["mean_r2"],
            first["fit"]["mean_r2"],
            src,
            _DIAGNOSTICS,
            _MEASURED,
            "the simulator renders eq. 5 exactly, without the real camera's residual systematics",
        ),
        _row(
            "calibration",
            "variability across the image, % (A, B, C, D, E)",
            ", ".join(_fmt(paper["variability_percent"][t]) for t in _TERMS),
            ", ".join(_fmt(first["variability_percent"]["plain"][t]) for t in _TERMS),
            src,
            _DIAGNOSTICS,
            _BUILT,
            _note(_preset("variability"), "plain 100 std/|mean|; E = 1 is the fit's gauge, so E does not vary here"),
        ),
    ]
    ours = first["correlation"]
    index = {t: i for i, t in enumerate(ours["terms"])}
    for a, b in (("C", "D"), ("A", "B"), ("A", "C"), ("A", "D"), ("B", "C"), ("B", "D")):
        theirs = paper["correlation"]["matrix"][_TERMS.index(a)][_TERMS.index(b)]
        rows.append(
            _row(
                "calibration",
                f"correlation {a}-{b} (Table 2)",
                theirs,
                ours["matrix"][index[a]][index[b]],
                src,
                _DIAGNOSTICS,
                _BUILT,
                _preset("correlation"),
            )
        )
    own = [w for w in diag["wall_features"] if w["calibration"] == "first" and w["views_in_fit"] == w["views"]]
    for name in ("R0", "n"):
        value = own[0][name]["std"] if own else None
        rows.append(
            _row(
                "calibration",
                f"std of {name} on the calibration wall",
                paper["wall_feature_std"][name],
                value,
                src,
                _DIAGNOSTICS,
                _MEASURED,
                "per-pixel fit over the wall views the calibration was fitted to",
            )
        )
    rep = diag["repeatability"]
    expected = paper["repeatability_percent"]
    if not rep["available"]:
        rows.append(
            _row(
                "calibration",
                "repeatability of two calibration sets",
                "see below",
                None,
                src,
                _DIAGNOSTICS,
                _MEASURED,
                rep["reason"],
            )
        )
        return rows
    rows += [
        _row(
            "calibration",
            "repeatability: coefficients, median |difference| % (A, B, C, D)",
            f"< {_fmt(expected['coefficients'])}",
            ", ".join(_fmt(rep["coefficients"][t]["median_abs_percent"]) for t in _TERMS[:4]),
            src,
            _DIAGNOSTICS,
            _MEASURED,
        ),
        _row(
            "calibration",
            "repeatability: instrument function k f, median |difference| %",
            "n/a",
            rep["calibration"]["median_abs_percent"],
            src,
            _DIAGNOSTICS,
            _MEASURED,
        ),
    ]
    wall = next(w for w in rep["wall"] if w["wall"] == diag["calibrations"]["first"]["calibration_set"]["wall"])
    rows.append(
        _row(
            "calibration",
            "repeatability: wall reflectance, median |difference| %",
            expected["reflectance"],
            wall["reflectance"]["median_abs_percent"],
            src,
            _DIAGNOSTICS,
            _MEASURED,
        )
    )
    for name in ("R0", "n"):
        rows.append(
            _row(
                "calibration",
                f"repeatability: {name} on the wall / on the specimens, median |difference| %",
                expected[name],
                f"{_fmt(wall[name]['median_abs_percent'])} / {_fmt(rep['specimens'][name]['median_abs_percent'])}",
                src,
                _DIAGNOSTICS,
                _MEASURED,
            )
        )
    return rows


def _read_table(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _number(text) -> float | None:
    """Read a CSV cell as a number; None where it is empty (NaN written by pandas)."""
    return float(text) if text not in ("", None) else None


def _sensitivity_rows(slopes: Sequence[Mapping], separation: Sequence[Mapping]) -> list[dict]:
    rows = []
    for row in slopes:
        rows.append(
            _row(
                "sensitivity",
                f"slope of std against K views, {row['parameter']}, {row['noise']} noise {row['sigma']}",
                SLOPES[row["parameter"]],
                _number(row["slope"]),
                "sensitivity/slopes.csv",
                _SENSITIVITY,
                _MEASURED,
                f"linearised {_fmt(_number(row['predicted_slope']), 2)}; "
                f"K >= 3 only: {_fmt(_number(row['slope_from_3']), 2)}",
            )
        )
    for row in separation:
        paper = SEPARATION_DEG if (row["noise"], row["level"]) == ("reflectance", "max") else "n/a"
        rows.append(
            _row(
                "sensitivity",
                f"separation for std < 10 %, {row['parameter']}, {row['noise']} noise {row['sigma']}, deg",
                paper,
                float(row["required_separation_deg"]),
                "sensitivity/sensitivity.zarr",
                _SENSITIVITY,
                _MEASURED,
                "paper: 'about 20 deg or more' at the high reflectance noise" if paper != "n/a" else "",
            )
        )
    return rows


def _feature_rows(summary: Mapping, specimens: Sequence[str]) -> list[dict]:
    items = summary["items"]
    rows = []
    for name in specimens:
        stats = items[name]
        spans = {f: 100 * stats[f]["std"] / stats[f]["mean"] for f in ("R0", "n")}
        rows.append(
            _row(
                "features",
                f"{name}: mean R0, n (relative std R0, n %)",
                "see Fig. 14",
                f"{_fmt(stats['R0']['mean'])}, {_fmt(stats['n']['mean'])} "
                f"({_fmt(spans['R0'], 2)}, {_fmt(spans['n'], 2)})",
                "summary.json",
                _MAIN,
                _BUILT,
                _note(
                    _preset("R0", "n"),
                    f"paper: span within a specimen ~{FEATURE_SPAN_PERCENT['R0']:g} % R0, "
                    f"~{FEATURE_SPAN_PERCENT['n']:g} % n",
                ),
            )
        )
    n = [items[s]["n"]["mean"] for s in specimens]
    r0 = [items[s]["R0"]["mean"] for s in specimens]
    rows.append(
        _row(
            "features",
            "n falls from the smoothest to the roughest specimen",
            "yes",
            "yes" if all(a > b for a, b in pairwise(n)) else "no",
            "summary.json",
            _MAIN,
            _BUILT,
            _preset("n", "roughness"),
        )
    )
    peak = r0.index(max(r0))
    rows.append(
        _row(
            "features",
            "specimen of largest mean R0 (paper: rises to S3, drops for S4)",
            specimens[2] if len(specimens) > 2 else "n/a",
            specimens[peak],
            "summary.json",
            _MAIN,
            _BUILT,
            _preset("R0"),
        )
    )
    return rows


def _classification_rows(summary: Mapping) -> list[dict]:
    rows = []
    for scene, result in summary["scenes"].items():
        for var in ("label", "label_filtered"):
            accuracy = result.get("accuracy", {}).get(var)
            rows.append(
                _row(
                    "classification",
                    f"{scene}: accuracy of {var} (unclassified counts as wrong)",
                    ACCURACY[var],
                    None if accuracy is None else accuracy["accuracy"],
                    "summary.json",
                    _MAIN,
                    _MEASURED,
                    "the classes lie as far apart as the preset's R0 and n put them"
                    if accuracy is not None
                    else "no truth for this scene",
                )
            )
    return rows


def _roughness_rows(relation: Mapping | None) -> list[dict]:
    if relation is None:
        return [
            _row(
                "roughness",
                "relation of mean n and roughness",
                "nearly linear",
                None,
                "roughness/relation.json",
                _MAIN,
                _BUILT,
                _note("fewer than two specimens carry roughness_mm", _preset("n")),
            )
        ]
    return [
        _row(
            "roughness",
            "linear relation of mean n and roughness: R²",
            "nearly linear",
            relation["r2"],
            "roughness/relation.json",
            _MAIN,
            _BUILT,
            _note(
                f"n = {_fmt(relation['intercept'], 4)} {relation['slope']:+.4g} roughness_mm", _preset("n", "roughness")
            ),
        ),
        _row(
            "roughness",
            "leave-one-out error of the roughness from n, mm",
            "n/a",
            relation["roughness_rmse_mm"],
            "roughness/relation.json",
            _MAIN,
            _MEASURED,
            "the preset's n is exactly linear in roughness, so this is the pipeline's error of mean n over the slope, "
            "not the relation's scatter",
        ),
    ]


def _runtime_rows(runtime: Mapping[str, Mapping]) -> list[dict]:
    rows = []
    for scene, spec in runtime.items():
        rows.append(
            _row(
                "runtime",
                f"{scene}: {spec['views']} views from raw files to labels, s",
                RUNTIME_S,
                spec["seconds"],
                f"logs/*/{scene}.log",
                _MAIN,
                _MEASURED,
                f"paper: ~5 min for {RUNTIME_VIEWS} views; here the wall times of its jobs (ingest to labels) summed",
            )
        )
    return rows


def comparison(
    *,
    summary: Mapping,
    specimens: Sequence[str],
    diagnostics: Mapping | None = None,
    slopes: Sequence[Mapping] = (),
    separation: Sequence[Mapping] = (),
    relation: Mapping | None = None,
    runtime: Mapping[str, Mapping] | None = None,
) -> list[dict]:
    """Rows of paper claims beside surffin's numbers.

    Parameters
    ----------
    summary : mapping
        ``summary.json``.
    specimens : sequence of str
        Specimen names from the smoothest to the roughest (the paper's S1..S4 order).
    diagnostics : mapping, optional
        ``diagnostics/calibration.json``.
    slopes, separation : sequence of mapping
        Rows of the sensitivity analysis' slopes and separation summary.
    relation : mapping, optional
        ``roughness/relation.json``; None when no relation was fitted.
    runtime : mapping, optional
        Scene -> ``{"views": int, "seconds": float or None}``: the wall time of its jobs from its
        view files to its labels, summed (None: not measured).

    Returns
    -------
    list of dict
        ``section``, ``quantity``, ``paper``, ``surffin``, ``source``, ``command``, ``origin``
        (a key of :data:`ORIGINS`: by construction where surffin's value echoes an input the
        simulator's ``paper`` preset took from the paper, named in the note; measured otherwise)
        and ``note``.
    """
    rows = _calibration_rows(diagnostics) if diagnostics is not None else []
    rows += _sensitivity_rows(slopes, separation)
    rows += _feature_rows(summary, specimens)
    rows += _roughness_rows(relation)
    rows += _classification_rows(summary)
    rows += _runtime_rows(runtime or {})
    return rows


def to_markdown(rows: Sequence[Mapping]) -> str:
    """Format the rows as a Markdown table, one section after the other, with the legend of the origins."""
    columns = ("section", "quantity", "paper", "surffin", "origin", "source", "note")
    cells = {"paper": _fmt, "surffin": _fmt, "source": lambda value: f"`{value}`"}
    lines = ["| " + " | ".join(columns) + " |", "| " + " | ".join("---" for _ in columns) + " |"]
    for row in rows:
        text = (cells.get(key, str)(row[key]) for key in columns)
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in text) + " |")
    legend = [
        "The origin column, for the synthetic `paper` campaign (on a real camera's campaign every row is measured):",
        "",
    ]
    legend += [f"- **{origin}**: {meaning}." for origin, meaning in ORIGINS.items()]
    commands = sorted({row["command"] for row in rows})
    return "\n".join([*lines, "", *legend, "", "Regenerate with: " + "; ".join(f"`{c}`" for c in commands), ""])


def write_comparison(
    output: str | os.PathLike,
    inputs: Mapping[str, str | os.PathLike | None],
    *,
    specimens: Sequence[str],
    runtime: Mapping[str, Mapping] | None = None,
) -> Path:
    """Write ``paper-comparison.md`` from the workflow's outputs (see :func:`comparison`).

    The workflow's job is :func:`surffin.pipeline.analyses.run_paper_comparison`.

    Parameters
    ----------
    output : path-like
        Written atomically.
    inputs : mapping
        Name (of :data:`COMPARISON_INPUTS`) -> path, None or left out where not
        given: ``summary`` (``summary.json``, required), ``diagnostics``
        (``diagnostics/calibration.json``), ``sensitivity`` (the sensitivity
        store: its separation summary is recomputed from the table), ``slopes``
        (its slopes CSV), ``relation`` (``roughness/relation.json``).
    specimens, runtime
        As for :func:`comparison`.

    Returns
    -------
    Path
        ``output``.

    Raises
    ------
    ValueError
        An unknown input, or no ``summary``.
    """
    if unknown := set(inputs) - set(COMPARISON_INPUTS):
        raise ValueError(f"unknown comparison inputs {sorted(unknown)}; known: {list(COMPARISON_INPUTS)}")
    if inputs.get("summary") is None:
        raise ValueError("the paper comparison needs the summary (summary.json)")
    summary, diagnostics, sensitivity, slopes, relation = (inputs.get(name) for name in COMPARISON_INPUTS)
    separation = []
    if sensitivity is not None:
        from surffin.analysis.sensitivity import separation_summary
        from surffin.io.store import open_store

        frame = separation_summary(open_store(sensitivity, stage="sensitivity").load()).to_dataframe()
        separation = frame.reset_index().to_dict("records")
    rows = comparison(
        summary=json.loads(Path(summary).read_text()),
        specimens=specimens,
        diagnostics=None if diagnostics is None else json.loads(Path(diagnostics).read_text()),
        slopes=_read_table(slopes) if slopes is not None else (),
        separation=separation,
        relation=None if relation is None else json.loads(Path(relation).read_text()),
        runtime=runtime,
    )
    log.info("paper comparison: %d rows", len(rows))
    header = (
        "# surffin beside the paper (generated by surffin.analysis.reproduction; see docs/paper-reproduction.md)\n\n"
    )
    return write_text(output, header + to_markdown(rows))
