"""The ``surffin`` command: simulate campaigns, check them, look into stores."""

from __future__ import annotations

import argparse
import sys

from surffin._version import __version__
from surffin.errors import SurffinError

__all__ = ["main"]


def _check(args: argparse.Namespace) -> int:
    from surffin.campaign import read_campaign

    camp = read_campaign(args.campaign, require_calibration=not args.no_calibration)
    print(f"{camp.path}: campaign {camp.name!r} is valid")
    print(f"  camera {camp.camera.width}x{camp.camera.height}, crop y={camp.crop.y} x={camp.crop.x}")
    if camp.calibration is not None:
        print(f"  calibration: {len(camp.calibration.wall)} wall views, {len(camp.calibration.reference.views)} reference views")
    for item in camp.items.values():
        label = f"class {item.cls}" if item.cls else "scene"
        print(f"  {item.kind} {item.name} ({label}): {len(item.views)} views, reference {item.reference}")
    return 0


def _inspect(args: argparse.Namespace) -> int:
    import json

    from surffin.store import open_store

    ds = open_store(args.store)
    print(ds)
    for key in ("surffin_version", "surffin_stage", "surffin_parameters", "surffin_inputs"):
        if key in ds.attrs:
            print(f"{key}: {json.dumps(ds.attrs[key], indent=2, default=str)}")
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
    check.add_argument("--no-calibration", action="store_true", help="the calibration comes from another campaign's store")
    check.set_defaults(run=_check)

    inspect = commands.add_parser("inspect", help="print what a processed store holds and how it was made")
    inspect.add_argument("store", help="path of a .zarr store")
    inspect.set_defaults(run=_inspect)
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
