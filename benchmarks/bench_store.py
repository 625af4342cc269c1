"""Writing an item's stores: ``write_store`` against zarr's file store, per stage.

Run by hand: ``python benchmarks/bench_store.py [--campaign DIR] [--items S1 T1] [--repeat 7]``.
Without ``--campaign`` it renders the ``paper`` preset into a temporary folder. Each item's chain runs
once (``bench_chunks.run_chain``) and its stores are read into memory, as a stage's result is. Then each
store is written in turn by :func:`~surffin.io.store.write_store` and, as the reference, by
``Dataset.to_zarr`` straight into zarr's file store with the same encoding (what ``write_store`` did before
it encoded Datasets in memory), the two alternating so that the machine's load (it is shared) falls on
both alike; one warm-up round is not counted. Prints per store the median milliseconds of each and the
ratio reference / ``write_store``, and both stores' files compared byte for byte.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import time
import warnings
from pathlib import Path

import xarray as xr
from bench_chunks import calibrated_campaign, quiet_logs, run_chain

from surffin.io.store import DEFAULT_CHUNKS, open_store, write_store


def file_store_write(ds, path: Path) -> None:
    """Write the reference: ``to_zarr`` into zarr's file store, ``ds`` as plain xarray reads a store (encoding kept)."""
    shutil.rmtree(path, ignore_errors=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        ds.to_zarr(path, mode="w-", zarr_format=3, consolidated=True)


def files(root: Path) -> dict[str, bytes]:
    """Every file of a store by its relative path."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def main():
    """Write each store both ways and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered campaign")
    parser.add_argument("--items", nargs="+", default=["S1", "T1"], help="items whose stores are written")
    parser.add_argument("--repeat", type=int, default=7, help="counted rounds")
    args = parser.parse_args()
    quiet_logs()
    with calibrated_campaign(args.campaign) as (camp, out, calibration):
        datasets = {}
        for name in args.items:
            stores, _ = run_chain(camp, name, out / "chain", calibration)
            for stage, path in stores.items():
                # write_store takes a stage's result (attributes decoded); the reference, the store as read
                datasets[f"{stage} {name}"] = (open_store(path).load(), xr.open_zarr(path, chunks=None).load())
        times = {key: ([], []) for key in datasets}
        for round_ in range(args.repeat + 1):
            for key, pair in datasets.items():
                for kind, (write, ds) in enumerate(zip((write_store, file_store_write), pair)):
                    start = time.perf_counter()
                    write(ds, out / "bench" / f"{kind}.zarr")
                    if round_:
                        times[key][kind].append(time.perf_counter() - start)
                if not round_:
                    same = files(out / "bench" / "0.zarr") == files(out / "bench" / "1.zarr")
                    print(f"{key}: the two stores' files {'are' if same else 'are NOT'} byte-identical")
        print(f"store writes (chunks {DEFAULT_CHUNKS}), median ms over {args.repeat} rounds")
        print(f"{'store':>20s}{'MB':>7s}{'write_store':>13s}{'file store':>12s}{'ratio':>8s}")
        for key, (new, old) in times.items():
            new, old = statistics.median(new) * 1e3, statistics.median(old) * 1e3
            print(f"{key:>20s}{datasets[key][0].nbytes / 1e6:7.1f}{new:13.1f}{old:12.1f}{old / new:8.2f}")


if __name__ == "__main__":
    main()
