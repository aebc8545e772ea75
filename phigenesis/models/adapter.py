"""Range-view adapter: per-pixel 4D Gaussian parameters from a frozen video VAE decoder's features.

The paper's Stage 1 (Generalist 4D Reconstruction): the decoder's multi-scale features of every view
are laid side by side as a range view (views in decreasing azimuth of their optical axes, so that
neighbouring cameras touch and convolutions see across the seams), fused feature-pyramid style
(1x1 lateral projections, top-down upsample-and-add, a 3x3 smoothing block per level), and two
convolution blocks at the finest level predict per pixel, with bounded activations:

======================  =====  =====================================================================
output                  ch.    activation
======================  =====  =====================================================================
depth                   1      regression head (``depth_bins = 0``): camera z in ``[near_m, far_m]``,
                               log-uniform: ``near (far/near)^sigmoid``; bins head: the residual
depth bins              K      bins head (``depth_bins = K > 0``): logits over K log-spaced bins
                               (:mod:`~phigenesis.models.depth_bins`); z = exp(expected log-depth
                               + residual), and the distribution's entropy is an output
opacity                 1      ``sigmoid(x + opacity_bias)``
scale                   3      ``min(0.6 * footprint * exp(clamp(x, -4, 4)), max_scale_m)``, where
                               the footprint ``z / f`` is the size of one pixel at that depth (m)
rotation                4      ``raw + (1, 0, 0, 0)``, normalised; in the camera frame
colour                  3      ``sigmoid(logit(input pixel) + x)``: a correction of the pixel's colour
semantic logits         K      none
motion                  3      ``max_speed_mps * tanh(x)``, camera axes (m/s)
dynamic                 1      logit of "this pixel moves"
======================  =====  =====================================================================

The finest fused map also sees the input pixel colours and the pixel rays (camera frame), which is
what lets a small adapter place depth: a ray's elevation says most of where the ground is.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from phigenesis.models.depth_bins import DepthBins

#: Channels of the head's outputs, in order (``semantic`` has ``num_classes``).
HEAD_CHANNELS = {"depth": 1, "opacity": 1, "scale": 3, "rotation": 4, "colour": 3, "motion": 3, "dynamic": 1}

#: Added to the dynamic logit: pixels start out static (p = 0.05), as most of a scene is.
DYNAMIC_BIAS = -3.0


@dataclass(frozen=True)
class AdapterConfig:
    """Sizes and bounds of a :class:`RangeViewAdapter`.

    Attributes:
        feature_channels: channels of the decoder's feature maps, coarse to fine.
        width: channels of the fused pyramid.
        num_classes: semantic classes (the unified taxonomy has 19).
        near_m, far_m: bounds of the predicted camera z-depth (metres).
        max_scale_m: cap of every Gaussian scale (metres).
        opacity_bias: added before the opacity sigmoid (2.0: opacities start near 0.88).
        max_speed_mps: bound of each velocity component (m/s).
        norm_groups: GroupNorm groups of the fusion blocks (must divide ``width``).
        depth_bins: 0 for the regression depth head (one channel; what checkpoints made before the
            bins head hold, so their configs, which lack this field, still load), or the number
            of log-spaced depth bins of the classification head.
    """

    feature_channels: tuple[int, ...] = (64, 32, 16)
    width: int = 32
    num_classes: int = 19
    near_m: float = 0.5
    far_m: float = 120.0
    max_scale_m: float = 2.0
    opacity_bias: float = 2.0
    max_speed_mps: float = 30.0
    norm_groups: int = 8
    depth_bins: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "feature_channels", tuple(int(c) for c in self.feature_channels))
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"AdapterConfig: need 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        if self.width % self.norm_groups:
            raise ValueError(
                f"AdapterConfig: width {self.width} does not divide by {self.norm_groups} groups"
            )
        if self.depth_bins < 0 or self.depth_bins == 1:
            raise ValueError(
                f"AdapterConfig: depth_bins must be 0 (regression) or >= 2, got {self.depth_bins}"
            )

    @property
    def out_channels(self) -> int:
        return sum(HEAD_CHANNELS.values()) + self.num_classes + self.depth_bins

    @property
    def bins(self) -> DepthBins | None:
        """The depth bins of the classification head (None for the regression head)."""
        return DepthBins(self.near_m, self.far_m, self.depth_bins) if self.depth_bins else None

    def to_dict(self) -> dict[str, object]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def _block(cin: int, cout: int, groups: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(groups, cout), nn.SiLU())


@dataclass(frozen=True)
class PixelGaussians:
    """Per-pixel predictions of :class:`RangeViewAdapter` for V views of H x W pixels (leading dims
    ``...`` as given, e.g. batch and frames), camera frame of each view."""

    depth: Tensor  # (..., V, H, W) camera z, metres
    opacity: Tensor  # (..., V, H, W) in (0, 1)
    scale: Tensor  # (..., V, H, W, 3) metres
    rotation: Tensor  # (..., V, H, W, 4) unit quaternion w, x, y, z, camera from Gaussian
    colour: Tensor  # (..., V, H, W, 3) RGB in (0, 1)
    semantic_logits: Tensor  # (..., V, H, W, K)
    velocity: Tensor  # (..., V, H, W, 3) camera axes, m/s
    dynamic_logit: Tensor  # (..., V, H, W)
    depth_logits: Tensor | None = None  # (..., V, H, W, K) bin logits (bins head only)
    depth_entropy: Tensor | None = None  # (..., V, H, W) nats, entropy of the bins (bins head only)


class RangeViewAdapter(nn.Module):
    """Feature-pyramid fusion over the range view and the per-pixel Gaussian heads (see module doc)."""

    def __init__(self, config: AdapterConfig):
        super().__init__()
        c = config
        self.config = c
        self.lateral = nn.ModuleList(nn.Conv2d(ch, c.width, 1) for ch in c.feature_channels)
        self.smooth = nn.ModuleList(_block(c.width, c.width, c.norm_groups) for _ in c.feature_channels)
        # Finest level: fused features + input RGB (3) + camera-frame ray (3).
        self.head = nn.Sequential(
            _block(c.width + 6, c.width, c.norm_groups), nn.Conv2d(c.width, c.out_channels, 3, padding=1)
        )
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def fuse(self, features: list[Tensor]) -> Tensor:
        """Top-down fusion of range-view feature maps ``[N, C_i, H_i, W_i]`` (coarse to fine) into
        ``[N, width, H, W]`` at the finest size."""
        if len(features) != len(self.lateral):
            raise ValueError(f"adapter expects {len(self.lateral)} feature levels, got {len(features)}")
        fused = None
        for feat, lateral, smooth in zip(features, self.lateral, self.smooth, strict=True):
            x = lateral(feat)
            if fused is not None:
                x = x + F.interpolate(fused, size=x.shape[-2:], mode="nearest")
            fused = smooth(x)
        assert fused is not None
        return fused

    def forward(
        self, features: list[Tensor], rgb: Tensor, rays_camera: Tensor, focal_px: Tensor
    ) -> PixelGaussians:
        """Per-pixel Gaussians of N range views.

        Args:
            features: decoder maps ``[N, V, C_i, H_i, W_i]`` per level, coarse to fine, views in
                range-view order (decreasing azimuth); the finest level is at the image size.
            rgb: ``[N, V, 3, H, W]`` input colours in [0, 1].
            rays_camera: ``[V, 3, H, W]`` pixel rays ``K^-1 (u, v, 1)`` (camera frame, z = 1).
            focal_px: ``[V]`` mean focal length in pixels (for the pixel footprint).
        """
        n, v = rgb.shape[:2]
        h, w = rgb.shape[-2:]

        def range_view(x: Tensor) -> Tensor:  # [N, V, C, h, w] -> [N, C, h, V * w]
            return x.permute(0, 2, 3, 1, 4).reshape(x.shape[0], x.shape[2], x.shape[3], -1)

        fused = self.fuse([range_view(f) for f in features])  # [N, width, H, V * W]
        rays = rays_camera.unsqueeze(0).expand(n, -1, -1, -1, -1)
        x = torch.cat([fused, range_view(rgb * 2 - 1), range_view(rays)], dim=1)
        out = self.head(x)  # [N, out, H, V * W]
        out = out.reshape(n, -1, h, v, w).permute(0, 3, 2, 4, 1)  # [N, V, H, W, out]
        return self._activate(out, rgb.permute(0, 1, 3, 4, 2), focal_px)

    def _activate(self, raw: Tensor, rgb: Tensor, focal_px: Tensor) -> PixelGaussians:
        c = self.config
        names = [*HEAD_CHANNELS, "semantic", "depth_bins"]
        sizes = [*HEAD_CHANNELS.values(), c.num_classes, c.depth_bins]
        parts = dict(zip(names, raw.split(sizes, dim=-1), strict=True))
        bins = c.bins
        logits = entropy = None
        # Zero-initialised head: depth starts at the geometric middle of the range (both heads).
        if bins is None:
            log_near, log_far = math.log(c.near_m), math.log(c.far_m)
            depth = torch.exp(log_near + torch.sigmoid(parts["depth"][..., 0]) * (log_far - log_near))
        else:
            logits = parts["depth_bins"]
            depth, entropy = bins.decode_logits(logits, parts["depth"][..., 0])
        footprint = depth / focal_px[:, None, None]  # metres per pixel at that depth
        scale = (0.6 * footprint[..., None] * torch.exp(parts["scale"].clamp(-4.0, 4.0))).clamp(
            max=c.max_scale_m
        )
        identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=raw.dtype, device=raw.device)
        rotation = F.normalize(parts["rotation"] + identity, dim=-1, eps=1e-6)
        colour = torch.sigmoid(torch.logit(rgb.clamp(0.01, 0.99)) + parts["colour"])
        return PixelGaussians(
            depth=depth,
            opacity=torch.sigmoid(parts["opacity"][..., 0] + c.opacity_bias),
            scale=scale,
            rotation=rotation,
            colour=colour,
            semantic_logits=parts["semantic"],
            velocity=c.max_speed_mps * torch.tanh(parts["motion"]),
            dynamic_logit=parts["dynamic"][..., 0] + DYNAMIC_BIAS,
            depth_logits=logits,
            depth_entropy=entropy,
        )
