"""The synthetic camera's radiometry: instrument function, scattering and noise.

The intensity of a pixel i seeing a surface point at distance d and angle of
incidence theta is ``I = g * f_i(d, theta) * R(theta)`` with the per-pixel
instrument function of the paper's eq. 5,
``f_i(d, theta) = (A_i + B_i / d^2) (C_i theta^2 + D_i theta + E_i)``, a global
gain ``g`` (counts) and the surface's reflectance
``R(theta) = R0 cos((2 - 1/n) theta)^n`` (eq. 3, zero beyond its lobe). Noise is
added to the intensity (relative, stronger on weak returns, plus a floor in
counts) and to the range along each pixel's ray (growing on weak returns); weak
returns, grazing angles and random dropouts become invalid.

Eq. 3 and eq. 5 are written here from the method's description, not imported
from :mod:`surffin.method.scattering` or :mod:`surffin.method.calibration`: the truth of a
synthetic campaign must not be made by the code it validates (a test keeps the
simulator free of such imports, another checks that both agree).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from surffin.simulate.camera import PinholeCamera
from surffin.simulate.imperfections import Imperfections, mix_edges, systematic_factor
from surffin.simulate.scene import Geometry

if TYPE_CHECKING:
    from surffin.simulate.presets import Preset

__all__ = ["TERMS", "Instrument", "draw_instrument", "instrument_function", "observe", "scattering"]

#: Names of the instrument function's coefficients, in the order of ``coef``'s first axis.
TERMS = ("A", "B", "C", "D", "E")

# Weights of the radial (vignetting-like), smooth low-order and white parts of
# each coefficient's spatial pattern before it is scaled to unit variance.
_RADIAL_WEIGHT = 0.6
_SMOOTH_WEIGHT = 0.75
_WHITE_WEIGHT = 0.25
_SMOOTH_ORDER = 3
# A, B and E fall off towards the image border; C and D rise.
_RADIAL_SIGN = (-1.0, -1.0, 1.0, 1.0, -1.0)


def instrument_function(coef: np.ndarray, distance: np.ndarray, aoi: np.ndarray) -> np.ndarray:
    """Eq. 5: ``f = (A + B / d^2) (C theta^2 + D theta + E)``.

    Parameters
    ----------
    coef : (5, ...) ndarray
        A, B (m^2), C, D, E along the first axis (:data:`TERMS`), broadcasting
        against ``distance`` and ``aoi``.
    distance : ndarray, metres
    aoi : ndarray, radians

    Returns
    -------
    ndarray
        The broadcast of the inputs.
    """
    A, B, C, D, E = coef
    distance_factor = A + B / np.square(distance)
    angular_factor = C * np.square(aoi) + D * aoi + E
    return distance_factor * angular_factor


def scattering(aoi: np.ndarray, R0: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Eq. 3: ``R = R0 cos((2 - 1/n) theta)^n``, zero beyond the lobe.

    Parameters
    ----------
    aoi : ndarray, radians
    R0, n : ndarray or float
        Reflectance at normal incidence and scattering coefficient (n > 0.5),
        broadcasting against ``aoi``.

    Returns
    -------
    ndarray
        Reflectance; 0 where ``(2 - 1/n) theta >= pi/2`` (no return), NaN
        where an input is NaN.
    """
    angle = (2.0 - 1.0 / np.asarray(n, dtype=np.float64)) * aoi
    lobe = R0 * np.power(np.maximum(np.cos(angle), 0.0), n)
    return np.where(angle >= np.pi / 2.0, 0.0, lobe)


