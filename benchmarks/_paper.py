"""The ``paper`` campaign the truth-checking benchmarks run on."""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path

import surffin


@contextlib.contextmanager
def paper_campaign(path: Path | None) -> Iterator[tuple[surffin.io.campaign.Campaign, Path]]:
    """Yield the campaign at ``path``, or the ``paper`` preset (seed 0) rendered into a temporary folder.

    Yields the validated campaign and its truth folder (``<campaign>-truth``); a
    rendered campaign is removed on exit, so read its truth inside the block.
    """
    with tempfile.TemporaryDirectory() as tmp:
        campaign = path or Path(tmp) / "paper"
        if path is None:
            surffin.simulate_campaign(campaign, preset="paper", seed=0)
        yield surffin.read_campaign(campaign), Path(f"{campaign}-truth")
