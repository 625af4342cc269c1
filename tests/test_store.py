import json

import numpy as np
import pytest
import xarray as xr
import zarr

import surffin
from surffin.errors import StoreError
from surffin.io.store import clean_leftovers, open_store, provenance, write_store


def cube(nview=3, ny=7, nx=9, seed=0):
    rng = np.random.default_rng(seed)
    return xr.Dataset(
        {
            "a": (("view", "y", "x"), rng.random((nview, ny, nx)).astype("f4"), {"units": "1", "long_name": "a"}),
            "m": (("view", "y", "x"), rng.random((nview, ny, nx)) > 0.5),
        },
        coords={"view": [f"v{i:02d}" for i in range(nview)], "y": np.arange(10, 10 + ny), "x": np.arange(nx)},
        attrs=provenance("test", {"window": 15}, {"a.npz": {"size": 3}}),
    )


def test_round_trip_with_plain_xarray(tmp_path):
    ds = cube()
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 4, "x": 5})
    back = xr.open_zarr(path)
    xr.testing.assert_identical(back.compute(), ds)
    assert back.attrs["surffin_version"] == surffin.__version__
    assert back.attrs["surffin_parameters"] == {"window": 15}
    # chunks that do not divide the image, view never split
    assert back["a"].chunks == ((3,), (4, 3), (5, 4))
    meta = json.loads((path / "zarr.json").read_text())
    assert meta["zarr_format"] == 3 and "consolidated_metadata" in meta


def test_strings_are_variable_length(tmp_path):
    path = write_store(cube(), tmp_path / "s.zarr")
    assert str(zarr.open_group(path)["view"].dtype) != "<U3"
    assert list(xr.open_zarr(path)["view"].values) == ["v00", "v01", "v02"]


def test_floats_uncompressed_masks_compressed(tmp_path):
    group = zarr.open_group(write_store(cube(), tmp_path / "s.zarr"))
    assert group["a"].compressors == ()
    assert group["m"].compressors != ()


def test_crash_leaves_previous_store_and_no_lookalike(tmp_path, monkeypatch):
    path = write_store(cube(seed=1), tmp_path / "s.zarr")

    def explode(self, *args, **kwargs):
        raise RuntimeError("killed")

    monkeypatch.setattr(xr.Dataset, "to_zarr", explode)
    with pytest.raises(RuntimeError):
        write_store(cube(seed=2), path)
    monkeypatch.undo()
    xr.testing.assert_identical(xr.open_zarr(path).load(), cube(seed=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_leftovers_of_a_kill_are_removed_by_next_write(tmp_path):
    partial = tmp_path / ".s.zarr.partial-deadbeef"
    (partial / "a").mkdir(parents=True)
    unrelated = tmp_path / ".t.zarr.partial-deadbeef"
    unrelated.mkdir()
    write_store(cube(), tmp_path / "s.zarr")
    assert not partial.exists() and unrelated.exists()
    assert clean_leftovers(tmp_path / "t.zarr") == [unrelated]


def test_replacing_a_store(tmp_path):
    path = write_store(cube(seed=1), tmp_path / "s.zarr")
    write_store(cube(seed=2), path)
    xr.testing.assert_identical(xr.open_zarr(path).load(), cube(seed=2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_open_store_errors(tmp_path):
    with pytest.raises(StoreError, match="no zarr store"):
        open_store(tmp_path / "missing.zarr")
    path = write_store(cube(), tmp_path / "s.zarr")
    assert open_store(path, stage="test").sizes["view"] == 3
    with pytest.raises(StoreError, match="stage 'aoi'"):
        open_store(path, stage="aoi")


def test_dask_input_is_written_lazily(tmp_path):
    ds = cube().chunk({"view": -1, "y": 2, "x": 3})
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 2, "x": 3})
    xr.testing.assert_identical(xr.open_zarr(path).load(), ds.load())
