"""``phigenesis-train stage2``: trains the multi-view video diffusion transformer
(:mod:`phigenesis.models.dit`) on a Stage 2 latent cache (:mod:`phigenesis.train.stage2_data`).

The latents of every window (history, targets, the history's render at the target cameras and its
uncertainty maps) are computed once, before the first step, into ``<out>/latents`` (or the
``latents`` folder given; resumable like every cache), so a step does no VAE or rasterizer work.

Each step draws ``batch_size`` windows from a generator seeded by (seed, step, rank) and builds the
sequence ``[history latent frames, target latent frames]`` of each ([B, V, C, T_h + T, h, w]):

- **rectified flow** ``z_t = (1 - t) z_0 + t eps``, the network predicting the velocity
  ``z_0 - eps`` (:mod:`phigenesis.models.flow`); target frames share one logit-normal ``t`` per
  window, shifted by ``time_shift``; history frames carry a small level drawn uniformly in
  ``[0, history_noise]`` (diffusion forcing: at sampling time the generated history is held at
  such a level, DFoT's stabilisation), and the loss counts the target frames only;
- **Stereo Forcing** condition ``SF(u, z_ren) = u * z_ren`` with ``u`` the chosen ``uncertainty``
  map, and ``u`` itself as a channel (:func:`~phigenesis.models.stereo_forcing.stereo_forcing`), on
  the target frames (the history frames' condition is zero: they are themselves the history);
  ``uncertainty: none`` trains the diffusion model without geometry (the ablation's "no geometry"
  row); the whole condition is dropped with probability ``condition_dropout``, so one network gives
  both terms of the guided score ``v(z) + omega [v(z | SF) - v(z)]``;
- **cameras**: Plücker rays per latent token (:func:`~phigenesis.models.dit.plucker_rays`) of each
  latent frame's last frame's camera, in the frame of the window's first history camera (so the
  moments stay small however far the scene has driven).

AdamW, warm-up then cosine annealing with restarts every ``restart_steps`` (the paper's schedule),
gradient clipping; safetensors checkpoints and exact resume, CSV + TensorBoard logs, a progress bar
and torchrun (gloo) through :mod:`phigenesis.train.runner`, as the other trainers.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from torch import Tensor
from tqdm import tqdm

from phigenesis.models.config_checks import create_overridden
from phigenesis.models.dit import MultiViewDiT
from phigenesis.models.flow import flow_loss, interpolate, sample_time
from phigenesis.models.loading import load_stage1, load_stage2
from phigenesis.models.stereo_forcing import drop_condition, stereo_forcing
from phigenesis.rollout.conditions import TargetCameras, sequence_plucker
from phigenesis.rollout.config import Stage2TrainConfig
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint
from phigenesis.train.runner import (
    DivergenceCheck,
    MetricsLog,
    ProcessGroup,
    load_training_state,
    process_group,
    restore_optimizer,
    save_training_state,
    step_generator,
    write_text_atomic,
)
from phigenesis.train.stage1 import check_run_folder
from phigenesis.train.stage2_data import Stage2Latents, Stage2Sample, precompute_stage2

log = logging.getLogger(__name__)

LOG_COLUMNS = ("loss", "lr", "grad_norm", "t_mean", "dropped", "seconds")


@dataclass
class Stage2Run:
    """What :func:`train_stage2` leaves: the run folder, the final weights, the last logged values."""

    out: Path
    checkpoint: Path | None
    latents: Path
    steps_done: int
    last: dict[str, float]
    seconds: float


def restarted_cosine_lr(step: int, cfg: Stage2TrainConfig) -> float:
    """Linear warm-up, then cosine annealing to ``final_lr_ratio * lr`` over each cycle of
    ``restart_steps`` (one cycle over the whole run when 0)."""
    if cfg.warmup_steps and step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    after = step - cfg.warmup_steps
    cycle = cfg.restart_steps or max(cfg.steps - cfg.warmup_steps, 1)
    progress = (after % cycle) / cycle
    return cfg.lr * (cfg.final_lr_ratio + (1 - cfg.final_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress)))


# --------------------------------------------------------------------------------------------
# Batches


@dataclass(frozen=True)
class Stage2Batch:
    """B windows as the denoiser takes them: ``z0`` [B, V, C, T_h + T, h, w] clean latents (history
    then targets), ``condition`` [B, V, C + 1, T_h + T, h, w], ``plucker`` [B, V, 6, T_h + T, h, w],
    ``target`` [T_h + T] bool (the frames the loss counts)."""

    z0: Tensor
    condition: Tensor
    plucker: Tensor
    target: Tensor


def window_plucker(sample: Stage2Sample, temporal_compression: int) -> Tensor:
    """[V, 6, T_h + T, h, w] Plücker rays of every latent token of a window
    (:func:`~phigenesis.rollout.conditions.sequence_plucker`)."""
    hist = TargetCameras(
        sample.history_world_from_camera, sample.intrinsics, sample.history_time_s, sample.image_hw
    )
    tgt = TargetCameras(sample.world_from_camera, sample.intrinsics, sample.time_s, sample.image_hw)
    latent = (int(sample.z_history.shape[2]), int(sample.z_target.shape[2]))
    return sequence_plucker(hist, tgt, latent, tuple(sample.z_target.shape[-2:]), temporal_compression)


def window_condition(sample: Stage2Sample, kind: str) -> Tensor:
    """[V, C + 1, T_h + T, h, w]: zeros on the history frames, ``SF(u, z_ren)`` and u on the targets
    (zeros everywhere for ``none``)."""
    v, c, t_h, h, w = sample.z_history.shape
    t = sample.z_target.shape[2]
    out = torch.zeros(v, c + 1, t_h + t, h, w)
    if kind == "none":
        return out
    if kind not in sample.u:
        raise ValueError(
            f"window {sample.scene_id}@{sample.history_indices[0]}: the latent cache has no {kind!r} map "
            f"(it has {sorted(sample.u)}; entropy needs Stage 1 Gaussians with a depth entropy)"
        )
    out[:, :, t_h:] = stereo_forcing(sample.u[kind][None], sample.z_render[None])[0]
    return out


def latent_statistics(data: Stage2Latents) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(mean, std) per channel of the target latents of every window of a latent cache, in float64:
    the statistics a ``latent_norm`` denoiser standardises its latents with."""
    total = total_sq = None
    count = 0
    for i in range(len(data)):
        z = data[i].z_target.double()  # [V, C, T, h, w]
        per_channel = z.transpose(0, 1).reshape(z.shape[1], -1)
        total = per_channel.sum(1) if total is None else total + per_channel.sum(1)
        total_sq = per_channel.square().sum(1) if total_sq is None else total_sq + per_channel.square().sum(1)
        count += per_channel.shape[1]
    if total is None or total_sq is None or count < 2:
        raise ValueError("latent_statistics: the latent cache holds no windows")
    mean = total / count
    std = (total_sq / count - mean.square()).clamp_min(1e-12).sqrt()
    return tuple(mean.tolist()), tuple(std.tolist())


