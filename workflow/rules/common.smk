import re
import zlib
from pathlib import Path
from types import SimpleNamespace

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

import surffin
import surffin.method.roughness
from surffin.method.calibration import calibration_set
from surffin.analysis.diagnostics import representative_specimens
from surffin.errors import SurffinError
from surffin.pipeline.parameters import aoi_parameters, calibration_parameters, feature_parameters, label_parameters

validate(config, "../schemas/config.schema.yaml")

DEFAULT_CAMPAIGN = Path(workflow.basedir, "data", "raw").resolve()
CAMPAIGN = Path(config["campaign"])
PROCESSED = config["processed"]
LOGS = config["logs"]
ENV = "../envs/surffin.yaml"

# The jobs on the way to summary.json run first: the calibration, each item's chain, the
# training set, labels and the summary. The other jobs (calibration diagnostics, sensitivity,
# figures) take the cores left over, and so fill the second core while training, labels and
# summary run one after another at the end. Without priorities snakemake's greedy scheduler
# prefers the jobs with the largest inputs: the diagnostics held a core while items waited, and
# the end of a run left a core idle (benchmarks/bench_campaign.py).
RESULTS_FIRST = 10

# Code version of each stage: bump it when a change to surffin alters what the
# stage writes, so that snakemake's params trigger reruns exactly that stage
# and what depends on it.
STAGE_VERSION = {
    "ingest": 1,
    "calibration": 3,
    "aoi": 2,
    "reflectance": 2,
    "registration": 1,
    "features": 3,
    "training": 3,
    "labels": 3,
    "summary": 2,
    "figures": 2,
    "roughness": 1,
    "sensitivity": 1,
    "diagnostics": 1,
    "comparison": 2,
}


def load_campaign():
    """The validated campaign; renders the default one first when it is absent."""
    if CAMPAIGN.resolve() == DEFAULT_CAMPAIGN and not (CAMPAIGN / "campaign.yaml").exists():
        preset = config["default_campaign"]["preset"]
        seed = config["default_campaign"]["seed"]
        print(f"surffin: rendering the default campaign (preset {preset}, seed {seed}) into {CAMPAIGN}")
        surffin.simulate_campaign(CAMPAIGN, preset=preset, seed=seed)
    try:
        camp = surffin.read_campaign(CAMPAIGN, require_calibration=config["calibration_store"] is None)
        if config["calibration_store"] is not None:
            from surffin.pipeline.run import check_calibration

            check_calibration(config["calibration_store"], camp)
        return camp
    except SurffinError as exc:
        raise WorkflowError(str(exc)) from None


CAMP = load_campaign()
CALIBRATION = config["calibration_store"] or f"{PROCESSED}/calibration.zarr"


def load_repeat_calibration():
    """The repeat calibration set, checked, when config names its folders and the campaign has them; else None."""
    folders = config["calibration_repeat"]
    if folders is None or CAMP.calibration is None:
        return None
    if not all((CAMP.root / folder).is_dir() for folder in folders.values()):
        return None
    try:
        return calibration_set(CAMP, folders["wall"], folders["reference"])
    except SurffinError as exc:
        raise WorkflowError(str(exc)) from None


REPEAT = load_repeat_calibration()


wildcard_constraints:
    item="|".join(re.escape(name) for name in CAMP.items),
    scene="|".join(re.escape(name) for name in CAMP.scenes) or "(?!)",


def roi_of(name):
    roi = CAMP.items[name].roi
    return None if roi is None else {"y": list(roi.y), "x": list(roi.x)}


def item_views(wildcards):
    """The view files of one item, so that replacing one reruns its chain."""
    return [str(path) for path in CAMP.items[wildcards.item].views]


def item_settings(wildcards):
    """What campaign.yaml says about one item and the camera: a change reruns that item."""
    item = CAMP.items[wildcards.item]
    camera = CAMP.camera
    return {
        "crop": {"y": list(CAMP.crop.y), "x": list(CAMP.crop.x)},
        "camera": {
            "width": camera.width,
            "height": camera.height,
            "units": camera.units,
            "abcy16": camera.abcy16,
            "intrinsics": camera.intrinsics,
        },
        "reference": item.reference,
        "class": item.cls,
    }


def item_roi(wildcards):
    return roi_of(wildcards.item)


