"""Stage 1 clips from a cache: context frames for the model and target frames for the losses.

A clip is ``T`` consecutive context frames of one scene plus target frames (the context frames
themselves and frames a few steps before or after them), every view resized to the model's size.
Times are seconds after the first context frame's timestamp (the clip's time origin).

Per view of a context frame, what moves comes from the ``scene_flow`` stage's maps where the cache
holds them (:func:`_stage_flow_pixels`: its dynamic mask and flow, the box's rotation included;
pixels whose flow confidence is below ``MIN_FLOW_CONFIDENCE`` are left unknown), else from the
cache's boxes: a pixel whose dense-depth point lies in a box moving faster than ``MOVING_MPS`` (the
box shifted to the image's own capture time at its velocity) is dynamic and moves at the box's
velocity.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from phigenesis import geometry
from phigenesis.data.loader import FrameDataset
from phigenesis.data.memory_cache import BoundedCache, tensor_bytes
from phigenesis.data.schema import cameras_of
from phigenesis.data.shards import CacheReader
from phigenesis.data.views import resize_images, resize_intrinsics, resize_nearest
from phigenesis.taxonomy import IGNORE_ID

#: A box moving faster than this (m/s) makes its pixels dynamic.
MOVING_MPS = 0.5
#: A dynamic pixel of the scene_flow stage's maps whose confidence is below this is left unknown
#: (-1) rather than trained on: its box's yaw rate or velocity is a guess.
MIN_FLOW_CONFIDENCE = 0.5
#: Boxes are enlarged by this (metres per side) when testing which pixels they hold.
BOX_MARGIN_M = 0.1
#: A cache whose dense depth covers less than this share of the pixels of the frames sampled
#: (:func:`dense_depth_coverage`) is refused: its depth loss would train on nothing. The synthetic
#: test caches (16- to 64-beam LiDARs) measure 7-35 %; nuScenes caches whose ego body hid every
#: camera had 0 %.
MIN_DENSE_DEPTH_COVERAGE = 0.01
#: Frames, spread evenly over the cache, on which that coverage is measured.
COVERAGE_SAMPLE_FRAMES = 8

SemanticTarget = Literal["auto", "pseudo", "truth"]


@dataclass(frozen=True)
class ViewSet:
    """The V views of F frames at the model's size (targets carry every field; context frames too)."""

    images: Tensor  # [F, V, 3, H, W] RGB in [0, 1]
    world_from_camera: Tensor  # [F, V, 4, 4] float64, OpenCV camera axes
    time_s: Tensor  # [F, V] float64 capture times, seconds after the clip's origin
    depth: Tensor  # [F, V, H, W] dense depth (camera z, metres), 0 = unknown
    depth_confidence: Tensor  # [F, V, H, W] in [0, 1]
    semantic: Tensor  # [F, V, H, W] uint8 unified classes, 255 = unknown
    moving: Tensor  # [F, V, H, W] float32: 1 moving, 0 static, -1 unknown (no depth, or not context)
    box_velocity: Tensor  # [F, V, H, W, 3] float32 world-frame velocity of the moving box, m/s


@dataclass(frozen=True)
class Clip:
    """One training or evaluation clip."""

    scene_id: str
    frame_indices: list[int]  # scene frame indices of the context frames
    target_indices: list[int]  # scene frame indices of the targets
    time_origin_micros: int
    intrinsics: Tensor  # [V, 3, 3] at the model's size
    camera_names: list[str]
    context: ViewSet
    targets: ViewSet
    #: The loaded cache frames by scene frame index (loader dicts), when the caller asked to keep them.
    frames: dict[int, dict[str, Any]] | None = None


