"""One item's chain from view files to features stores, per chunk size of the stores.

Run by hand: ``python benchmarks/bench_chunks.py [--campaign DIR] [--chunks 256 512]
[--repeat 5] [--threads 1]``. Without ``--campaign`` it renders the ``paper`` preset into a
temporary folder. The calibration is fitted once; then :func:`surffin.pipeline.run.run_item` (the
five stores, written and read back as the workflow's jobs do) runs for each specimen and the
scene with each chunk size in turn, the sizes alternating so that the machine's load (it is
shared) falls on all of them alike. One warm-up round is not counted. Prints the median seconds
of a chain per chunk size and its ratio to the first size.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration, run_item

from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script

#: The workflow's AOI and feature settings (config/config.yaml).
CONFIG = parameters.read_config()
PARAMS = {"aoi": parameters.aoi_parameters(CONFIG), "features": parameters.feature_parameters(CONFIG)}


def params_of(item) -> dict:
    roi = None if item.roi is None else {"y": list(item.roi.y), "x": list(item.roi.x)}
    return {
        **PARAMS,
        "registration": {"method": "auto", "roi": roi},
        "features": {**PARAMS["features"], "roi": roi},
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign")
    parser.add_argument("--chunks", type=int, nargs="+", default=[256, 512], help="y and x chunk sizes to compare")
    parser.add_argument("--repeat", type=int, default=5, help="counted rounds")
    parser.add_argument("--threads", type=int, default=1, help="dask threads (the workflow's per-item jobs: 1)")
    args = parser.parse_args()
    logging.getLogger("surffin").setLevel(logging.WARNING)
    with paper_campaign(args.campaign) as (camp, _), tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        calibration = run_calibration(camp.path, out / "calibration.zarr", params=parameters.calibration_parameters(CONFIG))
        times = {size: [] for size in args.chunks}
        for round_ in range(args.repeat + 1):
            for size in args.chunks:
                for name, item in camp.items.items():
                    stores = {key: out / str(size) / key / f"{name}.zarr" for key in
                              ("ingest", "aoi", "reflectance", "registered", "features")}
                    start = time.perf_counter()
                    run_item(camp.path, name, stores, calibration=calibration, params=params_of(item),
                             chunks={"y": size, "x": size}, scheduler="threads", threads=args.threads)
                    if round_:
                        times[size].append(time.perf_counter() - start)
        crop = camp.crop
        print(f"run_item over {len(camp.items)} items ({crop.shape[0]} x {crop.shape[1]} crop), "
              f"threads {args.threads}, {args.repeat} rounds")
        print(f"{'chunks':>8s}{'median s':>10s}{'ratio':>8s}")
        reference = statistics.median(times[args.chunks[0]])
        for size, values in times.items():
            median = statistics.median(values)
            print(f"{size:>8d}{median:10.3f}{median / reference:8.2f}")


if __name__ == "__main__":
    main()
