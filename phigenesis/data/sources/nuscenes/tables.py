"""nuScenes' 13 JSON tables, loaded and indexed without the devkit, every field read typed.

A nuScenes version (``v1.0-mini``, ``v1.0-trainval``) is a folder ``<dataroot>/<version>/`` holding
one JSON list per table; every record has a ``token`` (its primary key) and refers to others by
``*_token`` fields (``""`` = no link). :class:`NuScenesTables` loads them all and indexes them by
token. Every field is read through :meth:`NuScenesTables.field`, which checks it against its
:data:`FieldKind` (a string that must be a bool, a list that must be a number, a missing field, a
wrong length, NaN/Inf, an absurd timestamp) once, where it is read; links are resolved with
:meth:`NuScenesTables.follow`. Every error is a :class:`NuScenesError` whose message starts with
the table's JSON file and names the record (table + token) and the field.

Records that cannot be indexed at all (no token, a duplicate token, a malformed link to their
sample) are collected in :attr:`NuScenesTables.load_problems` rather than raised, so the source's
error policy decides: ``raise`` stops at the first, ``skip`` leaves those records out.

Reverse indexes (what the devkit adds on load): sample_data and sample_annotation by sample
token. :meth:`NuScenesTables.timeline` gives a scene's samples and which of them are in time order.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis.data import records
from phigenesis.errors import SourceError

#: The tables of a nuScenes version, all required.
TABLE_NAMES: tuple[str, ...] = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)

Record = dict[str, Any]

#: What a field must hold (see :meth:`NuScenesTables.field`):
#: ``text`` a string; ``token`` a string (``""`` = no link); ``tokens`` a list of strings;
#: ``bool`` JSON true/false; ``timestamp`` integer Unix microseconds in [0, MAX_TIMESTAMP_MICROS];
#: ``pixels`` an integer image size in [1, MAX_PIXELS]; ``count`` an integer in [-1, 2^31 - 1]
#: (-1 = unknown); ``position`` 3 finite numbers (metres, each |x| <= MAX_POSITION_M); ``mount``
#: a sensor's position on the vehicle, 3 finite numbers (metres, each |x| <= MAX_MOUNT_M);
#: ``size`` 3 finite numbers in (0, MAX_BOX_SIZE_M] (metres); ``quaternion`` 4 finite numbers
#: (w, x, y, z) of norm within QUATERNION_NORM_TOLERANCE of 1, returned normalised;
#: ``intrinsics`` a 3x3 pinhole matrix (positive focal lengths, last row 0 0 1, pixels).
FieldKind = Literal[
    "text",
    "token",
    "tokens",
    "bool",
    "timestamp",
    "pixels",
    "count",
    "position",
    "mount",
    "size",
    "quaternion",
    "intrinsics",
]
#: Latest accepted timestamp: 2100-01-01 in Unix microseconds (1e18 is not a capture time).
MAX_TIMESTAMP_MICROS = 4_102_444_800_000_000
#: Largest accepted |coordinate| of a position, metres (any map is far smaller): half the scene
#: model's limit, so that a position relative to the scene's origin stays within it.
MAX_POSITION_M = records.MAX_COORDINATE_M / 2
#: Largest accepted |coordinate| of a sensor's mount on the vehicle, metres (the scene model's
#: range for LiDAR points and ray origins in the ego frame).
MAX_MOUNT_M = records.MAX_POINT_DISTANCE_M
#: Largest accepted box dimension, metres (the scene model's).
MAX_BOX_SIZE_M = records.MAX_BOX_SIZE_M
#: Largest accepted image width or height, pixels (the scene model's).
MAX_PIXELS = records.MAX_IMAGE_SIDE
#: Largest accepted |entry| of a camera matrix, pixels (the scene model's).
MAX_INTRINSIC_PX = records.MAX_INTRINSIC_PX
#: How far a rotation quaternion's norm may be from 1 (nuScenes stores unit quaternions).
QUATERNION_NORM_TOLERANCE = 1e-2
#: Largest accepted count (stored as int32).
MAX_COUNT = 2**31 - 1


class NuScenesError(SourceError):
    """A nuScenes dataset is incomplete or inconsistent; the message names the file, the record
    (table + token) and the field."""


class _Invalid(Exception):
    """A value that does not have its field's kind; the message says what was expected."""


