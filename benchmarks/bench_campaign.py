"""Campaign scale: specimens per minute, memory per job, start-up share; one cube 10x a frame.

Run by hand: ``python benchmarks/bench_campaign.py [--specimens 10 50] [--variants default ...]
[--cubes 480x640 1600x1920] [--workdir DIR]`` (about 15 minutes on 2 cores with the defaults,
each further variant adds its campaign runs). Prints tables; nothing is written inside the
repository.

Campaigns
---------
Each campaign is the ``paper`` preset scaled to N reference specimens with
:func:`surffin.simulate.presets.scaled_preset` (the four plaster classes repeated, each
specimen with its own textures, place and poses; the scene T1 keeps one specimen of each
class) and a smaller wall set (5 distances x 4 tilts = 20 views instead of 105) so that
rendering and the calibration stay quick. It is rendered first (not timed), then processed
with ``snakemake --cores 2`` and the repository's default configuration.

- **specimens per minute** = N / wall time of the snakemake command (from its start to its
  exit: parsing, DAG, every job, bookkeeping).
- **peak memory per job** = ``max_rss`` of the job's benchmark TSV (snakemake's
  ``benchmark:`` files under the logs folder), median and maximum per rule.
- **where the wall time goes**: the budget is ``cores x wall`` core-seconds. Each job holds
  ``threads`` cores for ``s`` seconds (benchmark TSV). Of that, the *stage time* is what the
  stage itself logged as its work (``<stage> done in X s`` of :func:`surffin.pipeline.run.run_stage`
  and ``run_ingest``, ``item <name> done in X s`` of ``run_item``: opening inputs, computing,
  writing the stores); the rest of ``s`` is *job start-up*: the new Python process, snakemake's
  script preamble, imports, and exit. Rules that do not log a total (calibration, training,
  summary, figures) are charged the median start-up of the jobs that do, in the same run. What
  the jobs do not hold is *idle*: snakemake parsing the workflow and validating the campaign,
  building the DAG, and its bookkeeping between jobs.
  **overhead** = (start-up + idle) / budget = 1 - stage time / budget; **no-overhead
  spec/min** = spec/min / (stage share), the rate if only the stages' own work took time (with
  the same threads per job). A no-op start-up (a process importing snakemake's script support,
  ``surffin.pipeline.run``, ``dask.array`` and ``zarr``) is printed beside it as a floor.
- **first use**: the logged stage time still holds one-off costs of a fresh process (modules
  imported on first use, first zarr open, dask's first graph). Each per-item stage of the first
  campaign's first specimen (and its scene's labels) is rerun twice in a fresh process from the
  parameters and inputs recorded in its store; first minus second call is that cost. **overhead
  incl. first use** also charges every job the median of it.
- ``--variants`` runs each campaign also with other settings, to measure the defaults against
  them: ``item stages 2 threads`` (``--set-threads``: one per-item stage at a time, with two
  dask threads; the defaults run them at one thread, two jobs at once), ``ilp scheduler``
  (snakemake's ILP job scheduler instead of the greedy one of ``profiles/default``), ``chunks
  256`` (the former default chunks, 256 x 256, against 512 x 512), ``item jobs`` (config
  ``jobs: item``: one job per item from view files to features), ``item jobs, scene
  figures`` (the same with ``item_figures: scenes``: no feature figure per specimen) and
  ``item batches, scene figures`` (the same with ``item_batches: 8``: the specimens' chains in
  8 batch jobs, reported as rule ``item_batch``).

Targets: >= 30 specimens/min, overhead <= 50 %, peak memory per job <= 1 GB and not growing
with N.

One large cube
--------------
A synthetic (view, y, x) = (5, H, W) cube (reflectance float64 from the scattering model with
noise, AOI float32) is written as a store with chunks (view -1, 256, 256); a fresh process then
runs :func:`surffin.method.scattering.fit_scattering`, :func:`surffin.method.features.variability` and
:func:`surffin.method.features.features` (Gaussian smoothing) from it and writes the features store,
under the threads scheduler with 2 workers. Peak RSS is the process's high-water mark (VmHWM);
the baseline is that mark after the imports. Bounded memory means the increment grows far
less than the cube (1600 x 1920 is 10x a 480 x 640 camera frame, 3200 x 3840 40x): the chunks
in flight, and the band of chunk rows the neighbourhood filters need, whose size follows the
image width.

The machine is shared: wall times move with other jobs' load (printed with each run), so
read ratios; memory is not affected.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORES = 2
#: Per-item stages: the rules the ``item stages 2 threads`` variant runs at two threads.
ITEM_STAGES = ("aoi", "reflectance", "registration", "features", "labels")
#: Variants of a campaign run: name -> (extra snakemake arguments, config overrides). The
#: overrides go through a config file: ``--config`` would pass nested numbers as strings.
VARIANTS = {
    "default": ((), {}),
    "item stages 2 threads": (("--set-threads", *(f"{rule}=2" for rule in ITEM_STAGES)), {}),
    "ilp scheduler": (("--scheduler", "ilp"), {}),
    "chunks 256": ((), {"chunks": {"y": 256, "x": 256}}),
    "item jobs": ((), {"jobs": "item"}),
    "item jobs, scene figures": ((), {"jobs": "item", "item_figures": "scenes"}),
    "item batches, scene figures": ((), {"jobs": "item", "item_figures": "scenes", "item_batches": 8}),
}
#: A job's logged work: the last "<stage> done in" line (an item job logs each stage, then its total;
#: a batch job each item, then the batch's total).
_DONE = re.compile(r"INFO (?:item \S+|batch of \d+ items|\w+) done in ([0-9.]+) s$", re.M)


# --- output --------------------------------------------------------------------------------


def table(title: str, headers: list[str], rows: list[list]) -> None:
    """Print an aligned plain-text table."""
    cells = [[f"{c:.3g}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(row[i]) for row in cells)) for i, h in enumerate(headers)]
    print(f"\n{title}")
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths)))


def load() -> str:
    """The 1, 5 and 15 minute load averages (other jobs share the machine)."""
    return "load %.2f %.2f %.2f" % os.getloadavg()


# --- campaigns -----------------------------------------------------------------------------


@dataclasses.dataclass
class Job:
    """One finished snakemake job: its rule, cores held, wall time, stage time and peak memory."""

    rule: str
    threads: int
    seconds: float
    max_rss_mb: float
    stage_seconds: float | None


@dataclasses.dataclass
class Run:
    """One snakemake run of a campaign: its size, variant, wall time, jobs and the load before it."""

    specimens: int
    label: str
    wall: float
    jobs: list[Job]
    load: str

    @property
    def startup(self) -> float:
        """Median job start-up: benchmark seconds minus the stage's own logged time."""
        return statistics.median(j.seconds - j.stage_seconds for j in self.jobs if j.stage_seconds is not None)

    def stage_seconds(self, job: Job) -> float:
        return job.stage_seconds if job.stage_seconds is not None else max(job.seconds - self.startup, 0.0)

    def shares(self) -> tuple[float, float, float]:
        """Stage time, job start-up and idle as shares of the ``cores x wall`` budget."""
        budget = CORES * self.wall
        held = sum(j.threads * j.seconds for j in self.jobs)
        stage = sum(j.threads * self.stage_seconds(j) for j in self.jobs)
        return stage / budget, (held - stage) / budget, 1 - held / budget


