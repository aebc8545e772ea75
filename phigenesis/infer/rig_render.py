"""A cache as another rig sees it: ``phigenesis-render`` (Python: :func:`render`).

For every frame of every scene of a cache, the frame's 4D Gaussians are built and rendered at the
cameras of another rig (:mod:`phigenesis.infer.rigs`: a named rig, a YAML rig file, or random rigs
drawn per scene), and written as a new cache in the same frame schema:

- **Gaussians** (``geometry``): ``stage1``, the Stage 1 model of ``ckpt`` on the frame's clip
  (the frame and the ``history_frames - 1`` before it, default none; the first frames of a scene
  use the scene's first clip); or ``cache``, the cache's own dense depth lifted to one Gaussian per
  pixel at its full size (:func:`phigenesis.rollout.conditions.cache_scene`; no checkpoint needed); or
  ``truth``,
  a synthetic cache's exact truth depth, classes and flow lifted the same way (the oracle). A Stage 2
  rollout is re-rendered through its generated cache, whose dense depth is the rollout's rendered
  depth, with ``geometry="cache"``.
- **Times and poses.** Camera ``i`` of the new rig fires ``time_offsets_micros[i]`` after the
  frame's time; its ego pose is the scene's recorded ego pose at that time (:class:`PoseTrack`:
  every frame's and every camera's recorded pose, linear in position and slerped in rotation
  between them, so a time the cache recorded gets its pose exactly). The Gaussians move at their
  velocities to each camera's own time.
- **What each new image holds.** The colour composited over the sky (the Stage 1 model's sky
  model; with ``cache`` geometry the mean colour of the clip's sky pixels); the rendered z-depth as
  the dense depth where the render's alpha is at least 0.5 (confidence: the alpha; dense origin
  ``rendered``); the rendered classes there as pseudo labels (source ``rendered``; holes 255); and
  the frame's LiDAR sweep projected into the new camera as its sparse depth, with the ego body as
  an occluder (:func:`phigenesis.data.stages.project.project_camera`). Cameras with lens
  distortion are rendered as their pinhole and resampled through the distortion.
- **Carried over unchanged**: the frame's pose and time, its LiDAR sweep and its 3D boxes (world
  frame), the scene's metadata (its ego body) plus the rig the scene was rendered with
  (``rendered_rig``).
- **Inserted assets** (``insert``, :mod:`phigenesis.infer.insert`): each asset's Gaussians join the
  frame's at their pose at each camera's own time, so they hide and are hidden by the scene like
  its own Gaussians; their class labels the rendered pseudo labels; the frame's LiDAR points behind
  an asset (in a camera's view) leave that camera's sparse depth; each asset's box (at the frame's
  time) joins the frame's boxes. The LiDAR sweep itself is not edited. ``export_ply`` writes each
  scene's first rendered frame's (edited) Gaussians as a 3DGS PLY, ``<export_ply>/<scene id>.ply``
  (at the frame's time).

The output verifies, previews and loads like any cache; its manifest (source ``rendered``) names
the source cache and its fingerprint, the checkpoint and its SHA-256, the geometry, the rig
specification, the seed and the random ranges. The output is written as every cache is
(:mod:`phigenesis.data.cache_run`): under the cache's lock (a second writer is refused), the
manifest recording the scenes asked for before the first one is rendered, each scene committed
once its shards are complete; so a run killed (or stopped by a full disk) at any point is resumed
by a rerun of the same command, and a folder holding anything else is refused.

Units: metres, microseconds; images RGB uint8 in the cache.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from phigenesis import geometry
from phigenesis.data import records
from phigenesis.data.cache_run import writing_cache
from phigenesis.data.clips import Clip, Stage1Clips
from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraDepth,
    CameraImage,
    CameraSemantics,
    Frame,
    encode_rgb,
)
from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch
from phigenesis.data.shards import MANIFEST_NAME, CacheReader, SceneEntry, ShardInfo, ShardWriter
from phigenesis.data.stages.aggregate import DEFAULT_EGO_BOXES
from phigenesis.data.stages.project import ProjectParams, ego_body_depth, project_camera, sweep_points
from phigenesis.export.ply import write_ply
from phigenesis.infer.insert import (
    Asset,
    AssetError,
    AssetPlacement,
    InsertSpec,
    asset_box,
    placed_gaussians,
    with_inserted_box,
)
from phigenesis.infer.rigs import RandomRigRanges, Rig, resolve_rig
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.loading import load_stage1
from phigenesis.models.stage1 import Stage1Model
from phigenesis.rollout.conditions import (
    TargetCameras,
    cache_scene,
    lifted_scene,
    render_condition,
    stage1_scene,
    truth_maps,
)
from phigenesis.taxonomy import SKY

log = logging.getLogger(__name__)

GEOMETRIES: tuple[str, ...] = ("stage1", "cache", "truth")
#: The manifest source of a rendered cache.
SOURCE_NAME = "rendered"
#: Render alpha at or above which a pixel has a rendered depth and class.
COVERED_ALPHA = 0.5


# --------------------------------------------------------------------------------------------
# Ego poses at any time of a scene


class PoseTrack:
    """A scene's ego poses at every recorded time, interpolated between them.

    ``samples`` are ``(timestamp_micros, world_from_ego)`` pairs (any order; repeated times keep
    the first). Between two recorded times the position is linear and the rotation slerped; at a
    recorded time the pose is that sample exactly; outside the recorded span the nearest end's pose
    is held (and :meth:`at` says how far out it was through ``outside_micros``).
    """

    def __init__(self, samples: list[tuple[int, np.ndarray]]):
        if not samples:
            raise ValueError("PoseTrack: no recorded pose")
        by_time: dict[int, np.ndarray] = {}
        for t, pose in samples:
            by_time.setdefault(int(t), np.asarray(pose, np.float64))
        self.times_micros = np.array(sorted(by_time), np.int64)
        self.poses = np.stack([by_time[int(t)] for t in self.times_micros])
        self.quaternions = np.stack([geometry.matrix_to_quaternion(p[:3, :3]) for p in self.poses])

    def outside_micros(self, t_micros: int) -> int:
        """How far ``t_micros`` lies outside the recorded span (0 inside)."""
        return int(max(self.times_micros[0] - t_micros, t_micros - self.times_micros[-1], 0))

    def at(self, t_micros: int) -> np.ndarray:
        """(4, 4) float64 world_from_ego at ``t_micros``."""
        return geometry.pose_at_time(self.times_micros, self.poses, self.quaternions, t_micros)


def scene_pose_track(frames: list[Frame]) -> PoseTrack:
    """The :class:`PoseTrack` of a scene's frames: each frame's pose and each camera's."""
    samples = [(f.timestamp_micros, f.world_from_ego) for f in frames]
    samples += [(c.timestamp_micros, c.world_from_ego) for f in frames for c in f.cameras]
    return PoseTrack(samples)


