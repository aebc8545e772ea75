"""Evaluation of a trained Stage 1 model on a (held-out) cache: ``phigenesis-eval stage1``.

For each evaluated clip (context windows spread over every scene) the model predicts a
:class:`~phigenesis.models.gaussians.GaussianScene` by its inference rules
(:meth:`Stage1Model.predict`), which is rendered with the sky model behind it
(``rgb + (1 - alpha) * sky``) and scored in sections of views:

- ``input``: the context views themselves (reconstruction);
- ``+5``, ``+10`` (``offsets``): the views of frame ``last context frame + k``, at their own poses
  and capture times (dynamic Gaussians move at their velocity): prediction of the future;
- ``shift_1m``, ``shift_2m``, ``shift_4m`` (``shifts_m``): novel views, every camera of the last
  context frame moved by d metres along the ego's +y (left) at its own capture time. Their truth
  is rendered exactly by the synthetic renderer without the ego's own body (it moves along; a
  pinhole without distortion at the cache's image
  size, then resized to the model's as the cache's own views are), so these sections exist only
  for synthetic caches (others skip them with a logged reason). A clip whose shifted rig would
  collide with a labelled road user (:func:`shift_collision`) is not scored in that section; the
  section's ``skipped_clips`` counts them.

Scores per image: PSNR (dB) and SSIM (mean of :func:`~phigenesis.models.losses.ssim`) of the
composited colour; the rendered depth against the truth depth (synthetic ``truth_depth`` when the
cache has it, else the dense depth) under the field's depth protocol
(:mod:`phigenesis.eval.depth_protocol`: every pixel with truth > 0, prediction and truth clamped to
[1e-3, 80] m, so a pixel the render leaves empty counts as a prediction of 1e-3 m; z-depth; AbsRel,
SqRel, RMSE, RMSE log, delta < 1.25, 1.25^2, 1.25^3), over three pixel subsets:

- ``all``: every truth pixel;
- ``lidar``: those the cache's LiDAR-derived depth covers (:func:`lidar_covered`: the dense depth
  > 0, or, where the cache records each dense pixel's origin, the LiDAR-measured and densified ones);
- ``no_lidar``: the others (surfaces the LiDAR missed: beyond its range, between or above its
  beams).

The shifted views have no cache depth: their ``lidar`` / ``no_lidar`` values are NaN (null in JSON).
The rendered semantics (argmax of the composited class probabilities, pixels with alpha < 0.5 as
sky) feed one confusion matrix per section, whose mIoU is reported (truth semantics, else pseudo
labels). Section values are means over images (depth: over the images with a pixel in the subset,
as SurroundDepth averages). Depth is also scored per class of those semantics, pooled over the
class's pixels (``model_by_class``), with each class's share of the pixels outside delta < 1.25: where
the depth error is.

The peers' metrics (:mod:`phigenesis.eval.scene_flow`, STORM's definitions), where the views have a
truth flow (synthetic caches): ``psnr_dynamic_db`` and ``ssim_dynamic`` over the truth's moving
surfaces (faster than 1 m/s), and the scene flow of the rendered Gaussians' velocity against the
truth (m/s, world frame; non-ground pixels with a truth depth; a section's views are skipped when
nothing in them moves): ``epe3d_mps``, ``acc5``, ``acc10``, ``outlier``, ``angle_rad`` and
``flow_pixels``.

Report keys of a section (:meth:`SectionScores.summary`, in :data:`METRICS` order): ``psnr_db``,
``ssim``, then per subset the depth metrics ``abs_rel``, ``sq_rel``, ``rmse_m``, ``rmse_log``,
``delta_1_25``, ``delta_1_25_2``, ``delta_1_25_3``, named plainly for ``all`` and with the subset
as a suffix otherwise (``abs_rel_lidar``, ``rmse_m_no_lidar``; :func:`depth_key`), ``miou``, then
``psnr_dynamic_db``, ``ssim_dynamic``, ``epe3d_mps``, ``acc5``, ``acc10``.
Besides them (not in the gap): the same depth metrics pooled over all pixels of the section with a
further ``_pooled`` suffix (``abs_rel_pooled``, ``abs_rel_lidar_pooled``), ``depth_pixels``
(``_lidar``, ``_no_lidar``) the truth pixels scored, and ``depth_coverage``, the mean share of truth
pixels the render has a depth for.

An ORACLE is scored the same way as a reference for what the representation can reach from the
context views alone: one Gaussian per context pixel at the true depth with the pixel's colour,
isotropic scale ``0.3 * depth / focal`` (0.3 pixel footprints: the rasterizer's 0.3 px^2 low-pass
still closes the gaps between neighbours, and the image is sharper than at the adapter's initial
0.6), opacity 0.99, its true class
and, where the truth flow exceeds 0.5 m/s, that velocity; a constant background (the mean colour of
the context images' sky pixels). ``gap`` is oracle - model for PSNR/SSIM/mIoU/deltas and
model - oracle for the depth errors (positive = the model is worse), per key of :data:`METRICS`.

Frames and units: poses are ``world_from_camera`` (OpenCV axes) in the cache's world frame,
metres; times are seconds after the clip's first context frame; images are RGB in [0, 1].
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from phigenesis import taxonomy
from phigenesis.data.clips import Clip, Stage1Clips, clip_inputs
from phigenesis.data.colormap import class_legend, classes_present, depth_color, depth_color_bar
from phigenesis.data.frame_truth import FrameTruth, frame_truth
from phigenesis.data.records import CameraCalibration, CameraTruth
from phigenesis.data.shards import MANIFEST_NAME
from phigenesis.data.views import resize_images, resize_intrinsics, resize_nearest
from phigenesis.eval.depth_protocol import ALL, DEPTH_METRICS, DepthAccumulator
from phigenesis.eval.scene_flow import FlowAccumulator, dynamic_mask, flow_pixels, masked_mean, masked_psnr
from phigenesis.models.loading import load_stage1
from phigenesis.models.losses import psnr, ssim
from phigenesis.models.metrics import confusion_matrix, segmentation_scores
from phigenesis.models.render import Rendered, Views, lift_views, render_views, sky_background
from phigenesis.models.stage1 import Stage1Model
from phigenesis.taxonomy import CLASS_NAMES, NUM_CLASSES

log = logging.getLogger(__name__)

#: The depth pixel subsets (see the module docstring); ``all`` is the protocol's own.
DEPTH_SUBSETS = (ALL, "lidar", "no_lidar")


def depth_key(metric: str, subset: str) -> str:
    """The report key of a depth metric on a subset: ``abs_rel`` (all), ``abs_rel_lidar``."""
    return metric if subset == ALL else f"{metric}_{subset}"


#: Metric names of a section, in table order; ``HIGHER_IS_BETTER`` decides the sign of the gap.
METRICS = (
    "psnr_db",
    "ssim",
    *(depth_key(m, s) for s in DEPTH_SUBSETS for m in DEPTH_METRICS),
    "miou",
    "psnr_dynamic_db",
    "ssim_dynamic",
    "epe3d_mps",
    "acc5",
    "acc10",
)
HIGHER_IS_BETTER = {
    "psnr_db": True,
    "ssim": True,
    **{depth_key(m, s): m.startswith("delta") for s in DEPTH_SUBSETS for m in DEPTH_METRICS},
    "miou": True,
    "psnr_dynamic_db": True,
    "ssim_dynamic": True,
    "epe3d_mps": False,
    "acc5": True,
    "acc10": True,
}


def section_name(kind: str, value: float) -> str:
    """``"input"``, ``"+5"`` (offset 5) or ``"shift_2m"`` (2 m; ``shift_0.5m`` for fractions)."""
    if kind == "offset":
        return f"{int(value):+d}"
    return f"shift_{value:g}m"


# --------------------------------------------------------------------------------------------
# Records


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


@dataclass
class SectionScores:
    """Running scores of one section for one renderer (model or oracle)."""

    psnr_db: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    psnr_dynamic_db: list[float] = field(default_factory=list)
    ssim_dynamic: list[float] = field(default_factory=list)
    flow: FlowAccumulator = field(default_factory=FlowAccumulator)
    depth: DepthAccumulator = field(default_factory=lambda: DepthAccumulator(DEPTH_SUBSETS[1:]))
    coverage: list[float] = field(default_factory=list)
    confusion: np.ndarray = field(default_factory=lambda: np.zeros((NUM_CLASSES, NUM_CLASSES + 1), np.int64))
    by_class: DepthAccumulator = field(default_factory=lambda: DepthAccumulator(CLASS_NAMES))

    def add(self, rendered: Rendered, views: Views) -> None:
        """Scores every view of ``rendered`` against ``views``' truth (depth: see the module docstring)."""
        truth_rgb = views.images
        self.psnr_db += psnr(rendered.rgb, truth_rgb).tolist()
        ssim_map = ssim(rendered.rgb, truth_rgb)
        self.ssim += ssim_map.mean(dim=(-2, -1)).tolist()
        if views.flow is not None:
            moving = dynamic_mask(views.flow)
            self.psnr_dynamic_db += masked_psnr(rendered.rgb, truth_rgb, moving)
            self.ssim_dynamic += masked_mean(ssim_map, moving)
            if rendered.velocity is not None:
                valid = flow_pixels(views.depth, views.semantic)
                self.flow.add(rendered.velocity, views.flow, valid)
        pred, truth = rendered.depth.numpy(), views.depth.numpy()
        covered = None if views.lidar_covered is None else views.lidar_covered.numpy()
        self.depth.add(pred, truth, {"lidar": covered, "no_lidar": None if covered is None else ~covered})
        known = (truth > 0).sum(axis=(1, 2))
        hit = ((truth > 0) & (pred > 0)).sum(axis=(1, 2))
        self.coverage += [
            h / k if k else float("nan") for h, k in zip(hit.tolist(), known.tolist(), strict=True)
        ]
        semantic = views.semantic.numpy()
        self.confusion += confusion_matrix(rendered.semantic.numpy(), semantic, NUM_CLASSES)
        self.by_class.add(pred, truth, {name: semantic == k for k, name in enumerate(CLASS_NAMES)})

    def summary(self) -> dict[str, float]:
        """The section's values (keys in the module docstring): means over images, depth under the
        protocol per subset (per-image means, and pooled with ``_pooled``), the pooled mIoU."""
        out = {"psnr_db": _mean(self.psnr_db), "ssim": _mean(self.ssim)}
        out |= {"psnr_dynamic_db": _mean(self.psnr_dynamic_db), "ssim_dynamic": _mean(self.ssim_dynamic)}
        out |= self.flow.summary()
        pooled = self.depth.pooled()
        for suffix, scores in (("", self.depth.image_mean()), ("_pooled", pooled)):
            for subset in DEPTH_SUBSETS:
                values = scores[subset]
                out |= {depth_key(m, subset) + suffix: getattr(values, m) for m in DEPTH_METRICS}
        out["miou"] = segmentation_scores(self.confusion).miou
        out |= {depth_key("depth_pixels", s): float(pooled[s].pixels) for s in DEPTH_SUBSETS}
        out["depth_coverage"] = _mean(self.coverage)
        return out

    def class_summary(self) -> dict[str, dict[str, float]]:
        """Depth per truth class (the views' semantics), for each class with a scored pixel: the
        protocol's metrics pooled over the class's pixels, ``pixels``, ``share`` (of the section's
        truth pixels) and ``miss_share``: the class's share of the section's pixels outside
        delta < 1.25 (where the error is)."""
        pooled = self.by_class.pooled()
        total = pooled[ALL]
        misses = total.pixels * (1.0 - total.delta_1_25) if total.pixels else 0.0
        out = {}
        for name in CLASS_NAMES:
            scores = pooled[name]
            if not scores.pixels:
                continue
            missed = scores.pixels * (1.0 - scores.delta_1_25)
            out[name] = {m: getattr(scores, m) for m in DEPTH_METRICS} | {
                "pixels": float(scores.pixels),
                "share": scores.pixels / total.pixels,
                "miss_share": missed / misses if misses else float("nan"),
            }
        return out


