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

Methods (the first three need no image):

- ``ipbasic``: IP-Basic-style morphology in inverted depth, focal-scaled kernels.
- ``planar``: local affine fit of inverse depth (exact on planes); a Gaussian-weighted mean
  where the window spans a depth edge.
- ``guided``: RGB edge-aware normalized convolution with OpenCV's fast global smoother.
- ``planar_guided`` (the default): ``planar``'s fit, with ``guided``'s estimate at depth edges.

Measured on the synthetic renderer (waymo5 rig, 10 images 240x160, f = 255 px; truth-sampled
inputs with 2 cm noise and background leaking through foreground edges; RMSE/MAE in metres on
pixels where truth and output are both > 0; 1920x1280 = the same images upscaled 8x with f x 8;
ms = median wall time of :func:`densify` on 2 CPU cores). ``/tmp``-free reproduction:
``python -m phigenesis.data.stages.densify`` prints nothing; see ``tests/test_densify.py``.

TABLE_PLACEHOLDER
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.records import CameraImage, Frame, LazyFrames, Scene
from phigenesis.data.stages import register_stage

log = logging.getLogger("phigenesis.prep")

#: Focal length (pixels) at which ``*_ref_px`` parameters are given: KITTI's (about 721 px).
REFERENCE_FOCAL_PX = 721.0
#: The method :func:`densify` and the stage use unless told otherwise.
DEFAULT_DENSIFIER = "planar_guided"
#: What the stage runs on a camera without an image when the method needs one.
DEFAULT_FALLBACK = "ipbasic"
#: Quadrant radius of the enclosure test, as a multiple of the fill distance.
ENCLOSURE_FACTOR = 1.5
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


def register_densifier(name: str, *, needs_rgb: bool = False) -> Callable[[Densifier], Densifier]:
    """Decorator registering a densification method under ``name``.

    The method is ``fn(sparse_m, sparse_confidence, rgb, focal_px, *, **params) -> DenseResult``
    with keyword-only parameters; ``needs_rgb``: it uses the image and raises ValueError when
    ``rgb`` is None.
    """

    def wrap(fn: Densifier) -> Densifier:
        if name in DENSIFIERS and DENSIFIERS[name] is not fn:
            raise ValueError(f"a densifier named {name!r} is already registered")
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
    sig = inspect.signature(get_densifier(method))
    return {p.name: p.default for p in sig.parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY}


