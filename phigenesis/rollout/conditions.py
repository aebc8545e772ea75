"""Stage 2's condition: the history's Gaussians rendered along the target trajectory.

For a window of history frames and the cameras of the frames to generate (each camera at its own
pose and capture time), the history becomes one :class:`~phigenesis.models.gaussians.GaussianScene`
and is rendered at every target camera: colour, alpha, expected depth and, where the Gaussians
carry one, the depth entropy. Where the Gaussians come from is ``geometry``:

- ``stage1``: the Stage 1 model's prediction from the history images (the paper). A model that
  takes one frame at a time predicts each history frame alone, and the frames' Gaussians are joined.
- ``cache``: the cache's dense depth lifted to one Gaussian per pixel (:func:`lift_views`), with
  the cache's semantics and, where a moving box covers a pixel, the box's velocity.
- ``truth``: the synthetic truth depth, semantics and scene flow lifted the same way: the ceiling
  of the ablation (what a perfect geometry gives).

Frames and units: poses ``world_from_camera`` (OpenCV axes) in the cache's world frame, metres;
times in seconds after the clip's origin (its first history frame); images RGB in [0, 1]. Symbols:
F frames, V views, H x W pixels at the model's size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

import torch
from torch import Tensor

from phigenesis.data.clips import Clip
from phigenesis.data.frame_truth import frame_truth
from phigenesis.data.views import resize_intrinsics
from phigenesis.models.dit import plucker_rays
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.render import SKY_ALPHA, Views, lift_views
from phigenesis.models.stage1 import Stage1Model
from phigenesis.models.uncertainty import (
    DEFAULT_LP_TRUST,
    HistoryViews,
    LpTrust,
    UncertaintyConfig,
    UncertaintyKind,
    uncertainty_map,
)
from phigenesis.taxonomy import SKY

GeometrySource = Literal["stage1", "cache", "truth"]
GEOMETRY_SOURCES: tuple[str, ...] = get_args(GeometrySource)
#: Every uncertainty kind, in the order latent caches store them.
UNCERTAINTY_KINDS: tuple[UncertaintyKind, ...] = ("coverage", "random", "entropy", "localization_potential")
#: Stereo Forcing's map of a Stage 2 model or rollout: an uncertainty kind, or "none" (no geometry).
ConditionKind = Literal["localization_potential", "entropy", "random", "coverage", "none"]


@dataclass(frozen=True)
class TargetCameras:
    """The cameras a condition is rendered at: F frames of a rig of V views."""

    world_from_camera: Tensor  # [F, V, 4, 4] float64, OpenCV axes, world frame
    intrinsics: Tensor  # [V, 3, 3] float32 pinhole at size_hw (pixel centres at integers)
    time_s: Tensor  # [F, V] float64 capture times, seconds after the clip's origin
    size_hw: tuple[int, int]

    def __post_init__(self) -> None:
        shape = tuple(self.world_from_camera.shape)
        if len(shape) != 4 or shape[2:] != (4, 4):
            raise ValueError(f"TargetCameras: world_from_camera must be [F, V, 4, 4], got {shape}")
        f, v = shape[:2]
        if self.intrinsics.shape != (v, 3, 3):
            raise ValueError(
                f"TargetCameras: intrinsics must be [{v}, 3, 3], got {tuple(self.intrinsics.shape)}"
            )
        if self.time_s.shape != (f, v):
            raise ValueError(f"TargetCameras: time_s must be [{f}, {v}], got {tuple(self.time_s.shape)}")
        for name in ("world_from_camera", "intrinsics", "time_s"):
            if not torch.isfinite(getattr(self, name)).all():
                raise ValueError(f"TargetCameras: {name} holds NaN or Inf")

    @property
    def frames(self) -> int:
        return int(self.world_from_camera.shape[0])

    @property
    def views(self) -> int:
        return int(self.world_from_camera.shape[1])


@dataclass(frozen=True)
class ConditionRender:
    """The history rendered at the F x V target cameras, without a background (holes are black:
    ``rgb`` is premultiplied by ``alpha``)."""

    rgb: Tensor  # [F, V, H, W, 3] in [0, 1]
    alpha: Tensor  # [F, V, H, W] accumulated opacity
    depth: Tensor  # [F, V, H, W] expected z-depth, metres, 0 where nothing
    entropy: Tensor | None  # [F, V, H, W] nats, when the Gaussians carry a depth entropy
    semantic: Tensor | None = None  # [F, V, H, W] uint8 argmax class, SKY where alpha < 0.5 (if asked)
    trust: Tensor | None = None  # [F, V, H, W] the Gaussians' trust averaged as the depth is (if given)


def context_cameras(clip: Clip) -> TargetCameras:
    """The clip's own context (history) cameras."""
    ctx = clip.context
    return TargetCameras(ctx.world_from_camera, clip.intrinsics, ctx.time_s, tuple(ctx.images.shape[-2:]))