def gap(model: dict[str, float], oracle: dict[str, float]) -> dict[str, float]:
    """How far the model is behind the oracle per metric (positive = worse than the oracle)."""
    return {k: (oracle[k] - model[k]) if HIGHER_IS_BETTER[k] else (model[k] - oracle[k]) for k in METRICS}


# --------------------------------------------------------------------------------------------
# Synthetic truth of shifted cameras


def _translation(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def shifted_calibration(
    name: str,
    intrinsics: np.ndarray,
    size_hw: tuple[int, int],
    ego_from_camera: np.ndarray,
    shift_m: float,
) -> CameraCalibration:
    """A distortion-free pinhole camera of ``size_hw`` pixels (``intrinsics`` at that size) moved by
    ``shift_m`` metres along the ego's +y (left) from ``ego_from_camera``."""
    return CameraCalibration(
        name=name,
        width=int(size_hw[1]),
        height=int(size_hw[0]),
        intrinsics=np.asarray(intrinsics, np.float64),
        distortion=np.zeros(5),
        ego_from_camera=_translation(0.0, shift_m, 0.0) @ np.asarray(ego_from_camera, np.float64),
    )


class SyntheticTruth:
    """Exact renders of a synthetic cache's scenes from any camera (the shifted views' truth).

    Built from the cache manifest's source arguments (:meth:`SyntheticConfig.from_dict`); raises
    ValueError when the cache is not synthetic.
    """

    def __init__(self, arguments: dict[str, Any], source: str):
        # the synthetic renderer (Open3D, trimesh) loads only for synthetic caches
        from phigenesis.data.sources.synthetic import SOURCE_NAME, SyntheticConfig, SyntheticScene

        if source != SOURCE_NAME:
            raise ValueError(f"the cache's source is {source!r}, not {SOURCE_NAME!r}")
        # Without the ego's own body: a camera moved metres sideways would otherwise see the ego car
        # standing where it was (a real lane change takes the body along); the world is otherwise
        # the same (the body is a mesh added last, drawing no random numbers).
        self.config = dataclasses.replace(SyntheticConfig.from_dict(arguments), ego_body=False)
        self._scene_class = SyntheticScene
        self._scenes: dict[str, Any] = {}

    def scene(self, scene_id: str) -> Any:
        """The :class:`SyntheticScene` of ``scene_id`` (built once)."""
        if scene_id not in self._scenes:
            ids = self.config.scene_ids()
            if scene_id not in ids:
                raise ValueError(f"scene {scene_id!r} is not one of the cache's synthetic scenes")
            self._scenes[scene_id] = self._scene_class(self.config, ids.index(scene_id))
        return self._scenes[scene_id]

    def render(
        self, scene_id: str, calibration: CameraCalibration, world_from_ego: np.ndarray, timestamp_micros: int
    ) -> tuple[np.ndarray, CameraTruth]:
        """(rgb (H, W, 3) uint8, truth) of ``calibration`` on the ego at ``world_from_ego`` at a time."""
        scene = self.scene(scene_id)
        return scene.renderer.render_camera(calibration, world_from_ego, scene.seconds(timestamp_micros))


# --------------------------------------------------------------------------------------------
# Views of a clip


def target_views(clip: Clip, index: int, truth: FrameTruth) -> Views:
    """The views of the clip's target frame ``index`` (position in ``clip.target_indices``)."""
    tg = clip.targets
    return Views(
        images=tg.images[index].permute(0, 2, 3, 1).contiguous(),
        world_from_camera=tg.world_from_camera[index],
        intrinsics=clip.intrinsics,
        time_s=tg.time_s[index],
        depth=truth.depth,
        semantic=truth.semantic,
        flow=truth.flow,
        lidar_covered=truth.lidar_covered,
    )


def concat_views(views: list[Views]) -> Views:
    """The views of several lists, one after another (optional maps only when every list has them)."""

    def cat(maps: list[Tensor | None]) -> Tensor | None:
        return torch.cat(maps) if all(m is not None for m in maps) else None  # type: ignore[arg-type]

    return Views(
        images=torch.cat([v.images for v in views]),
        world_from_camera=torch.cat([v.world_from_camera for v in views]),
        intrinsics=torch.cat([v.intrinsics for v in views]),
        time_s=torch.cat([v.time_s for v in views]),
        depth=torch.cat([v.depth for v in views]),
        semantic=torch.cat([v.semantic for v in views]),
        flow=cat([v.flow for v in views]),
        lidar_covered=cat([v.lidar_covered for v in views]),
    )


#: A shifted frame is scored only where every shifted camera centre stays at least this far (metres)
#: outside every labelled box at its capture time. A camera 2 m left of its lane can sit inside or at
#: the skin of a truck in the next lane; its exact truth is then that truck's surface a few
#: centimetres away over the whole image (AbsRel of any prediction in the tens), not a novel view of
#: the scene. On the benchmark's held-out scenes 0.5 m catches every such view (median truth depth
#: under 1 m) and nothing else; a 1 m margin (the ego body's half width: "the shifted car would
#: touch another") would also drop ordinary views and skip most 2 m frames of dense traffic.
SHIFT_CLEARANCE_M = 0.5


def shift_collision(
    sample: dict[str, Any], shift_m: float, clearance_m: float = SHIFT_CLEARANCE_M
) -> str | None:
    """Why the rig of ``sample`` (a loaded cache frame with cameras and boxes) moved ``shift_m`` metres
    to the ego's left collides with a labelled box, or None where it does not.

    A camera collides when its centre, at its own capture time, lies inside a box (moved along its
    velocity from the frame's time to the camera's) grown by ``clearance_m`` on every side.
    """
    if "boxes_center_world" not in sample or len(sample["boxes_center_world"]) == 0:
        return None
    centers = sample["boxes_center_world"].double().numpy()
    half = sample["boxes_size_lwh"].double().numpy() / 2 + clearance_m
    yaw = sample["boxes_yaw_world"].double().numpy()
    velocity = sample["boxes_velocity_world"].double().numpy()
    frame_micros = int(sample["frame_timestamp_micros"])
    cos, sin = np.cos(yaw), np.sin(yaw)
    shift = _translation(0.0, shift_m, 0.0)
    for c, name in enumerate(sample["camera_names"]):
        world_from_ego = sample["camera_world_from_ego"][c].double().numpy()
        origin = (world_from_ego @ shift @ sample["ego_from_camera"][c].double().numpy())[:3, 3]
        dt_s = (int(sample["camera_timestamp_micros"][c]) - frame_micros) * 1e-6
        d = origin - (centers + velocity * dt_s)
        local = np.stack([cos * d[:, 0] + sin * d[:, 1], -sin * d[:, 0] + cos * d[:, 1], d[:, 2]], -1)
        inside = np.flatnonzero((np.abs(local) < half).all(-1))
        if inside.size:
            b = int(inside[0])
            track = sample["boxes_track_id"][b] if "boxes_track_id" in sample else str(b)
            cls = int(sample["boxes_class_id"][b])
            name_cls = taxonomy.CLASS_NAMES[cls] if 0 <= cls < len(taxonomy.CLASS_NAMES) else str(cls)
            return (
                f"camera {name} moved {shift_m:g} m left is within {clearance_m:g} m of box {track} "
                f"({name_cls})"
            )
    return None


def shifted_views(
    truth: SyntheticTruth,
    clip: Clip,
    sample: dict[str, Any],
    shift_m: float,
    size_hw: tuple[int, int],
) -> Views:
    """The views of frame ``sample`` (a loaded cache frame of ``clip``'s scene) with every camera
    moved ``shift_m`` metres to the ego's left at its own capture time, truth rendered exactly.

    The renderer casts a distortion-free pinhole camera at the cache's image size (the cache's
    intrinsics), and the result is brought to ``size_hw`` as :class:`Stage1Clips` brings the cache's
    own views (area-averaged colour, nearest-sampled depth / classes / flow), so shifted and
    unshifted sections are equally sharp; at equal sizes this is the render itself.
    """
    h_in, w_in = sample["images"].shape[-2:]
    k_in = sample["intrinsics"].double()
    images, poses, times, depths, sems, flows = [], [], [], [], [], []
    for c, name in enumerate(sample["camera_names"]):
        cal = shifted_calibration(
            name, k_in[c].numpy(), (h_in, w_in), sample["ego_from_camera"][c].numpy(), shift_m
        )
        world_from_ego = sample["camera_world_from_ego"][c].double().numpy()
        stamp = int(sample["camera_timestamp_micros"][c])
        rgb, tr = truth.render(clip.scene_id, cal, world_from_ego, stamp)
        images.append(resize_images(torch.from_numpy(rgb).permute(2, 0, 1), size_hw).permute(1, 2, 0))
        poses.append(torch.from_numpy(world_from_ego @ cal.ego_from_camera))
        times.append((stamp - clip.time_origin_micros) * 1e-6)
        depths.append(resize_nearest(torch.from_numpy(tr.depth_m), size_hw))
        sems.append(resize_nearest(torch.from_numpy(tr.semantic), size_hw))
        flows.append(
            resize_nearest(torch.from_numpy(tr.flow_world_mps).permute(2, 0, 1), size_hw).permute(1, 2, 0)
        )
    return Views(
        images=torch.stack(images).contiguous(),
        world_from_camera=torch.stack(poses),
        intrinsics=resize_intrinsics(k_in, (h_in, w_in), size_hw).float(),
        time_s=torch.tensor(times, dtype=torch.float64),
        depth=torch.stack(depths),
        semantic=torch.stack(sems),
        flow=torch.stack(flows).contiguous(),
    )


# --------------------------------------------------------------------------------------------
# The evaluation


@dataclass(frozen=True)
class ClipResult:
    """What one clip left for the picture: per section its views and both renders."""

    scene_id: str
    start: int
    views: dict[str, Views]
    model: dict[str, Rendered]
    oracle: dict[str, Rendered]


def clip_starts(length: int, frames: int, max_offset: int, count: int) -> list[int]:
    """Up to ``count`` context start frames spread evenly over a scene of ``length`` frames such
    that the last context frame + ``max_offset`` stays inside it (empty if none fits)."""
    last = length - frames - max_offset
    if last < 0:
        return []
    return sorted({round(float(v)) for v in np.linspace(0, last, max(count, 1))})


def _open_clips(shards: Path, model: Stage1Model) -> Stage1Clips:
    if not shards.is_dir() or not (shards / MANIFEST_NAME).is_file():
        raise ValueError(f"{shards}: not a phigenesis cache (no {MANIFEST_NAME})")
    return Stage1Clips(shards, model.config.image_size, model.config.frames, "auto")


def evaluate_clip(
    model: Stage1Model,
    data: Stage1Clips,
    scene_id: str,
    start: int,
    offsets: tuple[int, ...],
    shifts_m: tuple[float, ...],
    truth: SyntheticTruth | None,
    oracle: bool,
) -> ClipResult:
    """Predicts one clip's scene and renders the model (and the oracle) at every section's views."""
    size = tuple(model.config.image_size)
    t = model.config.frames
    clip = data.clip(scene_id, start, list(offsets), keep_frames=True)
    samples = clip.frames
    assert samples is not None
    truths = {i: frame_truth(s, size) for i, s in samples.items()}  # type: ignore[arg-type]
    views = {"input": concat_views([target_views(clip, j, truths[clip.target_indices[j]]) for j in range(t)])}
    for j, off in enumerate(offsets):
        views[section_name("offset", off)] = target_views(clip, t + j, truths[clip.target_indices[t + j]])
    if truth is not None:
        last = samples[clip.frame_indices[-1]]
        for d in shifts_m:
            why = shift_collision(last, d)  # type: ignore[arg-type]
            if why is not None:
                log.info("%s @ %d: not scoring the %g m shift: %s", scene_id, start, d, why)
                continue
            views[section_name("shift", d)] = shifted_views(truth, clip, last, d, size)  # type: ignore[arg-type]
    scene = model.predict(*clip_inputs([clip]), time_origin_micros=clip.time_origin_micros)
    model_out, oracle_out = {}, {}
    with torch.no_grad():
        for name, v in views.items():
            sky = model.background(v.world_from_camera.float(), v.intrinsics.float(), *v.size_hw)
            model_out[name] = render_views(scene, v, sky)
        if oracle:
            ctx = views["input"]
            gauss = lift_views(ctx, clip.time_origin_micros)
            bg = sky_background(ctx)
            for name, v in views.items():
                oracle_out[name] = render_views(gauss, v, bg)
    return ClipResult(scene_id, start, views, model_out, oracle_out)


def evaluate_stage1(
    checkpoint: str | os.PathLike[str],
    shards: str | os.PathLike[str],
    *,
    offsets: tuple[int, ...] | list[int] = (5, 10),
    shifts_m: tuple[float, ...] | list[float] = (1.0, 2.0, 4.0),
    clips_per_scene: int = 3,
    oracle: bool = True,
    picture: str | os.PathLike[str] | None = None,
    threads: int | None = None,
    out_json: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Scores the Stage 1 model of ``checkpoint`` on the cache ``shards`` (see the module docstring).

    Returns a dict: ``checkpoint``, ``shards``, ``model``, ``image_size``, ``offsets``, ``shifts_m``
    (those evaluated), ``clips``, ``images`` (views scored per section), ``seconds_per_clip``,
    ``clip_list`` ([scene id, start]) and ``sections``: per section name ``{"images", "model",
    "oracle", "gap", "model_by_class", "oracle_by_class"}`` with the metrics of :data:`METRICS` (model
    and oracle also with the pooled depth metrics, ``depth_pixels*`` and ``depth_coverage``: see the
    module docstring) and the depth per truth class (:meth:`SectionScores.class_summary`); ``oracle*``
    and ``gap`` only when ``oracle``. Writes it as JSON to ``out_json`` and a PNG of the first clip to
    ``picture`` when given. Raises :class:`CheckpointError` for a checkpoint that is not a Stage 1
    model and ValueError naming the cache when it is empty, lacks dense depth or has no scene long
    enough for ``max(offsets)``.
    """
    if threads:
        torch.set_num_threads(int(threads))
    offsets = tuple(int(o) for o in offsets)
    shifts = tuple(float(d) for d in shifts_m)
    if any(o < 1 for o in offsets) or clips_per_scene < 1:
        raise ValueError(f"offsets {list(offsets)} must be positive and clips_per_scene at least 1")
    shards = Path(shards)
    model = load_stage1(checkpoint)
    model.eval()
    data = _open_clips(shards, model)
    truth = None
    if shifts:
        manifest = data.reader.manifest
        try:
            truth = SyntheticTruth(manifest.arguments, manifest.source)
        except (ValueError, TypeError) as e:
            log.warning("%s: skipping the shifted views (%s): no exact truth for novel views", shards, e)
            shifts = ()
    max_offset = max(offsets, default=0)
    plan = [
        (scene, s)
        for scene in data.scenes
        for s in clip_starts(data.scene_length(scene), model.config.frames, max_offset, clips_per_scene)
    ]
    if not plan:
        raise ValueError(
            f"{shards}: no scene has the {model.config.frames + max_offset} frames a clip with offset "
            f"{max_offset} needs"
        )
    sections = ["input"] + [section_name("offset", o) for o in offsets]
    sections += [section_name("shift", d) for d in shifts]
    scores = {name: (SectionScores(), SectionScores()) for name in sections}
    skipped = dict.fromkeys(sections, 0)
    first: ClipResult | None = None
    t0 = time.perf_counter()
    for scene, start in plan:
        result = evaluate_clip(model, data, scene, start, offsets, shifts, truth, oracle)
        for name in sections:
            if name not in result.views:  # a shift that would collide (see shift_collision)
                skipped[name] += 1
                continue
            scores[name][0].add(result.model[name], result.views[name])
            if oracle:
                scores[name][1].add(result.oracle[name], result.views[name])
        first = first or result
        log.info("clip %s @ %d done", scene, start)
    seconds = (time.perf_counter() - t0) / len(plan)
    report: dict[str, Any] = {
        "checkpoint": str(checkpoint),
        "shards": str(shards),
        "model": model.name,
        "image_size": list(model.config.image_size),
        "offsets": list(offsets),
        "shifts_m": list(shifts),
        "clips": len(plan),
        "images": {name: len(scores[name][0].psnr_db) for name in sections},
        "seconds_per_clip": seconds,
        "clip_list": [[s, i] for s, i in plan],
        "sections": {},
    }
    for name in sections:
        entry: dict[str, Any] = {
            "images": len(scores[name][0].psnr_db),
            "skipped_clips": skipped[name],
            "model": scores[name][0].summary(),
            "model_by_class": scores[name][0].class_summary(),
        }
        if oracle:
            entry["oracle"] = scores[name][1].summary()
            entry["oracle_by_class"] = scores[name][1].class_summary()
            entry["gap"] = gap(entry["model"], entry["oracle"])
        report["sections"][name] = entry
    if out_json is not None:
        write_json(report, out_json)
    if picture is not None and first is not None:
        save_picture(first, picture, shifts)
    return report


def write_json(report: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Writes ``report`` as JSON (NaN as null) to ``path``, creating its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def clean(x: Any) -> Any:
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    path.write_text(json.dumps(clean(report), indent=2))
    return path


# --------------------------------------------------------------------------------------------
# Picture


def picture_panels(
    result: ClipResult, shifts_m: tuple[float, ...] = ()
) -> tuple[list[str], list[list[np.ndarray]]]:
    """The picture's column titles and, per input view (at most 3), its panels as (H, W, 3) uint8
    RGB: input image, render, rendered depth, truth depth (both in the toolkit's depth colours,
    :func:`phigenesis.data.colormap.depth_color`, as ``phigenesis-prep preview`` draws depth), the
    rendered depth entropy when the render has one (:func:`entropy_color`, scaled to the largest
    shown, which the title gives in nats), rendered semantics, and the shifted render beside its
    truth for the shift nearest 2 m when there is one."""

    def u8(rgb: np.ndarray) -> np.ndarray:
        return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)

    views, render = result.views["input"], result.model["input"]
    shift = min(shifts_m, key=lambda d: abs(d - 2.0)) if shifts_m else None
    shift_name = section_name("shift", shift) if shift is not None else None
    if shift_name not in result.views:  # that shift collided in this clip
        shift_name = None
    shown = min(len(views), 3)
    columns = ["input", "render", "rendered depth", "truth depth"]
    entropy_high = 0.0
    if render.entropy is not None:
        entropy_high = max(float(render.entropy[:shown].max()), 1e-6)
        columns.append(f"entropy 0-{entropy_high:.2g} nats")
    columns.append("rendered semantics")
    if shift_name is not None:
        columns += [f"render {shift_name}", f"truth {shift_name}"]
    rows = []
    for r in range(shown):
        panels = [
            u8(views.images[r].numpy()),
            u8(render.rgb[r].numpy()),
            depth_color(render.depth[r].numpy()),
            depth_color(views.depth[r].numpy()),
        ]
        if render.entropy is not None:
            panels.append(entropy_color(render.entropy[r].numpy(), entropy_high))
        panels.append(taxonomy.PALETTE_RGB[render.semantic[r].numpy()])
        if shift_name is not None:
            panels += [
                u8(result.model[shift_name].rgb[r].numpy()),
                u8(result.views[shift_name].images[r].numpy()),
            ]
        rows.append(panels)
    return columns, rows


def entropy_color(entropy_nats: np.ndarray, high_nats: float) -> np.ndarray:
    """(..., 3) uint8 RGB of entropies (..., nats) on the stretch of the turbo map the depth panels
    use (its dark ends left out): 0 blue to ``high_nats`` (and above) red."""
    u = np.clip(np.nan_to_num(np.asarray(entropy_nats, np.float64)) / high_nats, 0.0, 1.0)
    index = np.round(20 + u * 220).astype(np.uint8)
    turbo = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return turbo[index]


def save_picture(result: ClipResult, path: str | os.PathLike[str], shifts_m: tuple[float, ...] = ()) -> Path:
    """A PNG of one clip: the panels of :func:`picture_panels` in a grid, then the depth colour bar
    (metres) and the legend of the classes the rendered semantics show."""
    # matplotlib loads only to draw a picture
    import matplotlib

    matplotlib.use("Agg")
    # matplotlib loads only to draw a picture
    import matplotlib.pyplot as plt

    columns, rows = picture_panels(result, shifts_m)
    fig, axes = plt.subplots(
        len(rows), len(columns), figsize=(2.2 * len(columns), 1.7 * len(rows)), dpi=100, squeeze=False
    )
    for r, panels in enumerate(rows):
        for c, panel in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(panel, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(columns[c], fontsize=8)
    fig.suptitle(f"{result.scene_id} frame {result.start}", fontsize=9)
    fig.tight_layout()
    fig.canvas.draw()
    grid = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    shown = classes_present(result.model["input"].semantic[: len(rows)].numpy())
    picture = np.concatenate(
        [grid, depth_color_bar(grid.shape[1]), class_legend(shown, grid.shape[1], "rendered classes")], axis=0
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), picture[..., ::-1]):
        raise OSError(f"could not write {path}")
    return path
