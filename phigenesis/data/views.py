"""Camera views at a model's resolution: resized images, label and depth maps, and intrinsics that
stay exact under the resize, plus the windows of consecutive frames that clips are cut from.

Pixel convention (as :mod:`phigenesis.models.rasterizer`): integer pixel coordinates are pixel
centres. Scaling an image by ``s`` maps a point at ``u`` to ``(u + 0.5) * s - 0.5``, so
``fx' = s fx`` and ``cx' = (cx + 0.5) s - 0.5``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from phigenesis.data.shards import CacheReader


def resize_intrinsics(intrinsics: Tensor, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> Tensor:
    """(..., 3, 3) pinhole matrices of images of size ``from_hw`` resized to ``to_hw`` (pixels)."""
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    k = intrinsics.clone()
    k[..., 0, 0] *= sx
    k[..., 0, 1] *= sx
    k[..., 1, 1] *= sy
    k[..., 0, 2] = (k[..., 0, 2] + 0.5) * sx - 0.5
    k[..., 1, 2] = (k[..., 1, 2] + 0.5) * sy - 0.5
    return k


def resize_images(images: Tensor, size_hw: tuple[int, int]) -> Tensor:
    """(..., 3, h, w) float32 RGB in [0, 1] from (..., 3, H, W) uint8 images (area-averaged)."""
    lead = images.shape[:-3]
    x = images.reshape(-1, *images.shape[-3:]).float() / 255.0
    if tuple(x.shape[-2:]) != tuple(size_hw):
        x = F.interpolate(x, size=size_hw, mode="area" if x.shape[-1] >= size_hw[1] else "bilinear")
    return x.reshape(*lead, 3, *size_hw).clamp(0.0, 1.0)


def resize_nearest(maps: Tensor, size_hw: tuple[int, int]) -> Tensor:
    """(..., h, w) maps (depth, confidence, labels) sampled at the new pixel centres, no blending,
    so depths and classes stay values that were measured."""
    h_in, w_in = maps.shape[-2:]
    h, w = size_hw
    rows = ((torch.arange(h) + 0.5) * h_in / h).long().clamp(max=h_in - 1)
    cols = ((torch.arange(w) + 0.5) * w_in / w).long().clamp(max=w_in - 1)
    return maps[..., rows[:, None], cols[None, :]]


def scene_windows(reader: CacheReader, length: int, stride: int = 1) -> list[tuple[str, list[int]]]:
    """Every run of ``length`` frames spaced ``stride`` apart within one scene, as
    (scene id, global frame indices), scene by scene in order."""
    out = []
    for scene in reader.scene_ids():
        frames = list(reader.frames_of(scene))
        span = (length - 1) * stride
        out += [(scene, frames[i : i + span + 1 : stride]) for i in range(len(frames) - span)]
    return out
