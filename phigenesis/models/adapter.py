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
what lets a small adapter place depth: a ray's elevation says most of where the ground is. With
``ground_feature`` it also sees that elevation's consequence, the ground prior of :func:`ground_log_depth`:
``-log(-up . ray)``, which differs from the log z-depth where the ray meets a level ground by the
camera's log height alone. The head's last layer is linear, and bin logits linear in a scalar ``x``
(``2 c_k x - c_k^2``) peak at the bin of ``x``, so the ground's depth is one the head can express
exactly rather than approximate through the ray's nonlinear ``1 / elevation``.

With ``column_base`` (which needs ``ground_feature``) a gate predicts per pixel whether it is ground,
and :func:`column_base` carries the ground prior up each image column from the nearest ground pixel
below: for a level camera, every point of a vertical surface (a facade, a car's side, a trunk) has the
camera z of the ground where the surface stands, which is the ground pixel at the bottom of its
column. The head sees that carried prior too, so the depth of what stands on visible ground is also
one it can express exactly. The gate's logit is an output (``ground_logit``) so training can supervise
it with the ground classes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, get_args

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from phigenesis.models.depth_bins import DepthBins
from phigenesis.options import check_options, option

#: Channels of the head's outputs, in order (``semantic`` has ``num_classes``).
HEAD_CHANNELS = {"depth": 1, "opacity": 1, "scale": 3, "rotation": 4, "colour": 3, "motion": 3, "dynamic": 1}

#: Added to the dynamic logit: pixels start out static (p = 0.05), as most of a scene is.
DYNAMIC_BIAS = -3.0

#: The prior's bump on the bin logits (``prior_gain``): flat beyond this many bins from the prior.
PRIOR_BUMP_BINS = 8.0
#: The gain is ``softplus(raw - offset)``: 0.31 for the zero-initialised head, whose flat bin logits it
#: then dominates (an untrained head starts every pixel at its prior's depth).
PRIOR_GAIN_OFFSET = 1.0

#: Smallest downward ray component of :func:`ground_log_depth`: rays at or above the horizon (and
#: within 0.6 degrees below it) get the prior of a ground 100 camera heights away.
GROUND_MIN_DOWN = 0.01


#: Dilations of the context blocks (``AdapterConfig.context_blocks``), repeated in this order. A block
#: of dilation d sees 2 d cells further either way, so the four see 2 (1 + 2 + 4 + 8) = 30 cells of the
#: coarsest map either way: at ``vae_tiny``'s 4x, the whole height of a 48-row view and more than a
#: view's width on each side, across the range view's seams.
CONTEXT_DILATIONS = (1, 2, 4, 8)

#: Where :func:`column_base` starts below the bottom row: ``"far"``, the prior of the farthest ground
#: (what checkpoints made before the choice used), or ``"bottom_row"``, the bottom row's own prior.
ColumnFloor = Literal["far", "bottom_row"]
COLUMN_FLOORS: tuple[str, ...] = get_args(ColumnFloor)
#: Most feature levels the adapter fuses (a VAE has at most ``vae.MAX_LEVELS``).
MAX_FEATURE_LEVELS = 8


def column_base(prior: Tensor, gate: Tensor, floor: str = "far") -> Tensor:
    """(..., H, W) each pixel's ground prior carried up its column from the nearest ground below.

    ``prior`` (..., H, W) is :func:`ground_log_depth`'s map and ``gate`` (..., H, W) in [0, 1] the
    probability that a pixel is ground. Scanning up from the bottom row, ``b_i = g_i G_i + (1 - g_i)
    b_{i+1}``. With a hard gate, a ground pixel keeps its own prior and every other pixel takes that
    of the first ground pixel below it in its column. ``floor`` says what a column with no ground
    below a pixel gives it (the recurrence's start): ``"far"``, the prior of the farthest ground, or
    ``"bottom_row"``, the prior of the column's bottom pixel. Something that runs off the bottom of
    the image (a car beside the ego) stands on ground below the image, which is nearer than the
    bottom row's ground, so the bottom row's prior bounds its depth where "far" put it at 100 camera
    heights (docs/design/stage1.md, "The column's floor"; the measurements are in
    docs/experiments.md)."""
    if floor not in COLUMN_FLOORS:
        raise ValueError(f"column_base: floor must be one of {COLUMN_FLOORS}, got {floor!r}")
    if floor == "far":
        below = torch.full_like(prior[..., -1, :], -math.log(GROUND_MIN_DOWN))
    else:
        below = prior[..., -1, :]
    rows = []
    for i in range(prior.shape[-2] - 1, -1, -1):
        g = gate[..., i, :]
        below = g * prior[..., i, :] + (1.0 - g) * below
        rows.append(below)
    return torch.stack(rows[::-1], dim=-2)


def ground_log_depth(rays_camera: Tensor, up_camera: Tensor) -> Tensor:
    """Ground prior of each pixel: ``-log(max(-up . ray, GROUND_MIN_DOWN))``.

    ``rays_camera`` (..., 3, H, W) are pixel rays with camera z = 1 (``K^-1 (u, v, 1)``) and
    ``up_camera`` (..., 3) the world's up direction in each camera's frame (unit). A ray with
    ``up . ray < 0`` meets a level ground a height ``h`` below the camera at camera z
    ``h / (-up . ray)``, so there this prior plus ``log h`` is the ground's log z-depth exactly.
    Returns (..., 1, H, W)."""
    down = -(rays_camera * up_camera[..., :, None, None]).sum(-3, keepdim=True)
    return -torch.log(down.clamp(min=GROUND_MIN_DOWN))


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
        ground_feature: the head also sees each pixel's ground prior (:func:`ground_log_depth`);
            False in checkpoints made before it.
        column_base: the head also sees the ground prior carried up each column from the ground
            a gate finds (:func:`column_base`); needs ``ground_feature``.
        column_floor: what :func:`column_base` gives a pixel with no ground below it in its
            column: ``"far"`` (the farthest ground; checkpoints made before the choice lack the
            field and rebuild with it) or ``"bottom_row"`` (the bottom row's ground).
        context_blocks: residual blocks of dilated 3x3 convolutions (:class:`ContextBlock`) on the
            coarsest level before the top-down pass, which widen what each pixel's prediction sees
            (0 in checkpoints made before them).
        head_kernel: kernel size of the head's last convolution (odd): 3 in checkpoints made
            before the choice and in the registered configs; 1 reads only a pixel's own hidden
            features and priors (the block before it keeps the 3x3 context): faster steps,
            but worse renders at shifted views, so the registered configs keep 3
            (docs/experiments.md, "Stage 1").
        depth_head_kernel: kernel size of a last layer of the depth outputs' own (the residual,
            the bin logits and the prior gain), or None for one last layer of ``head_kernel``
            for every output (checkpoints made before the choice, and the registered configs).
            1 beside a 3x3 ``head_kernel`` reads depth per pixel and the splats' extent, opacity
            and colour from their neighbourhood: faster steps, depth level with one 3x3 layer,
            slightly worse photometry (docs/experiments.md, "Stage 1").
    """

    feature_channels: tuple[int, ...] = option((64, 32, 16), ge=1, le=8192, help="decoder widths")
    width: int = option(32, ge=1, le=8192, help="channels of the fused pyramid")
    num_classes: int = option(19, ge=1, le=1024, help="semantic classes")
    near_m: float = option(0.5, gt=0, le=1e5, help="nearest predicted depth (m)")
    far_m: float = option(120.0, gt=0, le=1e5, help="farthest predicted depth (m)")
    max_scale_m: float = option(2.0, gt=0, le=1e5, help="cap of every Gaussian scale (m)")
    opacity_bias: float = option(2.0, ge=-100, le=100, help="added before the opacity sigmoid")
    max_speed_mps: float = option(30.0, ge=0, le=1e4, help="bound of each velocity component (m/s)")
    norm_groups: int = option(8, ge=1, le=1024, help="GroupNorm groups")
    depth_bins: int = option(0, ge=0, le=4096, help="0: regression head; else log-spaced depth bins")
    ground_feature: bool = option(False, help="the head sees each pixel's ground prior")
    column_base: bool = option(False, help="the head sees the ground prior carried up each column")
    column_floor: ColumnFloor = option("far", help="column_base below the bottom row")
    context_blocks: int = option(0, ge=0, le=64, help="dilated residual blocks on the coarsest level")
    head_kernel: int = option(3, ge=1, le=31, help="kernel of the head's last convolution (odd)")
    depth_head_kernel: int | None = option(None, ge=1, le=31, help="kernel of the depth outputs' own layer")

    def __post_init__(self) -> None:
        check_options(self, "AdapterConfig")
        if self.column_base and not self.ground_feature:
            raise ValueError("AdapterConfig: column_base needs ground_feature")
        if not self.feature_channels or len(self.feature_channels) > MAX_FEATURE_LEVELS:
            raise ValueError(
                f"AdapterConfig: feature_channels must list 1 to {MAX_FEATURE_LEVELS} widths, "
                f"got {list(self.feature_channels)}"
            )
        if not self.near_m < self.far_m:
            raise ValueError(f"AdapterConfig: need 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        if self.width % self.norm_groups:
            raise ValueError(
                f"AdapterConfig: width {self.width} does not divide by {self.norm_groups} groups"
            )
        if self.head_kernel % 2 == 0:
            raise ValueError(f"AdapterConfig: head_kernel must be odd and >= 1, got {self.head_kernel}")
        if self.depth_head_kernel is not None and self.depth_head_kernel % 2 == 0:
            raise ValueError(
                "AdapterConfig: depth_head_kernel must be odd and >= 1 (or None), "
                f"got {self.depth_head_kernel}"
            )
        if self.depth_bins == 1:
            raise ValueError(
                f"AdapterConfig: depth_bins must be 0 (regression) or >= 2, got {self.depth_bins}"
            )

    @property
    def prior_gain(self) -> bool:
        """Whether the bins head has a ground prior to pull towards (:meth:`RangeViewAdapter._activate`)."""
        return self.ground_feature and self.depth_bins > 0

    @property
    def out_channels(self) -> int:
        return sum(HEAD_CHANNELS.values()) + self.num_classes + self.depth_bins + int(self.prior_gain)

    @property
    def depth_channels(self) -> int:
        """Channels of the depth outputs: the residual (or regression) channel, the bin logits and
        the prior gain."""
        return HEAD_CHANNELS["depth"] + self.depth_bins + int(self.prior_gain)

    @property
    def split_head(self) -> bool:
        """Whether the depth outputs have a last layer of their own (``depth_head_kernel``)."""
        return self.depth_head_kernel is not None and self.depth_head_kernel != self.head_kernel

    @property
    def bins(self) -> DepthBins | None:
        """The depth bins of the classification head (None for the regression head)."""
        return DepthBins(self.near_m, self.far_m, self.depth_bins) if self.depth_bins else None

    def to_dict(self) -> dict[str, object]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def _block(cin: int, cout: int, groups: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.GroupNorm(groups, cout), nn.SiLU())


class ContextBlock(nn.Module):
    """``x + conv(SiLU(GroupNorm(conv(x))))``: two 3x3 convolutions of one dilation (``width`` ->
    ``2 width`` -> ``width``), the second zero-initialised so the block starts as the identity and an
    adapter with context blocks starts where one without them does."""

    def __init__(self, width: int, dilation: int, groups: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(width, 2 * width, 3, padding=dilation, dilation=dilation),
            nn.GroupNorm(groups, 2 * width),
            nn.SiLU(),
            nn.Conv2d(2 * width, width, 3, padding=dilation, dilation=dilation),
        )
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


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
    ground_logit: Tensor | None = None  # (..., V, H, W) logit of "this pixel is ground" (column_base)


class RangeViewAdapter(nn.Module):
    """Feature-pyramid fusion over the range view and the per-pixel Gaussian heads (see module doc)."""

    def __init__(self, config: AdapterConfig):
        super().__init__()
        c = config
        self.config = c
        self.lateral = nn.ModuleList(nn.Conv2d(ch, c.width, 1) for ch in c.feature_channels)
        self.smooth = nn.ModuleList(_block(c.width, c.width, c.norm_groups) for _ in c.feature_channels)
        self.context = nn.Sequential(
            *(
                ContextBlock(c.width, CONTEXT_DILATIONS[i % len(CONTEXT_DILATIONS)], c.norm_groups)
                for i in range(c.context_blocks)
            )
        )
        # Finest level: fused features + input RGB (3) + camera-frame ray (3) [+ ground prior (1)]
        # [+ the prior carried up from the ground below (1), after a gate that finds the ground].
        inputs = c.width + 6 + int(c.ground_feature)
        if c.column_base:
            self.ground_gate = nn.Sequential(
                _block(inputs, c.width, c.norm_groups), nn.Conv2d(c.width, 1, 3, padding=1)
            )
        # The priors also skip the block (whose GroupNorm rescales them by each sample's statistics)
        # straight into the last layer, where bin logits linear in them can peak at their bins.
        priors = int(c.ground_feature) + int(c.column_base)
        rest = c.out_channels - c.depth_channels if c.split_head else c.out_channels
        self.head = nn.Sequential(
            _block(inputs + int(c.column_base), c.width, c.norm_groups),
            nn.Conv2d(c.width + priors, rest, c.head_kernel, padding=c.head_kernel // 2),
        )
        last = [self.head[-1]]
        if c.split_head:
            assert c.depth_head_kernel is not None
            k = c.depth_head_kernel
            self.depth_out = nn.Conv2d(c.width + priors, c.depth_channels, k, padding=k // 2)
            last.append(self.depth_out)
        if c.prior_gain:  # log of the camera height that turns the ground prior into a depth
            self.log_height_m = nn.Parameter(torch.tensor(math.log(2.0)))
        for layer in last:
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def fuse(self, features: list[Tensor]) -> Tensor:
        """Top-down fusion of range-view feature maps ``[N, C_i, H_i, W_i]`` (coarse to fine) into
        ``[N, width, H, W]`` at the finest size."""
        if len(features) != len(self.lateral):
            raise ValueError(f"adapter expects {len(self.lateral)} feature levels, got {len(features)}")
        fused = None
        for feat, lateral, smooth in zip(features, self.lateral, self.smooth, strict=True):
            x = lateral(feat)
            if fused is None:
                x = self.context(x)  # the coarsest level: where a wide view is cheap
            else:
                x = x + F.interpolate(fused, size=x.shape[-2:], mode="nearest")
            fused = smooth(x)
        assert fused is not None
        return fused

    def forward(
        self,
        features: list[Tensor],
        rgb: Tensor,
        rays_camera: Tensor,
        focal_px: Tensor,
        up_camera: Tensor | None = None,
    ) -> PixelGaussians:
        """Per-pixel Gaussians of N range views.

        Args:
            features: decoder maps ``[N, V, C_i, H_i, W_i]`` per level, coarse to fine, views in
                range-view order (decreasing azimuth); the finest level is at the image size.
            rgb: ``[N, V, 3, H, W]`` input colours in [0, 1].
            rays_camera: ``[V, 3, H, W]`` pixel rays ``K^-1 (u, v, 1)`` (camera frame, z = 1).
            focal_px: ``[V]`` mean focal length in pixels (for the pixel footprint).
            up_camera: ``[N, V, 3]`` the world's up direction in each view's camera frame; needed
                (only) with ``ground_feature``.
        """
        if self.config.ground_feature and up_camera is None:
            raise ValueError("this adapter has ground_feature: it needs up_camera")
        n, v = rgb.shape[:2]
        h, w = rgb.shape[-2:]

        def range_view(x: Tensor) -> Tensor:  # [N, V, C, h, w] -> [N, C, h, V * w]
            return x.permute(0, 2, 3, 1, 4).reshape(x.shape[0], x.shape[2], x.shape[3], -1)

        fused = self.fuse([range_view(f) for f in features])  # [N, width, H, V * W]
        rays = rays_camera.unsqueeze(0).expand(n, -1, -1, -1, -1)
        parts = [fused, range_view(rgb * 2 - 1), range_view(rays)]
        ground_logit = base = None
        priors: list[Tensor] = []  # the head's prior inputs, shifted to about [-1, 2.6]
        if self.config.ground_feature:
            assert up_camera is not None  # checked above
            prior = range_view(ground_log_depth(rays.to(up_camera.dtype), up_camera)).to(fused.dtype)
            base_rv = prior  # [N, 1, H, V * W]: what the bins are pulled towards
            priors.append(prior - 2.0)
            if self.config.column_base:
                gate = self.ground_gate(torch.cat(parts + priors, dim=1))  # [N, 1, H, V * W]
                base_rv = column_base(prior, torch.sigmoid(gate), self.config.column_floor)
                priors.append(base_rv - 2.0)
                ground_logit = gate.reshape(n, h, v, w).permute(0, 2, 1, 3)  # [N, V, H, W]
            base = base_rv.reshape(n, h, v, w).permute(0, 2, 1, 3)  # [N, V, H, W]
        hidden = self.head[0](torch.cat(parts + priors, dim=1))
        last_in = torch.cat([hidden, *priors], dim=1)
        out = self.head[1](last_in)  # [N, out, H, V * W]
        if self.config.split_head:  # back in HEAD_CHANNELS order: depth first, bins and gain last
            d = self.depth_out(last_in)
            out = torch.cat([d[:, :1], out, d[:, 1:]], dim=1)
        out = out.reshape(n, -1, h, v, w).permute(0, 3, 2, 4, 1)  # [N, V, H, W, out]
        px = self._activate(out, rgb.permute(0, 1, 3, 4, 2), focal_px, base)
        return px if ground_logit is None else dataclasses.replace(px, ground_logit=ground_logit)

    def _activate(
        self, raw: Tensor, rgb: Tensor, focal_px: Tensor, base: Tensor | None = None
    ) -> PixelGaussians:
        """Bounded Gaussians from the head's raw outputs (see the module docstring). ``base``
        [N, V, H, W] is the ground prior the bins may be pulled towards (``prior_gain``)."""
        c = self.config
        names = [*HEAD_CHANNELS, "semantic", "depth_bins", "prior_gain"]
        sizes = [*HEAD_CHANNELS.values(), c.num_classes, c.depth_bins, int(c.prior_gain)]
        parts = dict(zip(names, raw.split(sizes, dim=-1), strict=True))
        bins = c.bins
        logits = entropy = None
        # Zero-initialised head: depth starts at the geometric middle of the range (both heads).
        if bins is None:
            log_near, log_far = math.log(c.near_m), math.log(c.far_m)
            depth = torch.exp(log_near + torch.sigmoid(parts["depth"][..., 0]) * (log_far - log_near))
        else:
            logits = parts["depth_bins"]
            if c.prior_gain and base is not None:
                gain = F.softplus(parts["prior_gain"] - PRIOR_GAIN_OFFSET)  # >= 0, 0.31 untrained
                logits = logits + gain * self._prior_bump(bins, base)
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

    def _prior_bump(self, bins: DepthBins, base: Tensor) -> Tensor:
        """(..., K) ``-min(d, PRIOR_BUMP_BINS)^2 / 2`` of each bin's distance ``d`` (in bins) from the
        depth the ground prior ``base`` (...) gives, ``base + log_height_m`` in log metres. A pixel's
        gain (``softplus(prior_gain - PRIOR_GAIN_OFFSET)``, never negative) times this adds a bump about
        one bin wide at that depth to its logits, flat beyond ``PRIOR_BUMP_BINS``: one number per pixel
        says "the depth of the ground below me", which the bin logits alone would have to spell out."""
        target = base + self.log_height_m  # (...) log metres
        distance = (bins.log_centres(base.dtype, base.device) - target[..., None]) / bins.step
        return -0.5 * distance.clamp(-PRIOR_BUMP_BINS, PRIOR_BUMP_BINS) ** 2
