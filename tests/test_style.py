"""The code's form is held by tools: ruff (format, lint with numpydoc docstrings) and snakefmt."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TOOLS = Path(sys.executable).parent
PYTHON = ["surffin", "tests", "benchmarks"]


@pytest.mark.parametrize(
    "command",
    [
        ["ruff", "format", "--check", *PYTHON],
        ["ruff", "check", *PYTHON],
        ["snakefmt", "--check", "Snakefile", "workflow/rules"],
    ],
    ids=["ruff format", "ruff check", "snakefmt"],
)
def test_the_code_is_formatted_and_linted(command):
    run = subprocess.run([TOOLS / command[0], *command[1:]], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 0, run.stdout + run.stderr