def make_batch(
    samples: list[Stage2Sample], kind: str, temporal_compression: int, model: MultiViewDiT | None = None
) -> Stage2Batch:
    """The :class:`Stage2Batch` of ``samples`` (all of one shape); the latents (targets, history and
    render) standardised by ``model``'s latent statistics when it has them."""

    def norm(z: Tensor) -> Tensor:
        return z if model is None else model.normalize_latents(z, channel_dim=1)

    t_h = samples[0].z_history.shape[2]
    samples = [
        dataclasses.replace(
            s, z_history=norm(s.z_history), z_target=norm(s.z_target), z_render=norm(s.z_render)
        )
        for s in samples
    ]
    z0 = torch.stack([torch.cat([s.z_history, s.z_target], dim=2) for s in samples])
    target = torch.zeros(z0.shape[3], dtype=torch.bool)
    target[t_h:] = True
    return Stage2Batch(
        z0=z0,
        condition=torch.stack([window_condition(s, kind) for s in samples]),
        plucker=torch.stack([window_plucker(s, temporal_compression) for s in samples]),
        target=target,
    )


def training_times(batch: Stage2Batch, cfg: Stage2TrainConfig, generator: torch.Generator) -> Tensor:
    """[B, T_h + T] flow times: one logit-normal level per window on its targets, a small uniform
    level on its history frames."""
    b, frames = batch.z0.shape[0], batch.z0.shape[3]
    t_target = sample_time(b, generator, shift=cfg.time_shift)  # [B]
    t = t_target[:, None].expand(b, frames).clone()
    hist = ~batch.target
    t[:, hist] = torch.rand(b, int(hist.sum()), generator=generator) * cfg.history_noise
    return t


