"""The Waymo Open Dataset source: v1 TFRecord files and v2 Parquet roots, without TensorFlow.

Entry point: :class:`WaymoSource` over a :class:`WaymoConfig`. ``input`` is a TFRecord file, a
folder of them (searched recursively), or a v2 dataset root (``{component}/{segment}.parquet``);
the format is detected. ``split`` picks a subfolder (``training``, ``validation``, ...) and
``segments`` filters segments by name (exact names or shell patterns).

A scene is a segment (its context name); frames are read and converted lazily, one at a time
(:mod:`.v1` / :mod:`.v2` read into :mod:`.raw` records, :mod:`.convert` builds the scene model).
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np

from phigenesis.data.records import LazyFrames, Scene
from phigenesis.data.sources.waymo import convert
from phigenesis.data.sources.waymo.raw import RawFrame, WaymoFormatError

SOURCE_NAME = "waymo"
WaymoFormat = Literal["auto", "v1", "v2"]
_V1_STEM = re.compile(r"^segment-(?P<name>.+?)(_with_camera_labels)?$")


@dataclass(frozen=True)
class WaymoConfig:
    """What to convert.

    Attributes:
        input: a v1 ``.tfrecord`` file, a folder of them, or a v2 root.
        split: optional subfolder of ``input`` (``training``, ``validation``, ``testing``).
        segments: segment names or shell patterns to keep (empty: all).
        format: "auto" (detect), "v1" or "v2".
        check_crc: check both CRCs of every v1 record (a corrupt record is an error).
    """

    input: str
    split: str | None = None
    segments: tuple[str, ...] = ()
    format: WaymoFormat = "auto"
    check_crc: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "segments", tuple(self.segments or ()))
        if self.format not in ("auto", "v1", "v2"):
            raise ValueError(f"format must be auto, v1 or v2, got {self.format!r}")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> WaymoConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown waymo source parameters {unknown}; known: {sorted(known)}")
        if not values.get("input"):
            raise ValueError("the waymo source needs an input path (--input)")
        return cls(**{k: v for k, v in values.items() if v is not None})

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["segments"] = list(self.segments)
        return d


def _segment_of_file(path: Path) -> str:
    m = _V1_STEM.match(path.stem)
    return m.group("name") if m else path.stem


class WaymoSource:
    """The segments under a Waymo input, each loaded as a :class:`Scene` with lazy frames."""

    name = SOURCE_NAME

    def __init__(self, config: WaymoConfig):
        self.config = config

    @cached_property
    def root(self) -> Path:
        root = Path(self.config.input).expanduser()
        if self.config.split:
            root = root / self.config.split
        if not root.exists():
            raise WaymoFormatError(f"{root}: no such file or directory")
        return root

    @cached_property
    def format(self) -> str:
        if self.config.format != "auto":
            return self.config.format
        from phigenesis.data.sources.waymo import v2

        return "v2" if self.root.is_dir() and v2.is_v2_root(self.root) else "v1"

    @cached_property
    def _v1_files(self) -> dict[str, Path]:
        root = self.root
        files = [root] if root.is_file() else sorted(root.rglob("*.tfrecord"))
        if not files:
            raise WaymoFormatError(
                f"{root}: no .tfrecord files, and not a v2 root (no vehicle_pose/ component folder)"
            )
        by_segment: dict[str, Path] = {}
        for f in files:
            seg = _segment_of_file(f)
            if seg in by_segment:
                raise WaymoFormatError(f"segment {seg} is in two files: {by_segment[seg]} and {f}")
            by_segment[seg] = f
        return by_segment

    @cached_property
    def _all_segments(self) -> list[str]:
        if self.format == "v2":
            from phigenesis.data.sources.waymo import v2

            return v2.list_segments(self.root)
        return sorted(self._v1_files)

    def scene_ids(self) -> list[str]:
        pats = self.config.segments
        ids = [s for s in self._all_segments if not pats or any(fnmatch.fnmatchcase(s, p) for p in pats)]
        if not ids:
            raise WaymoFormatError(
                f"{self.root}: no segment matches {list(pats)}" if pats else f"{self.root}: no segments"
            )
        return ids

    def arguments(self) -> dict[str, Any]:
        return self.config.to_dict()

    def load(self, scene_id: str) -> Scene:
        if scene_id not in self._all_segments:
            raise KeyError(f"{self.root} has no Waymo segment {scene_id!r}")
        if self.format == "v2":
            from phigenesis.data.sources.waymo import v2

            segment = v2.V2Segment(self.root, scene_id)
            return _scene(scene_id, len(segment), segment.frame, {"format": "v2", "path": str(self.root)})
        from phigenesis.data.sources.waymo.v1 import V1File

        path = self._v1_files[scene_id]
        file = V1File(path, check_crc=self.config.check_crc)
        if file.error is not None:
            raise WaymoFormatError(file.error)
        if not len(file):
            raise WaymoFormatError(f"{path}: the file holds no records")
        return _scene(scene_id, len(file), file.frame, {"format": "v1", "path": str(path)})


def _scene(scene_id: str, count: int, read: Any, metadata: dict[str, Any]) -> Scene:
    """A scene over ``count`` raw frames given by ``read(index)``; frame 0 fixes the world origin."""
    first: RawFrame = read(0)
    origin = first.global_from_vehicle[:3, 3].copy()
    global_from_world = np.eye(4)
    global_from_world[:3, 3] = origin
    cache = {0: first}

    def load(index: int) -> Any:
        raw = cache.pop(index) if index in cache else read(index)
        converted = convert.frame(raw, index, origin)
        converted.scene_id = scene_id
        return converted

    try:
        calibrations = convert.rig_calibrations(first)
    except WaymoFormatError as e:
        raise WaymoFormatError(f"{first.where}: {e}") from None
    return Scene(
        scene_id=scene_id,
        source=SOURCE_NAME,
        calibrations=calibrations,
        frames=LazyFrames(count, load),
        metadata={
            **metadata,
            "context_name": first.segment,
            "global_from_world": global_from_world.reshape(-1).tolist(),
            **{k: v for k, v in first.stats.items() if v},
        },
    )


__all__ = ["WaymoConfig", "WaymoFormatError", "WaymoSource"]
