"""``surffin simulate``: the command line of :func:`~surffin.simulate.acquire.simulate_campaign`.

``--preset NAME`` renders a named preset (default ``paper``; files as ``--format``,
``--units`` and ``--no-poses`` say, default npz in m with poses). ``--validation
NAME`` renders a validation campaign (:data:`~surffin.simulate.validation.VALIDATION`)
instead, written in its own format, units, poses and imperfections unless those options
are given. ``--imperfections NAMES`` renders a real camera's imperfections, named as in
:data:`~surffin.simulate.imperfections.STANDARD` and separated by commas (``all``,
``pose,mixed``, ...; ``none`` for an ideal camera).

Kept free of heavy imports, so that building the ``surffin`` parser stays cheap;
the simulator itself is imported when the command runs.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from surffin.simulate.imperfections import STANDARD, Imperfections, named_imperfections
from surffin.simulate.presets import PRESETS
from surffin.simulate.validation import FORMATS, UNITS, VALIDATION, Validation

__all__ = ["cli_parser", "cli_run"]


def cli_parser(parser: argparse.ArgumentParser) -> None:
    """Add the arguments of ``surffin simulate`` to ``parser``."""
    parser.add_argument("directory", help="campaign directory to create (must not hold a campaign.yaml)")
    design = parser.add_mutually_exclusive_group()
    design.add_argument("--preset", choices=sorted(PRESETS), help="acquisition design (default: paper)")
    design.add_argument(
        "--validation",
        choices=sorted(VALIDATION),
        help="a validation campaign: its design, and its format, units and poses unless given",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed; same seed, same files (default: 0)")
    parser.add_argument(
        "--format", dest="fmt", choices=FORMATS, help="view file form; mixed cycles npz/ply/raw (default: npz)"
    )
    parser.add_argument("--units", choices=UNITS, help="unit of xyz in npz and ply files (default: m)")
    parser.add_argument(
        "--no-poses", dest="poses", action="store_false", default=None, help="do not write camera poses"
    )
    parser.add_argument("--truth", default=None, help="folder of the truth stores (default: <directory>-truth)")
    parser.add_argument(
        "--imperfections",
        type=_imperfections,
        metavar="NAMES",
        help=f"a real camera's imperfections, comma-separated, of: {', '.join(STANDARD)} (default: none)",
    )


def _imperfections(names: str) -> Imperfections:
    """Parse ``--imperfections``: names of :data:`STANDARD` separated by commas."""
    try:
        return named_imperfections(names)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _campaign(args: argparse.Namespace) -> Validation:
    """Choose the design and file options the arguments ask for: a validation campaign's or a preset's with defaults."""
    if args.validation is not None:
        chosen = VALIDATION[args.validation]
    else:
        chosen = Validation(PRESETS[args.preset or "paper"])
    options = ("fmt", "units", "poses", "imperfections")
    given = {key: getattr(args, key) for key in options if getattr(args, key) is not None}
    return replace(chosen, **given)


def cli_run(args: argparse.Namespace) -> int:
    """Run ``surffin simulate`` with parsed arguments; print the campaign.yaml path; return 0.

    Errors (:class:`~surffin.errors.SurffinError`) propagate to the command's main, which reports them.
    """
    from surffin.simulate.acquire import simulate_campaign

    campaign = _campaign(args)
    path = simulate_campaign(
        args.directory,
        campaign.preset,
        args.seed,
        fmt=campaign.fmt,
        units=campaign.units,
        poses=campaign.poses,
        truth=args.truth,
        imperfections=campaign.imperfections,
    )
    print(path)
    return 0
