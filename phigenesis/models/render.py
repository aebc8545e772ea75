"""Rendering a set of camera views from Gaussians, and lifting views with a depth to Gaussians.

What evaluation, export and Stage 2 share: :class:`Views` (cameras at their capture times with
their truth), :func:`render_views` (a :class:`~phigenesis.models.gaussians.GaussianScene` into
every view, with a background behind it), :func:`lift_views` (one Gaussian per pixel with a
depth: the oracle of ``phigenesis-eval stage1``, and Stage 2's ``geometry: cache | truth``) and
:func:`sky_background`.

Frames and units: poses are ``world_from_camera`` (OpenCV axes) in the cache's world frame,
metres; times are seconds after a clip's origin; images are RGB in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.stage1 import pixel_rays
from phigenesis.taxonomy import NUM_CLASSES, SKY

#: Lifted Gaussians' opacity, logit of their true class (softmax ~ 1) and the speed above which
#: they move (m/s).
ORACLE_OPACITY = 0.99
ORACLE_CLASS_LOGIT = 20.0
ORACLE_MOVING_MPS = 0.5
#: Lifted Gaussians' (the oracle's) Gaussian scale in pixel footprints (depth / focal).
ORACLE_SCALE = 0.3
#: Rendered pixels below this alpha count as sky in the semantic maps.
SKY_ALPHA = 0.5


@dataclass(frozen=True)
class Views:
    """N views to score, all at the model's size H x W, with their truth.

    Attributes:
        images: [N, H, W, 3] float32 RGB in [0, 1] (the truth image).
        world_from_camera: [N, 4, 4] float64 camera poses (OpenCV axes), world frame.
        intrinsics: [N, 3, 3] float32 pinhole matrices at H x W.
        time_s: [N] float64 capture times, seconds after the clip's origin.
        depth: [N, H, W] float32 truth z-depth, metres, 0 = none.
        semantic: [N, H, W] uint8 truth classes, 255 = unknown.
        flow: [N, H, W, 3] float32 world-frame surface velocity (m/s), or None when unknown.
        lidar_covered: [N, H, W] bool, the pixels the cache's LiDAR-derived depth covers
            (:func:`lidar_covered`), or None for views the cache has no depth for (shifted ones).
    """

    images: Tensor
    world_from_camera: Tensor
    intrinsics: Tensor
    time_s: Tensor
    depth: Tensor
    semantic: Tensor
    flow: Tensor | None = None
    lidar_covered: Tensor | None = None

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def size_hw(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])


@dataclass(frozen=True)
class Rendered:
    """A scene rendered into N views: ``rgb`` [N, H, W, 3] with the background composited, ``depth``
    [N, H, W] metres (0 where nothing), ``alpha`` [N, H, W], ``semantic`` [N, H, W] uint8 (argmax
    of the class probabilities, sky where alpha < 0.5) and ``entropy`` [N, H, W], nats, the entropy
    of each ray's depth distribution when the rasterizer reports one (else None); ``velocity``
    [N, H, W, 3] the Gaussians' world-frame velocity (m/s) blended as the depth is (0 where nothing),
    when the views carry a truth flow to score it against (else None)."""

    rgb: Tensor
    depth: Tensor
    alpha: Tensor
    semantic: Tensor
    entropy: Tensor | None = None
    velocity: Tensor | None = None


def render_views(scene: GaussianScene, views: Views, background: Tensor) -> Rendered:
    """Renders ``scene`` into every view at its own time, ``background`` [N, H, W, 3] (or [3])
    filling what the Gaussians leave uncovered."""
    h, w = views.size_hw
    n = len(views)
    if len(scene) == 0:
        bg = background.expand(n, h, w, 3).float()
        zeros = torch.zeros(n, h, w)
        velocity = None if views.flow is None else torch.zeros(n, h, w, 3)
        return Rendered(
            bg, zeros, zeros.clone(), torch.full((n, h, w), SKY, dtype=torch.uint8), velocity=velocity
        )
    out = scene.render(
        views.world_from_camera.float(),
        views.intrinsics.float(),
        w,
        h,
        views.time_s,
        semantics=True,
        motion=views.flow is not None,
        entropy=scene.depth_entropy is not None,
    )
    rgb = (out.rgb + (1 - out.alpha[..., None]) * background).clamp(0.0, 1.0)
    assert out.semantic_probs is not None
    labels = out.semantic_probs.argmax(-1).to(torch.uint8)
    labels = torch.where(out.alpha < SKY_ALPHA, torch.full_like(labels, SKY), labels)
    velocity = None
    if out.velocity is not None:  # premultiplied: the blend weights' average, as the depth is
        alpha = out.alpha[..., None]
        blended = out.velocity / alpha.clamp_min(1e-12)
        velocity = torch.where(alpha > 0, blended, torch.zeros_like(blended))
    return Rendered(
        rgb=rgb,
        depth=out.depth,
        alpha=out.alpha,
        semantic=labels,
        entropy=out.depth_entropy,
        velocity=velocity,
    )


def lift_views(views: Views, time_origin_micros: int = 0) -> GaussianScene:
    """One Gaussian per pixel of ``views`` with ``depth`` > 0: the pixel's colour, an isotropic
    scale of ``ORACLE_SCALE`` pixel footprints (``depth / focal``), opacity ``ORACLE_OPACITY``, its
    class (logit ``ORACLE_CLASS_LOGIT``; none where the class is unknown) and, where ``flow`` is
    faster than ``ORACLE_MOVING_MPS``, that velocity (the rest is static). With the truth depth
    this is ``phigenesis-eval stage1``'s oracle; with a cache's dense depth, a geometry Stage 2
    can be conditioned on.

    Pixels are unprojected with the pinhole ``intrinsics`` at their truth z-depth into the world
    frame at their view's capture time; velocities come from ``views.flow`` (static if None).
    """
    h, w = views.size_hw
    rays = pixel_rays(views.intrinsics.double(), h, w).permute(0, 2, 3, 1)  # [N, H, W, 3], z = 1
    depth = views.depth.double()
    keep = depth > 0
    pts_cam = rays * depth[..., None]
    rot = views.world_from_camera[:, None, None, :3, :3]
    means = (rot @ pts_cam[..., None])[..., 0] + views.world_from_camera[:, None, None, :3, 3]
    focal = 0.5 * (views.intrinsics[:, 0, 0] + views.intrinsics[:, 1, 1]).double()
    scale = ORACLE_SCALE * depth / focal[:, None, None]
    sem = views.semantic.long()
    known = sem < NUM_CLASSES
    logits = torch.zeros(*sem.shape, NUM_CLASSES)
    logits[known] = ORACLE_CLASS_LOGIT * torch.nn.functional.one_hot(sem[known], NUM_CLASSES).float()
    if views.flow is not None:
        velocity = views.flow.float()
        dynamic = velocity.norm(dim=-1) > ORACLE_MOVING_MPS
        velocity = velocity * dynamic[..., None]
    else:
        velocity = torch.zeros(*sem.shape, 3)
        dynamic = torch.zeros(sem.shape, dtype=torch.bool)
    n = int(keep.sum())
    times = views.time_s[:, None, None].expand(depth.shape)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return GaussianScene(
        means=means[keep].float(),
        quats=quats,
        scales=scale[keep].float()[:, None].expand(n, 3).contiguous(),
        opacities=torch.full((n,), ORACLE_OPACITY),
        colors=views.images[keep].float(),
        semantic_logits=logits[keep],
        velocity=velocity[keep],
        dynamic=dynamic[keep],
        time_s=times[keep].float(),
        time_origin_micros=time_origin_micros,
    )


def sky_background(views: Views) -> Tensor:
    """(3,) mean colour of the sky pixels of ``views`` (black when none is sky)."""
    sky = views.semantic == SKY
    if not sky.any():
        return torch.zeros(3)
    return views.images[sky].mean(0).float()