def future_cameras(clip: Clip) -> TargetCameras:
    """The cameras of the clip's targets after its context frames (``clip.targets`` beyond the
    first ``len(clip.frame_indices)``): a window to generate, at its recorded poses and times."""
    t = len(clip.frame_indices)
    tg = clip.targets
    return TargetCameras(
        tg.world_from_camera[t:], clip.intrinsics, tg.time_s[t:], tuple(tg.images.shape[-2:])
    )


def lifted_scene(
    clip: Clip, depth_m: Tensor, semantic: Tensor, flow_mps: Tensor | None = None
) -> GaussianScene:
    """One Gaussian per context pixel of ``clip`` with ``depth_m`` > 0 (:func:`lift_views`).

    ``depth_m`` [F, V, H, W] z-depth in metres (0 = none), ``semantic`` [F, V, H, W] uint8 classes
    (255 = unknown), ``flow_mps`` [F, V, H, W, 3] world-frame velocities (None: all static), for the
    F context frames of ``clip``."""
    ctx = clip.context
    f, v = ctx.images.shape[:2]
    if depth_m.shape != (f, v, *ctx.images.shape[-2:]):
        raise ValueError(f"lifted_scene: depth_m must be [{f}, {v}, H, W], got {tuple(depth_m.shape)}")
    views = Views(
        images=ctx.images.permute(0, 1, 3, 4, 2).flatten(0, 1).contiguous(),
        world_from_camera=ctx.world_from_camera.flatten(0, 1),
        intrinsics=clip.intrinsics.expand(f, v, 3, 3).flatten(0, 1),
        time_s=ctx.time_s.flatten(0, 1),
        depth=depth_m.flatten(0, 1).float(),
        semantic=semantic.flatten(0, 1),
        flow=None if flow_mps is None else flow_mps.flatten(0, 1).float(),
    )
    return lift_views(views, clip.time_origin_micros)


def cache_scene(clip: Clip) -> GaussianScene:
    """``geometry: cache``: the clip's dense depth and semantics lifted, moving boxes' pixels at
    their box's velocity."""
    ctx = clip.context
    flow = ctx.box_velocity * (ctx.moving > 0)[..., None]
    return lifted_scene(clip, ctx.depth, ctx.semantic, flow)


def stage1_scene(model: Stage1Model, clip: Clip) -> GaussianScene:
    """``geometry: stage1``: the Stage 1 model's Gaussians of the clip's context frames. A model of
    ``frames`` frames predicts consecutive groups of that many; their Gaussians are joined (the
    history's frames overlap: a voxel-bounded buffer is the caller's to apply)."""
    ctx = clip.context
    f = ctx.images.shape[0]
    group = int(model.config.frames)
    if f % group:
        raise ValueError(f"stage1_scene: {f} context frames do not split into groups of the model's {group}")
    scenes = []
    for s in range(0, f, group):
        sl = slice(s, s + group)
        scenes.append(
            model.predict(
                ctx.images[None, sl],
                clip.intrinsics[None],
                ctx.world_from_camera[None, sl],
                ctx.time_s[None, sl].float(),
                time_origin_micros=clip.time_origin_micros,
            )
        )
    return GaussianScene.concatenate(scenes) if len(scenes) > 1 else scenes[0]


def truth_maps(clip: Clip) -> tuple[Tensor, Tensor, Tensor | None]:
    """The synthetic truth (depth [F, V, H, W] metres, classes [F, V, H, W], flow [F, V, H, W, 3] m/s or
    None) of the clip's context frames at its image size: what ``geometry: truth`` lifts. The clip must
    carry its frames (``keep_frames``); a cache without truth depth is refused naming the scene."""
    assert clip.frames is not None
    size = tuple(clip.context.images.shape[-2:])
    truths = [frame_truth(clip.frames[i], size) for i in clip.frame_indices]  # type: ignore[arg-type]
    if not all(t.has_truth_depth for t in truths):
        raise ValueError(f"scene {clip.scene_id}: geometry 'truth' needs a synthetic cache with truth depth")
    flows = [t.flow for t in truths]
    flow = torch.stack(flows) if all(f is not None for f in flows) else None  # type: ignore[arg-type]
    return torch.stack([t.depth for t in truths]), torch.stack([t.semantic for t in truths]), flow


