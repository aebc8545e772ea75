"""Densifying one depth map with a registered method (:func:`densify`): input checks, a crop to
the sparse depth's bounding box where it saves enough, the call, and the result's checks; and
:func:`densify_reference`, the same without the crop and the native kernels.

Depths in metres along the camera's +z, float32, 0 = unknown; (H, W) maps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.densification.inverse_depth import EDGE_FILTERS
from phigenesis.data.stages.densification.registry import (
    _NEEDS_RGB,
    DEFAULT_DENSIFIER,
    ENCLOSURE_FACTOR,
    F32,
    DenseResult,
    Mask,
    check_params,
    get_densifier,
    method_params,
)
from phigenesis.data.stages.densification.support import (
    _CleanResult,
    _radius,
    scaled_px,
)


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
        The dense depth and its confidence (densify.py's docstring). The inputs are never modified:
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
