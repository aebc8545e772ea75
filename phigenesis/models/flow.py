"""Rectified flow for Stage 2: the noising path, its velocity target, timesteps and an Euler sampler.

The PhiGenesis paper is Lu, Ma et al., "4D Driving Scene Generation With Stereo Forcing".

Conventions (shared by :mod:`phigenesis.models.stereo_forcing` and Stage 2's trainer):

* **Latents** are ``[B, V, C, T, h, w]``: batch, camera views, latent channels, latent frames,
  latent height and width (the video VAE's output for each view).
* **Flow time** ``t`` is in [0, 1], ``t = 0`` clean and ``t = 1`` pure noise, on the straight path
  of the PhiGenesis paper's Preliminary (rectified flow)::

      z_t = (1 - t) z_0 + t eps,        eps ~ N(0, I)

* **Velocity sign**: the network predicts ``v = z_0 - eps``, the PhiGenesis paper's ``L_RF`` target
  (MagicDriveDiT, whose multi-view DiT the paper builds on, uses the same sign). It is the
  *denoising* direction, ``v = -dz_t/dt``: the sampler runs time from 1 down to 0 and steps
  *along* ``v``, ``z_{t'} = z_t + (t - t') v`` for ``t' < t``. We keep the paper's sign so that the
  loss reads as the paper writes it; Open-Sora 2 predicts the opposite sign
  (``(1 - sigma_min) eps - x_0``), so weights ported from it need their output negated.
* **Time per clip or per latent frame**: ``t`` is ``[B]`` (one level per clip) or ``[B, T]`` (one
  level per latent frame: diffusion forcing, with history frames at a small noise level).
  :func:`as_frame_time` turns either into ``[B, T]`` and :func:`broadcast_time` into a shape that
  broadcasts against the latents. The sampler always hands the network ``[B, T]``.

Timesteps in training are logit-normal (``t = sigmoid(n)``, ``n ~ N(0, 1)``) and then shifted
towards noise for larger signals by ``t' = r t / (1 + (r - 1) t)`` (:func:`shift_time`), with ``r``
from the image size and latent length (:func:`resolution_shift`); the sampling grid
(:func:`time_grid`) takes the same shift.

Guidance (the PhiGenesis paper's Stereo Forcing score, ``v(z) + omega [v(z | c) - v(z)]``) combines a
conditional and an unconditional pass of the same network; the unconditional input is the
*zero* condition, which is also what :func:`phigenesis.models.stereo_forcing.stereo_forcing` gives
for ``u = 0`` and what :func:`phigenesis.models.stereo_forcing.drop_condition` trains on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

#: ``velocity_fn(z_t, t, condition) -> v``: latents [B, V, C, T, h, w], time [B, T] (the latents'
#: dtype), the condition (any tensor the network takes, or None) -> velocity like ``z_t``.
VelocityFn = Callable[[Tensor, Tensor, Tensor | None], Tensor]

#: ``callback(step, t, z)`` after each Euler step: the step's index (0-based), the time [B, T] the
#: latents are now at, and the latents [B, V, C, T, h, w].
StepCallback = Callable[[int, Tensor, Tensor], None]

#: Image pixels at which the resolution shift is 1 (MagicDriveDiT's and Open-Sora 1.2's base).
BASE_PIXELS = 512 * 512

LATENT_DIMS = "[B, V, C, T, h, w]"


def _check_latents(x: Tensor, name: str, fn: str) -> None:
    if x.ndim != 6:
        raise ValueError(f"{fn}: {name} must be latents {LATENT_DIMS}, got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{fn}: {name} must be a floating-point tensor, got {x.dtype}")


def _check_same_shape(a: Tensor, b: Tensor, names: str, fn: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{fn}: {names} must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


def as_frame_time(t: Tensor, batch: int, frames: int) -> Tensor:
    """[B, T] time per latent frame from a per-clip time [B] (repeated over frames) or a per-frame
    time [B, T] (checked and returned as is)."""
    if t.ndim == 1 and t.shape[0] == batch:
        return t[:, None].expand(batch, frames)  # [B, T]
    if t.ndim == 2 and tuple(t.shape) == (batch, frames):
        return t
    raise ValueError(f"time must be [B]=[{batch}] or [B, T]=[{batch}, {frames}], got shape {tuple(t.shape)}")


def broadcast_time(t: Tensor | float, latents: Tensor) -> Tensor:
    """Time shaped to broadcast against latents [B, V, C, T, h, w], in the latents' dtype and device.

    A float or 0-d tensor stays 0-d; [B] becomes [B, 1, 1, 1, 1, 1]; [B, T] becomes
    [B, 1, 1, T, 1, 1]."""
    _check_latents(latents, "latents", "broadcast_time")
    t = torch.as_tensor(t, dtype=latents.dtype, device=latents.device)
    batch, _, _, frames, _, _ = latents.shape
    if t.ndim == 0:
        return t
    if t.ndim == 1:
        as_frame_time(t, batch, frames)  # checks the shape
        return t.view(batch, 1, 1, 1, 1, 1)
    return as_frame_time(t, batch, frames)[:, None, None, :, None, None]  # [B, 1, 1, T, 1, 1]


def interpolate(z0: Tensor, eps: Tensor, t: Tensor | float) -> Tensor:
    """``z_t = (1 - t) z_0 + t eps``: clean latents ``z0`` and noise ``eps`` (both [B, V, C, T, h, w])
    mixed at flow time ``t`` (float, [B] or [B, T]; 0 clean, 1 noise)."""
    _check_latents(z0, "z0", "interpolate")
    _check_same_shape(z0, eps, "z0 and eps", "interpolate")
    tb = broadcast_time(t, z0)
    return (1 - tb) * z0 + tb * eps


def velocity_target(z0: Tensor, eps: Tensor) -> Tensor:
    """The velocity the network learns, ``v = z_0 - eps`` (the PhiGenesis paper's sign: ``-dz_t/dt``, pointing
    from noise to data), [B, V, C, T, h, w]."""
    _check_latents(z0, "z0", "velocity_target")
    _check_same_shape(z0, eps, "z0 and eps", "velocity_target")
    return z0 - eps


def _check_shift(shift: float, fn: str) -> None:
    if not (math.isfinite(shift) and shift > 0):
        raise ValueError(f"{fn}: shift must be a finite number > 0, got {shift}")


def shift_time(t: Tensor | float, shift: float) -> Tensor | float:
    """``t' = r t / (1 + (r - 1) t)``: time moved towards noise for ``r > 1`` (towards clean for
    ``r < 1``), with 0 and 1 fixed, strictly increasing in ``t``, the identity at ``r = 1``, and
    ``shift_time(., 1 / r)`` its inverse. Same type and shape as ``t``."""
    _check_shift(shift, "shift_time")
    return shift * t / (1 + (shift - 1) * t)


def resolution_shift(height: int, width: int, latent_frames: int, base_pixels: int = BASE_PIXELS) -> float:
    """The time shift ``r`` for a clip, as MagicDriveDiT computes it, clamped to at least 1::

        r = max(1, sqrt(height * width / base_pixels) * sqrt(latent_frames))

    ``height`` and ``width`` are the *image* size in pixels (one view, before the VAE);
    ``latent_frames`` is T, the latent frames after the VAE's temporal compression (a 9-frame
    clip at compression 4 has 3). At 512 x 512 and one latent frame ``r = 1``.

    Clamped to 1 because a shift below 1 would move training and sampling *towards the clean
    end* for small clips (Waymo's 160 x 240 at one latent frame gives 0.38 unclamped): the shift
    exists to add noise for signals whose redundancy survives it, not to remove it where the base
    schedule was already tuned. MagicDriveDiT does not clamp; callers who want its value at small
    sizes compute the product themselves.
    """
    if height < 1 or width < 1 or latent_frames < 1 or base_pixels < 1:
        raise ValueError(
            "resolution_shift: height, width, latent_frames and base_pixels must be >= 1, got "
            f"{height}, {width}, {latent_frames}, {base_pixels}"
        )
    return max(1.0, math.sqrt(height * width / base_pixels) * math.sqrt(latent_frames))


def sample_time(
    batch: int,
    generator: torch.Generator | None = None,
    shift: float = 1.0,
    per_frame: int | None = None,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Training times: logit-normal ``t = sigmoid(n)``, ``n ~ N(0, 1)``, then :func:`shift_time`.

    ``per_frame=None`` gives one level per clip, [B] (DFoT's ``random_uniform``); ``per_frame=T``
    gives independent levels per latent frame, [B, T] (diffusion forcing's ``random_independent``).
    Values lie in the open interval (0, 1); with ``shift=1`` their median is 0.5, with shift ``r``
    it is ``r / (1 + r)``. Drawn in float64 from ``generator`` (which must live on ``device``),
    returned in ``dtype``.
    """
    if batch < 1:
        raise ValueError(f"sample_time: batch must be >= 1, got {batch}")
    if per_frame is not None and per_frame < 1:
        raise ValueError(f"sample_time: per_frame must be None or >= 1, got {per_frame}")
    _check_shift(shift, "sample_time")
    shape = (batch,) if per_frame is None else (batch, per_frame)
    n = torch.randn(shape, generator=generator, dtype=torch.float64, device=device)
    return shift_time(torch.sigmoid(n), shift).to(dtype)


def time_grid(steps: int, shift: float = 1.0) -> Tensor:
    """The sampling grid, float64 [steps + 1]: ``shift_time(1 - i / steps, shift)`` for
    ``i = 0 .. steps``, strictly decreasing from exactly 1 to exactly 0."""
    if steps < 1:
        raise ValueError(f"time_grid: steps must be >= 1, got {steps}")
    _check_shift(shift, "time_grid")
    uniform = torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64)
    return shift_time(uniform, shift)


