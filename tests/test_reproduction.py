"""The paper comparison lines up the workflow's numbers with the paper's (surffin.analysis.reproduction)."""

import json

import pytest

from surffin.analysis.reproduction import (
    ORIGINS,
    comparison,
    to_markdown,
)
from surffin.paper import ACCURACY
from surffin.paper import CALIBRATION as CALIBRATION_PAPER
from surffin.pipeline.analyses import run_paper_comparison
from surffin.simulate.presets import PRESETS


def stats(mean, std):
    return {"mean": mean, "std": std, "median": mean, "n_pixels": 100}


SUMMARY = {
    "items": {
        "S1": {"R0": stats(0.80, 0.008), "n": stats(1.28, 0.02), "variability": stats(0.03, 0.01)},
        "S2": {"R0": stats(0.86, 0.009), "n": stats(1.24, 0.02), "variability": stats(0.03, 0.01)},
        "S3": {"R0": stats(0.92, 0.009), "n": stats(1.18, 0.02), "variability": stats(0.03, 0.01)},
        "S4": {"R0": stats(0.81, 0.009), "n": stats(0.95, 0.02), "variability": stats(0.03, 0.01)},
    },
    "scenes": {"T1": {"accuracy": {"label": {"accuracy": 0.991}, "label_filtered": {"accuracy": 0.999}}}},
}
SLOPES = [
    {
        "noise": "reflectance",
        "level": "max",
        "sigma": "0.04",
        "parameter": "n",
        "slope": "-0.29",
        "predicted_slope": "-0.24",
        "slope_from_3": "-0.37",
    },
]
SEPARATION = [
    {"noise": "reflectance", "level": "max", "sigma": 0.04, "parameter": "n", "required_separation_deg": 18.0}
]
RELATION = {"r2": 0.998, "intercept": 1.3, "slope": -2.4, "roughness_rmse_mm": 0.004}


def percent(value):
    return {"median_abs_percent": value}


CORRELATION = [[1.0, 0.40, 0.23, -0.24], [0.40, 1.0, 0.41, -0.38], [0.23, 0.41, 1.0, -0.97], [-0.24, -0.38, -0.97, 1.0]]
DIAGNOSTICS = {
    "paper": CALIBRATION_PAPER,
    "calibrations": {
        "first": {
            "fit": {"mean_r2": 0.999},
            "variability_percent": {"plain": dict(zip("ABCDE", (8.2, 5.8, 47.6, 181.0, 0.0)))},
            "correlation": {"terms": ["A", "B", "C", "D"], "matrix": CORRELATION},
            "calibration_set": {"wall": "calibration/wall"},
        }
    },
    "wall_features": [
        {"calibration": "first", "views": 105, "views_in_fit": 105, "R0": {"std": 0.002}, "n": {"std": 0.015}}
    ],
    "repeatability": {
        "available": True,
        "coefficients": {term: percent(1.0) for term in "ABCDE"},
        "calibration": percent(0.85),
        "wall": [{"wall": "calibration/wall", "reflectance": percent(0.6), "R0": percent(0.45), "n": percent(1.35)}],
        "specimens": {"R0": percent(0.15), "n": percent(0.65)},
    },
}


def by_quantity(rows):
    return {row["quantity"]: row for row in rows}


def every_row():
    """Rows of every kind: calibration, sensitivity, features, roughness, classification, runtime."""
    return comparison(
        summary=SUMMARY,
        specimens=["S1", "S2", "S3", "S4"],
        diagnostics=DIAGNOSTICS,
        slopes=SLOPES,
        separation=SEPARATION,
        relation=RELATION,
        runtime={"T1": {"views": 5, "seconds": 4.0}},
    )


def test_rows_carry_the_numbers_of_their_sources():
    rows = by_quantity(every_row())
    assert rows["T1: accuracy of label (unclassified counts as wrong)"]["surffin"] == 0.991
    assert rows["T1: accuracy of label_filtered (unclassified counts as wrong)"]["paper"] == ACCURACY["label_filtered"]
    assert rows["n falls from the smoothest to the roughest specimen"]["surffin"] == "yes"
    assert rows["specimen of largest mean R0 (paper: rises to S3, drops for S4)"]["surffin"] == "S3"
    assert rows["slope of std against K views, n, reflectance noise 0.04"]["surffin"] == pytest.approx(-0.29)
    assert rows["separation for std < 10 %, n, reflectance noise 0.04, deg"]["paper"] == 20.0
    assert rows["linear relation of mean n and roughness: R²"]["surffin"] == 0.998
    assert rows["T1: 5 views from raw files to labels, s"]["surffin"] == pytest.approx(4.0)
    assert rows["correlation C-D (Table 2)"]["surffin"] == -0.97


def test_every_row_says_where_its_number_comes_from():
    rows = every_row()
    assert {row["section"] for row in rows} == {
        "calibration",
        "sensitivity",
        "features",
        "roughness",
        "classification",
        "runtime",
    }
    assert all(row["origin"] in ORIGINS for row in rows)
    assert {row["origin"] for row in rows} == set(ORIGINS)