def check_params(method: str, params: dict[str, Any]) -> None:
    """Raises ValueError if ``params`` holds a name that ``method`` does not accept."""
    accepted = method_params(method)
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ValueError(f"densifier {method!r}: unknown parameters {unknown}; accepted: {sorted(accepted)}")


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
        params: the method's keyword parameters (an unknown name raises ValueError).

    Returns:
        The dense depth and its confidence (module docstring). The inputs are never modified:
        methods get read-only views of them.
    """
    fn = get_densifier(method)
    check_params(method, params)
    sparse, conf = _check_sparse(sparse_m, sparse_confidence)
    if rgb is not None:
        rgb = _check_rgb(rgb, sparse.shape)
    elif method in _NEEDS_RGB:
        raise ValueError(f"densifier {method!r} needs the RGB image, got rgb=None")
    focal_px = float(focal_px)
    if not np.isfinite(focal_px) or focal_px <= 0:
        raise ValueError(f"focal_px must be a positive finite number of pixels, got {focal_px}")
    if not np.any((sparse > 0) & (conf > 0)):
        zeros = np.zeros(sparse.shape, np.float32)
        return DenseResult(zeros, zeros.copy())
    return _check_result(fn(sparse, conf, rgb, focal_px, **params), sparse.shape, method)


def _readonly(arr: np.ndarray) -> np.ndarray:
    view = arr.view()
    view.flags.writeable = False
    return view


def _check_sparse(sparse_m: Any, sparse_confidence: Any) -> tuple[F32, F32]:
    """Validates the sparse inputs; returns them as read-only float32 (converted copies if needed)."""
    arrays = []
    for name, value in (("sparse_m", sparse_m), ("sparse_confidence", sparse_confidence)):
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
        raise ValueError(f"sparse_confidence has shape {conf.shape}, sparse_m has {sparse.shape}")
    negative = int(np.count_nonzero(sparse < 0))
    if negative:
        raise ValueError(f"sparse_m has {negative} negative depths (0 marks unknown)")
    if np.any((conf < 0) | (conf > 1)):
        raise ValueError(f"sparse_confidence must lie in [0, 1], got [{conf.min()}, {conf.max()}]")
    return sparse, conf


def _check_rgb(rgb: Any, shape: tuple[int, ...]) -> NDArray[np.uint8]:
    arr = np.asarray(rgb)
    if arr.shape != (*shape, 3):
        raise ValueError(f"rgb must have shape {(*shape, 3)} (H, W, 3, as sparse_m), got {arr.shape}")
    if arr.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8, got dtype {arr.dtype}")
    return _readonly(arr)


def _check_result(result: DenseResult, shape: tuple[int, ...], method: str) -> DenseResult:
    depth = np.asarray(result.depth_m, np.float32)
    conf = np.asarray(result.confidence, np.float32)
    if depth.shape != shape or conf.shape != shape:
        raise ValueError(f"densifier {method!r} returned shapes {depth.shape}, {conf.shape}; want {shape}")
    depth = np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
    depth = depth * (depth > 0)
    conf = np.clip(np.nan_to_num(conf), 0, 1) * (depth > 0)
    return DenseResult(depth, conf)


# --------------------------------------------------------------------------------------------
# Shared pieces: scale, outlier test, support, confidence


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
    trusted: Mask,
    distance_scale_px: float,
    relative_depth_scale: float,
    nearest_index: NDArray[np.int32],
    distance_px: F32,
) -> F32:
    """Confidence of ``dense``, (H, W) float32 (formula in the module docstring).

    ``nearest_index`` / ``distance_px``: flat index of and distance to the nearest ``trusted``
    pixel (:func:`nearest_trusted`).
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
    src = (~trusted).view(np.uint8) * np.uint8(255)
    dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
    lut = np.zeros(int(labels.max()) + 1, np.int32)
    lut[labels[trusted]] = np.flatnonzero(trusted)
    return lut[labels], dist


@dataclass(frozen=True)
class FillParams:
    """Parameters every method shares (see the module docstring)."""

    max_fill_ref_px: float
    extrapolate_top: bool
    conf_distance_ref_px: float
    conf_relative_depth: float


