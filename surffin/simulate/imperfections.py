"""A real camera's imperfections, each switchable: what an ideal synthetic camera lacks.

:class:`Imperfections` holds the switches, all off by default (an ideal camera,
the campaigns the simulator always wrote). :func:`~surffin.simulate.acquire.simulate_campaign`
renders them; the truth stays the true geometry (true poses, AOI, distance, R0, n),
so that the method is scored against what is, not against what the files say:

- lens distortion (OpenCV's radial-tangential model): pixel (u, v) sees the ray of
  the undistorted normalised coordinates (:class:`~surffin.simulate.camera.PinholeCamera`);
  ``campaign.yaml`` gives the distortion, only the pinhole intrinsics, or none;
- pose error: the recorded poses are off from the true ones by a fixed translation
  and rotation in a random direction per view (:func:`perturb_pose`);
- mixed (flying) pixels: a pixel beside a depth edge returns a range between its
  surface and the one across the edge (:func:`mix_edges`);
- saturation: intensities clip at a count, optionally written as ``camera.saturation``;
- residual instrument systematics: a smooth factor in distance and angle of
  incidence that the paper's eq. 5 cannot represent (:func:`systematic_factor`);
- acquisition settings sidecars ``<stem>.meta.json`` and ``camera.match_settings``;
- signed raw files (``Coord3D_ABCY16s``).

:func:`named_imperfections` combines the named standard ones (:data:`STANDARD`) for
the command line and the validation campaigns.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "INTRINSICS",
    "STANDARD",
    "Imperfections",
    "mix_edges",
    "named_imperfections",
    "perturb_pose",
    "systematic_factor",
]

#: Values of :attr:`Imperfections.intrinsics`: what ``campaign.yaml`` says of the lens.
INTRINSICS = ("full", "pinhole", "none")

# Period in distance (metres) and angular rate (per radian) of the systematic factor's
# wave: about 1.75 periods over the wall distances 0.3-1.0 m, its phase turning by 3 rad
# per radian of incidence, so that it is a function of neither d nor theta alone.
_SYSTEMATIC_PERIOD = 0.4
_SYSTEMATIC_ANGLE_RATE = 3.0
# A neighbour across a depth edge sees another face at least this much farther or nearer, metres.
_EDGE_STEP = 0.002
# The largest share of a mixed pixel's footprint on the surface across the edge.
_MAX_MIX = 0.5
# The standard lens: k1, k2, p1, p2, k3 of a moderate barrel distortion.
_LENS = (-0.12, 0.05, 0.0, 0.0, 0.0)
# The 4-neighbours, (row, column) offsets.
_NEIGHBOURS = ((-1, 0), (1, 0), (0, -1), (0, 1))


@dataclass(frozen=True)
class Imperfections:
    """The imperfections a synthetic camera renders; the defaults render none.

    Attributes
    ----------
    distortion : tuple of float
        OpenCV distortion ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])`` of the lens
        (e.g. ``(-0.12, 0.05, 0, 0, 0)``); empty: none.
    intrinsics : {"full", "pinhole", "none"}
        What ``campaign.yaml``'s ``camera.intrinsics`` says: the pinhole
        intrinsics and the distortion (the distortion is known), the pinhole
        intrinsics alone (an unknown distortion), or nothing.
    pose_error : (float, float) or None
        Translation (mm) and rotation (degrees) between each view's recorded
        pose and its true one, in a random direction per view; None: exact poses.
    mixed_pixels : bool
        Pixels beside a depth edge mix their range and signal with the surface
        across the edge (:func:`mix_edges`).
    saturation : float or None
        Intensities clip at this many counts; None: no clipping.
    saturation_known : bool
        Write ``saturation`` as ``camera.saturation`` into ``campaign.yaml``.
    systematics : float
        Peak relative amplitude of the instrument's residual systematics
        (:func:`systematic_factor`), e.g. 0.03; 0: none.
    settings : tuple of (str, float or str) pairs
        Acquisition settings written to every view's ``<stem>.meta.json``
        (e.g. ``(("exposure_us", 250), ("gain", "low"))``); empty: no sidecars.
    match_settings : bool
        Name the settings in ``camera.match_settings``.
    signed_raw : float or None
        Scale (mm per code) of signed ``Coord3D_ABCY16s`` raw files (offset 0),
        written as ``camera.abcy16``; None: the unsigned ``Coord3D_ABCY16`` with
        the camera's usual encoding. Only raw files are affected.
    """

    distortion: tuple[float, ...] = ()
    intrinsics: str = "full"
    pose_error: tuple[float, float] | None = None
    mixed_pixels: bool = False
    saturation: float | None = None
    saturation_known: bool = True
    systematics: float = 0.0
    settings: tuple[tuple[str, float | str], ...] = ()
    match_settings: bool = False
    signed_raw: float | None = None

    def __post_init__(self):
        """Refuse values no camera has."""
        if len(self.distortion) not in (0, 4, 5, 8):
            raise ValueError(f"distortion must hold 4, 5 or 8 OpenCV coefficients, got {self.distortion!r}")
        if self.intrinsics not in INTRINSICS:
            raise ValueError(f"intrinsics {self.intrinsics!r} is not one of {INTRINSICS}")
        if self.pose_error is not None and (len(self.pose_error) != 2 or min(self.pose_error) < 0):
            raise ValueError(f"pose_error must be (mm, degrees), both >= 0, got {self.pose_error!r}")
        if self.saturation is not None and not self.saturation > 0:
            raise ValueError(f"saturation must be a positive count, got {self.saturation!r}")
        if not 0.0 <= self.systematics < 1.0:
            raise ValueError(f"systematics must be a relative amplitude in [0, 1), got {self.systematics!r}")
        if self.match_settings and not self.settings:
            raise ValueError("match_settings needs settings to match")
        if self.signed_raw is not None and not self.signed_raw > 0:
            raise ValueError(f"signed_raw must be a positive scale in mm per code, got {self.signed_raw!r}")

    @property
    def any(self) -> bool:
        """Whether any imperfection is switched on."""
        return self != Imperfections()


#: The named standard imperfections of :func:`named_imperfections`, each a set of
#: :class:`Imperfections` fields; ``none`` is the ideal camera, ``all`` the combination
#: the validation benchmark scores (those that change the data the method sees most,
#: with the distortion unknown).
STANDARD: dict[str, dict] = {
    "none": {},
    "distortion": {"distortion": _LENS, "intrinsics": "full"},
    "unknown-distortion": {"distortion": _LENS, "intrinsics": "pinhole"},
    "no-intrinsics": {"intrinsics": "none"},
    "pose": {"pose_error": (1.0, 0.2)},
    "mixed": {"mixed_pixels": True},
    "saturation": {"saturation": 2000.0},
    "systematics": {"systematics": 0.03},
    "settings": {"settings": (("exposure_us", 250), ("gain", "low")), "match_settings": True},
    "signed-raw": {"signed_raw": 0.1},
}
STANDARD["all"] = {**STANDARD["unknown-distortion"], **STANDARD["pose"], **STANDARD["mixed"], **STANDARD["systematics"]}


def named_imperfections(names: str) -> Imperfections:
    """Combine named standard imperfections.

    Parameters
    ----------
    names : str
        Comma-separated names of :data:`STANDARD` (e.g. ``"pose,mixed"``, ``"all"``).

    Returns
    -------
    Imperfections

    Raises
    ------
    ValueError
        An unknown name, or two names that set one field to different values
        (``distortion`` and ``unknown-distortion``).
    """
    chosen: dict = {}
    for name in (part.strip() for part in names.split(",") if part.strip()):
        if name not in STANDARD:
            raise ValueError(f"imperfection {name!r} is not known; expected names of {sorted(STANDARD)}")
        for key, value in STANDARD[name].items():
            if chosen.get(key, value) != value:
                raise ValueError(f"imperfections {names!r} set {key} to both {chosen[key]!r} and {value!r}")
            chosen[key] = value
    return replace(Imperfections(), **chosen)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians about the unit vector ``axis`` (Rodrigues)."""
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def _direction(rng: np.random.Generator) -> np.ndarray:
    """Draw a unit vector uniform on the sphere."""
    vector = rng.standard_normal(3)
    return vector / np.linalg.norm(vector)


