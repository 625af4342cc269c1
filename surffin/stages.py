"""The method's stages as pure functions: Datasets in, one Dataset out.

Each stage here is what one workflow rule computes; :mod:`surffin.pipeline`
opens its input stores, calls it and writes its output store, and
:func:`process_item` chains them in memory (tests, benchmarks, notebooks).
"""

from __future__ import annotations

from collections.abc import Mapping

import xarray as xr

from surffin.calibration import reflectance
from surffin.campaign import Roi
from surffin.classify import classify, filter_labels
from surffin.features import DEFAULT_SIZE, features, most_perpendicular_view, residual_correlation, variability
from surffin.geometry import DEFAULT_JUMP, DEFAULT_WINDOW, angle_of_incidence
from surffin.registration import register, registration_maps, warp
from surffin.roughness import roughness_map
from surffin.scattering import DEFAULT_MIN_SPREAD, fit_scattering

__all__ = [
    "aoi_stage",
    "reflectance_stage",
    "registration_stage",
    "features_stage",
    "labels_stage",
    "roughness_stage",
    "process_item",
    "as_roi",
]


def as_roi(roi: Roi | Mapping | None) -> Roi | None:
    """A Roi from its ``{"y": [a, b], "x": [c, d]}`` form (as passed through workflow params)."""
    if roi is None or isinstance(roi, Roi):
        return roi
    return Roi(tuple(roi["y"]), tuple(roi["x"]))


def _item_attrs(ingest: xr.Dataset) -> dict:
    keys = ("item", "kind", "class", "reference_view", "campaign", "camera", "crop")
    return {key: ingest.attrs[key] for key in keys if key in ingest.attrs}


def aoi_stage(ingest: xr.Dataset, *, window: int = DEFAULT_WINDOW, jump: float = DEFAULT_JUMP) -> xr.Dataset:
    """Angle of incidence and distance of every view (method step 2)."""
    ds = angle_of_incidence(ingest["xyz"], window=window, jump=jump)
    ds.attrs = {**ds.attrs, **_item_attrs(ingest)}
    return ds


def reflectance_stage(ingest: xr.Dataset, aoi: xr.Dataset, calibration: xr.Dataset) -> xr.Dataset:
    """Calibrated reflectance of every view on its own grid (paper eq. 2)."""
    r = reflectance(ingest["intensity"], aoi["distance"], aoi["aoi"], calibration["coef"], calibration.attrs["scale_k"])
    return xr.Dataset({"reflectance": r.where(ingest["valid"])}, attrs=_item_attrs(ingest))


def registration_stage(
    ingest: xr.Dataset, aoi: xr.Dataset, reflectance: xr.Dataset, *, method: str = "auto", roi=None
) -> xr.Dataset:
    """Reflectance and AOI of every view on the reference view's grid (method step 4)."""
    roi = as_roi(roi)
    # The roi picks the plane a homography registers (a specimen on its board); poses need none.
    options = {"roi": {"y": list(roi.y), "x": list(roi.x)}} if roi is not None and method != "poses" else {}
    maps = registration_maps(ingest.compute(), method=method, **options)
    both = xr.Dataset({"reflectance": reflectance["reflectance"], "aoi": aoi["aoi"]})
    registered = register(both.compute(), maps)
    registered.attrs = {**registered.attrs, **_item_attrs(ingest)}
    return registered


def features_stage(
    registered: xr.Dataset,
    reflectance: xr.Dataset,
    aoi: xr.Dataset,
    *,
    roi=None,
    size: int = DEFAULT_SIZE,
    variability_size: int = DEFAULT_SIZE,
    min_views: int = 2,
    min_spread: float = DEFAULT_MIN_SPREAD,
) -> xr.Dataset:
    """The per-pixel features R0, n (smoothed fit) and variability (method step 5).

    The variability comes from the most perpendicular view (smallest median
    AOI over the item's roi, else over all its pixels), computed on that
    view's own grid and then warped: resampling first would smooth the noise
    it measures. The uncertainties of the smoothed R0 and n account for the
    spatial correlation of the fit's residuals over the item
    (:func:`surffin.features.residual_correlation`).
    """
    fit = fit_scattering(
        registered["reflectance"].chunk({"view": -1}),
        registered["aoi"].chunk({"view": -1}),
        min_views=min_views,
        min_spread=min_spread,
    ).persist()
    correlation = residual_correlation(registered["reflectance"], registered["aoi"], fit, max_lag=size - 1)
    view = most_perpendicular_view(aoi["aoi"], as_roi(roi))
    own = variability(reflectance["reflectance"].sel(view=view), aoi["aoi"].sel(view=view), size=variability_size)
    maps = registered[["map_x", "map_y"]].sel(view=[view])
    warped = warp(own.expand_dims(view=[view]), maps).squeeze("view", drop=True)
    ds = features(fit, warped, size=size, error_correlation=correlation)
    ds.attrs = {**ds.attrs, **registered.attrs, "variability_view": str(view)}
    return ds


def labels_stage(
    features: xr.Dataset,
    training: xr.Dataset,
    *,
    k: int = 1,
    filter_kind: str = "median",
    filter_size: int = 5,
    max_uncertainty: float | None = None,
    max_distance: float | None = None,
) -> xr.Dataset:
    """Per-pixel class labels of a scene, before and after the label filter (method step 6).

    Pixels too uncertain (``max_uncertainty``) or unlike every class
    (``max_distance``) are unclassified, as :func:`surffin.classify.classify`
    says; the filter keeps them so.
    """
    label = classify(features.compute(), training, k=k, max_uncertainty=max_uncertainty, max_distance=max_distance)
    filtered = filter_labels(label, kind=filter_kind, size=filter_size)
    filtered.attrs = {**label.attrs, "filter": filter_kind, "filter_size": filter_size}
    return xr.Dataset({"label": label, "label_filtered": filtered}, attrs=features.attrs)


def roughness_stage(features: xr.Dataset, *, relation: Mapping) -> xr.Dataset:
    """Indicative roughness map of an item from its smoothed n (:mod:`surffin.roughness`)."""
    ds = roughness_map(features["n"], relation)
    ds.attrs = {**_item_attrs(features), **ds.attrs}
    return ds


def process_item(ingest: xr.Dataset, calibration: xr.Dataset, *, roi=None, method: str = "auto", **params) -> dict:
    """Chain aoi -> reflectance -> registration -> features for one item, in memory.

    Returns
    -------
    dict of Dataset
        ``aoi``, ``reflectance``, ``registered``, ``features`` (features computed).
    """
    aoi = aoi_stage(ingest, **{key: params[key] for key in ("window", "jump") if key in params}).compute()
    refl = reflectance_stage(ingest, aoi, calibration).compute()
    registered = registration_stage(ingest, aoi, refl, method=method, roi=roi)
    feature_params = {key: params[key] for key in ("size", "variability_size", "min_views", "min_spread") if key in params}
    feats = features_stage(registered, refl, aoi, roi=roi, **feature_params).compute()
    return {"aoi": aoi, "reflectance": refl, "registered": registered, "features": feats}
