"""Sparse LiDAR depth -> dense per-camera depth (the ``densify_depth`` stage).

Entry point: :func:`densify` (one image). Methods live in :data:`DENSIFIERS`, registered with
:func:`register_densifier`; each is ``method(sparse_m, sparse_confidence, rgb, focal_px, **params)
-> DenseResult``. The stage ``densify_depth`` runs one on every camera that has a
:class:`CameraDepth` and fills its ``dense_m`` / ``dense_confidence``.

Conventions shared by every method:

- Depths are metres along the camera's +z, float32, 0 = unknown. A pixel is *measured* where
  ``sparse_m > 0`` and ``sparse_confidence > 0``.
- Parameters named ``*_ref_px`` are pixels of a camera with focal length
  :data:`REFERENCE_FOCAL_PX` (KITTI's, for which IP-Basic was tuned); a method scales them by
  ``focal_px / REFERENCE_FOCAL_PX``, so it looks at the same angular neighbourhood at any
  resolution.
- Only *trusted* measurements (see each method) seed the output. A pixel is filled only if it
  lies within ``max_fill_ref_px`` of one, has one in each of its four quadrants within 1.5 times
  that (or the image border there), and, unless ``extrapolate_top``, is not above the top-most one
  of its column (:func:`support_mask`): holes are interpolated, surfaces never grow into sky or
  into regions the LiDAR did not reach.
- Confidence (:func:`depth_confidence`) of an output depth ``z``::

      conf = c * exp(-d / d0) * exp(-(|z - z_ref| / (z * rel0))^2)      (0 where z == 0)

  At a measured pixel: ``c`` its input confidence, ``d = 0``, ``z_ref`` its measured depth, so a
  measurement kept as is has exactly its input confidence and one the method changed (an outlier
  it replaced) loses it. At any other pixel: ``c``, ``z_ref`` the input confidence and depth of
  the nearest trusted measurement, ``d`` the distance to it in pixels; every filled pixel is
  below 1. ``d0`` = ``conf_distance_ref_px`` (scaled), ``rel0`` = ``conf_relative_depth``.

Methods (``ipbasic`` and ``planar`` use no image):

- ``ipbasic``: IP-Basic-style morphology in inverted depth, focal-scaled kernels.
- ``planar``: local affine fit of inverse depth (exact on planes); a Gaussian-weighted mean
  where the window spans a depth edge.
- ``guided`` (:data:`DEFAULT_DENSIFIER`): RGB edge-aware normalized convolution of inverse depth
  (domain transform filter, or the fast global smoother with ``edge_filter="fgs"``).
- ``planar_guided``: ``planar``'s fit where the window holds one surface, ``guided``'s estimate
  along depth edges.

Measured with :func:`benchmark` (``python -c "from phigenesis.data.stages.densify import
benchmark; print(benchmark(repeats=7))"``, 2-core CPU): the 10 images of frames 0 and 5 of
synthetic scene 0 (waymo5 rig, 240x160, f = 255 px); inputs: the frame's own LiDAR sweep
(~15 % of pixels), and 30 % / 60 % of the exact depth with 2 cm noise and background leaking
through foreground edges; RMSE / MAE in metres over pixels where truth and output are > 0;
ms = median per image; 1920x1280 = one agg30 image upscaled 8x (f = 2040 px); "common": on the
pixels where all four methods give a depth::

                     ms per image              RMSE m          RMSE m, common        MAE m       coverage
    method         sweep agg30 agg60 1920  sweep agg30 agg60  sweep agg30 agg60  sweep agg30 agg60  agg30
    ipbasic          1.3   2.0   1.8  239  2.233 4.204 4.360  1.514 3.063 3.565  0.212 0.368 0.399  0.997
    planar           1.8   2.4   2.1  169  2.192 3.898 3.505  1.417 2.625 2.396  0.178 0.357 0.298  0.996
    guided           1.8   2.4   2.1  198  1.388 2.029 1.579  1.383 2.017 1.568  0.112 0.140 0.096  0.962
    planar_guided    2.2   2.9   2.6  175  1.374 2.046 1.608  1.381 2.015 1.562  0.096 0.125 0.089  0.979

Coverage (sweep / agg60): ipbasic 0.631 / 1.000, planar 0.630 / 0.999, guided 0.601 / 0.989,
planar_guided 0.616 / 0.994. On these inputs ``planar_guided``: RMSE 38 / 51 / 63 % and MAE
55 / 66 / 78 % below ``ipbasic``'s at 1.4-1.7x its time at 240x160 (1.45x at 720x480, 0.7x at
1920x1280, where ipbasic's focal-scaled bilateral filter dominates). Part of that gain is that
it leaves 0.6-1.8 % of the pixels unknown where the image cuts them off from every sample; on
the common pixels its RMSE is 9 / 34 / 56 % below. In ``benchmarks/depth.py --quick``
(aggregated, splat-filtered input) it measured 3.49 m against 4.33 m RMSE (-20 %) at equal
coverage and 1.5x the time. ``guided`` is as good in RMSE but fills less and is worse in MAE and
AbsRel (planes are not exact). ``edge_filter="fgs"`` (the fast global smoother) gains 2-4 % RMSE
for about 0.8 ms more per 240x160 image.

The default is ``guided``: on the projection's real output at 720x480 (``benchmarks/depth.py``:
plane-fitted sparse depth with depth-edge pixels excluded as seeds), it measured RMSE 2.04 m
against 4.10 m for ``ipbasic`` (-50 %) and 3.14 m for ``planar_guided``, MAE 0.10 m against 0.46
and 0.20, at 1.2x ``ipbasic``'s time: with the sparse input already plane-fitted, ``planar``'s
extra fit adds little, and its windows straddle the silhouettes the image edges resolve.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.native import load_densify_finish
from phigenesis.data.records import (
    DENSE_ORIGINS,
    TRUSTED_DEPTH_CONFIDENCE,
    CameraImage,
    Frame,
    LazyFrames,
    Scene,
)
from phigenesis.data.stages import register_stage
from phigenesis.options import ConfigError, check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

#: Focal length (pixels) at which ``*_ref_px`` parameters are given: KITTI's (about 721 px).
REFERENCE_FOCAL_PX = 721.0
#: The method :func:`densify` and the stage use unless told otherwise.
DEFAULT_DENSIFIER = "guided"
#: What the stage runs on a camera without an image when the method needs one.
DEFAULT_FALLBACK = "ipbasic"
#: Quadrant radius of the enclosure test, as a multiple of the fill distance.
ENCLOSURE_FACTOR = 1.5
#: Default of the stage's ``min_sparse_coverage``: a camera with a sparse depth on fewer of its
#: pixels than this share (over a scene) is warned about. The synthetic test scenes measure 3-50 %
#: per camera (16- to 64-beam LiDARs, 60x90 to 96x160 images); a camera the ego body hid, 0 %.
MIN_SPARSE_COVERAGE = 0.01
# Stand-ins for 0 and infinity that keep arithmetic finite: masks are applied by multiplying,
# since np.where is slow on the scattered masks of sparse depth.
_TINY = np.float32(1e-12)
_FAR = np.float32(1e30)

F32 = NDArray[np.float32]
Mask = NDArray[np.bool_]


@dataclass
class DenseResult:
    """A densified depth map.

    Attributes:
        depth_m: (H, W) float32 z-depth in metres, 0 where still unknown.
        confidence: (H, W) float32 in [0, 1], exactly 0 where ``depth_m`` is 0.
    """

    depth_m: F32
    confidence: F32


Densifier = Callable[..., DenseResult]
#: The registered methods by name.
DENSIFIERS: dict[str, Densifier] = {}
_NEEDS_RGB: set[str] = set()
Blur = Literal["bilateral", "gaussian", "none"]
EdgeFilter = Literal["dtf", "fgs"]


@dataclass(frozen=True)
class DensifyParams:
    """Parameters of the ``densify_depth`` stage: the stage's own, then every method's keyword
    parameters, each declared once here with its type and range (None: not given, so the method
    keeps its own default; a method is given only the parameters it takes, and naming one it does
    not take is an error). ``*_ref_px`` lengths are pixels at :data:`REFERENCE_FOCAL_PX`.

    Attributes:
        method: the registered method (:data:`DENSIFIERS`) run on every camera.
        fallback: the method run on a camera without an image when ``method`` needs one (it gets
            those of the given parameters it takes); it must not need the image.
        min_confidence: sparse depths below this confidence (depth-edge pixels) seed nothing.
        min_sparse_coverage: share of a camera's pixels, over the scene, below which its sparse
            depth is warned about.
        max_depth_m ... keep_tau: ``ipbasic``'s (see :func:`ipbasic`).
        window_ref_px, min_spread_px, residual_tol, edge_sigma_ref_px: ``planar``'s plane fits.
        edge_filter, smooth_ref_px, sigma_color, min_image_support: ``guided``'s image-guided mean.
        occlusion_ref_px, occlusion_tau: see-through samples dropped (all but ``ipbasic``).
        max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth: what every
            method may fill and the confidence of what it fills (module docstring).
    """

    method: str = option(DEFAULT_DENSIFIER)
    fallback: str = option(DEFAULT_FALLBACK)
    min_confidence: float = option(TRUSTED_DEPTH_CONFIDENCE, ge=0, le=1)
    min_sparse_coverage: float = option(MIN_SPARSE_COVERAGE, ge=0, le=1)
    max_depth_m: float | None = option(None, gt=0, le=1000)
    blur: Blur | None = option(None)
    dilate_ref_px: float | None = option(None, ge=0, le=1000)
    close_ref_px: float | None = option(None, ge=0, le=1000)
    fill_ref_px: float | None = option(None, ge=0, le=1000)
    blur_ref_px: float | None = option(None, gt=0, le=1000)
    bilateral_sigma_m: float | None = option(None, gt=0, le=1000)
    keep_measured: bool | None = option(None)
    keep_tau: float | None = option(None, ge=0, le=10)
    window_ref_px: float | None = option(None, ge=0, le=1000)
    min_spread_px: float | None = option(None, ge=0, le=1000)
    residual_tol: float | None = option(None, ge=0, le=10)
    edge_sigma_ref_px: float | None = option(None, gt=0, le=1000)
    edge_filter: EdgeFilter | None = option(None)
    smooth_ref_px: float | None = option(None, gt=0, le=1000)
    sigma_color: float | None = option(None, gt=0, le=1000)
    min_image_support: float | None = option(None, ge=0, le=1)
    occlusion_ref_px: float | None = option(None, ge=0, le=1000)
    occlusion_tau: float | None = option(None, ge=0, le=10)
    max_fill_ref_px: float | None = option(None, ge=0, le=10_000)
    extrapolate_top: bool | None = option(None)
    conf_distance_ref_px: float | None = option(None, gt=0, le=10_000)
    conf_relative_depth: float | None = option(None, gt=0, le=10)

    def __post_init__(self) -> None:
        check_options(self, "DensifyParams")
        for key in ("method", "fallback"):
            name = getattr(self, key)
            if name not in DENSIFIERS:
                known = sorted(DENSIFIERS)
                raise ConfigError(f"DensifyParams: {key} = {name!r}: must be one of {known}")
        if needs_rgb(self.fallback):
            raise ConfigError(f"DensifyParams: fallback = {self.fallback!r}: must not need the image")
        stage_keys = {"method", "fallback", "min_confidence", "min_sparse_coverage"}
        given = [f.name for f in dataclasses.fields(self) if f.name not in stage_keys]
        foreign = [k for k in given if getattr(self, k) is not None and k not in method_params(self.method)]
        if foreign:
            raise ConfigError(
                f"DensifyParams: method {self.method!r} takes no parameters {foreign}; it takes "
                f"{sorted(method_params(self.method))}"
            )

    def method_kwargs(self, method: str) -> dict[str, Any]:
        """The given parameters (not None) that ``method`` takes, as its keyword arguments."""
        values = {k: getattr(self, k) for k in method_params(method)}
        return {k: v for k, v in values.items() if v is not None}


def register_densifier(name: str, *, needs_rgb: bool = False) -> Callable[[Densifier], Densifier]:
    """Decorator registering a densification method under ``name``.

    The method is ``fn(sparse_m, sparse_confidence, rgb, focal_px, *, **params) -> DenseResult``
    with keyword-only parameters, each a field of :class:`DensifyParams` (its type and range are
    declared there, once for every method; ValueError otherwise); ``needs_rgb``: it uses the image
    and raises ValueError when ``rgb`` is None.
    """

    def wrap(fn: Densifier) -> Densifier:
        if name in DENSIFIERS and DENSIFIERS[name] is not fn:
            raise ValueError(f"a densifier named {name!r} is already registered")
        declared = {f.name for f in dataclasses.fields(DensifyParams)}
        undeclared = sorted(k for k, _ in _keyword_params(fn) if k not in declared)
        if undeclared:
            raise ValueError(
                f"densifier {name!r}: parameters {undeclared} are not declared in DensifyParams "
                "(each needs its type and range there)"
            )
        DENSIFIERS[name] = fn
        if needs_rgb:
            _NEEDS_RGB.add(name)
        return fn

    return wrap


def get_densifier(method: str) -> Densifier:
    """The method registered as ``method``; KeyError naming the registered ones otherwise."""
    if method not in DENSIFIERS:
        raise KeyError(f"unknown densifier {method!r}; registered: {sorted(DENSIFIERS)}")
    return DENSIFIERS[method]


def needs_rgb(method: str) -> bool:
    """Whether the method ``method`` needs the RGB image."""
    get_densifier(method)
    return method in _NEEDS_RGB


def method_params(method: str) -> dict[str, Any]:
    """The keyword parameters of ``method`` with their defaults."""
    return dict(_keyword_params(get_densifier(method)))


@functools.cache
def _keyword_params(fn: Densifier) -> tuple[tuple[str, Any], ...]:
    sig = inspect.signature(fn)
    return tuple(
        (p.name, p.default) for p in sig.parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY
    )


def check_params(method: str, params: dict[str, Any]) -> None:
    """Raises :class:`~phigenesis.options.ConfigError` (a ValueError) if ``params`` holds a name
    that ``method`` does not accept or a value outside its type or range (:class:`DensifyParams`)."""
    accepted = method_params(method)
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ConfigError(f"densifier {method!r}: unknown parameters {unknown}; accepted: {sorted(accepted)}")
    from_mapping(DensifyParams, {**params, "method": method}, f"densifier {method!r}")


# --------------------------------------------------------------------------------------------
# Entry point


def densify(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None = None,
    *,
    focal_px: float,
    method: str = DEFAULT_DENSIFIER,
    **params: Any,
) -> DenseResult:
    """Densifies one sparse depth map with the registered method ``method``.

    Args:
        sparse_m: (H, W) float z-depth in metres, 0 = unknown; finite and >= 0.
        sparse_confidence: (H, W) float in [0, 1]; pixels with confidence 0 count as unknown.
        rgb: (H, W, 3) uint8 RGB image of the same camera, or None (methods that need it raise
            ValueError).
        focal_px: the camera's focal length in pixels (scales the method's neighbourhoods).
        method: a name in :data:`DENSIFIERS` (an unknown name raises KeyError).
        params: the method's keyword parameters (an unknown name, or a value outside its type or
            range in :class:`DensifyParams`, raises :class:`~phigenesis.options.ConfigError`).

    Returns:
        The dense depth and its confidence (module docstring). The inputs are never modified:
        methods get read-only views of them.
    """
    get_densifier(method)
    check_params(method, params)
    return _densify_checked(sparse_m, sparse_confidence, rgb, focal_px, method, params)


def _densify_checked(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None,
    focal_px: float,
    method: str,
    params: dict[str, Any],
    crop: bool = True,
) -> DenseResult:
    """:func:`densify` with ``method`` and ``params`` already checked (the stage checks them once
    per scene, :class:`DensifyParams`, not once per image).

    ``crop``: a method with a crop margin (:data:`CROP_MARGINS`) runs only on the measurements'
    bounding box grown by that margin (:func:`crop_box`), the rest of the image staying 0: at
    real size the LiDAR reaches little above the horizon, so a third or more of the pixels can be
    left out. :func:`densify_reference` is the whole-image run it is tested against."""
    fn = get_densifier(method)
    sparse, conf = check_depth_maps(sparse_m, sparse_confidence)
    if rgb is not None:
        rgb = check_rgb(rgb, sparse.shape)
    elif method in _NEEDS_RGB:
        raise ValueError(f"densifier {method!r} needs the RGB image, got rgb=None")
    focal_px = float(focal_px)
    if not np.isfinite(focal_px) or focal_px <= 0:
        raise ValueError(f"focal_px must be a positive finite number of pixels, got {focal_px}")
    measured = (sparse > 0) & (conf > 0)
    if not measured.any():
        zeros = np.zeros(sparse.shape, np.float32)
        return DenseResult(zeros, zeros.copy())
    box = crop_box(measured, method, params, focal_px) if crop else None
    if box is None:
        return _check_result(fn(sparse, conf, rgb, focal_px, **params), sparse.shape, method)
    rows, cols = box
    sub_rgb = None if rgb is None else np.ascontiguousarray(rgb[rows, cols])
    part = fn(
        _readonly(np.ascontiguousarray(sparse[rows, cols])),
        _readonly(np.ascontiguousarray(conf[rows, cols])),
        sub_rgb,
        focal_px,
        **params,
    )
    part = _check_result(part, (rows.stop - rows.start, cols.stop - cols.start), method)
    depth, confidence = np.zeros(sparse.shape, np.float32), np.zeros(sparse.shape, np.float32)
    depth[rows, cols], confidence[rows, cols] = part.depth_m, part.confidence
    return DenseResult(depth, confidence)


def densify_reference(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None = None,
    *,
    focal_px: float,
    method: str = DEFAULT_DENSIFIER,
    **params: Any,
) -> DenseResult:
    """:func:`densify` on the whole image, without the crop to the measurements (the reference the
    cropped run is tested against: identical for ``ipbasic``, within float rounding of the
    recursive edge-aware filter for ``guided``, tests/test_densify.py)."""
    get_densifier(method)
    check_params(method, params)
    return _densify_checked(sparse_m, sparse_confidence, rgb, focal_px, method, params, crop=False)


def _guided_margin(params: dict[str, Any], focal_px: float) -> float:
    """Crop margin of ``guided`` (pixels): the fill reach and its enclosure test, the occlusion
    test's radius, and eight spatial scales of the edge-aware filter (its recursive passes carry a
    sample's weight ``exp(-sqrt(2) d / scale)`` at most ``d`` pixels on: ~1e-5 at eight)."""
    full = {**method_params("guided"), **params}
    smooth_ref = full["smooth_ref_px"]
    if smooth_ref is None:
        smooth_ref = EDGE_FILTERS[full["edge_filter"]][0]
    reach = scaled_px(full["max_fill_ref_px"], focal_px) * (1 + ENCLOSURE_FACTOR)
    return reach + scaled_px(full["occlusion_ref_px"], focal_px) + 8 * scaled_px(smooth_ref, focal_px)


