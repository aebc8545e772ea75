"""Depth-edge bands and image silhouettes: pixels whose depth may belong to either side of an edge.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported


def _known_box(known: NDArray[np.bool_], margin: int) -> tuple[slice, slice] | None:
    """The rows and columns of the known pixels' bounding box widened by ``margin`` (clipped to
    the image), None if none is known."""
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if rows.size == 0:
        return None
    h, w = known.shape
    return (
        slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)),
        slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + margin + 1, w)),
    )


def depth_edge_band(
    depth_m: NDArray[np.floating],
    band_px: int,
    rel: float,
    abs_m: float,
    min_share: float = 0.05,
    near_band_px: int | None = None,
) -> NDArray[np.bool_]:
    """(H, W) True for known pixels (depth > 0) near a depth edge: within ``band_px`` (Chebyshev)
    of a known pixel nearer by more than ``rel * z + abs_m`` (the far side of an edge, or a
    background point seen through a gap), or within ``near_band_px`` (default ``band_px``) of a
    farther one when at least ``min_share`` of the known pixels around are such far-side pixels
    (the near side of a silhouette; a lone leak of background among foreground pixels does not
    make them edge pixels).

    Computed on the known pixels' bounding box: outside it every filter's input already holds
    its border value, so the result equals :func:`depth_edge_band_reference`'s."""
    out = np.zeros(depth_m.shape, bool)
    box = _known_box(depth_m > 0, 0)
    if box is not None:
        out[box] = depth_edge_band_reference(depth_m[box], band_px, rel, abs_m, min_share, near_band_px)
    return out


def silhouette_pixels(
    rgb: NDArray[np.uint8], depth_m: NDArray[np.floating], threshold: float
) -> NDArray[np.bool_]:
    """(H, W) True for known pixels (depth > 0) on the rim of the known region (an unknown
    8-neighbour) that lie within a pixel of a strong image edge (Sobel magnitude of the grey image,
    0-255 scale, above ``threshold``).

    A foreground point landing in a pixel whose centre sees the background beyond a silhouette
    cannot be caught by comparing depths when the background has no depth there (above the
    LiDAR's field, beyond its range): the image still shows the silhouette.

    Computed on the known pixels' bounding box widened by 3 pixels (the Sobel and the 3 x 3
    dilation reach 2, the rim test 1, and the replicated border then repeats unknown pixels):
    equal to :func:`silhouette_pixels_reference`."""
    out = np.zeros(depth_m.shape, bool)
    box = _known_box(depth_m > 0, 3)
    if box is not None:
        out[box] = silhouette_pixels_reference(rgb[box], depth_m[box], threshold)
    return out


def depth_edge_band_reference(
    depth_m: NDArray[np.floating],
    band_px: int,
    rel: float,
    abs_m: float,
    min_share: float = 0.05,
    near_band_px: int | None = None,
) -> NDArray[np.bool_]:
    """The reference :func:`depth_edge_band`, over the whole image. Kept for the tests."""
    known = depth_m > 0
    if band_px <= 0 or not known.any():
        return np.zeros(depth_m.shape, bool)
    near_band_px = band_px if near_band_px is None else near_band_px
    z = depth_m.astype(np.float32)
    far_size = 2 * band_px + 1
    nearest = cv2.erode(
        np.where(known, z, np.inf).astype(np.float32),
        np.ones((far_size, far_size), np.uint8),
        borderValue=np.inf,
    )
    far_side = known & (nearest * (1 + rel) + abs_m < z)
    if near_band_px <= 0:
        return far_side
    size = 2 * near_band_px + 1
    farthest = cv2.dilate(
        np.where(known, z, 0).astype(np.float32), np.ones((size, size), np.uint8), borderValue=0
    )
    counts = [
        cv2.boxFilter(
            m.astype(np.float32), -1, (far_size, far_size), normalize=False, borderType=cv2.BORDER_CONSTANT
        )
        for m in (far_side, known)
    ]
    share = counts[0] / np.maximum(counts[1], 1.0)
    near_side = known & (farthest > z * (1 + rel) + abs_m) & (share >= min_share)
    return far_side | near_side


def silhouette_pixels_reference(
    rgb: NDArray[np.uint8], depth_m: NDArray[np.floating], threshold: float
) -> NDArray[np.bool_]:
    """The reference :func:`silhouette_pixels`, over the whole image. Kept for the tests."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    magnitude = np.hypot(
        cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    )
    near_edge = cv2.dilate((magnitude > threshold).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    known = depth_m > 0
    neighbours = cv2.boxFilter(
        known.astype(np.float32), -1, (3, 3), normalize=False, borderType=cv2.BORDER_REPLICATE
    )
    return known & (neighbours < 9) & near_edge


#: What :func:`camera_pixels` gives: indices into the points, (u, v), z, flat pixel, counts.
CameraPixels = tuple[
    NDArray[np.int64], NDArray[np.float64], NDArray[np.float32], NDArray[np.int64], dict[str, int]
]