def _finish(
    dense: F32, sparse: F32, conf: F32, trusted: Mask, focal_px: float, fill: FillParams
) -> DenseResult:
    """Restricts ``dense`` to the support of the ``trusted`` measurements and adds its confidence."""
    if not trusted.any():
        zeros = np.zeros(sparse.shape, np.float32)
        return DenseResult(zeros, zeros.copy())
    index, dist = nearest_trusted(trusted)
    support = support_mask(trusted, dist, scaled_px(fill.max_fill_ref_px, focal_px), fill.extrapolate_top)
    dense = dense * (support & (dense > 0))
    confidence = depth_confidence(
        dense,
        sparse,
        conf,
        trusted,
        scaled_px(fill.conf_distance_ref_px, focal_px),
        fill.conf_relative_depth,
        index,
        dist,
    )
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
    ``fill_ref_px``; 3x3 median (5x5 from twice the reference focal length; OpenCV's float median
    has no larger kernel); ``blur``: "bilateral" (range sigma ``bilateral_sigma_m`` metres,
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
    inv = cv2.medianBlur(inv, 5 if blur_r >= 4 else 3)
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
    Inverse depth is affine in (u, v) on any plane, so planes are reproduced exactly. From a
    radius of 3 px the moments are first averaged over tiles of about ``radius_px / 2`` pixels
    and each pixel takes the plane fitted over the 5 x 5 tiles around its own (a window that
    contains it): a quarter of the per-pixel solves or fewer, at any resolution.

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
    wq, wu, wv = w * q, w * u, w * v
    moments = [w, wu, wv, wq, wu * u, wu * v, wv * v, wq * q, wq * u, wq * v]
    if block > 1:
        moments = [_block_mean(m, block) for m in moments]
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


def guided_mean(q: F32, w: F32, rgb: NDArray[np.uint8], smooth_px: float, sigma_color: float) -> F32:
    """Edge-aware weighted mean ``FGS(w q) / FGS(w)`` with OpenCV's fast global smoother guided by
    ``rgb``: samples spread over about ``smooth_px`` pixels but little across image edges
    (``sigma_color`` on 0-255 values). 0 where no sample reaches."""
    # One iteration (a horizontal and a vertical pass) measured as accurate as three, at half the cost.
    fgs = cv2.ximgproc.createFastGlobalSmootherFilter(
        np.ascontiguousarray(rgb), smooth_px**2, sigma_color, num_iter=1
    )
    num, den = cv2.split(fgs.filter(cv2.merge([w * q, w])))
    return num / np.maximum(den, np.float32(1e-4)) * (den > 1e-4)


def _assemble(
    estimate: F32,
    samples: _Samples,
    sparse: F32,
    conf: F32,
    focal_px: float,
    outlier_tau: float,
    fill: FillParams,
) -> DenseResult:
    """Dense depth from an inverse-depth ``estimate``: kept measurements within ``outlier_tau``
    (relative) of the estimate keep their exact value and are trusted; the others (leaks at
    edges the occlusion test cannot catch) are replaced by the estimate."""
    q = samples.q
    trusted = samples.kept & (np.abs(estimate - q) <= outlier_tau * q)
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
    residual_tol: float = 0.02,
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
    smooth_ref_px: float = 4.0,
    sigma_color: float = 4.0,
    occlusion_ref_px: float = 10.0,
    occlusion_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """Image-guided normalized convolution of inverse depth.

    See-through samples are dropped as in ``planar``; then :func:`guided_mean` (spatial scale
    ``smooth_ref_px``, colour sigma ``sigma_color``), so depth edges follow image edges;
    measurements within ``occlusion_tau`` of the estimate keep their value.
    """
    if rgb is None:
        raise ValueError("densifier 'guided' needs the RGB image, got rgb=None")
    s = _samples(sparse_m, sparse_confidence, focal_px, occlusion_ref_px, occlusion_tau)
    estimate = guided_mean(s.q, s.w, rgb, scaled_px(smooth_ref_px, focal_px), sigma_color)
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
    residual_tol: float = 0.02,
    smooth_ref_px: float = 4.0,
    sigma_color: float = 4.0,
    occlusion_ref_px: float = 10.0,
    occlusion_tau: float = 0.1,
    max_fill_ref_px: float = 8.0,
    extrapolate_top: bool = False,
    conf_distance_ref_px: float = 8.0,
    conf_relative_depth: float = 0.05,
) -> DenseResult:
    """``planar`` with the image-guided estimate of ``guided`` along depth edges.

    Planes are fitted exactly where the window holds one surface; where it spans a depth edge
    the image decides which side a pixel belongs to (:func:`guided_mean`).
    """
    if rgb is None:
        raise ValueError("densifier 'planar_guided' needs the RGB image, got rgb=None")
    s = _samples(sparse_m, sparse_confidence, focal_px, occlusion_ref_px, occlusion_tau)
    edge = guided_mean(s.q, s.w, rgb, scaled_px(smooth_ref_px, focal_px), sigma_color)
    estimate = _planar_estimate(s, focal_px, window_ref_px, min_spread_px, residual_tol, edge)
    fill = FillParams(max_fill_ref_px, extrapolate_top, conf_distance_ref_px, conf_relative_depth)
    return _assemble(estimate, s, sparse_m, sparse_confidence, focal_px, occlusion_tau, fill)


# --------------------------------------------------------------------------------------------
# The stage


