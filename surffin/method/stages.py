"""The method's stages as pure functions: Datasets in, one Dataset out.

Each stage here is what one workflow rule computes; :mod:`surffin.pipeline.run`
opens its input stores, calls it and writes its output store. :data:`ITEM_CHAIN`
is an item's chain from its ingest store to its features (a stage's input
stores are its positional arguments, its parameters its keyword-only ones);
:func:`process_item` runs it in memory (tests, benchmarks, notebooks) and the
stage table (:mod:`surffin.pipeline.table`) builds the workflow's jobs on it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import xarray as xr

from surffin.grid import Roi
from surffin.method.calibration import reflectance
from surffin.method.classify import NOISE_CORRECTED, UNCLASSIFIED, classify, filter_labels, unclassified_counts
from surffin.method.features import (
    DEFAULT_SIZE,
    feature_window,
    features,
    first_available,
    residual_correlation,
    select_roi,
    variability,
    views_by_incidence,
)
from surffin.method.geometry import (
    DEFAULT_JUMP,
    DEFAULT_MAX_WINDOW,
    DEFAULT_WINDOW,
    angle_of_incidence,
    mixed_pixels,
)
from surffin.method.noise import relative_noise
from surffin.method.registration import POSE_OPTIONS, register, registration_maps, warp
from surffin.method.roughness import roughness_map
from surffin.method.scattering import DEFAULT_MIN_SPREAD, fit_scattering

__all__ = [
    "aoi_stage",
    "reflectance_stage",
    "registration_stage",
    "features_stage",
    "labels_stage",
    "roughness_stage",
    "Step",
    "ITEM_CHAIN",
    "process_item",
]


def _item_attrs(ingest: xr.Dataset) -> dict:
    keys = ("item", "kind", "class", "reference_view", "campaign", "camera", "crop")
    return {key: ingest.attrs[key] for key in keys if key in ingest.attrs}


def _grid(ds: xr.Dataset) -> Roi:
    """Return the sensor pixels of a store's (y, x) grid (on the views' own grids: the item's crop)."""
    return Roi.spanning(ds["y"].values, ds["x"].values)


def _single(ds: xr.Dataset) -> xr.Dataset:
    # The camera's intensity and points are float32: what is computed from them is no more
    # precise than that, and float64 would only double the stores (kernels compute in float64).
    return ds.assign({name: var.astype(np.float32) for name, var in ds.data_vars.items() if var.dtype == np.float64})


def aoi_stage(
    ingest: xr.Dataset,
    *,
    window: int = DEFAULT_WINDOW,
    jump: float = DEFAULT_JUMP,
    max_window: int = DEFAULT_MAX_WINDOW,
) -> xr.Dataset:
    """Angle of incidence and distance of every view (method step 2), without its mixed pixels.

    The mixed ("flying") pixels, between two surfaces at a depth edge
    (:func:`surffin.method.geometry.mixed_pixels`, with the same ``jump``),
    are dropped before the plane fits: they get no AOI and no distance, hence
    no reflectance. The attr ``mixed_pixels`` counts them per view.
    """
    xyz = ingest["xyz"]
    mixed = mixed_pixels(xyz, jump=jump).compute()
    ds = angle_of_incidence(xyz.where(~mixed), window=window, jump=jump, max_window=max_window)
    counts = dict(zip(mixed["view"].values.tolist(), mixed.sum(("y", "x")).values.tolist()))
    ds.attrs = {**ds.attrs, **_item_attrs(ingest), "mixed_pixels": counts}
    return ds


def reflectance_stage(ingest: xr.Dataset, aoi: xr.Dataset, calibration: xr.Dataset) -> xr.Dataset:
    """Calibrated reflectance of every view on its own grid (paper eq. 2), and its relative noise.

    The calibration's residual correction, where it has one, divides it too: ``R = I / (k f c)``.

    ``reflectance_noise`` is each pixel's relative noise from its intensity and
    the calibration's noise model (:mod:`surffin.method.noise`); a calibration
    without one gives none.
    """
    r = reflectance(
        ingest["intensity"],
        aoi["distance"],
        aoi["aoi"],
        calibration["coef"],
        calibration.attrs["scale_k"],
        calibration.get("correction"),
    )
    ds = xr.Dataset({"reflectance": r.where(ingest["valid"])}, attrs=_item_attrs(ingest))
    if "noise_variance" in calibration:
        # where the reflectance is: not on invalid pixels, nor on mixed ones (no AOI, no distance)
        ds["reflectance_noise"] = relative_noise(ingest["intensity"], calibration).where(ds["reflectance"].notnull())
    return _single(ds)


