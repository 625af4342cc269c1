"""The paper comparison lines up the workflow's numbers with the paper's (surffin.reproduction)."""

import json

import pytest

from surffin.reproduction import PAPER, comparison, run_paper_comparison, to_markdown


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
    {"noise": "reflectance", "level": "max", "sigma": "0.04", "parameter": "n", "slope": "-0.29",
     "predicted_slope": "-0.24", "slope_from_3": "-0.37"},
]
SEPARATION = [{"noise": "reflectance", "level": "max", "sigma": 0.04, "parameter": "n", "required_separation_deg": 18.0}]


def by_quantity(rows):
    return {row["quantity"]: row for row in rows}


def test_rows_carry_the_numbers_of_their_sources(tmp_path):
    benchmarks = []
    for k, seconds in enumerate([1.5, 2.0, 0.5]):
        path = tmp_path / f"b{k}.tsv"
        path.write_text(f"s\th:m:s\tmax_rss\n{seconds}\t0:00:01\t100\n")
        benchmarks.append(path)
    rows = by_quantity(
        comparison(
            summary=SUMMARY, specimens=["S1", "S2", "S3", "S4"], slopes=SLOPES, separation=SEPARATION,
            relation={"r2": 0.998, "intercept": 1.3, "slope": -2.4, "roughness_rmse_mm": 0.004},
            runtime={"T1": {"views": 5, "benchmarks": benchmarks}},
        )
    )
    assert rows["T1: accuracy of label (unclassified counts as wrong)"]["surffin"] == 0.991
    assert rows["T1: accuracy of label_filtered (unclassified counts as wrong)"]["paper"] == PAPER["accuracy"]["label_filtered"]
    assert rows["n falls from the smoothest to the roughest specimen"]["surffin"] == "yes"
    assert rows["specimen of largest mean R0 (paper: rises to S3, drops for S4)"]["surffin"] == "S3"
    assert rows["slope of std against K views, n, reflectance noise 0.04"]["surffin"] == pytest.approx(-0.29)
    assert rows["separation for std < 10 %, n, reflectance noise 0.04, deg"]["paper"] == 20.0
    assert rows["linear relation of mean n and roughness: R²"]["surffin"] == 0.998
    assert rows["T1: 5 views from raw files to labels, s"]["surffin"] == pytest.approx(4.0)


def test_order_claims_can_fail():
    summary = json.loads(json.dumps(SUMMARY))
    summary["items"]["S3"]["n"]["mean"] = 1.30  # no longer falling
    rows = by_quantity(comparison(summary=summary, specimens=["S1", "S2", "S3", "S4"]))
    assert rows["n falls from the smoothest to the roughest specimen"]["surffin"] == "no"
    assert rows["relation of mean n and roughness"]["surffin"] is None


def test_markdown_table_and_file(tmp_path):
    rows = comparison(summary=SUMMARY, specimens=["S1", "S2", "S3", "S4"])
    text = to_markdown(rows)
    table = [line for line in text.splitlines() if line.startswith("| ")]
    assert len(table) == len(rows) + 2 and all(line.count(" | ") == 5 for line in table)  # header, rule, rows
    assert "Regenerate with: `snakemake --cores 2`" in text
    (tmp_path / "summary.json").write_text(json.dumps(SUMMARY))
    out = run_paper_comparison(tmp_path / "out" / "cmp.md", summary=tmp_path / "summary.json", specimens=["S1", "S2", "S3", "S4"])
    assert "| classification | T1: accuracy of label " in out.read_text()
