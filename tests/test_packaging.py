"""Packaging and workflow conventions: floors, config reference, citation, catalog file.

Run as a script (``python tests/test_packaging.py``) to rewrite ``config/README.md`` from the schema.
"""

import ast
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import xarray as xr
import yaml
from packaging.requirements import Requirement
from packaging.version import Version

from surffin.io.store import provenance, write_store
from surffin.paper import DOI

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
CONFIG_README = REPO / "config" / "README.md"


def pyproject():
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def floors_in_pyproject():
    """Package name -> floor version of every dependency with one (core and extras but test tools)."""
    project = pyproject()["project"]
    declared = [
        *project["dependencies"],
        *(project["optional-dependencies"][extra] for extra in ("workflow", "distributed")),
    ]
    floors = {}
    for entry in declared:
        for text in [entry] if isinstance(entry, str) else entry:
            requirement = Requirement(text)
            lower = [spec.version for spec in requirement.specifier if spec.operator == ">="]
            floors[requirement.name.lower()] = Version(lower[0])
    return floors


def pinned_floors():
    lines = (REPO / ".ci" / "floors.txt").read_text().splitlines()
    pins = [Requirement(line) for line in lines if line.strip() and not line.startswith("#")]
    return {pin.name.lower(): Version(next(iter(pin.specifier)).version) for pin in pins}


def test_ci_floors_pin_exactly_the_pyproject_floors():
    assert pinned_floors() == floors_in_pyproject()


def test_identical_inputs_give_identical_stores(tmp_path):
    # why zarr's floor is 3.1.2: before it, consolidated metadata listed the arrays in the order their writes ended
    rng = np.random.default_rng(0)
    data = {f"v{index}": (("y", "x"), rng.random((20, 30), dtype=np.float32)) for index in range(12)}
    ds = xr.Dataset(data, coords={"y": np.arange(20), "x": np.arange(30)}, attrs=provenance("test", {"k": 1}))
    stores = [write_store(ds, tmp_path / f"{name}.zarr", chunks={"y": 8, "x": 8}) for name in "ab"]
    files = [sorted(path for path in store.rglob("*") if path.is_file()) for store in stores]
    assert [path.relative_to(stores[0]) for path in files[0]] == [path.relative_to(stores[1]) for path in files[1]]
    assert [path.read_bytes() for path in files[0]] == [path.read_bytes() for path in files[1]]


def test_the_library_imports_without_the_workflow_or_distributed():
    # a plain `pip install surffin` has neither snakemake nor distributed: the package must not need them
    code = (
        "import sys; sys.modules['snakemake'] = None; sys.modules['distributed'] = None; "
        "import surffin, surffin.cli, surffin.pipeline.run, surffin.pipeline.analyses, surffin.report.export"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr


def test_every_imported_third_party_package_is_declared():
    imported = set()
    for path in (REPO / "surffin").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                imported.add(node.module.split(".")[0])
    declared = {Requirement(text).name.lower() for text in pyproject()["project"]["dependencies"]}
    import_names = {"cv2": "opencv-python-headless", "sklearn": "scikit-learn", "yaml": "pyyaml", "PIL": "pillow"}
    optional = {"distributed"}  # imported only when a dask.distributed scheduler is asked for
    third_party = {name for name in imported if name not in sys.stdlib_module_names and name != "surffin"}
    assert {import_names.get(name, name).lower() for name in third_party} - optional <= declared


def schema_keys(schema, prefix=""):
    """(dotted key, schema) of every leaf of the config schema, in its order."""
    for name, spec in schema["properties"].items():
        key = f"{prefix}{name}"
        if spec.get("type") == "object" and "properties" in spec and prefix == "":
            yield from schema_keys(spec, f"{key}.")
        else:
            yield key, spec


def config_reference():
    """config/README.md as the schema says it."""
    schema = yaml.safe_load(SCHEMA.read_text())
    lines = [
        "# Configuration keys",
        "",
        "Every key of `config/config.yaml`, one line each, from `workflow/schemas/config.schema.yaml`",
        "(regenerate with `python tests/test_packaging.py`; `tests/test_packaging.py` checks it is current).",
        "Override any on the command line: `snakemake --cores 2 --config KEY=VALUE`.",
        "",
    ]
    for key, spec in schema_keys(schema):
        kind = spec.get("type", "object" if "properties" in spec else "")
        kind = " or ".join(kind) if isinstance(kind, list) else kind
        default = yaml.safe_dump(spec.get("default"), default_flow_style=True).removesuffix("\n...\n").strip()
        default = f", default `{default}`" if "default" in spec else ""
        description = " ".join(spec.get("description", "").split())
        lines.append(f"- `{key}` ({kind}{default}): {description}")
    return "\n".join(lines) + "\n"


def test_config_reference_is_the_schemas():
    assert CONFIG_README.read_text() == config_reference(), "run: python tests/test_packaging.py"


def test_config_reference_names_every_key_of_the_default_config():
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    text = CONFIG_README.read_text()
    for name, value in config.items():
        keys = (
            [f"{name}.{sub}" for sub in value] if isinstance(value, dict) and name != "calibration_repeat" else [name]
        )
        for key in keys:
            assert f"- `{key}` (" in text, key


def test_citation_prefers_the_paper():
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["version"] == __import__("surffin").__version__
    preferred = citation["preferred-citation"]
    assert preferred["title"] == "Surface finish classification using depth camera data"
    assert (preferred["journal"], preferred["year"], preferred["doi"]) == ("Automation in Construction", 2021, DOI)
    assert [author["family-names"] for author in preferred["authors"]] == ["Frangez", "Salido-Monzú", "Wieser"]


def test_license_file_is_shipped_and_typed_marker_present():
    project = pyproject()
    assert project["project"]["license-files"] == ["LICENSE"] and (REPO / "LICENSE").read_text().startswith("BSD 3")
    assert (REPO / "surffin" / "py.typed").is_file()
    assert "py.typed" in project["tool"]["setuptools"]["package-data"]["surffin"]


def test_workflow_catalog_file_names_the_run_flags_and_no_rule_asks_for_conda():
    catalog = yaml.safe_load((REPO / ".snakemake-workflow-catalog.yml").read_text())
    flags = catalog["usage"]["mandatory-flags"]["flags"]
    assert "--config campaign=" in flags and "processed=" in flags
    # every rule is a run: block, which snakemake runs in its own environment, never in a conda env or container
    assert catalog["usage"]["software-stack-deployment"] == {"conda": False, "singularity": False}
    workflow = [REPO / "Snakefile", *(REPO / "workflow" / "rules").glob("*.smk")]
    assert not [path.name for path in workflow if re.search(r"^\s+(conda|container):", path.read_text(), re.M)]


if __name__ == "__main__":
    CONFIG_README.write_text(config_reference())
    print(f"wrote {CONFIG_README}")
