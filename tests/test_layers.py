"""The import layers of surffin, read from the source with ``ast`` (nothing is imported).

Every import statement at any depth of every module (inside functions and
``if TYPE_CHECKING:`` blocks too; relative imports resolved) must

- go downwards: a module imports only from its own layer or the layers below
  it (:data:`MAY_IMPORT`); the simulator in particular imports no method code,
  so that the truth it makes is not made by the code it checks;
- name no private (single-underscore) name of another surffin module, neither
  ``from m import _x`` nor ``alias._x`` of an imported surffin module; the
  tests, benchmarks and workflow scripts are held to this rule too;
- close no cycle between surffin modules (function-level imports count).

``python tests/test_layers.py`` (or ``pytest -s tests/test_layers.py``) prints
the modules per layer and the number of imports checked.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "surffin"
#: Folders of code outside the package that may use only surffin's public names.
CLIENTS = ("tests", "benchmarks")

#: The layers from the bottom up, and what each may import besides itself.
LAYERS = ("base", "io", "method", "simulate", "analysis", "report", "pipeline", "top")
MAY_IMPORT = {
    "base": {"base"},
    "io": {"base", "io"},
    "method": {"base", "io", "method"},
    "simulate": {"base", "io", "simulate"},
    "analysis": {"base", "io", "method", "analysis"},
    "report": {"base", "io", "method", "analysis", "report"},
    "pipeline": {"base", "io", "method", "simulate", "analysis", "report", "pipeline"},
    "top": set(LAYERS),
}
#: The modules of the base layer, directly in the package.
BASE = {"errors", "grid", "paper", "_version"}
#: Subpackages that are layers of their own.
SUBPACKAGES = {"io", "method", "simulate", "analysis", "report", "pipeline"}
#: Modules of the top layer.
TOP = {"", "cli"}


def layer_of(module: str) -> str | None:
    """The layer of a surffin module (None: in no layer, which is itself a violation)."""
    parts = module.split(".")
    if parts[0] != PACKAGE:
        return None
    rest = ".".join(parts[1:])
    if rest in TOP:
        return "top"
    if rest in BASE:
        return "base"
    return parts[1] if parts[1] in SUBPACKAGES else None


def is_private(name: str) -> bool:
    """A single-underscore name (not a dunder)."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


@dataclass(frozen=True)
class Import:
    """One imported name: ``module`` (absolute) and ``name`` (None for ``import module``), at ``line``."""

    module: str
    name: str | None
    line: int


@dataclass
class Source:
    """One Python file: its name (module name, or path outside the package), imports and name bindings."""

    path: Path
    name: str
    module: str | None
    imports: list[Import]
    bindings: dict[str, str]
    tree: ast.Module


def module_name(path: Path, root: Path) -> str:
    """``surffin/io/store.py`` -> ``surffin.io.store``; a package's ``__init__.py`` -> the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _absolute(node: ast.ImportFrom, package: str | None, path: Path) -> str:
    """The module of ``from ... import``, a relative one resolved against ``package``."""
    if not node.level:
        return node.module
    if package is None:
        raise ValueError(f"{path}:{node.lineno}: relative import outside the package")
    parts = package.split(".")
    if node.level - 1 >= len(parts):
        raise ValueError(f"{path}:{node.lineno}: relative import beyond the top of the package")
    return ".".join([*parts[: len(parts) - node.level + 1], *([node.module] if node.module else [])])


def read_source(path: Path, root: Path, module: str | None = None) -> Source:
    """Parse ``path``: every import statement in it (relative ones made absolute) and the names they bind.

    ``import a.b`` binds ``a`` to module a, ``import a.b as c`` binds c to a.b,
    ``from a import b as c`` binds c to a.b (a module or not).
    """
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = None
    if module is not None:
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    imports, bindings = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                imports.append(Import(alias.name, None, node.lineno))
                bound = alias.name if alias.asname else alias.name.split(".")[0]
                bindings[alias.asname or bound] = bound
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node, package, path)
            for alias in node.names:
                imports.append(Import(base, alias.name, node.lineno))
                bindings[alias.asname or alias.name] = f"{base}.{alias.name}"
    name = module if module is not None else path.relative_to(root).as_posix()
    return Source(path, name, module, imports, bindings, tree)


def read_package(root: Path, package: str = PACKAGE) -> dict[str, Source]:
    """Every module of the package under ``root / package``, by module name."""
    return {
        module_name(path, root): read_source(path, root, module_name(path, root))
        for path in sorted((root / package).rglob("*.py"))
    }


def read_clients(root: Path, folders: Iterable[str] = CLIENTS) -> list[Source]:
    """The Python files of the folders (those that exist) outside the package."""
    return [read_source(path, root) for folder in folders for path in sorted((root / folder).rglob("*.py"))]


def targets(item: Import, modules: Iterable[str]) -> list[str]:
    """The surffin modules an import names: ``from a import b`` names a and, if it is a module, a.b."""
    names = [item.module]
    if item.name is not None and f"{item.module}.{item.name}" in modules:
        names.append(f"{item.module}.{item.name}")
    return [name for name in names if name == PACKAGE or name.startswith(f"{PACKAGE}.")]


def layer_violations(modules: Mapping[str, Source]) -> list[str]:
    """Imports from a layer above (or beside) the importer's, and modules in no layer."""
    problems = []
    for module, source in modules.items():
        layer = layer_of(module)
        if layer is None:
            problems.append(f"{module}: in no layer (add it to tests/test_layers.py)")
            continue
        for item in source.imports:
            for target in targets(item, modules):
                if layer_of(target) not in MAY_IMPORT[layer]:
                    problems.append(f"{module}:{item.line}: {layer} imports {target} ({layer_of(target)})")
    return sorted(set(problems))


