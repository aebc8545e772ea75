"""The Waymo Open Dataset source: v1 TFRecord files and v2 Parquet roots, without TensorFlow.

Entry point: :class:`WaymoSource` over a :class:`WaymoConfig`. ``input`` is a TFRecord file, a
folder of them (searched recursively), or a v2 dataset root (``{component}/{segment}.parquet``);
the format is detected. ``split`` picks a subfolder (``training``, ``validation``, ...) and
``segments`` filters segments by name (exact names or shell patterns).

A scene is a segment (its context name); frames are read and converted lazily, one at a time
(:mod:`.v1` / :mod:`.v2` read into :mod:`.raw` records, :mod:`.convert` builds the scene model).

Invalid input: every error names the file, the record (v1: record number and byte offset; v2: the
component file and frame timestamp) and the field. Frame-level fields (time and pose) are read for
the whole segment first, from an index that parses no more than them (v1: each record's top-level
fields; v2: the vehicle_pose component), so that a non-rigid pose or frame times that do not
strictly increase are found before any frame is converted. ``on_error="raise"`` stops the segment
at the first invalid record; ``"skip"`` leaves out the smallest part that keeps the rest correct
(that frame, camera image, LiDAR or box), logs why and counts it in ``Scene.dropped``. A file that
cannot be read as a whole (truncated, a corrupt record header or CRC, an unreadable Parquet file
or column) still fails its segment.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np

from phigenesis.data.ego_body import WAYMO_PACIFICA_BOXES
from phigenesis.data.records import (
    INT64_MAX,
    DroppedValues,
    Frame,
    InvalidRecord,
    LazyFrames,
    Scene,
    check_frame_times,
    increasing_frames,
)
from phigenesis.data.sources import given
from phigenesis.data.sources.waymo import convert
from phigenesis.data.sources.waymo.raw import (
    FRAMES_LEFT_OUT,
    FrameKey,
    OnError,
    Problems,
    RawFrame,
    WaymoFormatError,
)
from phigenesis.options import ConfigError, check_options, from_mapping, option

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
        on_error: "raise" stops a segment at its first invalid record; "skip" leaves out the
            invalid frame, camera image, LiDAR or box and counts it (``Scene.dropped``).
    """

    input: str = option()
    split: str | None = option(None)
    segments: tuple[str, ...] = option(())
    format: WaymoFormat = option("auto")
    check_crc: bool = option(True)
    on_error: OnError = option("raise")

    def __post_init__(self) -> None:
        check_options(self, "WaymoConfig")
        if not self.input:
            raise ConfigError("WaymoConfig: the waymo source needs an input path (--input)")

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "waymo source parameters") -> WaymoConfig:
        """The config from plain values (None: the default); a missing input, an unknown key or a
        value outside its type is a :class:`~phigenesis.options.ConfigError` naming ``where``."""
        return from_mapping(cls, {"input": "", **given(values)}, where)

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
        # each format's reader (TFRecord protobufs, Parquet) loads only for that format
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
            # each format's reader (TFRecord protobufs, Parquet) loads only for that format
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
        problems = Problems(self.config.on_error)
        dropped = DroppedValues()
        if self.format == "v2":
            # each format's reader (TFRecord protobufs, Parquet) loads only for that format
            from phigenesis.data.sources.waymo import v2

            segment = v2.V2Segment(self.root, scene_id)
            frames = _Frames.index(segment.frame_keys(), segment.frame, problems, dropped)
            return _scene(scene_id, frames, {"format": "v2", "path": str(self.root)}, problems, dropped)
        # each format's reader (TFRecord protobufs, Parquet) loads only for that format
        from phigenesis.data.sources.waymo.v1 import V1File

        path = self._v1_files[scene_id]
        file = V1File(path, check_crc=self.config.check_crc)
        if file.error is not None:
            raise WaymoFormatError(file.error)
        if not len(file):
            raise WaymoFormatError(f"{path}: the file holds no records")
        keys = [(file.where(k), key) for k, key in enumerate(file.keys())]
        frames = _Frames.index(keys, file.frame, problems, dropped)
        return _scene(scene_id, frames, {"format": "v1", "path": str(path)}, problems, dropped)


#: One entry of a segment's index: where the record is, and its frame key or why it is unusable.
_IndexEntry = tuple[str, FrameKey | WaymoFormatError]
#: Reads a segment's record by its number.
_ReadRecord = Callable[[int], RawFrame]


