"""Benchmarks that time this tree against a checkout of another revision, each in processes of its own."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

#: This tree: the repository the benchmarks are in.
THIS_TREE = Path(__file__).resolve().parents[1]


def run_in_tree(tree: Path, script: str, *arguments: str) -> str:
    """Run a benchmark ``script`` in a new process that imports surffin from ``tree``; return what it printed.

    Exits with the script's error output when it fails.
    """
    done = subprocess.run(
        [sys.executable, script, *arguments],
        env={**os.environ, "PYTHONPATH": str(tree)},
        capture_output=True,
        text=True,
    )
    if done.returncode:
        sys.exit(f"{Path(script).name} failed with surffin from {tree}:\n{done.stderr[-4000:]}")
    return done.stdout