def _integer(value: Any, what: str) -> int:
    """``value`` as an int: a JSON integer, or a float with an integral value (Lyft writes those)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Invalid(f"must be {what}")
    if isinstance(value, float):
        if not math.isfinite(value) or not value.is_integer():
            raise _Invalid(f"must be {what}")
        return int(value)
    return value


def _finite(value: Any, limit: float) -> float:
    """``value`` as a finite float with ``|value| <= limit``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Invalid("must hold numbers only")
    try:
        x = float(value)
    except OverflowError:
        raise _Invalid(f"must hold numbers within +-{limit:g}") from None
    if not math.isfinite(x):
        raise _Invalid("must hold finite numbers (no NaN or Infinity)")
    if abs(x) > limit:
        raise _Invalid(f"must hold numbers within +-{limit:g}")
    return x


def _vector(value: Any, length: int, limit: float) -> NDArray[np.float64]:
    """A JSON list of ``length`` finite numbers as a float64 array."""
    if not isinstance(value, list) or len(value) != length:
        raise _Invalid(f"must be a list of {length} numbers")
    return np.array([_finite(x, limit) for x in value], np.float64)


def _text(value: Any) -> str:
    if not isinstance(value, str):
        raise _Invalid("must be a string")
    return value


def _token(value: Any) -> str:
    if not isinstance(value, str):
        raise _Invalid('must be a token string ("" for no link)')
    return value


def _tokens(value: Any) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(t, str) for t in value):
        raise _Invalid("must be a list of token strings")
    return list(value)


def _bool(value: Any) -> bool:
    if not isinstance(value, bool):
        raise _Invalid("must be true or false")
    return value


def _integer_in(value: Any, low: int, high: int, what: str) -> int:
    """``value`` as an int in ``[low, high]``; ``what`` describes the field for the error."""
    n = _integer(value, what)
    if not low <= n <= high:
        raise _Invalid(f"must be {what}")
    return n


def _timestamp(value: Any) -> int:
    what = f"an integer timestamp in microseconds in [0, {MAX_TIMESTAMP_MICROS}] (before 2100)"
    return _integer_in(value, 0, MAX_TIMESTAMP_MICROS, what)


def _pixels(value: Any) -> int:
    return _integer_in(value, 1, MAX_PIXELS, f"an integer number of pixels in [1, {MAX_PIXELS}]")


def _count(value: Any) -> int:
    return _integer_in(value, -1, MAX_COUNT, f"an integer count in [-1, {MAX_COUNT}] (-1 = unknown)")


def _position(value: Any) -> NDArray[np.float64]:
    return _vector(value, 3, MAX_POSITION_M)


def _mount(value: Any) -> NDArray[np.float64]:
    return _vector(value, 3, MAX_MOUNT_M)


def _size(value: Any) -> NDArray[np.float64]:
    size = _vector(value, 3, MAX_BOX_SIZE_M)
    if np.any(size <= 0):
        raise _Invalid("must be 3 positive sizes (width, length, height)")
    return size


def _quaternion(value: Any) -> NDArray[np.float64]:
    q = _vector(value, 4, math.inf)
    norm = math.hypot(*q)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise _Invalid(f"must be a unit quaternion (w, x, y, z); its norm is {norm:.6g}")
    return q / norm


