"""``surffin simulate``: the command line of :func:`~surffin.simulate.acquire.simulate_campaign`.

Kept free of heavy imports, so that building the ``surffin`` parser stays cheap;
the simulator itself is imported when the command runs.
"""

from __future__ import annotations

import argparse

from surffin.simulate.presets import PRESETS

__all__ = ["FORMATS", "UNITS", "cli_parser", "cli_run"]

#: Values of ``fmt``: one view file form for all views, or ``mixed`` (npz, ply, raw in turn).
FORMATS = ("npz", "ply", "raw", "mixed")
#: Units of xyz in npz and ply view files.
UNITS = ("m", "mm")


def cli_parser(parser: argparse.ArgumentParser) -> None:
    """Add the arguments of ``surffin simulate`` to ``parser``."""
    parser.add_argument("directory", help="campaign directory to create (must not hold a campaign.yaml)")
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS), help="acquisition design (default: paper)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; same seed, same files (default: 0)")
    parser.add_argument(
        "--format", dest="fmt", default="npz", choices=FORMATS, help="view file form; mixed cycles npz/ply/raw"
    )
    parser.add_argument("--units", default="m", choices=UNITS, help="unit of xyz in npz and ply files (default: m)")
    parser.add_argument("--no-poses", dest="poses", action="store_false", help="do not write camera poses")
    parser.add_argument("--truth", default=None, help="folder of the truth stores (default: <directory>-truth)")


def cli_run(args: argparse.Namespace) -> int:
    """Run ``surffin simulate`` with parsed arguments; print the campaign.yaml path; return 0.

    Errors (:class:`~surffin.errors.SurffinError`) propagate to the command's main, which reports them.
    """
    from surffin.simulate.acquire import simulate_campaign

    path = simulate_campaign(
        args.directory, args.preset, args.seed, fmt=args.fmt, units=args.units, poses=args.poses, truth=args.truth
    )
    print(path)
    return 0