def history_scene(
    geometry: GeometrySource,
    clip: Clip,
    model: Stage1Model | None = None,
    truth_depth_m: Tensor | None = None,
    truth_semantic: Tensor | None = None,
    truth_flow_mps: Tensor | None = None,
) -> GaussianScene:
    """The Gaussians of the clip's context frames from ``geometry`` (see the module docstring).

    ``stage1`` needs ``model``; ``truth`` needs ``truth_depth_m`` and ``truth_semantic`` [F, V, H, W]
    (and ``truth_flow_mps`` [F, V, H, W, 3] where the scene moves) at the model's size."""
    if geometry == "stage1":
        if model is None:
            raise ValueError("geometry 'stage1' needs a Stage 1 model")
        return stage1_scene(model, clip)
    if geometry == "cache":
        return cache_scene(clip)
    if geometry == "truth":
        if truth_depth_m is None or truth_semantic is None:
            raise ValueError(
                "geometry 'truth' needs the truth depth and semantics (a synthetic cache's truth maps)"
            )
        return lifted_scene(clip, truth_depth_m, truth_semantic, truth_flow_mps)
    raise ValueError(f"geometry must be one of {GEOMETRY_SOURCES}, got {geometry!r}")


def render_condition(
    scene: GaussianScene, cameras: TargetCameras, semantics: bool = False, trust: Tensor | None = None
) -> ConditionRender:
    """``scene`` rendered at every target camera at its own capture time (no background); with
    ``semantics``, also the argmax class of every pixel (sky in holes); with ``trust`` (N,) in [0, 1]
    per Gaussian, also its per-pixel average (0 in holes)."""
    f, v = cameras.frames, cameras.views
    h, w = cameras.size_hw
    with_entropy = scene.depth_entropy is not None
    if len(scene) == 0:
        zeros = torch.zeros(f, v, h, w)
        sky = torch.full((f, v, h, w), SKY, dtype=torch.uint8) if semantics else None
        return ConditionRender(
            torch.zeros(f, v, h, w, 3),
            zeros,
            zeros.clone(),
            zeros.clone() if with_entropy else None,
            sky,
            None if trust is None else zeros.clone(),
        )
    with torch.no_grad():
        out = scene.render(
            cameras.world_from_camera.flatten(0, 1).float(),
            cameras.intrinsics.expand(f, v, 3, 3).flatten(0, 1).float(),
            w,
            h,
            cameras.time_s.flatten(0, 1),
            semantics=semantics,
            entropy=with_entropy,
            values=trust,
        )

    def unflatten(x: Tensor) -> Tensor:
        return x.reshape(f, v, *x.shape[1:])

    labels = None
    if semantics:
        assert out.semantic_probs is not None
        labels = out.semantic_probs.argmax(-1).to(torch.uint8)
        labels = unflatten(torch.where(out.alpha < SKY_ALPHA, torch.full_like(labels, SKY), labels))
    return ConditionRender(
        rgb=unflatten(out.rgb.clamp(0.0, 1.0)),
        alpha=unflatten(out.alpha),
        depth=unflatten(out.depth),
        entropy=None if out.depth_entropy is None else unflatten(out.depth_entropy),
        semantic=labels,
        trust=None if out.value is None else unflatten(out.value),
    )