def render(directory: Path, specimens: int) -> float:
    """Render the scaled paper campaign; returns the seconds it took."""
    from surffin.simulate import PRESETS, simulate_campaign
    from surffin.simulate.presets import scaled_preset

    preset = dataclasses.replace(
        scaled_preset(PRESETS["paper"], specimens),
        wall_distances=(0.3, 0.475, 0.65, 0.825, 1.0),
        wall_tilts=(0.0, 10.0, 20.0, 30.0),
    )
    start = time.perf_counter()
    simulate_campaign(directory, preset=preset, seed=0)
    return time.perf_counter() - start


def parse_jobs(output: str) -> list[Job]:
    """The jobs of a snakemake run, from its printed job blocks and their benchmark and log files."""
    jobs = []
    for block in re.split(r"^\[.*\]\n(?=(?:local)?rule )", output, flags=re.M)[1:]:
        rule = re.sub(r"^item_batch_\d+$", "item_batch", re.match(r"(?:local)?rule (\w+):", block).group(1))
        bench = re.search(r"^\s+benchmark: (.+)$", block, re.M)
        if bench is None:  # the target rule `all`
            continue
        threads = re.search(r"^\s+threads: (\d+)$", block, re.M)
        values = dict(zip(*(line.split("\t") for line in Path(bench.group(1)).read_text().splitlines()[:2])))
        log_text = Path(re.search(r"^\s+log: (.+)$", block, re.M).group(1)).read_text()
        done = _DONE.findall(log_text)
        jobs.append(
            Job(
                rule=rule,
                threads=int(threads.group(1)) if threads else 1,
                seconds=float(values["s"]),
                max_rss_mb=float(values["max_rss"]),
                stage_seconds=float(done[-1]) if done else None,
            )
        )
    return jobs


