"""Data sources: each turns a dataset (or the synthetic generator) into :class:`Scene` records.

A source has a ``name``, lists its ``scene_ids()``, builds a scene with ``load(scene_id)`` (frames
lazily), and reports ``arguments()``: the JSON-serialisable settings that determine its output
(recorded in the cache manifest and its fingerprint). Sources only read.
"""

from __future__ import annotations

from typing import Any, Protocol

from phigenesis.data.records import Scene


class Source(Protocol):
    name: str

    def scene_ids(self) -> list[str]: ...

    def load(self, scene_id: str) -> Scene: ...

    def arguments(self) -> dict[str, Any]: ...


SOURCE_NAMES = ("synthetic", "waymo", "nuscenes")


def source_config(name: str) -> type:
    """The config class of the source called ``name`` (a dataclass of options,
    :mod:`phigenesis.options`, with ``from_dict(values, where)``)."""
    if name == "synthetic":
        # each source's dependencies load only when that source is chosen
        from phigenesis.data.sources.synthetic import SyntheticConfig

        return SyntheticConfig
    if name == "waymo":
        # each source's dependencies load only when that source is chosen
        from phigenesis.data.sources.waymo import WaymoConfig

        return WaymoConfig
    if name == "nuscenes":
        # each source's dependencies load only when that source is chosen
        from phigenesis.data.sources.nuscenes import NuScenesConfig

        return NuScenesConfig
    raise ValueError(f"unknown source {name!r}; available: {', '.join(SOURCE_NAMES)}")


def given(values: dict[str, Any]) -> dict[str, Any]:
    """The source parameters of ``values`` that are given: a null (None) one takes its default."""
    return {k: v for k, v in values.items() if v is not None}


def make_source(name: str, params: dict[str, Any]) -> Source:
    """The source called ``name`` configured with ``params`` (its ``arguments()`` round-trip); an
    unknown key or a value outside its type or range is a
    :class:`~phigenesis.options.ConfigError` naming the source's parameters, the key and the value."""
    config = source_config(name).from_dict(params)
    if name == "synthetic":
        # each source's dependencies load only when that source is chosen
        from phigenesis.data.sources.synthetic import SyntheticSource

        return SyntheticSource(config)
    if name == "waymo":
        # each source's dependencies load only when that source is chosen
        from phigenesis.data.sources.waymo import WaymoSource

        return WaymoSource(config)
    # each source's dependencies load only when that source is chosen
    from phigenesis.data.sources.nuscenes import NuScenesSource

    return NuScenesSource(config)
