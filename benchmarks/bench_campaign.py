"""Campaign scale: specimens per minute and the whole run's peak memory; one cube 10x a frame.

Run by hand: ``python benchmarks/bench_campaign.py [--specimens 12 48] [--variants default ...]
[--cubes 480x640 1600x1920] [--workdir DIR]``; prints tables, writes nothing in the repository.
Each campaign is the ``paper`` preset scaled to N specimens (``scaled_preset``) with 20 wall views
instead of 105, rendered first (not timed), then processed by ``snakemake --cores 2`` with the
repository's config and workflow profile: every job runs in a thread of the snakemake process,
its work in a worker process (``surffin.pipeline.jobs.in_worker``).

- **spec/min** = N / wall time of the snakemake command (parsing, DAG, every job, bookkeeping).
- **peak MB** = the RSS of the snakemake process and all its children, summed, sampled every 0.2 s
  (at least **max process MB**: the largest single process's high-water mark, ``wait4``'s ru_maxrss).
- **jobs** = the jobs' wall times as they log them (``job done in X s``, read by
  ``surffin.pipeline.jobs.job_seconds``) x their threads, over the ``cores x wall`` budget; **overhead** =
  1 - jobs: snakemake's own time and idle cores; **snakemake CPU s**: the snakemake process's own CPU
  time (user + system, its worker processes not counted); **tree CPU s**: that of the snakemake process
  and all its descendants (the workers), which a shared machine's load changes less than the wall time.
  Snakemake's ``benchmark:`` directive, which the rules no longer carry, sampled the memory of the whole
  process tree twice a second per job: 12-15 s of system time in a 48-specimen run, against 0.6 s without.
- ``--variants``: ``scene figures`` (``item_figures: scenes``), ``ilp scheduler``, ``chunks 256``
  (against 512), ``item stages 2 threads`` (``--set-threads``: one per-item stage at a time, two dask
  threads) and ``processes`` (no ``force-use-threads``: each job a spawned snakemake process).
Targets: >= 60 specimens/min at 48 specimens with the default config; whole-run peak memory.

One cube: a synthetic (5, H, W) store, chunks (view -1, 256, 256), through fit_scattering,
variability and features in a fresh process (threads x 2); its peak RSS (VmHWM) over the baseline
after the imports should grow far less than the cube (1600 x 1920 is 10x a 480 x 640 frame).
The machine is shared: wall times move with its load (printed with each run); memory does not.
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
import threading
import time
from collections import defaultdict
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]
CORES = 2
#: Per-item stages: the rules the ``item stages 2 threads`` variant runs at two threads.
ITEM_STAGES = ("aoi", "reflectance", "registration", "features", "labels")
#: Stands for a copy of ``profiles/default`` without ``force-use-threads``, written for the run.
NO_THREADS_PROFILE = "<profiles/default without force-use-threads>"
#: Variants of a campaign run: name -> (extra snakemake arguments, config overrides). The
#: overrides go through a config file: ``--config`` would pass nested numbers as strings.
VARIANTS = {
    "default": ((), {}),
    "scene figures": ((), {"item_figures": "scenes"}),
    "ilp scheduler": (("--scheduler", "ilp"), {}),
    "chunks 256": ((), {"chunks": {"y": 256, "x": 256}}),
    "item stages 2 threads": (("--set-threads", *(f"{rule}=2" for rule in ITEM_STAGES)), {}),
    "processes": (("--workflow-profile", NO_THREADS_PROFILE), {}),
}


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
    """Return the 1, 5 and 15 minute load averages (other jobs share the machine)."""
    return "load %.2f %.2f %.2f" % os.getloadavg()


# --- campaigns -----------------------------------------------------------------------------


@dataclasses.dataclass
class Job:
    """One finished snakemake job: its rule, cores held and wall time as its log says."""

    rule: str
    threads: int
    seconds: float


@dataclasses.dataclass
class Usage:
    """What a command used: wall s, summed RSS peak, largest process's peak, own and process tree's CPU s."""

    wall: float
    peak_mb: float
    max_process_mb: float
    own_cpu: float
    tree_cpu: float


@dataclasses.dataclass
class Run:
    """One snakemake run of a campaign: its size, variant, resource use, jobs and the load before it."""

    specimens: int
    label: str
    usage: Usage
    jobs: list[Job]
    load: str

    def share(self, seconds: float) -> float:
        """Core-seconds as a share of the run's ``cores x wall`` budget."""
        return seconds / (CORES * self.usage.wall)


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
    """Read the jobs of a snakemake run from its printed job blocks and their log files."""
    from surffin.pipeline.jobs import job_seconds

    jobs = []
    for block in re.split(r"^\[.*\]\n(?=(?:local)?rule )", output, flags=re.M)[1:]:
        log = re.search(r"^\s+log: (.+)$", block, re.M)
        if log is None:  # the target rule `all`
            continue
        threads = re.search(r"^\s+threads: (\d+)$", block, re.M)
        seconds = job_seconds(log.group(1))
        rule = re.match(r"(?:local)?rule (\w+):", block).group(1)
        if seconds is None:
            sys.exit(f"the {rule} job's log {log.group(1)} does not say how long it took")
        jobs.append(Job(rule, int(threads.group(1)) if threads else 1, seconds))
    return jobs


