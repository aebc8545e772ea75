"""The configs a Stage 2 model is trained with and its checkpoint records: what its latent cache
holds (:class:`Stage2DataConfig`) and the training run's options (:class:`Stage2TrainConfig`), read
back from a checkpoint with their own checks (:func:`trained_config`) so a rollout is sampled as
the model was trained."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from phigenesis import limits
from phigenesis.errors import CheckpointError
from phigenesis.models.config_checks import check_model_name, check_model_overrides
from phigenesis.models.uncertainty import DEFAULT_LP_TRUST, LpTrust
from phigenesis.options import ConfigError, check_options, from_mapping, option, same_as
from phigenesis.rollout.conditions import UNCERTAINTY_KINDS, ConditionKind, GeometrySource
from phigenesis.user_files import read_config_file

#: Stereo Forcing's map kinds a Stage 2 model is trained with: an uncertainty kind or none.
CONDITION_KINDS: tuple[str, ...] = (*UNCERTAINTY_KINDS, "none")

#: The most frames a window (history or generated) or a stride may span.
MAX_WINDOW_FRAMES = 1024


@dataclass(frozen=True)
class Stage2DataConfig:
    """What a latent cache holds (every field is part of its fingerprint)."""

    history_frames: int = option(
        1,
        ge=1,
        le=MAX_WINDOW_FRAMES,
        help="frames of history per window (a multiple of the Stage 1 model's frames)",
    )
    window_frames: int = option(
        5,
        ge=1,
        le=MAX_WINDOW_FRAMES,
        help="frames to generate per window: 1 + k x the VAE's temporal compression",
    )
    stride: int = option(
        5, ge=1, le=MAX_WINDOW_FRAMES, help="frames between the starts of consecutive windows"
    )
    geometry: GeometrySource = option("stage1", help="where the history's Gaussians come from")
    random_patch_px: int = option(8, ge=1, le=4096, help="side of the random map's patches, pixels")
    seed: int = option(0, ge=0, le=2**32 - 1, help="seeds the random maps (per window: seed, scene, start)")
    lp_trust: LpTrust = option(DEFAULT_LP_TRUST, help="which points the localization potential's u trusts")

    def __post_init__(self) -> None:
        check_options(self, "Stage2DataConfig")


@dataclass(frozen=True)
class Stage2TrainConfig:
    """Options of :func:`phigenesis.train.stage2.train_stage2` (configs/stage2/tiny.yaml, paper.yaml)."""

    model: str = option(
        "stage2_tiny", help="registered denoiser variant (phigenesis.models.list_models('dit'))"
    )
    model_overrides: dict[str, Any] = option(factory=dict, help="fields of the variant's config replaced")
    stage1_checkpoint: str = option(
        "runs/stage1-tiny/model.safetensors", help="the Stage 1 model whose VAE encodes; --stage1 overrides"
    )
    history_frames: int = same_as(Stage2DataConfig, "history_frames")
    window_frames: int = same_as(Stage2DataConfig, "window_frames")
    stride: int = same_as(Stage2DataConfig, "stride")
    geometry: GeometrySource = same_as(Stage2DataConfig, "geometry")
    uncertainty: ConditionKind = option(
        "localization_potential", help="Stereo Forcing's map; none: no geometric condition"
    )
    lp_trust: LpTrust = same_as(Stage2DataConfig, "lp_trust")
    condition_dropout: float = option(
        0.1, ge=0, le=1, help="probability of dropping the whole condition (guidance)"
    )
    history_noise: float = option(0.1, ge=0, lt=1, help="history frames' flow time is uniform in [0, this]")
    time_shift: float = option(
        1.0, gt=0, le=100, help="resolution shift of the logit-normal training times (1: none)"
    )
    latent_norm: bool = option(
        False, help="flow on per-channel standardised latents (stats of the latent cache)"
    )
    steps: int = option(2000, ge=1, le=limits.MAX_STEPS)
    batch_size: int = option(4, ge=1, le=limits.MAX_BATCH, help="windows per step, over all processes")
    lr: float = option(1e-3, gt=0, le=limits.MAX_LR)
    weight_decay: float = option(5e-5, ge=0, le=limits.MAX_WEIGHT_DECAY)
    warmup_steps: int = option(50, ge=0, le=limits.MAX_STEPS)
    restart_steps: int = option(
        0, ge=0, le=limits.MAX_STEPS, help="cosine annealing restarts every this many steps (0: one cosine)"
    )
    final_lr_ratio: float = option(0.1, ge=0, le=1)
    grad_clip: float = option(1.0, gt=0, le=limits.MAX_GRAD_CLIP)
    checkpoint_every: int = option(250, ge=1, le=limits.MAX_STEPS)
    log_every: int = option(10, ge=1, le=limits.MAX_STEPS)
    seed: int = option(0, ge=0, le=limits.MAX_SEED, help="seeds the initialisation and every step's draws")
    data_seed: int = option(
        0,
        ge=0,
        le=limits.MAX_SEED,
        help="seeds the latent cache's random maps (runs of several seeds share one cache)",
    )
    threads: int | None = option(None, ge=1, le=limits.MAX_THREADS)

    def __post_init__(self) -> None:
        check_options(self, "Stage2TrainConfig")
        check_model_name(self.model, "dit", "Stage2TrainConfig")
        check_model_overrides(self.model, self.model_overrides, "Stage2TrainConfig")
        self.data_config()  # checks the data fields

    def data_config(self) -> Stage2DataConfig:
        return Stage2DataConfig(
            history_frames=self.history_frames,
            window_frames=self.window_frames,
            stride=self.stride,
            geometry=self.geometry,
            seed=self.data_seed,
            lp_trust=self.lp_trust,
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str], **overrides: Any) -> Stage2TrainConfig:
        """The config in a YAML file with ``overrides`` (the command line's; None: not given)
        applied; unknown keys and values outside their type or range raise
        :class:`~phigenesis.options.ConfigError` naming the file, the key and the range."""
        path = Path(path)
        given = {k: v for k, v in overrides.items() if v is not None}
        return from_mapping(cls, read_config_file(path), str(path), **given)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def trained_config(path: str | os.PathLike[str], train: Any) -> Stage2TrainConfig:
    """The training config a Stage 2 checkpoint's ``meta`` records (``train``), built by
    :class:`Stage2TrainConfig` so that its checks apply: a checkpoint saying ``window_frames: 0``
    is refused here, naming the file and the key, rather than dividing by zero in a rollout. Keys
    the config no longer has (fields since removed) are left out; fields a checkpoint predates take
    their defaults. Raises :class:`CheckpointError`."""
    if not isinstance(train, dict) or "window_frames" not in train:
        raise CheckpointError(f"{path}: has no Stage 2 training config in its metadata (window_frames)")
    known = {f.name for f in dataclasses.fields(Stage2TrainConfig)}
    values = {k: v for k, v in train.items() if k in known}
    try:
        return from_mapping(Stage2TrainConfig, values, f"{path}: its training config")
    except ConfigError as e:
        raise CheckpointError(str(e)) from None
