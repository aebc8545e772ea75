"""Training the causal video VAE on a cache's camera clips (``phigenesis-train vae``).

Entry point: :func:`train_vae`. Stage 1 of the paper runs a *frozen* video VAE over every camera's
video; this trains the toolkit's own (:mod:`phigenesis.models.vae`) on the cache it will serve.

- **Clips.** A clip is ``frames`` consecutive frames of one camera (matched by name) within one
  scene: every window of :func:`~phigenesis.data.views.scene_windows` (stride 1), every camera
  with an image in all of its frames. Images are area-resized to ``size`` = (H, W) pixels and
  scaled to [-1, 1]; ``frames - 1`` must divide by the VAE's temporal compression and H, W by its
  spatial one.
- **Validation by scene.** A share ``val_fraction`` of the scenes (at least one; chosen with
  ``seed``) is held out. A cache of one scene holds out its last frames instead (at least one
  clip's worth; clips that straddle the cut are dropped). Validation reconstructs up to
  ``val_clips`` clips from the posterior mean and reports PSNR in dB (peak-to-peak 2, the [-1, 1]
  range; reconstructions clamped to it), mean L1 and KL (nats per clip).
- **Optimisation.** AdamW, linear warm-up then cosine decay (:func:`~phigenesis.train.runner.cosine_lr`),
  gradient-norm clipping, loss :func:`~phigenesis.models.vae.vae_loss`, random horizontal flips.
- **Reproducible and resumable.** Every random draw of a step (which clips, flips, the posterior
  sample) comes from :func:`~phigenesis.train.runner.step_generator` (seed, step, rank), so a run
  resumed from a checkpoint writes the same loss curve as one never interrupted.
- **Run folder** (:mod:`phigenesis.train.runner`): ``config.yaml``, ``metrics.csv`` and ``tb/``
  (loss, reconstruction, kl, lr, grad_norm each step; val_psnr, val_recon, val_kl at each
  checkpoint), ``checkpoints/``, and at the end ``model.safetensors`` (the VAE, meta: steps,
  val_psnr_db, size, frames, ...) and ``metrics.json``.
- **torchrun.** With ``WORLD_SIZE > 1`` the model is wrapped in DistributedDataParallel over gloo;
  each rank draws ``batch_size / world_size`` clips; only rank 0 writes files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
import yaml
from torch import nn

from phigenesis import limits
from phigenesis.data.records import InvalidRecord, decode_whole
from phigenesis.data.schema import cameras_of
from phigenesis.data.shards import CacheReader
from phigenesis.data.views import resize_images, scene_windows
from phigenesis.errors import CacheError
from phigenesis.models import create_model
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.config_checks import check_model_name
from phigenesis.models.vae import VideoVAE, vae_loss
from phigenesis.options import check_options, option
from phigenesis.train.checkpoint import save_checkpoint
from phigenesis.train.runner import (
    DivergenceCheck,
    MetricsLog,
    ProcessGroup,
    checkpoint_to_resume,
    cosine_lr,
    latest_checkpoint,
    load_training_state,
    process_group,
    read_metrics,
    read_run_config,
    restore_optimizer,
    run_evidence,
    save_training_state,
    step_generator,
    write_text_atomic,
)

log = logging.getLogger("phigenesis.train")

#: Per-step columns of ``metrics.csv``; the ``val_*`` ones are filled at checkpoints only.
STEP_COLUMNS = ("loss", "reconstruction", "kl", "lr", "grad_norm")
VAL_COLUMNS = ("val_psnr", "val_recon", "val_kl")
VAL_KEYS = {"psnr": "psnr_db", "recon": "recon_l1", "kl": "kl"}
#: Options that may change between a run and its resumption (they do not change the loss curve).
RESUMABLE_CHANGES = ("threads", "log_every", "device", "checkpoint_every", "val_clips")


@dataclass(frozen=True)
class VAETrainConfig:
    """Options of :func:`train_vae`.

    Attributes:
        model: registered VAE variant (``phigenesis.models.list_models("vae")``).
        frames: frames per clip (T); ``T - 1`` must divide by the temporal compression.
        size: (H, W) pixels clips are resized to; each must divide by the spatial compression.
        steps: optimiser steps (the length of the learning-rate schedule).
        batch_size: clips per step, over all processes.
        lr: peak learning rate (AdamW).
        weight_decay: AdamW weight decay of convolution kernels (not of norms and biases).
        warmup_steps: linear warm-up steps; None: ``min(100, steps // 10)``.
        grad_clip: gradient-norm clip.
        kl_weight: beta of :func:`~phigenesis.models.vae.vae_loss` (per-element KL weight).
        reconstruction: "l1" or "l2" reconstruction loss.
        flip: random horizontal flips of training clips.
        val_fraction: share of the scenes held out for validation (0: none).
        val_clips: at most this many validation clips (evenly spaced) are reconstructed.
        checkpoint_every: steps between checkpoints (and validations); the last step always has one.
        log_every: steps between progress log lines.
        seed: seeds the split, the initialisation and every step's draws.
        threads: torch CPU threads (None: torch's default).
        device: torch device.
        init: start from the weights of this checkpoint (it must be of ``model``, same config).
        image_cache_bytes: memory for decoded, resized images kept between steps.
    """

    model: str = option("vae_tiny")
    frames: int = option(5, ge=1, le=1024)
    size: tuple[int, int] = option((48, 72), ge=1, le=limits.MAX_IMAGE_SIDE)
    steps: int = option(2000, ge=1, le=limits.MAX_STEPS)
    batch_size: int = option(8, ge=1, le=limits.MAX_BATCH)
    lr: float = option(1e-3, gt=0, le=limits.MAX_LR)
    weight_decay: float = option(0.0, ge=0, le=limits.MAX_WEIGHT_DECAY)
    warmup_steps: int | None = option(None, ge=0, le=limits.MAX_STEPS)
    grad_clip: float = option(1.0, gt=0, le=limits.MAX_GRAD_CLIP)
    kl_weight: float = option(1e-6, ge=0, le=limits.MAX_LOSS_WEIGHT)
    reconstruction: Literal["l1", "l2"] = option("l1")
    flip: bool = option(True)
    val_fraction: float = option(0.2, ge=0, lt=1)
    val_clips: int = option(32, ge=1, le=1_000_000)
    checkpoint_every: int = option(500, ge=1, le=limits.MAX_STEPS)
    log_every: int = option(10, ge=1, le=limits.MAX_STEPS)
    seed: int = option(0, ge=0, le=limits.MAX_SEED)
    threads: int | None = option(None, ge=1, le=limits.MAX_THREADS)
    device: str = option("cpu")
    init: str | None = option(None)
    image_cache_bytes: int = option(1 << 30, ge=0, le=1 << 50)

    def __post_init__(self) -> None:
        check_options(self, "VAETrainConfig")
        check_model_name(self.model, "vae", "VAETrainConfig")

    @property
    def warmup(self) -> int:
        return self.warmup_steps if self.warmup_steps is not None else min(100, self.steps // 10)

    def to_dict(self) -> dict[str, Any]:
        """Plain values (tuples as lists), as written to ``config.yaml``."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


@dataclass(frozen=True)
class Clip:
    """``len(frames)`` consecutive frames (global indices) of one camera of one scene."""

    scene: str
    frames: tuple[int, ...]
    camera: str


@dataclass
class VAERun:
    """What :func:`train_vae` produced.

    Attributes:
        out: the run folder.
        checkpoint: ``out/model.safetensors`` when the run finished, else the newest training
            checkpoint's ``model.safetensors`` (``stop_after``).
        step: steps done.
        finished: whether all ``steps`` are done and the final files written.
        val: validation metrics of the final model (``psnr_db``, ``recon_l1``, ``kl``, ``clips``);
            empty without validation clips, on ranks other than 0 and when stopped early.
        train_scenes, val_scenes: the split.
    """

    out: Path
    checkpoint: Path
    step: int
    finished: bool
    val: dict[str, float]
    train_scenes: list[str]
    val_scenes: list[str]


# --------------------------------------------------------------------------------------------
# Data


def check_shapes(model: str, frames: int, size: tuple[int, int]) -> None:
    """Raises ValueError unless clips of ``frames`` frames at ``size`` fit VAE variant ``model``."""
    config = create_model(model).config
    s, r = config.spatial_compression, config.temporal_compression
    if size[0] % s or size[1] % s:
        raise ValueError(
            f"size {size[0]}x{size[1]}: height and width must divide by {s}, the spatial compression "
            f"of {model} (e.g. {max(s, size[0] // s * s)}x{max(s, size[1] // s * s)})"
        )
    if (frames - 1) % r:
        raise ValueError(
            f"frames={frames}: frames - 1 must divide by {r}, the temporal compression of {model} "
            f"(e.g. {1 + max(1, (frames - 1) // r) * r})"
        )


def camera_images(reader: CacheReader) -> list[dict[str, int]]:
    """Per global frame: the cameras (name -> index in the frame's rig order) that have an image."""
    out = []
    for frame in range(len(reader)):
        cf = cameras_of(reader.read(frame, ["cameras"]))
        names, images = cf["camera_name"].to_pylist(), cf["image"]
        out.append({name: k for k, name in enumerate(names) if images[k].is_valid})
    return out


def list_clips(reader: CacheReader, frames: int) -> list[Clip]:
    """Every clip of ``frames`` frames of the cache, scene by scene, window by window, camera by
    camera (rig order). Raises ValueError naming the cache when there is none, saying why."""
    where = reader.cache_dir
    if len(reader) == 0:
        raise ValueError(f"{where}: the cache has no frames")
    available = camera_images(reader)
    if not any(available):
        raise ValueError(f"{where}: the cache has no camera images to train a VAE on")
    clips = []
    for scene, window in scene_windows(reader, frames):
        for name in available[window[0]]:
            if all(name in available[f] for f in window):
                clips.append(Clip(scene, tuple(window), name))
    if not clips:
        longest = max(len(reader.frames_of(s)) for s in reader.scene_ids())
        raise ValueError(
            f"{where}: no clip of {frames} consecutive frames of one camera (the longest scene has "
            f"{longest} frames); lower --frames"
        )
    return clips


def split_clips(
    clips: list[Clip], frames: int, val_fraction: float, seed: int
) -> tuple[list[str], list[str], list[Clip], list[Clip]]:
    """(train scenes, validation scenes, train clips, validation clips).

    ``val_fraction`` of the scenes (at least one when there are two or more and the fraction is
    > 0) are held out, chosen with ``seed``. A single scene holds out its last
    ``max(frames, val_fraction * n)`` frames when at least one clip's worth stays for training;
    clips that cross the cut belong to neither side.
    """
    scenes = sorted({c.scene for c in clips})
    if val_fraction == 0:
        return scenes, [], clips, []
    if len(scenes) == 1:
        all_frames = sorted({f for c in clips for f in c.frames})
        n_val = max(frames, round(val_fraction * len(all_frames)))
        if len(all_frames) - n_val < frames:
            log.warning("one scene of %d frames: too short to hold any out, no validation", len(all_frames))
            return scenes, [], clips, []
        cut = all_frames[len(all_frames) - n_val]
        log.warning("only one scene: holding out its last %d frames for validation", n_val)
        train = [c for c in clips if c.frames[-1] < cut]
        return scenes, scenes, train, [c for c in clips if c.frames[0] >= cut]
    order = np.random.default_rng(seed).permutation(len(scenes))
    n_val = min(len(scenes) - 1, max(1, round(val_fraction * len(scenes))))
    val = sorted(scenes[k] for k in order[:n_val])
    train = [s for s in scenes if s not in val]
    return train, val, [c for c in clips if c.scene in train], [c for c in clips if c.scene in val]


class ClipImages:
    """Camera images of a cache, decoded and resized on first use and kept (least recently used
    out) within ``cache_bytes``; clips come out as float video ``[B, 3, T, H, W]`` in [-1, 1]."""

    def __init__(self, reader: CacheReader, size: tuple[int, int], cache_bytes: int = 1 << 30):
        self.reader, self.size = reader, size
        self.capacity = max(1, cache_bytes // (3 * size[0] * size[1]))
        self._cache: OrderedDict[tuple[int, str], torch.Tensor] = OrderedDict()

    def image(self, frame: int, camera: str) -> torch.Tensor:
        """uint8 ``[3, H, W]`` RGB of ``camera`` at global frame ``frame``, at ``size``."""
        key = (frame, camera)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        cf = cameras_of(self.reader.read(frame, ["cameras"]))
        k = cf["camera_name"].to_pylist().index(camera)
        data = np.frombuffer(cf["image"][k].as_buffer(), np.uint8)
        try:
            bgr = decode_whole(data, cv2.IMREAD_COLOR, "image")
        except InvalidRecord as e:
            path, row = self.reader.locate(frame)
            raise CacheError(f"{path}: row {row}: camera {camera}: {e}") from None
        rgb = torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1)  # [3, h, w]
        image = (resize_images(rgb, self.size) * 255.0).round().to(torch.uint8)  # [3, H, W]
        self._cache[key] = image
        if len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return image

    def video(self, clips: Sequence[Clip], flips: Sequence[bool] | None = None) -> torch.Tensor:
        """Float32 ``[B, 3, T, H, W]`` in [-1, 1] of ``clips`` (mirrored left-right where ``flips``)."""
        videos = []
        for i, clip in enumerate(clips):
            v = torch.stack([self.image(f, clip.camera) for f in clip.frames], dim=1)  # [3, T, H, W]
            videos.append(v.flip(-1) if flips is not None and flips[i] else v)
        return torch.stack(videos).float() / 127.5 - 1.0


# --------------------------------------------------------------------------------------------
# Training


def psnr_db(reconstruction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``[B]`` PSNR in dB of videos ``[B, 3, T, H, W]`` in [-1, 1] (peak-to-peak 2; the
    reconstruction is clamped to the range first)."""
    mse = (reconstruction.clamp(-1.0, 1.0) - target).square().flatten(1).mean(dim=1)
    return 10.0 * torch.log10(4.0 / mse.clamp_min(1e-12))


@torch.no_grad()
def evaluate(
    model: VideoVAE, images: ClipImages, clips: Sequence[Clip], batch_size: int = 4, device: str = "cpu"
) -> dict[str, float]:
    """Validation of ``model`` on ``clips`` reconstructed from the posterior mean: ``psnr_db``
    (mean over clips), ``recon_l1`` (mean absolute error in [-1, 1] units), ``kl`` (nats per clip)."""
    if not clips:
        return {}
    was_training = model.training
    model.eval()
    psnr, l1, kl = [], [], []
    for i in range(0, len(clips), batch_size):
        x = images.video(clips[i : i + batch_size]).to(device)
        posterior = model.encode(x)
        rec = model.decode(posterior.mode())
        psnr.append(psnr_db(rec, x))
        l1.append((rec - x).abs().flatten(1).mean(dim=1))
        kl.append(posterior.kl())
    model.train(was_training)
    return {
        "psnr_db": float(torch.cat(psnr).mean()),
        "recon_l1": float(torch.cat(l1).mean()),
        "kl": float(torch.cat(kl).mean()),
        "clips": len(clips),
    }


def make_optimizer(model: nn.Module, cfg: VAETrainConfig) -> torch.optim.Optimizer:
    """AdamW with weight decay on convolution kernels only (not on norms and biases)."""
    decay = [p for p in model.parameters() if p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.ndim <= 1]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=cfg.lr)


#: What runs between a step's backward pass and its update (see :func:`train_step`).
ClipGradients = Callable[[dict[str, torch.Tensor]], float]


def train_step(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    video: torch.Tensor,
    cfg: VAETrainConfig,
    lr: float,
    generator: torch.Generator,
    clip: ClipGradients | None = None,
) -> dict[str, torch.Tensor]:
    """One optimiser step on ``video`` ``[B, 3, T, H, W]`` in [-1, 1]; the posterior sample is
    drawn from ``generator``. ``clip`` is called between the backward pass and the update with the
    (local) loss terms: it clips the gradients to ``cfg.grad_clip`` and returns their norm before
    clipping (default: ``clip_grad_norm_``; the trainer's, :class:`_CheckedClip`, first stops a
    run that diverged). Returns the (local) loss terms and that gradient norm."""
    for group in optimizer.param_groups:
        group["lr"] = lr
    # The noise generator lives on the model's device; its seed is a draw of the step's generator.
    noise = torch.Generator(video.device).manual_seed(int(torch.randint(2**62, (1,), generator=generator)))
    output = model(video, generator=noise)
    terms = vae_loss(output, video, beta=cfg.kl_weight, reconstruction=cfg.reconstruction)
    optimizer.zero_grad(set_to_none=True)
    terms["loss"].backward()
    terms = {k: v.detach() for k, v in terms.items()}
    if clip is None:
        grad_norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip))
    else:
        grad_norm = clip(terms)
    optimizer.step()
    return terms | {"grad_norm": torch.tensor(grad_norm)}


@dataclass
class _CheckedClip:
    """The trainer's ``clip`` of :func:`train_step`: averages the loss terms over the processes
    (kept in ``values`` for the log), stops the run at a non-finite term or gradient
    (:class:`DivergenceCheck`), then clips the gradients. ``step`` (1-based) is set per step."""

    pg: ProcessGroup
    divergence: DivergenceCheck
    model: nn.Module
    max_norm: float
    step: int = 0
    values: dict[str, float] = field(default_factory=dict)

    def __call__(self, terms: dict[str, torch.Tensor]) -> float:
        mean = self.pg.mean(torch.stack([terms["loss"], terms["reconstruction"], terms["kl"]]).cpu())
        self.values = dict(zip(("loss", "reconstruction", "kl"), mean.tolist(), strict=True))
        self.divergence.losses(self.step, self.values)
        return self.divergence.clip_gradients(self.step, self.model.named_parameters(), self.max_norm)


def draw_batch(
    clips: Sequence[Clip], batch: int, flip: bool, generator: torch.Generator
) -> tuple[list[Clip], list[bool]]:
    """``batch`` clips drawn with replacement and their flips, from ``generator`` only."""
    index = torch.randint(len(clips), (batch,), generator=generator).tolist()
    flips = (torch.rand(batch, generator=generator) < 0.5).tolist()
    return [clips[i] for i in index], [f and flip for f in flips]


def _check_run_folder(out: Path, cfg: dict[str, Any], resume: bool) -> Path | None:
    """The checkpoint folder to resume from (None: start at step 0); refuses to overwrite a run
    unless ``resume``, to resume one whose configuration differs in fields that shape the loss
    curve, and to restart one with logged steps but no usable checkpoint."""
    if not resume:
        if run_evidence(out) is not None:
            raise ValueError(
                f"{out}: already holds a run (checkpoints or model.safetensors); pass resume=True "
                "(--resume) to continue it, or choose another folder"
            )
        return None
    folder = checkpoint_to_resume(out)
    if folder is None:
        log.info("%s: no checkpoint to resume from; starting at step 0", out)
        return None
    stored = read_run_config(out)
    if stored is not None:
        differ = sorted(
            k for k in set(stored) | set(cfg) if k not in RESUMABLE_CHANGES and stored.get(k) != cfg.get(k)
        )
        if differ:
            raise ValueError(
                f"{out}: cannot resume with other options than the run's config.yaml (differing: "
                f"{', '.join(differ)}); start a new folder (--init {folder / 'model.safetensors'})"
            )
    return folder


def train_vae(
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: str = "vae_tiny",
    resume: bool = False,
    stop_after: int | None = None,
    progress: Callable[[dict[str, float]], None] | None = None,
    **options: Any,
) -> VAERun:
    """Trains VAE variant ``config`` on the camera clips of the cache at ``shards`` into the run
    folder ``out`` (see the module docstring).

    ``options`` are :class:`VAETrainConfig` fields (``frames``, ``size``, ``steps``,
    ``batch_size``, ``lr``, ``kl_weight``, ``val_fraction``, ``checkpoint_every``, ``seed``,
    ``threads``, ``init``, ...). ``resume``: continue from the newest checkpoint in ``out``
    (without it, a folder that holds a run is refused). ``stop_after``: leave after this many
    steps in all (the schedule still spans ``steps``) with a checkpoint to resume from.
    ``progress`` is called with each step's logged values (and ``step``).

    Raises ValueError (naming the cache) for a cache without frames, images or a single clip,
    and for a ``size`` or ``frames`` the VAE cannot take; CheckpointError for an ``init`` of
    another config.

    Example::

        run = train_vae("cache/", "runs/vae", config="vae_tiny", steps=2000, size=(48, 72))
        print(run.val["psnr_db"], run.checkpoint)
    """
    cfg = VAETrainConfig(model=config, **options)
    out = Path(out)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    check_shapes(cfg.model, cfg.frames, cfg.size)
    with process_group() as pg:
        if cfg.batch_size % pg.world_size:
            raise ValueError(
                f"batch_size {cfg.batch_size} must divide by the number of processes ({pg.world_size})"
            )
        return _train(Path(shards), out, cfg, pg, resume, stop_after, progress)


def _train(
    shards: Path,
    out: Path,
    cfg: VAETrainConfig,
    pg: ProcessGroup,
    resume: bool,
    stop_after: int | None,
    progress: Callable[[dict[str, float]], None] | None,
) -> VAERun:
    reader = CacheReader(shards)
    clips = list_clips(reader, cfg.frames)
    train_scenes, val_scenes, train_clips, val_clips = split_clips(
        clips, cfg.frames, cfg.val_fraction, cfg.seed
    )
    if not train_clips:
        raise ValueError(f"{shards}: no training clips left after holding out {val_scenes}")
    if len(val_clips) > cfg.val_clips:
        keep = np.linspace(0, len(val_clips) - 1, cfg.val_clips).round().astype(int)
        val_clips = [val_clips[k] for k in keep]
    recorded = {**cfg.to_dict(), "cache": str(shards.resolve())}
    folder = _check_run_folder(out, recorded, resume)
    state = load_training_state(folder) if folder is not None else None
    start = state.step if state is not None else 0
    stop = min(cfg.steps, stop_after if stop_after is not None else cfg.steps)

    torch.manual_seed(cfg.seed)
    model: VideoVAE = (
        load_checkpoint(cfg.init, cfg.model).model if cfg.init is not None else create_model(cfg.model)
    )
    model.to(cfg.device).train()
    optimizer = make_optimizer(model, cfg)
    if folder is not None and state is not None:
        model.load_state_dict(load_checkpoint(folder / "model.safetensors", cfg.model).model.state_dict())
        restore_optimizer(optimizer, state)
    net: nn.Module = model
    if pg.world_size > 1:
        net = nn.parallel.DistributedDataParallel(model)
    images = ClipImages(reader, cfg.size, cfg.image_cache_bytes)

    metrics = None
    if pg.is_main:
        out.mkdir(parents=True, exist_ok=True)
        if state is None:
            write_text_atomic(out / "config.yaml", yaml.safe_dump(recorded, sort_keys=False))
        metrics = MetricsLog(
            out, STEP_COLUMNS + VAL_COLUMNS, resume_step=start if state is not None else None
        )
    log.info(
        "vae %s: %d training clips (%d scenes), %d validation clips (%d scenes), steps %d..%d of %d, "
        "%d process(es)",
        cfg.model, len(train_clips), len(train_scenes), len(val_clips), len(val_scenes), start, stop,
        cfg.steps, pg.world_size,
    )  # fmt: skip
    local_batch = cfg.batch_size // pg.world_size
    divergence = DivergenceCheck(out, cfg.lr, cfg.weight_decay, {"kl": ("kl_weight", cfg.kl_weight)})
    clip = _CheckedClip(pg, divergence, model, cfg.grad_clip)
    tic, val = time.perf_counter(), {}
    try:
        for step in range(start, stop):
            g = step_generator(cfg.seed, step, pg.rank)
            batch, flips = draw_batch(train_clips, local_batch, cfg.flip, g)
            video = images.video(batch, flips).to(cfg.device)
            lr = cosine_lr(step, cfg.steps, cfg.lr, cfg.warmup)
            clip.step = step + 1
            terms = train_step(net, optimizer, video, cfg, lr, g, clip)
            divergence.weights_after(step + 1, model.named_parameters())
            values = clip.values | {"lr": lr, "grad_norm": float(terms["grad_norm"])}
            done = step + 1
            checkpoint = done % cfg.checkpoint_every == 0 or done == stop
            if checkpoint and pg.is_main:
                val = evaluate(model, images, val_clips, device=cfg.device)
                if val:
                    values |= {f"val_{k}": val[v] for k, v in VAL_KEYS.items()}
            # The row goes in before the checkpoint: a run stopped between the two resumes from the
            # checkpoint before and writes the row again, never one without it.
            if metrics is not None:
                metrics.log(done, values)
            if checkpoint:
                if pg.is_main:
                    save_training_state(out, done, model, optimizer)
                pg.barrier()
            if done % cfg.log_every == 0 or done == stop:
                rate = (time.perf_counter() - tic) / (done - start)
                extra = f", val PSNR {values['val_psnr']:.2f} dB" if "val_psnr" in values else ""
                log.info(
                    "step %d/%d: loss %.4f recon %.4f kl %.1f lr %.2e grad %.3f (%.2f s/step)%s",
                    done, cfg.steps, values["loss"], values["reconstruction"], values["kl"], lr,
                    values["grad_norm"], rate, extra,
                )  # fmt: skip
            if progress is not None:
                progress({"step": done, **values})
    finally:
        if metrics is not None:
            metrics.close()

    done = max(start, stop)
    if done < cfg.steps:
        kept = latest_checkpoint(out)
        return VAERun(out, (kept or out) / "model.safetensors", done, False, {}, train_scenes, val_scenes)
    final = out / "model.safetensors"
    if pg.is_main:
        if not val:  # resumed after the last step: nothing trained in this call
            val = evaluate(model, images, val_clips, device=cfg.device)
        split = {"train_scenes": train_scenes, "val_scenes": val_scenes}
        counts = {"train_clips": len(train_clips), "val_clips": len(val_clips)}
        _write_final(out, model, recorded, val, split, counts)
    pg.barrier()
    return VAERun(out, final, cfg.steps, True, val if pg.is_main else {}, train_scenes, val_scenes)


def _write_final(
    out: Path,
    model: VideoVAE,
    recorded: dict[str, Any],
    val: dict[str, float],
    split: dict[str, list[str]],
    counts: dict[str, int],
) -> None:
    """Writes ``out/model.safetensors`` (meta: steps, val_psnr_db, size, frames, the options, the
    split, the validation) and ``out/metrics.json`` (the same plus every validation of the run and
    the mean training loss of the last 10 steps)."""
    meta = {
        "steps": recorded["steps"],
        "val_psnr_db": val.get("psnr_db"),
        "size": recorded["size"],
        "frames": recorded["frames"],
        "training": recorded,
        **split,
        "val": val,
    }
    final = save_checkpoint(out / "model.safetensors", model, meta)
    rows = read_metrics(out)
    history = [
        {"step": int(r["step"]), **{k: r[k] for k in VAL_COLUMNS if k in r}} for r in rows if "val_psnr" in r
    ]
    last = [r["loss"] for r in rows[-10:]]
    summary = {
        **meta,
        **counts,
        "final_train_loss": float(np.mean(last)) if last else None,
        "history": history,
    }
    write_text_atomic(out / "metrics.json", json.dumps(summary, indent=1))
    if val:
        log.info("val PSNR %.2f dB on %d clips; wrote %s", val["psnr_db"], val["clips"], final)
