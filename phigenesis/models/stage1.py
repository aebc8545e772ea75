"""Stage 1 model: frozen video VAE + range-view adapter + sky model -> a 4D Gaussian scene.

``create_model("stage1_tiny")`` (CPU tests and the 30-minute CPU run) and ``"stage1_base"`` (GPUs).
The VAE is part of the model (its weights travel in Stage 1 checkpoints) but is frozen: only the
adapter and the sky model train (the paper's Stage 1).

Input (one batch of B clips, T frames, V views of H x W pixels):

- ``images`` [B, T, V, 3, H, W] RGB in [0, 1];
- ``intrinsics`` [B, V, 3, 3] pinhole matrices at H x W (pixel centres at integers);
- ``world_from_camera`` [B, T, V, 4, 4] each image's camera pose (OpenCV axes), world frame;
- ``time_s`` [B, T, V] each image's capture time, seconds after the scene's time origin.

:meth:`Stage1Model.forward` gives a :class:`Stage1Prediction` (per-pixel Gaussians in the world
frame, still differentiable); :meth:`Stage1Prediction.scene` turns one clip of it into a
:class:`~phigenesis.models.gaussians.GaussianScene`, leaving out sky and empty pixels, and
:meth:`Stage1Model.background` gives the sky colour behind every rendered pixel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from phigenesis import geometry
from phigenesis.models import register_model
from phigenesis.models.adapter import AdapterConfig, PixelGaussians, RangeViewAdapter
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.rasterizer import ALPHA_THRESHOLD
from phigenesis.models.vae import CONFIGS as VAE_CONFIGS
from phigenesis.models.vae import VideoVAE, VideoVAEConfig
from phigenesis.options import check_options, from_mapping, option
from phigenesis.taxonomy import NUM_CLASSES, SKY


@dataclass(frozen=True)
class Stage1Config:
    """A Stage 1 model: its VAE, its adapter and the sizes it runs at.

    Attributes:
        vae_name: registered VAE variant; ``vae`` holds its full config.
        vae: the VAE's config as plain values (``VideoVAEConfig.to_dict``).
        adapter: the adapter's config as plain values (``AdapterConfig``); its
            ``feature_channels`` follow the VAE's decoder.
        image_size: (H, W) the model runs at (pixels); divisible by the VAE's spatial compression.
        frames: input frames per clip (1 + a multiple of the VAE's temporal compression).
        sky_hidden: hidden width of the sky model (ray direction -> colour).
        dynamic_threshold: a Gaussian moves when its dynamic probability exceeds this.
    """

    vae_name: str = option("vae_tiny", help="registered VAE variant")
    vae: dict[str, Any] = option(factory=dict, help="the VAE's config (VideoVAEConfig fields)")
    adapter: dict[str, Any] = option(factory=dict, help="the adapter's config (AdapterConfig fields)")
    image_size: tuple[int, int] = option((48, 72), ge=1, le=8192, help="(H, W) in pixels")
    frames: int = option(1, ge=1, le=1024, help="input frames per clip")
    sky_hidden: int = option(32, ge=1, le=8192, help="hidden width of the sky model")
    dynamic_threshold: float = option(
        0.5, ge=0, le=1, help="dynamic probability above which a Gaussian moves"
    )

    def __post_init__(self) -> None:
        check_options(self, "Stage1Config")
        if self.vae_name not in VAE_CONFIGS:
            raise ValueError(f"Stage1Config: unknown VAE {self.vae_name!r}; known: {sorted(VAE_CONFIGS)}")
        vae = VAE_CONFIGS[self.vae_name].to_dict() | self.vae
        vae_cfg = from_mapping(VideoVAEConfig, vae, "Stage1Config.vae")
        object.__setattr__(self, "vae", vae_cfg.to_dict())
        adapter = {"feature_channels": list(reversed(vae_cfg.channels)), "num_classes": NUM_CLASSES}
        adapter_cfg = from_mapping(AdapterConfig, adapter | self.adapter, "Stage1Config.adapter")
        if list(adapter_cfg.feature_channels) != list(reversed(vae_cfg.channels)):
            raise ValueError(
                f"Stage1Config: adapter feature_channels {list(adapter_cfg.feature_channels)} do not match "
                f"the VAE decoder's {list(reversed(vae_cfg.channels))}"
            )
        object.__setattr__(self, "adapter", adapter_cfg.to_dict())
        s, r = vae_cfg.spatial_compression, vae_cfg.temporal_compression
        h, w = self.image_size
        if h % s or w % s:
            raise ValueError(f"Stage1Config: image_size {h}x{w} must divide by the VAE's compression {s}")
        if self.frames < 1 or (self.frames - 1) % r:
            raise ValueError(f"Stage1Config: frames={self.frames}; needs 1 + a multiple of {r}")

    @property
    def vae_config(self) -> VideoVAEConfig:
        return VideoVAEConfig.from_dict(self.vae)

    @property
    def adapter_config(self) -> AdapterConfig:
        return AdapterConfig(**self.adapter)

    def to_dict(self) -> dict[str, object]:
        values = dataclasses.asdict(self)
        values["image_size"] = list(self.image_size)
        return values

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> Stage1Config:
        return cls(**values)  # type: ignore[arg-type]


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of (..., 4) w, x, y, z quaternions (``a`` applied after ``b``)."""
    return torch.stack(geometry.quaternion_product_entries(a.unbind(-1), b.unbind(-1)), dim=-1)


def pixel_rays(intrinsics: Tensor, height: int, width: int) -> Tensor:
    """(..., 3, H, W) camera-frame rays ``K^-1 (u, v, 1)`` (z = 1) of every pixel centre."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=intrinsics.dtype, device=intrinsics.device),
        torch.arange(width, dtype=intrinsics.dtype, device=intrinsics.device),
        indexing="ij",
    )
    fx, fy = intrinsics[..., 0, 0, None, None], intrinsics[..., 1, 1, None, None]
    cx, cy = intrinsics[..., 0, 2, None, None], intrinsics[..., 1, 2, None, None]
    skew = intrinsics[..., 0, 1, None, None]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    return torch.stack([x, y, torch.ones_like(x)], dim=-3)


def range_view_order(world_from_camera: Tensor) -> Tensor:
    """(V,) view indices in decreasing azimuth of their optical axes (left to right), measured in
    view 0's camera frame: the order in which views sit side by side in the range view."""
    rot = world_from_camera[..., :3, :3].double()
    axes = rot[0].T @ rot[:, :, 2].T  # (3, V) optical axes in view 0's frame
    azimuth = torch.atan2(-axes[0], axes[2])  # left of view 0 is positive
    return torch.argsort(azimuth, descending=True, stable=True)


@dataclass(frozen=True)
class Stage1Prediction:
    """Per-pixel Gaussians of B clips in the world frame (differentiable), views in input order.

    ``pixels`` holds the camera-frame predictions with leading dims (B, T, V); the world-frame
    geometry is ``means`` [B, T, V, H, W, 3], ``quats`` [..., 4] and ``velocity`` [..., 3] (m/s,
    soft: scaled by the dynamic probability while training).
    """

    pixels: PixelGaussians
    means: Tensor
    quats: Tensor
    velocity: Tensor
    dynamic_prob: Tensor  # [B, T, V, H, W]
    time_s: Tensor  # [B, T, V]

    def default_keep(self, b: int) -> Tensor:
        """[T, V, H, W] bool: the pixels of clip ``b`` that spawn Gaussians by default (class not sky,
        opacity at least 1/255)."""
        p = self.pixels
        return (p.semantic_logits[b].argmax(-1) != SKY) & (p.opacity[b] >= ALPHA_THRESHOLD)

    def scene(
        self,
        b: int,
        keep: Tensor | None = None,
        hard: bool = True,
        dynamic_threshold: float = 0.5,
        time_origin_micros: int = 0,
    ) -> GaussianScene:
        """Clip ``b`` as a :class:`GaussianScene`.

        ``keep`` [T, V, H, W] bool picks the pixels that spawn Gaussians; by default every pixel
        whose predicted class is not sky and whose opacity reaches 1/255. ``hard``: a Gaussian is
        dynamic when its probability exceeds ``dynamic_threshold`` and only then moves (the
        inference rule); otherwise every velocity is scaled by the probability (training).
        """
        p = self.pixels
        logits = p.semantic_logits[b]
        if keep is None:
            keep = self.default_keep(b)
        prob = self.dynamic_prob[b]
        dynamic = prob > dynamic_threshold
        velocity = self.velocity[b] * (dynamic[..., None].to(prob.dtype) if hard else prob[..., None])
        time_s = self.time_s[b][:, :, None, None].expand_as(prob)
        return GaussianScene(
            means=self.means[b][keep],
            quats=self.quats[b][keep],
            scales=p.scale[b][keep],
            opacities=p.opacity[b][keep],
            colors=p.colour[b][keep],
            semantic_logits=logits[keep],
            velocity=velocity[keep],
            dynamic=dynamic[keep],
            time_s=time_s[keep],
            time_origin_micros=time_origin_micros,
            depth_entropy=None if p.depth_entropy is None else p.depth_entropy[b][keep],
        )


class Stage1Model(nn.Module):
    """Frozen video VAE + range-view adapter + sky model (see the module docstring)."""

    def __init__(self, config: Stage1Config, name: str = "stage1"):
        super().__init__()
        self.name = name
        self.config = config
        self.vae = VideoVAE(config.vae_config, name=config.vae_name).freeze()
        self.adapter = RangeViewAdapter(config.adapter_config)
        self.sky = nn.Sequential(
            nn.Linear(3, config.sky_hidden), nn.SiLU(), nn.Linear(config.sky_hidden, 3), nn.Sigmoid()
        )

    def trainable_parameters(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def load_vae(self, vae: VideoVAE) -> None:
        """Takes the weights of a trained VAE (same config) and freezes them."""
        if vae.config != self.vae.config:
            diff = [k for k, v in vae.config.to_dict().items() if self.vae.config.to_dict()[k] != v]
            raise ValueError(f"the VAE's config differs from this model's in {diff}")
        self.vae.load_state_dict(vae.state_dict())
        self.vae.freeze()

    def background(self, world_from_camera: Tensor, intrinsics: Tensor, height: int, width: int) -> Tensor:
        """(..., H, W, 3) sky colour seen through every pixel of cameras (..., 4, 4) / (..., 3, 3)."""
        rays = pixel_rays(intrinsics, height, width)  # (..., 3, H, W)
        dirs = torch.einsum("...ij,...jhw->...hwi", world_from_camera[..., :3, :3].to(rays.dtype), rays)
        return self.sky(F.normalize(dirs, dim=-1).float())

    def encode(self, images: Tensor) -> Tensor:
        """The frozen VAE's latents (the posterior's mode) of [B, T, V, 3, H, W] images in [0, 1],
        as [B, V, C_z, T_z, H_z, W_z]: what :meth:`forward_latents` takes."""
        b, t, v = images.shape[:3]
        video = (images * 2 - 1).permute(0, 2, 3, 1, 4, 5).reshape(b * v, 3, t, *images.shape[-2:])
        with torch.no_grad():
            latents = self.vae.encode(video).mode()
        return latents.reshape(b, v, *latents.shape[1:])

    def decode(self, latents: Tensor) -> Tensor:
        """[B, T, V, 3, H, W] images in [0, 1] that the frozen VAE decodes from [B, V, C_z, T_z,
        H_z, W_z] latents (T frames: 1 + (T_z - 1) x the VAE's temporal compression)."""
        return self._decoded(latents)[0]

    def features(self, images: Tensor) -> list[Tensor]:
        """The frozen decoder's multi-scale features of [B, T, V, 3, H, W] images, each level as
        [B, T, V, C_i, H_i, W_i] (coarse levels repeated over the frames they cover)."""
        return self._decoded(self.encode(images))[1]

    def latent_frames(self, latents: Tensor) -> int:
        """Frames of the clip that [B, V, C_z, T_z, H_z, W_z] latents decode to (causal VAE)."""
        return 1 + (int(latents.shape[3]) - 1) * self.vae.config.temporal_compression

    def _decoded(self, latents: Tensor) -> tuple[Tensor, list[Tensor]]:
        """(:meth:`decode`, :meth:`features`) of [B, V, C_z, T_z, H_z, W_z] latents, from one
        pass of the frozen decoder."""
        b, v = latents.shape[:2]
        t = self.latent_frames(latents)
        with torch.no_grad():
            video, feats = self.vae.decode_with_features(latents.flatten(0, 1))  # video in [-1, 1]
        video = ((video + 1) / 2).clamp(0.0, 1.0)
        images = video.reshape(b, v, *video.shape[1:]).permute(0, 3, 1, 2, 4, 5)
        out = []
        for f in feats:
            t_i = f.shape[2]
            # Causal VAE: latent frame 0 is frame 0 alone, latent j covers the r frames ending at j * r.
            r = max((t - 1) // max(t_i - 1, 1), 1)
            index = torch.div(torch.arange(t) + r - 1, r, rounding_mode="floor").clamp(max=t_i - 1)
            f = f[:, :, index]  # [B*V, C, T, h, w]
            out.append(f.reshape(b, v, *f.shape[1:]).permute(0, 3, 1, 2, 4, 5))
        return images, out

    def forward(
        self,
        images: Tensor,
        intrinsics: Tensor,
        world_from_camera: Tensor,
        time_s: Tensor,
        features: list[Tensor] | None = None,
    ) -> Stage1Prediction:
        """Per-pixel Gaussians of [B, T, V, 3, H, W] images: :meth:`forward_latents` of their
        latents (:meth:`encode`), with the images themselves as the pixel colours. ``features``:
        the frozen VAE's :meth:`features` of these images when the caller has them already
        (training keeps them per clip), which skips the VAE; the result is the same."""
        if features is None:
            return self.forward_latents(self.encode(images), intrinsics, world_from_camera, time_s, images)
        b, t, v = images.shape[:3]
        if any(tuple(f.shape[:3]) != (b, t, v) for f in features):
            raise ValueError(
                f"features {[tuple(f.shape) for f in features]} do not match images {tuple(images.shape)}"
            )
        return self._gaussians(features, images, intrinsics, world_from_camera, time_s)

    def forward_latents(
        self,
        latents: Tensor,
        intrinsics: Tensor,
        world_from_camera: Tensor,
        time_s: Tensor,
        images: Tensor | None = None,
    ) -> Stage1Prediction:
        """Per-pixel Gaussians of clips given as VAE latents [B, V, C_z, T_z, H_z, W_z] (what
        Stage 2 generates): the decoder's features of the latents feed the adapter, and the pixel
        colours it corrects are ``images`` [B, T, V, 3, H, W] when given, else the VAE's decoding
        of the latents (:meth:`decode`). ``intrinsics`` [B, V, 3, 3], ``world_from_camera``
        [B, T, V, 4, 4] and ``time_s`` [B, T, V] as for :meth:`forward`, which is this method on
        the latents of its images."""
        decoded, latent_feats = self._decoded(latents)
        if images is None:
            images = decoded
        t = images.shape[1]
        if t != self.latent_frames(latents) or images.shape[:3:2] != latents.shape[:2]:
            raise ValueError(
                f"images {tuple(images.shape)} do not match latents {tuple(latents.shape)} "
                f"({self.latent_frames(latents)} frames, [B, V] = {list(latents.shape[:2])})"
            )
        return self._gaussians(latent_feats, images, intrinsics, world_from_camera, time_s)

    def _gaussians(
        self,
        latent_feats: list[Tensor],
        images: Tensor,
        intrinsics: Tensor,
        world_from_camera: Tensor,
        time_s: Tensor,
    ) -> Stage1Prediction:
        """The adapter's Gaussians from the decoder's features (as :meth:`features` gives them) and
        the pixel colours ``images`` [B, T, V, 3, H, W]."""
        b, t, _, _, h, w = images.shape
        if (h, w) != tuple(self.config.image_size):
            raise ValueError(f"Stage 1 model runs at {self.config.image_size}, got images of {h}x{w}")
        order = range_view_order(world_from_camera[0, 0])
        inverse = torch.argsort(order)
        feats = [f[:, :, order].flatten(0, 1) for f in latent_feats]  # [B*T, V, C, h, w]
        k = intrinsics[:, order]  # [B, V, 3, 3]
        rays = pixel_rays(k[0], h, w)  # [V, 3, H, W]; the rig is the same over the batch
        focal = 0.5 * (k[0, :, 0, 0] + k[0, :, 1, 1])
        # The world's up (+z) in every camera's frame: the third row of camera-to-world rotation.
        up = world_from_camera[:, :, order, 2, :3].flatten(0, 1).to(rays.dtype)  # [B*T, V, 3]
        px = self.adapter(feats, images[:, :, order].flatten(0, 1), rays, focal, up)

        def restore(x: Tensor) -> Tensor:  # [B*T, V', ...] in range order -> [B, T, V, ...] input order
            return x.reshape(b, t, *x.shape[1:])[:, :, inverse]

        px = PixelGaussians(
            **{
                f.name: None if (x := getattr(px, f.name)) is None else restore(x)
                for f in dataclasses.fields(px)
            }
        )
        rays_in = pixel_rays(intrinsics, h, w).permute(0, 1, 3, 4, 2)  # [B, V, H, W, 3]
        pts_cam = rays_in[:, None] * px.depth[..., None]  # [B, T, V, H, W, 3]
        rot = world_from_camera[..., :3, :3].to(pts_cam.dtype)[:, :, :, None, None]  # [B, T, V, 1, 1, 3, 3]
        trans = world_from_camera[..., :3, 3].to(pts_cam.dtype)[:, :, :, None, None]
        means = (rot @ pts_cam[..., None])[..., 0] + trans
        q_cam = torch.as_tensor(
            geometry.matrix_to_quaternion(world_from_camera[..., :3, :3].detach().cpu().double().numpy()),
            dtype=pts_cam.dtype,
            device=pts_cam.device,
        )[:, :, :, None, None]
        quats = quaternion_multiply(q_cam.expand_as(px.rotation), px.rotation)
        velocity = (rot @ px.velocity[..., None])[..., 0]
        return Stage1Prediction(
            pixels=px,
            means=means,
            quats=quats,
            velocity=velocity,
            dynamic_prob=torch.sigmoid(px.dynamic_logit),
            time_s=time_s.to(pts_cam.dtype),
        )

    @torch.no_grad()
    def predict(
        self,
        images: Tensor,
        intrinsics: Tensor,
        world_from_camera: Tensor,
        time_s: Tensor,
        time_origin_micros: int = 0,
    ) -> GaussianScene:
        """The Gaussian scene of one clip (batch of 1), by the inference rules of
        :meth:`Stage1Prediction.scene`."""
        was = self.training
        self.eval()
        try:
            pred = self(images, intrinsics, world_from_camera, time_s)
            return pred.scene(
                0, dynamic_threshold=self.config.dynamic_threshold, time_origin_micros=time_origin_micros
            )
        finally:
            self.train(was)

    def num_parameters(self, trainable: bool = True) -> int:
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable)


CONFIGS = {
    # CPU: vae_tiny (4x spatial, 4x temporal), 32-wide pyramid with four context blocks on its coarsest
    # level, 64 depth bins, the ground prior carried up the columns, single frames at 48 x 72.
    "stage1_tiny": Stage1Config(
        vae_name="vae_tiny",
        adapter={
            "width": 32,
            "depth_bins": 64,
            "ground_feature": True,
            "column_base": True,
            "column_floor": "bottom_row",
            "context_blocks": 4,
        },
        image_size=(48, 72),
        frames=1,
    ),
    # GPUs: vae_base (8x spatial, 4x temporal), 128-wide pyramid with four context blocks, 200 depth bins
    # (DrivingRecon's), the ground prior, 5-frame clips at 160 x 240 (STORM's size).
    "stage1_base": Stage1Config(
        vae_name="vae_base",
        adapter={
            "width": 128,
            "norm_groups": 32,
            "depth_bins": 200,
            "ground_feature": True,
            "column_base": True,
            "column_floor": "bottom_row",
            "context_blocks": 4,
        },
        image_size=(160, 240),
        frames=5,
    ),
}


def _create(name: str, **overrides: object) -> Stage1Model:
    return Stage1Model(dataclasses.replace(CONFIGS[name], **overrides), name=name)  # type: ignore[arg-type]


@register_model
def stage1_tiny(**overrides: object) -> Stage1Model:
    """Stage 1 model for CPUs (tiny VAE and adapter, 48 x 72 views)."""
    return _create("stage1_tiny", **overrides)


@register_model
def stage1_base(**overrides: object) -> Stage1Model:
    """Stage 1 model for GPUs (base VAE, 160 x 240 views, 5-frame clips)."""
    return _create("stage1_base", **overrides)
