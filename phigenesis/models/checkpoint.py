"""Reading model checkpoints: a trained model's weights with the variant and config that made
them, rebuilt into the model (the writers, and the optimiser state a resumed run needs, are
:mod:`phigenesis.train.checkpoint`'s). Every reader here treats its file as untrusted input: nothing
is unpickled beyond plain tensors and containers, and a damaged file is a one-line
:class:`CheckpointError` naming the file and what is wrong.

**Model checkpoints** hold the weights, the registered variant name, the full config and JSON-like
facts (training options, metrics, classes). Two encodings, chosen by the file's suffix:

- ``*.safetensors`` (the default of the trainers): the state dict as safetensors tensors, with
  ``format``, ``version``, ``model``, ``config``, ``meta`` and ``checksum`` as JSON strings in
  the header's metadata; it loads without unpickling anything and memory-maps;
- any other suffix (``*.pt``): one ``torch.save`` dict ``{"format", "version", "model", "config",
  "state_dict", "meta", "checksum"}``, read with ``weights_only=True`` (plain tensors and containers only: a
  file that asks for any other object is refused, not run).

``config`` is the model's config as plain values, so a checkpoint rebuilds its model without the
code's current defaults.

``checksum`` (in both encodings, and in a trainer-state file) is ``"sha256:<64 hex digits>"``, the
SHA-256 of the state dict (:func:`tensor_checksum`): for each tensor in the order of its name, the
line ``["<name>", "<dtype>", [<shape>]]`` (JSON and a newline) followed by the tensor's bytes in C
order (little-endian, as safetensors stores them). A file whose tensors do not hash to it is refused
("checksum mismatch"); a file written before the field existed loads with one warning.

Loading is bounded by the file: the header's model name must be of the family the caller asks
for (``kind``: ``"vae"``, ``"stage1"``, ``"dit"``, ``"segformer"``), its config must pass the
model config's declared ranges (:mod:`phigenesis.options`), and the model is first built on
PyTorch's ``meta`` device (no memory) and its parameter names and shapes compared with the
file's tensors (read from the safetensors header, without reading them) before anything is
allocated. Non-finite weights (NaN or infinity) are refused on load (and, by the writers, on save).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file
from torch import nn

from phigenesis.errors import CheckpointError
from phigenesis.models import FAMILY_NAMES, create_model, list_models, model_family
from phigenesis.torch_files import read_torch_file

__all__ = [
    "Checkpoint",
    "CheckpointError",
    "load_checkpoint",
    "read_safetensors_metadata",
    "tensor_checksum",
]

FORMAT = "phigenesis.checkpoint"
VERSION = 1
#: The header field holding the checksum of a file's tensors (see the module docstring).
CHECKSUM = "checksum"

log = logging.getLogger(__name__)


@dataclass
class Checkpoint:
    """A loaded checkpoint: the rebuilt model (eval mode) and what the file said about it."""

    model: nn.Module
    model_name: str
    config: dict[str, Any]
    meta: dict[str, Any]
    path: Path


# --------------------------------------------------------------------------------------------
# Integrity: checksums and finite values


def tensor_checksum(tensors: Mapping[str, torch.Tensor]) -> str:
    """``"sha256:<hex>"`` of a state dict (see the module docstring): every tensor's name, dtype,
    shape and bytes, in the order of the names; the same for a dict and for what it reads back as."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        tensor = tensors[name].detach().cpu().contiguous()
        dtype = str(tensor.dtype).removeprefix("torch.")
        digest.update(json.dumps([name, dtype, list(tensor.shape)]).encode() + b"\n")
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy())
    return f"sha256:{digest.hexdigest()}"


def verify_checksum(path: Path, tensors: Mapping[str, torch.Tensor], recorded: Any) -> None:
    """Raises :class:`CheckpointError` unless ``tensors`` hash to the file's ``recorded`` checksum;
    a file without one (written before checksums) passes with a warning."""
    if recorded is None:
        log.warning(
            "%s: written without a checksum (by an older phigenesis); its tensors are not verified", path
        )
        return
    if not isinstance(recorded, str) or not recorded.startswith("sha256:"):
        raise CheckpointError(f"{path}: damaged header (checksum {str(recorded)[:80]!r} is not 'sha256:...')")
    if tensor_checksum(tensors) != recorded:
        raise CheckpointError(
            f"{path}: checksum mismatch: its tensors are not the ones that were written (the file is "
            "damaged); use another copy or an earlier checkpoint"
        )


def _non_finite(tensors: Mapping[str, torch.Tensor]) -> list[tuple[str, int, int]]:
    """(name, non-finite values, values) of every floating-point tensor holding NaN or infinity,
    in the order of the names."""
    found = []
    for name in sorted(tensors):
        tensor = tensors[name]
        if (tensor.is_floating_point() or tensor.is_complex()) and not bool(torch.isfinite(tensor).all()):
            found.append((name, int((~torch.isfinite(tensor)).sum()), tensor.numel()))
    return found