@pytest.mark.parametrize(
    ("quantity", "preset_input"),
    [
        ("n falls from the smoothest to the roughest specimen", "n = 1.30 - 2.4 roughness_mm"),
        ("specimen of largest mean R0 (paper: rises to S3, drops for S4)", "R0 = 0.80, 0.86, 0.92, 0.81"),
        ("S3: mean R0, n (relative std R0, n %)", "R0 = 0.80, 0.86, 0.92, 0.81"),
        ("linear relation of mean n and roughness: R²", "roughness_mm of Table 4"),
        ("variability across the image, % (A, B, C, D, E)", "coef_variability = Table 2's"),
        ("correlation C-D (Table 2)", "coef_variability = Table 2's"),
    ],
)
def test_rows_echoing_a_preset_input_are_by_construction(quantity, preset_input):
    row = by_quantity(every_row())[quantity]
    assert row["origin"] == "by construction"
    assert preset_input in row["note"]


@pytest.mark.parametrize(
    "quantity",
    [
        "T1: accuracy of label (unclassified counts as wrong)",
        "T1: accuracy of label_filtered (unclassified counts as wrong)",
        "T1: 5 views from raw files to labels, s",
        "slope of std against K views, n, reflectance noise 0.04",
        "separation for std < 10 %, n, reflectance noise 0.04, deg",
        "mean R² over the crop's pixels",
        "std of n on the calibration wall",
        "repeatability: wall reflectance, median |difference| %",
        "leave-one-out error of the roughness from n, mm",
    ],
)
def test_measured_rows_are_not_by_construction(quantity):
    assert by_quantity(every_row())[quantity]["origin"] == "measured"


def test_the_preset_inputs_the_notes_name_are_the_papers():
    """What the "by construction" notes say the ``paper`` preset took from the paper is what it holds."""
    preset = PRESETS["paper"]
    assert [(s.name, s.roughness_mm, s.material.R0) for s in preset.specimens] == [
        ("S1", 0.0068, 0.80),
        ("S2", 0.0255, 0.86),
        ("S3", 0.0532, 0.92),
        ("S4", 0.1459, 0.81),
    ]
    assert [s.material.n for s in preset.specimens] == pytest.approx(
        [1.30 - 2.4 * s.roughness_mm for s in preset.specimens]
    )
    assert preset.coef_variability == pytest.approx(
        [CALIBRATION_PAPER["variability_percent"][t] / 100 for t in "ABCDE"]
    )
    C, D = preset.coef_mean[2:4]
    assert C < 0 < D


def test_order_claims_can_fail():
    summary = json.loads(json.dumps(SUMMARY))
    summary["items"]["S3"]["n"]["mean"] = 1.30  # no longer falling
    rows = by_quantity(comparison(summary=summary, specimens=["S1", "S2", "S3", "S4"]))
    assert rows["n falls from the smoothest to the roughest specimen"]["surffin"] == "no"
    assert rows["relation of mean n and roughness"]["surffin"] is None


def test_markdown_table_and_file(tmp_path):
    rows = every_row()
    text = to_markdown(rows)
    table = [line for line in text.splitlines() if line.startswith("| ")]
    assert len(table) == len(rows) + 2 and all(line.count(" | ") == 6 for line in table)  # header, rule, rows
    assert table[0] == "| section | quantity | paper | surffin | origin | source | note |"
    assert [line.split(" | ")[4] for line in table[2:]] == [row["origin"] for row in rows]
    for origin, meaning in ORIGINS.items():
        assert f"- **{origin}**: {meaning}." in text
    assert "Regenerate with: `snakemake --cores 2`" in text
    (tmp_path / "summary.json").write_text(json.dumps(SUMMARY))
    out = run_paper_comparison(
        tmp_path / "out" / "cmp.md", summary=tmp_path / "summary.json", specimens=["S1", "S2", "S3", "S4"]
    )
    assert "| classification | T1: accuracy of label " in out.read_text()


def test_the_runtime_sums_the_scene_jobs_logged_times(tmp_path):
    (tmp_path / "summary.json").write_text(json.dumps(SUMMARY))
    logs = []
    for k, seconds in enumerate([1.5, 2.0, 0.5]):
        logs.append(tmp_path / f"job{k}.log")
        logs[-1].write_text(
            f"2026-11-27 02:00:00,000 INFO aoi: inputs\n2026-11-27 02:00:01,000 INFO job done in {seconds} s\n"
        )

    def runtime_row():
        runtime = {"T1": {"views": 5, "logs": logs}}
        out = run_paper_comparison(
            tmp_path / "cmp.md", summary=tmp_path / "summary.json", specimens=["S1"], runtime=runtime
        )
        return next(line for line in out.read_text().splitlines() if line.startswith("| runtime |"))

    assert runtime_row().startswith("| runtime | T1: 5 views from raw files to labels, s | 300 | 4 |")
    logs[1].write_text("2026-11-27 02:00:00,000 ERROR job failed\n")  # a job that did not finish: not measured
    assert runtime_row().startswith("| runtime | T1: 5 views from raw files to labels, s | 300 | n/a |")
