"""Reading ``torch.save`` files without unpickling code: every ``.pt`` file the toolkit reads
(checkpoints, an older run's trainer state, Hugging Face ``.bin`` weights) goes through
:func:`read_torch_file`, which loads with ``weights_only=True`` and turns torch's long refusal
into one line naming the file (without its advice to load with ``weights_only=False``, which
would run the file's code).

It sits below models and trainers alike, so both read files the same way.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import torch

from phigenesis.errors import CheckpointError

#: Lines of torch's ``weights_only`` message that advise the reader, not describe the file.
_TORCH_ADVICE = (
    "Weights only load failed",
    "Re-running `torch.load`",
    "Check the documentation",
    "Please use",
)


def _torch_error_reason(error: Exception) -> str:
    """What a failed ``torch.load(weights_only=True)`` found wrong with its file, in one line,
    without torch's advice on ``weights_only`` (which does not apply: the file is the problem)."""
    text = str(error)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    facts = [line for line in lines if not line.startswith(_TORCH_ADVICE)]
    first = facts[0] if facts else type(error).__name__
    for cut in (". Please use", ". This is an internal", ". Check the documentation"):
        first = first.split(cut, 1)[0]
    return first.rstrip(".")


#: How torch names the object a refused file asks for ("GLOBAL posix.system"), across its versions.
_ASKED_GLOBAL = re.compile(r"(?:GLOBAL|Unsupported global:)\s+([\w.]+)")


def read_torch_file(path: str | os.PathLike[str], map_location: str = "cpu") -> Any:
    """The contents of a ``torch.save`` file, read with ``weights_only=True``: tensors, numbers,
    strings and containers only. A file that asks for any other object (code, a class) is refused
    without running anything; an unreadable one is a :class:`CheckpointError` naming it."""
    path = Path(path)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except OSError as e:
        raise CheckpointError(f"{path}: cannot be read ({e.strerror or e})") from e
    except Exception as e:  # any unpickling failure means "not a usable file"
        reason = _torch_error_reason(e)
        asked = _ASKED_GLOBAL.search(str(e))
        if asked is not None:
            raise CheckpointError(
                f"{path}: refused: the file asks for {asked.group(1)!r} (code or a class, which no "
                "checkpoint holds); nothing in it was run"
            ) from e
        raise CheckpointError(
            f"{path}: not a readable checkpoint (truncated, damaged or not a PyTorch file: {reason})"
        ) from e
