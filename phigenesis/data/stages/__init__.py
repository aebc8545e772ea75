"""Pipeline stages: plain functions ``stage(scene, params) -> scene`` with no I/O of their own.

A stage is registered under a name with :func:`register_stage` and referenced by that name in a
pipeline spec (``pipelines/*.yaml``). A stage declares its parameters as a dataclass of options
(:mod:`phigenesis.options`: every value's type and range), registered with it; the spec's mapping
for the stage is built into it when the spec loads (:func:`stage_params`), so a typo or a value
out of range fails before any scene is read, and the stage function gets the built parameters.
Stages that work frame by frame should wrap the scene's frames lazily (``LazyFrames.map``) so a
scene never sits in memory whole. What depends only on the scene or its calibrations (pixel rays,
the ego body's depth, a range-view layout) is not per-frame work: a stage declares it as its
per-scene ``setup`` (:func:`register_stage`), which the pipeline runs once per scene before the
stage (:func:`run_stage`), and keeps it in a shared table
(:mod:`phigenesis.data.camera_tables`) or in ``Scene.products``.
"""

from __future__ import annotations

import functools
import importlib
from collections import Counter
from collections.abc import Callable
from typing import Any

from phigenesis.data.records import Scene
from phigenesis.options import from_mapping

Stage = Callable[[Scene, Any], Scene]
#: A stage's per-scene setup: ``setup(scene, params)``, run once per scene before the stage.
Setup = Callable[[Scene, Any], None]
STAGES: dict[str, Stage] = {}
#: The per-scene setup of each registered stage that declares one.
STAGE_SETUPS: dict[str, Setup] = {}
#: How many times each stage's setup ran (in this process): once per scene and stage.
SETUP_RUNS: Counter[str] = Counter()
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
    "flow",
)


def register_stage(
    name: str, params: type | None = None, setup: Setup | None = None
) -> Callable[[Stage], Stage]:
    """Decorator registering a stage function under ``name``.

    ``setup`` is the stage's per-scene setup, ``setup(scene, params)`` with the built
    parameters: the work that depends only on the scene or its calibrations, which
    :func:`run_stage` runs once per scene before the stage (and counts in :data:`SETUP_RUNS`).

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
        if setup is not None:
            STAGE_SETUPS[name] = setup
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


def run_stage(name: str, scene: Scene, values: Any) -> Scene:
    """Runs the stage registered as ``name`` on ``scene``: its per-scene setup first (if it
    declares one), then the stage, with the parameters built from ``values``."""
    stage = get_stage(name)
    params = stage_params(name, values)
    setup = STAGE_SETUPS.get(name)
    if setup is not None:
        setup(scene, params)
        SETUP_RUNS[name] += 1
    return stage(scene, params)