def process(campaign: Path, workdir: Path, extra: tuple[str, ...], overrides: dict) -> tuple[float, list[Job]]:
    """Run ``snakemake --cores 2`` on a campaign; returns its wall time and jobs."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir)]
    cmd += ["--cores", str(CORES), *extra]
    if overrides:
        configfile = workdir / "overrides.json"  # JSON is YAML
        configfile.write_text(json.dumps(overrides))
        cmd += ["--configfiles", str(configfile)]
    cmd += ["--config", f"campaign={campaign}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}"]
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=workdir)
    wall = time.perf_counter() - start
    if run.returncode != 0:
        sys.exit(f"snakemake failed in {workdir}:\n{run.stderr[-4000:]}")
    return wall, parse_jobs(run.stdout + run.stderr)


def noop_startup(repeat: int = 5) -> float:
    """Median seconds of a Python process that only imports what every stage job imports."""
    imports = "import snakemake.script, surffin.pipeline.run, dask.array, zarr, xarray.backends.zarr"
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", imports], check=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def first_and_second_call(store: str, scratch: str) -> dict:
    """Rerun the stage that made ``store`` twice in this fresh process, from its recorded provenance.

    Returns
    -------
    dict
        ``stage``, seconds of ``import surffin.pipeline.run``, of the ``first`` and the ``second`` call.
    """
    start = time.perf_counter()
    from surffin.pipeline.run import run_stage

    imported = time.perf_counter() - start
    attrs = json.loads((Path(store) / "zarr.json").read_text())["attributes"]  # reading it imports nothing
    stage = attrs["surffin_stage"]
    seconds = []
    for call in range(2):
        start = time.perf_counter()
        run_stage(
            stage, f"{scratch}-{call}.zarr", stores=attrs["surffin_inputs"], params=attrs["surffin_parameters"],
            scheduler="threads", threads=CORES,
        )
        seconds.append(time.perf_counter() - start)
    return {"stage": stage, "import": imported, "first": seconds[0], "second": seconds[1]}


def first_use(processed: Path, scratch: Path) -> list[dict]:
    """First and second call of each per-item stage on the campaign's first specimen and scene, in fresh processes."""
    specimen = sorted(processed.glob("features/*.zarr"))[0].name
    stores = [processed / folder / specimen for folder in ("aoi", "reflectance", "registered", "features")]
    stores += sorted(processed.glob("labels/*.zarr"))[:1]
    return [in_fresh_process(first_and_second_call, str(store), str(scratch / store.parent.name)) for store in stores]


def campaign_runs(root: Path, sizes: list[int], variants: list[str]) -> tuple[list[Run], list[dict]]:
    """Render and process each campaign size in each variant; first-use costs from the first run."""
    runs, calls = [], []
    for n in sizes:
        campaign = root / f"campaign-{n}"
        seconds = render(campaign, n)
        print(f"rendered {n} specimens in {seconds:.0f} s ({load()})", flush=True)
        for label in variants:
            workdir = root / f"run-{n}-{len(runs)}"
            workdir.mkdir()
            before = load()
            wall, jobs = process(campaign, workdir, *VARIANTS[label])
            runs.append(Run(n, label, wall, jobs, before))
            print(f"processed {n} specimens ({label}) in {wall:.0f} s ({before} before)", flush=True)
            if not calls:
                calls = first_use(workdir / "processed", root)
            shutil.rmtree(workdir / "processed")
    return runs, calls