def source_rig(frame: Frame, name: str = "source") -> Rig:
    """The rig of a cache frame: its cameras' calibrations, firing when they did in ``frame``."""
    return Rig(
        name=name,
        cameras=tuple(c.calibration for c in frame.cameras),
        time_offsets_micros=tuple(int(c.timestamp_micros - frame.timestamp_micros) for c in frame.cameras),
    )


# --------------------------------------------------------------------------------------------
# Rendering one camera


@dataclass(frozen=True)
class CameraRender:
    """One new camera's render at its own size."""

    rgb: np.ndarray  # (H, W, 3) uint8, composited over the sky
    depth_m: np.ndarray  # (H, W) float32 z-depth where alpha >= COVERED_ALPHA, else 0
    alpha: np.ndarray  # (H, W) float32 accumulated opacity
    semantic: np.ndarray  # (H, W) uint8 class where covered, 255 elsewhere


def distortion_grid_of(cal: CameraCalibration) -> Tensor | None:
    """grid_sample grid [1, H, W, 2] taking each pixel of the distorted camera to where its ray lands
    in the pinhole image of the same K (None for a camera without distortion)."""
    if not np.any(cal.distortion):
        return None
    h, w = cal.height, cal.width
    k = cal.intrinsics
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xd = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1]], -1).reshape(-1, 2)
    xu = geometry.undistort_normalized(xd, cal.distortion)
    pu = xu[:, 0] * k[0, 0] + k[0, 2]
    pv = xu[:, 1] * k[1, 1] + k[1, 2]
    grid = np.stack([2 * (pu + 0.5) / w - 1, 2 * (pv + 0.5) / h - 1], -1).reshape(1, h, w, 2)
    return torch.from_numpy(grid).float()