def _intrinsics(value: Any) -> NDArray[np.float64]:
    if not isinstance(value, list) or len(value) != 3:
        raise _Invalid("must be a 3x3 camera matrix (a list of 3 rows of 3 numbers)")
    k = np.stack([_vector(row, 3, MAX_INTRINSIC_PX) for row in value])  # (3, 3)
    if not (k[0, 0] > 0 and k[1, 1] > 0 and k[1, 0] == 0 and np.array_equal(k[2], [0.0, 0.0, 1.0])):
        raise _Invalid(
            "must be a pinhole camera matrix: positive focal lengths, rows [fx s cx] [0 fy cy] [0 0 1]"
        )
    return k


_CHECKS: dict[str, Callable[[Any], Any]] = {
    "text": _text,
    "token": _token,
    "tokens": _tokens,
    "bool": _bool,
    "timestamp": _timestamp,
    "pixels": _pixels,
    "count": _count,
    "position": _position,
    "mount": _mount,
    "size": _size,
    "quaternion": _quaternion,
    "intrinsics": _intrinsics,
}
_MISSING = object()


def _show(value: Any) -> str:
    """A short JSON rendering of a bad value for a message."""
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


@dataclass(frozen=True)
class SceneTimeline:
    """A scene's samples along its ``next`` links, and which of them have a valid time.

    Attributes:
        samples: every sample of the scene in link order.
        times: sample token -> timestamp (microseconds) of the samples whose timestamp is valid
            and strictly after the previous such sample's (the most samples that are in order).
        rejected: (sample token, error) of each sample left out of ``times``; the error names
            the file, the token and the field.
    """

    samples: list[Record]
    times: dict[str, int]
    rejected: list[tuple[str, NuScenesError]]


