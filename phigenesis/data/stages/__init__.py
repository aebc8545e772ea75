"""Pipeline stages: plain functions ``stage(scene, params) -> scene`` with no I/O of their own.

A stage is registered under a name with :func:`register_stage` and referenced by that name in a
pipeline spec (``pipelines/*.yaml``). Stages that work frame by frame should wrap the scene's
frames lazily (``LazyFrames.map``) so a scene never sits in memory whole.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from phigenesis.data.records import Scene

Stage = Callable[[Scene, dict[str, Any]], Scene]
STAGES: dict[str, Stage] = {}


def register_stage(name: str) -> Callable[[Stage], Stage]:
    """Decorator registering a stage function under ``name``."""

    def wrap(fn: Stage) -> Stage:
        if name in STAGES and STAGES[name] is not fn:
            raise ValueError(f"a stage named {name!r} is already registered")
        STAGES[name] = fn
        return fn

    return wrap


def get_stage(name: str) -> Stage:
    if name not in STAGES:
        raise KeyError(f"unknown stage {name!r}; registered stages: {sorted(STAGES) or 'none'}")
    return STAGES[name]