def _resample(x: Tensor, grid: Tensor, mode: str) -> Tensor:
    """[H, W, C] sampled at ``grid`` (zeros outside)."""
    out = F.grid_sample(x.permute(2, 0, 1)[None].float(), grid, mode=mode, align_corners=False)
    return out[0].permute(1, 2, 0)


def render_camera(
    gaussians: GaussianScene,
    cal: CameraCalibration,
    world_from_ego: np.ndarray,
    time_s: float,
    sky: Tensor | None,
    model: Stage1Model | None,
    distortion_grid: Tensor | None = None,
) -> CameraRender:
    """``gaussians`` seen by camera ``cal`` on the ego at ``world_from_ego`` (world frame), at
    ``time_s`` seconds after the Gaussians' time origin. The sky behind: ``model``'s sky where a
    model is given, else the constant colour ``sky`` (3,) in [0, 1]. ``distortion_grid``: the
    camera's :func:`distortion_grid_of`, computed once per camera by a caller rendering many frames
    (None: computed here)."""
    h, w = cal.height, cal.width
    world_from_camera = torch.from_numpy(world_from_ego @ cal.ego_from_camera)[None, None]
    k = torch.from_numpy(cal.intrinsics).float()[None]
    cams = TargetCameras(world_from_camera, k, torch.tensor([[time_s]], dtype=torch.float64), (h, w))
    out = render_condition(gaussians, cams, semantics=True)
    if model is not None:
        with torch.no_grad():
            background = model.background(world_from_camera[0, 0].float(), k[0], h, w)
    else:
        background = (sky if sky is not None else torch.zeros(3)).expand(h, w, 3)
    alpha = out.alpha[0, 0]
    rgb = out.rgb[0, 0] + (1 - alpha[..., None]) * background
    depth = out.depth[0, 0]
    assert out.semantic is not None
    semantic = out.semantic[0, 0]
    grid = distortion_grid_of(cal) if distortion_grid is None else distortion_grid
    if grid is not None:
        rgb = _resample(rgb, grid, "bilinear")
        # Outside the pinhole image: nothing rendered; the sky there is the nearest border's.
        border = F.grid_sample(
            background.permute(2, 0, 1)[None].float(), grid, align_corners=False, padding_mode="border"
        )[0].permute(1, 2, 0)
        alpha = _resample(alpha[..., None], grid, "bilinear")[..., 0]
        rgb = rgb + (1 - _resample(torch.ones(h, w, 1), grid, "bilinear")) * border
        depth = _resample(depth[..., None], grid, "nearest")[..., 0]
        semantic = _resample(semantic[..., None].float(), grid, "nearest")[..., 0].round().to(torch.uint8)
    covered = (alpha >= COVERED_ALPHA) & (depth > 0)
    return CameraRender(
        rgb=(rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8),
        depth_m=torch.where(covered, depth, torch.zeros_like(depth)).numpy().astype(np.float32),
        alpha=alpha.clamp(0, 1).numpy().astype(np.float32),
        semantic=torch.where(covered, semantic, torch.full_like(semantic, 255)).numpy().astype(np.uint8),
    )


def _sparse_depth(camera: CameraImage, frame: Frame, ego_boxes: list[dict]) -> CameraDepth:
    """The frame's own LiDAR sweep projected into ``camera`` (the ego body occludes)."""
    h, w = camera.calibration.height, camera.calibration.width
    if frame.lidar is None or len(frame.lidar.points_ego) == 0:
        return CameraDepth.empty(h, w)
    depth, _ = project_camera(camera, sweep_points(frame), ProjectParams(), ego_body_depth(camera, ego_boxes))
    return depth


def _hidden_by(sparse: CameraDepth, occluder: CameraRender) -> CameraDepth:
    """``sparse`` without the points farther than what ``occluder`` (an inserted asset) covers."""
    hidden = (occluder.depth_m > 0) & (sparse.sparse_m > occluder.depth_m)
    if not hidden.any():
        return sparse
    keep = ~hidden
    return CameraDepth(
        np.where(keep, sparse.sparse_m, 0).astype(np.float32),
        np.where(keep, sparse.sparse_confidence, 0).astype(np.float32),
        np.where(keep, sparse.sparse_origin, 0).astype(np.uint8),
    )