def registration_stage(
    ingest: xr.Dataset,
    aoi: xr.Dataset,
    reflectance: xr.Dataset,
    *,
    method: str = "auto",
    roi=None,
    size: int = DEFAULT_SIZE,
    refine: bool = True,
    max_translation: float = POSE_OPTIONS["max_translation"],
    max_rotation: float = POSE_OPTIONS["max_rotation"],
) -> xr.Dataset:
    """Reflectance and AOI of every view on the reference view's grid (method step 4).

    ``method`` is one of :data:`~surffin.method.registration.METHODS`. With
    poses, ``refine`` refines each view's pose against the reference view's
    first, refusing a correction beyond ``max_translation`` (metres) or
    ``max_rotation`` (degrees); the corrections are in the attrs
    (``diagnostics``). Poses estimated from the clouds (``"clouds"``) are
    refined too, without those bounds. The homography ignores the three.

    With a ``roi`` (a specimen's pixels), only the roi and the pixels around it that the
    features of smoothing window ``size`` read there are mapped and warped
    (:func:`~surffin.method.features.feature_window`); the poses are found as without one.
    """
    roi = Roi.from_mapping(roi)
    options = {}
    if method != "homography":
        options.update(refine=refine, max_translation=max_translation, max_rotation=max_rotation)
    if roi is not None and method in ("auto", "homography"):
        # the roi picks the plane a homography registers (a specimen on its board); poses need none
        options["roi"] = {"y": list(roi.y), "x": list(roi.x)}
    window = None if roi is None else feature_window(roi, size, _grid(ingest))
    maps = registration_maps(ingest.compute(), method=method, window=window, **options)
    both = xr.Dataset({"reflectance": reflectance["reflectance"], "aoi": aoi["aoi"]})
    registered = register(both.compute(), maps)
    registered.attrs = {**registered.attrs, **_item_attrs(ingest)}
    return _single(registered)


def _read_pixels(map_x: np.ndarray, map_y: np.ndarray, grid: Roi) -> Roi:
    """Return pixels of ``grid`` that hold all those a bilinear warp to the sensor positions ``map_x``, ``map_y`` reads.

    A position reads the pixels around it: the box of the positions' floors grown by one pixel
    holds them. Empty (at the grid's corner) when no position is finite or near the grid.
    """
    finite = np.isfinite(map_x) & np.isfinite(map_y)
    corner = Roi((grid.y[0], grid.y[0]), (grid.x[0], grid.x[0]))
    if not finite.any():
        return corner
    y, x = (np.floor(positions[finite]) for positions in (map_y, map_x))
    try:
        return Roi.spanning((y.min(), y.max()), (x.min(), x.max())).grown(1).clip(grid)
    except ValueError:  # no position near the grid
        return corner