def _non_finite_text(found: list[tuple[str, int, int]]) -> str:
    """``found`` (:func:`_non_finite`) in words: the count, the first tensor and its share."""
    total = sum(bad for _, bad, _ in found)
    name, bad, size = found[0]
    where = f"{len(found)} tensors, the first" if len(found) > 1 else "tensor"
    return f"{total:,} non-finite values (NaN or infinity) in {where} {name!r} ({bad:,} of {size:,})"


def refuse_non_finite(path: Path, tensors: Mapping[str, torch.Tensor], what: str) -> None:
    """Raises :class:`CheckpointError` naming ``path`` when a tensor holds NaN or infinity."""
    found = _non_finite(tensors)
    if found:
        raise CheckpointError(f"{path}: {what} {_non_finite_text(found)}")


# --------------------------------------------------------------------------------------------
# Reading files safely


def read_safetensors_metadata(path: str | os.PathLike[str]) -> dict[str, str]:
    """The header metadata of a safetensors file, checking that the file is complete (its header
    parses and its data covers every tensor the header lists); tensors are not read."""
    return _read_safetensors_header(Path(path))[0]


def _read_safetensors_header(path: Path) -> tuple[dict[str, str], dict[str, tuple[int, ...]]]:
    """(metadata, tensor name -> shape) of a safetensors file, from its header alone (safetensors
    checks on opening that the file's data covers every tensor the header lists)."""
    try:
        with safe_open(path, framework="pt") as f:
            shapes = {name: tuple(f.get_slice(name).get_shape()) for name in f.keys()}  # noqa: SIM118
            return dict(f.metadata() or {}), shapes
    except SafetensorError as e:
        raise CheckpointError(f"{path}: truncated, damaged or not a safetensors file ({e})") from e
    except OSError as e:
        raise CheckpointError(f"{path}: cannot be read ({e.strerror or e})") from e


def decode_header(path: Path, metadata: dict[str, str]) -> dict[str, Any]:
    """The JSON values of a safetensors header written by this module."""
    try:
        return {k: json.loads(v) for k, v in metadata.items()}
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path}: damaged header (a metadata value is not JSON: {e})") from e


def read_tensors(path: Path, map_location: str) -> dict[str, torch.Tensor]:
    try:
        return load_file(path, device=map_location)
    except SafetensorError as e:
        raise CheckpointError(f"{path}: truncated, damaged or not a safetensors file ({e})") from e


def one_line(error: BaseException) -> str:
    """An error's message with its line breaks and runs of spaces folded into single spaces."""
    return " ".join(str(error).split())


# --------------------------------------------------------------------------------------------
# Model checkpoints


def _read_model_file(
    path: Path, map_location: str
) -> tuple[dict[str, Any], dict[str, tuple[int, ...]], dict[str, torch.Tensor] | None]:
    """(header fields, tensor name -> shape, the tensors or None when not read yet) of a model
    checkpoint: a safetensors file's tensors are left unread; a ``.pt`` file is read whole (with
    ``weights_only=True``), so its size bounds what it costs."""
    if path.suffix == ".safetensors":
        metadata, shapes = _read_safetensors_header(path)
        return decode_header(path, metadata), shapes, None
    payload = read_torch_file(path, map_location)
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: not a phigenesis checkpoint")
    tensors = payload.get("state_dict")
    if not isinstance(tensors, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in tensors.items()
    ):
        raise CheckpointError(f"{path}: damaged checkpoint (the state dict is not a mapping of tensors)")
    header = {k: v for k, v in payload.items() if k != "state_dict"}
    return header, {k: tuple(v.shape) for k, v in tensors.items()}, tensors


def _check_header(path: Path, header: dict[str, Any]) -> None:
    """Raises unless ``header`` has the fields of a model checkpoint, with the right types."""
    if header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a phigenesis checkpoint")
    if not isinstance(header.get("version"), int) or header["version"] > VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {header.get('version')!r}; this phigenesis reads "
            f"up to {VERSION}"
        )
    expected = {"model": str, "config": dict}
    for field, kind in expected.items():
        if not isinstance(header.get(field), kind):
            raise CheckpointError(
                f"{path}: damaged checkpoint ({field!r} is missing or not a {kind.__name__})"
            )
    if not isinstance(header.get("meta", {}), dict):
        raise CheckpointError(f"{path}: damaged checkpoint ('meta' is not a mapping)")


