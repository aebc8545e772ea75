"""Writing checkpoints, and the optimiser state a resumed run needs. Model checkpoints are read by
:func:`phigenesis.models.checkpoint.load_checkpoint` (their format is described there); what is
written here is what that reader accepts, with the checksum of its tensors
(:func:`~phigenesis.models.checkpoint.tensor_checksum`), and non-finite weights are refused on save.
Every reader here treats its file as untrusted input, as that one does.

**Trainer state** (``trainer.safetensors`` in a run's checkpoint folder, see
:mod:`phigenesis.train.runner`): the optimiser's per-parameter tensors (AdamW's ``step``,
``exp_avg``, ``exp_avg_sq``) as safetensors tensors named ``state/<param>/<name>``, and the
header's JSON metadata ``format`` (``"phigenesis.trainer"``), ``version``, ``step``,
``param_groups`` (the optimiser's hyperparameters), ``scalars`` (non-tensor per-parameter
state), ``extra`` (the trainer's own facts) and ``checksum`` (of its tensors, as above).
Learning rate, random draws and data position are functions of the step, so the step is all
the rest a resume needs. Older runs' ``trainer.pt``
(a ``torch.save`` dict) is still read, with ``weights_only=True``.

Files are written under a temporary name, flushed to disk and renamed, so a killed or
interrupted run, or a full disk, never leaves half a file under a final name; a write that fails
is a :class:`CheckpointWriteError` naming the file and the system's reason.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import save_file
from torch import nn

from phigenesis.data.shards import fsync_dir, os_reason
from phigenesis.errors import CheckpointError
from phigenesis.models.checkpoint import (
    CHECKSUM,
    FORMAT,
    VERSION,
    decode_header,
    one_line,
    read_safetensors_metadata,
    read_tensors,
    refuse_non_finite,
    tensor_checksum,
    verify_checksum,
)
from phigenesis.torch_files import read_torch_file

__all__ = [
    "CheckpointWriteError",
    "TrainingState",
    "atomic_path",
    "read_trainer_state",
    "restore_optimizer",
    "save_checkpoint",
    "trainer_state_step",
    "write_trainer_state",
]

TRAINER_FORMAT = "phigenesis.trainer"
TRAINER_VERSION = 1

log = logging.getLogger(__name__)

#: The per-parameter state tensors each optimiser of the trainers needs to take a step.
REQUIRED_STATE = {"AdamW": ("step", "exp_avg", "exp_avg_sq"), "Adam": ("step", "exp_avg", "exp_avg_sq")}


@dataclass(frozen=True)
class TrainingState:
    """An optimiser's state as read from a checkpoint folder.

    Attributes:
        step: optimiser steps taken when it was written.
        optimizer: ``torch.optim.Optimizer.state_dict()`` layout (``state``: parameter index ->
            name -> tensor or number; ``param_groups``: hyperparameters and parameter indices).
        extra: the trainer's JSON facts (e.g. Stage 1's config).
        path: the file it was read from (error messages name it).
    """

    step: int
    optimizer: dict[str, Any]
    extra: dict[str, Any]
    path: Path


# --------------------------------------------------------------------------------------------
# Writing


class CheckpointWriteError(CheckpointError):
    """A checkpoint or trainer-state file that could not be written (a full disk, a file-size
    limit, no permission): nothing of it is left under its name or a temporary one (a file
    already under its name is unchanged), and the files written before stay. ``path`` and
    ``reason`` (the system's words) are kept for callers that name what they were writing."""

    def __init__(self, path: Path, reason: str, message: str | None = None):
        super().__init__(
            message or f"{path}: cannot be written ({reason}); a file already there is unchanged"
        )
        self.path = path
        self.reason = reason


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temporary name beside ``path`` (``.NAME.PID.tmp``) to write to; renamed to ``path`` when
    the block ends normally, removed when it raises (an interrupt included), so ``path`` only ever
    holds a complete file.

    Example::

        with atomic_path(out / "summary.json") as tmp:
            tmp.write_text(text)
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _safetensors_reason(error: SafetensorError) -> str:
    """The system's reason inside a safetensors write error ("... (os error 28)")."""
    code = re.search(r"os error (\d+)", str(error))
    return os.strerror(int(code.group(1))) if code else one_line(error)


def _write_durably(path: Path, write: Callable[[Path], None]) -> None:
    """Runs ``write(tmp)`` on a temporary name beside ``path``, flushes it to disk and renames it
    to ``path``. Any failure (a full disk shows at the write or at the flush) leaves nothing under
    either name and raises :class:`CheckpointWriteError` naming ``path`` and the reason."""
    try:
        with atomic_path(path) as tmp:
            write(tmp)
            with tmp.open("rb") as f:
                os.fsync(f.fileno())
    except OSError as e:
        raise CheckpointWriteError(path, os_reason(e)) from e
    except SafetensorError as e:
        raise CheckpointWriteError(path, _safetensors_reason(e)) from e
    fsync_dir(path.parent)


def _torch_bytes(payload: dict[str, Any]) -> bytes:
    """``payload`` as ``torch.save`` writes it (serialised in memory, so a failed write is the
    system's error, not torch's)."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return buffer.getvalue()


def save_checkpoint(
    path: str | os.PathLike[str], model: nn.Module, meta: dict[str, Any] | None = None
) -> Path:
    """Writes ``model`` (a registered variant: it has ``name`` and ``config``) to ``path``
    atomically, with the checksum of its tensors. Raises :class:`CheckpointError` naming the file
    and the tensor, writing nothing, when a weight is NaN or infinite, and
    :class:`CheckpointWriteError` when the file cannot be written (the file it would replace
    stays as it was)."""
    path = Path(path)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    refuse_non_finite(path, tensors, f"not written: model {model.name!r} holds")
    header = {
        "format": FORMAT,
        "version": VERSION,
        "model": model.name,
        "config": model.config.to_dict(),
        "meta": dict(meta or {}),
        CHECKSUM: tensor_checksum(tensors),
    }
    if path.suffix == ".safetensors":
        metadata = {k: json.dumps(v) for k, v in header.items()}
        _write_durably(path, lambda tmp: save_file(tensors, tmp, metadata=metadata))
    else:
        data = _torch_bytes({**header, "state_dict": tensors})
        _write_durably(path, lambda tmp: tmp.write_bytes(data))
    return path


def write_trainer_state(
    path: str | os.PathLike[str], step: int, optimizer_state: dict[str, Any], extra: dict[str, Any]
) -> Path:
    """Writes an optimiser's ``state_dict()`` at ``step`` and the trainer's JSON ``extra`` to
    ``path`` (safetensors + JSON, see the module docstring) atomically, with the checksum of its
    tensors; non-finite state and a failed write raise as :func:`save_checkpoint` does."""
    path = Path(path)
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for index, entries in optimizer_state["state"].items():
        for name, value in entries.items():
            if isinstance(value, torch.Tensor):
                tensors[f"state/{int(index)}/{name}"] = value.detach().cpu().contiguous().clone()
            else:
                scalars.setdefault(str(int(index)), {})[name] = value
    refuse_non_finite(path, tensors, "not written: the optimiser state holds")
    header = {
        "format": TRAINER_FORMAT,
        "version": TRAINER_VERSION,
        "step": int(step),
        "param_groups": optimizer_state["param_groups"],
        "scalars": scalars,
        "extra": extra,
        CHECKSUM: tensor_checksum(tensors),
    }
    metadata = {k: json.dumps(v) for k, v in header.items()}
    _write_durably(path, lambda tmp: save_file(tensors, tmp, metadata=metadata))
    return path


# --------------------------------------------------------------------------------------------
# Trainer state


def _tensor_state(path: Path, tensors: dict[str, torch.Tensor]) -> dict[int, dict[str, Any]]:
    """Per-parameter state from the ``state/<param>/<name>`` tensors of a trainer file."""
    state: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        parts = key.split("/", 2)
        if len(parts) != 3 or parts[0] != "state" or not parts[1].isdigit() or not parts[2]:
            raise CheckpointError(f"{path}: damaged trainer state (unexpected tensor {key!r})")
        state.setdefault(int(parts[1]), {})[parts[2]] = value
    return state


def _add_scalars(path: Path, state: dict[int, dict[str, Any]], scalars: Any) -> None:
    """Adds the header's non-tensor per-parameter state (``{"3": {"name": 1.0}}``) to ``state``."""
    if not isinstance(scalars, dict):
        raise CheckpointError(f"{path}: damaged trainer state ('scalars' is not a mapping)")
    for index, entries in scalars.items():
        if not str(index).isdigit() or not isinstance(entries, dict):
            raise CheckpointError(f"{path}: damaged trainer state (scalars of {index!r})")
        for name, value in entries.items():
            if not isinstance(value, (bool, int, float)):
                raise CheckpointError(f"{path}: damaged trainer state (scalar {index}/{name} is {value!r})")
            state.setdefault(int(index), {})[name] = value


def _check_optimizer_layout(path: Path, optimizer_state: Any) -> None:
    """Raises unless ``optimizer_state`` has the layout of ``Optimizer.state_dict()``: parameter
    groups with distinct integer parameter indices, and state only for those parameters."""
    if not isinstance(optimizer_state, dict):
        raise CheckpointError(f"{path}: damaged trainer state (the optimiser state is not a mapping)")
    groups, state = optimizer_state.get("param_groups"), optimizer_state.get("state")
    if not isinstance(groups, list) or not all(isinstance(g, dict) for g in groups):
        raise CheckpointError(f"{path}: damaged trainer state ('param_groups' is not a list of mappings)")
    lists = [g.get("params") for g in groups]
    if not all(isinstance(p, list) for p in lists):
        raise CheckpointError(f"{path}: damaged trainer state (a parameter group lists no parameters)")
    indices = [i for params in lists for i in params]
    if not all(type(i) is int for i in indices) or len(set(indices)) < len(indices):
        raise CheckpointError(f"{path}: damaged trainer state (parameter indices are not distinct integers)")
    if not isinstance(state, dict) or not set(state) <= set(indices):
        raise CheckpointError(f"{path}: damaged trainer state (state of parameters no group lists)")
    for index, entries in state.items():
        if not isinstance(entries, dict) or not all(isinstance(n, str) for n in entries):
            raise CheckpointError(f"{path}: damaged trainer state (state of parameter {index})")


def _read_trainer_safetensors(path: Path) -> TrainingState:
    header = decode_header(path, read_safetensors_metadata(path))
    if header.get("format") != TRAINER_FORMAT:
        raise CheckpointError(f"{path}: not a phigenesis trainer state (format {header.get('format')!r})")
    if not isinstance(header.get("version"), int) or header["version"] > TRAINER_VERSION:
        raise CheckpointError(
            f"{path}: trainer state version {header.get('version')!r}; this phigenesis reads up to "
            f"{TRAINER_VERSION}"
        )
    tensors = read_tensors(path, "cpu")
    verify_checksum(path, tensors, header.get(CHECKSUM))
    refuse_non_finite(path, tensors, "not a usable optimiser state:")
    state = _tensor_state(path, tensors)
    _add_scalars(path, state, header.get("scalars", {}))
    optimizer = {"state": state, "param_groups": header.get("param_groups")}
    return _trainer_state(path, header.get("step"), optimizer, header.get("extra", {}))


def _read_trainer_pt(path: Path) -> TrainingState:
    """An older run's ``trainer.pt`` (``{"step", "optimizer", "extra"}``), read with
    ``weights_only=True``."""
    payload = read_torch_file(path)
    if not isinstance(payload, dict) or not {"step", "optimizer"} <= set(payload):
        raise CheckpointError(f"{path}: not a phigenesis trainer state (no step and optimiser state)")
    return _trainer_state(path, payload["step"], payload["optimizer"], payload.get("extra", {}))


def _trainer_state(path: Path, step: Any, optimizer: Any, extra: Any) -> TrainingState:
    """A checked :class:`TrainingState` from a trainer file's fields."""
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise CheckpointError(f"{path}: damaged trainer state (step is {step!r})")
    if not isinstance(extra, dict):
        raise CheckpointError(f"{path}: damaged trainer state ('extra' is not a mapping)")
    _check_optimizer_layout(path, optimizer)
    return TrainingState(step, optimizer, extra, path)


def read_trainer_state(path: str | os.PathLike[str]) -> TrainingState:
    """Reads a trainer-state file: ``*.safetensors`` (this version's format) or an older run's
    ``trainer.pt`` (``weights_only=True``). A truncated, damaged or foreign file raises
    :class:`CheckpointError` naming it; use :func:`restore_optimizer` to load the state into an
    optimiser (it checks that the state fits)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: trainer state not found")
    if path.suffix == ".safetensors":
        return _read_trainer_safetensors(path)
    return _read_trainer_pt(path)


def trainer_state_step(path: str | os.PathLike[str]) -> int | None:
    """The step a trainer-state file was written at, from its header alone: the cheap check that
    the file is complete (a checkpoint folder's completeness, :mod:`phigenesis.train.runner`).
    None for an older run's ``trainer.pt``, whose step sits inside its pickled data (only its zip
    directory is checked). Raises :class:`CheckpointError` for a truncated or foreign file."""
    path = Path(path)
    if path.suffix != ".safetensors":
        _check_zip_directory(path)
        return None
    metadata = read_safetensors_metadata(path)
    header = decode_header(path, {k: v for k, v in metadata.items() if k in ("format", "step")})
    step = header.get("step")
    if header.get("format") != TRAINER_FORMAT or type(step) is not int:
        raise CheckpointError(f"{path}: not a phigenesis trainer state")
    return step


def _check_zip_directory(path: Path) -> None:
    """Raises unless ``path`` is a zip archive (``torch.save``'s container) whose directory reads."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError) as e:
        raise CheckpointError(f"{path}: truncated, damaged or not a PyTorch file ({e})") from e
    if not any(name.endswith("data.pkl") for name in names):
        raise CheckpointError(f"{path}: not a PyTorch file (no data.pkl in the archive)")


def _check_fits(optimizer: torch.optim.Optimizer, trainer: TrainingState) -> None:
    """Raises unless ``trainer``'s optimiser state fits ``optimizer``'s parameters: as many groups
    and parameters, every parameter's state complete (for the optimisers of
    :data:`REQUIRED_STATE`) and every non-scalar state tensor of its parameter's shape."""
    path, saved = trainer.path, trainer.optimizer
    unfit = f"{path}: the optimiser state does not fit the model"
    live_groups, saved_groups = optimizer.param_groups, saved["param_groups"]
    if len(live_groups) != len(saved_groups):
        raise CheckpointError(
            f"{unfit} ({len(saved_groups)} parameter groups, the optimiser has {len(live_groups)})"
        )
    for g, (live, kept) in enumerate(zip(live_groups, saved_groups, strict=True)):
        if len(live["params"]) != len(kept["params"]):
            raise CheckpointError(
                f"{unfit} (group {g} holds {len(kept['params'])} parameters, the optimiser's "
                f"{len(live['params'])})"
            )
        required = set(REQUIRED_STATE.get(type(optimizer).__name__, ()))
        if required and kept.get("amsgrad"):
            required.add("max_exp_avg_sq")
        for param, index in zip(live["params"], kept["params"], strict=True):
            entries = saved["state"].get(index)
            if entries is None:  # a parameter that never had a gradient has no state
                continue
            missing = sorted(required - set(entries))
            if missing:
                raise CheckpointError(f"{unfit} (parameter {index} lacks {', '.join(missing)})")
            for name, value in entries.items():
                if isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape != param.shape:
                    raise CheckpointError(
                        f"{unfit} ({name} of parameter {index} has shape {tuple(value.shape)}, the "
                        f"parameter {tuple(param.shape)})"
                    )


def _as_live(live: dict[str, Any], saved: dict[str, Any]) -> dict[str, Any]:
    """A saved parameter group with the live group's tuples (JSON gives lists) and with any
    hyperparameter it lacks taken from the live group."""
    group = {k: v for k, v in live.items() if k != "params"}
    for key, value in saved.items():
        group[key] = tuple(value) if isinstance(live.get(key), tuple) and isinstance(value, list) else value
    return group


def restore_optimizer(optimizer: torch.optim.Optimizer, trainer: TrainingState) -> None:
    """Loads ``trainer``'s optimiser state into ``optimizer`` (built for the same model), after
    checking it fits: state of other parameters or of other shapes raises
    :class:`CheckpointError` naming the file, instead of failing at the next step."""
    _check_fits(optimizer, trainer)
    saved = trainer.optimizer
    groups = [
        _as_live(live, kept) for live, kept in zip(optimizer.param_groups, saved["param_groups"], strict=True)
    ]
    try:
        optimizer.load_state_dict({"state": saved["state"], "param_groups": groups})
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(
            f"{trainer.path}: the optimiser state does not fit the model ({one_line(e)})"
        ) from e