def report_campaigns(runs: list[Run], calls: list[dict], noop: float) -> None:
    """Print the run summary, where the time goes per rule, first-use costs and peak memory."""
    first = statistics.median(c["first"] - c["second"] for c in calls)
    rows = []
    for run in runs:
        stage, startup, idle = run.shares()
        warm = sum(j.threads * max(run.stage_seconds(j) - first, 0.0) for j in run.jobs) / (CORES * run.wall)
        rate = 60 * run.specimens / run.wall
        rows.append(
            [run.specimens, run.label, len(run.jobs), round(run.wall), round(rate, 1), round(rate / stage, 1),
             f"{stage:.0%}", f"{startup:.0%}", f"{idle:.0%}", f"{1 - stage:.0%}", f"{1 - warm:.0%}",
             round(run.startup, 2), round(max(j.max_rss_mb for j in run.jobs)), run.load]
        )
    table(
        f"Campaign runs (snakemake --cores {CORES}); targets >= 30 specimens/min, overhead <= 50 %, "
        f"peak <= 1000 MB; no-op start-up {noop:.2f} s",
        ["specimens", "variant", "jobs", "wall s", "spec/min", "no-overhead spec/min", "stage", "start-up", "idle",
         "overhead", "incl. first use", "start-up s/job", "peak MB", "before"],
        rows,
    )
    for run in runs:
        budget = CORES * run.wall
        rows = [
            [rule, len(jobs), jobs[0].threads, statistics.median(j.seconds for j in jobs),
             statistics.median(run.stage_seconds(j) for j in jobs),
             f"{sum(j.threads * j.seconds for j in jobs) / budget:.0%}"]
            for rule, jobs in by_rule(run).items()
        ]
        table(
            f"Where the time goes, {run.specimens} specimens, {run.label} (s: job wall; stage: logged work)",
            ["rule", "jobs", "threads", "median s", "median stage s", "share of cores x wall"],
            rows,
        )
    table(
        "Per-item stages run twice in a fresh process (run_stage from the stores' recorded provenance), s",
        ["stage", "import surffin.pipeline.run", "first call", "second call", "first use"],
        [[c["stage"], c["import"], c["first"], c["second"], c["first"] - c["second"]] for c in calls],
    )
    rules = list(dict.fromkeys(rule for run in runs for rule in by_rule(run)))
    rows = [
        [rule, *(f(j.max_rss_mb for j in by_rule(run)[rule]) if rule in by_rule(run) else "-"
                 for run in runs for f in (statistics.median, max))]
        for rule in rules
    ]
    table(
        "Peak memory per job, MB (max_rss of the benchmark TSVs, sampled every 0.5 s), by run",
        ["rule", *(f"{run.specimens} {run.label}: {stat}" for run in runs for stat in ("median", "max"))],
        [[row[0], *(v if v == "-" else round(v) for v in row[1:])] for row in rows],
    )


def by_rule(run: Run) -> dict[str, list[Job]]:
    """The run's jobs grouped by rule, in order of first appearance."""
    jobs = defaultdict(list)
    for job in run.jobs:
        jobs[job.rule].append(job)
    return jobs


# --- one large cube ------------------------------------------------------------------------


def write_cube(path: str, shape: tuple[int, int, int]) -> None:
    """A synthetic registered cube: AOI from 0 to 40 deg over the views, plaster-like R0 and n, 2 % noise."""
    import dask.array as da
    import numpy as np
    import xarray as xr

    from surffin.method.scattering import scattering_model
    from surffin.io.store import write_store

    nview, ny, nx = shape
    rng = da.random.default_rng(0)
    cube, image = (nview, 256, 256), (256, 256)
    tilt = np.deg2rad(np.linspace(0.0, 40.0, nview))[:, None, None]
    aoi = abs(tilt + rng.normal(0.0, np.deg2rad(1.0), shape, chunks=cube))
    r0 = 0.8 + 0.05 * rng.standard_normal((ny, nx), chunks=image)
    n = 1.1 + 0.1 * rng.standard_normal((ny, nx), chunks=image)
    model = da.map_blocks(scattering_model, aoi, r0[None], n[None], dtype=np.float64)
    reflectance = model * (1.0 + 0.02 * rng.standard_normal(shape, chunks=cube))
    dims = ("view", "y", "x")
    coords = {"view": [f"v{k:02d}" for k in range(nview)], "y": np.arange(ny), "x": np.arange(nx)}
    ds = xr.Dataset({"reflectance": (dims, reflectance), "aoi": (dims, aoi.astype(np.float32))}, coords=coords)
    write_store(ds, path, chunks={"y": 256, "x": 256})


