"""Entry points of the workflow's analysis and report jobs: diagnostics, sensitivity, paper comparison, figures.

Each runs one job as a workflow rule calls it: the work of a function of
:mod:`surffin.analysis` or :mod:`surffin.report`, with the job's log file
(:func:`surffin.pipeline.jobs.logging_to`). They are plain Python and usable
without snakemake; the modules they run are imported on first use.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from surffin.analysis.sensitivity import DEFAULT_DRAWS
from surffin.grid import Roi
from surffin.pipeline.jobs import job_seconds, logging_to
from surffin.pipeline.table import STAGES
from surffin.report.sensitivity import write_sensitivity

__all__ = ["run_calibration_diagnostics", "run_sensitivity", "run_paper_comparison", "run_figures", "run_export"]


def run_calibration_diagnostics(
    output_json: str | os.PathLike,
    *,
    calibration: str | os.PathLike,
    repeat: str | os.PathLike | None = None,
    campaign: str | os.PathLike,
    repeat_folders: Mapping[str, str] | None = None,
    item_params: Mapping | None = None,
    specimen_stores: Mapping[str, Mapping[str, str | os.PathLike]] | None = None,
    instrument_truth: str | os.PathLike | None = None,
    figures_dir: str | os.PathLike | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Write the calibration diagnostics of a campaign as JSON (and figures).

    The stores are first checked against the campaign's camera
    (:func:`surffin.method.calibration.check_calibration`); the diagnostics are
    :func:`surffin.analysis.diagnostics.calibration_report`'s, the figures
    :func:`surffin.report.diagnostics.calibration_figures`'.

    Parameters
    ----------
    output_json : path-like
        Written atomically (:func:`surffin.analysis.diagnostics.write_report`).
    calibration, repeat, repeat_folders, item_params, specimen_stores, instrument_truth
        As for :func:`surffin.analysis.diagnostics.calibration_report`.
    campaign : path-like
        The campaign directory.
    figures_dir : path-like, optional
        Folder of the figures (``calibration_correlation.png``,
        ``calibration_repeatability.png``); none without it.
    log_path : path-like, optional
        The job's log file.

    Returns
    -------
    Path
        ``output_json``.
    """
    from surffin.analysis.diagnostics import calibration_report, write_report
    from surffin.io.campaign import read_campaign

    # to move below the pipeline (surffin.method.calibration): run -> table -> analyses -> run is a cycle
    from surffin.method.calibration import check_calibration
    from surffin.report.diagnostics import calibration_figures

    with logging_to(log_path):
        camp = read_campaign(campaign, require_calibration=False, check_views=False)
        for path in (calibration, repeat):
            if path is not None:
                check_calibration(path, camp)
        found = calibration_report(
            camp,
            calibration=calibration,
            repeat=repeat,
            repeat_folders=repeat_folders,
            item_params=item_params,
            specimen_stores=specimen_stores,
            instrument_truth=instrument_truth,
        )
        if figures_dir is not None:
            calibration_figures(found, figures_dir)
        return write_report(found.report, output_json)


def run_sensitivity(
    out_dir: str | os.PathLike,
    *,
    draws: int = DEFAULT_DRAWS,
    seed: int = 0,
    log_path: str | os.PathLike | None = None,
) -> dict[str, Path]:
    """Run the sensitivity Monte Carlo and write its files (:func:`surffin.report.sensitivity.write_sensitivity`).

    Parameters
    ----------
    out_dir, draws, seed
        As for :func:`~surffin.report.sensitivity.write_sensitivity`.
    log_path : path-like, optional
        The job's log file.

    Returns
    -------
    dict of str to Path
        The written files by the keys of :data:`surffin.report.sensitivity.OUTPUTS`.
    """
    with logging_to(log_path):
        return write_sensitivity(out_dir, draws=draws, seed=seed, code_version=STAGES["sensitivity"].version)


def run_paper_comparison(
    output: str | os.PathLike,
    *,
    summary: str | os.PathLike,
    specimens: Sequence[str],
    diagnostics: str | os.PathLike | None = None,
    sensitivity: str | os.PathLike | None = None,
    slopes: str | os.PathLike | None = None,
    relation: str | os.PathLike | None = None,
    runtime: Mapping[str, Mapping] | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Write ``paper-comparison.md`` (:func:`surffin.analysis.reproduction.write_comparison`).

    Parameters
    ----------
    output, specimens
        As for :func:`~surffin.analysis.reproduction.write_comparison`.
    summary, diagnostics, sensitivity, slopes, relation : path-like
        Its ``inputs``; ``summary`` is required.
    runtime : mapping, optional
        Scene -> ``{"views": int, "logs": [the log files of its jobs from view files to labels]}``;
        their times (:func:`~surffin.pipeline.jobs.job_seconds`) are summed, None if one is missing.
    log_path : path-like, optional
        The job's log file.

    Returns
    -------
    Path
        ``output``.
    """
    from surffin.analysis.reproduction import write_comparison

    inputs = {
        "summary": summary,
        "diagnostics": diagnostics,
        "sensitivity": sensitivity,
        "slopes": slopes,
        "relation": relation,
    }
    with logging_to(log_path):
        times = {}
        for scene, spec in (runtime or {}).items():
            seconds = [job_seconds(path) for path in spec["logs"]]
            times[scene] = {"views": spec["views"], "seconds": None if None in seconds else sum(seconds)}
        return write_comparison(output, inputs, specimens=specimens, runtime=times)


def run_figures(
    outputs: Mapping[str, str | os.PathLike | Sequence[str | os.PathLike]],
    *,
    calibration: str | os.PathLike | None = None,
    training: str | os.PathLike | None = None,
    summary: str | os.PathLike | None = None,
    features: str | os.PathLike | None = None,
    registered: str | os.PathLike | None = None,
    labels: str | os.PathLike | None = None,
    ingest: str | os.PathLike | None = None,
    roughness: str | os.PathLike | None = None,
    roi: Roi | Mapping | None = None,
    log_path: str | os.PathLike | None = None,
) -> list[Path]:
    """Open the stores and write the requested figures and tables (:func:`surffin.report.figures.write_figures`).

    Parameters
    ----------
    outputs, roi
        As for :func:`~surffin.report.figures.write_figures`.
    calibration, training, summary, features, registered, labels, ingest, roughness : path-like, optional
        Its ``inputs``.
    log_path : path-like, optional
        The job's log file.

    Returns
    -------
    list of Path
        What :func:`~surffin.report.figures.write_figures` wrote (and raises on a bad kind or missing input).
    """
    from surffin.report.figures import write_figures

    inputs = {
        "calibration": calibration,
        "training": training,
        "summary": summary,
        "features": features,
        "registered": registered,
        "labels": labels,
        "ingest": ingest,
        "roughness": roughness,
    }
    with logging_to(log_path):
        return write_figures(outputs, inputs, roi=roi)


def run_export(
    out: str | os.PathLike,
    *,
    training: str | os.PathLike,
    calibration: str | os.PathLike | None = None,
    log_path: str | os.PathLike | None = None,
) -> list[Path]:
    """Export the results of the processed folder holding ``training`` (:func:`surffin.report.export.export_results`).

    The workflow names the training store, not the folder, so that the job's inputs say what it reads.
    """
    from surffin.report.export import export_results

    with logging_to(log_path):
        return export_results(Path(training).parent, out, calibration=calibration)