def _ipbasic_margin(params: dict[str, Any], focal_px: float) -> float:
    """Crop margin of ``ipbasic`` (pixels): the fill reach and its enclosure test, and every
    morphology and blur radius in turn (each can carry a value that far)."""
    full = {**method_params("ipbasic"), **params}
    reach = scaled_px(full["max_fill_ref_px"], focal_px) * (1 + ENCLOSURE_FACTOR)
    radii = sum(
        _radius(full[k], focal_px) for k in ("dilate_ref_px", "close_ref_px", "fill_ref_px", "blur_ref_px")
    )
    return reach + 2 * radii + 3  # closing = dilate + erode; median 5x5


#: Methods that may run on a crop around their measurements, with the margin (pixels) a crop needs
#: so that every pixel they can fill, and everything that decides it, lies inside. ``planar`` and
#: ``planar_guided`` are not here: their plane fits pool samples over tiles aligned to the image.
CROP_MARGINS: dict[str, Callable[[dict[str, Any], float], float]] = {
    "guided": _guided_margin,
    "ipbasic": _ipbasic_margin,
}
#: A crop is used only where it leaves out at least this share of the image's pixels.
MIN_CROP_SAVING = 0.1


def crop_box(
    measured: Mask, method: str, params: dict[str, Any], focal_px: float
) -> tuple[slice, slice] | None:
    """The (rows, cols) slices of the bounding box of the (H, W) ``measured`` pixels grown by the
    method's crop margin (:data:`CROP_MARGINS`) and clipped to the image; None where the method
    has none, where the image has no measurement, or where the crop would save less than
    :data:`MIN_CROP_SAVING` of the pixels."""
    margin_of = CROP_MARGINS.get(method)
    if margin_of is None:
        return None
    rows_any, cols_any = measured.any(axis=1), measured.any(axis=0)
    if not rows_any.any():
        return None
    h, w = measured.shape
    m = int(np.ceil(margin_of(params, focal_px))) + 1
    r0, r1 = int(rows_any.argmax()), h - int(rows_any[::-1].argmax())
    c0, c1 = int(cols_any.argmax()), w - int(cols_any[::-1].argmax())
    r0, r1, c0, c1 = max(0, r0 - m), min(h, r1 + m), max(0, c0 - m), min(w, c1 + m)
    if (r1 - r0) * (c1 - c0) > (1 - MIN_CROP_SAVING) * h * w:
        return None
    return slice(r0, r1), slice(c0, c1)