def private_violations(sources: Iterable[Source], modules: Iterable[str]) -> list[str]:
    """``from m import _x`` of a surffin module m, and ``alias._x`` of an imported surffin module."""
    modules = set(modules)
    problems = []
    for source in sources:
        for item in source.imports:
            if targets(item, modules) and item.name is not None and is_private(item.name):
                if item.module != source.module:
                    problems.append(f"{source.name}:{item.line}: imports {item.name} from {item.module}")
        aliases = {name: bound for name, bound in source.bindings.items() if bound in modules}
        for node in ast.walk(source.tree):
            if not isinstance(node, ast.Attribute):
                continue
            chain, base = [node.attr], node.value
            while isinstance(base, ast.Attribute):
                chain.insert(0, base.attr)
                base = base.value
            if not isinstance(base, ast.Name) or base.id not in aliases:
                continue
            owner = aliases[base.id]
            for attr in chain:
                if is_private(attr):
                    if owner != source.module:
                        problems.append(f"{source.name}:{node.lineno}: uses {owner}.{attr}")
                    break
                if f"{owner}.{attr}" not in modules:
                    break
                owner = f"{owner}.{attr}"
    return sorted(set(problems))


def import_graph(modules: Mapping[str, Source]) -> dict[str, set[str]]:
    """Module -> the surffin modules it imports (every import, at any depth)."""
    return {
        module: {target for item in source.imports for target in targets(item, modules) if target in modules}
        for module, source in modules.items()
    }


def cycles(modules: Mapping[str, Source]) -> list[list[str]]:
    """The import cycles: strongly connected components of more than one module, or a module importing itself."""
    graph = import_graph(modules)
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:  # Tarjan's algorithm
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in graph[node]:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def report(root: Path = ROOT) -> str:
    """Modules per layer and the imports checked, as a short text table."""
    modules = read_package(root)
    clients = read_clients(root)
    graph = import_graph(modules)
    rows = [f"{'layer':<9} {'modules':>7}  {'surffin imports':>15}  may import"]
    for layer in LAYERS:
        members = [module for module in modules if layer_of(module) == layer]
        edges = sum(len(graph[module]) for module in members)
        below = ", ".join(name for name in LAYERS if name in MAY_IMPORT[layer] - {layer}) or "-"
        rows.append(f"{layer:<9} {len(members):>7}  {edges:>15}  {below}")
    statements = sum(len(source.imports) for source in modules.values())
    folders = ", ".join(folder for folder in CLIENTS if (root / folder).is_dir())
    rows.append(
        f"layers and cycles: {len(modules)} modules, {statements} imported names, "
        f"{sum(map(len, graph.values()))} distinct imports of surffin modules"
    )
    rows.append(
        f"private names: those modules and {len(clients)} files of {folders}, "
        f"{statements + sum(len(source.imports) for source in clients)} imported names"
    )
    return "\n".join(rows)


# --- the repository ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def modules():
    return read_package(ROOT)


def test_every_module_is_in_a_layer_and_imports_downwards(modules):
    assert {"surffin.paper", "surffin.simulate.acquire", "surffin.pipeline.analyses"} <= set(modules)
    assert layer_violations(modules) == []


def test_the_simulator_imports_no_method_code(modules):
    simulator = {module: source for module, source in modules.items() if layer_of(module) == "simulate"}
    assert {"surffin.simulate.instrument", "surffin.simulate.truth", "surffin.simulate.acquire"} <= set(simulator)
    assert not MAY_IMPORT["simulate"] & {"method", "analysis", "report", "pipeline", "top"}
    assert layer_violations(simulator) == []


def test_no_private_name_crosses_a_module(modules):
    assert private_violations([*modules.values(), *read_clients(ROOT)], modules) == []


def test_no_import_cycle(modules):
    assert cycles(modules) == []


def test_no_test_module_imports_another():
    tests = {path.stem for path in (ROOT / "tests").glob("test_*.py")}
    clients = read_clients(ROOT, ("tests",))
    imported = {
        (source.name, item.module if item.name is None else f"{item.module}.{item.name}")
        for source in clients
        for item in source.imports
    }
    assert {(name, module) for name, module in imported if module.split(".")[0] in tests} == set()
    assert len(clients) >= len(tests) > 20