def uncertainty_maps(
    render: ConditionRender,
    targets: TargetCameras,
    history: TargetCameras,
    history_depth: Tensor,
    num_bins: int,
    generator: torch.Generator,
    patch_px: int,
    kinds: tuple[str, ...] = UNCERTAINTY_KINDS,
    lp_trust: LpTrust = DEFAULT_LP_TRUST,
) -> dict[str, Tensor]:
    """Stereo Forcing's maps u [F, V, H, W] (1 = trust the render, 0 in holes) of each of ``kinds``
    for a condition ``render`` at the ``targets`` cameras, at image resolution
    (:func:`~phigenesis.models.uncertainty.uncertainty_map`): the localization potential against the
    ``history`` cameras with their rendered depth ``history_depth`` [F_h, V, H, W] (occlusion),
    the entropy of a depth distribution of ``num_bins`` bins (only where the render has one);
    ``lp_trust`` says which points the localization potential's u trusts (:data:`LpTrust`)."""
    render_alpha, render_depth, render_entropy = render.alpha, render.depth, render.entropy
    cfg = UncertaintyConfig(patch_px=patch_px, num_bins=max(num_bins, 2), lp_trust=lp_trust)
    f, v = targets.frames, targets.views
    hv = HistoryViews(
        intrinsics=history.intrinsics.expand(history.frames, v, 3, 3).flatten(0, 1).double(),
        world_from_camera=history.world_from_camera.flatten(0, 1).double(),
        hw=history.size_hw,
        depth_m=history_depth.flatten(0, 1).double(),
    )
    common: dict[str, Any] = {
        "config": cfg,
        "depth_m": render_depth.flatten(0, 1),
        "intrinsics": targets.intrinsics.expand(f, v, 3, 3).flatten(0, 1).double(),
        "world_from_camera": targets.world_from_camera.flatten(0, 1).double(),
        "history": hv,
        "generator": generator,
    }
    out = {}
    for kind in kinds:
        if kind == "entropy":
            if render_entropy is None:
                continue
            common["entropy_nats"] = render_entropy.flatten(0, 1)
        u = uncertainty_map(kind, render_alpha.flatten(0, 1), **common)
        out[kind] = u.reshape(f, v, *u.shape[1:]).float()
    return out


def latent_frame_cameras(world_from_camera: Tensor, latent_frames: int, temporal_compression: int) -> Tensor:
    """[T_z, V, 4, 4] the camera of each latent frame of a clip of F frames ([F, V, 4, 4]): the last
    of the frames it covers (causal VAE: latent k covers frames ``(k - 1) c + 1 .. k c``, latent 0
    frame 0)."""
    f = world_from_camera.shape[0]
    index = torch.clamp(torch.arange(latent_frames) * temporal_compression, max=f - 1)
    return world_from_camera[index]


def sequence_plucker(
    history: TargetCameras,
    targets: TargetCameras,
    latent_frames: tuple[int, int],
    latent_hw: tuple[int, int],
    temporal_compression: int,
) -> Tensor:
    """[V, 6, T_h + T, h, w] Plücker rays (:func:`~phigenesis.models.dit.plucker_rays`) of every
    latent token of a sequence of history then target latent frames (``latent_frames`` = (T_h, T)),
    in the frame of the first history camera of view 0 (so the moments stay small however far the
    scene has driven)."""
    t_h, t = latent_frames
    h, w = latent_hw
    cams = torch.cat(
        [
            latent_frame_cameras(history.world_from_camera.double(), t_h, temporal_compression),
            latent_frame_cameras(targets.world_from_camera.double(), t, temporal_compression),
        ]
    )  # [T_h + T, V, 4, 4]
    rel = torch.linalg.inv(history.world_from_camera[0, 0].double()) @ cams
    v = cams.shape[1]
    k = resize_intrinsics(targets.intrinsics.double(), targets.size_hw, (h, w))  # [V, 3, 3]
    rays = plucker_rays(k.expand(t_h + t, v, 3, 3), rel, h, w)  # [T_h + T, V, 6, h, w]
    return rays.permute(1, 2, 0, 3, 4).float()


def with_sky(render: ConditionRender, stage1: Stage1Model, cameras: TargetCameras) -> Tensor:
    """[F, V, H, W, 3] ``render`` over Stage 1's sky (:meth:`Stage1Model.background` seen from each
    target camera): the whole image the history's Gaussians predict, in [0, 1]. The sky lies at
    infinity, so it is as valid from a new camera as from a recorded one."""
    f, v = cameras.frames, cameras.views
    with torch.no_grad():
        sky = stage1.background(
            cameras.world_from_camera.flatten(0, 1).float(),
            cameras.intrinsics.expand(f, v, 3, 3).flatten(0, 1).float(),
            *cameras.size_hw,
        ).reshape(f, v, *cameras.size_hw, 3)
    return (render.rgb + (1 - render.alpha[..., None]) * sky).clamp(0, 1)