def no_threads_profile(folder: Path) -> Path:
    """Copy ``profiles/default`` into ``folder`` without its ``force-use-threads`` line."""
    lines = (REPO / "profiles" / "default" / "config.yaml").read_text().splitlines(keepends=True)
    profile = folder / "profile-no-threads"
    profile.mkdir(exist_ok=True)
    (profile / "config.yaml").write_text("".join(line for line in lines if not line.startswith("force-use-threads:")))
    return profile


def tree_sample(process: psutil.Process, cpu: dict[int, float]) -> float:
    """Sum the RSS of a process and its descendants, MB (0 once it is gone); note each one's CPU s in ``cpu``."""
    total = 0
    try:
        members = [process, *process.children(recursive=True)]
    except psutil.Error:
        return 0.0
    for member in members:
        try:
            total += member.memory_info().rss
            times = member.cpu_times()
            cpu[member.pid] = times.user + times.system
        except psutil.Error:  # ended meanwhile
            pass
    return total / 2**20


def measured(cmd: list[str], cwd: Path, output: Path) -> tuple[int, Usage]:
    """Run ``cmd`` with stdout and stderr into ``output``; its exit code and what it used.

    The peak summed RSS is sampled every 0.2 s while it runs (and is at least the largest process's
    peak), and so are the CPU times of the command and of each of its descendants (their last samples:
    up to 0.2 s of each process's end missed); that largest peak comes from ``wait4`` (the command and
    its waited-for descendants).
    """
    with open(output, "w") as stream:
        start = time.perf_counter()
        child = subprocess.Popen(cmd, stdout=stream, stderr=subprocess.STDOUT, cwd=cwd)
        peak, cpu, done = [0.0], {}, threading.Event()

        def sample():
            process = psutil.Process(child.pid)
            while not done.wait(0.2):
                peak[0] = max(peak[0], tree_sample(process, cpu))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        _, status, rusage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - start
        done.set()
        sampler.join()
        child.returncode = os.waitstatus_to_exitcode(status)  # reaped here, for wait4's rusage
    largest = rusage.ru_maxrss / 1024
    usage = Usage(wall, max(peak[0], largest), largest, cpu.get(child.pid, 0.0), sum(cpu.values()))
    return child.returncode, usage


