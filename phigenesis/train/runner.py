"""What every trainer of this package shares: run folders, logs, schedules, resumable state, and
torchrun (gloo) process groups.

A run folder ``runs/NAME`` holds::

    config.yaml                  the run's full configuration (written once, checked on resume)
    metrics.csv                  one row per logged step (the loss curve); TensorBoard events in tb/
    checkpoints/step-0000100/    model.safetensors (the model, see :mod:`phigenesis.train.checkpoint`)
                                 trainer.safetensors (optimiser state and step: tensors + JSON)
    checkpoints/latest           the name of the newest complete checkpoint folder
    model.safetensors            the final weights (written when the run ends)

A run stops at the first step whose loss (any term), gradient or updated weights are not finite
(:class:`DivergenceCheck`): a :class:`~phigenesis.errors.TrainingDivergedError` names the run
folder, the step, the term or parameter and the config value most likely at fault; nothing of that
step is written, so the newest checkpoint is the last good one. A checkpoint that cannot be
written (a full disk) is an error naming the file, with the earlier checkpoints intact.

Resuming loads the newest complete checkpoint and truncates ``metrics.csv`` to its step, so a run
killed or interrupted at any moment continues with the same loss curve as one never interrupted:
every random draw of a step comes from a generator seeded by (seed, step), never from state that a
restart loses, and every file is written under a temporary name and renamed.

A run folder is untrusted input. Nothing in it is unpickled (older runs' ``trainer.pt`` is read
with ``weights_only=True``); a checkpoint folder counts only when it is complete (both files
present, their headers readable, the step they record that of the folder) and resolves inside the
run folder; ``checkpoints/latest`` is a hint that is checked, never followed outside
``checkpoints/``: when it is missing, damaged or names another folder, the newest complete folder
is used, with a warning naming the pointer and what it said. Resuming a folder that has logged
steps but no usable checkpoint is refused rather than restarted from step 0 over its log.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import re
import shutil
import signal
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
import yaml
from torch import Tensor, nn

from phigenesis.data.shards import os_reason
from phigenesis.errors import CheckpointError, TrainingDivergedError
from phigenesis.models.checkpoint import FORMAT, read_safetensors_metadata
from phigenesis.train.checkpoint import (
    CheckpointWriteError,
    TrainingState,
    atomic_path,
    read_trainer_state,
    restore_optimizer,
    save_checkpoint,
    trainer_state_step,
    write_trainer_state,
)

__all__ = [
    "CHECKPOINTS",
    "LATEST",
    "CheckpointFolder",
    "DivergenceCheck",
    "MetricsLog",
    "ProcessGroup",
    "TrainingState",
    "checkpoint_to_resume",
    "cosine_lr",
    "inspect_checkpoints",
    "kept_step",
    "latest_checkpoint",
    "load_training_state",
    "process_group",
    "read_metrics",
    "read_run_config",
    "restore_optimizer",
    "run_evidence",
    "save_training_state",
    "step_generator",
    "write_text_atomic",
]

log = logging.getLogger(__name__)

CHECKPOINTS = "checkpoints"
LATEST = "latest"
MODEL_FILE = "model.safetensors"
TRAINER_FILE = "trainer.safetensors"
#: The trainer state of runs written before ``trainer.safetensors`` (read with ``weights_only=True``).
LEGACY_TRAINER_FILE = "trainer.pt"
METRICS_FILE = "metrics.csv"
CONFIG_FILE = "config.yaml"

_STEP_FOLDER = re.compile(r"step-(\d+)")
_LEFTOVER = re.compile(r"\.[\w.-]+\.(\d+)\.tmp")
#: Bytes of ``checkpoints/latest`` read at most (it holds one folder name).
_POINTER_BYTES = 256


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


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Writes ``text`` to ``path`` under a temporary name and renames it, so ``path`` never holds
    half a file (a run folder's ``config.yaml``, ``metrics.json``, ``summary.json``)."""
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    except OSError as e:
        raise CheckpointWriteError(path, os_reason(e)) from e
    return path


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Holds a Ctrl-C (SIGINT) back while a run writes something that belongs together (a log row,
    a checkpoint and its pointer), then delivers it, so an interrupt lands between steps' files.
    Outside the main thread (where Python cannot handle signals) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[tuple[int, Any]] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append((signum, frame)))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received and callable(previous):  # SIG_IGN / SIG_DFL: nothing of ours to deliver
            previous(*received[0])


