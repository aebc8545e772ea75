"""Stereo Forcing's condition: a rendered video's latents weighed by a per-pixel map ``u``.

Stage 2 renders the history's 4D Gaussians along the future trajectory, encodes the render with the
video VAE (``z_ren``) and conditions the diffusion model on it through the PhiGenesis paper's
``SF(u, z_ren) = u * z_ren``, guided at sampling time by the paper's score::

    v(z) + omega [v(z | SF(u, z_ren)) - v(z)]

(:func:`guided_velocity`, the same as :func:`phigenesis.models.flow.guided_velocity`; the sampler
is :func:`phigenesis.models.flow.euler_sample`).

Conventions (those of :mod:`phigenesis.models.flow`): latents are ``[B, V, C, T, h, w]`` (batch,
views, latent channels, latent frames, latent height and width); maps at latent resolution are
``[B, V, T, h, w]``; maps at image resolution are ``[..., H, W]`` in pixels, with frames ``F`` at
dim -3 when they have them.

**What u means here.** ``u`` is in [0, 1] and *weighs the render*: ``u = 1`` passes the render's
latent unchanged (geometry to keep), ``u = 0`` removes it (the model generates freely there). The
seed calls ``u`` an "uncertainty map" yet multiplies the render by it, so the map fed here must
be oriented as a trust weight: high where the geometry is well determined (as the localization
potential is, high for a wide baseline); a map that is high where depth is *uncertain* (the
entropy of the depth bins) is turned round, e.g. ``1 - H / log K``, before it comes here.

**Layout of the condition.** :func:`stereo_forcing` returns ``u * z_ren`` channel-concatenated
with ``u`` itself as the last channel, [B, V, C + 1, T, h, w]: without ``u`` the network could not
tell a zero latent that ``u`` removed from a render that encodes to zero (GEN3C and Open-Sora 2
feed such a validity channel too). At ``u = 0`` the whole condition is zeros, exactly the
unconditional input the sampler's guidance and :func:`drop_condition` use, so the unconditional
branch, condition dropout and "no trusted render" are one and the same input.

**Where u is reduced to latent resolution.** ``SF`` is applied to the latents, so ``u`` is pooled
from image pixels to the latent grid first (:func:`pool_to_latent`): area averages in space and,
for a causal video VAE, averages over the frames each latent frame covers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from phigenesis.models.flow import guided_velocity

__all__ = ["drop_condition", "guided_velocity", "latent_frame_count", "pool_to_latent", "stereo_forcing"]


def _check_unit_map(u: Tensor, name: str, fn: str) -> None:
    """ValueError unless ``u`` is a floating tensor with every value in [0, 1] (no NaN)."""
    if not u.is_floating_point():
        raise ValueError(f"{fn}: {name} must be a floating-point tensor, got {u.dtype}")
    if u.numel() == 0:
        raise ValueError(f"{fn}: {name} is empty, shape {tuple(u.shape)}")
    if torch.isnan(u).any():
        raise ValueError(f"{fn}: {name} has NaN values ({int(torch.isnan(u).sum())} of {u.numel()})")
    low, high = float(u.min()), float(u.max())
    if low < 0 or high > 1:
        raise ValueError(f"{fn}: {name} must lie in [0, 1], got values in [{low}, {high}]")


def latent_frame_count(frames: int, temporal_compression: int) -> int:
    """Latent frames of a causal video VAE for ``frames`` image frames: ``1 + (F - 1) / c``, where
    latent frame 0 is image frame 0 and latent frame ``k >= 1`` covers frames ``c (k - 1) + 1 ..
    c k`` (frames 1-4, 5-8, ... at ``c = 4``); ``F - 1`` must be a multiple of ``c``."""
    if temporal_compression < 1:
        raise ValueError(f"latent_frame_count: temporal_compression must be >= 1, got {temporal_compression}")
    if frames < 1 or (frames - 1) % temporal_compression != 0:
        raise ValueError(
            f"latent_frame_count: a causal VAE at temporal compression {temporal_compression} takes "
            f"1 + k * {temporal_compression} frames, got {frames}"
        )
    return 1 + (frames - 1) // temporal_compression


def pool_to_latent(u: Tensor, latent_hw: tuple[int, int], temporal_compression: int | None = None) -> Tensor:
    """A map in [0, 1] at image resolution reduced to the latent grid by averaging.

    Args:
        u: [..., H, W] float in [0, 1] (image pixels), or [..., F, H, W] over ``F`` image frames
            when ``temporal_compression`` is given.
        latent_hw: (h, w), the latent grid, at most (H, W).
        temporal_compression: None to pool only in space; ``c`` to also pool frames as a causal
            VAE does (:func:`latent_frame_count`): latent frame 0 takes frame 0, latent frame
            ``k >= 1`` the mean over frames ``c (k - 1) + 1 .. c k``. ``F`` must be ``1 + k c``.

    Returns:
        [..., h, w] (or [..., T, h, w], ``T = 1 + (F - 1) / c``), u's dtype, still in [0, 1].

    Space is pooled with adaptive average pooling: latent cell ``i`` averages pixel rows
    ``floor(i H / h) .. ceil((i + 1) H / h) - 1`` (the same for columns). When ``H / h`` is an
    integer these windows tile the image and each cell is its exact area mean, so the map's mean is
    preserved; when it is not, neighbouring windows share the pixel row or column they both touch,
    each cell is the plain mean of the pixels its window touches, and the mean is only close. A
    constant map stays that constant either way.
    """
    fn = "pool_to_latent"
    _check_unit_map(u, "u", fn)
    if u.ndim < 2:
        raise ValueError(f"{fn}: u must be [..., H, W], got shape {tuple(u.shape)}")
    height, width = u.shape[-2:]
    h, w = latent_hw
    if not (1 <= h <= height and 1 <= w <= width):
        raise ValueError(f"{fn}: latent_hw must be within 1 .. (H, W) = {(height, width)}, got {(h, w)}")
    lead = u.shape[:-2]
    pooled = F.adaptive_avg_pool2d(u.reshape(-1, height, width), (h, w)).reshape(*lead, h, w)
    if temporal_compression is None:
        return pooled
    if u.ndim < 3:
        raise ValueError(f"{fn}: temporal pooling needs frames, u as [..., F, H, W], got {tuple(u.shape)}")
    frames = u.shape[-3]
    latent_frames = latent_frame_count(frames, temporal_compression)
    first = pooled[..., :1, :, :]  # [..., 1, h, w]: latent frame 0 is frame 0
    rest = pooled[..., 1:, :, :].reshape(*lead[:-1], latent_frames - 1, temporal_compression, h, w)
    return torch.cat([first, rest.mean(dim=-3)], dim=-3)  # [..., T, h, w]


def stereo_forcing(u_latent: Tensor, z_render: Tensor) -> Tensor:
    """The Stereo Forcing condition ``[SF(u, z_ren), u]``, with ``SF(u, z_ren) = u * z_ren``.

    Args:
        u_latent: [B, V, T, h, w] float in [0, 1], the weight map at latent resolution
            (:func:`pool_to_latent`); 1 keeps the render, 0 removes it. NaN or values outside
            [0, 1] raise ValueError.
        z_render: [B, V, C, T, h, w] float, the VAE latents of the rendered video; NaN or inf
            raise ValueError.

    Returns:
        [B, V, C + 1, T, h, w] in z_render's dtype: channels ``0 .. C-1`` are ``u * z_ren``, channel
        ``C`` is ``u``. All zeros where ``u = 0`` (the unconditional input).
    """
    fn = "stereo_forcing"
    if z_render.ndim != 6:
        raise ValueError(
            f"{fn}: z_render must be latents [B, V, C, T, h, w], got shape {tuple(z_render.shape)}"
        )
    if not z_render.is_floating_point():
        raise ValueError(f"{fn}: z_render must be a floating-point tensor, got {z_render.dtype}")
    batch, views, _, frames, h, w = z_render.shape
    if tuple(u_latent.shape) != (batch, views, frames, h, w):
        raise ValueError(
            f"{fn}: u_latent must be [B, V, T, h, w] = {[batch, views, frames, h, w]} to match z_render, "
            f"got {list(u_latent.shape)}"
        )
    _check_unit_map(u_latent, "u_latent", fn)
    if not torch.isfinite(z_render).all():
        raise ValueError(f"{fn}: z_render has NaN or infinite values")
    u = u_latent.to(dtype=z_render.dtype, device=z_render.device)[:, :, None]  # [B, V, 1, T, h, w]
    return torch.cat([u * z_render, u], dim=2)  # [B, V, C + 1, T, h, w]


def drop_condition(
    condition: Tensor, p: float, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Condition dropout for guidance training: each sample's whole condition is zeroed (the
    unconditional input) with probability ``p``, independently.

    Args:
        condition: [B, ...] float, one condition per sample along dim 0 (e.g. [B, V, C + 1, T, h, w]).
        p: drop probability in [0, 1]; 0 keeps every sample, 1 drops every one.
        generator: for the draws, on condition's device.

    Returns:
        (condition with dropped samples exactly zero, same shape and dtype; bool [B] keep mask,
        True for a sample whose condition was kept).
    """
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"drop_condition: p must be in [0, 1], got {p}")
    if condition.ndim < 1 or condition.shape[0] < 1:
        raise ValueError(
            f"drop_condition: condition must be [B, ...] with B >= 1, got {tuple(condition.shape)}"
        )
    batch = condition.shape[0]
    draws = torch.rand(batch, generator=generator, device=condition.device)  # [B] in [0, 1)
    keep = draws >= p
    cells = keep.view(batch, *([1] * (condition.ndim - 1)))
    return torch.where(cells, condition, torch.zeros_like(condition)), keep
