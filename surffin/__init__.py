"""surffin: surface finish classification from time-of-flight depth camera data.

The public functions are imported on first use, so that ``import surffin`` stays
cheap for the short-lived processes of a workflow.
"""

import importlib

from surffin._version import __version__
from surffin.errors import (
    CalibrationError,
    CampaignError,
    RegistrationError,
    StoreError,
    SurffinError,
    ViewFileError,
)

_LAZY = {
    "read_campaign": "surffin.io.campaign",
    "simulate_campaign": "surffin.simulate",
    "fit_scattering": "surffin.method.scattering",
    "angle_of_incidence": "surffin.method.geometry",
}

__all__ = [
    "__version__",
    *_LAZY,
    "SurffinError",
    "CampaignError",
    "ViewFileError",
    "StoreError",
    "CalibrationError",
    "RegistrationError",
]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'surffin' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
