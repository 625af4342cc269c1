"""Are the reported uncertainties calibrated? Coverage against the simulator's truth, paper preset.

Run by hand: ``python benchmarks/bench_uncertainty.py [--campaign DIR]``. Without
``--campaign`` it renders the ``paper`` preset into a temporary folder (truth in
``<campaign>-truth``). Each item is processed in memory as the workflow does
(calibration, then aoi, reflectance, registration, features, all with the
workflow's parameters). Scored pixels: at least the preset's ``label_margin``
from the edges of surfaces. Prints, per item and parameter, the share of pixels
whose true error lies within 1 and 2 reported uncertainties
(:func:`surffin.analysis.uncertainty.coverage`):

1. the per-pixel fit's ``R0_sigma`` / ``n_sigma`` against Student's t with
   ``n_views - 2`` degrees of freedom;
2. the smoothed features' uncertainty under three propagations: independent
   errors, the fully correlated bound, and the residual correlation the
   features store carries (0.683 and 0.954 when calibrated);
3. the scene's accuracy with the reject options of ``config/config.yaml``
   (``classify.min_posterior``, ``classify.outlier_probability``) and without them,
   with the unclassified pixels by reason.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import dask
import xarray as xr
from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script

from surffin.analysis.uncertainty import coverage
from surffin.io.campaign import read_truth
from surffin.io.ingest import ingest_item
from surffin.method.calibration import calibrate
from surffin.method.classify import score, training_set
from surffin.method.features import UNCERTAINTY, smooth_uncertainty
from surffin.method.stages import labels_stage, process_item
from surffin.pipeline import parameters


def propagated(feats: xr.Dataset, inflation: float) -> xr.Dataset:
    """``feats`` with its uncertainties propagated for the variance inflation factor ``inflation``."""
    attrs = feats.attrs
    return feats.assign(
        {
            f"{name}_uncertainty": smooth_uncertainty(
                feats[f"{name}_fit"],
                feats[sigma],
                attrs["smoothing_size"],
                sigma=attrs["smoothing_sigma"],
                min_weight=attrs["min_weight"],
                inflation=inflation,
            )
            for name, sigma in UNCERTAINTY.items()
        }
    )


def row(label: str, result: dict) -> str:
    """Format one table row: per parameter, the shares within 1 and 2 uncertainties and the error scale."""
    cells = "".join(
        f"{result[name]['within_1']:10.3f}{result[name]['within_2']:10.3f}{result[name]['z_scale']:10.2f}"
        for name in UNCERTAINTY
    )
    return f"{label:28s}{cells}"


def main():
    """Parse the command line, process the paper campaign and print the coverage and accuracy tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (truth in <campaign>-truth)")
    args = parser.parse_args()
    config = parameters.read_config()
    with paper_campaign(args.campaign) as (camp, truth_dir):
        with dask.config.set(scheduler="threads", num_workers=2):
            calibration = calibrate(camp, **parameters.calibration_parameters(config))
            item_params = {**parameters.aoi_parameters(config), **parameters.feature_parameters(config)}
            features = {
                name: process_item(ingest_item(camp, name), calibration, roi=item.roi, **item_params)["features"]
                for name, item in camp.items.items()
            }
        header = f"{'':28s}" + "".join(
            f"{name + ' 1u':>10s}{name + ' 2u':>10s}{name + ' scale':>10s}" for name in UNCERTAINTY
        )
        print(
            "share of scored pixels with |error| <= 1 and 2 uncertainties; scale: 1.4826 median |error| / uncertainty"
        )
        for name, feats in features.items():
            truth = xr.open_zarr(truth_dir / f"{name}.zarr")
            scored = (truth["edge_distance"] >= truth.attrs["label_margin"]) & (truth["surface"] >= 0)
            fit = coverage(feats, truth, mask=scored, unsmoothed=True)
            expected = {
                key: {**value, "within_1": value["expected_1"], "within_2": value["expected_2"], "z_scale": math.nan}
                for key, value in fit.items()
            }
            inflation = feats.attrs.get("uncertainty_inflation", math.inf)
            print(
                f"\n{name}: {fit['R0']['n_pixels']} fitted pixels scored; residual correlation F = {inflation:.2f} "
                f"({feats.attrs.get('uncertainty_effective_pixels', math.nan):.2f} effectively independent pixels)"
            )
            print(header)
            print(row("fit sigma", fit))
            print(row("  Student t expected", expected))
            for label, value in (("smoothed: independent", 1.0), ("smoothed: fully correlated", math.inf)):
                print(row(label, coverage(propagated(feats, value), truth, mask=scored)))
            print(row("smoothed: residual corr.", coverage(feats, truth, mask=scored)))
        training = training_set({name: (features[name], item.cls, item.roi) for name, item in camp.specimens.items()})
        bounds = config["classify"]
        for name, item in camp.scenes.items():
            truth_label, truth_classes = read_truth(item.truth, width=camp.camera.width, height=camp.camera.height)
            print(f"\nscene {name}: accuracy (unclassified = wrong) and unclassified pixels by reason")
            for label, options in (
                ("no reject", {}),
                (f"min_posterior {bounds['min_posterior']}", {"min_posterior": bounds["min_posterior"]}),
                (
                    f"  + outlier_probability {bounds['outlier_probability']}",
                    {"min_posterior": bounds["min_posterior"], "outlier_probability": bounds["outlier_probability"]},
                ),
            ):
                labels = labels_stage(features[name], training, **options)
                accuracy = [
                    score(labels[v], truth_label, truth_classes, training.attrs["classes"])["accuracy"]
                    for v in ("label", "label_filtered")
                ]
                print(
                    f"  {label:40s} {accuracy[0]:.4f} raw, {accuracy[1]:.4f} filtered; "
                    f"{labels['label'].attrs['unclassified']}"
                )


if __name__ == "__main__":
    main()