def _readonly(arr: np.ndarray) -> np.ndarray:
    view = arr.view()
    view.flags.writeable = False
    return view


def check_depth_maps(
    depth_m: Any, confidence: Any, names: tuple[str, str] = ("sparse_m", "sparse_confidence")
) -> tuple[F32, F32]:
    """Validates a depth map and its confidence (2-D, float, finite, same shape, depths >= 0,
    confidences in [0, 1]; ``names`` name them in errors); returns them as read-only float32
    (converted copies if needed)."""
    arrays = []
    for name, value in zip(names, (depth_m, confidence), strict=True):
        arr = np.asarray(value)
        if arr.ndim != 2:
            raise ValueError(f"{name} must be a 2-D (H, W) array, got shape {arr.shape}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{name} must be a floating-point (float32) array, got dtype {arr.dtype}")
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise ValueError(f"{name} has {bad} NaN or infinite values")
        arrays.append(_readonly(arr.astype(np.float32, copy=False)))
    sparse, conf = arrays
    if conf.shape != sparse.shape:
        raise ValueError(f"{names[1]} has shape {conf.shape}, {names[0]} has {sparse.shape}")
    negative = int(np.count_nonzero(sparse < 0))
    if negative:
        raise ValueError(f"{names[0]} has {negative} negative depths (0 marks unknown)")
    if np.any((conf < 0) | (conf > 1)):
        raise ValueError(f"{names[1]} must lie in [0, 1], got [{conf.min()}, {conf.max()}]")
    return sparse, conf


def check_rgb(rgb: Any, shape: tuple[int, ...], like: str = "sparse_m") -> NDArray[np.uint8]:
    """Validates an (H, W, 3) uint8 image of ``shape`` (that of the map named ``like``); returns a
    read-only view."""
    arr = np.asarray(rgb)
    if arr.shape != (*shape, 3):
        raise ValueError(f"rgb must have shape {(*shape, 3)} (H, W, 3, as {like}), got {arr.shape}")
    if arr.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8, got dtype {arr.dtype}")
    return _readonly(arr)


def _check_result(result: DenseResult, shape: tuple[int, ...], method: str) -> DenseResult:
    depth = np.asarray(result.depth_m, np.float32)
    conf = np.asarray(result.confidence, np.float32)
    if depth.shape != shape or conf.shape != shape:
        raise ValueError(f"densifier {method!r} returned shapes {depth.shape}, {conf.shape}; want {shape}")
    if isinstance(result, _CleanResult):
        return DenseResult(depth, conf)
    depth = np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
    depth = depth * (depth > 0)
    conf = np.clip(np.nan_to_num(conf), 0, 1) * (depth > 0)
    return DenseResult(depth, conf)


# --------------------------------------------------------------------------------------------
# Shared pieces: scale, occlusion test, support, confidence


def scaled_px(ref_px: float, focal_px: float) -> float:
    """A length in reference pixels (:data:`REFERENCE_FOCAL_PX`) in this camera's pixels."""
    return float(ref_px) * focal_px / REFERENCE_FOCAL_PX


