"""Training a semantic segmenter on a cache's labelled images (``phigenesis-train segmenter``).

Entry point: :func:`train_segmenter`. As in the paper, a SegFormer is fine-tuned on the frames that
carry per-pixel labels and then run over every frame by the ``pseudo_semantics`` stage.

- **Labels.** Each image's target is the dataset's human labels (``label_semantic_png``: Waymo's
  camera panoptic labels) where it has them, else exact synthetic truth (``truth_semantic_png``);
  ``labels`` = "labels" or "truth" uses one kind only. Images without a target are skipped; 255 is
  ignored by the loss and the metrics.
- **Validation by scene.** A share ``val_fraction`` of the scenes (at least one; chosen with
  ``seed``) is held out, so no validation image shares a street with a training image. A cache
  of a single scene holds out the last ``val_fraction`` of its frames instead (logged).
- **Optimisation.** AdamW, linear warm-up then cosine decay (the paper's schedule), gradient
  clipping, random horizontal flips and optional random crops (``crop``) of images resized to
  ``image_height``.
- **Output.** ``OUT/best.pt`` (best validation mIoU) and ``OUT/last.pt`` (checkpoints, see
  :mod:`phigenesis.train.checkpoint`, with the training options, scenes and scores in their meta)
  and ``OUT/metrics.json`` (every evaluation: step, train loss, mIoU, per-class IoU).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray

from phigenesis import limits
from phigenesis import taxonomy as tx
from phigenesis.data import codec
from phigenesis.data.records import decode_whole
from phigenesis.data.schema import cameras_of
from phigenesis.data.shards import CacheReader
from phigenesis.errors import CacheError
from phigenesis.models import create_model
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.config_checks import check_model_name
from phigenesis.models.metrics import confusion_matrix, segmentation_scores
from phigenesis.models.segformer import load_hf_weights
from phigenesis.options import check_options, option
from phigenesis.train.checkpoint import save_checkpoint
from phigenesis.train.runner import DivergenceCheck, write_text_atomic

log = logging.getLogger("phigenesis.train")

LabelKind = Literal["auto", "truth", "labels"]
#: Label columns by kind, in the order "auto" tries them.
LABEL_COLUMNS = {"labels": "label_semantic_png", "truth": "truth_semantic_png"}


@dataclass(frozen=True)
class SegmenterTrainConfig:
    """Options of :func:`train_segmenter`.

    Attributes:
        model: registered model variant (``phigenesis.models.list_models()``).
        steps: optimiser steps; None: ``epochs`` passes over the training images.
        epochs: passes over the training images when ``steps`` is None.
        batch_size: images per step.
        lr: peak learning rate (AdamW).
        weight_decay: AdamW weight decay.
        warmup_steps: steps of linear warm-up before the cosine decay.
        grad_clip: gradient-norm clip.
        val_fraction: share of the scenes held out for validation.
        labels: which labels to train on: "auto" (human labels, else synthetic truth), "truth", "labels".
        image_height: images are resized to this height (aspect kept); None: stored size.
        crop: random crops (height, width) in pixels for training; None: whole images (all must
            then share a size).
        flip: random horizontal flips.
        eval_every: steps between validations (and checkpoints); the last step always evaluates.
        seed: seeds the split, the initialisation and the sampling.
        threads: torch CPU threads (None: torch's default).
        device: torch device.
        init: start from this checkpoint's weights (it must be of ``model``).
        pretrained: start from a local Hugging Face SegFormer checkpoint (``pytorch_model.bin``;
            :func:`phigenesis.models.segformer.load_hf_weights`), e.g. MiT-B0 or SegFormer-B0
            fine-tuned on Cityscapes for ``segformer_b0``.
    """

    model: str = option("segformer_tiny")
    steps: int | None = option(None, ge=1, le=limits.MAX_STEPS)
    epochs: float = option(10.0, gt=0, le=1e6)
    batch_size: int = option(8, ge=1, le=limits.MAX_BATCH)
    lr: float = option(2e-3, gt=0, le=limits.MAX_LR)
    weight_decay: float = option(1e-2, ge=0, le=limits.MAX_WEIGHT_DECAY)
    warmup_steps: int = option(50, ge=0, le=limits.MAX_STEPS)
    grad_clip: float = option(1.0, gt=0, le=limits.MAX_GRAD_CLIP)
    val_fraction: float = option(0.2, ge=0, lt=1)
    labels: LabelKind = option("auto")
    image_height: int | None = option(None, ge=1, le=limits.MAX_IMAGE_SIDE)
    crop: tuple[int, int] | None = option(None, ge=1, le=limits.MAX_IMAGE_SIDE)
    flip: bool = option(True)
    eval_every: int = option(250, ge=1, le=limits.MAX_STEPS)
    seed: int = option(0, ge=0, le=limits.MAX_SEED)
    threads: int | None = option(None, ge=1, le=limits.MAX_THREADS)
    device: str = option("cpu")
    init: str | None = option(None)
    pretrained: str | None = option(None)

    def __post_init__(self) -> None:
        check_options(self, "SegmenterTrainConfig")
        check_model_name(self.model, "segformer", "SegmenterTrainConfig")


@dataclass(frozen=True)
class LabelledImage:
    """One camera image with a label map: global frame index, camera index, label column."""

    frame: int
    camera: int
    column: str


class LabelledImages(torch.utils.data.Dataset):
    """Labelled camera images of a cache as (image uint8 [3, H, W], label int64 [H, W]) pairs.

    ``train``: random flips and crops (see :class:`SegmenterTrainConfig`); otherwise whole images.
    """

    def __init__(
        self,
        reader: CacheReader,
        items: list[LabelledImage],
        config: SegmenterTrainConfig,
        train: bool,
    ):
        self.reader, self.items, self.config, self.train = reader, items, config, train
        self.rng = np.random.default_rng(config.seed + (0 if train else 1))

    def __len__(self) -> int:
        return len(self.items)

    def load(self, index: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """(H, W, 3) uint8 RGB and (H, W) uint8 labels of item ``index`` at the training size."""
        item = self.items[index]
        cf = cameras_of(self.reader.read(item.frame, ["cameras"]))
        camera = cf["camera_name"][item.camera].as_py()
        try:
            image = decode_whole(cf["image"][item.camera].as_py(), cv2.IMREAD_COLOR, "image")
            label = codec.decode_semantic(cf[item.column][item.camera].as_py())
        except ValueError as e:
            path, row = self.reader.locate(item.frame)
            raise CacheError(f"{path}: row {row}: camera {camera}: {e}") from None
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        height = self.config.image_height
        if height is not None and height != rgb.shape[0]:
            width = max(8, round(rgb.shape[1] * height / rgb.shape[0]))
            rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
            label = cv2.resize(label, (width, height), interpolation=cv2.INTER_NEAREST)
        return rgb, label

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        rgb, label = self.load(index)
        if self.train:
            if self.config.flip and self.rng.random() < 0.5:
                rgb, label = rgb[:, ::-1], label[:, ::-1]
            if self.config.crop is not None:
                rgb, label = random_crop(rgb, label, self.config.crop, self.rng)
        image = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)  # [3, H, W] uint8
        return image, torch.from_numpy(np.ascontiguousarray(label)).long()


def random_crop(
    rgb: NDArray[np.uint8], label: NDArray[np.uint8], size: tuple[int, int], rng: np.random.Generator
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A random (h, w) window of an image and its labels, padded (black, ignore) where smaller."""
    h, w = size
    pad_h, pad_w = max(0, h - rgb.shape[0]), max(0, w - rgb.shape[1])
    if pad_h or pad_w:
        rgb = np.pad(rgb, ((0, pad_h), (0, pad_w), (0, 0)))
        label = np.pad(label, ((0, pad_h), (0, pad_w)), constant_values=tx.IGNORE_ID)
    top = int(rng.integers(0, rgb.shape[0] - h + 1))
    left = int(rng.integers(0, rgb.shape[1] - w + 1))
    return rgb[top : top + h, left : left + w], label[top : top + h, left : left + w]


def labelled_images(reader: CacheReader, labels: LabelKind = "auto") -> dict[str, list[LabelledImage]]:
    """Every image of the cache with a label map of the kind asked for, by scene id (in order)."""
    kinds = ("labels", "truth") if labels == "auto" else (labels,)
    out: dict[str, list[LabelledImage]] = {}
    for frame in range(len(reader)):
        batch = reader.read(frame, ["scene_id", "cameras"])
        scene = batch.column("scene_id")[0].as_py()
        cf = cameras_of(batch)
        for cam in range(len(cf["camera_name"])):
            if not cf["image"][cam].is_valid:
                continue
            for kind in kinds:
                column = LABEL_COLUMNS[kind]
                if column in cf and cf[column][cam].is_valid:
                    out.setdefault(scene, []).append(LabelledImage(frame, cam, column))
                    break
    return out


def split_by_scene(
    images: dict[str, list[LabelledImage]], val_fraction: float, seed: int
) -> tuple[list[str], list[str], list[LabelledImage], list[LabelledImage]]:
    """(train scenes, validation scenes, train images, validation images): ``val_fraction`` of the
    scenes (at least one when there are two or more and the fraction is > 0) are held out; a single
    scene holds out its last ``val_fraction`` of frames instead."""
    scenes = sorted(images)
    if val_fraction == 0 or not scenes:
        return scenes, [], [i for s in scenes for i in images[s]], []
    if len(scenes) == 1:
        items = images[scenes[0]]
        frames = sorted({i.frame for i in items})
        n_val = min(len(frames) - 1, max(1, round(val_fraction * len(frames))))
        cut = frames[len(frames) - n_val] if n_val > 0 else None
        log.warning("only one labelled scene: holding out its last %.0f%% of frames", 100 * val_fraction)
        train = [i for i in items if cut is None or i.frame < cut]
        return scenes, scenes, train, [i for i in items if cut is not None and i.frame >= cut]
    order = np.random.default_rng(seed).permutation(len(scenes))
    n_val = min(len(scenes) - 1, max(1, round(val_fraction * len(scenes))))
    val = sorted(scenes[k] for k in order[:n_val])
    train = [s for s in scenes if s not in val]
    return train, val, [i for s in train for i in images[s]], [i for s in val for i in images[s]]


@torch.no_grad()
def evaluate(model: torch.nn.Module, data: LabelledImages, device: str = "cpu") -> dict[str, Any]:
    """Validation scores of ``model`` on every image of ``data`` at its stored size: mIoU,
    per-class IoU (by class name, NaN-free: absent classes left out), pixel accuracy."""
    num_classes = model.config.num_classes
    cm = np.zeros((num_classes, num_classes + 1), np.int64)
    for index in range(len(data)):
        image, label = data[index]
        prob = model.predict(image[None].to(device))
        cm += confusion_matrix(prob.argmax(dim=1)[0].cpu().numpy(), label.numpy(), num_classes)
    scores = segmentation_scores(cm)
    names = tx.CLASS_NAMES if num_classes == tx.NUM_CLASSES else [str(k) for k in range(num_classes)]
    return {
        "miou": scores.miou,
        "pixel_accuracy": scores.pixel_accuracy,
        "iou": {names[k]: v for k, v in enumerate(scores.iou) if not math.isnan(v)},
        "images": len(data),
    }


@dataclass
class SegmenterRun:
    """What :func:`train_segmenter` produced.

    Attributes:
        best: path of the best checkpoint (validation mIoU; the last one without validation).
        last: path of the last checkpoint.
        scores: the best checkpoint's validation scores (:func:`evaluate`), empty without validation.
        history: every evaluation (step, seconds, train loss, scores).
        train_scenes, val_scenes: the split.
    """

    best: Path
    last: Path
    scores: dict[str, Any]
    history: list[dict[str, Any]]
    train_scenes: list[str]
    val_scenes: list[str]


def _learning_rate(step: int, total: int, config: SegmenterTrainConfig) -> float:
    """Linear warm-up to ``lr`` over ``warmup_steps``, then cosine decay to 0 at ``total``."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    progress = (step - config.warmup_steps) / max(1, total - config.warmup_steps)
    return 0.5 * config.lr * (1 + math.cos(math.pi * min(1.0, progress)))


def _optimizer(model: torch.nn.Module, cfg: SegmenterTrainConfig) -> torch.optim.Optimizer:
    """AdamW with weight decay on weight matrices and kernels only (not on norms and biases)."""
    decay = [p for p in model.parameters() if p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.ndim <= 1]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=cfg.lr)


def _train_step(
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    images_u8: torch.Tensor,
    target: torch.Tensor,
    cfg: SegmenterTrainConfig,
    divergence: DivergenceCheck,
    step: int,
) -> float:
    """Optimiser step ``step`` (1-based) on uint8 images [B, 3, H, W] and int64 labels [B, H, W]
    (255 ignored): cross-entropy of the logits upsampled to the labels' size. A non-finite loss,
    gradient or weight stops training (``divergence``). Returns the loss."""
    x = images_u8.to(cfg.device).float() / 255.0  # [B, 3, H, W]
    logits = F.interpolate(model(x), size=x.shape[-2:], mode="bilinear", align_corners=False)
    loss = F.cross_entropy(logits, target.to(cfg.device), ignore_index=tx.IGNORE_ID)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    divergence.losses(step, {"loss": float(loss.detach())})
    divergence.clip_gradients(step, model.named_parameters(), cfg.grad_clip)
    optimizer.step()
    divergence.weights_after(step, model.named_parameters())
    return float(loss.detach())


def _kept_files(paths: dict[str, Path]) -> str:
    """What a diverged segmenter run keeps, in words (it does not resume: ``--init`` starts from them)."""
    kept = [p.name for p in paths.values() if p.is_file()]
    if not kept:
        return "nothing was written before it"
    return f"{' and '.join(kept)} of the last evaluation are kept (--init starts a new run from them)"


def train_segmenter(
    shards: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: str = "segformer_tiny",
    steps: int | None = None,
    epochs: float | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    **options: Any,
) -> SegmenterRun:
    """Trains segmenter ``config`` (a model variant) on the labelled images of the cache at
    ``shards``, writing checkpoints and metrics to ``out`` (see the module docstring).

    ``steps``/``epochs`` and ``options`` are :class:`SegmenterTrainConfig` fields; ``progress`` is
    called with each evaluation's record. Raises ValueError if the cache has no labelled images.

    Example::

        run = train_segmenter("cache/", "runs/seg", config="segformer_tiny", steps=500)
        print(run.scores["miou"], run.best)
    """
    cfg = SegmenterTrainConfig(
        model=config, steps=steps, **({"epochs": epochs} if epochs is not None else {}), **options
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    reader = CacheReader(shards)
    images = labelled_images(reader, cfg.labels)
    if not images:
        raise ValueError(f"{shards}: no images with {cfg.labels} semantic labels to train on")
    train_scenes, val_scenes, train_items, val_items = split_by_scene(images, cfg.val_fraction, cfg.seed)
    if not train_items:
        raise ValueError(f"{shards}: no training images left after holding out {val_scenes}")
    train_data = LabelledImages(reader, train_items, cfg, train=True)
    val_data = LabelledImages(reader, val_items, cfg, train=False)
    total = cfg.steps or max(1, math.ceil(cfg.epochs * len(train_data) / cfg.batch_size))
    log.info(
        "segmenter %s: %d training images (%d scenes), %d validation images (%d scenes), %d steps",
        cfg.model, len(train_data), len(train_scenes), len(val_data), len(val_scenes), total,
    )  # fmt: skip
    if cfg.init is not None:
        model = load_checkpoint(cfg.init, cfg.model).model.train()
    else:
        model = create_model(cfg.model)
    if cfg.pretrained is not None:
        model = load_hf_weights(model, cfg.pretrained)
    model.to(cfg.device).train()
    optimizer = _optimizer(model, cfg)
    loader = torch.utils.data.DataLoader(
        train_data,
        batch_size=min(cfg.batch_size, len(train_data)),
        shuffle=True,
        drop_last=True,
        generator=torch.Generator().manual_seed(cfg.seed),
    )
    meta_base = {
        "training": {k: v for k, v in dataclasses.asdict(cfg).items()},
        "train_scenes": train_scenes,
        "val_scenes": val_scenes,
        "classes": list(tx.CLASS_NAMES),
        "cache": str(Path(shards).resolve()),
    }
    history: list[dict[str, Any]] = []
    best_miou, best_scores = -1.0, {}
    paths = {"best": out / "best.pt", "last": out / "last.pt"}
    divergence = DivergenceCheck(out, cfg.lr, cfg.weight_decay, kept=lambda: _kept_files(paths))
    start, step, losses = time.perf_counter(), 0, []
    while step < total:
        for images_u8, target in loader:
            if step >= total:
                break
            for group in optimizer.param_groups:
                group["lr"] = _learning_rate(step, total, cfg)
            losses.append(_train_step(model, optimizer, images_u8, target, cfg, divergence, step + 1))
            step += 1
            if step % cfg.eval_every == 0 or step == total:
                record = {
                    "step": step,
                    "seconds": round(time.perf_counter() - start, 1),
                    "train_loss": float(np.mean(losses)),
                }
                losses = []
                if len(val_data):
                    record["val"] = evaluate(model, val_data, cfg.device)
                    model.train()
                history.append(record)
                miou = record["val"]["miou"] if "val" in record else float(step)
                save_checkpoint(
                    paths["last"], model, {**meta_base, "step": step, "scores": record.get("val", {})}
                )
                if miou > best_miou or not paths["best"].exists():
                    best_miou, best_scores = miou, record.get("val", {})
                    save_checkpoint(paths["best"], model, {**meta_base, "step": step, "scores": best_scores})
                write_text_atomic(
                    out / "metrics.json", json.dumps({"config": meta_base, "history": history}, indent=1)
                )
                log.info("step %d/%d: %s", step, total, {k: v for k, v in record.items() if k != "val"})
                if progress is not None:
                    progress(record)
    return SegmenterRun(paths["best"], paths["last"], best_scores, history, train_scenes, val_scenes)