def guided_velocity(v_cond: Tensor, v_uncond: Tensor, omega: float) -> Tensor:
    """``v_uncond + omega (v_cond - v_uncond)``: the guided velocity (the PhiGenesis paper's Stereo Forcing
    score with ``v_cond = v(z | SF(u, z_ren))`` and ``v_uncond = v(z)``).

    ``omega = 0`` returns ``v_uncond`` and ``omega = 1`` returns ``v_cond`` exactly (the same
    tensors, no rounding); other values extrapolate (> 1, as classifier-free guidance) or
    interpolate. Both velocities have the same shape."""
    _check_same_shape(v_cond, v_uncond, "v_cond and v_uncond", "guided_velocity")
    if not math.isfinite(omega):
        raise ValueError(f"guided_velocity: omega must be finite, got {omega}")
    if omega == 0:
        return v_uncond
    if omega == 1:
        return v_cond
    return v_uncond + omega * (v_cond - v_uncond)


@dataclass(frozen=True, eq=False)
class FixedFrames:
    """Latent frames the sampler holds at a fixed small noise level (history, or DFoT's
    stabilisation of self-generated history), while it samples the others.

    Held frames sit at ``interpolate(z0, noise, level)`` for the whole run and are given
    ``t = level``; the others start at pure noise and go from ``t = 1`` to 0.
    """

    mask: Tensor  # bool [T] or [B, T]: True for a held latent frame
    z0: Tensor  # [B, V, C, T, h, w] clean latents; only the held frames are read
    level: float = 0.0  # k_s: flow time of the held frames, in [0, 1); 0 = clean history
    noise: Tensor | None = None  # [B, V, C, T, h, w] their eps; None: drawn from the sampler's generator

    def __post_init__(self) -> None:
        if not (0.0 <= self.level < 1.0):
            raise ValueError(f"FixedFrames: level must be in [0, 1), got {self.level}")
        if self.mask.dtype != torch.bool or self.mask.ndim not in (1, 2):
            raise ValueError(
                "FixedFrames: mask must be bool [T] or [B, T], "
                f"got {self.mask.dtype} {tuple(self.mask.shape)}"
            )
        _check_latents(self.z0, "z0", "FixedFrames")
        if self.noise is not None:
            _check_same_shape(self.z0, self.noise, "z0 and noise", "FixedFrames")


