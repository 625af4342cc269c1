"""The synthetic depth camera: campaigns with known truth.

A pinhole camera at known poses looks at planar surfaces (a calibration wall, a
reference panel, plaster specimens on a board) whose reflectance follows the
paper's scattering model with textured R0 and n maps; a per-pixel instrument
function, intensity and depth noise and invalid pixels make the views behave
like the real camera's; a real camera's imperfections (lens distortion, pose
error, mixed pixels, saturation, instrument systematics, settings sidecars,
signed raw files) can be switched on. :func:`simulate_campaign` writes them as
a campaign (CAMPAIGN.md layout) plus truth stores outside it.

Modules: :mod:`~surffin.simulate.camera` (geometry, poses, lens distortion),
:mod:`~surffin.simulate.imperfections` (a real camera's imperfections),
:mod:`~surffin.simulate.scene` (faces, textures, ray casting),
:mod:`~surffin.simulate.instrument` (radiometry, noise; eq. 3 and eq. 5 written here,
not imported from the method, so that the truth is not made by the code it checks),
:mod:`~surffin.simulate.presets` (named designs and materials),
:mod:`~surffin.simulate.plan` (the acquisitions of a campaign),
:mod:`~surffin.simulate.truth` (truth stores),
:mod:`~surffin.simulate.acquire` (rendering and writing a campaign),
:mod:`~surffin.simulate.command` (``surffin simulate``),
:mod:`~surffin.simulate.validation` (campaigns unlike ``paper``, for validation).

The names below are imported on first use, so that the command line parser
does not pay for xarray and zarr.
"""

import importlib

_LAZY = {
    "simulate_campaign": "acquire",
    "FORMATS": "validation",
    "UNITS": "validation",
    "cli_parser": "command",
    "cli_run": "command",
    "Acquisition": "plan",
    "REPEAT_FOLDERS": "plan",
    "plan_campaign": "plan",
    "PRESETS": "presets",
    "Preset": "presets",
    "Specimen": "presets",
    "plaster": "presets",
    "SceneLayout": "presets",
    "another_piece": "presets",
    "class_material": "presets",
    "VALIDATION": "validation",
    "IMPERFECT": "validation",
    "Validation": "validation",
    "Imperfections": "imperfections",
    "STANDARD": "imperfections",
    "named_imperfections": "imperfections",
    "perturb_pose": "imperfections",
    "systematic_factor": "imperfections",
    "mix_edges": "imperfections",
    "PinholeCamera": "camera",
    "distort": "camera",
    "undistort": "camera",
    "look_at_pose": "camera",
    "world_rays": "camera",
    "to_camera": "camera",
    "TERMS": "instrument",
    "Instrument": "instrument",
    "draw_instrument": "instrument",
    "instrument_function": "instrument",
    "scattering": "instrument",
    "observe": "instrument",
    "Face": "scene",
    "Geometry": "scene",
    "Material": "scene",
    "Scene": "scene",
    "Texture": "scene",
    "box_faces": "scene",
    "plane_face": "scene",
    "keyed_rng": "scene",
    "random_field": "scene",
    "render": "scene",
    "reference_coordinates": "truth",
    "scene_truth_label": "truth",
    "item_truth": "truth",
    "instrument_truth": "truth",
}

__all__ = list(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