class _Frames:
    """The records of a segment that become its frames, with their Waymo timestamps."""

    def __init__(self, read: _ReadRecord, records: list[int], timestamps: list[int]):
        self._read = read
        self.records = records
        self.timestamps = timestamps

    def __len__(self) -> int:
        return len(self.records)

    def frame(self, index: int) -> RawFrame:
        return self._read(self.records[index])

    @classmethod
    def index(
        cls, entries: list[_IndexEntry], read: _ReadRecord, problems: Problems, dropped: DroppedValues
    ) -> _Frames:
        """The usable records of ``entries`` ((where, FrameKey or WaymoFormatError) per record,
        read by ``read(record)``): a record with an invalid pose, or a time that breaks the strict
        order, raises, or under ``skip`` is left out (``FRAMES_LEFT_OUT``, keyed by record)."""
        usable = []
        for k, (where, key) in enumerate(entries):
            if isinstance(key, WaymoFormatError):
                _leave_out(problems, dropped, k, key)
            elif key.timestamp_micros > INT64_MAX - convert.POSE_TIME_OFFSET_MICROS:
                _leave_out(
                    problems,
                    dropped,
                    k,
                    WaymoFormatError(f"{where}: timestamp_micros {key.timestamp_micros} is beyond int64"),
                )
            else:
                usable.append(k)
        keys: dict[int, FrameKey] = {k: entries[k][1] for k in usable}  # type: ignore[misc]
        times = [keys[k].timestamp_micros for k in usable]
        if problems.skip:
            order = increasing_frames(times)
            for j in sorted(set(range(len(usable))) - set(order)):
                error = WaymoFormatError(
                    f"{entries[usable[j]][0]}: timestamp_micros {times[j]} is out of the strictly increasing "
                    "order of the segment's other frames (a repeated, earlier or negative time)"
                )
                _leave_out(problems, dropped, usable[j], error)
            usable = [usable[j] for j in order]
        else:
            try:
                check_frame_times(times)
            except InvalidRecord as e:
                where = entries[usable[e.index if e.index is not None else 0]][0]
                raise WaymoFormatError(f"{where}: {e}") from None
        return cls(read, usable, [keys[k].timestamp_micros for k in usable])

    def first(self, problems: Problems, dropped: DroppedValues) -> RawFrame | None:
        """The first frame's raw record (None if there is none); under ``skip``, records that
        cannot be parsed are left out until one can (the segment's length is not fixed yet)."""
        while self.records:
            try:
                return self.frame(0)
            except WaymoFormatError as e:
                _leave_out(problems, dropped, self.records[0], e)
                del self.records[0], self.timestamps[0]
        return None


def _leave_out(problems: Problems, dropped: DroppedValues, record: int, error: WaymoFormatError) -> None:
    """Raises ``error``, or under ``skip`` counts record ``record`` as a frame left out."""
    left_out: dict[str, int] = {}
    problems.report(error, FRAMES_LEFT_OUT, left_out)
    dropped.add(FRAMES_LEFT_OUT, record, left_out[FRAMES_LEFT_OUT])


def _scene(
    scene_id: str, frames: _Frames, metadata: dict[str, Any], problems: Problems, dropped: DroppedValues
) -> Scene:
    """A scene over the usable ``frames``; the first of them fixes the world origin and the rig."""
    first = frames.first(problems, dropped)
    if first is None:
        raise WaymoFormatError(f"{metadata['path']}: segment {scene_id} has no usable frames")
    origin = first.global_from_vehicle[:3, 3].copy()
    global_from_world = np.eye(4)
    global_from_world[:3, 3] = origin
    cache = {0: first}
    calibrations = convert.rig_calibrations(first, problems)
    rig = frozenset(c.name for c in calibrations)

    def load(index: int, images: bool = True) -> Frame:
        raw = cache.pop(index) if index in cache else frames.frame(index)
        converted = convert.frame(raw, index, origin, problems, dropped, rig, images)
        converted.scene_id = scene_id
        return converted

    return Scene(
        scene_id=scene_id,
        source=SOURCE_NAME,
        calibrations=calibrations,
        frames=LazyFrames(
            len(frames),
            load,
            lambda index: load(index, images=False),
            timestamps_micros=[t + convert.POSE_TIME_OFFSET_MICROS for t in frames.timestamps],
        ),
        metadata={
            **metadata,
            "context_name": first.segment,
            "global_from_world": global_from_world.reshape(-1).tolist(),
            "ego_boxes": WAYMO_PACIFICA_BOXES,
            **{k: v for k, v in first.stats.items() if v},
        },
        dropped=dropped,
    )


__all__ = ["WaymoConfig", "WaymoFormatError", "WaymoSource"]
