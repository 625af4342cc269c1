"""The one config -> keyword mapping (surffin.pipeline.parameters) against the functions and the schema."""

import inspect
import math

import pytest
import yaml

from surffin.analysis.evaluation import evaluate_campaign
from surffin.method.calibration import calibrate
from surffin.method.stages import aoi_stage, features_stage, labels_stage, registration_stage
from surffin.pipeline import parameters

SCHEMA = parameters.DEFAULT_CONFIG.parent.parent / "workflow" / "schemas" / "config.schema.yaml"


@pytest.mark.parametrize(
    ("mapping", "function"),
    [
        (parameters.calibration_parameters, calibrate),
        (parameters.aoi_parameters, aoi_stage),
        (parameters.registration_parameters, registration_stage),
        (parameters.feature_parameters, features_stage),
        (parameters.label_parameters, labels_stage),
        (parameters.evaluation_parameters, evaluate_campaign),
    ],
)
def test_every_keyword_is_a_parameter_of_its_function(mapping, function):
    keywords = mapping(parameters.read_config())
    accepted = inspect.signature(function).parameters
    assert keywords and set(keywords) <= set(accepted), set(keywords) - set(accepted)


def test_every_mapped_key_is_in_the_config_and_the_schema():
    config = parameters.read_config()
    schema = yaml.safe_load(SCHEMA.read_text())["properties"]
    for section, keys in parameters.KEYWORDS.values():
        for key in keys.values():
            assert key in config[section], (section, key)
            assert key in schema[section]["properties"], (section, key)


def test_values_come_from_the_config_with_their_units():
    config = parameters.read_config()
    config["features"]["min_aoi_spread_deg"] = 30.0
    config["aoi"]["max_window"] = 60
    config["calibration"]["aoi_window"] = 9
    assert parameters.feature_parameters(config)["min_spread"] == pytest.approx(math.pi / 6)
    assert parameters.aoi_parameters(config)["max_window"] == 60
    assert parameters.calibration_parameters(config)["window"] == 9
    config["registration"]["max_pose_correction_mm"] = 4.0
    assert parameters.registration_parameters(config)["max_translation"] == pytest.approx(0.004)


def test_default_registration_config_gives_the_stage_defaults():
    defaults = inspect.signature(registration_stage).parameters
    for keyword, value in parameters.registration_parameters(parameters.read_config()).items():
        assert value == pytest.approx(defaults[keyword].default), keyword