class MetricsLog:
    """The loss curve: ``metrics.csv`` (one row per logged step) and TensorBoard scalars in ``tb/``.

    ``resume_step``: rows after this step (written by a run that was killed before its next
    checkpoint) are dropped, so the resumed run writes them again; the file is rewritten under a
    temporary name, so an interrupt never loses the rows kept. A row whose step is not a number
    raises :class:`CheckpointError` naming the file and line. TensorBoard gets the same: a resumed
    run's event file purges the steps after ``resume_step`` (TensorBoard's ``purge_step``), and a
    run that starts from step 0 removes the event files an earlier run left in ``tb/``, as it
    empties the CSV, so no killed run's curve is mixed in.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike[str],
        columns: Sequence[str],
        resume_step: int | None = None,
        tensorboard: bool = True,
    ):
        self.path = Path(out_dir) / METRICS_FILE
        self.columns = ["step", *columns]
        kept: list[dict[str, str]] = []
        if resume_step is not None and self.path.exists():
            kept = _rows_up_to(self.path, resume_step)
        with atomic_path(self.path) as tmp, tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)
        self._tb = None
        if tensorboard:
            try:
                # optional dependency: only when TensorBoard logging is on
                from torch.utils.tensorboard import SummaryWriter

                tb_dir = Path(out_dir) / "tb"
                if resume_step is None:
                    _remove_event_files(tb_dir)
                self._tb = SummaryWriter(str(tb_dir), purge_step=(resume_step or 0) + 1)
            except ImportError:  # tensorboard not installed: the CSV is the log
                log.warning("tensorboard is not installed; logging to %s only", self.path)

    def log(self, step: int, values: dict[str, float]) -> None:
        """Appends a step's row to metrics.csv and its scalars to TensorBoard; Ctrl-C waits until
        both are written (an interrupt inside TensorBoard's writer can hang its close)."""
        row = {"step": step, **{k: f"{float(values[k]):.8g}" for k in self.columns[1:] if k in values}}
        with interrupts_held():
            try:
                with self.path.open("a", newline="") as f:
                    csv.DictWriter(f, self.columns, extrasaction="ignore").writerow(row)
            except OSError as e:
                reason = os_reason(e)
                raise CheckpointWriteError(
                    self.path, reason, f"{self.path}: cannot add the row of step {step} ({reason})"
                ) from e
            if self._tb is not None:
                for k, v in values.items():
                    self._tb.add_scalar(k, float(v), step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


def _remove_event_files(tb_dir: Path) -> None:
    """Removes the TensorBoard event files of an earlier run from ``tb_dir`` (only those: plain
    files named ``events.out.tfevents.*``), saying how many."""
    if not tb_dir.is_dir() or tb_dir.is_symlink():
        return
    stale = [p for p in tb_dir.glob("events.out.tfevents.*") if p.is_file() and not p.is_symlink()]
    for path in stale:
        path.unlink()
    if stale:
        log.info(
            "%s: removed %d TensorBoard event file(s) of an earlier run (this run starts at step 0)",
            tb_dir,
            len(stale),
        )


def _rows_up_to(path: Path, step: int) -> list[dict[str, str]]:
    """The rows of ``metrics.csv`` logged at or before ``step``."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = [(reader.line_num, row) for row in reader]
    except (UnicodeDecodeError, csv.Error) as e:
        raise CheckpointError(f"{path}: damaged ({e})") from e
    kept = []
    for line, row in rows:
        value = row.get("step")
        if value is None or not value.strip().isdigit():
            raise CheckpointError(f"{path}: line {line}: step {value!r} is not a step number")
        if int(value) <= step:
            kept.append(row)
    return kept


def _logged_steps(out_dir: Path) -> int:
    """How many rows ``metrics.csv`` of a run folder holds (0 without one)."""
    path = out_dir / METRICS_FILE
    if not path.is_file():
        return 0
    with path.open("rb") as f:
        lines = sum(1 for line in f if line.strip())
    return max(lines - 1, 0)


def read_metrics(out_dir: str | os.PathLike[str]) -> list[dict[str, float]]:
    """The rows of a run's ``metrics.csv`` as numbers."""
    with (Path(out_dir) / METRICS_FILE).open(newline="") as f:
        return [{k: float(v) for k, v in row.items() if v != ""} for row in csv.DictReader(f)]


def read_run_config(out_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
    """A run folder's ``config.yaml`` (None when there is none); a file that is not a YAML mapping
    raises :class:`CheckpointError` naming it."""
    path = Path(out_dir) / CONFIG_FILE
    if not path.is_file():
        return None
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError) as e:
        raise CheckpointError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from e
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise CheckpointError(f"{path}: a YAML {type(values).__name__}, not a mapping of options")
    return values


# --------------------------------------------------------------------------------------------
# Checkpoint folders


@dataclass(frozen=True)
class CheckpointFolder:
    """A ``checkpoints/step-N`` entry of a run folder and whether a resume can use it.

    Attributes:
        step: N, the optimiser steps done when it was written.
        path: the folder.
        problem: None when complete; else what is wrong ("trainer.safetensors: truncated ...").
    """

    step: int
    path: Path
    problem: str | None


def _inside(path: Path, root: Path) -> bool:
    """Whether ``path``, with every symbolic link followed, lies in ``root`` (False for a path
    that cannot be resolved: a NUL byte, a loop of links)."""
    try:
        return path.resolve().is_relative_to(root.resolve())
    except (OSError, RuntimeError, ValueError):
        return False


def _trainer_file(folder: Path) -> Path | None:
    """A checkpoint folder's trainer state: ``trainer.safetensors``, else an older run's ``trainer.pt``."""
    for name in (TRAINER_FILE, LEGACY_TRAINER_FILE):
        if (folder / name).is_file():
            return folder / name
    return None


def _header_problem(folder: Path, trainer: Path, step: int) -> str | None:
    """What is wrong with the headers of a checkpoint folder's model and trainer state (None: both
    read, the model is a phigenesis checkpoint and the trainer state is of the folder's step)."""
    try:
        if read_safetensors_metadata(folder / MODEL_FILE).get("format") != json.dumps(FORMAT):
            return f"{MODEL_FILE} is not a phigenesis checkpoint"
        written = trainer_state_step(trainer)
    except CheckpointError as e:
        return str(e).removeprefix(f"{folder}{os.sep}")
    if written is not None and written != step:
        return f"{trainer.name} is of step {written}"
    return None


def _folder_problem(folder: Path, run: Path, step: int) -> str | None:
    """What makes a checkpoint folder unusable, or None when it is complete: inside the run
    folder, both files present with readable headers, the trainer state of the folder's step."""
    if not _inside(folder, run):
        return "resolves outside the run folder"
    if not folder.is_dir():
        return "not a folder"
    trainer = _trainer_file(folder)
    if not (folder / MODEL_FILE).is_file():
        return f"no {MODEL_FILE}"
    if trainer is None:
        return f"no {TRAINER_FILE}"
    for path in (folder / MODEL_FILE, trainer):
        if not _inside(path, run):
            return f"{path.name} resolves outside the run folder"
    return _header_problem(folder, trainer, step)


def inspect_checkpoints(out_dir: str | os.PathLike[str]) -> list[CheckpointFolder]:
    """Every ``checkpoints/step-N`` entry of a run folder, oldest first, each with what (if
    anything) keeps a resume from using it. Reads headers only."""
    run = Path(out_dir)
    root = run / CHECKPOINTS
    if not root.is_dir():
        return []
    found = []
    for entry in root.iterdir():
        match = _STEP_FOLDER.fullmatch(entry.name)
        if match is not None:
            step = int(match.group(1))
            found.append(CheckpointFolder(step, entry, _folder_problem(entry, run, step)))
    return sorted(found, key=lambda f: (f.step, f.path.name))


def _pointer_problem(root: Path, folders: list[CheckpointFolder], newest: Path) -> str | None:
    """What is wrong with ``checkpoints/latest`` given the newest complete folder (None: it names
    that folder)."""
    pointer = root / LATEST
    if not pointer.exists():
        return "is missing"
    if pointer.is_symlink() or not pointer.is_file():
        return "is not a plain file"
    with pointer.open("rb") as f:
        raw = f.read(_POINTER_BYTES)
    try:
        said = raw.decode("utf-8").strip()
    except UnicodeDecodeError:
        return f"holds {raw[:40]!r}, not a checkpoint folder name"
    if not said:
        return "is empty"
    if _STEP_FOLDER.fullmatch(said) is None:
        if not _inside(root / said, root):
            return f"says {said!r}, a path outside {root}; not followed"
        return f"says {said!r}, not a checkpoint folder name"
    entry = next((f for f in folders if f.path.name == said), None)
    if entry is None:
        return f"says {said!r}, which does not exist"
    if entry.problem is not None:
        return f"says {said!r}, which cannot be used ({entry.problem})"
    if entry.path != newest:
        return f"says {said!r}, but {newest.name} is newer and complete"
    return None


def _newest_complete(out_dir: Path, folders: list[CheckpointFolder], check_pointer: bool) -> Path | None:
    """The newest complete folder of ``folders``; with ``check_pointer``, a warning when
    ``checkpoints/latest`` does not name it."""
    complete = [f.path for f in folders if f.problem is None]
    if not complete:
        return None
    newest = complete[-1]
    if check_pointer:
        root = out_dir / CHECKPOINTS
        problem = _pointer_problem(root, folders, newest)
        if problem is not None:
            log.warning(
                "%s: %s; using %s, the newest complete checkpoint", root / LATEST, problem, newest.name
            )
    return newest


def latest_checkpoint(out_dir: str | os.PathLike[str]) -> Path | None:
    """The newest complete checkpoint folder of a run (see the module docstring), or None.

    ``checkpoints/latest`` is checked against it: when the pointer is missing, damaged, names a
    missing or incomplete folder or a path outside ``checkpoints/``, a warning names the pointer
    and what it said, and the newest complete folder is returned all the same."""
    out_dir = Path(out_dir)
    return _newest_complete(out_dir, inspect_checkpoints(out_dir), check_pointer=True)


def kept_step(out_dir: str | os.PathLike[str]) -> int | None:
    """The step a resume of ``out_dir`` would continue from (its newest complete checkpoint), or
    None when nothing resumable was kept; logs nothing. For messages after an interrupt::

        step = kept_step(out)
        print(f"interrupted; {out} holds step {step}: continue with --resume" if step is not None
              else f"interrupted before the first checkpoint of {out}")
    """
    out_dir = Path(out_dir)
    folders = inspect_checkpoints(out_dir)
    newest = _newest_complete(out_dir, folders, check_pointer=False)
    return next(f.step for f in folders if f.path == newest) if newest is not None else None


def run_evidence(out_dir: str | os.PathLike[str]) -> str | None:
    """What shows that ``out_dir`` holds a run ("checkpoint step-0000100", "model.safetensors"),
    or None: a trainer refuses to start a new run over it without resume."""
    out_dir = Path(out_dir)
    folders = inspect_checkpoints(out_dir)
    if folders:
        return f"checkpoint {folders[-1].path.name}"
    if (out_dir / MODEL_FILE).exists():
        return MODEL_FILE
    return None


def checkpoint_to_resume(out_dir: str | os.PathLike[str]) -> Path | None:
    """The checkpoint folder a resumed run continues from: the newest complete one
    (:func:`latest_checkpoint`). None when the folder holds no checkpoint and no logged step (the
    run starts at step 0). Raises :class:`CheckpointError` naming the folder when it has logged
    steps or checkpoint folders but none usable: restarting would overwrite the run's log."""
    out_dir = Path(out_dir)
    folders = inspect_checkpoints(out_dir)
    newest = _newest_complete(out_dir, folders, check_pointer=True)
    if newest is not None:
        return newest
    logged = _logged_steps(out_dir)
    if not folders and not logged:
        return None
    held = f"{METRICS_FILE} holds {logged} logged step{'s' * (logged != 1)}"
    if not folders:
        raise CheckpointError(
            f"{out_dir}: nothing to resume: there is no checkpoint in {out_dir / CHECKPOINTS}, but "
            f"{held}; rerun without resume to start again from step 0 (overwriting that log), or use "
            "another folder"
        )
    found = "; ".join(f"{f.path.name}: {f.problem}" for f in folders)
    raise CheckpointError(
        f"{out_dir}: no usable checkpoint to resume from in {out_dir / CHECKPOINTS} ({found})"
        + (f", but {held}" if logged else "")
        + "; refusing to restart the run from step 0. Repair or remove those folders, or start the run "
        "in another folder"
    )


# --------------------------------------------------------------------------------------------
# Writing and reading checkpoints


def _remove(path: Path) -> None:
    """Removes a file, a symbolic link (not what it points at) or a folder tree."""
    if path.is_symlink() or path.is_file():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path, ignore_errors=True)


def _pid_alive(pid: int) -> bool:
    """Whether a process of this machine has the id ``pid``."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. another user's process
        return True
    return True


def _remove_leftovers(folder: Path) -> None:
    """Removes the temporary files and folders (``.NAME.PID.tmp``) that a killed process of this
    machine left in ``folder``; those of live processes stay."""
    if not folder.is_dir():
        return
    for entry in folder.iterdir():
        match = _LEFTOVER.fullmatch(entry.name)
        if match is not None and int(match.group(1)) != os.getpid() and not _pid_alive(int(match.group(1))):
            _remove(entry)


def _prune(out_dir: Path, step: int, keep: int) -> None:
    """After writing the checkpoint of ``step``: keeps the newest ``keep`` complete checkpoints up
    to ``step`` and removes the other step folders up to it, and the incomplete ones past it (left
    by a run that was resumed from before them)."""
    folders = inspect_checkpoints(out_dir)
    kept = {f.path for f in [f for f in folders if f.step <= step and f.problem is None][-keep:]}
    for folder in folders:
        ours = folder.path.is_symlink() or _inside(folder.path, out_dir)  # never what lies outside
        if ours and folder.path not in kept and (folder.step <= step or folder.problem is not None):
            _remove(folder.path)


def save_training_state(
    out_dir: str | os.PathLike[str],
    step: int,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    extra: dict[str, Any] | None = None,
    keep: int = 2,
) -> Path:
    """Writes ``checkpoints/step-NNNNNNN/`` (model.safetensors + trainer.safetensors) atomically,
    points ``checkpoints/latest`` at it and keeps the newest ``keep`` checkpoints. ``extra``: JSON
    facts stored with the optimiser state. An interrupt while it writes leaves the earlier
    checkpoints as they were and nothing under a final name. A ``checkpoints/`` that resolves
    outside the run folder raises :class:`CheckpointError`."""
    out_dir = Path(out_dir)
    root = out_dir / CHECKPOINTS
    root.mkdir(parents=True, exist_ok=True)
    if not _inside(root, out_dir):
        raise CheckpointError(
            f"{root}: resolves outside the run folder (to {root.resolve()}); a resume would not read "
            "checkpoints there. Link the whole run folder instead"
        )
    _remove_leftovers(root)
    _remove_leftovers(out_dir)
    name = f"step-{step:07d}"
    tmp = root / f".{name}.{os.getpid()}.tmp"
    final = root / name
    _remove(tmp)
    with interrupts_held():  # the folder and the pointer to it come together
        try:
            tmp.mkdir()
            save_checkpoint(tmp / MODEL_FILE, model, {"step": step})
            write_trainer_state(tmp / TRAINER_FILE, step, optimizer.state_dict(), dict(extra or {}))
            _remove(final)  # a damaged folder of this step, from a run resumed before it
            os.replace(tmp, final)
        except CheckpointWriteError as e:
            _remove(tmp)
            raise _not_written(out_dir, final / e.path.name, step, e.reason) from e
        except OSError as e:
            _remove(tmp)
            raise _not_written(out_dir, final, step, os_reason(e)) from e
        except BaseException:
            _remove(tmp)
            raise
        try:
            with atomic_path(root / LATEST) as pointer:
                pointer.write_text(name + "\n")
        except OSError as e:
            raise CheckpointWriteError(
                root / LATEST,
                os_reason(e),
                f"{root / LATEST}: cannot be written ({os_reason(e)}); the checkpoint of step {step} is "
                f"complete in {final}, and a resume finds it without the pointer",
            ) from e
    _prune(out_dir, step, keep)
    return final


def _not_written(out_dir: Path, path: Path, step: int, reason: str) -> CheckpointWriteError:
    """The error of a checkpoint of ``step`` that could not be written: the file, the system's
    reason and what the run keeps."""
    return CheckpointWriteError(
        path,
        reason,
        f"{path}: the checkpoint of step {step} cannot be written ({reason}); {_kept_checkpoint(out_dir)}",
    )


def load_training_state(folder: str | os.PathLike[str]) -> TrainingState:
    """Reads the optimiser state and step of a checkpoint folder (``trainer.safetensors``, or an
    older run's ``trainer.pt`` with ``weights_only=True``); the model is read with
    ``load_checkpoint``. Load it into an optimiser with :func:`restore_optimizer`. A missing,
    truncated or damaged file, or one of another step than its folder, raises
    :class:`CheckpointError` naming it."""
    folder = Path(folder)
    path = _trainer_file(folder)
    if path is None:
        raise CheckpointError(f"{folder}: no {TRAINER_FILE} (the optimiser state) in the checkpoint folder")
    if path.name == LEGACY_TRAINER_FILE:
        log.info("%s: an older run's trainer state, read with weights_only=True", path)
    state = read_trainer_state(path)
    match = _STEP_FOLDER.fullmatch(folder.name)
    if match is not None and int(match.group(1)) != state.step:
        raise CheckpointError(f"{path}: the trainer state of step {state.step}, in the folder {folder.name}")
    return state


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


# --------------------------------------------------------------------------------------------
# Divergence


def _first_non_finite(named: Iterable[tuple[str, Tensor | None]]) -> str | None:
    """The name of the first tensor holding NaN or infinity (None entries are skipped); one
    device synchronisation, however many tensors."""
    items = [(name, tensor) for name, tensor in named if tensor is not None]
    if not items:
        return None
    finite = torch.stack([torch.isfinite(tensor).all() for _, tensor in items])
    if bool(finite.all()):
        return None
    return items[int((~finite).nonzero()[0, 0])][0]


@dataclass(frozen=True)
class DivergenceCheck:
    """Stops a training run at the first non-finite loss term, gradient or weight, with a
    :class:`TrainingDivergedError` naming the run folder, the step, the term (or parameter), the
    config value most likely at fault and what is kept; nothing of that step is written.

    After the backward pass call :meth:`losses`, then :meth:`clip_gradients` (in place of
    ``clip_grad_norm_``), then step the optimiser and call :meth:`weights_after`. Under torchrun
    pass every rank the same values (the losses averaged over the ranks; the gradients are
    synchronised), so all ranks stop at the same step.

    Attributes:
        run: the run folder (messages name it).
        lr: the config's peak learning rate; weight_decay: its weight decay.
        weights: loss term -> (its config key, its weight), for terms that have a weight in the
            config (``{"rgb": ("weights.rgb", 1.0)}``).
        kept: what is kept for a resume, in words; None: the newest complete checkpoint of
            ``run`` (:func:`kept_step`).
    """

    run: Path
    lr: float
    weight_decay: float = 0.0
    weights: Mapping[str, tuple[str, float]] = dataclasses.field(default_factory=dict)
    kept: Callable[[], str] | None = None

    def losses(self, step: int, terms: Mapping[str, float], total: str = "loss") -> None:
        """Raises when a loss term of ``step`` (1-based, as logged) is not finite: the first such
        term, else the weighted ``total`` (the sum of finite terms overflowed)."""
        bad = next((k for k, v in terms.items() if k != total and not math.isfinite(v)), None)
        if bad is not None:
            self._stop(step, f"the loss term {bad!r} is {terms[bad]}", self._term_suspect(step, bad))
        if total in terms and not math.isfinite(terms[total]):
            what = "the total loss" if len(terms) > 1 else "the loss"
            self._stop(step, f"{what} is {terms[total]}", self._total_suspect(step, terms))

    def clip_gradients(
        self, step: int, named_parameters: Iterable[tuple[str, nn.Parameter]], max_norm: float
    ) -> float:
        """Clips the gradients of ``step`` to the total 2-norm ``max_norm`` exactly as
        ``torch.nn.utils.clip_grad_norm_`` does, and returns their norm before clipping; raises
        first when that norm is not finite, naming the first parameter whose gradient holds NaN
        or infinity (clipping would spread the NaN to every gradient)."""
        named = [(name, p) for name, p in named_parameters if p.grad is not None]
        grads = [p.grad for _, p in named if p.grad is not None]
        norm = torch.nn.utils.get_total_norm(grads)
        if not bool(torch.isfinite(norm)):
            name = _first_non_finite((n, p.grad) for n, p in named)
            what = (
                f"the gradient of {name!r} is not finite"
                if name is not None
                else f"the gradient norm is {float(norm)} (every gradient finite: their squares overflowed)"
            )
            self._stop(step, what, self._lr_suspect(step))
        torch.nn.utils.clip_grads_with_norm_([p for _, p in named], max_norm, norm)
        return float(norm)

    def weights_after(self, step: int, named_parameters: Iterable[tuple[str, nn.Parameter]]) -> None:
        """Raises when the optimiser's update of ``step`` left a parameter NaN or infinite."""
        name = _first_non_finite(named_parameters)
        if name is None:
            return
        suspect = f"lr = {self.lr:g} (lower it)"
        factor = 1.0 - self.lr * self.weight_decay
        if self.lr * self.weight_decay >= 1.0:
            key = f"lr = {self.lr:g}" if self.lr > 1.0 else f"weight_decay = {self.weight_decay:g}"
            suspect = (
                f"{key} (AdamW scales each weight by 1 - lr x weight_decay = {factor:g} per step: lower it)"
            )
        self._stop(step, f"the update left {name!r} with NaN or infinite values", suspect)

    def _term_suspect(self, step: int, term: str) -> str:
        """A non-finite weight of ``term``, else what changes the model between steps."""
        key, weight = self.weights.get(term, ("", 1.0))
        if not math.isfinite(weight):
            return f"{key} = {weight}"
        return self._lr_suspect(step)

    def _total_suspect(self, step: int, terms: Mapping[str, float]) -> str:
        """A non-finite weight, else the weight of the largest weighted term (the sum of finite
        terms overflowed), or the learning rate when the loss has no weighted terms."""
        for key, weight in self.weights.values():
            if not math.isfinite(weight):
                return f"{key} = {weight}"
        weighted = {k: abs(w * terms[k]) for k, (_, w) in self.weights.items() if k in terms}
        if not weighted:
            return self._lr_suspect(step)
        term = max(weighted, key=lambda k: weighted[k])
        key, weight = self.weights[term]
        return f"{key} = {weight:g} (lower it)"

    def _lr_suspect(self, step: int) -> str:
        """The learning rate, after the first update; before it, no config value changed anything."""
        if step <= 1:
            return "the data or the initial weights (no update had been applied yet)"
        return f"lr = {self.lr:g} (lower it)"

    def _stop(self, step: int, what: str, suspect: str) -> None:
        kept = self.kept() if self.kept is not None else _kept_checkpoint(self.run)
        raise TrainingDivergedError(
            f"{self.run}: training diverged at step {step}: {what}; most likely at fault: {suspect}; {kept}"
        )


def _kept_checkpoint(run: Path) -> str:
    """What a diverged run keeps, in words: its newest complete checkpoint."""
    step = kept_step(run)
    if step is None:
        return "no checkpoint was written before it"
    return f"the checkpoint of step {step} is kept (nothing of this step was written)"
