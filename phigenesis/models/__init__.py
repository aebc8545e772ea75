"""Models, by registered name: ``create_model("segformer_tiny")``, ``list_models()``.

One model family per module; each registers its variants (a factory per named config) with
:func:`register_model`. Every model is an ``nn.Module`` with ``name`` (its registered variant),
``config`` (a frozen dataclass with ``to_dict``), ``forward`` and ``predict``.

Beside the networks: reading their checkpoints (:mod:`.checkpoint`) and loading trained ones
(:mod:`.loading`), and the math on their outputs that training, generation and evaluation share
(rendering views, flow matching, Stereo Forcing, uncertainty maps, the Gaussian buffer, metrics).
This package imports nothing of the toolkit but its core (docs/design/layers.md).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from torch import nn

ModelFactory = Callable[..., nn.Module]
MODELS: dict[str, ModelFactory] = {}
#: Modules of the built-in model families, imported (and so registered) on the first lookup.
BUILTIN_MODEL_MODULES = ("segformer", "vae", "stage1", "dit")
#: What each built-in family is, in the words of an error message ("not a VAE").
FAMILY_NAMES = {
    "segformer": "segmenter",
    "vae": "VAE",
    "stage1": "Stage 1 model",
    "dit": "Stage 2 denoiser",
}


def register_model(fn: ModelFactory) -> ModelFactory:
    """Decorator registering a variant factory under its function name."""
    name = fn.__name__
    if name in MODELS and MODELS[name] is not fn:
        raise ValueError(f"a model named {name!r} is already registered")
    MODELS[name] = fn
    return fn


def _load_builtins() -> None:
    for module in BUILTIN_MODEL_MODULES:
        importlib.import_module(f"{__name__}.{module}")


def list_models(family: str | None = None) -> list[str]:
    """Names of the registered variants, sorted; with ``family``, only those of that module
    (``"segformer"``, ``"vae"``)."""
    _load_builtins()
    if family is None:
        return sorted(MODELS)
    return sorted(n for n, fn in MODELS.items() if fn.__module__ == f"{__name__}.{family}")


def model_family(name: str) -> str | None:
    """The family (module name: ``"vae"``, ``"stage1"``, ``"dit"``, ``"segformer"``) of the
    registered variant ``name``; None for a name no module registered."""
    _load_builtins()
    fn = MODELS.get(name)
    return None if fn is None else fn.__module__.rsplit(".", 1)[-1]


def create_model(name: str, **overrides: Any) -> nn.Module:
    """The variant ``name``, freshly initialised, with config fields replaced by ``overrides``."""
    _load_builtins()
    if name not in MODELS:
        raise KeyError(f"unknown model {name!r}; registered models: {sorted(MODELS)}")
    return MODELS[name](**overrides)
