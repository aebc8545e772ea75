"""Image segments for the completion (step 1 of :mod:`phigenesis.data.stages.complete`): graph
segmentation of the image with similar adjacent segments merged, a segment's majority label, and
the distance to the nearest pixel of a mask.

Arrays are (H, W) images or their flat (H * W,) pixel indices; segment labels int32 0..S-1.
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import taxonomy as tx
from phigenesis.data.stages.completion.params import (
    F32,
    NEVER_FILLED_CLASSES,
    CompletionParams,
    Mask,
)
from phigenesis.data.stages.densification.registry import REFERENCE_FOCAL_PX


@functools.lru_cache(maxsize=8)
def _graph_segmentation(k: float, min_size: int) -> Any:
    return cv2.ximgproc.segmentation.createGraphSegmentation(0.0, k, min_size)


def segment_image(rgb: NDArray[np.uint8], focal_px: float, params: CompletionParams) -> NDArray[np.int32]:
    """(H, W) int32 segment labels 0..S-1 of an (H, W, 3) uint8 image.

    Graph segmentation (``cv2.ximgproc``, Felzenszwalb-Huttenlocher) of the image blurred with a
    Gaussian of ``segment_sigma_ref_px``, scale ``segment_k_ref_px2`` and minimum size
    ``segment_min_size_ref_px2`` (focal-scaled), then :func:`merge_similar_segments`.
    """
    scale = focal_px / REFERENCE_FOCAL_PX
    sigma = params.segment_sigma_ref_px * scale
    image = cv2.GaussianBlur(rgb, (0, 0), sigma) if sigma >= 0.2 else rgb
    k = params.segment_k_ref_px2 * scale**2
    min_size = max(1, round(params.segment_min_size_ref_px2 * scale**2))
    labels = _graph_segmentation(float(k), int(min_size)).processImage(np.ascontiguousarray(image))
    if params.merge_color_tol > 0:
        labels = merge_similar_segments(labels, image, params.merge_color_tol, params.merge_edge_tol)
    return labels


def _adjacent_pixels(shape: tuple[int, int]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Flat indices of every pair of horizontally or vertically adjacent pixels."""
    h, w = shape
    index = np.arange(h * w).reshape(h, w)
    first = np.concatenate([index[:, :-1].reshape(-1), index[:-1, :].reshape(-1)])
    second = np.concatenate([index[:, 1:].reshape(-1), index[1:, :].reshape(-1)])
    return first, second


def merge_similar_segments(
    labels: NDArray[np.int32], rgb: NDArray[np.uint8], tol: float, edge_tol: float
) -> NDArray[np.int32]:
    """Merges adjacent segments whose mean colours differ by less than ``tol`` across a faint
    boundary (the colour difference of the pixel pairs across it averages less than
    ``edge_tol``), most similar first; two groups join only while their merged means stay within
    ``tol``, so that a slow gradient cannot chain unlike regions together. Returns labels 0..S'-1.
    """
    n = int(labels.max()) + 1
    flat = labels.reshape(-1)
    count = np.bincount(flat, minlength=n).astype(np.float64)
    colour = rgb.reshape(-1, 3).astype(np.float32)
    sums = np.stack([np.bincount(flat, colour[:, c], n) for c in range(3)], axis=1)
    i, j = _adjacent_pixels(labels.shape)
    cut = flat[i] != flat[j]
    i, j = i[cut], j[cut]
    la, lb = flat[i].astype(np.int64), flat[j].astype(np.int64)
    pairs, inverse = np.unique(np.minimum(la, lb) * n + np.maximum(la, lb), return_inverse=True)
    edge = np.bincount(inverse, np.linalg.norm(colour[i] - colour[j], axis=1)) / np.bincount(inverse)
    lo, hi = np.divmod(pairs, n)
    mean = sums / np.maximum(count, 1)[:, None]
    dist = np.linalg.norm(mean[lo] - mean[hi], axis=1)
    close = np.flatnonzero((dist < tol) & (edge < edge_tol))
    if len(close) == 0:
        return labels
    parent = np.arange(n)

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for e in close[np.argsort(dist[close], kind="stable")].tolist():
        ra, rb = root(int(lo[e])), root(int(hi[e]))
        if ra == rb:
            continue
        diff = sums[ra] / count[ra] - sums[rb] / count[rb]
        if float(diff @ diff) >= tol * tol:
            continue
        parent[rb] = ra
        sums[ra] += sums[rb]
        count[ra] += count[rb]
    _, compact = np.unique([root(k) for k in range(n)], return_inverse=True)
    return compact.astype(np.int32)[labels]


def _nearest_pixel(sources: Mask) -> tuple[F32, NDArray[np.intp]]:
    """Distance (pixels) to, and flat index of, the nearest ``True`` pixel of the (h, w)
    ``sources`` from every pixel (approximate Euclidean, 3x3 mask); none: infinity."""
    if not sources.any():
        return np.full(sources.shape, np.inf, np.float32), np.zeros(sources.shape, np.intp)
    dist, labels = cv2.distanceTransformWithLabels(
        (~sources).view(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    lut = np.zeros(int(labels.max()) + 1, np.intp)
    lut[labels[sources]] = np.flatnonzero(sources)
    return dist, lut[labels]


def _majority_never_filled(flat: NDArray[np.int32], classes: NDArray[np.uint8], count: int) -> Mask:
    """(S,) whether the most frequent label of each segment (among its labelled pixels) is in
    :data:`NEVER_FILLED_CLASSES`."""
    return _majority_in(flat, classes, count, NEVER_FILLED_CLASSES)


def _majority_in(
    flat: NDArray[np.int32], classes: NDArray[np.uint8], count: int, ids: frozenset[int]
) -> Mask:
    """(S,) whether the most frequent label of each segment (among its labelled pixels) is in
    ``ids`` and labels at least a quarter of its pixels (the few labelled pixels of a facade that a
    person in front of it has merged into its segment do not make it a person)."""
    labelled = classes != tx.IGNORE_ID
    if not labelled.any():
        return np.zeros(count, bool)
    votes = np.zeros((count, 256), np.int64)
    np.add.at(votes, (flat[labelled], classes[labelled]), 1)
    sizes = np.bincount(flat, minlength=count)
    return np.isin(votes.argmax(axis=1), list(ids)) & (votes.max(axis=1) >= 0.25 * np.maximum(sizes, 1))