def aoi_params(wildcards):
    return aoi_parameters(config)


def registration_params(wildcards):
    return {"method": config["registration"]["method"], "roi": roi_of(wildcards.item)}


def feature_params(wildcards):
    return {"roi": roi_of(wildcards.item), **feature_parameters(config)}


def item_stage_params(wildcards):
    """Each stage's parameters for one item, when one job runs its whole chain (config jobs: item)."""
    return {
        "aoi": aoi_params(wildcards),
        "reflectance": {},
        "registration": registration_params(wildcards),
        "features": feature_params(wildcards),
    }


def calibration_views(wildcards):
    cal = CAMP.calibration
    return [str(path) for path in (*cal.wall, *cal.reference.views)]


def calibration_settings(wildcards):
    ref = CAMP.calibration.reference
    return {"reflectance": ref.reflectance, "roi": {"y": list(ref.roi.y), "x": list(ref.roi.x)}}


def repeat_calibration_views(wildcards):
    if REPEAT is None:
        raise WorkflowError(
            f"no repeat calibration set in {CAMPAIGN}: calibration_repeat is null or names folders the campaign lacks"
        )
    return [str(path) for path in (*REPEAT.wall, *REPEAT.reference.views)]


def repeat_calibration_store(wildcards):
    """The repeat calibration store when there is a repeat set; else none (the diagnostics say why)."""
    return [] if REPEAT is None else f"{PROCESSED}/diagnostics/calibration-repeat.zarr"


def diagnostics_views(wildcards):
    """The campaign's wall views and the views of the specimens the calibration diagnostics reprocess."""
    wall = () if CAMP.calibration is None else CAMP.calibration.wall
    specimens = [CAMP.specimens[name] for name in representative_specimens(CAMP)]
    return [str(path) for path in (*wall, *(view for item in specimens for view in item.views))]


def diagnostics_settings(wildcards):
    """The crop and the specimens' rois and reference views: a change reruns the diagnostics."""
    return {
        "crop": {"y": list(CAMP.crop.y), "x": list(CAMP.crop.x)},
        "specimens": {
            name: {"roi": roi_of(name), "reference": CAMP.specimens[name].reference}
            for name in representative_specimens(CAMP)
        },
    }


def diagnostics_item_params(wildcards):
    """The registration, AOI and feature parameters the diagnostics process the specimens with."""
    return {"method": config["registration"]["method"], **aoi_parameters(config), **feature_parameters(config)}


def features_of(names):
    return {name: f"{PROCESSED}/features/{name}.zarr" for name in names}


def specimen_features(wildcards):
    return features_of(CAMP.specimens)


def specimen_settings(wildcards):
    return {
        name: {"store": f"{PROCESSED}/features/{name}.zarr", "class": item.cls, "roi": roi_of(name)}
        for name, item in CAMP.specimens.items()
    }


ROUGH_SPECIMENS = [name for name, item in CAMP.specimens.items() if item.roughness_mm is not None]


def roughness_settings(wildcards):
    specimens = specimen_settings(wildcards)
    return {name: {**specimens[name], "roughness_mm": CAMP.items[name].roughness_mm} for name in ROUGH_SPECIMENS}


def roughness_features(wildcards):
    return features_of(ROUGH_SPECIMENS)


def roughness_outputs():
    """The relation and the scenes' maps, when enough specimens carry a roughness."""
    if len(ROUGH_SPECIMENS) < surffin.method.roughness.MIN_SPECIMENS:
        return []
    return [
        f"{PROCESSED}/roughness/relation.json",
        *expand(f"{PROCESSED}/roughness/{{scene}}.zarr", scene=CAMP.scenes),
        *expand(f"{PROCESSED}/figures/roughness/{{scene}}.png", scene=CAMP.scenes),
    ]


def specimens_by_roughness(wildcards):
    """Specimen names from the smoothest to the roughest (campaign order where roughness is unknown)."""
    order = {name: item.roughness_mm for name, item in CAMP.specimens.items()}
    return sorted(CAMP.specimens, key=lambda name: (order[name] is None, order[name] or 0.0))