def process(campaign: Path, workdir: Path, extra: tuple[str, ...], overrides: dict) -> tuple[Usage, list[Job]]:
    """Run ``snakemake --cores 2`` on a campaign; returns what it used and its jobs."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir)]
    cmd += ["--cores", str(CORES)]
    cmd += [str(no_threads_profile(workdir)) if arg == NO_THREADS_PROFILE else arg for arg in extra]
    if overrides:
        configfile = workdir / "overrides.json"  # JSON is YAML
        configfile.write_text(json.dumps(overrides))
        cmd += ["--configfiles", str(configfile)]
    cmd += ["--config", f"campaign={campaign}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}"]
    output = workdir / "snakemake.out"
    returncode, usage = measured(cmd, workdir, output)
    text = output.read_text()
    if returncode != 0:
        sys.exit(f"snakemake failed in {workdir}:\n{text[-4000:]}")
    return usage, parse_jobs(text)


def campaign_runs(root: Path, sizes: list[int], variants: list[str]) -> list[Run]:
    """Render and process each campaign size in each variant."""
    runs = []
    for n in sizes:
        campaign = root / f"campaign-{n}"
        seconds = render(campaign, n)
        print(f"rendered {n} specimens in {seconds:.0f} s ({load()})", flush=True)
        for label in variants:
            workdir = root / f"run-{n}-{len(runs)}"
            workdir.mkdir()
            before = load()
            usage, jobs = process(campaign, workdir, *VARIANTS[label])
            runs.append(Run(n, label, usage, jobs, before))
            print(f"processed {n} specimens ({label}) in {usage.wall:.0f} s ({before} before)", flush=True)
            shutil.rmtree(workdir / "processed")
    return runs


def report_campaigns(runs: list[Run]) -> None:
    """Print the run summary and, per run, where the time goes per rule."""
    rows = []
    for run in runs:
        busy = run.share(sum(j.threads * j.seconds for j in run.jobs))
        rows.append(
            [
                run.specimens,
                run.label,
                len(run.jobs),
                round(run.usage.wall),
                round(60 * run.specimens / run.usage.wall, 1),
                f"{busy:.0%}",
                f"{1 - busy:.0%}",
                round(run.usage.own_cpu, 1),
                round(run.usage.tree_cpu, 1),
                round(run.usage.peak_mb),
                round(run.usage.max_process_mb),
                run.load,
            ]
        )
    table(
        f"Campaign runs (snakemake --cores {CORES}); target >= 60 specimens/min at 48 specimens (default)",
        [
            "specimens",
            "variant",
            "jobs",
            "wall s",
            "spec/min",
            "jobs",
            "overhead",
            "snakemake CPU s",
            "tree CPU s",
            "peak MB",
            "max process MB",
            "before",
        ],
        rows,
    )
    for run in runs:
        rows = [
            [
                rule,
                len(jobs),
                jobs[0].threads,
                statistics.median(j.seconds for j in jobs),
                f"{run.share(sum(j.threads * j.seconds for j in jobs)):.0%}",
            ]
            for rule, jobs in by_rule(run).items()
        ]
        table(
            f"Where the time goes, {run.specimens} specimens, {run.label} (s: a job's wall time, as it logs it)",
            ["rule", "jobs", "threads", "median s", "share"],
            rows,
        )


def by_rule(run: Run) -> dict[str, list[Job]]:
    """Group the run's jobs by rule, in order of first appearance."""
    jobs = defaultdict(list)
    for job in run.jobs:
        jobs[job.rule].append(job)
    return jobs


# --- one large cube ------------------------------------------------------------------------


def write_cube(path: str, shape: tuple[int, int, int]) -> None:
    """Write a synthetic registered cube: AOI 0 to 40 deg over the views, plaster-like R0 and n, 2 % noise."""
    import dask.array as da
    import numpy as np
    import xarray as xr

    from surffin.io.store import write_store
    from surffin.method.scattering import scattering_model

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
    from surffin.io.store import open_store, write_store
    from surffin.method.features import features, variability
    from surffin.method.scattering import fit_scattering
    from surffin.pipeline.jobs import dask_scheduler

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
            [
                f"{shape[0]}x{shape[1]}x{shape[2]}",
                round(shape[1] * shape[2] / (480 * 640), 1),
                round(cube_mb),
                round(result["baseline"]),
                round(result["peak"]),
                round(increment),
                f"{increment / cube_mb:.2f}",
                round(result["seconds"], 1),
                round(shape[1] * shape[2] / result["seconds"] / 1e6, 2),
                before,
            ]
        )
        shutil.rmtree(source)
        shutil.rmtree(output)
    table(
        f"One cube through fit_scattering + features from a store chunked (view -1, 256, 256), threads x{CORES}",
        [
            "cube",
            "frames",
            "cube MB",
            "baseline MB",
            "peak MB",
            "increment MB",
            "increment/cube",
            "s",
            "Mpx/s",
            "before",
        ],
        rows,
    )


def main():
    """Render the campaigns, run the variants and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--specimens", type=int, nargs="*", default=[12, 48], help="campaign sizes")
    parser.add_argument(
        "--variants",
        nargs="+",
        choices=list(VARIANTS),
        default=["default"],
        help="run variants to compare (default: the repository's settings only)",
    )
    parser.add_argument("--cubes", nargs="*", default=["480x640", "1600x1920"], help="cube sizes HxW (5 views)")
    parser.add_argument(
        "--workdir",
        type=Path,
        help="keep the campaigns and the runs' logs in a new folder here (default: a temporary one, removed after)",
    )
    args = parser.parse_args()
    if args.workdir is not None:
        args.workdir.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="surffin-bench-", dir=args.workdir))
    try:
        print(f"surffin campaign benchmark in {root}, {os.cpu_count()} cpus, {load()}", flush=True)
        runs = campaign_runs(root, args.specimens, args.variants)
        if runs:
            report_campaigns(runs)
        if args.cubes:
            report_cubes(root, [(5, *map(int, size.split("x"))) for size in args.cubes])
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
