"""The code's form is held by tools: ruff (format, lint with numpydoc docstrings), snakefmt, short module docstrings."""

import ast
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


#: A module's docstring says what and why; measurements go to docs/performance.md or the benchmarks' output.
MAX_MODULE_DOCSTRING_LINES = 25


def test_module_docstrings_are_short():
    long = {}
    for path in sorted((REPO / "surffin").rglob("*.py")):
        lines = len((ast.get_docstring(ast.parse(path.read_text())) or "").splitlines())
        if lines > MAX_MODULE_DOCSTRING_LINES:
            long[str(path.relative_to(REPO))] = lines
    assert not long, f"module docstrings over {MAX_MODULE_DOCSTRING_LINES} lines: {long}"