class NuScenesTables:
    """All tables of one version, indexed by token.

    Attributes:
        dataroot: the folder holding ``<version>/`` and the data files.
        root: the version folder (``<dataroot>/<version>``).
        tables: table name -> {token: record}.
        load_problems: records left out of the index (no token, a duplicate token, a malformed
            sample link), one error each.
    """

    def __init__(self, dataroot: str | Path, version: str):
        self.dataroot = Path(dataroot).expanduser()
        self.version = version
        self.root = self.dataroot / version
        if not self.root.is_dir():
            raise NuScenesError(f"{self.root}: no such nuScenes version folder")
        self.load_problems: list[NuScenesError] = []
        self._repeated: dict[tuple[str, str], NuScenesError] = {}  # (table, token) -> why it is not used
        self.tables: dict[str, dict[str, Record]] = {name: self._load(name) for name in TABLE_NAMES}
        self.sample_data_by_sample = self._by_sample("sample_data")
        self.annotations_by_sample = self._by_sample("sample_annotation")
        self._timelines: dict[str, SceneTimeline] = {}

    def path(self, table: str) -> Path:
        """The JSON file of ``table``."""
        return self.root / f"{table}.json"

    def _load(self, name: str) -> dict[str, Record]:
        path = self.path(name)
        if not path.is_file():
            raise NuScenesError(f"{path}: table {name!r} is missing (a nuScenes version needs all 13 tables)")
        try:
            rows = json.loads(path.read_bytes())
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
            raise NuScenesError(
                f"{path}: table {name!r} is not valid JSON ({type(e).__name__}: {e})"
            ) from None
        if not isinstance(rows, list):
            raise NuScenesError(f"{path}: table {name!r} must be a JSON list of records")
        out: dict[str, Record] = {}
        for i, row in enumerate(rows):
            if not isinstance(row, dict) or not isinstance(row.get("token"), str):
                self.load_problems.append(NuScenesError(f"{path}: record {i} of table {name!r} has no token"))
            elif row["token"] in out or (name, row["token"]) in self._repeated:
                problem = NuScenesError(
                    f"{path}: record {i} of table {name!r} repeats the token {row['token']!r}"
                )
                self._repeated.setdefault((name, row["token"]), problem)
                self.load_problems.append(problem)
                out.pop(row["token"], None)  # which of the records is meant is unknowable: none is used
            else:
                out[row["token"]] = row
        return out

    def _by_sample(self, table: str) -> dict[str, list[Record]]:
        """Records of ``table`` grouped by their ``sample_token`` (those without a valid one are
        load problems)."""
        index: dict[str, list[Record]] = defaultdict(list)
        for record in self.tables[table].values():
            try:
                index[self.field(table, record, "sample_token", "token")].append(record)
            except NuScenesError as e:
                self.load_problems.append(e)
        return index

    def __getitem__(self, table: str) -> dict[str, Record]:
        return self.tables[table]

    def error(self, table: str, record: Record, problem: str) -> NuScenesError:
        """The error for ``problem`` (e.g. ``"'size' must be ..."``) of a record of ``table``,
        naming the table's file and the record's token."""
        return NuScenesError(f"{self.path(table)}: {table} {record.get('token')!r}: {problem}")

    def named_by(self, table: str, record: Record, name: str) -> str:
        """Where a value came from, for errors about what it names: ``<table> '<token>' '<name>'
        in <table's file>``."""
        return f"{table} {record.get('token')!r} {name!r} in {self.path(table)}"

    def field(self, table: str, record: Record, name: str, kind: FieldKind, default: Any = _MISSING) -> Any:
        """``record[name]`` checked against ``kind`` (see :data:`FieldKind`) and converted (numbers
        to float64 arrays, quaternions normalised). A missing field is ``default`` where one is
        given, an error otherwise; a present field of the wrong kind is always an error."""
        if name not in record:
            if default is not _MISSING:
                return default
            raise self.error(table, record, f"has no field {name!r}")
        try:
            return _CHECKS[kind](record[name])
        except _Invalid as e:
            raise self.error(table, record, f"{name!r} {e}, got {_show(record[name])}") from None

    def valid(self, table: str, record: Record, name: str, kind: FieldKind) -> Any | None:
        """:meth:`field`, or None where the field is missing or invalid (for optional evidence,
        such as a neighbouring annotation)."""
        try:
            return self.field(table, record, name, kind)
        except NuScenesError:
            return None

    def link(self, table: str, record: Record, name: str, token: str, target: str) -> Record:
        """The record ``token`` of ``target`` that field ``name`` of ``record`` (in ``table``) links to."""
        found = self.tables[target].get(token)
        if found is None:
            repeated = self._repeated.get((target, token))
            why = f" ({repeated})" if repeated is not None else ""
            raise self.error(
                table, record, f"{name!r}: table {target!r} has no record with token {token!r}{why}"
            )
        return found

    def follow(self, table: str, record: Record, name: str, target: str) -> Record:
        """The record of ``target`` that the token field ``record[name]`` points to."""
        return self.link(table, record, name, self.field(table, record, name, "token"), target)

    def data_path(self, table: str, record: Record, name: str) -> Path:
        """The existing file that field ``name`` of ``record`` names, relative to the dataroot.

        The path must stay inside the dataroot: an absolute path, a ``..`` component or a symlink
        that leads out of it is an error naming the record and the path, and nothing is read.
        """
        value = self.field(table, record, name, "text")
        relative = PurePosixPath(value)
        if not value or "\x00" in value:
            raise self.error(table, record, f"{name!r} must name a file, got {_show(value)}")
        if relative.is_absolute() or ".." in relative.parts:
            raise self.error(table, record, f"{name!r} {value!r} leads outside the dataroot {self.dataroot}")
        try:
            resolved = (self.dataroot / relative).resolve()
        except (OSError, RuntimeError) as e:
            raise self.error(table, record, f"{name!r} {value!r} cannot be resolved ({e})") from None
        if not resolved.is_relative_to(self._resolved_dataroot):
            raise self.error(
                table,
                record,
                f"{name!r} {value!r} leads outside the dataroot {self.dataroot} (to {resolved})",
            )
        path = self.dataroot / relative
        if not resolved.is_file():
            named_by = self.named_by(table, record, name)
            raise NuScenesError(
                f"{path}: file of {table} {record['token']!r} is missing (named by {named_by})"
            )
        return path

    @cached_property
    def _resolved_dataroot(self) -> Path:
        return self.dataroot.resolve()

    def channel(self, sample_data: Record) -> tuple[str, str]:
        """(channel, modality) of a sample_data record, through its calibrated sensor."""
        cs = self.follow("sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor")
        sensor = self.follow("calibrated_sensor", cs, "sensor_token", "sensor")
        modality = self.field("sensor", sensor, "modality", "text")
        if modality not in ("camera", "lidar", "radar"):
            raise self.error(
                "sensor", sensor, f"'modality' must be camera, lidar or radar, got {_show(modality)}"
            )
        return self.field("sensor", sensor, "channel", "text"), modality

    def scene_samples(self, scene: Record) -> list[Record]:
        """The samples of ``scene`` in link order, by its ``first_sample_token`` and ``next`` links."""
        out: list[Record] = []
        seen: set[str] = set()
        sample = self.follow("scene", scene, "first_sample_token", "sample")
        while True:
            if sample["token"] in seen:
                raise self.error("sample", sample, f"'next': the samples of scene {scene['token']!r} loop")
            seen.add(sample["token"])
            scene_token = self.field("sample", sample, "scene_token", "token")
            if scene_token != scene["token"]:
                raise self.error(
                    "sample",
                    sample,
                    f"'scene_token' is {scene_token!r}, but scene {scene['token']!r} links to it",
                )
            out.append(sample)
            if not self.field("sample", sample, "next", "token", ""):
                return out
            sample = self.follow("sample", sample, "next", "sample")

    def timeline(self, scene: Record) -> SceneTimeline:
        """The scene's samples and their valid times (cached per scene; see :class:`SceneTimeline`)."""
        cached = self._timelines.get(scene["token"])
        if cached is None:
            cached = self._timelines[scene["token"]] = self._timeline(scene)
        return cached

    def _timeline(self, scene: Record) -> SceneTimeline:
        samples = self.scene_samples(scene)
        rejected: list[tuple[str, NuScenesError]] = []
        timed: list[tuple[Record, int]] = []
        for sample in samples:
            try:
                timed.append((sample, self.field("sample", sample, "timestamp", "timestamp")))
            except NuScenesError as e:
                rejected.append((sample["token"], e))
        kept_at = set(records.increasing_frames([t for _, t in timed]))
        keep = [i in kept_at for i in range(len(timed))]
        times = {sample["token"]: t for (sample, t), kept in zip(timed, keep, strict=True) if kept}
        kept_times = [t for (_, t), kept in zip(timed, keep, strict=True) if kept]
        for i, ((sample, t), kept) in enumerate(zip(timed, keep, strict=True)):
            if not kept:
                # Kept neighbours: were t strictly between them, keeping it too would keep more.
                n_before = sum(keep[:i])
                before = kept_times[n_before - 1] if n_before else "the start"
                after = kept_times[n_before] if n_before < len(kept_times) else "the end"
                problem = (
                    f"'timestamp' {t} is out of time order: not strictly between the samples "
                    f"around it ({before} and {after})"
                )
                rejected.append((sample["token"], self.error("sample", sample, problem)))
        return SceneTimeline(samples, times, rejected)

    def sample_time(self, token: str) -> int | None:
        """The timestamp of sample ``token`` where it is valid and in time order within its scene
        (:meth:`timeline`); None otherwise."""
        sample = self.tables["sample"].get(token)
        scene_token = None if sample is None else self.valid("sample", sample, "scene_token", "token")
        scene = self.tables["scene"].get(scene_token) if scene_token is not None else None
        if scene is None:
            return None
        return self.timeline(scene).times.get(token)