@dataclass(frozen=True, eq=False)
class Anchor:
    """Clean latents the sampler pulls its latents towards, cell by cell (render anchoring).

    After every Euler step that lands at a time ``t' >= until``, each latent cell moves by
    ``weight`` of the way to ``interpolate(z0, noise, t')``, the point of the straight path from
    the sampler's own starting noise to ``z0`` at that time (the path the flow would follow if
    the network knew ``z0`` exactly). ``weight = 1`` with ``until = 0`` ends at ``z0`` exactly;
    ``weight = 0`` leaves the cell to the network. With ``until > 0`` the last steps are the
    network's alone, so it can smooth the seams between anchored and free cells (SDEdit's idea,
    applied per cell as RePaint replaces the known region of an inpainting).
    """

    z0: Tensor  # [B, V, C, T, h, w] the latents to anchor to
    weight: Tensor  # [B, V, 1 or C, T, h, w] in [0, 1], how strongly each cell is pulled
    until: float = 0.0  # the anchor acts at flow times >= until; in [0, 1)

    def __post_init__(self) -> None:
        _check_latents(self.z0, "z0", "Anchor")
        if not torch.isfinite(self.z0).all():
            raise ValueError("Anchor: z0 has NaN or infinite values")
        if self.weight.ndim != 6 or torch.isnan(self.weight).any():
            raise ValueError(
                f"Anchor: weight must be [B, V, 1 or C, T, h, w] without NaN, got {tuple(self.weight.shape)}"
            )
        if float(self.weight.min()) < 0 or float(self.weight.max()) > 1:
            raise ValueError("Anchor: weight must lie in [0, 1]")
        if not (0.0 <= self.until < 1.0):
            raise ValueError(f"Anchor: until must be in [0, 1), got {self.until}")