def _first_variability(
    reflectance: xr.Dataset, aoi: xr.Dataset, maps: xr.Dataset, order: list, *, size: int
) -> tuple[xr.DataArray, xr.DataArray]:
    """Return each reference pixel's variability from the first view of ``order`` that has one, and that view.

    What :func:`~surffin.method.features.first_available` of all the views' warped
    :func:`~surffin.method.features.variability` gives, with less work: the views after the
    first are warped only onto the pixels that the first leaves without a value (a few
    percent), and each view's variability is computed only on the pixels its warp reads
    (its ``region``; a view that reads none is skipped). The warp of a pixel does not
    depend on the others', so the values are the same to the bit.

    Parameters
    ----------
    reflectance, aoi : Dataset
        The reflectance store (``reflectance``, optional ``reflectance_noise``) and the AOI
        store (``aoi``) of the item, (view, y, x) on the views' own grids.
    maps : Dataset
        ``map_x``, ``map_y`` (view, y, x) onto the reference grid.
    order : list
        The views, the first choice first (:func:`~surffin.method.features.views_by_incidence`).
    size : int
        Window side of the variability, pixels.

    Returns
    -------
    values : (y, x) DataArray of float64
        On the maps' grid, with the attrs of the first view's variability; NaN where no view has one.
    source : (y, x) DataArray of int16
        Position in ``order`` of the view each value comes from, -1 where none.
    """
    noise = reflectance.get("reflectance_noise")
    grid = _grid(reflectance)

    def own(views: list, regions: list[Roi]) -> xr.DataArray:
        """Return the variability (view, y, x) of ``views``, each on its region (NaN elsewhere)."""
        images = [
            variability(
                reflectance["reflectance"].sel(view=v),
                aoi["aoi"].sel(view=v),
                size=size,
                relative_noise=None if noise is None else noise.sel(view=v),
                region=region,
            )
            for v, region in zip(views, regions)
        ]
        return xr.concat(images, dim=xr.DataArray(views, dims="view", name="view"))

    maps = maps.sel(view=order).transpose("view", "y", "x")
    reads = _read_pixels(maps["map_x"].values[0], maps["map_y"].values[0], grid)
    first = warp(own(order[:1], [reads]), maps.isel(view=[0])).isel(view=0, drop=True).compute()
    values = first.values.flatten()
    source = np.where(np.isfinite(values), np.int16(0), np.int16(-1))
    missing = np.flatnonzero(source < 0)
    if missing.size and len(order) > 1:
        # the missing pixels as one row of a grid of their own: warp samples each at its map position
        flat = {name: maps[name].values.reshape(len(order), 1, -1)[..., missing] for name in maps}
        regions = {k: _read_pixels(flat["map_x"][k], flat["map_y"][k], grid) for k in range(1, len(order))}
        # a view whose maps send no missing pixel near its grid has a value for none
        seen = [k for k, region in regions.items() if all(region.shape)]
        if seen:
            row = xr.Dataset({name: (maps[name].dims, a[seen]) for name, a in flat.items()}, maps["view"][seen].coords)
            filled, position = first_available(warp(own([order[k] for k in seen], [regions[k] for k in seen]), row))
            position = position.values.ravel()
            values[missing] = filled.values.ravel()
            source[missing] = np.where(position < 0, position, np.asarray(seen)[position])
    shape = first.shape
    return first.copy(data=values.reshape(shape)), xr.DataArray(source.reshape(shape), first.coords, first.dims)


def _window_of(registered: xr.Dataset, window: Roi) -> xr.Dataset:
    """Return the part of a registered store inside ``window``; ValueError when it lacks some of it."""
    part = select_roi(registered, window)
    if (part.sizes["y"], part.sizes["x"]) != window.shape:
        raise ValueError(
            f"item {registered.attrs.get('item', '?')!r}: the registered grid {_grid(registered)} does not hold "
            f"{window}, the roi and the pixels around it that its features read; register it with the same roi and size"
        )
    return part


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
    """Compute the per-pixel features R0, n (smoothed fit) and variability (method step 5).

    The variability of a pixel comes from the most perpendicular view that
    sees it: the views are ranked by their median AOI over the item's roi
    (else over all its pixels), the paper's choice of one view, and a pixel
    that view misses takes the next view's. Each view's variability is
    computed on its own grid and then warped: resampling first would smooth
    the noise it measures. Where the reflectance comes with its relative
    noise (``reflectance_noise``), the noise's variance is taken out of the
    variability. ``variability_view`` (y, x) says which view, as a
    position in the attr ``variability_views``. The uncertainties of the smoothed R0 and n account for the
    spatial correlation of the fit's residuals over the item's roi, else over all its pixels
    (:func:`surffin.method.features.residual_correlation`).

    With a roi, the features are computed on the part of the registered grid that those inside
    the roi read (:func:`~surffin.method.features.feature_window`, what
    :func:`registration_stage` registers with the same ``size``): inside the roi they are those
    of the whole grid. A registered grid without all of it is refused (ValueError).
    """
    roi = Roi.from_mapping(roi)
    if roi is not None:
        registered = _window_of(registered, feature_window(roi, size, _grid(aoi)))
    observed = registered[["reflectance", "aoi"]]
    if observed.chunks:  # dask: each pixel's views in one chunk (in memory, an item needs no graph)
        observed = observed.chunk({"view": -1})
    fit = fit_scattering(observed["reflectance"], observed["aoi"], min_views=min_views, min_spread=min_spread).persist()
    pixels = registered if roi is None else select_roi(registered, roi)
    correlation = residual_correlation(
        pixels["reflectance"], pixels["aoi"], fit.sel(y=pixels["y"], x=pixels["x"]), max_lag=size - 1
    )
    order = views_by_incidence(aoi["aoi"], roi)
    warped, source = _first_variability(reflectance, aoi, registered[["map_x", "map_y"]], order, size=variability_size)
    ds = features(fit, warped, size=size, error_correlation=correlation)
    ds["variability_view"] = source.assign_attrs(
        units="1", long_name="view the variability comes from: position in variability_views, -1 none"
    )
    ds.attrs = {
        **ds.attrs,
        **registered.attrs,
        "variability_views": [str(v) for v in order],
        NOISE_CORRECTED: int("reflectance_noise" in reflectance),
    }
    return _single(ds)