def test_report(capsys):
    text = report()
    with capsys.disabled():
        print(f"\n{text}")
    assert text.splitlines()[1].startswith("base")


# --- the checks find what they look for --------------------------------------------------------


def write_package(root: Path, files: Mapping[str, str]) -> dict[str, Source]:
    """A synthetic surffin package under ``root`` (empty ``__init__.py`` where none is given)."""
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for path in list(root.rglob("*.py")):
        for folder in path.relative_to(root).parents[:-1]:
            (root / folder / "__init__.py").touch()
    return read_package(root)


def test_the_layer_check_sees_every_form_of_import(tmp_path):
    modules = write_package(
        tmp_path,
        {
            "surffin/method/scattering.py": "",
            "surffin/method/geometry.py": "",
            "surffin/method/stages.py": "",
            "surffin/method/calibration.py": "",
            "surffin/simulate/scene.py": "",
            "surffin/simulate/sample.py": (
                "import numpy\nfrom surffin.method import calibration\n"
                "from ..method.scattering import scattering_model\n"
                "from .scene import render\ndef f():\n    import surffin.method.geometry as g\n"
                "if False:\n    from surffin.method.stages import process_item\n"
            ),
            "surffin/grid.py": (
                "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from surffin.io.campaign import Campaign\n"
            ),
            "surffin/io/campaign.py": "",
            "surffin/analysis/diagnostics.py": "def plot():\n    from surffin.report import figures\n",
            "surffin/report/figures.py": "from surffin.pipeline.jobs import logging_to\n",
            "surffin/pipeline/jobs.py": "from surffin import cli\n",
            "surffin/cli.py": "from surffin.pipeline import jobs\n",
            "surffin/extra.py": "",
        },
    )
    assert layer_violations(modules) == [
        "surffin.analysis.diagnostics:2: analysis imports surffin.report (report)",
        "surffin.analysis.diagnostics:2: analysis imports surffin.report.figures (report)",
        "surffin.extra: in no layer (add it to tests/test_layers.py)",
        "surffin.grid:3: base imports surffin.io.campaign (io)",
        "surffin.pipeline.jobs:1: pipeline imports surffin (top)",
        "surffin.pipeline.jobs:1: pipeline imports surffin.cli (top)",
        "surffin.report.figures:1: report imports surffin.pipeline.jobs (pipeline)",
        "surffin.simulate.sample:2: simulate imports surffin.method (method)",
        "surffin.simulate.sample:2: simulate imports surffin.method.calibration (method)",
        "surffin.simulate.sample:3: simulate imports surffin.method.scattering (method)",
        "surffin.simulate.sample:6: simulate imports surffin.method.geometry (method)",
        "surffin.simulate.sample:8: simulate imports surffin.method.stages (method)",
    ]


def test_the_private_check_sees_imports_and_attributes(tmp_path):
    modules = write_package(
        tmp_path,
        {
            "surffin/method/features.py": "_helper = 1\nvalue = _helper\n",
            "surffin/method/classify.py": (
                "from surffin.method.features import _helper, value\nfrom .features import _helper as h\n"
            ),
            "surffin/method/stages.py": (
                "import surffin.method.features\nimport surffin.method.features as f\n"
                "from surffin.method import features\n"
                "a = f._helper\nb = features._helper\nc = surffin.method.features._helper\nd = f.__name__\n"
            ),
        },
    )
    client = tmp_path / "tests" / "test_x.py"
    client.parent.mkdir()
    client.write_text("import numpy as np\nfrom surffin.method.features import _helper\nnp._private = 1\n")
    found = private_violations([*modules.values(), *read_clients(tmp_path)], modules)
    assert found == sorted(
        [
            "tests/test_x.py:2: imports _helper from surffin.method.features",
            "surffin.method.classify:1: imports _helper from surffin.method.features",
            "surffin.method.classify:2: imports _helper from surffin.method.features",
            "surffin.method.stages:4: uses surffin.method.features._helper",
            "surffin.method.stages:5: uses surffin.method.features._helper",
            "surffin.method.stages:6: uses surffin.method.features._helper",
        ]
    )


def test_the_cycle_check_counts_function_level_imports(tmp_path):
    modules = write_package(
        tmp_path,
        {
            "surffin/simulate/acquire.py": "from surffin.simulate.command import FORMATS\n",
            "surffin/simulate/command.py": "def run():\n    from .acquire import simulate_campaign\n",
            "surffin/simulate/plan.py": "from surffin.simulate import scene\n",
            "surffin/simulate/scene.py": "",
            "surffin/io/store.py": "import surffin.io.store\n",
        },
    )
    assert cycles(modules) == [["surffin.io.store"], ["surffin.simulate.acquire", "surffin.simulate.command"]]


def main() -> int:
    print(report())
    return 0


if __name__ == "__main__":
    sys.exit(main())
