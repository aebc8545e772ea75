"""``phigenesis-train stage1``: trains the range-view adapter of a Stage 1 model on a cache.

Each step draws ``batch_size`` clips (context frames + targets, see :mod:`phigenesis.data.clips`)
from a generator seeded by (seed, step, rank), predicts the clips' Gaussians with the frozen VAE and
the adapter, renders them at every target view at its own capture time (the sky model fills what
no Gaussian covers) and minimises:

- ``rgb``: ``0.8 L1 + 0.2 (1 - SSIM)`` of the rendered views against the images;
- ``depth``: confidence-weighted ``|log z - log z_gt|`` of the rendered depth and of the per-pixel
  depth against the cache's dense depth (each target weighs ``floor + (1 - floor) confidence``,
  ``depth_confidence_floor``); ``smooth``: edge-aware smoothness of the per-pixel inverse
  depth (it carries depth to pixels the LiDAR never reached);
- ``depth_ce`` (bins head only): confidence-weighted cross-entropy of the per-pixel depth-bin
  logits against the bin of the dense depth (DrivingRecon's classification loss; the residual is
  trained by ``pixel_depth``);
- ``target_semantic``: cross-entropy of the rendered class probabilities (normalised by alpha) at
  the target views against their labels, on pixels the render covers (alpha >= 0.5): a target
  frame the model did not see is only right where the geometry puts each Gaussian where it belongs;
- ``semantic``: cross-entropy of the per-pixel logits against the labels (synthetic truth where the
  cache has it, else the pseudo labels), plus ``-log(1 - p_sky)`` on unlabelled pixels that have a
  dense depth (a surface is never sky);
- ``dynamic``: binary cross-entropy of the per-pixel dynamic logit against the moving-box mask, and
  ``velocity``: L1 of the world-frame velocity against the box's on moving pixels;
- ``motion`` regulariser: mean |soft velocity| (what does not move should not carry motion);
- ``opacity`` regulariser: mean rendered alpha on sky pixels (sky spawns nothing and stays empty).

Pixels labelled sky spawn no Gaussians. AdamW, warm-up + cosine learning rate, gradient clipping;
checkpoints (safetensors) every ``checkpoint_every`` steps and exact resume (see
:mod:`phigenesis.train.runner`); under ``torchrun`` the ranks share the batch over gloo. A
non-finite loss term, gradient or weight stops the run at that step, naming the term and the
config value most likely at fault (``runner.DivergenceCheck``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
import yaml
from torch import Tensor
from tqdm import tqdm

from phigenesis import limits
from phigenesis.data.clips import Clip, Stage1Clips, ViewSet, clip_inputs
from phigenesis.data.memory_cache import BoundedCache, tensor_bytes
from phigenesis.errors import argument
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.config_checks import check_model_name, check_model_overrides, create_overridden
from phigenesis.models.depth_bins import DepthBins
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.losses import edge_aware_smoothness, log_depth_loss, photometric_loss, semantic_loss
from phigenesis.models.stage1 import Stage1Model, Stage1Prediction
from phigenesis.options import ConfigError, check_options, from_mapping, option
from phigenesis.taxonomy import GROUND_IDS, IGNORE_ID, SKY
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint
from phigenesis.train.runner import (
    DivergenceCheck,
    MetricsLog,
    ProcessGroup,
    checkpoint_to_resume,
    cosine_lr,
    load_training_state,
    process_group,
    read_run_config,
    restore_optimizer,
    run_evidence,
    save_training_state,
    step_generator,
    write_text_atomic,
)
from phigenesis.user_files import read_config_file

log = logging.getLogger(__name__)

LOSS_NAMES = (
    "rgb",
    "depth",
    "pixel_depth",
    "depth_ce",
    "smooth",
    "semantic",
    "target_semantic",
    "dynamic",
    "velocity",
    "motion",
    "opacity",
    "ground",
)
LOG_COLUMNS = ("loss", *LOSS_NAMES, "lr", "grad_norm", "gaussians", "seconds")
SemanticTarget = Literal["auto", "pseudo", "truth"]


@dataclass(frozen=True)
class Stage1TrainConfig:
    """A Stage 1 training run (``configs/stage1/*.yaml`` holds these fields).

    Attributes:
        model: registered Stage 1 variant; ``model_overrides`` replaces fields of its config.
        vae_checkpoint: a trained VAE (``phigenesis-train vae``) whose config matches the model's
            VAE; None keeps the VAE at its initialisation (only for tests).
        steps, batch_size: optimiser steps and clips per step (over all processes).
        lr, weight_decay, warmup_steps, final_lr_ratio, grad_clip: AdamW with warm-up + cosine.
        target_offset: targets are the context frames and ``targets_per_clip`` other frames, each
            up to this many frames before or after the clip's last context frame.
        targets_per_clip: frames besides the context drawn as targets per clip (distinct offsets).
        semantic_target: "auto" (synthetic truth where the cache has it, else the pseudo labels, as
            ``phigenesis-train segmenter --labels auto`` prefers the best labels), "pseudo" or "truth".
        weights: weight of each loss term (``LOSS_NAMES``).
        depth_confidence_floor: the depth terms (``depth``, ``pixel_depth``, ``depth_ce``) weigh a
            dense-depth target by ``floor + (1 - floor) * confidence`` (:func:`depth_target_weight`):
            0 weighs by the cache's confidence alone, 1 weighs every target alike. The cache's
            confidence orders its targets' reliability but is not a probability: even its
            low-confidence targets are mostly right (docs/design/stage1.md, "Every depth target
            weighed alike").
        checkpoint_every, log_every: in steps.
        seed: seed of the initialisation and of every step's draws.
        threads: torch CPU threads per process (None: torch's default).
        cache_mb: memory per process (MiB) for what a clip costs to prepare and the weights do not
            change, kept between the steps that draw it again: a third for its frames decoded and
            resized, two thirds for the frozen VAE's features of its context (:class:`VaeFeatureCache`).
            The results are the same with any value; 0 keeps nothing.
    """

    model: str = option("stage1_tiny")
    model_overrides: dict[str, Any] = option(factory=dict)
    vae_checkpoint: str | None = option(None)
    steps: int = option(1000, ge=1, le=limits.MAX_STEPS)
    batch_size: int = option(1, ge=1, le=limits.MAX_BATCH)
    lr: float = option(2e-3, gt=0, le=limits.MAX_LR)
    weight_decay: float = option(0.01, ge=0, le=limits.MAX_WEIGHT_DECAY)
    warmup_steps: int = option(50, ge=0, le=limits.MAX_STEPS)
    final_lr_ratio: float = option(0.05, ge=0, le=1)
    grad_clip: float = option(1.0, gt=0, le=limits.MAX_GRAD_CLIP)
    target_offset: int = option(3, ge=0, le=1000)
    targets_per_clip: int = option(1, ge=0, le=2000)
    semantic_target: SemanticTarget = option("auto")
    weights: dict[str, float] = option(
        factory=lambda: {
            "rgb": 1.0,
            "depth": 0.5,
            "pixel_depth": 0.5,
            "depth_ce": 0.05,
            "smooth": 0.2,
            "semantic": 0.2,
            "target_semantic": 0.1,
            "dynamic": 0.2,
            "velocity": 0.05,
            "motion": 0.005,
            "opacity": 0.1,
        },
        ge=0,
        le=limits.MAX_LOSS_WEIGHT,
        keys=LOSS_NAMES,
    )
    checkpoint_every: int = option(100, ge=1, le=limits.MAX_STEPS)
    log_every: int = option(10, ge=1, le=limits.MAX_STEPS)
    seed: int = option(0, ge=0, le=limits.MAX_SEED)
    threads: int | None = option(None, ge=1, le=limits.MAX_THREADS)
    cache_mb: float = option(1024.0, ge=0, le=limits.MAX_CACHE_MB)
    depth_confidence_floor: float = option(0.0, ge=0, le=1)

    def __post_init__(self) -> None:
        check_options(self, "Stage1TrainConfig")
        object.__setattr__(self, "weights", {k: self.weights.get(k, 0.0) for k in LOSS_NAMES})
        check_model_name(self.model, "stage1", "Stage1TrainConfig")
        check_model_overrides(self.model, self.model_overrides, "Stage1TrainConfig")
        if self.target_offset and self.targets_per_clip > 2 * self.target_offset:
            raise ConfigError(
                f"Stage1TrainConfig: targets_per_clip = {self.targets_per_clip}: must be at most "
                f"2 x target_offset ({2 * self.target_offset}): each target is a distinct frame"
            )

    @classmethod
    def load(cls, path: str | os.PathLike[str], **overrides: Any) -> Stage1TrainConfig:
        """The config in a YAML file, with ``overrides`` (the command line's, None: not given)
        applied. Unknown keys, values outside their type or range, and a file without the key
        ``vae_checkpoint`` when no override gives one raise :class:`ConfigError` naming the file
        (``vae_checkpoint: null`` asks for an untrained VAE, which only tests want)."""
        path = Path(path)
        values = read_config_file(path)
        given = {k: v for k, v in overrides.items() if v is not None}
        if "vae_checkpoint" not in values and not given.get("vae_checkpoint"):
            raise ConfigError(
                f"{path}: vae_checkpoint is missing: Stage 1 trains on a frozen, trained VAE "
                "(phigenesis-train vae); name its checkpoint here or pass "
                f"{argument('vae_checkpoint=', '--vae')} (null: an untrained VAE, for tests only)"
            )
        return from_mapping(cls, values, str(path), **given)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Stage1Run:
    """What :func:`train_stage1` leaves: the run folder, final weights and the last logged losses."""

    out: Path
    checkpoint: Path | None
    steps_done: int
    last: dict[str, float]
    seconds: float
    stopped_by_time: bool = False


def build_model(config: Stage1TrainConfig) -> Stage1Model:
    """The Stage 1 model of a config, with its trained VAE loaded and frozen."""
    model = create_overridden(config.model, config.model_overrides, "Stage1TrainConfig")
    assert isinstance(model, Stage1Model)
    if config.vae_checkpoint:
        if not Path(config.vae_checkpoint).exists():
            raise CheckpointError(
                f"{config.vae_checkpoint}: VAE checkpoint not found (the config's vae_checkpoint, read "
                f"relative to the working directory {os.getcwd()}); train one with phigenesis-train vae "
                f"or pass {argument('vae_checkpoint=', '--vae')} to name another"
            )
        vae = load_checkpoint(config.vae_checkpoint, kind="vae").model
        try:
            model.load_vae(vae)  # type: ignore[arg-type]
        except ValueError as e:
            raise CheckpointError(f"{config.vae_checkpoint}: {e}") from e
    else:
        log.warning("no vae_checkpoint: the frozen VAE keeps its random initialisation")
    return model


def config_differences(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the (nested) config fields whose values differ between ``a`` and ``b``."""
    out = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            out += config_differences(x, y, f"{prefix}{key}.")
        elif x != y:
            out.append(f"{prefix}{key}")
    return out


def training_scene(pred: Stage1Prediction, b: int, clip: Clip, model: Stage1Model) -> GaussianScene:
    """Clip ``b``'s Gaussians for the losses: every pixel not labelled sky, soft motion."""
    keep = clip.context.semantic != SKY
    return pred.scene(b, keep=keep, hard=False, time_origin_micros=clip.time_origin_micros)


@dataclass(frozen=True)
class TargetRenders:
    """A clip's Gaussians rendered at its S target frames (V views of H x W each)."""

    rgb: Tensor  # [S, V, H, W, 3] with the sky model behind
    depth: Tensor  # [S, V, H, W] metres, 0 where nothing
    alpha: Tensor  # [S, V, H, W]
    semantic_probs: Tensor  # [S, V, H, W, K] premultiplied class probabilities


def render_targets(model: Stage1Model, scene: GaussianScene, clip: Clip) -> TargetRenders:
    """Renders ``scene`` (colour, depth, class probabilities) at every target view of ``clip`` at
    its own capture time."""
    h, w = clip.context.images.shape[-2:]
    rgbs, depths, alphas, probs = [], [], [], []
    for s in range(clip.targets.images.shape[0]):
        wfc = clip.targets.world_from_camera[s]
        r = scene.render(wfc.float(), clip.intrinsics, w, h, clip.targets.time_s[s], semantics=True)
        sky = model.background(wfc.float(), clip.intrinsics, h, w)
        rgbs.append(r.rgb + (1 - r.alpha[..., None]) * sky)
        depths.append(r.depth)
        alphas.append(r.alpha)
        probs.append(r.semantic_probs)
    return TargetRenders(
        torch.stack(rgbs),
        torch.stack(depths),
        torch.stack(alphas),
        torch.stack(probs),  # type: ignore[arg-type]  # semantics=True: never None
    )


def rendered_semantic_loss(probs: Tensor, alpha: Tensor, labels: Tensor, min_alpha: float = 0.5) -> Tensor:
    """Mean ``-log q_label`` of rendered (..., K) premultiplied class probabilities, ``q = probs /
    alpha``, over pixels whose label is known and whose alpha reaches ``min_alpha``."""
    use = (labels != IGNORE_ID) & (alpha >= min_alpha)
    if not use.any():
        return probs.sum() * 0.0
    q = probs[use] / alpha[use][:, None]
    picked = q.gather(1, labels[use].long()[:, None])[:, 0]
    return -torch.log(picked.clamp(min=1e-6)).mean()


def depth_bin_loss(
    logits: Tensor | None, bins: DepthBins | None, depth: Tensor, confidence: Tensor
) -> Tensor:
    """Confidence-weighted mean cross-entropy of (..., K) depth-bin logits against the bin of
    ``depth`` (metres, > 0 where known); 0 without the bins head (``logits`` and ``bins`` None)."""
    known = depth > 0
    if logits is None or bins is None or not known.any():
        return depth.sum() * 0.0 if logits is None else logits.sum() * 0.0
    weight = confidence[known]
    ce = F.cross_entropy(logits[known], bins.index(depth[known]), reduction="none")
    return (weight * ce).sum() / weight.sum().clamp(min=1e-6)


def ground_gate_loss(logits: Tensor | None, b: int, labels: Tensor) -> Tensor:
    """Mean binary cross-entropy of clip ``b``'s ground-gate logits ([B, T, V, H, W], the adapter's
    ``column_base``) against "the label is a ground class" (``taxonomy.GROUND_IDS``) over labelled
    pixels; 0 without the gate."""
    if logits is None:
        return labels.new_zeros((), dtype=torch.float32)
    known = labels != IGNORE_ID
    if not known.any():
        return logits.sum() * 0.0
    target = torch.isin(labels, torch.tensor(sorted(GROUND_IDS), device=labels.device)).to(logits.dtype)
    return F.binary_cross_entropy_with_logits(logits[b][known], target[known])


class VaeFeatureCache:
    """The frozen VAE's features (:meth:`Stage1Model.features`) of clips' context images, kept per
    (scene, context frames) up to ``max_bytes``: the VAE does not train, and there is no image
    augmentation, so a window's features are the same every time it is drawn (a sixth of a
    ``stage1_tiny`` step on a CPU core)."""

    def __init__(self, model: Stage1Model, max_bytes: int):
        self.model = model
        self.kept: BoundedCache[list[Tensor]] = BoundedCache(max_bytes, tensor_bytes)

    def __call__(self, clips: list[Clip], images: Tensor) -> list[Tensor]:
        """Per level, [B, T, V, C, h, w]: the features of ``images`` (the clips' context images,
        [B, T, V, 3, H, W]), each clip's computed alone on a miss."""
        per_clip = [
            self.kept.get_or_make(
                (c.scene_id, tuple(c.frame_indices)),
                lambda b=b: [f[0] for f in self.model.features(images[b : b + 1])],
            )
            for b, c in enumerate(clips)
        ]
        return [torch.stack(level) for level in zip(*per_clip, strict=True)]


def depth_target_weight(confidence: Tensor, floor: float) -> Tensor:
    """Weight in [floor, 1] of each dense-depth target of the given confidence (same shape, in
    [0, 1]): ``floor + (1 - floor) * confidence``."""
    return floor + (1.0 - floor) * confidence


def stage1_losses(
    model: Stage1Model,
    clips: list[Clip],
    features: VaeFeatureCache | None = None,
    depth_confidence_floor: float = 0.0,
) -> tuple[dict[str, Tensor], int]:
    """Every loss term (unweighted, means over the batch) of a batch of clips, and the number of
    Gaussians rendered; ``features`` supplies the VAE's features where it has them; the depth
    terms weigh each target by :func:`depth_target_weight` of its confidence."""
    inputs = clip_inputs(clips)
    pred = model(*inputs, None if features is None else features(clips, inputs[0]))
    terms: dict[str, list[Tensor]] = {k: [] for k in LOSS_NAMES}
    gaussians = 0
    for b, clip in enumerate(clips):
        scene = training_scene(pred, b, clip, model)
        gaussians += len(scene)
        r = render_targets(model, scene, clip)
        tg = clip.targets
        terms["rgb"].append(photometric_loss(r.rgb, tg.images.permute(0, 1, 3, 4, 2)))
        target_weight = depth_target_weight(tg.depth_confidence, depth_confidence_floor)
        terms["depth"].append(log_depth_loss(r.depth, tg.depth, target_weight))
        terms["target_semantic"].append(rendered_semantic_loss(r.semantic_probs, r.alpha, tg.semantic))
        sky = (tg.semantic == SKY).float()
        terms["opacity"].append((r.alpha * sky).sum() / sky.sum().clamp(min=1.0))
        px, ctx = pred.pixels, clip.context
        context_weight = depth_target_weight(ctx.depth_confidence, depth_confidence_floor)
        terms["pixel_depth"].append(log_depth_loss(px.depth[b], ctx.depth, context_weight))
        logits = None if px.depth_logits is None else px.depth_logits[b]
        bins = model.config.adapter_config.bins
        terms["depth_ce"].append(depth_bin_loss(logits, bins, ctx.depth, context_weight))
        terms["smooth"].append(edge_aware_smoothness(px.depth[b], ctx.images.permute(0, 1, 3, 4, 2)))
        terms["semantic"].append(
            semantic_loss(px.semantic_logits[b], ctx.semantic) + _not_sky(px.semantic_logits[b], ctx)
        )
        known = ctx.moving >= 0
        bce = F.binary_cross_entropy_with_logits(
            px.dynamic_logit[b], ctx.moving.clamp(min=0), reduction="none"
        )
        terms["dynamic"].append((bce * known).sum() / known.sum().clamp(min=1))
        moving = (ctx.moving > 0)[..., None]
        err = (pred.velocity[b] - ctx.box_velocity).abs() * moving
        terms["velocity"].append(err.sum() / moving.sum().clamp(min=1))
        soft = pred.velocity[b] * pred.dynamic_prob[b][..., None]
        terms["motion"].append(soft.abs().mean())
        terms["ground"].append(ground_gate_loss(px.ground_logit, b, ctx.semantic))
    return {k: torch.stack(v).mean() for k, v in terms.items()}, gaussians


def _not_sky(logits: Tensor, views: ViewSet) -> Tensor:
    """-log(1 - p_sky) over unlabelled pixels with a dense depth: a surface is there, so whatever
    its class it is not sky. Sparse labels (geometric pseudo labels alone) otherwise leave the
    classifier free to call unlabelled walls sky, and sky spawns no Gaussians."""
    solid = (views.semantic == IGNORE_ID) & (views.depth > 0)
    if not solid.any():
        return logits.sum() * 0.0
    log_p = torch.log_softmax(logits[solid], dim=-1)  # [P, K]
    others = torch.cat([log_p[:, :SKY], log_p[:, SKY + 1 :]], dim=-1)
    return -torch.logsumexp(others, dim=-1).mean()  # -log(1 - p_sky), stable


def _draw_clips(data: Stage1Clips, cfg: Stage1TrainConfig, step: int, group: ProcessGroup) -> list[Clip]:
    """This rank's clips of ``step``: a pure function of (seed, step, rank)."""
    per_rank = max(cfg.batch_size // group.world_size, 1)
    g = step_generator(cfg.seed, step, group.rank)
    windows = data.windows()
    clips = []
    # Offsets -k..-1, 1..k of the last context frame; each clip draws targets_per_clip distinct ones.
    offsets = [o for o in range(-cfg.target_offset, cfg.target_offset + 1) if o]
    count = min(cfg.targets_per_clip, len(offsets))
    for _ in range(per_rank):
        scene, start = windows[int(torch.randint(len(windows), (1,), generator=g))]
        picked = torch.randperm(len(offsets), generator=g)[:count].tolist() if count else []
        clips.append(data.clip(scene, start, [offsets[i] for i in picked]))
    return clips


#: Config fields that change how a run uses the machine, not its results: a run may resume with
#: other values (and runs from before a field existed, without it).
RESULT_NEUTRAL_FIELDS = frozenset({"cache_mb"})

#: Training-config fields added after runs were made, with the value that reproduces what such a
#: run did: a ``config.yaml`` without one resumes as if it held that value.
LATER_FIELDS = {"depth_confidence_floor": 0.0}


def check_run_folder(out: Path, cfg: Any, resume: bool) -> Path | None:
    """The checkpoint to resume from (or None) for a run of ``cfg`` (a training config with
    ``to_dict``, as its ``config.yaml`` records it; Stage 1's and Stage 2's); refuses to mix runs in
    one folder, and to restart one with logged steps but no usable checkpoint."""
    if not resume:
        evidence = run_evidence(out)
        if evidence is not None:
            raise CheckpointError(
                f"{out}: holds a run already ({evidence}); pass {argument('resume=True', '--resume')} "
                f"or another {argument('out', '--out')}"
            )
        return None
    before = read_run_config(out)
    now = {k: v for k, v in cfg.to_dict().items() if k not in RESULT_NEUTRAL_FIELDS}
    if before is not None:
        before = {k: v for k, v in before.items() if k not in RESULT_NEUTRAL_FIELDS}
        before |= {k: v for k, v in LATER_FIELDS.items() if k in now and k not in before}
    if before is not None and before != now:
        diff = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
        raise ValueError(
            f"{out / 'config.yaml'}: the run was started with another config (fields differ: {diff})"
        )
    return checkpoint_to_resume(out)


def train_stage1(
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    config: Stage1TrainConfig | str | os.PathLike[str],
    *,
    resume: bool = False,
    stop_after: int | None = None,
    progress: bool = True,
    time_limit_s: float | None = None,
) -> Stage1Run:
    """Trains a Stage 1 adapter on the cache ``shards`` into the run folder ``out``.

    ``config``: a :class:`Stage1TrainConfig` or a YAML path. ``resume``: continue from the run's
    newest checkpoint. ``stop_after``: end this process after that many steps in total (as if
    killed; for tests of resuming). ``time_limit_s``: a wall-clock budget for this call's steps
    (seconds from the first step): once a step ends past it, training ends there and the final
    weights are written as if ``steps`` had been that step (the learning-rate schedule stays the
    one of ``steps``, so it has not decayed all the way; ``Stage1Run.stopped_by_time`` says so).
    Returns the run's summary; the final weights are ``out/model.safetensors`` (written when all
    ``steps`` are done or the time limit ends the run).
    """
    cfg = config if isinstance(config, Stage1TrainConfig) else Stage1TrainConfig.load(config)
    out = Path(out)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    with process_group() as group:
        return _train(Path(shards), out, cfg, group, resume, stop_after, progress, time_limit_s)


def _train(
    shards: Path,
    out: Path,
    cfg: Stage1TrainConfig,
    group: ProcessGroup,
    resume: bool,
    stop_after: int | None,
    progress: bool,
    time_limit_s: float | None = None,
) -> Stage1Run:
    resume_from = check_run_folder(out, cfg, resume)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg)
    cache_bytes = int(cfg.cache_mb * 2**20)
    data = Stage1Clips(
        shards,
        model.config.image_size,
        model.config.frames,
        cfg.semantic_target,  # type: ignore[arg-type]
        cache_mb=cfg.cache_mb / 3,
    )
    out.mkdir(parents=True, exist_ok=True)  # only once the VAE and the cache are known to load
    features = VaeFeatureCache(model, cache_bytes - cache_bytes // 3)
    optimizer = torch.optim.AdamW(model.trainable_parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    if resume_from is not None:
        loaded = load_checkpoint(resume_from / "model.safetensors", kind="stage1").model
        if loaded.config != model.config:
            changed = config_differences(loaded.config.to_dict(), model.config.to_dict())
            raise CheckpointError(
                f"{resume_from}: checkpoint of another model config than {cfg.model} "
                f"(differs in {', '.join(changed)})"
            )
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
    resume_step = start if resume_from is not None else None
    metrics = MetricsLog(out, LOG_COLUMNS, resume_step=resume_step) if group.is_main else None
    model.train()
    trainable = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    divergence = DivergenceCheck(
        out, cfg.lr, cfg.weight_decay, {k: (f"weights.{k}", w) for k, w in cfg.weights.items()}
    )
    last: dict[str, float] = {}
    stopped_by_time = False
    t_start = time.perf_counter()
    end = cfg.steps if stop_after is None else min(cfg.steps, stop_after)
    bar = tqdm(range(start, end), initial=start, total=cfg.steps, disable=not (progress and group.is_main))
    try:
        for step in bar:
            t0 = time.perf_counter()
            lr = cosine_lr(step, cfg.steps, cfg.lr, cfg.warmup_steps, cfg.final_lr_ratio)
            for pg in optimizer.param_groups:
                pg["lr"] = lr
            clips = _draw_clips(data, cfg, step, group)
            terms, gaussians = stage1_losses(
                trainee if group.world_size == 1 else _Forward(trainee, model),
                clips,
                features,
                cfg.depth_confidence_floor,
            )
            loss = sum(cfg.weights[k] * v for k, v in terms.items())
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            late = time_limit_s is not None and time.perf_counter() - t_start >= time_limit_s
            values = torch.stack(
                [loss.detach(), *[terms[k].detach() for k in LOSS_NAMES], torch.tensor(float(late))]
            )
            values = group.mean(values)
            late = float(values[-1]) > 0  # any rank past the limit: all stop after this step
            values = values[:-1]
            last = {
                "loss": float(values[0]),
                **{k: float(v) for k, v in zip(LOSS_NAMES, values[1:], strict=True)},
            }
            divergence.losses(step + 1, last)
            grad_norm = divergence.clip_gradients(step + 1, trainable, cfg.grad_clip)
            optimizer.step()
            divergence.weights_after(step + 1, trainable)
            last |= {
                "lr": lr,
                "grad_norm": grad_norm,
                "gaussians": gaussians,
                "seconds": time.perf_counter() - t0,
            }
            if metrics is not None:
                metrics.log(step + 1, last)
            bar.set_postfix(loss=f"{last['loss']:.4f}")
            if group.is_main and ((step + 1) % cfg.checkpoint_every == 0 or step + 1 == cfg.steps or late):
                save_training_state(out, step + 1, model, optimizer, {"config": cfg.to_dict()})
            group.barrier()
            if late:
                stopped_by_time, end = True, step + 1
                log.info("time limit of %.0f s reached after step %d of %d", time_limit_s, end, cfg.steps)
                break
    finally:
        if metrics is not None:
            metrics.close()
    final = None
    if group.is_main and (end == cfg.steps or stopped_by_time):
        summary = {"steps": end, "planned_steps": cfg.steps, "stopped_by_time": stopped_by_time}
        final = save_checkpoint(out / "model.safetensors", model, summary | {"train": cfg.to_dict()})
        write_text_atomic(out / "summary.json", json.dumps(summary | {"last": last}, indent=2))
    return Stage1Run(
        out=out,
        checkpoint=final,
        steps_done=end,
        last=last,
        seconds=time.perf_counter() - t_start,
        stopped_by_time=stopped_by_time,
    )


class _Forward(torch.nn.Module):
    """The model as :func:`stage1_losses` uses it, with the forward pass going through DDP (so its
    gradients are averaged over the ranks) and every other attribute from the plain model."""

    def __init__(self, ddp: torch.nn.Module, model: Stage1Model):
        super().__init__()
        self.ddp = ddp
        self.model = model

    def forward(self, *args: Any) -> Stage1Prediction:
        return self.ddp(*args)

    @property
    def config(self) -> Any:
        return self.model.config

    def background(self, *args: Any) -> Tensor:
        return self.model.background(*args)
