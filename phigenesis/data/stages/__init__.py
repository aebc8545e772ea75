"""Pipeline stages: plain functions ``stage(scene, params) -> scene`` with no I/O of their own.

A stage is registered under a name with :func:`register_stage` and referenced by that name in a
pipeline spec (``pipelines/*.yaml``). A stage declares its parameters as a dataclass of options
(:mod:`phigenesis.options`: every value's type and range), registered with it; the spec's mapping
for the stage is built into it when the spec loads (:func:`stage_params`), so a typo or a value
out of range fails before any scene is read, and the stage function gets the built parameters.
Stages that work frame by frame should wrap the scene's frames lazily (``LazyFrames.map``) so a
scene never sits in memory whole.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import Any

from phigenesis.data.records import Scene
from phigenesis.options import from_mapping

Stage = Callable[[Scene, Any], Scene]
STAGES: dict[str, Stage] = {}
#: The parameter class of each registered stage (None: the stage takes its spec mapping as is).
STAGE_PARAMS: dict[str, type | None] = {}
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


def register_stage(name: str, params: type | None = None) -> Callable[[Stage], Stage]:
    """Decorator registering a stage function under ``name``.

    ``params`` is the dataclass of the stage's parameters, declared with
    :func:`phigenesis.options.option`; the registered stage then takes either an instance of it
    or a mapping of its options (a spec's, built with :func:`stage_params`), and the function
    gets the instance. Without ``params`` the function gets whatever mapping it is given.
    """

    def wrap(fn: Stage) -> Stage:
        registered = STAGES.get(name)
        if registered is not None and getattr(registered, "__wrapped__", registered) is not fn:
            raise ValueError(f"a stage named {name!r} is already registered")
        stage = fn
        if params is not None:

            @functools.wraps(fn)
            def stage(scene: Scene, values: Any) -> Scene:
                return fn(scene, _built(params, values, f"stage {name}"))

        STAGES[name] = stage
        STAGE_PARAMS[name] = params
        return stage

    return wrap


def stage_params(name: str, values: Any, where: str | None = None) -> Any:
    """The parameters of the stage registered as ``name`` from ``values``: an instance of its
    parameter class as is, a mapping (None: empty) built with
    :func:`~phigenesis.options.from_mapping`, or, for a stage registered without a class, the
    mapping itself. Raises :class:`~phigenesis.options.ConfigError` naming ``where`` (default:
    the stage), the key, the value and what it allows."""
    get_stage(name)
    return _built(STAGE_PARAMS[name], values, where or f"stage {name}")


def _built(cls: type | None, values: Any, where: str) -> Any:
    if cls is None:
        return {} if values is None else values
    if isinstance(values, cls):
        return values
    return from_mapping(cls, values, where)


def get_stage(name: str) -> Stage:
    """The stage registered as ``name`` (built-in stages included)."""
    for module in BUILTIN_STAGE_MODULES:
        importlib.import_module(f"{__name__}.{module}")
    if name not in STAGES:
        raise KeyError(f"unknown stage {name!r}; registered stages: {sorted(STAGES) or 'none'}")
    return STAGES[name]