def camera_focal_px(cam: CameraImage) -> float:
    """The camera's focal length in pixels (geometric mean of fx and fy)."""
    k = cam.calibration.intrinsics
    return float(np.sqrt(k[0, 0] * k[1, 1]))


@register_stage("densify_depth")
def densify_depth(scene: Scene, params: dict[str, Any]) -> Scene:
    """Fills ``dense_m`` / ``dense_confidence`` of every camera that has a :class:`CameraDepth`.

    Params: ``method`` (default :data:`DEFAULT_DENSIFIER`), ``fallback`` (default
    :data:`DEFAULT_FALLBACK`: what runs on a camera without an image when the method needs one;
    a warning is logged once per scene), and the method's own parameters (the fallback gets
    those of them it accepts). Cameras without depth are left alone. Frames are processed
    lazily when the scene's frames are a :class:`LazyFrames`.
    """
    params = dict(params)
    method = params.pop("method", DEFAULT_DENSIFIER)
    fallback = params.pop("fallback", DEFAULT_FALLBACK)
    check_params(method, params)
    if needs_rgb(fallback):
        raise ValueError(f"densify_depth: the fallback {fallback!r} must not need the image")
    fallback_params = {k: v for k, v in params.items() if k in method_params(fallback)}
    warned = False

    def densify_camera(cam: CameraImage) -> CameraImage:
        nonlocal warned
        if cam.depth is None:
            return cam
        name, kwargs, rgb = method, params, None
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
                name, kwargs = fallback, fallback_params
            else:
                rgb = cam.decode_image()
        depth = cam.depth
        result = densify(
            depth.sparse_m, depth.sparse_confidence, rgb, focal_px=camera_focal_px(cam), method=name, **kwargs
        )
        dense = dataclasses.replace(depth, dense_m=result.depth_m, dense_confidence=result.confidence)
        return dataclasses.replace(cam, depth=dense)

    def densify_frame(frame: Frame) -> Frame:
        return dataclasses.replace(frame, cameras=[densify_camera(c) for c in frame.cameras])

    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(densify_frame)
    else:
        scene.frames = [densify_frame(f) for f in scene.frames]
    return scene


# --------------------------------------------------------------------------------------------
# Benchmark (the table in the module docstring)


def sweep_sparse_depth(frame: Frame, cam: CameraImage) -> F32:
    """The frame's own LiDAR sweep in ``cam``: nearest point per pixel (z-buffer only)."""
    from phigenesis import geometry

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
    Errors in metres on pixels where truth and output are both > 0, coverage over pixels with
    truth; ms = median over images and ``repeats`` runs, the methods interleaved; the ``xN``
    rows time one agg30 image upscaled ``upscale`` times (nearest neighbour, points at the
    centres of the pixel blocks, focal length times ``upscale``).
    """
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
        sums = {m: np.zeros(5) for m in methods}  # squared, absolute, relative error, hits, cover
        for truth, rgb, focal, inputs in images:
            outs = {}
            for _ in range(repeats):
                for method in methods:
                    outs[method], seconds = timed(method, inputs[kind], rgb, focal)
                    times[method].append(seconds)
            for method, out in outs.items():
                both = (out.depth_m > 0) & (truth > 0)
                err = np.abs(out.depth_m[both] - truth[both])
                cover = both.sum() / max((truth > 0).sum(), 1)
                sums[method] += [np.sum(err**2), err.sum(), np.sum(err / truth[both]), both.sum(), cover]
        for method in methods:
            se, ae, rel, hits, cover = sums[method]
            rows.append(
                f"{method:14s} {kind:6s} {1e3 * np.median(times[method]):6.1f} {np.sqrt(se / hits):6.3f} "
                f"{ae / hits:6.3f} {rel / hits:7.4f} {cover / len(images):6.3f}"
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
    header = f"{'method':14s} {'input':6s} {'ms':>6s} {'RMSE':>6s} {'MAE':>6s} {'AbsRel':>7s} {'cover':>6s}"
    return "\n".join([header, *sorted(rows, key=lambda r: r.split()[0])])