def rendered_camera(
    frame: Frame, cal: CameraCalibration, t_micros: int, world_from_ego: np.ndarray, out: CameraRender,
    ego_boxes: list[dict], occluder: CameraRender | None = None,
) -> CameraImage:  # fmt: skip
    """The new camera's :class:`CameraImage` record: the render as image, dense depth and pseudo
    labels, the frame's LiDAR as sparse depth (less the points behind ``occluder``, the render of
    the inserted assets alone, where there is one)."""
    camera = CameraImage(cal, int(t_micros), world_from_ego, encode_rgb(out.rgb))
    sparse = _sparse_depth(camera, frame, ego_boxes)
    if occluder is not None:
        sparse = _hidden_by(sparse, occluder)
    has = out.depth_m > 0
    depth = CameraDepth(
        sparse.sparse_m,
        sparse.sparse_confidence,
        sparse.sparse_origin,
        out.depth_m,
        np.where(has, out.alpha, 0).astype(np.float32),
        np.where(has, records.DENSE_ORIGINS.index("rendered"), 0).astype(np.uint8),
    )
    labelled = out.semantic != 255
    pseudo = CameraSemantics(
        out.semantic,
        labelled.astype(np.float32),
        np.where(labelled, records.PSEUDO_SOURCES.index("rendered"), 0).astype(np.uint8),
    )
    return dataclasses.replace(camera, depth=depth, pseudo=pseudo)


