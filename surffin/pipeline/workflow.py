"""What the workflow's rules need to know about a campaign: its jobs' files, settings and parameters.

A :class:`Plan` joins a validated campaign, the configuration and the stage
table (:mod:`surffin.pipeline.table`); the input functions of
``workflow/rules/common.smk`` are one call each into it, so that the logic is
plain Python, testable without snakemake. Settings returned here go into
rules' ``params``: a change to one reruns the jobs that read it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from surffin.analysis.diagnostics import SPECIMEN_STORES, representative_specimens
from surffin.errors import CampaignError
from surffin.io.campaign import Calibration, Campaign, check_pixels, read_campaign
from surffin.io.files import write_json
from surffin.io.viewfile import view_sidecars
from surffin.method.calibration import calibration_set, check_calibration
from surffin.method.roughness import MIN_SPECIMENS
from surffin.pipeline.parameters import aoi_parameters, feature_parameters, registration_parameters
from surffin.pipeline.table import output_path

__all__ = ["Plan", "CHECKED_VIEWS"]

#: Under the processed folder: the view files whose pixels were checked, their sizes and times.
CHECKED_VIEWS = "checked_views.json"


def _with_sidecars(views) -> list[str]:
    # A view's pose and settings sidecars are inputs of the jobs that read it: editing one reruns them.
    return [str(path) for view in views for path in (view, *view_sidecars(view))]


def _record(config: Mapping) -> dict | None:
    """Return the processed folder's record of checked view files; None when absent or unreadable (all are read)."""
    try:
        record = json.loads(Path(config["processed"], CHECKED_VIEWS).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and isinstance(record.get("views"), dict) else None


@dataclass(frozen=True)
class Plan:
    """The workflow's view of one campaign.

    Attributes
    ----------
    campaign : Campaign
        Validated.
    config : mapping
        The workflow configuration.
    repeat : Calibration or None
        The repeat calibration set, when configured and present.
    checked : dict
        What :func:`~surffin.io.campaign.check_pixels` returned for every view file a run reads.
    recorded : dict or None
        The processed folder's :data:`CHECKED_VIEWS` when the plan was read (None: none usable).
    """

    campaign: Campaign
    config: Mapping
    repeat: Calibration | None = None
    checked: dict = field(default_factory=dict)
    recorded: dict | None = None

    @classmethod
    def read(cls, path, config: Mapping) -> Plan:
        """Read and check the campaign at ``path`` (and ``calibration_store``, the repeat set) for ``config``.

        Every view file's pixels are read (:func:`~surffin.io.campaign.check_pixels`), but for those
        whose size and time the processed folder's :data:`CHECKED_VIEWS` records (:meth:`keep_checked`).

        Raises
        ------
        SurffinError
            The campaign, a view file, or the calibration store it is given, is not usable, or the campaign
            has scenes but nothing to train their classifier on (no specimens, no ``extra_training`` stores).
        """
        camp = read_campaign(path, require_calibration=config["calibration_store"] is None)
        if camp.scenes and not camp.specimens and not config["extra_training"]:
            raise CampaignError(
                f"{camp.path}: specimens: none, and the configuration names no extra_training stores, so there is "
                f"nothing to train the classifier of the scenes ({', '.join(camp.scenes)}) on; expected specimens "
                f"of known class in campaign.yaml, or training.zarr stores of other campaigns in the "
                f"configuration's extra_training"
            )
        if config["calibration_store"] is not None:
            check_calibration(config["calibration_store"], camp)
        folders = config["calibration_repeat"]
        present = folders is not None and camp.calibration is not None
        present = present and all((camp.root / folder).is_dir() for folder in folders.values())
        repeat = calibration_set(camp, folders["wall"], folders["reference"]) if present else None
        views = [*camp.view_files, *(() if repeat is None else (*repeat.wall, *repeat.reference.views))]
        recorded = _record(config)
        return cls(camp, config, repeat, check_pixels(camp, views, recorded), recorded)

    def keep_checked(self) -> None:
        """Record the checked view files (:data:`CHECKED_VIEWS`): the next run reads only new or changed ones."""
        if self.checked != self.recorded:
            write_json(Path(self.config["processed"], CHECKED_VIEWS), self.checked)

    # --- paths -------------------------------------------------------------------------------

    def output(self, stage: str, name: str | None = None) -> str:
        """Return a stage's output under the processed folder, for one item or scene (``{item}`` when None)."""
        return output_path(stage, self.config["processed"], name)

    def outputs(self, stage: str, names) -> list[str]:
        """Return a stage's outputs for the items or scenes ``names``."""
        return [self.output(stage, name) for name in names]

    # --- items -------------------------------------------------------------------------------

    def roi(self, name: str) -> dict | None:
        """Return an item's roi as a mapping, or None when it has none."""
        roi = self.campaign.items[name].roi
        return None if roi is None else roi.as_mapping()

    def item_views(self, name: str) -> list[str]:
        """Return an item's view files and their sidecars (pose, settings): a change to any reruns its ingest."""
        return _with_sidecars(self.campaign.items[name].views)

    def item_settings(self, name: str) -> dict:
        """Return what campaign.yaml says about one item and the camera: a change reruns that item."""
        item = self.campaign.items[name]
        return {
            "crop": self.campaign.crop.as_mapping(),
            "camera": self.campaign.camera.settings,
            "reference": item.reference,
            "class": item.cls,
        }

    def registration_parameters(self, name: str) -> dict:
        """Return an item's registration parameters: the configured ones and the item's roi.

        The features' window ``size`` sets the margin registered around a roi: an item without
        one is not given it, so that a change of the smoothing does not rerun its registration.
        """
        params = {**registration_parameters(self.config), "roi": self.roi(name)}
        return params if params["roi"] is not None else {key: params[key] for key in params if key != "size"}

    def feature_parameters(self, name: str) -> dict:
        """Return an item's feature parameters: its roi and the configured ones."""
        return {"roi": self.roi(name), **feature_parameters(self.config)}

    def features_of(self, names) -> dict[str, str]:
        """Return the features store of each of the items ``names``, by name."""
        return {name: self.output("features", name) for name in names}

    def specimen_features(self) -> dict[str, str]:
        """Return every specimen's features store, by name."""
        return self.features_of(self.campaign.specimens)

    def item_features(self) -> list[str]:
        """Return every item's features store."""
        return self.outputs("features", self.campaign.items)

    def scene_labels(self) -> dict[str, str]:
        """Return every scene's labels store, by name."""
        return {name: self.output("labels", name) for name in self.campaign.scenes}

    def scene_label_stores(self) -> list[str]:
        """Return every scene's labels store."""
        return list(self.scene_labels().values())

    def truth_files(self) -> list[str]:
        """Return the truth files of the scenes that have one."""
        return [spec["path"] for spec in self.scene_truth().values()]

    def specimen_settings(self) -> dict:
        """Return each specimen's features store, class and roi, by name."""
        return {
            name: {"store": self.output("features", name), "class": item.cls, "roi": self.roi(name)}
            for name, item in self.campaign.specimens.items()
        }

    def summary_features(self) -> dict:
        """Return each item's features store and roi, by name."""
        return {name: {"store": self.output("features", name), "roi": self.roi(name)} for name in self.campaign.items}

    def scene_truth(self) -> dict:
        """Return the truth file and the sensor size of each scene that has a truth, by name."""
        camera = self.campaign.camera
        return {
            name: {"path": str(item.truth), "width": camera.width, "height": camera.height}
            for name, item in self.campaign.scenes.items()
            if item.truth is not None
        }

    # --- calibration and its diagnostics -----------------------------------------------------

    def calibration_views(self) -> list[str]:
        """Return the calibration set's view files (the wall views, then the reference views) and their sidecars."""
        cal = self.campaign.calibration
        return _with_sidecars((*cal.wall, *cal.reference.views))

    def calibration_settings(self) -> dict:
        """Return the reference panel's reflectance and roi and the camera: a change reruns the calibration."""
        ref = self.campaign.calibration.reference
        return {"reflectance": ref.reflectance, "roi": ref.roi.as_mapping(), "camera": self.campaign.camera.settings}

    def repeat_views(self) -> list[str]:
        """Return the repeat calibration set's view files: the wall views, then the reference views."""
        return [str(path) for path in (*self.repeat.wall, *self.repeat.reference.views)]

    def diagnostics_views(self) -> list[str]:
        """Return the campaign's wall views and their sidecars, which the calibration diagnostics read."""
        calibration = self.campaign.calibration
        return [] if calibration is None else _with_sidecars(calibration.wall)

    def diagnostics_stores(self) -> dict[str, dict[str, str]]:
        """Return the stores of the specimens the calibration diagnostics reprocess with the repeat calibration.

        By specimen name (none without a repeat calibration set): they read them instead of processing the
        specimens with the campaign's calibration again.
        """
        if self.repeat is None:
            return {}
        return {
            name: {key: self.output(stage, name) for key, stage in SPECIMEN_STORES.items()}
            for name in representative_specimens(self.campaign)
        }

    def diagnostics_store_files(self) -> list[str]:
        """Return the files of :meth:`diagnostics_stores`."""
        return [path for stores in self.diagnostics_stores().values() for path in stores.values()]

    def diagnostics_settings(self) -> dict:
        """Return the crop and the specimens' rois and reference views: a change reruns the diagnostics."""
        camp = self.campaign
        return {
            "crop": camp.crop.as_mapping(),
            "specimens": {
                name: {"roi": self.roi(name), "reference": camp.specimens[name].reference}
                for name in representative_specimens(camp)
            },
        }

    def diagnostics_item_parameters(self) -> dict:
        """Return the registration, AOI and feature parameters the diagnostics process the specimens with."""
        config = self.config
        return {**registration_parameters(config), **aoi_parameters(config), **feature_parameters(config)}

    # --- roughness, figures, comparison ------------------------------------------------------

    @cached_property
    def rough_specimens(self) -> list[str]:
        """Specimens whose roughness is known, in campaign order."""
        return [name for name, item in self.campaign.specimens.items() if item.roughness_mm is not None]

    def roughness_features(self) -> dict[str, str]:
        """Return the features store of every specimen whose roughness is known, by name."""
        return self.features_of(self.rough_specimens)

    def roughness_settings(self) -> dict:
        """Return the features store, class, roi and roughness of each specimen whose roughness is known."""
        specimens = self.specimen_settings()
        return {
            name: {**specimens[name], "roughness_mm": self.campaign.items[name].roughness_mm}
            for name in self.rough_specimens
        }

    def roughness_outputs(self) -> list[str]:
        """Return the relation and the scenes' maps and figures, when enough specimens carry a roughness."""
        if len(self.rough_specimens) < MIN_SPECIMENS:
            return []
        processed = self.config["processed"]
        return [
            self.output("roughness_relation"),
            *self.outputs("roughness", self.campaign.scenes),
            *(f"{processed}/figures/roughness/{scene}.png" for scene in self.campaign.scenes),
        ]

    def specimens_by_roughness(self) -> list[str]:
        """Specimen names from the smoothest to the roughest (campaign order where roughness is unknown)."""
        order = {name: item.roughness_mm for name, item in self.campaign.specimens.items()}
        return sorted(self.campaign.specimens, key=lambda name: (order[name] is None, order[name] or 0.0))

    def figure_items(self) -> list[str]:
        """Return the items whose feature figure is drawn (config ``item_figures``)."""
        camp = self.campaign
        return {"all": list(camp.items), "scenes": list(camp.scenes), "none": []}[self.config["item_figures"]]

    def export_inputs(self) -> dict[str, str | list[str]]:
        """Return what the export reads: the training set, the summary, and the items' stores it draws on."""
        camp = self.campaign
        return {
            "training": self.output("training"),
            "summary": self.output("summary"),
            "labels": self.outputs("labels", camp.scenes),
            "aoi": self.outputs("aoi", camp.scenes),
            "features": self.outputs("features", camp.items),
            "ingest": self.outputs("ingest", camp.items),
        }

    def results(self) -> list[str]:
        """Every item's features, every scene's labels, the summary and the roughness outputs."""
        return [
            *self.outputs("features", self.campaign.items),
            *self.outputs("labels", self.campaign.scenes),
            self.output("summary"),
            *self.roughness_outputs(),
        ]