def stage2_loss(
    model: torch.nn.Module, batch: Stage2Batch, cfg: Stage2TrainConfig, generator: torch.Generator
) -> tuple[Tensor, dict[str, float]]:
    """The rectified-flow loss of one batch (condition dropout and noise from ``generator``)."""
    t = training_times(batch, cfg, generator)
    eps = torch.randn(batch.z0.shape, generator=generator)
    condition, keep = drop_condition(batch.condition, cfg.condition_dropout, generator)
    z_t = interpolate(batch.z0, eps, t)
    pred = model(z_t, t, condition, batch.plucker)
    loss = flow_loss(pred, batch.z0, eps, batch.target)
    return loss, {"t_mean": float(t[:, batch.target].mean()), "dropped": float((~keep).float().mean())}


# --------------------------------------------------------------------------------------------
# Training


def build_denoiser(
    cfg: Stage2TrainConfig,
    latent_channels: int,
    latent_stats: tuple[tuple[float, ...], tuple[float, ...]] | None = None,
) -> MultiViewDiT:
    """The denoiser of a config, its latent channels those of the Stage 1 model's VAE, standardising
    latents by ``latent_stats`` (mean, std per channel) when given."""
    overrides = {"latent_channels": latent_channels, **cfg.model_overrides}
    if latent_stats is not None:
        overrides |= {"latent_mean": latent_stats[0], "latent_std": latent_stats[1]}
    model = create_overridden(cfg.model, overrides, "Stage2TrainConfig")
    if not isinstance(model, MultiViewDiT):
        raise ValueError(f"Stage2TrainConfig.model {cfg.model!r} is not a Stage 2 denoiser (stage2_*)")
    return model


def train_stage2(
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    config: Stage2TrainConfig | str | os.PathLike[str],
    *,
    stage1: str | os.PathLike[str] | None = None,
    latents: str | os.PathLike[str] | None = None,
    resume: bool = False,
    stop_after: int | None = None,
    progress: bool = True,
) -> Stage2Run:
    """Trains the Stage 2 denoiser of ``config`` on the frame cache ``shards`` into ``out``.

    ``stage1``: the Stage 1 checkpoint (overrides the config's ``stage1_checkpoint``): its VAE
    encodes the latents and, for ``geometry: stage1``, its adapter builds the history's Gaussians.
    ``latents``: where the latent cache is (default ``out/latents``); computed there first when
    missing or unfinished. ``resume``: continue ``out`` from its newest checkpoint; ``stop_after``:
    leave after this many steps in all. Returns the run; the final weights are
    ``out/model.safetensors``.

    Example::

        run = train_stage2("cache/", "runs/stage2", "configs/stage2/tiny.yaml",
                           stage1="runs/stage1-tiny/model.safetensors", steps=500)
    """
    cfg = config if isinstance(config, Stage2TrainConfig) else Stage2TrainConfig.load(config)
    if stage1 is not None:
        cfg = dataclasses.replace(cfg, stage1_checkpoint=str(stage1))
    out = Path(out)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    with process_group() as group:
        if cfg.batch_size % group.world_size:
            raise ValueError(
                f"batch_size {cfg.batch_size} must divide by the number of processes ({group.world_size})"
            )
        latent_dir = Path(latents) if latents else out / "latents"
        return _train(Path(shards), out, cfg, group, latent_dir, resume, stop_after, progress)