def perturb_pose(pose: np.ndarray, translation_mm: float, rotation_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Move a camera-to-world pose by a given translation and rotation in random directions.

    Parameters
    ----------
    pose : (4, 4) ndarray
        True camera-to-world transform, translation in metres.
    translation_mm : float
        Distance between the true and the returned camera centre, mm.
    rotation_deg : float
        Angle of the rotation between the true and the returned orientation, degrees.
    rng : Generator
        Draws the direction of the translation and the axis of the rotation
        (uniform on the sphere).

    Returns
    -------
    (4, 4) ndarray of float64
        ``R' = R Q`` (``Q`` the rotation about the axis, in the camera frame),
        ``t' = t + translation_mm / 1000 * direction``.
    """
    moved = np.array(pose, dtype=np.float64)
    moved[:3, 3] += translation_mm / 1000.0 * _direction(rng)
    moved[:3, :3] = moved[:3, :3] @ _rotation(_direction(rng), np.deg2rad(rotation_deg))
    return moved


def systematic_factor(distance: np.ndarray, aoi: np.ndarray, amplitude: float) -> np.ndarray:
    """Residual instrument systematics: ``1 + a sin(2 pi d / 0.4 m + 3 theta)``.

    A smooth wave in distance whose phase turns with the angle of incidence,
    like a time-of-flight camera's cyclic error: within ``a`` of 1, and neither
    a product of a function of d and one of theta nor of eq. 5's form, so that
    no per-pixel ``(A + B/d^2)(C theta^2 + D theta + E)`` absorbs it.

    Parameters
    ----------
    distance : ndarray, metres
    aoi : ndarray, radians
    amplitude : float
        ``a``, relative.

    Returns
    -------
    ndarray
        The broadcast of ``distance`` and ``aoi``.
    """
    return 1.0 + amplitude * np.sin(2.0 * np.pi * distance / _SYSTEMATIC_PERIOD + _SYSTEMATIC_ANGLE_RATE * aoi)


def _shifted(array: np.ndarray, dy: int, dx: int, fill) -> np.ndarray:
    """``array`` moved so that ``out[y, x] = array[y + dy, x + dx]``, ``fill`` beyond the border."""
    out = np.full_like(array, fill)
    height, width = array.shape
    rows_out = slice(max(0, -dy), height - max(0, dy))
    cols_out = slice(max(0, -dx), width - max(0, dx))
    rows_in = slice(max(0, dy), height - max(0, -dy))
    cols_in = slice(max(0, dx), width - max(0, -dx))
    out[rows_out, cols_out] = array[rows_in, cols_in]
    return out


def mix_edges(
    distance: np.ndarray, signal: np.ndarray, face: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Mixed pixels: blend each pixel beside a depth edge with the surface across it.

    A pixel whose 4-neighbour sees another face more than 2 mm nearer or
    farther straddles a depth edge: a random share ``w`` (uniform in [0, 0.5])
    of its footprint lies on the neighbour's surface (the one with the largest
    step). It returns the sum of both returns, ``(1 - w) s + w s'``, at the
    range of their phasor sum, for steps far below the camera's ambiguity range
    the signal-weighted mean ``((1 - w) s d + w s' d') / ((1 - w) s + w s')``.

    Parameters
    ----------
    distance : (height, width) ndarray, metres
        Noise-free range along each pixel's ray; NaN where nothing is hit.
    signal : (height, width) ndarray, counts
        Noise-free signal of each pixel's own surface.
    face : (height, width) ndarray of int
        Face seen, -1 for none.
    rng : Generator
        Draws ``w`` for every pixel (the same draws whatever the scene).

    Returns
    -------
    distance, signal : (height, width) ndarray of float64
        Mixed beside depth edges, the inputs elsewhere.
    """
    share = _MAX_MIX * rng.random(distance.shape)
    step = np.zeros_like(distance)
    across_distance = distance.copy()
    across_signal = signal.copy()
    for dy, dx in _NEIGHBOURS:
        other_distance = _shifted(distance, dy, dx, np.nan)
        other_signal = _shifted(signal, dy, dx, np.nan)
        other_face = _shifted(face, dy, dx, -1)
        with np.errstate(invalid="ignore"):
            size = np.where((other_face != face) & (other_face >= 0), np.abs(other_distance - distance), 0.0)
        larger = np.nan_to_num(size) > step
        step = np.where(larger, size, step)
        across_distance = np.where(larger, other_distance, across_distance)
        across_signal = np.where(larger, other_signal, across_signal)
    mixed = (step > _EDGE_STEP) & (face >= 0) & (signal > 0)
    w = np.where(mixed, share, 0.0)
    with np.errstate(invalid="ignore"):
        total = (1.0 - w) * signal + w * across_signal
        blended = ((1.0 - w) * signal * distance + w * across_signal * across_distance) / total
    return np.where(mixed, blended, distance), np.where(mixed, total, signal)
