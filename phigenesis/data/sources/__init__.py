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


def make_source(name: str, params: dict[str, Any]) -> Source:
    """The source called ``name`` configured with ``params`` (its ``arguments()`` round-trip)."""
    if name == "synthetic":
        from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticSource

        return SyntheticSource(SyntheticConfig.from_dict(params))
    if name == "waymo":
        from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource

        return WaymoSource(WaymoConfig.from_dict(params))
    if name == "nuscenes":
        from phigenesis.data.sources.nuscenes import NuScenesConfig, NuScenesSource

        return NuScenesSource(NuScenesConfig.from_dict(params))
    raise ValueError(f"unknown source {name!r}; available: {', '.join(SOURCE_NAMES)}")
