"""The relation of mean n and roughness, and the indicative roughness map (surffin.method.roughness)."""

import json

import dask.array as da
import numpy as np
import pytest
import xarray as xr

from surffin.errors import SurffinError
from surffin.io.store import open_store, write_store
from surffin.method.roughness import roughness_map, roughness_relation
from surffin.pipeline.run import run_roughness_map, run_roughness_relation

ROUGHNESS = {"S1": 0.0068, "S2": 0.05, "S3": 0.11, "S4": 0.2}


def mean_n(intercept=1.30, slope=-2.4, noise=(0.004, -0.003, 0.002, -0.001)):
    return {k: intercept + slope * r + e for (k, r), e in zip(ROUGHNESS.items(), noise)}


def test_relation_matches_polyfit_and_brute_force_leave_one_out():
    n = mean_n()
    rel = roughness_relation(n, ROUGHNESS)
    r = np.array(list(ROUGHNESS.values()))
    y = np.array(list(n.values()))
    slope, intercept = np.polyfit(r, y, 1)
    assert rel["slope"] == pytest.approx(slope, rel=1e-12)
    assert rel["intercept"] == pytest.approx(intercept, rel=1e-12)
    residual = y - (intercept + slope * r)
    assert rel["r2"] == pytest.approx(1 - (residual**2).sum() / ((y - y.mean()) ** 2).sum(), rel=1e-12)
    assert rel["residual_std"] == pytest.approx(np.sqrt((residual**2).sum() / 2), rel=1e-12)
    # leave one out: refit on the other three by polyfit and invert
    for i, name in enumerate(ROUGHNESS):
        keep = np.arange(4) != i
        s, c = np.polyfit(r[keep], y[keep], 1)
        assert rel["specimens"][name]["loo_roughness_mm"] == pytest.approx((y[i] - c) / s, rel=1e-10)
    assert rel["n_range"] == [y.min(), y.max()]


def test_exact_line_is_recovered():
    rel = roughness_relation(mean_n(noise=(0, 0, 0, 0)), ROUGHNESS)
    assert rel["slope"] == pytest.approx(-2.4) and rel["intercept"] == pytest.approx(1.30)
    assert rel["r2"] == pytest.approx(1.0) and rel["roughness_rmse_mm"] == pytest.approx(0.0, abs=1e-12)


def test_two_specimens_fix_a_line_without_a_quality():
    rel = roughness_relation({"a": 1.2, "b": 1.0}, {"a": 0.1, "b": 0.2})
    assert rel["slope"] == pytest.approx(-2.0) and rel["residual_std"] is None and rel["roughness_rmse_mm"] is None


@pytest.mark.parametrize(
    ("n", "r", "match"),
    [
        ({"a": 1.0}, {"a": 0.1}, "at least 2"),
        ({"a": 1.0, "b": 1.1}, {"a": 0.1, "c": 0.2}, "differ"),
        ({"a": 1.0, "b": np.nan}, {"a": 0.1, "b": 0.2}, "finite"),
        ({"a": 1.0, "b": 1.1}, {"a": 0.1, "b": 0.1}, "same roughness"),
    ],
)
def test_relation_refuses_what_gives_no_line(n, r, match):
    with pytest.raises(SurffinError, match=match):
        roughness_relation(n, r)


def test_given_range_is_kept():
    assert roughness_relation(mean_n(), ROUGHNESS, n_range=(0.5, 1.5))["n_range"] == [0.5, 1.5]


def test_map_inverts_the_line_and_marks_extrapolation():
    rel = roughness_relation(mean_n(noise=(0, 0, 0, 0)), ROUGHNESS)
    n = xr.DataArray(np.array([[1.30 - 2.4 * 0.05, np.nan], [1.5, 1.30 - 2.4 * 0.3]]), dims=("y", "x"))
    ds = roughness_map(n, rel)
    np.testing.assert_allclose(ds["roughness"].values, [[0.05, np.nan], [-0.2 / 2.4, 0.3]], rtol=1e-12)
    np.testing.assert_array_equal(ds["extrapolated"].values, [[False, False], [True, True]])
    lazy = roughness_map(n.chunk({"y": 1}), rel)
    assert isinstance(lazy["roughness"].data, da.Array)
    np.testing.assert_array_equal(lazy["roughness"].values, ds["roughness"].values)


def test_pipeline_writes_relation_and_map(tmp_path):
    """Specimen stores whose n follows the line give it back; the map store records the relation."""
    rng = np.random.default_rng(0)
    specimens, inside = {}, {}
    for name, r in ROUGHNESS.items():
        n = 1.30 - 2.4 * r + 0.01 * rng.standard_normal((20, 30))
        n[:2] = 5.0  # outside the roi: must not count
        inside[name] = n[2:]
        ds = xr.Dataset({"n": (("y", "x"), n)}, coords={"y": np.arange(10, 30), "x": np.arange(40, 70)})
        ds.attrs["surffin_stage"] = "features"
        write_store(ds, tmp_path / f"{name}.zarr")
        specimens[name] = {
            "store": str(tmp_path / f"{name}.zarr"),
            "roi": {"y": [12, 30], "x": [40, 70]},
            "roughness_mm": r,
        }
    out = run_roughness_relation(tmp_path / "rough" / "relation.json", specimens=specimens)
    rel = json.loads(out.read_text())
    assert rel["slope"] == pytest.approx(-2.4, rel=0.01) and rel["r2"] > 0.999
    # supported n: from the lowest 2nd to the highest 98th percentile of the specimens' roi pixels
    assert rel["n_range"] == pytest.approx([np.percentile(inside["S4"], 2), np.percentile(inside["S1"], 98)], rel=1e-12)
    store = run_roughness_map(tmp_path / "T1.zarr", features=specimens["S2"]["store"], relation=out)
    ds = open_store(store, stage="roughness")
    assert ds.attrs["surffin_parameters"]["relation"]["slope"] == rel["slope"]
    assert float(ds["roughness"][5:, :].compute().median()) == pytest.approx(0.05, abs=0.005)