@dataclass(frozen=True, eq=False)
class Instrument:
    """Per-pixel instrument function and gain of one camera.

    Attributes
    ----------
    coef : (5, height, width) ndarray of float64
        Coefficients A, B (m^2), C, D, E of eq. 5 (theta in radians, d in metres).
    gain : float
        Counts per unit of ``f * R``.
    """

    coef: np.ndarray
    gain: float

    def intensity(self, distance: np.ndarray, aoi: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Noise-free intensity ``g * f(d, theta) * R``, counts, same shape as the inputs (height, width)."""
        return self.gain * instrument_function(self.coef, distance, aoi) * R

    def calibration(self, rho_wall: float) -> tuple[np.ndarray, float]:
        """Compute what a perfect calibration on a Lambertian wall finds, in the gauge E = 1.

        A wall of reflectance ``rho_wall`` gives ``I / cos(theta) = g rho_wall f``;
        moving E into the distance factor gives ``A' = g rho_wall E A``,
        ``B' = g rho_wall E B``, ``C' = C / E``, ``D' = D / E``, ``E' = 1`` and
        ``scale_k = 1 / rho_wall``, so that ``I = scale_k f'(d, theta) R``.

        Parameters
        ----------
        rho_wall : float
            Reflectance of the calibration wall.

        Returns
        -------
        coef : (5, height, width) ndarray of float64
            A', B', C', D', E' = 1.
        scale_k : float
        """
        A, B, C, D, E = self.coef
        level = self.gain * rho_wall * E
        coef = np.stack([level * A, level * B, C / E, D / E, np.ones_like(E)])
        return coef, 1.0 / rho_wall


def _unit(field: np.ndarray) -> np.ndarray:
    field = field - field.mean()
    return field / field.std()


def _spatial_pattern(rng: np.random.Generator, camera: PinholeCamera, radial_sign: float) -> np.ndarray:
    """Zero-mean, unit-variance pattern over the sensor: radial + low-order modes + white."""
    x = (np.arange(camera.width) - camera.cx) / (camera.width / 2.0)
    y = (np.arange(camera.height) - camera.cy) / (camera.height / 2.0)
    radial = _unit(x[None, :] ** 2 + y[:, None] ** 2)
    order = np.arange(_SMOOTH_ORDER + 1)
    columns = np.cos(np.pi * order[:, None] * (x[None, :] + 1.0) / 2.0)  # (order, width)
    rows = np.cos(np.pi * order[:, None] * (y[None, :] + 1.0) / 2.0)  # (order, height)
    weights = rng.standard_normal((order.size, order.size)) / (1.0 + order[:, None] + order[None, :])
    weights[0, 0] = 0.0
    smooth = _unit(np.einsum("pq,py,qx->yx", weights, rows, columns))
    white = _unit(rng.standard_normal(camera.shape))
    return _unit(_RADIAL_WEIGHT * radial_sign * radial + _SMOOTH_WEIGHT * smooth + _WHITE_WEIGHT * white)


def draw_instrument(
    camera: PinholeCamera,
    mean: tuple[float, ...],
    variability: tuple[float, ...],
    gain: float,
    rng: np.random.Generator,
) -> Instrument:
    """Draw a camera's per-pixel instrument function.

    Parameters
    ----------
    camera : PinholeCamera
    mean : (5,) tuple of float
        Image means of A, B (m^2), C, D, E.
    variability : (5,) tuple of float
        Relative standard deviation of each coefficient over the image (the
        paper's Table 2: 0.0894, 0.0392, 0.0179, 0.0138, 0.0444).
    gain : float
        Counts per unit of ``f * R``.
    rng : Generator

    Returns
    -------
    Instrument
        ``coef[k] = mean[k] (1 + variability[k] P_k)`` with a smooth, spatially
        structured pattern ``P_k`` of zero mean and unit variance per term.
    """
    coef = np.stack(
        [
            m * (1.0 + cv * _spatial_pattern(rng, camera, sign))
            for m, cv, sign in zip(mean, variability, _RADIAL_SIGN, strict=True)
        ]
    )
    return Instrument(coef=coef, gain=float(gain))


def _growing(level: float, cap: float, reference: float, signal: np.ndarray) -> np.ndarray:
    """Compute a noise level that grows as ``1/sqrt(signal)`` below ``reference`` counts, from ``level`` up to ``cap``.

    A ``cap`` at or below ``level`` means no growth: ``level`` everywhere
    (NaN where ``signal`` is NaN).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.clip(level * np.sqrt(reference / signal), level, max(level, cap))


def observe(
    geometry: Geometry,
    instrument: Instrument,
    preset: Preset,
    rng: np.random.Generator,
    imperfections: Imperfections | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One noisy acquisition of what a camera sees.

    The intensity noise has the standard deviation
    ``sqrt((sigma_rel I)^2 + intensity_floor^2)`` counts, with ``sigma_rel``
    ``intensity_noise`` on returns stronger than ``noise_reference`` counts,
    growing as ``1/sqrt(I)`` below up to ``intensity_noise_max``. The range
    noise along the ray grows likewise from ``depth_noise`` up to
    ``depth_noise_max`` (I the noise-free signal). The same random draws are
    made whatever the noise levels, so variants of a preset differing only in
    noise share dropouts and noise patterns.

    The imperfections, when asked, act in the camera's order: the residual
    systematics scale the noise-free signal, mixed pixels blend it and the
    range at depth edges (their draws follow the noise's, which stay the
    same), the noise is added, and the intensity clips at the saturation.

    Parameters
    ----------
    geometry : Geometry
        Noise-free geometry and material of the view.
    instrument : Instrument
    preset : Preset
        Supplies the noise levels above, ``dropout`` (fraction of pixels lost
        at random), ``min_intensity`` (counts) and ``max_aoi`` (degrees).
    rng : Generator
        The view's own random stream.
    imperfections : Imperfections, optional
        Its ``systematics``, ``mixed_pixels`` and ``saturation``; default none.

    Returns
    -------
    xyz : (height, width, 3) ndarray of float64, metres
        Camera frame; NaN on invalid pixels.
    intensity : (height, width) ndarray of float64, counts
        0 on invalid pixels.
    """
    shape = geometry.distance.shape
    intensity_draw = rng.standard_normal(shape)
    range_draw = rng.standard_normal(shape)
    kept = rng.random(shape) >= preset.dropout
    imperfections = imperfections or Imperfections()
    signal = instrument.intensity(geometry.distance, geometry.aoi, scattering(geometry.aoi, geometry.R0, geometry.n))
    distance = geometry.distance
    if imperfections.systematics:
        signal = signal * systematic_factor(distance, geometry.aoi, imperfections.systematics)
    if imperfections.mixed_pixels:
        distance, signal = mix_edges(distance, signal, geometry.face, rng)
    relative = _growing(preset.intensity_noise, preset.intensity_noise_max, preset.noise_reference, signal)
    intensity = signal + np.hypot(relative * signal, preset.intensity_floor) * intensity_draw
    if imperfections.saturation is not None:
        intensity = np.minimum(intensity, imperfections.saturation)
    depth_sigma = _growing(preset.depth_noise, preset.depth_noise_max, preset.noise_reference, signal)
    distance = distance + depth_sigma * range_draw
    valid = (
        (geometry.face >= 0)
        & kept
        & (geometry.aoi <= np.deg2rad(preset.max_aoi))
        & (intensity >= preset.min_intensity)
        & (distance > 0)
    )
    xyz = geometry.rays * np.where(valid, distance, np.nan)[..., None]
    return xyz, np.where(valid, intensity, 0.0)