# --------------------------------------------------------------------------------------------
# The command


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render` wrote."""

    out: Path
    scenes: list[str]  # scene ids rendered by this call (finished ones skipped)
    skipped: list[str]  # scene ids already complete in ``out``
    frames: int  # frames rendered by this call
    seconds: float
    rigs: dict[str, dict[str, Any]]  # scene id -> the rig it was rendered with (Rig.to_dict)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _scene_metadata(reader: CacheReader, scene_id: str) -> dict[str, Any]:
    """The scene metadata its shard's schema records (``{}`` when none)."""
    for i, shard in enumerate(reader.shards):
        if shard.scene_id == scene_id:
            raw = (reader.shard(i).schema.metadata or {}).get(b"phigenesis.scene_metadata")
            if raw:
                value = json.loads(raw)
                return value if isinstance(value, dict) else {}
            return {}
    return {}


def _scene_seed(seed: int, scene_index: int) -> int:
    """The random rig seed of the scene at ``scene_index`` (of the source's scene order)."""
    return int(np.random.SeedSequence([int(seed), int(scene_index)]).generate_state(1)[0])


def _sky_colour(clip: Clip) -> Tensor:
    """(3,) mean colour of the clip's context pixels labelled sky (black without any)."""
    ctx = clip.context
    sky = ctx.semantic == SKY
    if not sky.any():
        return torch.zeros(3)
    return ctx.images.permute(0, 1, 3, 4, 2)[sky].mean(0).float()


def _gaussians(geometry: str, clip: Clip, model: Stage1Model | None) -> GaussianScene:
    """The Gaussians of ``clip``'s context frames from ``geometry`` (see the module docstring)."""
    if geometry == "stage1":
        assert model is not None
        return stage1_scene(model, clip)
    if geometry == "cache":
        return cache_scene(clip)
    return lifted_scene(clip, *truth_maps(clip))


def _placed(
    assets: list[Asset], placements: list[AssetPlacement], t_micros: int, like: GaussianScene
) -> GaussianScene:
    """The Gaussians of every inserted asset at ``t_micros`` (one scene, like ``like``)."""
    parts = [placed_gaussians(a, p, t_micros, like) for a, p in zip(assets, placements, strict=True)]
    return GaussianScene.concatenate(parts) if len(parts) > 1 else parts[0]


def _export(
    gaussians: GaussianScene, assets: list[Asset], placements: list[AssetPlacement], t_micros: int,
    folder: Path, scene_id: str,
) -> Path:  # fmt: skip
    """Writes the (edited) Gaussians at ``t_micros`` to ``folder/<scene_id>.ply``."""
    if assets:
        gaussians = GaussianScene.concatenate([gaussians, _placed(assets, placements, t_micros, gaussians)])
    folder.mkdir(parents=True, exist_ok=True)
    path = write_ply(gaussians, folder / f"{scene_id}.ply", t_s=gaussians.seconds(t_micros))
    log.info("%s: %d Gaussians written to %s", scene_id, len(gaussians), path)
    return path


def render(
    ckpt: str | os.PathLike[str] | None,
    shards: str | os.PathLike[str],
    rig: str,
    out: str | os.PathLike[str],
    *,
    geometry: str = "stage1",
    seed: int = 0,
    ranges: RandomRigRanges | None = None,
    height: int | None = None,
    width: int | None = None,
    scenes: list[str] | None = None,
    max_frames: int | None = None,
    history_frames: int = 1,
    progress: bool = True,
    threads: int | None = None,
    insert: Sequence[InsertSpec] = (),
    export_ply: str | os.PathLike[str] | None = None,
) -> RenderResult:
    """Writes the cache ``shards`` as rig ``rig`` sees it into ``out`` (see the module docstring).

    Args:
        ckpt: the Stage 1 checkpoint (``geometry="stage1"``; unused with ``"cache"``).
        shards: the source cache.
        rig: ``"waymo5"``, ``"nuscenes6"``, a YAML rig file, or ``"random"`` (a rig per scene drawn from
            ``ranges`` around the source's own rig, its seed from ``seed`` and the scene's index).
        out: the new cache's folder (new, empty, or a previous run of the same arguments to resume).
        geometry: ``"stage1"``, ``"cache"`` or ``"truth"`` (synthetic caches).
        height, width: the image size of a named rig (default: the source's first camera's).
        scenes: only these scene ids (default all); ``max_frames``: at most this many per scene.
        history_frames: the Gaussians of this many frames up to each frame are joined (a multiple of
            the Stage 1 model's ``frames``): a rig that looks where the source's cameras did not (a
            rear camera) sees what they saw earlier; moving Gaussians move at their velocities.
        insert: assets to insert into every frame (:class:`~phigenesis.infer.insert.InsertSpec`; their
            track ids must differ from each other and from the frames' boxes').
        export_ply: a folder to write each rendered scene's first frame's Gaussians into, as
            ``<scene id>.ply`` (3DGS PLY at the frame's time; not part of the cache or its manifest).

    Returns a :class:`RenderResult`. Raises ValueError naming what is wrong (an unknown scene or
    geometry, a missing checkpoint), RigError for a bad rig, CheckpointError for a checkpoint that
    is not Stage 1's, AssetError for an asset, pose or track id that cannot be used, PrepError when
    another run is writing ``out`` or ``out`` holds a cache made otherwise (or anything else), and
    CacheWriteError naming the file when one cannot be written (a full disk: the finished scenes
    are kept and a rerun resumes).
    """
    t0 = time.perf_counter()
    if threads:
        torch.set_num_threads(int(threads))
    if geometry not in GEOMETRIES:
        raise ValueError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
    shards, out = Path(shards), Path(out)
    if not (shards / MANIFEST_NAME).is_file():
        raise ValueError(f"{shards}: not a phigenesis cache (no {MANIFEST_NAME})")
    reader = CacheReader(shards)
    all_scenes = reader.scene_ids()
    chosen = list(all_scenes) if scenes is None else list(scenes)
    unknown = [s for s in chosen if s not in all_scenes]
    if unknown:
        raise ValueError(f"{shards}: no complete scene {unknown}; it has {all_scenes}")
    if history_frames < 1:
        raise ValueError(f"history_frames must be at least 1, got {history_frames}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    inserts = list(insert)
    track_ids = [spec.track_id for spec in inserts]
    if len(set(track_ids)) != len(track_ids):
        raise AssetError(f"inserted assets need distinct track ids, got {track_ids}")
    assets = [spec.load() for spec in inserts]
    model: Stage1Model | None = None
    checkpoint = None
    if geometry == "stage1":
        if ckpt is None:
            raise ValueError("geometry 'stage1' needs a Stage 1 checkpoint (--ckpt)")
        checkpoint = Path(ckpt)
        if not checkpoint.is_file():
            raise ValueError(f"{checkpoint}: no such checkpoint file")
        model = load_stage1(checkpoint)
        model.eval()
    first = reader.frame(reader.frames_of(chosen[0])[0], decode_truth=False) if chosen else None
    if height is None or width is None:
        assert first is not None
        height = height or first.cameras[0].calibration.height
        width = width or first.cameras[0].calibration.width
    arguments = {
        "source_cache": str(shards.resolve()),
        "source_fingerprint": reader.manifest.fingerprint,
        "checkpoint": None if checkpoint is None else str(checkpoint.resolve()),
        "checkpoint_sha256": None if checkpoint is None else _sha256(checkpoint),
        "geometry": geometry,
        "rig": rig,
        "rig_file_sha256": _sha256(Path(rig)) if Path(rig).is_file() else None,
        "seed": int(seed),
        "ranges": dataclasses.asdict(ranges or RandomRigRanges()) if rig == "random" else None,
        "height": int(height),
        "width": int(width),
        "scenes": chosen,
        "max_frames": max_frames,
        "history_frames": int(history_frames),
    }
    if inserts:  # only then: a run without assets keeps the fingerprint it always had
        arguments["insert"] = [{**s.to_dict(), "asset_sha256": _sha256(s.asset)} for s in inserts]
    pipeline = {"name": SOURCE_NAME, "output": {"camera_truth": [], "depth": True, "pseudo_semantics": True}}
    if model is not None:
        group = int(model.config.frames)
        if history_frames % group:
            raise ValueError(
                f"history_frames {history_frames} is not a multiple of the Stage 1 model's {group} frames"
            )
        data = Stage1Clips(shards, tuple(model.config.image_size), int(history_frames), "auto")
    else:
        assert first is not None
        cal0 = first.cameras[0].calibration
        data = Stage1Clips(shards, (cal0.height, cal0.width), int(history_frames), "auto")
    job = _RenderJob(
        shards=shards,
        reader=reader,
        data=data,
        model=model,
        geometry=geometry,
        rig=rig,
        seed=int(seed),
        ranges=ranges,
        height=int(height),
        width=int(width),
        max_frames=max_frames,
        inserts=inserts,
        assets=assets,
        export_ply=None if export_ply is None else Path(export_ply),
        progress=progress,
    )
    ordered = [s for s in all_scenes if s in chosen]  # rendered in the source's order
    # Every scene's rig and placements are checked before anything is written.
    plans = {sid: _plan_scene(job, sid, all_scenes.index(sid)) for sid in ordered}
    rigs = {sid: plan.rig.to_dict() for sid, plan in plans.items()}
    done, skipped, total = [], [], 0
    with writing_cache(out, SOURCE_NAME, arguments, pipeline, ordered, "render") as run:
        for scene_id in ordered:
            if run.is_complete(scene_id):
                skipped.append(scene_id)
                log.info("%s: already rendered in %s; skipped", scene_id, out)
                continue
            entry, written = _render_scene(job, run.target, scene_id, plans[scene_id])
            run.commit(entry, written)
            done.append(scene_id)
            total += entry.frames
    return RenderResult(out, done, skipped, total, time.perf_counter() - t0, rigs)


@dataclass(frozen=True)
class _RenderJob:
    """What every scene of one :func:`render` call shares (its arguments, resolved)."""

    shards: Path
    reader: CacheReader
    data: Stage1Clips
    model: Stage1Model | None
    geometry: str
    rig: str
    seed: int
    ranges: RandomRigRanges | None
    height: int
    width: int
    max_frames: int | None
    inserts: list[InsertSpec]
    assets: list[Asset]
    export_ply: Path | None
    progress: bool


@dataclass(frozen=True)
class _ScenePlan:
    """What one scene is rendered with, settled (and checked) before anything is written."""

    rig: Rig
    metadata: dict[str, Any]  # the source scene's metadata
    ego_boxes: list[dict]
    placements: list[AssetPlacement]  # one per inserted asset


def _plan_scene(job: _RenderJob, scene_id: str, scene_index: int) -> _ScenePlan:
    """The rig, metadata and asset placements of one scene; raises (ValueError, RigError,
    AssetError) naming what is wrong. ``scene_index``: the scene's position in the source cache
    (seeds a random rig)."""
    indices = job.reader.frames_of(scene_id)
    if len(indices) < job.data.frames:
        raise ValueError(
            f"{job.shards}: scene {scene_id} has {len(indices)} frames, fewer than history_frames "
            f"{job.data.frames}"
        )
    first = job.reader.frame(indices[0], decode_truth=False)
    metadata = _scene_metadata(job.reader, scene_id)
    ego_boxes = metadata.get("ego_boxes", DEFAULT_EGO_BOXES)
    rig = resolve_rig(
        job.rig,
        base=source_rig(first),
        height=job.height,
        width=job.width,
        seed=_scene_seed(job.seed, scene_index),
        ranges=job.ranges,
        ego_boxes=ego_boxes,
    )
    placements = [s.placement(first.timestamp_micros, first.world_from_ego) for s in job.inserts]
    return _ScenePlan(rig, metadata, ego_boxes, placements)


def _render_scene(
    job: _RenderJob, target: Path, scene_id: str, plan: _ScenePlan
) -> tuple[SceneEntry, list[ShardInfo]]:
    """Renders one scene of the source cache as ``plan`` says into complete shards in ``target``:
    (its manifest entry, its shards), which the caller commits."""
    reader, data, model, geometry = job.reader, job.data, job.model, job.geometry
    inserts, assets, max_frames = job.inserts, job.assets, job.max_frames
    scene_rig, ego_boxes, placements = plan.rig, plan.ego_boxes, plan.placements
    frames = [reader.frame(i, decode_truth=False) for i in reader.frames_of(scene_id)]
    n = len(frames) if max_frames is None else min(len(frames), max_frames)
    track = scene_pose_track(frames)
    grids = [distortion_grid_of(cal) for cal in scene_rig.cameras]
    schema = frame_schema(
        CacheContents(
            camera_truth=(),
            lidar=any(f.lidar is not None for f in frames),
            lidar_truth=False,
            camera_labels=False,
            depth=True,
            pseudo_semantics=True,
        ),
        {
            "phigenesis.source": SOURCE_NAME,
            "phigenesis.scene_metadata": json.dumps({**plan.metadata, "rendered_rig": scene_rig.to_dict()}),
        },
    )
    window = data.frames
    with ShardWriter(target, scene_id, schema) as writer:
        bar = tqdm(range(n), desc=scene_id, unit="frame", disable=not job.progress)
        for k in bar:
            frame = frames[k]
            start = min(max(k - window + 1, 0), len(frames) - window)
            clip = data.clip(scene_id, start, [], keep_frames=geometry == "truth")
            gaussians = _gaussians(geometry, clip, model)
            sky = None if model is not None else _sky_colour(clip)
            if job.export_ply is not None and k == 0:
                _export(gaussians, assets, placements, frame.timestamp_micros, job.export_ply, scene_id)
            cameras = []
            for cal, offset, grid in zip(
                scene_rig.cameras, scene_rig.time_offsets_micros, grids, strict=True
            ):
                t_cam = frame.timestamp_micros + int(offset)
                if track.outside_micros(t_cam):
                    log.debug("%s frame %d camera %s: time outside the recorded poses", scene_id, k, cal.name)
                pose = track.at(t_cam)
                t_s = (t_cam - clip.time_origin_micros) * 1e-6
                occluder = None
                if assets:
                    placed = _placed(assets, placements, t_cam, gaussians)
                    shot = render_camera(
                        GaussianScene.concatenate([gaussians, placed]), cal, pose, t_s, sky, model, grid
                    )
                    occluder = render_camera(placed, cal, pose, t_s, None, None, grid)
                else:
                    shot = render_camera(gaussians, cal, pose, t_s, sky, model, grid)
                cameras.append(rendered_camera(frame, cal, t_cam, pose, shot, ego_boxes, occluder))
            boxes = frame.boxes if frame.boxes is not None else Boxes.empty()
            for asset, placement, spec in zip(assets, placements, inserts, strict=True):
                box = asset_box(asset, placement, frame.timestamp_micros, spec.track_id)
                boxes = with_inserted_box(boxes, box)
            new = Frame(
                scene_id, k, frame.timestamp_micros, frame.world_from_ego, cameras, frame.lidar, boxes
            )
            writer.write(frame_to_batch(new, SOURCE_NAME, schema))
        written = writer.close()
    log.info("%s: %d frames rendered with rig %s", scene_id, n, scene_rig.name)
    return SceneEntry(scene_id, SOURCE_NAME, n, "complete", [s.path for s in written]), written
