"""Checks of the model a training config names: a registered variant of the right family, with
``model_overrides`` it takes (within the declared ranges of its config). Each raises
:class:`~phigenesis.options.ConfigError` naming the config."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from phigenesis.models import create_model, list_models
from phigenesis.options import ConfigError


def check_model_name(name: str, family: str, label: str) -> None:
    """Raises :class:`~phigenesis.options.ConfigError` unless ``name`` is a registered model of
    ``family`` (``"stage1"``, ``"dit"``, ``"vae"``, ``"segformer"``), naming the known ones."""
    known = list_models(family)
    if name not in known:
        raise ConfigError(f"{label}: model = {name!r}: must be one of {known}")


def create_overridden(name: str, overrides: dict[str, Any], label: str) -> nn.Module:
    """The registered model ``name`` with its config fields replaced by ``overrides`` (a training
    config's ``model_overrides``); an unknown field or a value outside its range raises
    :class:`~phigenesis.options.ConfigError` naming ``label``."""
    try:
        return create_model(name, **overrides)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{label}: model_overrides {overrides}: {' '.join(str(e).split())}") from None


def check_model_overrides(name: str, overrides: dict[str, Any], label: str) -> None:
    """Raises :class:`~phigenesis.options.ConfigError` naming ``label`` unless the registered model
    ``name`` takes ``overrides`` (every field known, every value within its declared range); the
    model is built on PyTorch's ``meta`` device, so the check allocates no weights."""
    if overrides:
        with torch.device("meta"):
            create_overridden(name, overrides, label)