def _radius(ref_px: float, focal_px: float) -> int:
    """A neighbourhood radius in reference pixels as a whole number of pixels (at least 1)."""
    return max(1, round(scaled_px(ref_px, focal_px)))


def occluded_samples(sparse: F32, measured: Mask, radius_px: int, tau: float) -> Mask:
    """Measured pixels seen through a nearer surface, (H, W) bool: deeper than ``(1 + tau)``
    times the nearest measurement in *each* of their four quadrants (radius ``radius_px``, axes
    included).

    No point of a plane fails: inverse depth is affine in (u, v) on a plane, so the quadrant
    opposite its gradient holds no nearer point. A point surrounded by a nearer surface (LiDAR
    see-through, background leaking between foreground samples) fails.
    """
    r = radius_px
    h, w = sparse.shape
    z = sparse + ~measured * _FAR
    # Nearest depth over each (r+1)^2 block, indexed by its top-left corner (padded by r so that
    # every quadrant of every pixel is a block): the four quadrants are four shifts of it.
    padded = cv2.copyMakeBorder(z, r, r, r, r, cv2.BORDER_CONSTANT, value=float(_FAR))
    block_min = cv2.erode(padded, np.ones((r + 1, r + 1), np.uint8), anchor=(0, 0))
    up, down, left, right = slice(0, h), slice(r, r + h), slice(0, w), slice(r, r + w)
    deepest = np.maximum(
        np.maximum(block_min[up, left], block_min[up, right]),
        np.maximum(block_min[down, left], block_min[down, right]),
    )
    return measured & (sparse > (1.0 + tau) * deepest)


def support_mask(trusted: Mask, distance_px: F32, max_fill_px: float, extrapolate_top: bool = False) -> Mask:
    """Pixels a method may fill, (H, W) bool.

    A pixel qualifies if it lies within ``max_fill_px`` (``distance_px``: distance to the nearest
    ``trusted`` pixel) of a trusted measurement, each of its four quadrants (axes included,
    radius ``ENCLOSURE_FACTOR * max_fill_px``) holds one or reaches the image border, and, unless
    ``extrapolate_top``, it is not above the top-most one of its column (that row taken as the
    minimum over +-``max_fill_px`` columns, so a column missing its top sample is not cut short).
    """
    support = distance_px <= max_fill_px
    present = trusted.astype(np.uint8)
    re = max(1, round(ENCLOSURE_FACTOR * max_fill_px))
    kernel = np.ones((re + 1, re + 1), np.uint8)
    for anchor in ((0, 0), (re, 0), (0, re), (re, re)):
        support &= cv2.dilate(present, kernel, anchor=anchor, borderValue=1) > 0
    if not extrapolate_top:
        h = trusted.shape[0]
        top = np.where(trusted.any(axis=0), trusted.argmax(axis=0), h).astype(np.float32)
        r = int(max_fill_px)
        if r > 0:
            top = cv2.erode(top[None, :], np.ones((1, 2 * r + 1), np.uint8))[0]
        support &= np.arange(h, dtype=np.float32)[:, None] >= top[None, :]
    return support


def depth_confidence(
    dense: F32,
    sparse: F32,
    conf: F32,
    nearest_index: NDArray[np.int32],
    distance_px: F32,
    distance_scale_px: float,
    relative_depth_scale: float,
) -> F32:
    """Confidence of ``dense``, (H, W) float32 (formula in the module docstring).

    ``nearest_index`` / ``distance_px``: flat index of and distance to the nearest trusted
    measurement (:func:`nearest_trusted`); ``distance_scale_px`` is ``d0`` and
    ``relative_depth_scale`` is ``rel0``.
    """
    measured = (sparse > 0) & (conf > 0)
    other = ~measured
    z_ref = sparse * measured + sparse.ravel()[nearest_index] * other
    c = conf * measured + conf.ravel()[nearest_index] * other
    filled = dense > 0
    rel = np.abs(dense - z_ref) / ((dense + ~filled) * relative_depth_scale)
    out = c * np.exp(distance_px * other * np.float32(-1.0 / distance_scale_px) - rel * rel)
    return out * filled


def nearest_trusted(trusted: Mask) -> tuple[NDArray[np.int32], F32]:
    """Flat index (``v * W + u``) of and distance in pixels to the nearest ``True`` pixel of
    ``trusted`` (at least one), both (H, W); 3x3-mask approximate Euclidean distance."""
    labels, lut, dist = _nearest_labels(trusted)
    return lut[labels], dist


def _nearest_labels(trusted: Mask) -> tuple[NDArray[np.int32], NDArray[np.int32], F32]:
    """:func:`nearest_trusted` before the lookup: OpenCV's (H, W) int32 labels, the int32 flat
    index of each label's pixel, and the (H, W) float32 distances."""
    src = (~trusted).view(np.uint8) * np.uint8(255)
    dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
    lut = np.zeros(int(labels.max()) + 1, np.int32)
    lut[labels[trusted]] = np.flatnonzero(trusted)
    return labels, lut, dist


class _CleanResult(DenseResult):
    """A :class:`DenseResult` already finite, >= 0 and with 0 confidence wherever its depth is 0
    (the native last pass's): :func:`_check_result` passes it through."""


@dataclass(frozen=True)
class FillParams:
    """Parameters every method shares (see the module docstring)."""

    max_fill_ref_px: float
    extrapolate_top: bool
    conf_distance_ref_px: float
    conf_relative_depth: float


def _finish(
    dense: F32, sparse: F32, conf: F32, trusted: Mask, focal_px: float, fill: FillParams, native: bool = True
) -> DenseResult:
    """Restricts ``dense`` to the support of the ``trusted`` measurements and adds its confidence.

    ``native``: the support applied and the confidence computed in one pass by the C kernel
    (``csrc/densify_finish.c``) where it can be built; :func:`_finish_reference` (numpy) is the
    reference it is tested against (equal up to the last bit of ``exp``)."""
    if not trusted.any():
        zeros = np.zeros(sparse.shape, np.float32)
        return DenseResult(zeros, zeros.copy())
    kernel = load_densify_finish() if native else None
    if kernel is None:
        return _finish_reference(dense, sparse, conf, trusted, focal_px, fill)
    labels, lut, dist = _nearest_labels(trusted)
    support = support_mask(trusted, dist, scaled_px(fill.max_fill_ref_px, focal_px), fill.extrapolate_top)
    d0 = scaled_px(fill.conf_distance_ref_px, focal_px)
    depth, confidence = kernel(
        np.ascontiguousarray(dense, np.float32),
        np.ascontiguousarray(support),
        np.ascontiguousarray(sparse, np.float32),
        np.ascontiguousarray(conf, np.float32),
        labels,
        lut,
        dist,
        d0,
        fill.conf_relative_depth,
    )
    return _CleanResult(depth, confidence)


def _finish_reference(
    dense: F32, sparse: F32, conf: F32, trusted: Mask, focal_px: float, fill: FillParams
) -> DenseResult:
    """:func:`_finish` in numpy: the support mask, then :func:`depth_confidence`."""
    index, dist = nearest_trusted(trusted)
    support = support_mask(trusted, dist, scaled_px(fill.max_fill_ref_px, focal_px), fill.extrapolate_top)
    dense = dense * (support & (dense > 0))
    d0 = scaled_px(fill.conf_distance_ref_px, focal_px)
    confidence = depth_confidence(dense, sparse, conf, index, dist, d0, fill.conf_relative_depth)
    return DenseResult(dense, confidence)


# --------------------------------------------------------------------------------------------
# ipbasic: morphology in inverted depth (after Ku et al., "In Defense of Classical Image
# Processing", CRV 2018, fill_in_fast), with focal-scaled kernels


def _diamond(radius: int) -> NDArray[np.uint8]:
    i = np.abs(np.arange(-radius, radius + 1))
    return (i[:, None] + i[None, :] <= radius).astype(np.uint8)


def _square(radius: int) -> NDArray[np.uint8]:
    return np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)