def _frame_mask(mask: Tensor, batch: int, frames: int, fn: str) -> Tensor:
    """Bool [B, T] from a frame mask [T] or [B, T]."""
    if mask.dtype != torch.bool:
        raise ValueError(f"{fn}: a frame mask must be bool, got {mask.dtype}")
    if mask.ndim == 1 and mask.shape[0] == frames:
        return mask[None, :].expand(batch, frames)
    if mask.ndim == 2 and tuple(mask.shape) == (batch, frames):
        return mask
    raise ValueError(
        f"{fn}: a frame mask must be [T]=[{frames}] or [B, T]=[{batch}, {frames}], got {tuple(mask.shape)}"
    )


def _held_latents(
    fixed: FixedFrames, noise: Tensor, generator: torch.Generator | None
) -> tuple[Tensor, Tensor]:
    """(bool [B, T] held frames, [B, V, C, T, h, w] their held latents) for ``noise``'s shape."""
    batch, _, _, frames, _, _ = noise.shape
    _check_same_shape(fixed.z0, noise, "fixed.z0 and noise", "euler_sample")
    if not torch.isfinite(fixed.z0).all():
        raise ValueError("euler_sample: fixed.z0 has NaN or infinite values")
    frame_mask = _frame_mask(fixed.mask.to(noise.device), batch, frames, "euler_sample (fixed.mask)")
    eps = fixed.noise
    if eps is None:
        eps = torch.randn(noise.shape, generator=generator, dtype=noise.dtype, device=noise.device)
    like = {"dtype": noise.dtype, "device": noise.device}
    held = interpolate(fixed.z0.to(**like), eps.to(**like), fixed.level)
    return frame_mask, held