def clip_inputs(clips: list[Clip]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(images, intrinsics, world_from_camera, time_s) of a batch of clips, as the model takes them."""
    return (
        torch.stack([c.context.images for c in clips]),
        torch.stack([c.intrinsics for c in clips]),
        torch.stack([c.context.world_from_camera for c in clips]),
        torch.stack([c.context.time_s for c in clips]).float(),
    )


@dataclass(frozen=True)
class _FrameViews:
    """One frame's views at the model's size, as a clip stacks them (see :class:`ViewSet`), with
    what the clip takes from its first frame. Kept by :class:`Stage1Clips` between clips."""

    images: Tensor  # [V, 3, H, W]
    world_from_camera: Tensor  # [V, 4, 4] float64
    capture_micros: Tensor  # [V] int64 camera capture times
    depth: Tensor
    depth_confidence: Tensor
    semantic: Tensor
    moving: Tensor  # -1 everywhere unless the frame was prepared as a context frame
    box_velocity: Tensor
    frame_timestamp_micros: int
    intrinsics: Tensor  # [V, 3, 3] float64 at the model's size
    camera_names: list[str]

    def nbytes(self) -> int:
        return tensor_bytes(getattr(self, f.name) for f in fields(self))


def _frame_views(
    f: dict[str, Any], size_hw: tuple[int, int], semantic: SemanticTarget, context: bool
) -> _FrameViews:
    """The views of the loaded cache frame ``f`` at ``size_hw``; what moves is found only for a
    ``context`` frame (the losses use it nowhere else), a target's is marked unknown (-1)."""
    h_in, w_in = f["images"].shape[-2:]
    wfc = f["camera_world_from_ego"] @ f["ego_from_camera"]
    d = resize_nearest(f["depth_dense"], size_hw)
    k = resize_intrinsics(f["intrinsics"].double(), (h_in, w_in), size_hw)
    if context:
        m, v = _stage_flow_pixels(f, d, size_hw) or _moving_pixels(f, d, k, wfc)
    else:
        m, v = torch.full(d.shape, -1.0), torch.zeros(*d.shape, 3)
    return _FrameViews(
        images=resize_images(f["images"], size_hw),
        world_from_camera=wfc,
        capture_micros=f["camera_timestamp_micros"],
        depth=d,
        depth_confidence=resize_nearest(f["depth_dense_confidence"], size_hw),
        semantic=resize_nearest(_semantic_map(f, semantic), size_hw),
        moving=m,
        box_velocity=v,
        frame_timestamp_micros=int(f["frame_timestamp_micros"]),
        intrinsics=k,
        camera_names=list(f["camera_names"]),
    )


def _views(frames: list[_FrameViews], origin: int) -> ViewSet:
    """The frames' views stacked, times in seconds after ``origin`` (microseconds)."""

    def stack(name: str) -> Tensor:
        return torch.stack([getattr(f, name) for f in frames])

    return ViewSet(
        images=stack("images"),
        world_from_camera=stack("world_from_camera"),
        time_s=(stack("capture_micros") - origin).double() * 1e-6,
        depth=stack("depth"),
        depth_confidence=stack("depth_confidence"),
        semantic=stack("semantic"),
        moving=stack("moving"),
        box_velocity=stack("box_velocity"),
    )


def _semantic_map(frame: dict[str, Any], semantic: SemanticTarget) -> Tensor:
    """The label map a clip trains on: "auto" takes synthetic truth where the cache has it (exact
    and complete), else the pseudo labels; 255 everywhere when neither exists."""
    if semantic in ("auto", "truth") and "truth_semantic" in frame:
        return frame["truth_semantic"]
    if semantic in ("auto", "pseudo") and "pseudo_semantic" in frame:
        return frame["pseudo_semantic"]
    return torch.full_like(frame["depth_dense"], IGNORE_ID, dtype=torch.uint8)


def _stage_flow_pixels(
    frame: dict[str, Any], depth: Tensor, size_hw: tuple[int, int]
) -> tuple[Tensor, Tensor] | None:
    """([V, H, W] moving label, [V, H, W, 3] world velocity, m/s) of one frame's views from the
    ``scene_flow`` stage's maps (loader group "flow") at ``size_hw``: 1 on its dynamic pixels whose
    confidence is at least :data:`MIN_FLOW_CONFIDENCE`, -1 on less confident ones and where
    ``depth`` [V, H, W] (at ``size_hw``) is unknown, 0 elsewhere; None where the cache has no
    such maps (caches written without the stage)."""
    if "flow_world" not in frame or isinstance(frame["flow_world"], list):
        return None
    dynamic = resize_nearest(frame["flow_dynamic"], size_hw) > 0
    confidence = resize_nearest(frame["flow_confidence"], size_hw)
    velocity = resize_nearest(frame["flow_world"], size_hw).permute(0, 2, 3, 1).float()  # [V, H, W, 3]
    moving = torch.where(depth > 0, 0.0, -1.0).float()
    moving[dynamic & (depth > 0)] = 1.0
    moving[dynamic & (confidence < MIN_FLOW_CONFIDENCE)] = -1.0
    velocity = velocity * (moving > 0)[..., None]
    return moving, velocity.contiguous()


def _moving_pixels(
    frame: dict[str, Any], depth: Tensor, intrinsics: Tensor, world_from_camera: Tensor
) -> tuple[Tensor, Tensor]:
    """([V, H, W] moving label, [V, H, W, 3] box velocity) of one frame's views (see module doc)."""
    v, h, w = depth.shape
    moving = torch.where(depth > 0, 0.0, -1.0).float()
    velocity = torch.zeros(v, h, w, 3)
    speed = np.linalg.norm(frame["boxes_velocity_world"].numpy()[:, :2], axis=1)
    if not np.any(speed > MOVING_MPS):
        return moving, velocity
    centers = frame["boxes_center_world"].numpy()
    box_v = frame["boxes_velocity_world"].numpy()
    rows, cols = np.mgrid[0:h, 0:w]
    for cam in range(v):
        known = depth[cam].numpy() > 0
        if not known.any():
            continue
        k = intrinsics[cam].numpy()
        z = depth[cam].numpy()[known]
        y = (rows[known] - k[1, 2]) / k[1, 1] * z
        x = (cols[known] - k[0, 2] - k[0, 1] * y / z) / k[0, 0] * z
        pts = geometry.transform_points(world_from_camera[cam].numpy(), np.stack([x, y, z], axis=1))
        dt = (int(frame["camera_timestamp_micros"][cam]) - int(frame["frame_timestamp_micros"])) * 1e-6
        inside = geometry.points_in_boxes(
            pts,
            centers + box_v * dt,
            frame["boxes_size_lwh"].numpy(),
            frame["boxes_yaw_world"].numpy(),
            BOX_MARGIN_M,
        )
        hit = inside >= 0
        is_moving = np.zeros(len(pts), bool)
        is_moving[hit] = speed[inside[hit]] > MOVING_MPS
        vel = np.zeros((len(pts), 3))
        vel[is_moving] = box_v[inside[is_moving]]
        idx = np.flatnonzero(known.ravel())
        moving[cam].view(-1)[idx] = torch.from_numpy(is_moving.astype(np.float32))
        velocity[cam].view(-1, 3)[idx] = torch.from_numpy(vel.astype(np.float32))
    return moving, velocity


def dense_depth_coverage(
    dataset: FrameDataset, frames: int = COVERAGE_SAMPLE_FRAMES
) -> tuple[float, dict[str, float], int]:
    """The share of pixels with a dense depth (> 0) on up to ``frames`` frames spread evenly over
    a cache opened with the "depth" field group.

    Returns ``(share over all pixels, share per camera name, frames measured)``; frames without
    dense depth are left out (a cache without any has share 0)."""
    rows = np.unique(np.linspace(0, len(dataset) - 1, min(frames, len(dataset))).round().astype(np.int64))
    known: dict[str, int] = {}
    pixels: dict[str, int] = {}
    measured = 0
    for row in rows.tolist():
        sample = dataset[row]
        if "depth_dense" not in sample:
            continue
        measured += 1
        for name, depth in zip(sample["camera_names"], sample["depth_dense"], strict=True):
            known[name] = known.get(name, 0) + int(torch.count_nonzero(depth > 0))
            pixels[name] = pixels.get(name, 0) + depth.numel()
    per_camera = {name: known[name] / max(pixels[name], 1) for name in pixels}
    total = sum(known.values()) / max(sum(pixels.values()), 1)
    return total, per_camera, measured


class Stage1Clips:
    """Clips of a cache: ``clip(window, offsets)`` loads one; :meth:`windows` lists the context windows.

    Raises ValueError naming the cache when it is empty, lacks dense depth (run the depth stages),
    has a dense depth that is (nearly) empty (below :data:`MIN_DENSE_DEPTH_COVERAGE` of the pixels
    of :data:`COVERAGE_SAMPLE_FRAMES` frames) or has scenes too short for one clip.
    """

    def __init__(
        self,
        cache_dir: str | os.PathLike[str],
        size_hw: tuple[int, int],
        frames: int = 1,
        semantic: SemanticTarget = "auto",
        check_crc: bool = True,
        cache_mb: float = 0.0,
    ):
        fields_ = ["images", "cameras", "depth", "pseudo", "flow", "boxes"] + (
            ["truth"] if semantic != "pseudo" else []
        )
        self.cache_dir = str(cache_dir)
        self.dataset = FrameDataset(cache_dir, fields=fields_, check_crc=check_crc)
        self.reader: CacheReader = self.dataset.reader
        self.size_hw = tuple(size_hw)
        self.frames = frames
        self.semantic = semantic
        if len(self.reader) == 0:
            raise ValueError(f"{cache_dir}: the cache holds no frames")
        if "depth_dense_png" not in cameras_of(self.reader.read(0, ["cameras"])):
            raise ValueError(
                f"{cache_dir}: the cache has no dense depth (cameras.depth_dense_png); build it with the "
                "depth stages (aggregate_lidar, project_depth, densify_depth) in the pipeline spec"
            )
        self._refuse_empty_depth(check_crc)
        self.scenes = {s: list(self.reader.frames_of(s)) for s in self.reader.scene_ids()}
        self._windows = [(s, i) for s, rows in self.scenes.items() for i in range(len(rows) - frames + 1)]
        #: Prepared frames kept between clips (``cache_mb``): (scene, index, as context) -> views.
        self.prepared: BoundedCache[_FrameViews] = BoundedCache(int(cache_mb * 2**20), _FrameViews.nbytes)
        if not self._windows:
            raise ValueError(f"{cache_dir}: no scene has the {frames} frames one clip needs")

    def _refuse_empty_depth(self, check_crc: bool) -> None:
        """Raises ValueError naming the cache and the measured coverage when its dense depth is
        (nearly) empty (:func:`dense_depth_coverage` below :data:`MIN_DENSE_DEPTH_COVERAGE`)."""
        depth_only = FrameDataset(self.cache_dir, fields=["depth"], check_crc=check_crc)
        total, per_camera, measured = dense_depth_coverage(depth_only)
        if total >= MIN_DENSE_DEPTH_COVERAGE:
            return
        cameras = ", ".join(f"{name} {100 * share:.2f} %" for name, share in per_camera.items())
        raise ValueError(
            f"{self.cache_dir}: the cache's dense depth is (nearly) empty: {100 * total:.2f} % of the "
            f"pixels of {measured} frames sampled evenly over it have a depth ({cameras or 'no camera'}); "
            f"at least {100 * MIN_DENSE_DEPTH_COVERAGE:.0f} % is needed to train on it. Rebuild the cache: "
            "phigenesis-prep logs each scene's depth coverage per camera and warns where it is low (an "
            "ego body over the cameras, a missing LiDAR)"
        )

    def windows(self) -> list[tuple[str, int]]:
        """Every (scene id, first context frame index within the scene)."""
        return list(self._windows)

    def scene_length(self, scene_id: str) -> int:
        return len(self.scenes[scene_id])

    def _frame(self, scene_id: str, index: int) -> dict[str, Any]:
        sample = self.dataset[self.scenes[scene_id][index]]
        if "depth_dense" not in sample:
            path, row = self.reader.locate(self.scenes[scene_id][index])
            raise ValueError(f"{path}: row {row} has no dense depth")
        return sample

    def clip(self, scene_id: str, start: int, target_offsets: list[int], keep_frames: bool = False) -> Clip:
        """The clip whose context starts at frame ``start`` of ``scene_id``; targets at the context
        frames plus ``start + T - 1 + offset`` for each offset (clamped to the scene).
        ``keep_frames``: the clip also carries the loaded cache frames (``Clip.frames``), for callers
        that need more of them (truth maps) without decoding them again."""
        n = self.scene_length(scene_id)
        context_idx = list(range(start, start + self.frames))
        last = context_idx[-1]
        target_idx = context_idx + [min(max(last + o, 0), n - 1) for o in target_offsets]
        loaded: dict[int, dict[str, Any]] = {}

        def views(i: int, context: bool) -> _FrameViews:
            def make() -> _FrameViews:
                if i not in loaded:
                    loaded[i] = self._frame(scene_id, i)
                return _frame_views(loaded[i], self.size_hw, self.semantic, context)

            return make() if keep_frames else self.prepared.get_or_make((scene_id, i, context), make)

        prepared = [views(i, j < self.frames) for j, i in enumerate(target_idx)]
        first = prepared[0]
        origin = first.frame_timestamp_micros
        targets = _views(prepared, origin)
        context = ViewSet(**{f.name: getattr(targets, f.name)[: self.frames] for f in fields(ViewSet)})
        return Clip(
            scene_id=scene_id,
            frame_indices=context_idx,
            target_indices=target_idx,
            time_origin_micros=origin,
            intrinsics=first.intrinsics.float(),
            camera_names=list(first.camera_names),
            context=context,
            targets=targets,
            frames=loaded if keep_frames else None,
        )