def comparison_inputs(wildcards):
    inputs = {
        "summary": f"{PROCESSED}/summary.json",
        "diagnostics": f"{PROCESSED}/diagnostics/calibration.json",
        "sensitivity": f"{PROCESSED}/sensitivity/sensitivity.zarr",
        "slopes": f"{PROCESSED}/sensitivity/slopes.csv",
    }
    if roughness_outputs():
        inputs["relation"] = f"{PROCESSED}/roughness/relation.json"
    return inputs


# The stages of an item's chain from view files to features, and their rules (config jobs);
# then a scene's labels.
CHAIN_STAGES = ("ingest", "aoi", "reflectance", "registration", "features")
ITEM_RULES = ("item",) if config["jobs"] == "item" else CHAIN_STAGES
SCENE_RULES = (*ITEM_RULES, "labels")


# --- config jobs: item (item.smk) ---


def chain_stores(item):
    """An item's chain stores by name, as pipeline.run_item writes them (item may be "{item}")."""
    return {
        "ingest": f"{PROCESSED}/ingest/{item}.zarr",
        "aoi": f"{PROCESSED}/aoi/{item}.zarr",
        "reflectance": f"{PROCESSED}/reflectance/{item}.zarr",
        "registered": f"{PROCESSED}/registered/{item}.zarr",
        "features": f"{PROCESSED}/features/{item}.zarr",
    }


def chains(names):
    """What an item or batch job runs, per item: its stores and stage parameters, and (rerun
    triggers only) what campaign.yaml says about it. Each item's are those of its own item job,
    whose wildcards a namespace stands in for."""
    return {
        name: {
            "stores": chain_stores(name),
            "params": item_stage_params(SimpleNamespace(item=name)),
            "settings": item_settings(SimpleNamespace(item=name)),
        }
        for name in names
    }


def item_batches():
    """Batch number -> its specimens (config item_batches; none when 0 or jobs: stage).

    A specimen's batch is the CRC-32 of its name modulo the number of batches: it
    stays in its batch as other specimens come and go, so adding one reruns its
    batch only.
    """
    count = config["item_batches"] if config["jobs"] == "item" else 0
    batches = {}
    for name in CAMP.specimens if count else ():
        batches.setdefault(zlib.crc32(name.encode()) % count, []).append(name)
    return dict(sorted(batches.items()))


def batch_views(names):
    """The input function of a batch job's view files (each of its items')."""
    return lambda wildcards: [view for name in names for view in item_views(SimpleNamespace(item=name))]


BATCHED = {name for names in item_batches().values() for name in names}
# The params of item and batch jobs besides their chains.
CHAIN_JOB_PARAMS = {
    "campaign": str(CAMPAIGN),
    "chunks": config["chunks"],
    "scheduler": config["scheduler"],
    "code": {stage: STAGE_VERSION[stage] for stage in CHAIN_STAGES},
}


def runtime_settings(wildcards):
    """Per scene, its view count and the benchmark files of its rules' jobs from raw views to labels."""
    return {
        name: {
            "views": len(item.views),
            "benchmarks": [expand(getattr(rules, rule).benchmark, item=name, scene=name)[0] for rule in SCENE_RULES],
        }
        for name, item in CAMP.scenes.items()
    }


def runtime_benchmarks(wildcards):
    return [path for spec in runtime_settings(wildcards).values() for path in spec["benchmarks"]]


def scene_truth(wildcards):
    camera = CAMP.camera
    return {
        name: {"path": str(item.truth), "width": camera.width, "height": camera.height}
        for name, item in CAMP.scenes.items()
        if item.truth is not None
    }


def summary_features(wildcards):
    return {name: {"store": f"{PROCESSED}/features/{name}.zarr", "roi": roi_of(name)} for name in CAMP.items}


def truth_files(wildcards):
    return [spec["path"] for spec in scene_truth(wildcards).values()]


def item_stores(stage):
    return expand(f"{PROCESSED}/{stage}/{{item}}.zarr", item=CAMP.items)


def figure_items():
    """The items whose feature figure is drawn (config item_figures)."""
    return {"all": list(CAMP.items), "scenes": list(CAMP.scenes), "none": []}[config["item_figures"]]


def final_outputs(wildcards):
    return [
        *item_stores("features"),
        *expand(f"{PROCESSED}/labels/{{scene}}.zarr", scene=CAMP.scenes),
        f"{PROCESSED}/summary.json",
        *roughness_outputs(),
    ]
