"""Pipeline stages: plain functions ``stage(scene, params) -> scene`` with no I/O of their own.

A stage is registered under a name with :func:`register_stage` and referenced by that name in a
pipeline spec (``pipelines/*.yaml``). Stages that work frame by frame should wrap the scene's
frames lazily (``LazyFrames.map``) so a scene never sits in memory whole.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any, TypeVar

from phigenesis.data.records import Scene

Stage = Callable[[Scene, dict[str, Any]], Scene]
P = TypeVar("P")
STAGES: dict[str, Stage] = {}
#: Modules of the built-in stages, imported (and so registered) on the first lookup.
BUILTIN_STAGE_MODULES = (
    "aggregate",
    "project",
    "densify",
    "complete",
    "interpolate",
    "semantics",
    "rangeview",
)


def register_stage(name: str) -> Callable[[Stage], Stage]:
    """Decorator registering a stage function under ``name``."""

    def wrap(fn: Stage) -> Stage:
        if name in STAGES and STAGES[name] is not fn:
            raise ValueError(f"a stage named {name!r} is already registered")
        STAGES[name] = fn
        return fn

    return wrap


def params_from_dict(cls: type[P], values: dict[str, Any], stage: str) -> P:
    """A stage's parameter dataclass from a pipeline spec's mapping; unknown keys are an error
    naming the stage and the known ones."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"{stage}: unknown parameters {unknown}; known: {sorted(known)}")
    return cls(**values)


def get_stage(name: str) -> Stage:
    """The stage registered as ``name`` (built-in stages included)."""
    for module in BUILTIN_STAGE_MODULES:
        importlib.import_module(f"{__name__}.{module}")
    if name not in STAGES:
        raise KeyError(f"unknown stage {name!r}; registered stages: {sorted(STAGES) or 'none'}")
    return STAGES[name]