@register_densifier("ipbasic")
def ipbasic(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None,
    focal_px: float,
    *,
    max_depth_m: float = 100.0,
    blur: str = "bilateral",
    dilate_ref_px: float = 2.0,
    close_ref_px: float = 2.0,
    fill_ref_px: float = 3.0,
    blur_ref_px: float = 2.0,
    bilateral_sigma_m: float = 1.5,
    keep_measured: bool = True,
    keep_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """Morphological fill in inverted depth, so that the nearer surface wins every dilation.

    Steps (radii in reference pixels, scaled and rounded, at least 1 px): invert
    ``d' = D - d`` with ``D = max(max_depth_m, deepest measurement + 1 m)``, so depths beyond
    ``max_depth_m`` survive; dilate with a diamond of radius ``dilate_ref_px``; close with a
    square of radius ``close_ref_px``; fill the still-empty pixels by a square dilation of radius
    ``fill_ref_px``; median over IP-Basic's 5x5 scaled, rounded to 3x3 or 5x5 (OpenCV's float
    median has no other sizes); ``blur``: "bilateral" (range sigma ``bilateral_sigma_m`` metres,
    space sigma ``blur_ref_px``), "gaussian" (normalized over filled pixels, so that empty pixels
    do not drag depth toward ``D``) or "none"; invert back. With ``keep_measured``, measured
    pixels that moved by less than ``keep_tau`` (relative) get their exact value back (IP-Basic
    itself lets the dilation and the blur move them); the others, see-through points that a
    nearer neighbour overrode, keep the new value. Does not use ``rgb``. Every measurement is
    trusted (seeds the support and the confidence).
    """
    if blur not in ("bilateral", "gaussian", "none"):
        raise ValueError(f"ipbasic: blur must be 'bilateral', 'gaussian' or 'none', got {blur!r}")
    measured = (sparse_m > 0) & (sparse_confidence > 0)
    offset = max(float(max_depth_m), float(sparse_m[measured].max()) + 1.0)
    inv = (np.float32(offset) - sparse_m) * measured

    inv = cv2.dilate(inv, _diamond(_radius(dilate_ref_px, focal_px)))
    inv = cv2.morphologyEx(inv, cv2.MORPH_CLOSE, _square(_radius(close_ref_px, focal_px)))
    inv = inv + (inv <= 0) * cv2.dilate(inv, _square(_radius(fill_ref_px, focal_px)))
    blur_r = _radius(blur_ref_px, focal_px)
    inv = cv2.medianBlur(inv, 5 if scaled_px(5, focal_px) >= 4 else 3)
    filled = inv > 0.1
    k = 2 * blur_r + 1
    if blur == "bilateral":
        smoothed = cv2.bilateralFilter(inv, k, bilateral_sigma_m, scaled_px(blur_ref_px, focal_px))
    elif blur == "gaussian":
        weight = cv2.GaussianBlur(filled.astype(np.float32), (k, k), 0)
        smoothed = cv2.GaussianBlur(inv * filled, (k, k), 0)
        smoothed = smoothed / np.maximum(weight, 1e-6)
    else:
        smoothed = inv
    dense = (np.float32(offset) - smoothed) * filled
    if keep_measured:
        # Measurements the morphology moved by less than keep_tau are restored; the others were
        # overridden by a nearer surface (see-through points) and stay overridden.
        kept = measured & (np.abs(dense - sparse_m) <= keep_tau * sparse_m)
        dense = sparse_m * kept + dense * ~kept
    fill = FillParams(max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth)
    return _finish(dense, sparse_m, sparse_confidence, measured, focal_px, fill)


# --------------------------------------------------------------------------------------------
# Inverse-depth estimators: local plane fit, Gaussian and image-guided weighted means


@dataclass
class _Samples:
    """The measurements a method works from, all (H, W).

    Attributes:
        kept: bool, measured and not seen through a nearer surface (:func:`occluded_samples`).
        q: float32 inverse depth (1/m) at kept pixels, 0 elsewhere.
        w: float32 weight: the input confidence at kept pixels, 0 elsewhere.
    """

    kept: Mask
    q: F32
    w: F32


def _samples(sparse: F32, conf: F32, focal_px: float, occlusion_ref_px: float, tau: float) -> _Samples:
    measured = (sparse > 0) & (conf > 0)
    kept = measured & ~occluded_samples(sparse, measured, _radius(occlusion_ref_px, focal_px), tau)
    q = kept / np.maximum(sparse, _TINY)
    return _Samples(kept, q, conf * kept)


def _box_sum(image: F32, radius: int) -> F32:
    """Sums over (2r+1)^2 windows, zero outside the image."""
    k = (2 * radius + 1, 2 * radius + 1)
    return cv2.boxFilter(image, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)


def _block_mean(image: F32, block: int) -> F32:
    """Means over ``block`` x ``block`` tiles (the image zero-padded to whole tiles)."""
    h, w = image.shape
    hb, wb = -(-h // block), -(-w // block)
    if (hb * block, wb * block) != (h, w):
        image = cv2.copyMakeBorder(image, 0, hb * block - h, 0, wb * block - w, cv2.BORDER_CONSTANT, value=0)
    return cv2.resize(image, (wb, hb), interpolation=cv2.INTER_AREA)


def _block_expand(image: np.ndarray, block: int, shape: tuple[int, int]) -> np.ndarray:
    """Each tile's value repeated over its ``block`` x ``block`` pixels, cropped to ``shape``."""
    hb, wb = image.shape
    big = cv2.resize(image, (wb * block, hb * block), interpolation=cv2.INTER_NEAREST)
    return big[: shape[0], : shape[1]]


def plane_fit(q: F32, w: F32, radius_px: int, min_spread_px: float, residual_tol: float) -> tuple[F32, Mask]:
    """Weighted least-squares plane ``q(u, v) = a + b u + c v`` of inverse depth around each pixel.

    Normalized convolution with a first-order basis: box sums of the weighted moments over a
    window of radius ``radius_px``, then a closed-form solve per pixel with centred moments.
    Inverse depth is affine in (u, v) on any plane, so planes are reproduced exactly.

    From a radius of 3 px the samples are first pooled over tiles of about ``radius_px / 2``
    pixels: each tile becomes one sample, its summed weight at its weighted centroid with its
    weighted mean inverse depth (on a plane, exactly the plane's value there), and each pixel
    takes the plane fitted over the 5 x 5 tiles around its own (a window that contains it).
    Planes stay exact and the cost stays about one pass over the image at any resolution.

    Args:
        q: (H, W) float32 inverse depth samples (1/m), anything where ``w == 0``.
        w: (H, W) float32 sample weights, 0 = no sample.
        radius_px: window radius in pixels.
        min_spread_px: the fit counts only where the samples' weighted position covariance has
            its smaller eigenvalue >= ``min_spread_px ** 2`` (not collinear, not a lone point).
        residual_tol: ... and where the weighted RMS residual is <= ``residual_tol`` times the
            fitted value (one surface in the window, not a depth edge).

    Returns:
        ``(value, ok)``: (H, W) float32 fitted inverse depth at each pixel and bool validity.
    """
    h, wd = q.shape
    block = max(1, round(radius_px / 2))
    # Coordinates in units of the radius keep float32 moments well conditioned at any size.
    u = ((np.arange(wd, dtype=np.float32) - wd / 2) / radius_px)[None, :]
    v = ((np.arange(h, dtype=np.float32) - h / 2) / radius_px)[:, None]
    if block > 1:
        w_t = _block_mean(w, block)
        inv_w = np.float32(1.0) / np.maximum(w_t, _TINY)
        q = _block_mean(w * q, block) * inv_w
        u_t = _block_mean(w * u, block) * inv_w
        v_t = _block_mean(w * v, block) * inv_w
        wq, wu, wv = w_t * q, w_t * u_t, w_t * v_t
        moments = [w_t, wu, wv, wq, wu * u_t, wu * v_t, wv * v_t, wq * q, wq * u_t, wq * v_t]
    else:
        wq, wu, wv = w * q, w * u, w * v
        moments = [w, wu, wv, wq, wu * u, wu * v, wv * v, wq * q, wq * u, wq * v]
    sums = [_box_sum(m, max(1, round(radius_px / block))) for m in moments]
    offset, gu, gv, ok = _solve_planes(sums, (min_spread_px / radius_px) ** 2, residual_tol)
    if block > 1:
        offset, gu, gv = (_block_expand(x, block, (h, wd)) for x in (offset, gu, gv))
        ok = _block_expand(ok.view(np.uint8), block, (h, wd)).view(bool)
    value = offset + gu * u + gv * v
    return value, ok & (value > 0)


def _solve_planes(sums: list[F32], min_spread: float, residual_tol: float) -> tuple[F32, F32, F32, Mask]:
    """Planes ``q = offset + gu * u + gv * v`` from the window sums of :func:`plane_fit`
    (``u``, ``v`` as there) and whether each is ``ok``."""
    s_w, s_u, s_v, s_q, s_uu, s_uv, s_vv, s_qq, s_qu, s_qv = sums
    inv_w = np.float32(1.0) / np.maximum(s_w, _TINY)
    mu, mv, mq = s_u * inv_w, s_v * inv_w, s_q * inv_w
    cuu = s_uu * inv_w - mu * mu
    cuv = s_uv * inv_w - mu * mv
    cvv = s_vv * inv_w - mv * mv
    cqu = s_qu * inv_w - mq * mu
    cqv = s_qv * inv_w - mq * mv
    cuv2 = cuv * cuv
    # The covariance's smaller eigenvalue exceeds t exactly when C - t I is positive definite:
    # cuu > t and det(C - t I) > 0. Then det(C) > t^2; elsewhere the gradient is set to 0.
    t = np.float32(min_spread)
    determined = (cuu > t) & ((cuu - t) * (cvv - t) > cuv2)
    inv_det = determined / np.maximum(cuu * cvv - cuv2, t * t)
    gu = (cqu * cvv - cqv * cuv) * inv_det
    gv = (cuu * cqv - cuv * cqu) * inv_det
    residual2 = s_qq * inv_w - mq * mq - gu * cqu - gv * cqv
    ok = determined & (residual2 <= (residual_tol * mq) ** 2) & (mq > 0)
    return mq - gu * mu - gv * mv, gu, gv, ok


def gaussian_mean(q: F32, w: F32, sigma_px: float) -> F32:
    """Gaussian-weighted mean of the samples ``q`` (weights ``w``), 0 where none is near."""
    num = cv2.GaussianBlur(w * q, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(w, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, np.float32(1e-6)) * (den > 1e-6)


#: Edge-aware filters of :func:`guided_mean` with their default (smooth_ref_px, sigma_color).
EDGE_FILTERS: dict[str, tuple[float, float]] = {"dtf": (6.0, 16.0), "fgs": (4.0, 4.0)}


def guided_mean(
    q: F32,
    w: F32,
    rgb: NDArray[np.uint8],
    smooth_px: float,
    sigma_color: float,
    edge_filter: str = "dtf",
    min_support: float = 0.0,
) -> F32:
    """Edge-aware weighted mean ``F(w q) / F(w)`` of the samples ``q`` (weights ``w``), 0 where no
    sample reaches; ``F`` is guided by ``rgb`` and spreads samples over about ``smooth_px``
    pixels but little across image edges (``sigma_color`` on 0-255 values).

    ``edge_filter``: "dtf", OpenCV's domain transform filter (recursive, one iteration), or
    "fgs", its fast global smoother (one iteration: measured as accurate as three). Both are
    linear-time; on the benchmark "fgs" is 2-4 % more accurate (RMSE) at about twice the cost
    (~1.1 ms against ~0.3 ms for a 240x160 image).

    ``F(w)`` is the sample density over the pixel's edge-bounded neighbourhood. Where it is
    below ``min_support`` times the plain density around the pixel (a box of radius
    ``smooth_px``), the image separates the pixel from the samples (a gap onto a background the
    LiDAR did not reach, a window, a thin object's far side) and the mean is 0 (unknown).
    """
    guide, src = np.ascontiguousarray(rgb), cv2.merge([w * q, w])
    if edge_filter == "dtf":
        out = cv2.ximgproc.dtFilter(guide, src, smooth_px, sigma_color, mode=cv2.ximgproc.DTF_RF, numIters=1)
    elif edge_filter == "fgs":
        out = cv2.ximgproc.createFastGlobalSmootherFilter(
            guide, smooth_px**2, sigma_color, num_iter=1
        ).filter(src)
    else:
        raise ValueError(f"edge_filter must be one of {sorted(EDGE_FILTERS)}, got {edge_filter!r}")
    num, den = out[..., 0], out[..., 1]  # views: cv2.split copied both (~30 ms at 1920x1280)
    estimate = num / np.maximum(den, np.float32(1e-4)) * (den > 1e-4)
    if min_support > 0:
        k = 2 * max(1, round(smooth_px)) + 1
        around = cv2.blur(w, (k, k), borderType=cv2.BORDER_CONSTANT)
        estimate = estimate * (den >= min_support * around)
    return estimate


def _edge_estimate(
    s: _Samples,
    rgb: NDArray[np.uint8],
    focal_px: float,
    edge_filter: str,
    smooth_ref_px: float | None,
    sigma_color: float | None,
    min_image_support: float,
) -> F32:
    if edge_filter not in EDGE_FILTERS:
        raise ValueError(f"edge_filter must be one of {sorted(EDGE_FILTERS)}, got {edge_filter!r}")
    default_smooth, default_sigma = EDGE_FILTERS[edge_filter]
    smooth = scaled_px(default_smooth if smooth_ref_px is None else smooth_ref_px, focal_px)
    sigma = default_sigma if sigma_color is None else sigma_color
    return guided_mean(s.q, s.w, rgb, smooth, sigma, edge_filter, min_image_support)


def _assemble(
    estimate: F32,
    samples: _Samples,
    sparse: F32,
    conf: F32,
    focal_px: float,
    outlier_tau: float,
    fill: FillParams,
) -> DenseResult:
    """Dense depth from an inverse-depth ``estimate`` (0 = none): kept measurements within
    ``outlier_tau`` (relative) of the estimate keep their exact value and are trusted; the others
    (leaks at edges that the occlusion test cannot catch, a foreground point one pixel off its
    silhouette) are replaced by the estimate."""
    q = samples.q
    # Where there is no estimate (0) a measurement is kept: nothing contradicts it.
    trusted = samples.kept & ((np.abs(estimate - q) <= outlier_tau * q) | (estimate <= 0))
    untrusted = ~trusted
    filled = untrusted & (estimate > 0)
    dense = sparse * trusted + filled / np.maximum(estimate, _TINY)
    return _finish(dense, sparse, conf, trusted, focal_px, fill)


# --------------------------------------------------------------------------------------------
# planar, guided, planar_guided


def _planar_estimate(
    samples: _Samples,
    focal_px: float,
    window_ref_px: float,
    min_spread_px: float,
    residual_tol: float,
    edge_estimate: F32,
) -> F32:
    value, ok = plane_fit(samples.q, samples.w, _radius(window_ref_px, focal_px), min_spread_px, residual_tol)
    return value * ok + edge_estimate * ~ok


@register_densifier("planar")
def planar(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None,
    focal_px: float,
    *,
    window_ref_px: float = 8.0,
    min_spread_px: float = 0.5,
    residual_tol: float = 0.01,
    edge_sigma_ref_px: float = 2.0,
    occlusion_ref_px: float = 10.0,
    occlusion_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """Local planes in inverse depth; no image.

    1. Drop see-through samples (:func:`occluded_samples`: radius ``occlusion_ref_px``,
       tolerance ``occlusion_tau``).
    2. Fit inverse depth with a plane over a window of radius ``window_ref_px`` around each pixel
       (:func:`plane_fit`, weights = input confidence), used where the window holds one
       surface (relative RMS residual <= ``residual_tol``) and the fit is determined (sample
       spread >= ``min_spread_px``).
    3. Elsewhere, i.e. along depth edges, a Gaussian-weighted mean of inverse depth (sigma
       ``edge_sigma_ref_px``).
    4. Measurements within ``occlusion_tau`` of that estimate keep their value (:func:`_assemble`).
    """
    s = _samples(sparse_m, sparse_confidence, focal_px, occlusion_ref_px, occlusion_tau)
    edge = gaussian_mean(s.q, s.w, scaled_px(edge_sigma_ref_px, focal_px))
    estimate = _planar_estimate(s, focal_px, window_ref_px, min_spread_px, residual_tol, edge)
    fill = FillParams(max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth)
    return _assemble(estimate, s, sparse_m, sparse_confidence, focal_px, occlusion_tau, fill)


@register_densifier("guided", needs_rgb=True)
def guided(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None,
    focal_px: float,
    *,
    edge_filter: str = "dtf",
    smooth_ref_px: float | None = None,
    sigma_color: float | None = None,
    min_image_support: float = 0.2,
    occlusion_ref_px: float = 10.0,
    occlusion_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """Image-guided normalized convolution of inverse depth.

    See-through samples are dropped as in ``planar``; then :func:`guided_mean` with
    ``edge_filter`` ("dtf" or "fgs"; spatial scale ``smooth_ref_px`` and colour sigma
    ``sigma_color``, None: that filter's defaults in :data:`EDGE_FILTERS`), so that depth
    edges follow image edges, and pixels the image cuts off from the samples
    (``min_image_support``) stay unknown; measurements within ``occlusion_tau`` of the estimate
    keep their value.
    """
    if rgb is None:
        raise ValueError("densifier 'guided' needs the RGB image, got rgb=None")
    s = _samples(sparse_m, sparse_confidence, focal_px, occlusion_ref_px, occlusion_tau)
    estimate = _edge_estimate(s, rgb, focal_px, edge_filter, smooth_ref_px, sigma_color, min_image_support)
    fill = FillParams(max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth)
    return _assemble(estimate, s, sparse_m, sparse_confidence, focal_px, occlusion_tau, fill)


@register_densifier("planar_guided", needs_rgb=True)
def planar_guided(
    sparse_m: F32,
    sparse_confidence: F32,
    rgb: NDArray[np.uint8] | None,
    focal_px: float,
    *,
    window_ref_px: float = 8.0,
    min_spread_px: float = 0.5,
    residual_tol: float = 0.01,
    edge_filter: str = "dtf",
    smooth_ref_px: float | None = None,
    sigma_color: float | None = None,
    min_image_support: float = 0.2,
    occlusion_ref_px: float = 10.0,
    occlusion_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """``planar`` with the image-guided estimate of ``guided`` along depth edges.

    Planes are fitted exactly where the window holds one surface; where it spans a depth edge
    the image decides which side a pixel belongs to, or that it belongs to neither and stays
    unknown (:func:`guided_mean`, ``min_image_support``).
    """
    if rgb is None:
        raise ValueError("densifier 'planar_guided' needs the RGB image, got rgb=None")
    s = _samples(sparse_m, sparse_confidence, focal_px, occlusion_ref_px, occlusion_tau)
    edge = _edge_estimate(s, rgb, focal_px, edge_filter, smooth_ref_px, sigma_color, min_image_support)
    estimate = _planar_estimate(s, focal_px, window_ref_px, min_spread_px, residual_tol, edge)
    fill = FillParams(max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth)
    return _assemble(estimate, s, sparse_m, sparse_confidence, focal_px, occlusion_tau, fill)


# --------------------------------------------------------------------------------------------
# The stage


def camera_focal_px(cam: CameraImage) -> float:
    """The camera's focal length in pixels (geometric mean of fx and fy)."""
    k = cam.calibration.intrinsics
    return float(np.sqrt(k[0, 0] * k[1, 1]))


@dataclass
class CameraCoverage:
    """Pixel counts of one camera over the frames of a scene seen so far."""

    pixels: int = 0
    sparse: int = 0  # pixels with a sparse depth (> 0)
    dense: int = 0  # pixels with a dense depth (> 0)

    def sparse_share(self) -> float:
        return self.sparse / max(self.pixels, 1)

    def dense_share(self) -> float:
        return self.dense / max(self.pixels, 1)


class DepthCoverage:
    """Per-camera share of pixels with a sparse and with a dense depth over a scene's frames.

    Each frame counts once however often a lazy frame is loaded (the last load wins). Once every
    frame of the scene has been seen, :meth:`add` logs the shares in one line and warns, naming the
    camera, where a camera's sparse share is below ``min_sparse_coverage``. The shares are known
    only after the frames are processed, that is while the shards are written (the scene metadata
    is fixed before), so they go to the log only.
    """

    def __init__(self, scene_id: str, frames: int, min_sparse_coverage: float = MIN_SPARSE_COVERAGE):
        self.scene_id = scene_id
        self.frames = frames
        self.min_sparse_coverage = min_sparse_coverage
        self.reported = False
        self._counts: dict[int, dict[str, CameraCoverage]] = {}

    def add(self, frame: Frame) -> None:
        """Counts the frame's cameras that have a depth; reports when the scene is complete."""
        counts = {}
        for cam in frame.cameras:
            if cam.depth is not None and cam.depth.dense_m is not None:
                counts[cam.name] = CameraCoverage(
                    int(cam.depth.sparse_m.size),
                    int(np.count_nonzero(cam.depth.sparse_m > 0)),
                    int(np.count_nonzero(cam.depth.dense_m > 0)),
                )
        self._counts[frame.frame_index] = counts
        if len(self._counts) >= self.frames:
            self.report()

    def per_camera(self) -> dict[str, CameraCoverage]:
        """The counts summed over the frames seen, by camera (in the order first seen)."""
        out: dict[str, CameraCoverage] = {}
        for counts in self._counts.values():
            for name, c in counts.items():
                total = out.setdefault(name, CameraCoverage())
                total.pixels += c.pixels
                total.sparse += c.sparse
                total.dense += c.dense
        return out

    def report(self) -> None:
        """Logs the sparse shares once (INFO), and a WARNING per camera below ``min_sparse_coverage``."""
        if self.reported:
            return
        self.reported = True
        cameras = self.per_camera()
        if not cameras:
            return
        shares = ", ".join(f"{name} {100 * c.sparse_share():.1f} %" for name, c in cameras.items())
        # The dense share is not logged here: completion fills more after this stage, and the
        # pipeline logs what the written rows hold (phigenesis.data.coverage).
        log.info(
            "scene %s: sparse depth coverage over %d frames, share of pixels with a sparse depth: %s",
            self.scene_id,
            len(self._counts),
            shares,
        )
        for name, c in cameras.items():
            if c.sparse_share() < self.min_sparse_coverage:
                log.warning(
                    "scene %s camera %s: only %.2f %% of its pixels have a sparse depth "
                    "(min_sparse_coverage %.2f %%): its depth ground truth is (nearly) empty. Does the "
                    "ego body (scene metadata ego_boxes) cover the view, or is the LiDAR missing?",
                    self.scene_id,
                    name,
                    100 * c.sparse_share(),
                    100 * self.min_sparse_coverage,
                )


_LIDAR_CODE, _DENSIFIED_CODE = DENSE_ORIGINS.index("lidar"), DENSE_ORIGINS.index("densified")


def densified_origin(sparse_m: F32, sparse_confidence: F32, dense_m: F32) -> NDArray[np.uint8]:
    """:func:`~phigenesis.data.records.dense_origin_of` (its reference, tested equal) in uint8
    throughout: (H, W) code 1 ("lidar") where ``dense_m`` is exactly a sparse depth of positive
    confidence, 2 ("densified") at every other pixel with a depth, 0 where ``dense_m`` is 0."""
    code = (dense_m > 0).view(np.uint8) * np.uint8(_DENSIFIED_CODE)
    kept = (sparse_m > 0) & (sparse_confidence > 0) & (dense_m == sparse_m)
    code -= kept.view(np.uint8) * np.uint8(_DENSIFIED_CODE - _LIDAR_CODE)
    return code


@register_stage("densify_depth", params=DensifyParams)
def densify_depth(scene: Scene, params: DensifyParams) -> Scene:
    """Fills ``dense_m`` / ``dense_confidence`` / ``dense_origin`` (lidar or densified,
    :func:`~phigenesis.data.records.dense_origin_of`) of every camera that has a :class:`CameraDepth`.

    Params: :class:`DensifyParams`: ``method`` (default :data:`DEFAULT_DENSIFIER`), ``fallback``
    (default :data:`DEFAULT_FALLBACK`: what runs on a camera without an image when the method
    needs one; a warning is logged once per scene), ``min_confidence`` (sparse depths below it,
    such as pixels at depth edges, are not used as seeds; default
    :data:`~phigenesis.data.records.TRUSTED_DEPTH_CONFIDENCE`), ``min_sparse_coverage`` (share of
    a camera's pixels, over the scene, below which its sparse depth is warned about; default
    :data:`MIN_SPARSE_COVERAGE`), and the method's own parameters (the fallback gets those of them
    it accepts). Cameras without depth are left alone. Frames are processed lazily when the
    scene's frames are a :class:`LazyFrames`.

    Once every frame is processed, the per-camera coverage (share of pixels with a sparse and with
    a dense depth) is logged in one line per scene (:class:`DepthCoverage`): log only, as it is
    known only while the shards are written.
    """
    method, fallback = params.method, params.fallback
    method_kwargs, fallback_kwargs = params.method_kwargs(method), params.method_kwargs(fallback)
    min_confidence, min_sparse_coverage = params.min_confidence, params.min_sparse_coverage
    warned = False

    def densify_camera(cam: CameraImage) -> CameraImage:
        nonlocal warned
        if cam.depth is None:
            return cam
        name, kwargs, rgb = method, method_kwargs, None
        if needs_rgb(method):
            if cam.image_bytes is None:
                if not warned:
                    log.warning(
                        "densify_depth: scene %s camera %s has no image; %r falls back to %r",
                        scene.scene_id,
                        cam.name,
                        method,
                        fallback,
                    )
                    warned = True
                name, kwargs = fallback, fallback_kwargs
            else:
                rgb = cam.decode_image()
        depth = cam.depth
        sparse_conf = np.asarray(depth.sparse_confidence, np.float32)
        seeds = sparse_conf * (sparse_conf >= min_confidence)  # float32, 0 below min_confidence
        result = _densify_checked(depth.sparse_m, seeds, rgb, camera_focal_px(cam), name, kwargs)
        dense = dataclasses.replace(
            depth,
            dense_m=result.depth_m,
            dense_confidence=result.confidence,
            dense_origin=densified_origin(depth.sparse_m, seeds, result.depth_m),
        )
        return dataclasses.replace(cam, depth=dense)

    coverage = DepthCoverage(scene.scene_id, len(scene.frames), min_sparse_coverage)

    def densify_frame(frame: Frame) -> Frame:
        dense = dataclasses.replace(frame, cameras=[densify_camera(c) for c in frame.cameras])
        coverage.add(dense)
        return dense

    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(densify_frame)
    else:
        scene.frames = [densify_frame(f) for f in scene.frames]
        coverage.report()
    return scene


# --------------------------------------------------------------------------------------------
# Benchmark (the table in the module docstring)


def sweep_sparse_depth(frame: Frame, cam: CameraImage) -> F32:
    """The frame's own LiDAR sweep in ``cam``: nearest point per pixel (z-buffer only)."""
    h, w = cam.calibration.height, cam.calibration.width
    p_cam = geometry.transform_points(np.linalg.inv(cam.world_from_camera), frame.lidar.points_world())
    uv, valid = geometry.project_points(p_cam, cam.calibration.intrinsics, cam.calibration.distortion)
    u, v = np.round(uv[valid]).astype(np.int64).T
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, v[inside] * w + u[inside], p_cam[valid, 2][inside])
    return np.where(np.isfinite(depth), depth, 0).reshape(h, w).astype(np.float32)


def _sampled_depth(truth: F32, fraction: float, rng: np.random.Generator) -> F32:
    """``fraction`` of the truth's pixels with 2 cm noise; 30 % of the sampled foreground pixels
    within 2 px of a surface 20 % deeper take that deeper depth (background leaking through)."""
    picked = (rng.random(truth.shape) < fraction) & (truth > 0)
    sparse = np.where(picked, truth + rng.normal(0, 0.02, truth.shape), 0)
    deeper = cv2.dilate(truth, np.ones((5, 5), np.uint8))
    leak = picked & (deeper > 1.2 * truth) & (rng.random(truth.shape) < 0.3)
    sparse[leak] = deeper[leak]
    return np.maximum(sparse, 0).astype(np.float32)


def benchmark(frames: tuple[int, ...] = (0, 5), repeats: int = 5, upscale: int = 8) -> str:
    """Scores every registered method on synthetic frames; returns a text table.

    Inputs per image of the waymo5 rig (240x160, 10-frame scene 0): "sweep", the frame's own
    LiDAR sweep; "agg30" and "agg60", 30 % / 60 % of the exact depth (:func:`_sampled_depth`).
    Errors in metres on pixels where truth and output are both > 0 (the last column: RMSE on
    the pixels where every method gives a depth), coverage over pixels with truth; ms = median
    over images and ``repeats`` runs, the methods interleaved; the ``xN`` rows time one agg30
    image upscaled ``upscale`` times (nearest neighbour, points at the centres of the pixel
    blocks, focal length times ``upscale``).
    """
    # the synthetic source (Open3D, trimesh: 1.3 s to import) loads only for this measurement
    from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene

    scene = SyntheticScene(SyntheticConfig(scenes=1, frames=10, rig="waymo5"), 0)
    rng = np.random.default_rng(0)
    images = []
    for index in frames:
        frame = scene.render_frame(index)
        for cam in frame.cameras:
            truth = cam.truth.depth_m
            inputs = {
                "sweep": sweep_sparse_depth(frame, cam),
                "agg30": _sampled_depth(truth, 0.3, rng),
                "agg60": _sampled_depth(truth, 0.6, rng),
            }
            images.append((truth, cam.decode_image(), camera_focal_px(cam), inputs))

    def timed(method: str, sparse: F32, rgb: NDArray[np.uint8], focal: float) -> tuple[DenseResult, float]:
        start = time.perf_counter()
        out = densify(sparse, (sparse > 0).astype(np.float32), rgb, focal_px=focal, method=method)
        return out, time.perf_counter() - start

    methods = sorted(DENSIFIERS)
    rows = []
    for kind in ("sweep", "agg30", "agg60"):
        times: dict[str, list[float]] = {m: [] for m in methods}
        # Squared, absolute, relative error, pixels, coverage; squared error and pixels where all
        # methods give a depth.
        sums = {m: np.zeros(7) for m in methods}
        for truth, rgb, focal, inputs in images:
            outs = {}
            for _ in range(repeats):
                for method in methods:
                    outs[method], seconds = timed(method, inputs[kind], rgb, focal)
                    times[method].append(seconds)
            common = np.logical_and.reduce([truth > 0, *(o.depth_m > 0 for o in outs.values())])
            for method, out in outs.items():
                both = (out.depth_m > 0) & (truth > 0)
                err = np.abs(out.depth_m[both] - truth[both])
                cover = both.sum() / max((truth > 0).sum(), 1)
                common_se = np.sum((out.depth_m[common] - truth[common]) ** 2)
                sums[method] += [
                    *(np.sum(err**2), err.sum(), np.sum(err / truth[both]), both.sum(), cover),
                    *(common_se, common.sum()),
                ]
        for method in methods:
            se, ae, rel, hits, cover, common_se, common_hits = sums[method]
            rows.append(
                f"{method:14s} {kind:6s} {1e3 * np.median(times[method]):6.1f} {np.sqrt(se / hits):6.3f} "
                f"{ae / hits:6.3f} {rel / hits:7.4f} {cover / len(images):6.3f} "
                f"{np.sqrt(common_se / common_hits):6.3f}"
            )
    truth, rgb, focal, inputs = images[0]
    big = np.zeros((truth.shape[0] * upscale, truth.shape[1] * upscale), np.float32)
    big[upscale // 2 :: upscale, upscale // 2 :: upscale] = inputs["agg30"]
    big_rgb = cv2.resize(rgb, big.shape[::-1], interpolation=cv2.INTER_NEAREST)
    big_times: dict[str, list[float]] = {m: [] for m in methods}
    for _ in range(max(1, repeats // 2)):
        for method in methods:
            big_times[method].append(timed(method, big, big_rgb, focal * upscale)[1])
    for method in methods:
        rows.append(f"{method:14s} x{upscale:<5d} {1e3 * np.median(big_times[method]):6.0f}")
    header = (
        f"{'method':14s} {'input':6s} {'ms':>6s} {'RMSE':>6s} {'MAE':>6s} {'AbsRel':>7s} {'cover':>6s} "
        f"{'common RMSE':>6s}"
    )
    return "\n".join([header, *sorted(rows, key=lambda r: r.split()[0])])
