"""The inverse-depth densifiers ``planar``, ``guided`` and ``planar_guided``: a local affine fit
of inverse depth (exact on planes), a Gaussian-weighted mean, and an image-guided (edge-aware)
normalized convolution, assembled where each holds.

Depths in metres (estimated as inverse depth, 1/m); ``*_ref_px`` at
:data:`~phigenesis.data.stages.densification.registry.REFERENCE_FOCAL_PX`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.densification.registry import (
    _TINY,
    F32,
    DenseResult,
    Mask,
    register_densifier,
)
from phigenesis.data.stages.densification.support import (
    FillParams,
    _finish,
    _radius,
    occluded_samples,
    scaled_px,
)


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
    linear-time; "fgs" is a little more accurate (RMSE) at a higher cost (BENCHMARKS.md,
    "Dense depth ground truth").

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
    num, den = out[..., 0], out[..., 1]  # views: cv2.split would copy both
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
