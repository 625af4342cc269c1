import re
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

import surffin
from surffin.errors import SurffinError


validate(config, "../schemas/config.schema.yaml")

DEFAULT_CAMPAIGN = Path(workflow.basedir, "data", "raw").resolve()
CAMPAIGN = Path(config["campaign"])
PROCESSED = config["processed"]
LOGS = config["logs"]

# Code version of each stage: bump it when a change to surffin alters what the
# stage writes, so that snakemake's params trigger reruns exactly that stage.
STAGE_VERSION = {
    "ingest": 1,
}


def load_campaign():
    """The validated campaign; renders the default one first when it is absent."""
    if CAMPAIGN.resolve() == DEFAULT_CAMPAIGN and not (CAMPAIGN / "campaign.yaml").exists():
        preset = config["default_campaign"]["preset"]
        seed = config["default_campaign"]["seed"]
        print(f"surffin: rendering the default campaign (preset {preset}, seed {seed}) into {CAMPAIGN}")
        surffin.simulate_campaign(CAMPAIGN, preset=preset, seed=seed)
    try:
        return surffin.read_campaign(CAMPAIGN, require_calibration=config["calibration_store"] is None)
    except SurffinError as exc:
        raise WorkflowError(str(exc)) from None


CAMP = load_campaign()


wildcard_constraints:
    item="|".join(re.escape(name) for name in CAMP.items),


def item_views(wildcards):
    """The view files of one item, so that replacing one reruns its chain."""
    return [str(path) for path in CAMP.items[wildcards.item].views]


def item_settings(wildcards):
    """What campaign.yaml says about one item and the camera: a change reruns that item."""
    item = CAMP.items[wildcards.item]
    camera = CAMP.camera
    return {
        "crop": {"y": list(CAMP.crop.y), "x": list(CAMP.crop.x)},
        "camera": {"width": camera.width, "height": camera.height, "units": camera.units, "abcy16": camera.abcy16},
        "reference": item.reference,
        "class": item.cls,
    }


def ingest_stores(wildcards):
    return expand(f"{PROCESSED}/ingest/{{item}}.zarr", item=CAMP.items)