def labels_stage(
    features: xr.Dataset,
    training: xr.Dataset,
    *,
    k: int = 1,
    filter_kind: str = "median",
    filter_size: int = 5,
    min_posterior: float | None = None,
    outlier_probability: float | None = None,
) -> xr.Dataset:
    """Per-pixel class labels of a scene, before and after the label filter (method step 6).

    Pixels unlike every class (``outlier_probability``) or between classes
    (``min_posterior``) are unclassified, as :func:`surffin.method.classify.classify`
    says; the filter fills isolated ones (:func:`surffin.method.classify.filter_labels`),
    and ``label_filtered``'s ``unclassified`` attr counts those left by reason.
    ``posterior`` is the class model's probability of each pixel's k-NN class.
    """
    labels = classify(
        features.compute(), training, k=k, min_posterior=min_posterior, outlier_probability=outlier_probability
    )
    label = labels["label"]
    filtered = filter_labels(label, kind=filter_kind, size=filter_size)
    left = unclassified_counts(labels["unclassified_reason"], where=filtered.values == UNCLASSIFIED)
    filtered.attrs = {**label.attrs, "filter": filter_kind, "filter_size": filter_size, "unclassified": left}
    return labels.assign(label_filtered=filtered).assign_attrs(features.attrs)


def roughness_stage(features: xr.Dataset, *, relation: Mapping) -> xr.Dataset:
    """Map the indicative roughness of an item from its smoothed n (:mod:`surffin.method.roughness`)."""
    ds = roughness_map(features["n"], relation)
    ds.attrs = {**_item_attrs(features), **ds.attrs}
    return _single(ds)


@dataclass(frozen=True)
class Step:
    """One stage of the item chain: its name, its function and the store it writes."""

    name: str
    function: Callable[..., xr.Dataset]
    output: str

    @property
    def inputs(self) -> tuple[str, ...]:
        """The input stores: the function's positional arguments, by name."""
        parameters = inspect.signature(self.function).parameters.values()
        return tuple(p.name for p in parameters if p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD)

    @property
    def keywords(self) -> tuple[str, ...]:
        """The stage's parameters: the function's keyword-only arguments."""
        parameters = inspect.signature(self.function).parameters.values()
        return tuple(p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY)


#: An item's chain after its ingest (``calibration`` is the campaign's store).
ITEM_CHAIN = (
    Step("aoi", aoi_stage, "aoi"),
    Step("reflectance", reflectance_stage, "reflectance"),
    Step("registration", registration_stage, "registered"),
    Step("features", features_stage, "features"),
)


def process_item(ingest: xr.Dataset, calibration: xr.Dataset, **params) -> dict[str, xr.Dataset]:
    """Run :data:`ITEM_CHAIN` for one item in memory.

    Parameters
    ----------
    ingest, calibration : Dataset
        The item's ingest store and the calibration.
    **params
        Keyword parameters of the stages, each given to every stage that takes
        it (``roi`` to registration and features).

    Returns
    -------
    dict of str to Dataset
        The stores by name: ``aoi``, ``reflectance``, ``registered``,
        ``features``, each computed.

    Raises
    ------
    TypeError
        A parameter no stage takes.
    """
    if unknown := set(params) - {key for step in ITEM_CHAIN for key in step.keywords}:
        raise TypeError(f"process_item: no stage of the chain takes {sorted(unknown)}")
    stores = {"ingest": ingest, "calibration": calibration}
    for step in ITEM_CHAIN:
        inputs = {name: stores[name] for name in step.inputs}
        keywords = {key: params[key] for key in step.keywords if key in params}
        stores[step.output] = step.function(**inputs, **keywords).compute()
    return {step.output: stores[step.output] for step in ITEM_CHAIN}
