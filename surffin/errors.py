"""The one exception hierarchy of surffin.

Every error a user can cause derives from :class:`SurffinError`; its message
names the file (and key, item or view), the offending value and what is
expected, so that it can be acted on without reading the code.
"""

__all__ = [
    "SurffinError",
    "CampaignError",
    "ViewFileError",
    "StoreError",
    "CalibrationError",
    "RegistrationError",
]


class SurffinError(Exception):
    """Base class of every error surffin raises on bad input."""


class CampaignError(SurffinError):
    """``campaign.yaml`` or the campaign directory breaks the contract."""


class ViewFileError(SurffinError):
    """A view file (``.npz``, ``.ply``, ``.raw``) or its pose is unreadable or inconsistent."""


class StoreError(SurffinError):
    """A processed zarr store is missing, incomplete or does not match its use."""


class CalibrationError(SurffinError):
    """The radiometric calibration cannot be fitted or applied."""


class RegistrationError(SurffinError):
    """The views of an item cannot be brought onto the reference grid."""