def peak_rss_mb() -> float:
    """Peak resident memory of this process (VmHWM), MB.

    Not ``ru_maxrss``: on Linux that keeps the peak of the parent a spawned process was forked from.
    """
    status = Path("/proc/self/status").read_text()
    return int(re.search(r"^VmHWM:\s+(\d+) kB", status, re.M).group(1)) / 1024


def features_from_cube(source: str, output: str) -> dict:
    """Fit and features of a cube store into a features store; peak RSS in this (fresh) process."""
    from surffin.method.features import features, variability
    from surffin.pipeline.jobs import dask_scheduler
    from surffin.method.scattering import fit_scattering
    from surffin.io.store import open_store, write_store

    baseline = peak_rss_mb()
    start = time.perf_counter()
    ds = open_store(source)
    fit = fit_scattering(ds["reflectance"], ds["aoi"])
    own = variability(ds["reflectance"].isel(view=0, drop=True), ds["aoi"].isel(view=0, drop=True))
    with dask_scheduler("threads", CORES):
        write_store(features(fit, own), output, chunks={"y": 256, "x": 256})
    return {
        "baseline": baseline,
        "peak": peak_rss_mb(),
        "seconds": time.perf_counter() - start,
    }


def in_fresh_process(func, *args):
    """``func(*args)`` in a new (spawned) Python process, so its memory and imports start from nothing."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(func, args)


def report_cubes(root: Path, shapes: list[tuple[int, int, int]]) -> None:
    """Write each cube, run the features on it in a fresh process, print peak memory against its size."""
    rows = []
    for shape in shapes:
        source, output = root / f"cube-{shape[1]}x{shape[2]}.zarr", root / f"features-{shape[1]}x{shape[2]}.zarr"
        in_fresh_process(write_cube, str(source), shape)
        before = load()
        result = in_fresh_process(features_from_cube, str(source), str(output))
        cube_mb = shape[0] * shape[1] * shape[2] * (8 + 4) / 2**20
        increment = result["peak"] - result["baseline"]
        rows.append(
            [f"{shape[0]}x{shape[1]}x{shape[2]}", round(shape[1] * shape[2] / (480 * 640), 1), round(cube_mb),
             round(result["baseline"]), round(result["peak"]), round(increment), f"{increment / cube_mb:.2f}",
             round(result["seconds"], 1), round(shape[1] * shape[2] / result["seconds"] / 1e6, 2), before]
        )
        shutil.rmtree(source)
        shutil.rmtree(output)
    table(
        f"One cube through fit_scattering + features from a store chunked (view -1, 256, 256), threads x{CORES}",
        ["cube", "frames", "cube MB", "baseline MB", "peak MB", "increment MB", "increment/cube", "s", "Mpx/s",
         "before"],
        rows,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--specimens", type=int, nargs="*", default=[10, 50], help="campaign sizes")
    parser.add_argument(
        "--variants", nargs="+", choices=list(VARIANTS), default=["default"],
        help="run variants to compare (default: the repository's settings only)",
    )
    parser.add_argument("--cubes", nargs="*", default=["480x640", "1600x1920"], help="cube sizes HxW (5 views)")
    parser.add_argument("--workdir", type=Path, help="scratch folder (default: a temporary one, removed after)")
    args = parser.parse_args()
    if args.workdir is not None:
        args.workdir.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="surffin-bench-", dir=args.workdir))
    try:
        print(f"surffin campaign benchmark in {root}, {os.cpu_count()} cpus, {load()}", flush=True)
        runs, calls = campaign_runs(root, args.specimens, args.variants)
        if runs:
            report_campaigns(runs, calls, noop_startup())
        if args.cubes:
            report_cubes(root, [(5, *map(int, size.split("x"))) for size in args.cubes])
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
