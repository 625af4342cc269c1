"""The ``surffin`` command: simulate and check campaigns, inspect stores, export results, run the sensitivity study."""

from __future__ import annotations

import argparse
import sys

from surffin._version import __version__
from surffin.errors import SurffinError

__all__ = ["main"]


def _check(args: argparse.Namespace) -> int:
    from surffin.io.campaign import check_pixels, read_campaign

    camp = read_campaign(args.campaign, require_calibration=not args.no_calibration)
    checked = check_pixels(camp, camp.view_files)
    print(f"{camp.path}: campaign {camp.name!r} is valid (the pixels of its {len(checked['views'])} view files read)")
    print(f"  camera {camp.camera.width}x{camp.camera.height}, crop y={camp.crop.y} x={camp.crop.x}")
    if camp.calibration is not None:
        print(
            f"  calibration: {len(camp.calibration.wall)} wall views, "
            f"{len(camp.calibration.reference.views)} reference views"
        )
    for item in camp.items.values():
        label = f"class {item.cls}" if item.cls else "scene"
        print(f"  {item.kind} {item.name} ({label}): {len(item.views)} views, reference {item.reference}")
    if camp.scenes and not camp.specimens:
        print(
            "  note: scenes but no specimens: the workflow runs it only with extra_training, the training.zarr "
            "stores of other campaigns (--config extra_training=[...]) to classify the scenes"
        )
    return 0


def _inspect(args: argparse.Namespace) -> int:
    import json

    from surffin.io.store import open_store

    ds = open_store(args.store)
    print(ds)
    for key in ("surffin_version", "surffin_stage", "surffin_code_version", "surffin_parameters", "surffin_inputs"):
        if key in ds.attrs:
            print(f"{key}: {json.dumps(ds.attrs[key], indent=2, default=str)}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from surffin.report.export import export_results

    written = export_results(args.processed, args.out, calibration=args.calibration)
    print(f"{args.out}: {len(written)} files written")
    return 0


def _whole_number(minimum: int):
    """Return an argparse type: an integer of at least ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} is below the minimum {minimum}")
        return value

    return parse


def _sensitivity(args: argparse.Namespace) -> int:
    from surffin.analysis.sensitivity import THRESHOLD, separation_summary, views_slopes
    from surffin.io.store import open_store
    from surffin.pipeline.analyses import run_sensitivity

    paths = run_sensitivity(args.out, draws=args.draws, seed=args.seed)
    table = open_store(paths["store"], stage="sensitivity").load()
    print(f"{args.out}: sensitivity analysis, {args.draws} draws per configuration, seed {args.seed}")
    print(f"  wrote {', '.join(path.name for path in paths.values())}")
    print("std ~ K^slope, K = 2..10 views over 0..45 deg (paper: R0 -0.5, n -1):")
    slopes = views_slopes(table).to_dataframe()
    for (noise, level, sigma), rows in slopes.groupby(["noise", "level", "sigma"], sort=False):
        fits = ", ".join(
            f"{r.parameter} {r.slope:+.2f} ± {r.slope_stderr:.2f} (K >= 3: {r.slope_from_3:+.2f})"
            for r in rows.itertuples()
        )
        print(f"  {noise} {level} (σ {sigma:g}{' deg' if noise == 'aoi' else ''}): {fits}")
    print(f"two views, one at 45 deg: separation from which std < {100 * THRESHOLD:g} % (and no fit fails):")
    summary = separation_summary(table).to_dataframe()
    for (noise, level, sigma), rows in summary.groupby(["noise", "level", "sigma"], sort=False):
        needed = ", ".join(
            f"{r.parameter} {r.required_separation_deg:g} deg ({r.no_failures_from_deg:g} deg)"
            for r in rows.itertuples()
        )
        print(f"  {noise} {level} (σ {sigma:g}{' deg' if noise == 'aoi' else ''}): {needed}")
    return 0


def _parser() -> argparse.ArgumentParser:
    from surffin import simulate

    parser = argparse.ArgumentParser(prog="surffin", description=__doc__)
    parser.add_argument("--version", action="version", version=f"surffin {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    sim = commands.add_parser("simulate", help="render a synthetic campaign with known truth")
    simulate.cli_parser(sim)
    sim.set_defaults(run=simulate.cli_run)

    check = commands.add_parser("check", help="validate a campaign directory")
    check.add_argument("campaign", help="campaign directory or its campaign.yaml")
    check.add_argument(
        "--no-calibration", action="store_true", help="the calibration comes from another campaign's store"
    )
    check.set_defaults(run=_check)

    inspect = commands.add_parser("inspect", help="print what a processed store holds and how it was made")
    inspect.add_argument("store", help="path of a .zarr store")
    inspect.set_defaults(run=_inspect)

    export = commands.add_parser(
        "export", help="write a processed folder's results as label PNGs, class areas (CSV), PLY clouds and PDF reports"
    )
    export.add_argument("processed", help="processed folder of a complete run")
    export.add_argument("out", help="output folder")
    export.add_argument("--calibration", help="calibration store the reports name (default PROCESSED/calibration.zarr)")
    export.set_defaults(run=_export)

    sensitivity = commands.add_parser(
        "sensitivity", help="Monte Carlo of the scattering fit's sensitivity to noise (paper section 4)"
    )
    sensitivity.add_argument("--out", required=True, help="output folder (table, zarr store, slopes, figures)")
    sensitivity.add_argument(
        "--draws", type=_whole_number(2), default=500, help="draws per configuration (default 500)"
    )
    sensitivity.add_argument("--seed", type=_whole_number(0), default=0, help="random seed (default 0)")
    sensitivity.set_defaults(run=_sensitivity)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; errors on bad input are one line, not a traceback."""
    args = _parser().parse_args(argv)
    try:
        return args.run(args)
    except SurffinError as exc:
        print(f"surffin: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
