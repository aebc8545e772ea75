"""A small causal 3D-convolution video VAE (in the spirit of HunyuanVideo's), written for this toolkit.

Layout (timm-style): blocks, model, init, config table, registered variants.

Stage 1 of the paper feeds videos of every camera through a *frozen* video VAE and hands the
decoder's multi-scale features to the range-view adapter; stage 2 diffuses in its latent space.
This module is the VAE the toolkit trains itself (a pretrained one may be plugged in later).

- **Causal in time.** Every 3D convolution pads time on the past side only (with copies of the
  first frame), and normalisation is per frame (GroupNorm over ``C, H, W`` of each frame), so an
  output at frame t never depends on input frames after t.
- **The first frame is encoded alone**, as an image VAE would: each temporal downsampling is a
  causal convolution with kernel 3 and stride 2 over the first-frame-padded sequence, which maps
  ``T`` frames to ``1 + (T - 1) / 2``; two of them give ``T_lat = 1 + (T - 1) / 4`` and ``T = 1``
  (an image) gives one latent frame. Temporal upsampling in the decoder is the inverse: latent
  frame 0 gives frame 0, every later latent frame gives two frames (nearest), then a causal
  convolution. So with temporal compression 4, latent frame k summarises input frames
  ``4k - 3 .. 4k`` (frame 0 alone for k = 0) and sees nothing after ``4k``; decoded frames
  ``<= 4k`` depend only on latent frames ``<= k``.
- **Spatial compression** ``2 ** (len(channels) - 1)``: 8x for ``vae_base``, 4x for ``vae_tiny``.
- **Latent**: a diagonal Gaussian with ``latent_channels`` channels; log-variance clamped to
  ``[logvar_min, logvar_max]``; reparameterised samples; KL to the standard normal prior.

Symbols: B videos, 3 colour channels, T frames, H x W pixels; latent ``[B, C_lat, T_lat, h, w]``
with ``T_lat = 1 + (T - 1) / temporal_compression`` and ``h = H / spatial_compression``.
Inputs are RGB in [-1, 1]; ``T - 1`` must divide by the temporal compression and ``H``, ``W`` by the
spatial one.

Variants (``phigenesis.models.vae`` must be imported to register them): ``vae_tiny`` (CPU tests,
4x spatial, 4x temporal, 4 latent channels) and ``vae_base`` (GPUs, 8x spatial, 4x temporal, 16
latent channels, like HunyuanVideo's VAE).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from phigenesis.models import register_model
from phigenesis.options import check_options, option

# --------------------------------------------------------------------------------------------
# Blocks


class CausalConv3d(nn.Module):
    """3D convolution padded in time on the past side only (replicating the first frame).

    ``[B, C_in, T, H, W] -> [B, C_out, T', H', W']`` with ``T' = (T - 1) // s_t + 1`` and
    ``H' = (H - 1) // s + 1`` for kernel 3 (odd spatial kernels are zero-padded by ``k // 2``).
    Output frame j sees input frames ``j * s_t - (k_t - 1) .. j * s_t`` only.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int | tuple[int, int, int] = 3,
        stride: int | tuple[int, int, int] = 1,
    ):
        super().__init__()
        kt, kh, kw = (kernel,) * 3 if isinstance(kernel, int) else kernel
        self.time_pad = kt - 1
        self.conv = nn.Conv3d(
            in_channels, out_channels, (kt, kh, kw), stride=stride, padding=(0, kh // 2, kw // 2)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.time_pad:
            first = x[:, :, :1].expand(-1, -1, self.time_pad, -1, -1)  # [B, C, k_t - 1, H, W]
            x = torch.cat([first, x], dim=2)
        return self.conv(x)


class FrameGroupNorm(nn.GroupNorm):
    """GroupNorm over ``C, H, W`` of each frame separately (statistics never cross frames)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, t, h, w = x.shape
        y = super().forward(x.transpose(1, 2).reshape(b * t, c, h, w))  # [B*T, C, H, W]
        return y.reshape(b, t, c, h, w).transpose(1, 2)


class ResBlock3d(nn.Module):
    """Pre-activation residual block: (norm, SiLU, causal conv) twice, plus a 1x1x1 skip if needed."""

    def __init__(self, in_channels: int, out_channels: int, groups: int):
        super().__init__()
        self.norm1 = FrameGroupNorm(groups, in_channels)
        self.conv1 = CausalConv3d(in_channels, out_channels)
        self.norm2 = FrameGroupNorm(groups, out_channels)
        self.conv2 = CausalConv3d(out_channels, out_channels)
        self.skip = nn.Conv3d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class Downsample3d(nn.Module):
    """Halves H and W, and (if ``temporal``) maps T frames to ``1 + (T - 1) / 2`` causally."""

    def __init__(self, channels: int, temporal: bool):
        super().__init__()
        self.conv = CausalConv3d(channels, channels, 3, stride=(2 if temporal else 1, 2, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class Upsample3d(nn.Module):
    """Doubles H and W (nearest), and (if ``temporal``) maps n frames to ``1 + 2 (n - 1)``: frame 0
    stays one frame, each later frame is repeated twice; then a causal 3x3x3 convolution."""

    def __init__(self, channels: int, temporal: bool):
        super().__init__()
        self.temporal = temporal
        self.conv = CausalConv3d(channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.temporal and x.shape[2] > 1:
            x = torch.cat([x[:, :, :1], x[:, :, 1:].repeat_interleave(2, dim=2)], dim=2)
        x = F.interpolate(x, scale_factor=(1.0, 2.0, 2.0), mode="nearest")  # [B, C, T, 2H, 2W]
        return self.conv(x)


class Encoder(nn.Module):
    """Video ``[B, 3, T, H, W]`` -> moments ``[B, 2 * C_lat, T_lat, h, w]`` (mean, log-variance)."""

    def __init__(self, c: VideoVAEConfig):
        super().__init__()
        ch = c.channels
        self.conv_in = CausalConv3d(c.in_channels, ch[0])
        stages = []
        for i, width in enumerate(ch):
            blocks: list[nn.Module] = [
                ResBlock3d(ch[i - 1] if (i > 0 and j == 0) else width, width, c.norm_groups)
                for j in range(c.num_res_blocks)
            ]
            if i < len(ch) - 1:
                blocks.append(Downsample3d(width, c.temporal_downsample[i]))
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.ModuleList(stages)
        self.mid = ResBlock3d(ch[-1], ch[-1], c.norm_groups)
        self.norm_out = FrameGroupNorm(c.norm_groups, ch[-1])
        self.conv_out = CausalConv3d(ch[-1], 2 * c.latent_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv_in(x)
        for stage in self.stages:
            x = stage(x)
        x = self.mid(x)
        return self.conv_out(F.silu(self.norm_out(x)))


class Decoder(nn.Module):
    """Latent ``[B, C_lat, T_lat, h, w]`` -> video ``[B, 3, T, H, W]`` and the per-stage features."""

    def __init__(self, c: VideoVAEConfig):
        super().__init__()
        ch = tuple(reversed(c.channels))  # coarse to fine
        temporal = tuple(reversed(c.temporal_downsample))
        self.conv_in = CausalConv3d(c.latent_channels, ch[0])
        self.mid = ResBlock3d(ch[0], ch[0], c.norm_groups)
        stages, ups = [], []
        for i, width in enumerate(ch):
            stages.append(
                nn.Sequential(
                    *[
                        ResBlock3d(ch[i - 1] if (i > 0 and j == 0) else width, width, c.norm_groups)
                        for j in range(c.num_res_blocks)
                    ]
                )
            )
            ups.append(Upsample3d(width, temporal[i]) if i < len(ch) - 1 else nn.Identity())
        self.stages = nn.ModuleList(stages)
        self.ups = nn.ModuleList(ups)
        self.norm_out = FrameGroupNorm(c.norm_groups, ch[-1])
        self.conv_out = CausalConv3d(ch[-1], c.in_channels)

    def forward(self, z: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        x = self.mid(self.conv_in(z))
        features = []
        for stage, up in zip(self.stages, self.ups, strict=True):
            x = stage(x)
            features.append(x)
            x = up(x)
        return self.conv_out(F.silu(self.norm_out(x))), features


class DiagonalGaussian:
    """The posterior ``N(mean, exp(logvar))`` per latent element, ``[B, C_lat, T_lat, h, w]`` each."""

    def __init__(self, mean: torch.Tensor, logvar: torch.Tensor):
        assert mean.shape == logvar.shape, (mean.shape, logvar.shape)
        self.mean = mean
        self.logvar = logvar

    @property
    def std(self) -> torch.Tensor:
        return torch.exp(0.5 * self.logvar)

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """A reparameterised sample ``mean + std * eps`` (differentiable in mean and logvar)."""
        eps = torch.randn(
            self.mean.shape, generator=generator, device=self.mean.device, dtype=self.mean.dtype
        )
        return self.mean + self.std * eps

    def mode(self) -> torch.Tensor:
        return self.mean

    def kl(self) -> torch.Tensor:
        """``KL(posterior || N(0, I))`` in nats, summed over each video's latent elements: ``[B]``."""
        kl = 0.5 * (self.mean.square() + self.logvar.exp() - 1.0 - self.logvar)  # [B, C, T, h, w]
        return kl.flatten(1).sum(dim=1)


class VAEOutput(NamedTuple):
    """What :meth:`VideoVAE.forward` returns."""

    reconstruction: torch.Tensor  # [B, 3, T, H, W], RGB (unbounded; the data lie in [-1, 1])
    posterior: DiagonalGaussian  # over [B, C_lat, T_lat, h, w]
    kl: torch.Tensor  # [B] KL to the prior in nats, summed over latent elements


# --------------------------------------------------------------------------------------------
# Model


#: Most resolution levels a VAE has (a spatial compression of at most 2 ** (MAX_LEVELS - 1)).
MAX_LEVELS = 8


@dataclass(frozen=True)
class VideoVAEConfig:
    """Sizes of a causal video VAE.

    Attributes:
        in_channels: colour channels of the video (RGB: 3).
        latent_channels: C_lat, channels of the latent.
        channels: encoder widths per resolution level, fine to coarse (the decoder mirrors them);
            spatial compression is ``2 ** (len(channels) - 1)``.
        temporal_downsample: per level transition (``len(channels) - 1`` entries), whether time is
            compressed 2x there (first frame kept alone).
        num_res_blocks: residual blocks per level, in the encoder and the decoder.
        norm_groups: GroupNorm groups (must divide every width).
        logvar_min: lower clamp of the posterior log-variance (nats).
        logvar_max: upper clamp of the posterior log-variance (nats).
    """

    in_channels: int = option(3, ge=1, le=64, help="colour channels of the video")
    latent_channels: int = option(16, ge=1, le=1024, help="channels of the latent")
    channels: tuple[int, ...] = option((64, 128, 256, 256), ge=1, le=8192, help="widths per level")
    temporal_downsample: tuple[bool, ...] = option((True, True, False), help="time halved per transition")
    num_res_blocks: int = option(2, ge=1, le=64, help="residual blocks per level")
    norm_groups: int = option(32, ge=1, le=1024, help="GroupNorm groups")
    logvar_min: float = option(-30.0, ge=-100, le=100, help="lower clamp of the log-variance (nats)")
    logvar_max: float = option(20.0, ge=-100, le=100, help="upper clamp of the log-variance (nats)")

    def __post_init__(self) -> None:
        check_options(self, "VideoVAEConfig")
        if not 1 <= len(self.channels) <= MAX_LEVELS:
            raise ValueError(
                f"VideoVAEConfig: channels must list 1 to {MAX_LEVELS} widths, got {list(self.channels)}"
            )
        if len(self.temporal_downsample) != len(self.channels) - 1:
            raise ValueError(
                f"VideoVAEConfig: temporal_downsample needs {len(self.channels) - 1} entries "
                f"(one per level transition), got {self.temporal_downsample}"
            )
        bad = [w for w in self.channels if w % self.norm_groups]
        if bad:
            raise ValueError(f"VideoVAEConfig: widths {bad} do not divide by norm_groups={self.norm_groups}")
        if self.logvar_min >= self.logvar_max:
            raise ValueError(
                f"VideoVAEConfig: logvar_min {self.logvar_min} must be below logvar_max {self.logvar_max}"
            )

    @property
    def spatial_compression(self) -> int:
        return 2 ** (len(self.channels) - 1)

    @property
    def temporal_compression(self) -> int:
        return 2 ** sum(self.temporal_downsample)

    def to_dict(self) -> dict[str, object]:
        """Plain values (tuples as lists), as stored in checkpoints."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> VideoVAEConfig:
        return cls(**values)  # type: ignore[arg-type]


class VideoVAE(nn.Module):
    """Causal 3D-convolution video VAE (see the module docstring).

    Exposes ``name``, ``config``, ``forward`` and ``predict`` like every model of
    :mod:`phigenesis.models`, plus ``encode``, ``decode``, ``decode_features`` and ``freeze``.

    Example::

        vae = create_model("vae_tiny")
        out = vae(video)                      # video [B, 3, 9, 64, 64] in [-1, 1]
        loss = vae_loss(out, video, beta=1e-6)
        feats = vae.freeze().decode_features(vae.encode(video).mode())
    """

    def __init__(self, config: VideoVAEConfig, name: str = "vae"):
        super().__init__()
        self.name = name
        self.config = config
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)
        self.frozen = False
        self.apply(_init_weights)

    def _check_video(self, x: torch.Tensor) -> None:
        c = self.config
        assert x.ndim == 5 and x.shape[1] == c.in_channels, x.shape
        t, h, w = x.shape[2:]
        s, r = c.spatial_compression, c.temporal_compression
        assert (t - 1) % r == 0 and h % s == 0 and w % s == 0, (
            f"video {tuple(x.shape)}: T - 1 must divide by {r}, H and W by {s}"
        )

    def encode(self, x: torch.Tensor) -> DiagonalGaussian:
        """Posterior over ``[B, C_lat, 1 + (T - 1) / r, H / s, W / s]`` of video ``[B, 3, T, H, W]``.

        ``x``: RGB in [-1, 1]; r and s are the temporal and spatial compressions.
        """
        self._check_video(x)
        moments = self.encoder(x)  # [B, 2 * C_lat, T_lat, h, w]
        mean, logvar = moments.chunk(2, dim=1)
        return DiagonalGaussian(mean, logvar.clamp(self.config.logvar_min, self.config.logvar_max))

    def _check_latent(self, z: torch.Tensor) -> None:
        assert z.ndim == 5 and z.shape[1] == self.config.latent_channels, z.shape

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Video ``[B, 3, 1 + (T_lat - 1) * r, h * s, w * s]`` of latent ``[B, C_lat, T_lat, h, w]``."""
        self._check_latent(z)
        return self.decoder(z)[0]

    def decode_features(self, z: torch.Tensor) -> list[torch.Tensor]:
        """The decoder's multi-scale features of latent ``[B, C_lat, T_lat, h, w]``, coarse to fine.

        One map per level, the output of that level's residual blocks (before upsampling):
        ``[B, C_i, T_i, H_i, W_i]`` with ``C_i = channels[-1 - i]``, ``H_i = h * 2**i`` and ``T_i``
        the frame count after the temporal upsamplings so far (``T_0 = T_lat``; the last map has the
        output's T, H and W). These feed the range-view adapter.
        """
        return self.decode_with_features(z)[1]

    def decode_with_features(self, z: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """(:meth:`decode`, :meth:`decode_features`) of ``z`` from one pass of the decoder."""
        self._check_latent(z)
        video, features = self.decoder(z)
        return video, features

    def forward(
        self, x: torch.Tensor, sample_posterior: bool = True, generator: torch.Generator | None = None
    ) -> VAEOutput:
        """Encodes, samples (or takes the mean if ``sample_posterior`` is false) and decodes ``x``."""
        posterior = self.encode(x)
        z = posterior.sample(generator) if sample_posterior else posterior.mode()
        return VAEOutput(self.decode(z), posterior, posterior.kl())

    @torch.no_grad()
    def predict(self, x: torch.Tensor) -> torch.Tensor:
        """Reconstruction (posterior mean decoded) of ``[B, 3, T, H, W]`` in [-1, 1], in eval mode."""
        was_training = self.training
        self.eval()
        try:
            return self.decode(self.encode(x).mode())
        finally:
            self.train(was_training)

    def freeze(self) -> VideoVAE:
        """Makes every parameter non-trainable and keeps the model in eval mode from now on."""
        for p in self.parameters():
            p.requires_grad_(False)
        self.frozen = True
        return self.eval()

    def train(self, mode: bool = True) -> VideoVAE:
        return super().train(mode and not getattr(self, "frozen", False))

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# --------------------------------------------------------------------------------------------
# Loss


def vae_loss(
    output: VAEOutput,
    target: torch.Tensor,
    beta: float = 1e-6,
    reconstruction: Literal["l1", "l2"] = "l1",
) -> dict[str, torch.Tensor]:
    """Reconstruction plus ``beta`` times KL, both per input element (no perceptual term).

    ``loss = mean |x_hat - x|`` (or squared for ``"l2"``) ``+ beta * KL / (3 * T * H * W)``, with KL
    summed over each video's latent elements and averaged over the batch. Dividing both terms of
    the classic "summed reconstruction + beta * summed KL" by the pixel count keeps ``beta``
    independent of the video size; ``1e-6`` is the usual weight of latent-diffusion autoencoders
    (a nearly deterministic latent), larger values trade detail for a smoother latent.

    Returns ``{"loss", "reconstruction", "kl"}`` (scalars; ``kl`` in nats per video).
    """
    assert output.reconstruction.shape == target.shape, (output.reconstruction.shape, target.shape)
    diff = output.reconstruction - target
    if reconstruction == "l1":
        rec = diff.abs().mean()
    elif reconstruction == "l2":
        rec = diff.square().mean()
    else:
        raise ValueError(f"unknown reconstruction loss {reconstruction!r}")
    kl = output.kl.mean()
    return {"loss": rec + beta * kl / target[0].numel(), "reconstruction": rec, "kl": kl}


# --------------------------------------------------------------------------------------------
# Init


def _init_weights(m: nn.Module) -> None:
    """Kaiming-normal (fan-in, ReLU gain) convolutions with zero bias; unit norms."""
    if isinstance(m, nn.Conv3d):
        nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.GroupNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


# --------------------------------------------------------------------------------------------
# Config table and registered variants

CONFIGS: dict[str, VideoVAEConfig] = {
    # CPU tests: 4x spatial, 4x temporal, 4 latent channels.
    "vae_tiny": VideoVAEConfig(
        latent_channels=4,
        channels=(16, 32, 64),
        temporal_downsample=(True, True),
        num_res_blocks=1,
        norm_groups=8,
    ),
    # GPUs: 8x spatial, 4x temporal, 16 latent channels (HunyuanVideo's compression).
    "vae_base": VideoVAEConfig(),
}


def _create(name: str, **overrides: object) -> VideoVAE:
    """The variant ``name`` with config fields replaced by ``overrides``."""
    return VideoVAE(dataclasses.replace(CONFIGS[name], **overrides), name=name)  # type: ignore[arg-type]


@register_model
def vae_tiny(**overrides: object) -> VideoVAE:
    """Tiny causal video VAE for CPU tests."""
    return _create("vae_tiny", **overrides)


@register_model
def vae_base(**overrides: object) -> VideoVAE:
    """Causal video VAE with HunyuanVideo-like compression (8x spatial, 4x temporal, 16 channels)."""
    return _create("vae_base", **overrides)