def _train(
    shards: Path,
    out: Path,
    cfg: Stage2TrainConfig,
    group: ProcessGroup,
    latent_dir: Path,
    resume: bool,
    stop_after: int | None,
    progress: bool,
) -> Stage2Run:
    out.mkdir(parents=True, exist_ok=True)
    resume_from = check_run_folder(out, cfg, resume)
    stage1 = load_stage1(cfg.stage1_checkpoint)
    tc = int(stage1.vae.config.temporal_compression)
    if group.is_main:
        data_cfg = cfg.data_config()
        precompute_stage2(
            shards, latent_dir, stage1, data_cfg, stage1_checkpoint=cfg.stage1_checkpoint, progress=progress
        )
    group.barrier()
    data = Stage2Latents(latent_dir)
    del stage1
    torch.manual_seed(cfg.seed)
    stats = latent_statistics(data) if cfg.latent_norm else None
    model = build_denoiser(cfg, int(data[0].z_target.shape[1]), stats)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    if resume_from is not None:
        loaded = load_stage2(resume_from / "model.safetensors")
        if loaded.config != model.config:
            raise CheckpointError(f"{resume_from}: checkpoint of another denoiser config than {cfg.model}")
        model.load_state_dict(loaded.state_dict())
        state = load_training_state(resume_from)
        restore_optimizer(optimizer, state)
        start = state.step
        log.info("resuming %s at step %d", out, start)
    if group.is_main:
        write_text_atomic(out / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    trainee: torch.nn.Module = model
    if group.world_size > 1:
        trainee = torch.nn.parallel.DistributedDataParallel(model)
    metrics = (
        MetricsLog(out, LOG_COLUMNS, resume_step=start if resume_from is not None else None)
        if group.is_main
        else None
    )
    local = cfg.batch_size // group.world_size
    params = model.num_parameters()
    log.info(
        "stage2 %s: %d windows, %d parameters, steps %d..%d", cfg.model, len(data), params, start, cfg.steps
    )
    model.train()
    divergence = DivergenceCheck(out, cfg.lr, cfg.weight_decay)
    last: dict[str, float] = {}
    t_start = time.perf_counter()
    end = cfg.steps if stop_after is None else min(cfg.steps, stop_after)
    bar = tqdm(range(start, end), initial=start, total=cfg.steps, disable=not (progress and group.is_main))
    try:
        for step in bar:
            t0 = time.perf_counter()
            lr = restarted_cosine_lr(step, cfg)
            for pg in optimizer.param_groups:
                pg["lr"] = lr
            g = step_generator(cfg.seed, step, group.rank)
            index = torch.randint(len(data), (local,), generator=g).tolist()
            batch = make_batch([data[i] for i in index], cfg.uncertainty, tc, model)
            loss, extra = stage2_loss(trainee, batch, cfg, g)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            mean = group.mean(
                torch.stack([loss.detach(), torch.tensor(extra["t_mean"]), torch.tensor(extra["dropped"])])
            )
            divergence.losses(step + 1, {"loss": float(mean[0])})
            grad_norm = divergence.clip_gradients(step + 1, model.named_parameters(), cfg.grad_clip)
            optimizer.step()
            divergence.weights_after(step + 1, model.named_parameters())
            last = {
                "loss": float(mean[0]),
                "lr": lr,
                "grad_norm": float(grad_norm),
                "t_mean": float(mean[1]),
                "dropped": float(mean[2]),
                "seconds": time.perf_counter() - t0,
            }
            if metrics is not None:
                metrics.log(step + 1, last)
            bar.set_postfix(loss=f"{last['loss']:.4f}")
            if group.is_main and ((step + 1) % cfg.checkpoint_every == 0 or step + 1 == cfg.steps):
                save_training_state(out, step + 1, model, optimizer, {"config": cfg.to_dict()})
            group.barrier()
    finally:
        if metrics is not None:
            metrics.close()
    final = None
    if group.is_main and end == cfg.steps:
        summary = {
            "steps": end,
            "windows": len(data),
            "latents": str(latent_dir),
            "uncertainty": cfg.uncertainty,
        }
        final = save_checkpoint(out / "model.safetensors", model, summary | {"train": cfg.to_dict()})
        write_text_atomic(out / "summary.json", json.dumps(summary | {"last": last}, indent=2))
    return Stage2Run(out, final, latent_dir, end, last, time.perf_counter() - t_start)
