"""The truth of one loaded cache frame at a model's image size: depth, semantics, scene flow and the
pixels its LiDAR covers, as Stage 1's evaluation, Stage 2's conditions and its evaluation compare
against them. Synthetic caches give their exact truth; other caches their dense depth and pseudo
labels."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from phigenesis.data.records import DENSE_ORIGINS
from phigenesis.data.views import resize_nearest
from phigenesis.taxonomy import IGNORE_ID

#: Dense-depth origins (:data:`~phigenesis.data.records.DENSE_ORIGINS`) that count as covered by the
#: LiDAR: a kept measurement or the densifier's fill between measurements (not a completion).
LIDAR_ORIGINS = ("lidar", "densified")


@dataclass(frozen=True)
class FrameTruth:
    """The truth maps of one frame's V views at the model's size (see :class:`Views`)."""

    depth: Tensor  # [V, H, W]
    semantic: Tensor  # [V, H, W]
    flow: Tensor | None  # [V, H, W, 3]
    has_truth_depth: bool
    lidar_covered: Tensor | None = None  # [V, H, W] bool


def lidar_covered(sample: dict[str, Any]) -> Tensor:
    """[V, H, W] bool at the cache's image size: the pixels of a loaded frame that its LiDAR-derived
    dense depth covers.

    Where the sample has the per-pixel origin of the dense depth (``depth_dense_origin``, codes
    indexing :data:`~phigenesis.data.records.DENSE_ORIGINS`), the pixels whose origin is in
    :data:`LIDAR_ORIGINS` (kept or densified LiDAR, not completed); otherwise the pixels with a
    dense depth > 0."""
    dense = sample["depth_dense"]
    origin = sample.get("depth_dense_origin")
    if origin is None:
        return dense > 0
    codes = torch.tensor([i for i, name in enumerate(DENSE_ORIGINS) if name in LIDAR_ORIGINS])
    return torch.isin(origin.long(), codes) & (dense > 0)


def frame_truth(sample: dict[str, Any], size_hw: tuple[int, int]) -> FrameTruth:
    """Truth depth / semantics / flow and the LiDAR-covered pixels (:func:`lidar_covered`) of a
    loaded frame (synthetic truth, else dense depth and pseudo labels), resized to ``size_hw`` by
    nearest sampling."""
    has_depth = "truth_depth" in sample
    depth = sample["truth_depth"] if has_depth else sample["depth_dense"]
    if "truth_semantic" in sample:
        sem = sample["truth_semantic"]
    elif "pseudo_semantic" in sample:
        sem = sample["pseudo_semantic"]
    else:
        sem = torch.full(depth.shape, IGNORE_ID, dtype=torch.uint8)
    flow = None
    if "truth_flow" in sample:
        flow = resize_nearest(sample["truth_flow"], size_hw).permute(0, 2, 3, 1).contiguous().float()
    return FrameTruth(
        depth=resize_nearest(depth, size_hw).float(),
        semantic=resize_nearest(sem, size_hw),
        flow=flow,
        has_truth_depth=has_depth,
        lidar_covered=resize_nearest(lidar_covered(sample), size_hw),
    )
