"""The ``ipbasic`` densifier: morphology in inverted depth (after Ku et al., "In Defense of
Classical Image Processing", CRV 2018, fill_in_fast), with focal-scaled kernels. Uses no image.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.densification.registry import (
    F32,
    DenseResult,
    register_densifier,
)
from phigenesis.data.stages.densification.support import (
    FillParams,
    _finish,
    _radius,
    scaled_px,
)


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
