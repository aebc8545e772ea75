"""What every trainer of this package shares: run folders, logs, schedules, resumable state, and
torchrun (gloo) process groups.

A run folder ``runs/NAME`` holds::

    config.yaml                  the run's full configuration (written once, checked on resume)
    metrics.csv                  one row per logged step (the loss curve); TensorBoard events in tb/
    checkpoints/step-0000100/    model.safetensors (the model, see :mod:`phigenesis.train.checkpoint`)
                                 trainer.pt (optimiser state, step, RNG states, data position)
    checkpoints/latest           the name of the newest complete checkpoint folder
    model.safetensors            the final weights (written when the run ends)

Resuming loads the newest complete checkpoint and truncates ``metrics.csv`` to its step, so a run
killed at any moment continues with the same loss curve as one never interrupted: every random draw
of a step comes from a generator seeded by (seed, step), never from state that a restart loses.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from phigenesis.train.checkpoint import save_checkpoint

log = logging.getLogger(__name__)

CHECKPOINTS = "checkpoints"
LATEST = "latest"


def cosine_lr(
    step: int, total_steps: int, peak: float, warmup_steps: int = 0, final_ratio: float = 0.05
) -> float:
    """Learning rate at ``step`` (0-based): linear warm-up to ``peak``, then a cosine decay to
    ``final_ratio * peak`` at ``total_steps``."""
    if warmup_steps and step < warmup_steps:
        return peak * (step + 1) / warmup_steps
    span = max(total_steps - warmup_steps, 1)
    progress = min(max(step - warmup_steps, 0) / span, 1.0)
    return peak * (final_ratio + (1.0 - final_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def step_generator(seed: int, step: int, rank: int = 0) -> torch.Generator:
    """The random source of one training step: the same (seed, step, rank) gives the same draws,
    in an interrupted run and in one resumed from a checkpoint."""
    g = torch.Generator()
    g.manual_seed((int(seed) * 1_000_003 + int(step)) * 131 + int(rank))
    return g


class MetricsLog:
    """The loss curve: ``metrics.csv`` (one row per logged step) and TensorBoard scalars in ``tb/``.

    ``resume_step``: rows after this step (written by a run that was killed before its next
    checkpoint) are dropped, so the resumed run writes them again.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike[str],
        columns: Sequence[str],
        resume_step: int | None = None,
        tensorboard: bool = True,
    ):
        self.path = Path(out_dir) / "metrics.csv"
        self.columns = ["step", *columns]
        kept: list[dict[str, str]] = []
        if resume_step is not None and self.path.exists():
            with self.path.open(newline="") as f:
                kept = [row for row in csv.DictReader(f) if int(row["step"]) <= resume_step]
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(str(Path(out_dir) / "tb"), purge_step=(resume_step or 0) + 1)
            except ImportError:  # tensorboard not installed: the CSV is the log
                log.warning("tensorboard is not installed; logging to %s only", self.path)

    def log(self, step: int, values: dict[str, float]) -> None:
        row = {"step": step, **{k: f"{float(values[k]):.8g}" for k in self.columns[1:] if k in values}}
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.columns, extrasaction="ignore").writerow(row)
        if self._tb is not None:
            for k, v in values.items():
                self._tb.add_scalar(k, float(v), step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


def read_metrics(out_dir: str | os.PathLike[str]) -> list[dict[str, float]]:
    """The rows of a run's ``metrics.csv`` as numbers."""
    with (Path(out_dir) / "metrics.csv").open(newline="") as f:
        return [{k: float(v) for k, v in row.items() if v != ""} for row in csv.DictReader(f)]


@dataclass(frozen=True)
class TrainingState:
    """What a resumed run needs besides the model: where it was and the optimiser's moments."""

    step: int
    optimizer: dict[str, Any]
    extra: dict[str, Any]


def save_training_state(
    out_dir: str | os.PathLike[str],
    step: int,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    extra: dict[str, Any] | None = None,
    keep: int = 2,
) -> Path:
    """Writes ``checkpoints/step-NNNNNNN/`` (model.safetensors + trainer.pt) atomically, points
    ``checkpoints/latest`` at it and keeps the newest ``keep`` checkpoints."""
    root = Path(out_dir) / CHECKPOINTS
    root.mkdir(parents=True, exist_ok=True)
    name = f"step-{step:07d}"
    tmp = root / f".{name}.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    save_checkpoint(tmp / "model.safetensors", model, {"step": step})
    torch.save(
        {"step": step, "optimizer": optimizer.state_dict(), "extra": dict(extra or {})}, tmp / "trainer.pt"
    )
    final = root / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    pointer = root / f".{LATEST}.tmp"
    pointer.write_text(name + "\n")
    os.replace(pointer, root / LATEST)
    done = sorted(p for p in root.glob("step-*") if p.is_dir())
    for old in done[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(out_dir: str | os.PathLike[str]) -> Path | None:
    """The newest complete checkpoint folder of a run, or None."""
    pointer = Path(out_dir) / CHECKPOINTS / LATEST
    if not pointer.is_file():
        return None
    folder = pointer.parent / pointer.read_text().strip()
    return folder if (folder / "trainer.pt").is_file() and (folder / "model.safetensors").is_file() else None


def load_training_state(folder: str | os.PathLike[str]) -> TrainingState:
    """Reads ``trainer.pt`` of a checkpoint folder (the model is read with ``load_checkpoint``)."""
    path = Path(folder) / "trainer.pt"
    payload = torch.load(path, map_location="cpu", weights_only=False)
    return TrainingState(step=int(payload["step"]), optimizer=payload["optimizer"], extra=payload["extra"])


@dataclass(frozen=True)
class ProcessGroup:
    """This process's place in a torchrun job (rank 0 of 1 when run directly)."""

    rank: int
    world_size: int

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def mean(self, values: torch.Tensor) -> torch.Tensor:
        """``values`` averaged over all processes (unchanged in a single process)."""
        if self.world_size == 1:
            return values
        out = values.detach().clone()
        dist.all_reduce(out)
        return out / self.world_size

    def barrier(self) -> None:
        if self.world_size > 1:
            dist.barrier()


@contextmanager
def process_group() -> Iterator[ProcessGroup]:
    """Joins the torchrun job described by the environment (``WORLD_SIZE``, ``RANK``, ...) over gloo
    (CPU), or yields a single-process group when there is none; leaves the group on exit."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        yield ProcessGroup(0, 1)
        return
    dist.init_process_group("gloo")
    try:
        yield ProcessGroup(dist.get_rank(), dist.get_world_size())
    finally:
        dist.destroy_process_group()
