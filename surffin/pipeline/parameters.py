"""Processing parameters: the workflow's config keys -> the keyword arguments of each stage.

One mapping, read by the workflow's rules and by the benchmarks alike, so that
both run the same method (a renamed key is changed here only). ``config`` is
the workflow's configuration (``config/config.yaml``, validated against
``workflow/schemas/config.schema.yaml``); :func:`read_config` loads that file
for code that runs without snakemake.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import yaml

__all__ = [
    "DEFAULT_CONFIG",
    "KEYWORDS",
    "read_config",
    "calibration_parameters",
    "aoi_parameters",
    "registration_parameters",
    "feature_parameters",
    "label_parameters",
    "evaluation_parameters",
]

#: The repository's configuration file (present in a source checkout).
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "config" / "config.yaml"


def read_config(path: str | os.PathLike = DEFAULT_CONFIG) -> dict:
    """Read the workflow configuration in ``path`` (safe YAML)."""
    with open(path, encoding="utf-8") as stream:
        return yaml.safe_load(stream)


#: Per stage function: its config section and, per keyword argument, the config key that sets it.
KEYWORDS = {
    "calibration": (
        "calibration",
        {
            "window": "aoi_window",
            "jump": "aoi_jump",
            "max_window": "aoi_max_window",
            "min_obs": "min_observations",
            "angular_smoothing": "angular_smoothing",
            "residual_correction": "residual_correction",
        },
    ),
    "aoi": ("aoi", {"window": "window", "jump": "jump", "max_window": "max_window"}),
    "registration": (
        "registration",
        {
            "method": "method",
            "refine": "refine_poses",
            "max_translation": "max_pose_correction_mm",
            "max_rotation": "max_pose_correction_deg",
        },
    ),
    "features": (
        "features",
        {
            "size": "smoothing",
            "variability_size": "variability_window",
            "min_views": "min_views",
            "min_spread": "min_aoi_spread_deg",
        },
    ),
    "labels": (
        "classify",
        {
            "k": "k",
            "filter_kind": "filter",
            "filter_size": "filter_size",
            "min_posterior": "min_posterior",
            "outlier_probability": "outlier_probability",
        },
    ),
}


def _keywords(config: Mapping, stage: str) -> dict:
    section, keys = KEYWORDS[stage]
    return {keyword: config[section][key] for keyword, key in keys.items()}


def calibration_parameters(config: Mapping) -> dict:
    """Keyword arguments of :func:`surffin.method.calibration.calibrate`."""
    return _keywords(config, "calibration")


def aoi_parameters(config: Mapping) -> dict:
    """Keyword arguments of :func:`surffin.method.stages.aoi_stage`."""
    return _keywords(config, "aoi")


def registration_parameters(config: Mapping) -> dict:
    """Keyword arguments of :func:`surffin.method.stages.registration_stage` (without the item's roi).

    ``size`` is the features' smoothing window: around a roi, what the features there read is registered.
    """
    keywords = _keywords(config, "registration")
    return keywords | {
        "max_translation": keywords["max_translation"] / 1000.0,
        "size": feature_parameters(config)["size"],
    }


def feature_parameters(config: Mapping) -> dict:
    """Keyword arguments of :func:`surffin.method.stages.features_stage` (without the item's roi)."""
    keywords = _keywords(config, "features")
    return keywords | {"min_spread": math.radians(keywords["min_spread"])}


def label_parameters(config: Mapping) -> dict:
    """Keyword arguments of :func:`surffin.method.stages.labels_stage`."""
    return _keywords(config, "labels")


def evaluation_parameters(config: Mapping) -> dict:
    """Return the keyword arguments of :func:`surffin.analysis.evaluation.evaluate_campaign` that ``config`` sets."""
    return {
        "calibration_params": calibration_parameters(config),
        "aoi_params": aoi_parameters(config),
        "feature_params": feature_parameters(config),
        "label_params": label_parameters(config),
        "method": config["registration"]["method"],
        "max_per_class": config["classify"]["max_training_samples"],
    }
