"""Trained models from their checkpoints: the Stage 1 model and the Stage 2 denoiser, each checked
to be of its family (:func:`phigenesis.models.checkpoint.load_checkpoint` reads and checks the file)."""

from __future__ import annotations

import os
from pathlib import Path

from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.dit import MultiViewDiT
from phigenesis.models.stage1 import Stage1Model


def load_stage1(path: str | os.PathLike[str]) -> Stage1Model:
    """A trained Stage 1 model from its checkpoint (a run's ``model.safetensors`` or a checkpoint
    folder); raises :class:`CheckpointError` for files that are not Stage 1 checkpoints."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.safetensors"
    model = load_checkpoint(path, kind="stage1").model
    assert isinstance(model, Stage1Model), type(model)  # every "stage1" variant is one
    return model


def load_stage2(path: str | os.PathLike[str]) -> MultiViewDiT:
    """A trained Stage 2 denoiser from its checkpoint; raises :class:`CheckpointError` for files that
    are not Stage 2 checkpoints (a Stage 1 checkpoint, a VAE)."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.safetensors"
    model = load_checkpoint(path, kind="dit").model
    assert isinstance(model, MultiViewDiT), type(model)  # every "dit" variant is one
    return model