def _check_kind(path: Path, name: str, kind: str | None) -> None:
    """Raises unless ``name`` is a registered variant of the family ``kind`` (any family when
    None): "X: a stage2_tiny checkpoint (Stage 2 denoiser), not a VAE"."""
    family = model_family(name)
    if family is None:
        raise CheckpointError(
            f"{path}: a checkpoint of model {name[:80]!r}, which this phigenesis does not know "
            f"(known: {', '.join(list_models())})"
        )
    if kind is not None and family != kind:
        what = FAMILY_NAMES.get(family, family)
        wanted = FAMILY_NAMES.get(kind, kind)
        raise CheckpointError(f"{path}: a {name} checkpoint ({what}), not a {wanted}")


def _check_registered(path: Path, name: str, config: dict[str, Any], model_name: str) -> None:
    """Raises unless the checkpoint is of the variant ``model_name`` with its registered config."""
    expected = _registered_config(model_name)
    if name != model_name or config != expected:
        diff = sorted(k for k in set(config) | set(expected) if config.get(k) != expected.get(k))
        raise CheckpointError(
            f"{path}: checkpoint is of model {name!r}, not {model_name!r}"
            + (f" (config fields differ: {', '.join(diff)})" if diff else "")
        )


def _registered_config(name: str) -> dict[str, Any]:
    """The registered config of the variant ``name`` as plain values (built without memory)."""
    with torch.device("meta"):
        return create_model(name).config.to_dict()


def _rebuild(path: Path, name: str, config: dict[str, Any], device: str | None = None) -> nn.Module:
    """The model ``name`` with the checkpoint's ``config`` (on ``device``: ``"meta"`` allocates
    nothing); a config outside the declared ranges raises :class:`CheckpointError` naming the
    file and the field."""
    try:
        if device is None:
            return create_model(name, **config)
        with torch.device(device):
            return create_model(name, **config)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: cannot rebuild model {name!r} from its config ({one_line(e)})") from e


def _check_shapes(path: Path, name: str, skeleton: nn.Module, shapes: dict[str, tuple[int, ...]]) -> None:
    """Raises unless the file's tensors are exactly the parameters and buffers of ``skeleton``
    (the model built on the meta device), by name and shape."""
    wanted = {k: tuple(v.shape) for k, v in skeleton.state_dict().items()}
    missing = sorted(set(wanted) - set(shapes))
    extra = sorted(set(shapes) - set(wanted))
    unfit = f"{path}: weights do not fit model {name!r} of its config"
    if missing or extra:
        parts = [
            f"missing {_names(missing)}" if missing else "",
            f"unexpected {_names(extra)}" if extra else "",
        ]
        raise CheckpointError(f"{unfit} ({'; '.join(p for p in parts if p)})")
    for key in sorted(wanted):
        if wanted[key] != shapes[key]:
            raise CheckpointError(
                f"{unfit} ({key!r} has shape {list(shapes[key])} in the file, the model {list(wanted[key])})"
            )


def _names(keys: list[str], most: int = 3) -> str:
    """Up to ``most`` tensor names and how many more."""
    shown = ", ".join(repr(k[:80]) for k in keys[:most])
    return shown + (f" and {len(keys) - most} more" if len(keys) > most else "")


def load_checkpoint(
    path: str | os.PathLike[str],
    model_name: str | None = None,
    map_location: str = "cpu",
    *,
    kind: str | None = None,
) -> Checkpoint:
    """Reads a checkpoint and rebuilds its model.

    ``kind``: the model family the caller needs (``"vae"``, ``"stage1"``, ``"dit"``,
    ``"segformer"``; :func:`phigenesis.models.list_models`); a checkpoint of another family raises
    :class:`CheckpointError` ("X: a stage2_tiny checkpoint (Stage 2 denoiser), not a VAE").
    ``model_name``: the variant the caller expects (its family is then the kind); a checkpoint of
    another variant, or of the same variant with another config than the registered one, raises
    :class:`CheckpointError` naming both and the fields that differ.

    A missing, truncated or damaged file, one that is not a phigenesis checkpoint, a config
    outside the model's declared ranges, tensors that do not fit the model (checked before the
    model is allocated), a checksum mismatch and non-finite weights all raise
    :class:`CheckpointError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    header, shapes, tensors = _read_model_file(path, map_location)
    _check_header(path, header)
    name, config = header["model"], header["config"]
    if model_name is not None:
        kind = model_family(model_name)
        if kind is None:
            raise ValueError(f"unknown model {model_name!r}; registered models: {', '.join(list_models())}")
    _check_kind(path, name, kind)
    if model_name is not None:
        _check_registered(path, name, config, model_name)
    _check_shapes(path, name, _rebuild(path, name, config, "meta"), shapes)
    if tensors is None:
        tensors = read_tensors(path, map_location)
    verify_checksum(path, tensors, header.get(CHECKSUM))
    refuse_non_finite(path, tensors, "not usable weights:")
    model = _rebuild(path, name, config)
    try:
        model.load_state_dict(tensors)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: weights do not fit model {name!r}: {one_line(e)}") from e
    return Checkpoint(model.eval(), name, config, dict(header.get("meta") or {}), path)
