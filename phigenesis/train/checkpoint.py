"""Model checkpoints: the weights with the variant name and full config that made them.

A checkpoint is one file holding the weights, the registered variant name, the full config and
JSON-like facts (training options, metrics, classes). Two encodings, chosen by the file's suffix:

- ``*.safetensors`` (the default of the trainers): the state dict as safetensors tensors, with
  ``format``, ``version``, ``model``, ``config`` and ``meta`` as JSON strings in the header's
  metadata; it loads without unpickling anything and memory-maps;
- any other suffix (``*.pt``): one ``torch.save`` dict ``{"format", "version", "model", "config",
  "state_dict", "meta"}`` (read with ``weights_only=True``).

``config`` is the model's config as plain values, so a checkpoint rebuilds its model without the
code's current defaults. Files are written under a temporary name and renamed, so a killed run
never leaves half a file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file
from torch import nn

from phigenesis.errors import CheckpointError
from phigenesis.models import create_model

FORMAT = "phigenesis.checkpoint"
VERSION = 1


@dataclass
class Checkpoint:
    """A loaded checkpoint: the rebuilt model (eval mode) and what the file said about it."""

    model: nn.Module
    model_name: str
    config: dict[str, Any]
    meta: dict[str, Any]
    path: Path


def save_checkpoint(
    path: str | os.PathLike[str], model: nn.Module, meta: dict[str, Any] | None = None
) -> Path:
    """Writes ``model`` (a registered variant: it has ``name`` and ``config``) to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "model": model.name,
        "config": model.config.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "meta": dict(meta or {}),
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    if path.suffix == ".safetensors":
        header = {k: json.dumps(v) for k, v in payload.items() if k != "state_dict"}
        tensors = {k: v.contiguous() for k, v in payload["state_dict"].items()}
        save_file(tensors, tmp, metadata=header)
    else:
        torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def _read_safetensors(path: Path, map_location: str) -> dict[str, Any]:
    with safe_open(path, framework="pt") as f:
        header = f.metadata() or {}
    payload: dict[str, Any] = {k: json.loads(v) for k, v in header.items()}
    payload["state_dict"] = load_file(path, device=map_location)
    return payload


def load_checkpoint(
    path: str | os.PathLike[str], model_name: str | None = None, map_location: str = "cpu"
) -> Checkpoint:
    """Reads a checkpoint and rebuilds its model.

    ``model_name``: the variant the caller expects; a checkpoint of another variant, or of the
    same variant with another config than the registered one, raises :class:`CheckpointError`
    naming both and the fields that differ.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        if path.suffix == ".safetensors":
            payload = _read_safetensors(path, map_location)
        else:
            payload = torch.load(path, map_location=map_location, weights_only=True)
    except (SafetensorError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({e})") from e
    except Exception as e:  # any unpickling failure means "not a checkpoint"
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a phigenesis checkpoint")
    name, config = payload["model"], payload["config"]
    if model_name is not None:
        expected = create_model(model_name).config.to_dict()
        if name != model_name or config != expected:
            diff = sorted(k for k in set(config) | set(expected) if config.get(k) != expected.get(k))
            raise CheckpointError(
                f"{path}: checkpoint is of model {name!r}, not {model_name!r}"
                + (f" (config fields differ: {', '.join(diff)})" if diff else "")
            )
    try:
        model = create_model(name, **config)
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, RuntimeError) as e:
        raise CheckpointError(f"{path}: weights do not fit model {name!r}: {e}") from e
    return Checkpoint(model.eval(), name, config, dict(payload.get("meta") or {}), path)