def euler_sample(
    velocity_fn: VelocityFn,
    noise: Tensor,
    steps: int,
    shift: float = 1.0,
    omega: float = 1.0,
    condition: Tensor | None = None,
    fixed: FixedFrames | None = None,
    generator: torch.Generator | None = None,
    callback: StepCallback | None = None,
    anchor: Anchor | None = None,
) -> Tensor:
    """Sample latents by Euler integration of the flow from ``t = 1`` (noise) to ``t = 0``.

    Args:
        velocity_fn: ``velocity_fn(z_t, t, condition) -> v``, latents [B, V, C, T, h, w] and time
            [B, T] (the latents' dtype) to a velocity like ``z_t`` in this module's sign
            (``z_0 - eps``).
        noise: [B, V, C, T, h, w] float, the start at ``t = 1``; NaN or inf raises ValueError.
        steps: Euler steps, on :func:`time_grid` ``(steps, shift)``.
        shift: the time shift ``r`` (:func:`resolution_shift`); 1 for the plain uniform grid.
        omega: guidance scale: ``v = v_uncond + omega (v_cond - v_uncond)`` with
            ``v_cond = velocity_fn(z, t, condition)`` and
            ``v_uncond = velocity_fn(z, t, zeros_like(condition))``. At ``omega = 1`` (or with no
            condition) only the conditional pass runs, at ``omega = 0`` only the unconditional one.
        condition: what the network is conditioned on (e.g. Stereo Forcing's
            [B, V, C + 1, T, h, w]), passed through untouched; None for an unconditional model.
        fixed: latent frames held at a small noise level throughout (:class:`FixedFrames`).
        generator: draws the held frames' noise when ``fixed.noise`` is None; unused otherwise.
        callback: called after every step as ``callback(step, t, z)``.
        anchor: latents to pull cells towards after each step (:class:`Anchor`), along the path
            from ``noise``; held frames stay as held.

    Returns:
        [B, V, C, T, h, w] the latents at ``t = 0``; held frames are returned as they were held,
        at ``interpolate(fixed.z0, eps, fixed.level)`` (take ``fixed.z0`` there for clean history).

    The sampler keeps autograd as the caller set it: run it under ``torch.no_grad()`` to sample.
    """
    _check_latents(noise, "noise", "euler_sample")
    if not torch.isfinite(noise).all():
        raise ValueError("euler_sample: noise has NaN or infinite values")
    if not math.isfinite(omega):
        raise ValueError(f"euler_sample: omega must be finite, got {omega}")
    if anchor is not None:
        _check_same_shape(anchor.z0, noise, "anchor.z0 and noise", "euler_sample")
    batch, _, _, frames, _, _ = noise.shape
    grid = time_grid(steps, shift).tolist()
    uncond = None if condition is None else torch.zeros_like(condition)
    z = noise
    frame_mask = held = held_cells = None
    level = 0.0
    if fixed is not None:
        frame_mask, held = _held_latents(fixed, noise, generator)
        held_cells = frame_mask[:, None, None, :, None, None]  # [B, 1, 1, T, 1, 1]
        level = fixed.level
        z = torch.where(held_cells, held, z)

    def frame_time(t_now: float) -> Tensor:
        t = torch.full((batch, frames), t_now, dtype=noise.dtype, device=noise.device)  # [B, T]
        return t if frame_mask is None else t.masked_fill(frame_mask, level)

    t = frame_time(grid[0])
    for step in range(steps):
        if condition is None or omega == 1:
            v = velocity_fn(z, t, condition)
        elif omega == 0:
            v = velocity_fn(z, t, uncond)
        else:
            v = guided_velocity(velocity_fn(z, t, condition), velocity_fn(z, t, uncond), omega)
        if v.shape != z.shape:
            raise ValueError(
                f"euler_sample: velocity_fn returned shape {tuple(v.shape)}, expected {tuple(z.shape)}"
            )
        z = z + (grid[step] - grid[step + 1]) * v  # steps along v = z_0 - eps as t falls
        if anchor is not None and grid[step + 1] >= anchor.until:
            target = interpolate(anchor.z0.to(z.dtype), noise, grid[step + 1])
            z = torch.lerp(z, target, anchor.weight.to(z.dtype).expand_as(z))  # exact at weights 0 and 1
        if held_cells is not None:
            z = torch.where(held_cells, held, z)
        t = frame_time(grid[step + 1])
        if callback is not None:
            callback(step, t, z)
    return z


def flow_loss(pred_velocity: Tensor, z0: Tensor, eps: Tensor, frame_mask: Tensor | None = None) -> Tensor:
    """0-d mean squared error of a predicted velocity against :func:`velocity_target` ``(z0, eps)``.

    ``frame_mask`` (bool [T] or [B, T], True = a generated frame that counts) leaves history and
    conditioning frames out of the loss (Open-Sora's ``no_i2v_ref_loss``): the mean runs over the
    elements of the counted frames only, and whatever the prediction holds elsewhere (even NaN)
    neither changes the loss nor gets a gradient. A mask that counts no frame raises ValueError.
    All three tensors are [B, V, C, T, h, w].
    """
    _check_latents(pred_velocity, "pred_velocity", "flow_loss")
    _check_same_shape(pred_velocity, z0, "pred_velocity and z0", "flow_loss")
    diff = pred_velocity - velocity_target(z0, eps)
    if frame_mask is None:
        return (diff**2).mean()
    batch, _, _, frames, _, _ = diff.shape
    counted = _frame_mask(frame_mask.to(diff.device), batch, frames, "flow_loss")
    counted = counted[:, None, None, :, None, None].expand(diff.shape)  # [B, V, C, T, h, w]
    count = int(counted.sum())
    if count == 0:
        raise ValueError("flow_loss: frame_mask counts no frame, so there is nothing to average")
    # Select before squaring, so that a NaN left out gets a zero gradient rather than 0 * NaN.
    diff = torch.where(counted, diff, torch.zeros_like(diff))
    return (diff**2).sum() / count
