"""Stage 2 denoiser: a multi-view video diffusion transformer over a frozen video VAE's latents.

Layout (timm-style): helpers, blocks, model, init, config table, registered variants.

The paper's Stage 2 ("Geometric-Guided Generation", "Stereo Forcing") renders the history's 4D
scene along the future trajectory, encodes the render with the frozen VAE and feeds the
Stereo-Forcing condition ``SF(u, z_ren) = u * z_ren`` beside the noisy target latent to a
multi-view video diffusion model (MagicDriveDiT-style) trained with a rectified-flow loss.

Symbols: B clips, V camera views, C latent channels, T latent frames, h x w latent grid, p the
spatial patch size, N = (h / p) (w / p) tokens per view and latent frame, D the hidden width.

- **Inputs** (the layout of :meth:`Stage1Model.encode`): ``z_t`` [B, V, C, T, h, w] the noisy
  target latent ``(1 - t) z_0 + t eps``; ``t`` [B] or [B, T] flow time in [0, 1] (0 clean, 1
  noise), per latent frame when [B, T] so that history frames can carry their own small noise
  level (diffusion forcing); ``condition`` [B, V, C + 1, T, h, w], the render latent times the
  uncertainty map, ``u * z_ren``, followed by ``u`` itself as the last channel (all zeros: no
  condition); ``plucker`` [B, V, 6, T, h, w] the Plücker ray of every latent cell
  (:func:`plucker_rays`). Output: the velocity [B, V, C, T, h, w] in ``z_t``'s dtype. The sign of
  the velocity is the loss's business: the model regresses whatever target the trainer gives it
  (``d z_t / d t = eps - z_0`` along the path; the PhiGenesis paper writes ``z_0 - eps``).
- **Tokens**: one per p x p latent patch of one view and one latent frame (time is not patched, so
  every token has one flow time). Three linear embeddings are summed: the noisy latent patch, the
  condition patch through a *zero-initialised* linear without bias (so the model starts as the
  unconditional one and an all-zero condition contributes exactly nothing, at any point of
  training) and the Plücker patch; plus fixed 2D sin-cos positions of the patch and 1D sin-cos of
  the latent frame index. Views get no positional embedding: the Plücker rays tell each token where
  in the world its view looks, which is what distinguishes views (and the model is equivariant to
  rotating the ring of views).
- **Block** (MagicDriveDiT's multi-view layout, DiT's adaLN-zero): spatial self-attention over the
  N tokens of one view and frame; cross-view attention per frame and token set, each view
  attending jointly to the tokens of its ring neighbours ``v - 1`` and ``v + 1`` (mod V, in the
  given view order; one neighbour when V = 2, skipped when V = 1), out through a zero-initialised
  projection; temporal self-attention of each spatial token over the T latent frames
  (bidirectional); an MLP. Spatial attention, temporal attention and the MLP are modulated (shift,
  scale, gate) by the flow-time embedding, per frame; the cross-view norm by shift and scale only
  (its zero projection is its gate: a second zero factor would never train).
- **Final layer**: adaLN-modulated norm and a zero-initialised linear to ``p * p * C``, so the
  initial output is exactly 0; unpatchified to [B, V, C, T, h, w].
- **Output** (``prediction``): ``velocity`` (the default, the paper's): the final layer's output is
  the velocity. ``x0_skip``: it is a correction ``r`` to the clean latent, ``x0 = u * z_ren + r``
  (the Stereo-Forcing condition itself as the skip), turned into the velocity along the path,
  ``v = (x0 - z_t) / max(t, t_min)`` (JiT's x-prediction with a velocity loss). The untrained
  model then reproduces the render latent where ``u = 1`` instead of having to learn to copy it
  through the zero-initialised condition embedding, and with a zero condition (the guidance's
  unconditional branch) the skip is zero, so the two branches stay one network.

Variants (``phigenesis.models.list_models("dit")``): ``stage2_tiny`` (CPU tests, the ``vae_tiny``
latent of 4 channels) and ``stage2_base`` (GPUs, 16 latent channels like HunyuanVideo's VAE).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, get_args

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from phigenesis.models import register_model
from phigenesis.models.stage1 import pixel_rays
from phigenesis.options import check_options, option

# --------------------------------------------------------------------------------------------
# Helpers: Plücker rays, sinusoidal embeddings, patches


def plucker_rays(intrinsics: Tensor, world_from_camera: Tensor, height: int, width: int) -> Tensor:
    """Plücker coordinates ``(d, o x d)`` of the ray through every pixel of pinhole cameras.

    Args:
        intrinsics: [..., 3, 3] pinhole matrices in pixels *of the grid asked for* (height x
            width): to get rays on a latent grid, scale fx, fy, cx, cy (and skew) by the VAE's
            spatial compression first. Pixel centres sit at integer coordinates, the convention
            of :func:`phigenesis.models.stage1.pixel_rays` (which this uses): pixel (row v, column
            u) looks along ``K^-1 (u, v, 1)``.
        world_from_camera: [..., 4, 4] camera poses (OpenCV axes: x right, y down, z forward) in
            the world frame; broadcast against ``intrinsics``' leading dims.
        height: H, rows of the grid.
        width: W, columns of the grid.

    Returns:
        [..., 6, H, W]: channels 0-2 the unit ray direction d in the world frame, channels 3-5 the
        moment ``o x d`` with o the camera centre (in the world's units: keep the world frame local
        to the clip, e.g. the first history frame, so that moments stay O(scene size)).

    Example::

        rays = plucker_rays(K_latent, world_from_camera, 12, 18)  # K [V, 3, 3], poses [T, V, 4, 4]
        rays.shape  # [T, V, 6, 12, 18]
    """
    assert intrinsics.shape[-2:] == (3, 3), intrinsics.shape
    assert world_from_camera.shape[-2:] == (4, 4), world_from_camera.shape
    batch = torch.broadcast_shapes(intrinsics.shape[:-2], world_from_camera.shape[:-2])
    k = intrinsics.expand(*batch, 3, 3)
    pose = world_from_camera.to(intrinsics.dtype).expand(*batch, 4, 4)
    rays = pixel_rays(k, height, width)  # [..., 3, H, W], camera frame, z = 1
    dirs = torch.einsum("...ij,...jhw->...ihw", pose[..., :3, :3], rays)  # [..., 3, H, W], world
    dirs = F.normalize(dirs, dim=-3)
    origin = pose[..., :3, 3, None, None].expand_as(dirs)  # [..., 3, H, W]
    moment = torch.linalg.cross(origin, dirs, dim=-3)  # [..., 3, H, W]
    return torch.cat([dirs, moment], dim=-3)


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """[..., dim] sinusoidal embedding of flow times ``t`` [...] in [0, 1] (scaled by 1000, as
    diffusion models' integer timesteps are): cos of the first half, sin of the second."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = 1000.0 * t.float()[..., None] * freqs  # [..., half]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


def _sincos_1d(positions: Tensor, dim: int) -> Tensor:
    """[n, dim] sin-cos embedding of positions [n] (sin of the first half, cos of the second)."""
    assert dim % 2 == 0, dim
    omega = 1.0 / 10_000.0 ** (
        torch.arange(dim // 2, dtype=torch.float32, device=positions.device) / (dim / 2)
    )
    args = positions.float()[:, None] * omega  # [n, dim / 2]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


def sincos_2d(rows: int, cols: int, dim: int, device: torch.device | None = None) -> Tensor:
    """[rows * cols, dim] fixed 2D sin-cos positions of a patch grid, row-major: half the channels
    encode the row, half the column."""
    assert dim % 4 == 0, f"hidden width {dim} must divide by 4 for 2D sin-cos positions"
    r, c = torch.meshgrid(torch.arange(rows, device=device), torch.arange(cols, device=device), indexing="ij")
    return torch.cat([_sincos_1d(r.flatten(), dim // 2), _sincos_1d(c.flatten(), dim // 2)], dim=1)


def patchify(x: Tensor, p: int) -> Tensor:
    """[B, V, C, T, h, w] -> [B, V, T, N, C * p * p] tokens, N = (h / p) (w / p) row-major."""
    b, v, c, t, h, w = x.shape
    x = x.reshape(b, v, c, t, h // p, p, w // p, p)
    x = x.permute(0, 1, 3, 4, 6, 2, 5, 7)  # [B, V, T, h/p, w/p, C, p, p]
    return x.reshape(b, v, t, (h // p) * (w // p), c * p * p)


def unpatchify(x: Tensor, p: int, h: int, w: int) -> Tensor:
    """[B, V, T, N, C * p * p] tokens -> [B, V, C, T, h, w] (the inverse of :func:`patchify`)."""
    b, v, t, _, cpp = x.shape
    c = cpp // (p * p)
    x = x.reshape(b, v, t, h // p, w // p, c, p, p)
    x = x.permute(0, 1, 5, 2, 3, 6, 4, 7)  # [B, V, C, T, h/p, p, w/p, p]
    return x.reshape(b, v, c, t, h, w)


def _modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    return x * (1 + scale) + shift


# --------------------------------------------------------------------------------------------
# Blocks


class Attention(nn.Module):
    """Multi-head attention of queries ``x`` [S, L, D] on keys/values ``context`` [S, M, D]
    (``x`` itself when None), with :func:`torch.nn.functional.scaled_dot_product_attention`."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        assert dim % heads == 0, f"hidden width {dim} must divide by heads {heads}"
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, context: Tensor | None = None) -> Tensor:
        s, n, d = x.shape
        ctx = x if context is None else context
        q = self.q(x).reshape(s, n, self.heads, d // self.heads).transpose(1, 2)  # [S, H, L, D/H]
        k, v = self.kv(ctx).reshape(s, ctx.shape[1], 2, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # [S, H, L, D/H]
        return self.proj(out.transpose(1, 2).reshape(s, n, d))


class CrossViewAttention(nn.Module):
    """Each view's tokens attend jointly to the tokens of its ring neighbours, per frame.

    ``x`` [S, V, N, D] (S = B * T) -> [S, V, N, D]: view v's N queries attend to the N tokens of view
    ``v - 1`` and the N of view ``v + 1`` (mod V) under one softmax; for V = 2 the two neighbours are
    the same view, attended once; for V = 1 the output is zero. ``proj`` is zero-initialised (the
    block's gate for this path).
    """

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.attn = Attention(dim, heads)

    def forward(self, x: Tensor) -> Tensor:
        s, v, n, d = x.shape
        if v == 1:
            return torch.zeros_like(x)
        # torch.roll(x, 1, dim=1)[:, i] is view i - 1; roll by -1 gives view i + 1.
        neighbours = (
            [torch.roll(x, 1, dims=1)] if v == 2 else [torch.roll(x, 1, dims=1), torch.roll(x, -1, dims=1)]
        )
        context = torch.cat(neighbours, dim=2)  # [S, V, n_nb * N, D]
        out = self.attn(x.reshape(s * v, n, d), context.reshape(s * v, -1, d))
        return out.reshape(s, v, n, d)


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


class MultiViewBlock(nn.Module):
    """Spatial, cross-view and temporal attention and an MLP on tokens [B, V, T, N, D], each a
    residual path modulated by the per-frame flow-time embedding ``c`` [B, T, D] (adaLN-zero)."""

    #: modulation chunks: spatial (shift, scale, gate), cross-view (shift, scale), temporal and MLP
    #: (shift, scale, gate each).
    CHUNKS = 11

    def __init__(self, dim: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm_spatial = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.spatial = Attention(dim, heads)
        self.norm_view = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.cross_view = CrossViewAttention(dim, heads)
        self.norm_temporal = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.temporal = Attention(dim, heads)
        self.norm_mlp = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.adaLN = nn.Sequential(nn.SiLU(), nn.Linear(dim, self.CHUNKS * dim))

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        b, v, t, n, d = x.shape
        mod = self.adaLN(c)[:, None, :, None]  # [B, 1, T, 1, 11 D]: broadcast over views and tokens
        (sh_s, sc_s, g_s, sh_v, sc_v, sh_t, sc_t, g_t, sh_m, sc_m, g_m) = mod.chunk(self.CHUNKS, dim=-1)

        h = _modulate(self.norm_spatial(x), sh_s, sc_s).reshape(b * v * t, n, d)
        x = x + g_s * self.spatial(h).reshape(b, v, t, n, d)

        if v > 1:
            h = _modulate(self.norm_view(x), sh_v, sc_v)  # [B, V, T, N, D]
            h = h.transpose(1, 2).reshape(b * t, v, n, d)
            x = x + self.cross_view(h).reshape(b, t, v, n, d).transpose(1, 2)

        h = _modulate(self.norm_temporal(x), sh_t, sc_t)  # [B, V, T, N, D]
        h = h.permute(0, 1, 3, 2, 4).reshape(b * v * n, t, d)
        x = x + g_t * self.temporal(h).reshape(b, v, n, t, d).permute(0, 1, 3, 2, 4)

        return x + g_m * self.mlp(_modulate(self.norm_mlp(x), sh_m, sc_m))


class FinalLayer(nn.Module):
    """adaLN-modulated norm and a zero-initialised linear: tokens [B, V, T, N, D] -> [..., p*p*C]."""

    def __init__(self, dim: int, out: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.adaLN = nn.Sequential(nn.SiLU(), nn.Linear(dim, 2 * dim))
        self.linear = nn.Linear(dim, out)

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        shift, scale = self.adaLN(c)[:, None, :, None].chunk(2, dim=-1)  # [B, 1, T, 1, D] each
        return self.linear(_modulate(self.norm(x), shift, scale))


# --------------------------------------------------------------------------------------------
# Model


#: What the final layer predicts (see the module docstring).
Prediction = Literal["velocity", "x0_skip"]
PREDICTIONS: tuple[str, ...] = get_args(Prediction)
#: ``x0_skip``: the smallest flow time the velocity divides by (keeps ``1 / t`` bounded).
X0_MIN_TIME = 0.05


@dataclass(frozen=True)
class DiTConfig:
    """Sizes of a multi-view video diffusion transformer.

    Attributes:
        latent_channels: C, channels of the VAE latent (the condition has C + 1).
        patch_size: p, latent cells per token side (h and w must divide by it; time is not patched).
        hidden: D, token width (divisible by 4 and by ``heads``).
        depth: number of multi-view blocks.
        heads: attention heads in every attention layer.
        mlp_ratio: MLP hidden width over D.
        time_embed_dim: channels of the sinusoidal flow-time features fed to the time MLP.
        prediction: ``velocity`` (the output is the velocity) or ``x0_skip`` (a correction to
            the Stereo-Forcing condition as the clean latent; see the module docstring).
        latent_mean, latent_std: per-channel statistics of the VAE latents the model was trained
            on (C values each), or None for none. With them the flow runs on ``(z - mean) / std``,
            as latent diffusion models scale their VAE's latents to unit variance (the noise is
            N(0, I)); :meth:`MultiViewDiT.normalize_latents` and ``denormalize_latents`` map
            between the two, and callers (training, rollouts) apply them.
    """

    latent_channels: int = option(16, ge=1, le=1024, help="C, channels of the VAE latent")
    patch_size: int = option(2, ge=1, le=64, help="p, latent cells per token side")
    hidden: int = option(768, ge=4, le=8192, help="D, token width")
    depth: int = option(12, ge=1, le=256, help="multi-view blocks")
    heads: int = option(12, ge=1, le=256, help="attention heads")
    mlp_ratio: float = option(4.0, gt=0, le=64, help="MLP hidden width over D")
    time_embed_dim: int = option(256, ge=2, le=8192, help="channels of the flow-time features")
    prediction: Prediction = option("velocity", help="what the final layer predicts")
    latent_mean: tuple[float, ...] | None = option(None, ge=-1e6, le=1e6, help="per-channel latent mean")
    latent_std: tuple[float, ...] | None = option(None, gt=0, le=1e6, help="per-channel latent std")

    def __post_init__(self) -> None:
        check_options(self, "DiTConfig")
        for name in ("latent_mean", "latent_std"):
            value = getattr(self, name)
            if value is not None and len(value) != self.latent_channels:
                raise ValueError(f"DiTConfig: {name} must be {self.latent_channels} values, got {value}")
        if (self.latent_mean is None) != (self.latent_std is None):
            raise ValueError("DiTConfig: latent_mean and latent_std come together")
        if self.hidden % self.heads or self.hidden % 4:
            raise ValueError(f"DiTConfig: hidden={self.hidden} must divide by heads={self.heads} and by 4")

    def to_dict(self) -> dict[str, object]:
        """Plain values, as stored in checkpoints."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, object]) -> DiTConfig:
        return cls(**values)  # type: ignore[arg-type]


class MultiViewDiT(nn.Module):
    """The Stage 2 denoiser (see the module docstring).

    Exposes ``name``, ``config``, ``forward``, ``predict`` and ``num_parameters`` like every model
    of :mod:`phigenesis.models`.

    Example::

        model = create_model("stage2_tiny")
        v = model(z_t, t, condition, plucker)  # z_t [1, 5, 4, 2, 12, 18], t [1] or [1, 2]
        loss = (v - (eps - z0)).square().mean()
    """

    def __init__(self, config: DiTConfig, name: str = "dit"):
        super().__init__()
        self.name = name
        self.config = config
        c, p, d = config.latent_channels, config.patch_size, config.hidden
        self.x_embed = nn.Linear(c * p * p, d)
        self.cond_embed = nn.Linear((c + 1) * p * p, d, bias=False)  # zero-initialised
        self.ray_embed = nn.Linear(6 * p * p, d)
        self.time_mlp = nn.Sequential(nn.Linear(config.time_embed_dim, d), nn.SiLU(), nn.Linear(d, d))
        self.blocks = nn.ModuleList(
            MultiViewBlock(d, config.heads, config.mlp_ratio) for _ in range(config.depth)
        )
        self.final = FinalLayer(d, c * p * p)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """DiT's initialisation: Xavier-uniform linears with zero bias, N(0, 0.02) time MLP, and
        zeros for every adaLN modulation, the cross-view projections, the condition embedding and
        the final linear (the output is then exactly 0 and ignores the condition)."""
        self.apply(_init_weights)
        for m in self.time_mlp:
            if isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, std=0.02)
        nn.init.zeros_(self.cond_embed.weight)
        for block in self.blocks:
            _zero(block.adaLN[-1])
            _zero(block.cross_view.attn.proj)
        _zero(self.final.adaLN[-1])
        _zero(self.final.linear)

    def _check_inputs(self, z_t: Tensor, t: Tensor, condition: Tensor, plucker: Tensor) -> None:
        cfg = self.config
        if z_t.ndim != 6 or z_t.shape[2] != cfg.latent_channels:
            raise ValueError(f"z_t must be [B, V, C={cfg.latent_channels}, T, h, w], got {tuple(z_t.shape)}")
        b, v, c, frames, h, w = z_t.shape
        p = cfg.patch_size
        if h % p or w % p:
            raise ValueError(f"z_t {tuple(z_t.shape)}: latent h={h} and w={w} must divide by patch_size={p}")
        if condition.shape != (b, v, c + 1, frames, h, w):
            raise ValueError(
                f"condition must be [B, V, C + 1, T, h, w] = {[b, v, c + 1, frames, h, w]} for z_t "
                f"{tuple(z_t.shape)}, got {tuple(condition.shape)}"
            )
        if plucker.shape != (b, v, 6, frames, h, w):
            raise ValueError(
                f"plucker must be [B, V, 6, T, h, w] = {[b, v, 6, frames, h, w]} for z_t {tuple(z_t.shape)}, "
                f"got {tuple(plucker.shape)}"
            )
        if t.shape not in ((b,), (b, frames)):
            raise ValueError(f"t must be [B] = [{b}] or [B, T] = [{b}, {frames}], got {tuple(t.shape)}")
        for label, x in (("z_t", z_t), ("t", t), ("condition", condition), ("plucker", plucker)):
            if not bool(torch.isfinite(x).all()):
                raise ValueError(f"{label} has NaN or Inf values")
        if bool((t < 0).any() or (t > 1).any()):
            raise ValueError(f"t must lie in [0, 1], got values in [{t.min().item()}, {t.max().item()}]")

    def forward(self, z_t: Tensor, t: Tensor, condition: Tensor, plucker: Tensor) -> Tensor:
        """Velocity [B, V, C, T, h, w] (``z_t``'s dtype) of noisy latents ``z_t`` [B, V, C, T, h, w]
        at flow times ``t`` [B] or [B, T] (0 clean, 1 noise), given the Stereo-Forcing
        ``condition`` [B, V, C + 1, T, h, w] (``u * z_ren`` then ``u``; zeros: none) and the
        Plücker rays ``plucker`` [B, V, 6, T, h, w] of every latent cell (:func:`plucker_rays`).

        Raises ValueError on shapes that do not fit (with the shapes) and on NaN/Inf inputs.
        """
        self._check_inputs(z_t, t, condition, plucker)
        b, _, _, frames, h, w = z_t.shape
        p = self.config.patch_size
        dtype = self.x_embed.weight.dtype
        x = self.x_embed(patchify(z_t.to(dtype), p))  # [B, V, T, N, D]
        x = x + self.cond_embed(patchify(condition.to(dtype), p))
        x = x + self.ray_embed(patchify(plucker.to(dtype), p))
        d = x.shape[-1]
        pos = sincos_2d(h // p, w // p, d, x.device).to(dtype)  # [N, D]
        frame_pos = _sincos_1d(torch.arange(frames, device=x.device), d).to(dtype)  # [T, D]
        x = x + pos + frame_pos[:, None]

        times = t.to(dtype)
        times = times[:, None].expand(b, frames) if times.ndim == 1 else times  # [B, T]
        c = self.time_mlp(timestep_embedding(times, self.config.time_embed_dim).to(dtype))  # [B, T, D]
        for block in self.blocks:
            x = block(x, c)
        out = unpatchify(self.final(x, c), p, h, w)  # [B, V, C, T, h, w]
        if self.config.prediction == "x0_skip":
            x0 = condition[:, :, :-1].to(dtype) + out
            t_cells = times.clamp_min(X0_MIN_TIME)[:, None, None, :, None, None]
            out = (x0 - z_t.to(dtype)) / t_cells
        return out.to(z_t.dtype)

    def _latent_stats(self, z: Tensor, channel_dim: int) -> tuple[Tensor, Tensor] | None:
        cfg = self.config
        if cfg.latent_mean is None or cfg.latent_std is None:
            return None
        shape = [1] * z.ndim
        shape[channel_dim] = cfg.latent_channels
        mean = torch.tensor(cfg.latent_mean, dtype=z.dtype, device=z.device).reshape(shape)
        return mean, torch.tensor(cfg.latent_std, dtype=z.dtype, device=z.device).reshape(shape)

    def normalize_latents(self, z: Tensor, channel_dim: int = 2) -> Tensor:
        """VAE latents (channels along ``channel_dim``) as the flow sees them: ``(z - mean) / std``
        with the config's statistics, ``z`` itself without them."""
        stats = self._latent_stats(z, channel_dim)
        return z if stats is None else (z - stats[0]) / stats[1]

    def denormalize_latents(self, z: Tensor, channel_dim: int = 2) -> Tensor:
        """The inverse of :meth:`normalize_latents`: flow latents back to the VAE's."""
        stats = self._latent_stats(z, channel_dim)
        return z if stats is None else z * stats[1] + stats[0]

    @torch.no_grad()
    def predict(self, z_t: Tensor, t: Tensor, condition: Tensor, plucker: Tensor) -> Tensor:
        """:meth:`forward` in eval mode without gradients."""
        was_training = self.training
        self.eval()
        try:
            return self(z_t, t, condition, plucker)
        finally:
            self.train(was_training)

    def num_parameters(self, trainable: bool = True) -> int:
        """Parameters (only those that require gradients when ``trainable``)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable)


# --------------------------------------------------------------------------------------------
# Init


def _init_weights(m: nn.Module) -> None:
    if isinstance(m, nn.Linear):
        nn.init.xavier_uniform_(m.weight)
        if m.bias is not None:
            nn.init.zeros_(m.bias)


def _zero(m: nn.Linear) -> None:
    nn.init.zeros_(m.weight)
    if m.bias is not None:
        nn.init.zeros_(m.bias)


# --------------------------------------------------------------------------------------------
# Config table and registered variants

CONFIGS: dict[str, DiTConfig] = {
    # 2-core CPUs: vae_tiny's 4-channel latent, 64 wide, 4 blocks.
    "stage2_tiny": DiTConfig(latent_channels=4, patch_size=2, hidden=64, depth=4, heads=4, time_embed_dim=64),
    # GPUs: HunyuanVideo-like 16-channel latent, DiT-B widths (768 wide, 12 blocks, 12 heads).
    "stage2_base": DiTConfig(latent_channels=16, patch_size=2, hidden=768, depth=12, heads=12),
}


def _create(name: str, **overrides: object) -> MultiViewDiT:
    return MultiViewDiT(dataclasses.replace(CONFIGS[name], **overrides), name=name)  # type: ignore[arg-type]


@register_model
def stage2_tiny(**overrides: object) -> MultiViewDiT:
    """Stage 2 denoiser for CPU tests (4 latent channels, 64 wide, 4 blocks)."""
    return _create("stage2_tiny", **overrides)


@register_model
def stage2_base(**overrides: object) -> MultiViewDiT:
    """Stage 2 denoiser for GPUs (16 latent channels, 768 wide, 12 blocks)."""
    return _create("stage2_base", **overrides)
