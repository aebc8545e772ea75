"""What every densification method shares: ``*_ref_px`` lengths scaled to the camera's focal
length, the see-through (occlusion) test of sparse samples, the support test (what a method may
fill), the confidence of an output depth, the nearest trusted measurement of every pixel, and the
finish (support, confidence, measured pixels kept) in C with a numpy reference.

Formulas: :mod:`phigenesis.data.stages.densify`. Depths in metres, (H, W) float32 maps, 0 =
unknown; distances in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.native import load_densify_finish
from phigenesis.data.stages.densification.registry import (
    _FAR,
    ENCLOSURE_FACTOR,
    F32,
    REFERENCE_FOCAL_PX,
    DenseResult,
    Mask,
)


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
    """Confidence of ``dense``, (H, W) float32 (formula in densify.py's docstring).

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
    """Parameters every method shares (see densify.py's docstring)."""

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
