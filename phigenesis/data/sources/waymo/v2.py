"""Waymo Open Dataset v2 (Parquet) reader and writer, with pyarrow only.

Layout: ``{root}/{component_tag}/{segment_context_name}.parquet``. Key columns are ``key.<field>``,
data columns ``[ComponentClass].<path>`` (see ``shared/reference/waymo.md`` section 4). Frames read
into and write from the records of :mod:`.raw`, which keep Waymo's own frames and units: 4x4 float64
``target_from_source`` transforms, ``global`` = Waymo's world frame, ``vehicle`` = Waymo's ego frame,
metres, radians, seconds since the epoch for camera times and microseconds for frame timestamps.

Reading is frame by frame: :class:`V2Segment` indexes the timestamp column of each component once
(which file rows hold each frame), then decodes each component a frame's rows at a time
(``ParquetFile.iter_batches``), so memory holds about one frame, not a row group (10 frames of
range images are 244 MiB in Arrow), and a pass in file order decodes each row once. Real files
differ from the declared schema; the reader accepts float32 or float64 transforms (fixed-size or
plain lists) and camera / LiDAR names stored as integer codes or as strings such as ``"FRONT"``.
"""

from __future__ import annotations

import math
import os
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from numpy.typing import NDArray

from phigenesis.data.records import InvalidRecord, check_transform
from phigenesis.data.sources.waymo.raw import (
    CAMERA_CODES,
    CAMERA_NAMES,
    LASER_CODES,
    LASER_NAMES,
    FrameKey,
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    RawProjectedBoxes,
    WaymoFormatError,
)

#: Component tags (folder names) this module reads and writes.
V2_COMPONENTS: tuple[str, ...] = (
    "vehicle_pose",
    "camera_calibration",
    "lidar_calibration",
    "camera_image",
    "camera_segmentation",
    "lidar",
    "lidar_pose",
    "lidar_box",
    "projected_lidar_box",
    "stats",
)
#: Number of frames per row group that :func:`write_v2` writes by default.
FRAMES_PER_ROW_GROUP = 10

_CLASS = {
    "vehicle_pose": "VehiclePoseComponent",
    "camera_calibration": "CameraCalibrationComponent",
    "lidar_calibration": "LiDARCalibrationComponent",
    "camera_image": "CameraImageComponent",
    "camera_segmentation": "CameraSegmentationLabelComponent",
    "lidar": "LiDARComponent",
    "lidar_pose": "LiDARPoseComponent",
    "lidar_box": "LiDARBoxComponent",
    "projected_lidar_box": "ProjectedLiDARBoxComponent",
    "stats": "StatsComponent",
}
_STATIC = ("camera_calibration", "lidar_calibration")
_SEG = "key.segment_context_name"
_TS = "key.frame_timestamp_micros"
_CAM = "key.camera_name"
_LASER = "key.laser_name"
_OBJ = "key.laser_object_id"
_INTRINSICS = ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")
_XYZ = ("x", "y", "z")
_MAPPING = "instance_id_to_global_id_mapping"
#: Read buffer of a component file, bytes: column chunks are read this much at a time.
_READ_BUFFER_BYTES = 1 << 20
_R = TypeVar("_R")


def _c(tag: str, field: str) -> str:
    """The data column ``[ComponentClass].field`` of component ``tag``."""
    return f"[{_CLASS[tag]}].{field}"


# ----------------------------------------------------------------------------------------------
# Declared schema


@dataclass(frozen=True)
class _Style:
    """How names and transforms are typed on write (declared schema or the real-file quirks)."""

    names_as_strings: bool = False
    transforms_float32: bool = False

    @property
    def name_type(self) -> pa.DataType:
        return pa.string() if self.names_as_strings else pa.int8()

    @property
    def transform_type(self) -> pa.DataType:
        return pa.list_(pa.float32() if self.transforms_float32 else pa.float64(), 16)


def _range_image_fields(tag: str, returns: tuple[int, ...]) -> list[tuple[str, pa.DataType]]:
    fields = []
    for r in returns:
        fields.append((_c(tag, f"range_image_return{r}.values"), pa.list_(pa.float32())))
        fields.append((_c(tag, f"range_image_return{r}.shape"), pa.list_(pa.int32(), 3)))
    return fields


def _schema(tag: str, style: _Style) -> pa.Schema:
    """The declared Arrow schema of component ``tag`` (names and transforms typed by ``style``)."""
    f64, name, tf = pa.float64(), style.name_type, style.transform_type
    frame_key = [(_SEG, pa.string()), (_TS, pa.int64())]
    fields: list[tuple[str, pa.DataType]]
    if tag == "vehicle_pose":
        fields = [*frame_key, (_c(tag, "world_from_vehicle.transform"), tf)]
    elif tag == "camera_calibration":
        fields = [(_SEG, pa.string()), (_CAM, name)]
        fields += [(_c(tag, f"intrinsic.{k}"), f64) for k in _INTRINSICS]
        fields += [
            (_c(tag, "extrinsic.transform"), tf),
            (_c(tag, "width"), pa.int32()),
            (_c(tag, "height"), pa.int32()),
            (_c(tag, "rolling_shutter_direction"), pa.int8()),
        ]
    elif tag == "lidar_calibration":
        fields = [
            (_SEG, pa.string()),
            (_LASER, name),
            (_c(tag, "extrinsic.transform"), tf),
            (_c(tag, "beam_inclination.min"), f64),
            (_c(tag, "beam_inclination.max"), f64),
            (_c(tag, "beam_inclination.values"), pa.list_(f64)),
        ]
    elif tag == "camera_image":
        fields = [*frame_key, (_CAM, name), (_c(tag, "image"), pa.binary()), (_c(tag, "pose.transform"), tf)]
        fields += [(_c(tag, f"velocity.linear_velocity.{a}"), pa.float32()) for a in _XYZ]
        fields += [(_c(tag, f"velocity.angular_velocity.{a}"), f64) for a in _XYZ]
        fields += [(_c(tag, "pose_timestamp"), f64)]
        fields += [
            (_c(tag, f"rolling_shutter_params.{k}"), f64)
            for k in ("shutter", "camera_trigger_time", "camera_readout_done_time")
        ]
    elif tag == "camera_segmentation":
        fields = [
            *frame_key,
            (_CAM, name),
            (_c(tag, "panoptic_label_divisor"), pa.int32()),
            (_c(tag, "panoptic_label"), pa.binary()),
            (_c(tag, f"{_MAPPING}.local_instance_ids"), pa.list_(pa.int32())),
            (_c(tag, f"{_MAPPING}.global_instance_ids"), pa.list_(pa.int32())),
            (_c(tag, f"{_MAPPING}.is_tracked"), pa.list_(pa.bool_())),
            (_c(tag, "sequence_id"), pa.string()),
            (_c(tag, "num_cameras_covered"), pa.binary()),
        ]
    elif tag == "lidar":
        fields = [*frame_key, (_LASER, name), *_range_image_fields(tag, (1, 2))]
    elif tag == "lidar_pose":
        fields = [*frame_key, (_LASER, name), *_range_image_fields(tag, (1,))]
    elif tag == "lidar_box":
        fields = [*frame_key, (_OBJ, pa.string())]
        fields += [(_c(tag, f"box.center.{a}"), f64) for a in _XYZ]
        fields += [(_c(tag, f"box.size.{a}"), f64) for a in _XYZ]
        fields += [
            (_c(tag, "box.heading"), f64),
            (_c(tag, "type"), pa.int8()),
            (_c(tag, "num_lidar_points_in_box"), pa.int64()),
            (_c(tag, "num_top_lidar_points_in_box"), pa.int64()),
        ]
        fields += [(_c(tag, f"{v}.{a}"), f64) for v in ("speed", "acceleration") for a in _XYZ]
        fields += [(_c(tag, f"difficulty_level.{k}"), pa.int8()) for k in ("detection", "tracking")]
    elif tag == "projected_lidar_box":
        fields = [*frame_key, (_CAM, name), (_OBJ, pa.string())]
        fields += [(_c(tag, f"box.{p}.{a}"), f64) for p in ("center", "size") for a in ("x", "y")]
        fields += [(_c(tag, "type"), pa.int8())]
    elif tag == "stats":
        fields = [*frame_key] + [(_c(tag, k), pa.string()) for k in ("time_of_day", "location", "weather")]
        for counts in ("lidar_object_counts", "camera_object_counts"):
            fields += [
                (_c(tag, f"{counts}.types"), pa.list_(pa.int8())),
                (_c(tag, f"{counts}.counts"), pa.list_(pa.int32())),
            ]
    else:
        raise ValueError(f"unknown Waymo v2 component {tag!r}")
    return pa.schema(fields)


#: Columns the reader may do without (filled with None / defaults when absent).
_OPTIONAL_COLUMNS = frozenset(
    {
        _c("lidar", "range_image_return2.values"),
        _c("lidar", "range_image_return2.shape"),
        _c("lidar_box", "num_top_lidar_points_in_box"),
        _c("stats", "time_of_day"),
        _c("stats", "location"),
        _c("stats", "weather"),
    }
)
#: Columns of the declared schema that the reader does not use.
_UNUSED_COLUMNS = frozenset(
    {
        _SEG,
        _c("lidar_box", "difficulty_level.detection"),
        _c("lidar_box", "difficulty_level.tracking"),
        _c("camera_segmentation", f"{_MAPPING}.is_tracked"),
        _c("camera_segmentation", "sequence_id"),
        _c("camera_segmentation", "num_cameras_covered"),
        *(
            _c("stats", f"{k}.{v}")
            for k in ("lidar_object_counts", "camera_object_counts")
            for v in ("types", "counts")
        ),
    }
)


def _read_columns(tag: str) -> tuple[list[str], list[str]]:
    """(required, optional) columns the reader uses from component ``tag``."""
    names = [n for n in _schema(tag, _Style()).names if n not in _UNUSED_COLUMNS]
    return [n for n in names if n not in _OPTIONAL_COLUMNS], [n for n in names if n in _OPTIONAL_COLUMNS]


# ----------------------------------------------------------------------------------------------
# Root and segment discovery


def is_v2_root(path: Path) -> bool:
    """Whether ``path`` is a directory holding a ``vehicle_pose/`` component folder."""
    path = Path(path)
    return path.is_dir() and (path / "vehicle_pose").is_dir()


def _check_root(root: Path) -> list[str]:
    """The component tags present in ``root``; raises if the root or a required folder is missing."""
    if not root.is_dir():
        raise WaymoFormatError(f"{root}: Waymo v2 root does not exist or is not a directory")
    present = [tag for tag in V2_COMPONENTS if (root / tag).is_dir()]
    if not present:
        raise WaymoFormatError(
            f"{root}: no Waymo v2 component folders (expected some of {', '.join(V2_COMPONENTS)})"
        )
    # lidar_box too: without it a segment would convert with no boxes, silently.
    required = ["vehicle_pose", "camera_calibration", "lidar_box"]
    if "lidar" in present:
        required += ["lidar_calibration", "lidar_pose"]
    for tag in required:
        if tag not in present:
            raise WaymoFormatError(f"{root}: required component folder {tag}/ is missing")
    return present


def list_segments(root: Path) -> list[str]:
    """Sorted segment context names of a v2 root (the file stems in ``vehicle_pose/``)."""
    root = Path(root)
    _check_root(root)
    return sorted(p.stem for p in (root / "vehicle_pose").glob("*.parquet"))


# ----------------------------------------------------------------------------------------------
# Column conversion (Arrow -> numpy)


class _ColumnError(ValueError):
    """A column value the reader cannot use; the message names the column and the row (and its
    key: camera, LiDAR or object). The segment prefixes the file and frame."""


_KEY_COLUMNS = ((_CAM, "camera"), (_LASER, "LiDAR"), (_OBJ, "object"))
_CAST_ERRORS = (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError)


def _row_name(table: pa.Table, row: int) -> str:
    """``row R (camera FRONT)`` for row ``row`` of a frame's rows, with its key where it has one."""
    keys = [
        f"{label} {table.column(col)[row].as_py()!r}"
        for col, label in _KEY_COLUMNS
        if col in table.column_names and row < table.num_rows
    ]
    return f"row {row}" + (f" ({', '.join(keys)})" if keys else "")


def _column(table: pa.Table, name: str) -> pa.Array:
    chunked = table.column(name)
    # combine_chunks copies even a single chunk (a frame's range images: ~20 MB).
    col = chunked.chunk(0) if chunked.num_chunks == 1 else chunked.combine_chunks()
    return pc.dictionary_decode(col) if pa.types.is_dictionary(col.type) else col


def _cast(table: pa.Table, name: str, type_: pa.DataType) -> pa.Array:
    """Column ``name`` cast to ``type_``; raises :class:`_ColumnError` naming the first row whose
    value does not convert (a string such as 'abc' in a number column)."""
    col = _column(table, name)
    try:
        return pc.cast(col, type_)
    except _CAST_ERRORS as e:
        for row in range(len(col)):
            try:
                pc.cast(col.slice(row, 1), type_)
            except _CAST_ERRORS:
                raise _ColumnError(
                    f"column {name} {_row_name(table, row)} holds {col[row].as_py()!r}, not a {type_} ({e})"
                ) from None
        raise _ColumnError(f"column {name} of type {col.type} does not convert to {type_} ({e})") from None


def _numbers(table: pa.Table, name: str, type_: pa.DataType, fill: float) -> NDArray[Any]:
    """Column ``name`` cast to ``type_`` as numpy (nulls -> ``fill``). A column already of that
    type without nulls is taken as it is (a frame reads some 30 such columns, and each compute
    call costs tens of microseconds of Python)."""
    col = _column(table, name)
    if col.type != type_:
        col = _cast(table, name, type_)
    if col.null_count:
        col = pc.fill_null(col, fill)
    return col.to_numpy(zero_copy_only=False)


def _floats(table: pa.Table, name: str, fill: float = np.nan) -> NDArray[np.float64]:
    """Column ``name`` as float64 (nulls -> ``fill``)."""
    return _numbers(table, name, pa.float64(), fill)


def _ints(table: pa.Table, name: str, fill: int = -1) -> NDArray[np.int64]:
    """Column ``name`` as int64 (nulls -> ``fill``); ``fill`` for every row when it is absent."""
    if name not in table.column_names:
        return np.full(table.num_rows, fill, np.int64)
    return _numbers(table, name, pa.int64(), fill)


def _name_codes(table: pa.Table, name: str, codes: dict[str, int], where: Path) -> NDArray[np.int32]:
    """Camera / LiDAR name column as int32 codes, whether stored as integers or as names."""
    col = _column(table, name)
    if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
        values = col.to_pylist()
        unknown = sorted({v for v in values if v not in codes}, key=str)
        if unknown:
            raise WaymoFormatError(f"{where}: column {name} has unknown names {unknown}")
        return np.array([codes[v] for v in values], np.int32)
    if col.null_count:
        raise WaymoFormatError(f"{where}: column {name} has null entries")
    return _cast(table, name, pa.int32()).to_numpy(zero_copy_only=False)


def _is_list(type_: pa.DataType) -> bool:
    return pa.types.is_list(type_) or pa.types.is_large_list(type_) or pa.types.is_fixed_size_list(type_)


def _list_column(table: pa.Table, name: str, value_type: pa.DataType | None = None) -> pa.Array:
    """List column ``name`` as a plain list array (of ``value_type`` if given)."""
    col = _column(table, name)
    if not _is_list(col.type):
        raise _ColumnError(f"column {name} is {col.type}, not a list column")
    target = pa.list_(col.type.value_type if value_type is None else value_type)
    if col.type == target:
        return col
    try:
        return col.cast(target)
    except _CAST_ERRORS as e:
        for row in range(len(col)):
            try:
                col.slice(row, 1).cast(target)
            except _CAST_ERRORS:
                raise _ColumnError(
                    f"column {name} {_row_name(table, row)} holds {col[row].as_py()!r}, not a {target} ({e})"
                ) from None
        raise _ColumnError(f"column {name} does not convert to {target} ({e})") from None


def _list_values(
    table: pa.Table, name: str, value_type: pa.DataType | None = None
) -> list[NDArray[Any] | None]:
    """Each row of list column ``name`` as a 1-D array (None for null rows)."""
    col = _list_column(table, name, value_type)
    # The offsets and the child array (zero-copy views; the offsets index the whole child, which
    # a sliced column shares with its neighbours) instead of compute calls, which cost tens of
    # microseconds of Python each.
    offsets = col.offsets.to_numpy(zero_copy_only=False).tolist()
    flat = col.values.to_numpy(zero_copy_only=False)
    valid = col.is_valid().to_numpy(zero_copy_only=False).tolist() if col.null_count else [True] * len(col)
    return [flat[lo:hi] if ok else None for lo, hi, ok in zip(offsets[:-1], offsets[1:], valid, strict=True)]


def _transforms(table: pa.Table, name: str, where: Path) -> NDArray[np.float64]:
    """(N, 4, 4) float64 from a column of 16 row-major values (fixed-size or plain list)."""
    col = _list_column(table, name, pa.float64())
    if col.null_count:
        raise WaymoFormatError(f"{where}: column {name} has null transforms")
    lengths = pc.list_value_length(col).to_numpy(zero_copy_only=False)
    bad = np.flatnonzero(lengths != 16)
    if len(bad):
        raise WaymoFormatError(
            f"{where}: column {name} {_row_name(table, int(bad[0]))} holds {int(lengths[bad[0]])} values, "
            "a transform needs 16"
        )
    flat = pc.list_flatten(col).to_numpy(zero_copy_only=False).astype(np.float64)
    return flat.reshape(len(col), 4, 4)


def _range_image(
    values: NDArray[Any] | None, shape_values: NDArray[Any] | None, channels: int, what: Callable[[], str]
) -> NDArray[np.float32] | None:
    """One row's range image as (H, W, channels) float32 (None if null or empty); raises
    naming ``what()`` if its shape is not three positive dims holding its values."""
    if values is None or shape_values is None or values.size == 0:
        return None
    shape = tuple(int(x) for x in shape_values)
    if len(shape) != 3 or shape[2] != channels or min(shape) <= 0 or math.prod(shape) != values.size:
        raise WaymoFormatError(f"{what()} has {values.size} values for shape {list(shape)}")
    return values.astype(np.float32, copy=False).reshape(shape)


def _range_images(
    table: pa.Table, tag: str, ret: int, channels: int, where: Path
) -> list[NDArray[np.float32] | WaymoFormatError | None]:
    """Range images ``range_image_return{ret}`` as (H, W, channels) float32 (None if null/absent),
    or the error of a row whose shape does not hold its values."""
    values_col, shape_col = (
        _c(tag, f"range_image_return{ret}.values"),
        _c(tag, f"range_image_return{ret}.shape"),
    )
    if values_col not in table.column_names:
        return [None] * table.num_rows
    values = _list_values(table, values_col, pa.float32())
    shapes = _list_values(table, shape_col, pa.int64())
    out: list[NDArray[np.float32] | WaymoFormatError | None] = []
    for row, (v, shape) in enumerate(zip(values, shapes, strict=True)):
        try:
            what = lambda r=row: f"{where}: {values_col} {_row_name(table, r)}"  # noqa: E731 (named on error only)
            out.append(_range_image(v, shape, channels, what))
        except WaymoFormatError as e:
            out.append(e)
    return out


# ----------------------------------------------------------------------------------------------
# Reading


class _RowStream:
    """The rows of a component file in file order from the start of one row group on, decoded
    a few at a time (``ParquetFile.iter_batches`` of ``batch_rows`` rows, one row group after the
    other), so only the batch in hand is in memory."""

    def __init__(self, file: _ComponentFile, group: int) -> None:
        self.file = file
        self.group = group
        #: File row number of the first row of ``pending``.
        self.position = int(file.group_starts[group])
        self.pending: pa.RecordBatch | None = None
        self._batches = self._decode(group)

    def _decode(self, first_group: int) -> Iterator[pa.RecordBatch]:
        f = self.file
        for group in range(first_group, f.num_row_groups):
            self.group = group
            f.reads[(f.tag, group)] += 1
            yield from f.file.iter_batches(
                batch_size=f.batch_rows, row_groups=[group], columns=f.columns, use_threads=False
            )

    def take(self, positions: NDArray[np.int64]) -> list[pa.RecordBatch]:
        """The rows at file row numbers ``positions`` (increasing, none before :attr:`position`),
        in file order; the stream moves on to the row after the last of them."""
        parts: list[pa.RecordBatch] = []
        end = int(positions[-1]) + 1
        while self.position < end:
            if self.pending is None or self.pending.num_rows == 0:
                self.pending = next(self._batches, None)
                if self.pending is None:
                    raise pa.ArrowInvalid(f"the file ends at row {self.position}, before row {end - 1}")
            stop = min(self.position + self.pending.num_rows, end)
            lo, hi = np.searchsorted(positions, [self.position, stop])
            if hi > lo:
                wanted = positions[lo:hi] - self.position
                if wanted[-1] - wanted[0] + 1 == len(wanted):  # contiguous: a slice, no copy
                    parts.append(self.pending.slice(int(wanted[0]), len(wanted)))
                else:
                    parts.append(self.pending.take(pa.array(wanted)))
            rest = self.pending.num_rows - (stop - self.position)
            # Drop a used-up batch at once: even an empty slice of it would keep its memory.
            self.pending = self.pending.slice(stop - self.position) if rest else None
            self.position = stop
        return parts


class _ComponentFile:
    """One component file of one segment: where each frame's rows are, and a stream that decodes
    the rows a frame at a time."""

    def __init__(self, tag: str, path: Path, reads: Counter[tuple[str, int]]) -> None:
        self.tag, self.path, self.reads = tag, path, reads
        try:
            # No pre-buffering and a small read buffer: a column chunk is read as it is decoded,
            # not all at once (a LiDAR row group's range images are tens of MB even compressed).
            self.file = pq.ParquetFile(path, pre_buffer=False, buffer_size=_READ_BUFFER_BYTES)
        except (pa.ArrowException, OSError) as e:
            raise WaymoFormatError(f"{path}: not a readable Parquet file ({e})") from e
        names = set(self.file.schema_arrow.names)
        required, optional = _read_columns(tag)
        missing = [c for c in required if c not in names]
        if missing:
            raise WaymoFormatError(f"{path}: {tag} is missing column(s) {', '.join(missing)}")
        self.columns = required + [c for c in optional if c in names]
        meta = self.file.metadata
        #: File row number where each row group starts, then the file's number of rows.
        self.group_starts = np.cumsum([0] + [meta.row_group(g).num_rows for g in range(meta.num_row_groups)])
        self.index: dict[int, NDArray[np.int64]] = {} if tag in _STATIC else self._index_frames()
        #: Rows per decoded batch: a frame's rows on average (5 per frame for the sensor components).
        self.batch_rows = max(1, -(-meta.num_rows // max(1, len(self.index))))
        self._stream: _RowStream | None = None

    @property
    def num_row_groups(self) -> int:
        return self.file.metadata.num_row_groups

    def _index_frames(self) -> dict[int, NDArray[np.int64]]:
        """Frame timestamp (us) -> the file row numbers of its rows, from the key column alone."""
        column = self._read(lambda: self.file.read(columns=[_TS])).column(_TS)
        if column.null_count:
            raise WaymoFormatError(f"{self.path}: column {_TS} has null entries")
        if not pa.types.is_integer(column.type):
            raise WaymoFormatError(f"{self.path}: column {_TS} is {column.type}, not integer microseconds")
        ts = column.to_numpy().astype(np.int64)
        order = np.argsort(ts, kind="stable")  # stable: each frame's row numbers stay increasing
        keys, starts = np.unique(ts[order], return_index=True)
        if not len(keys):
            return {}
        return dict(zip(keys.tolist(), np.split(order.astype(np.int64), starts[1:]), strict=True))

    def _read(self, fn: Callable[[], _R]) -> _R:
        try:
            return fn()
        except (pa.ArrowException, OSError) as e:
            raise WaymoFormatError(f"{self.path}: cannot read {self.tag} ({e})") from e

    def _group_of(self, row: int) -> int:
        return int(np.searchsorted(self.group_starts, row, side="right")) - 1

    def rows(self, timestamp: int) -> pa.Table:
        """The rows of frame ``timestamp`` (only the used columns), in file order.

        Read from the file's stream: frames asked for in file order decode each row once; a frame
        behind the stream (or row groups ahead of it) restarts it at the frame's row group.
        """
        positions = self.index.get(timestamp)
        if positions is None:
            return self.file.schema_arrow.empty_table().select(self.columns)
        first = int(positions[0])
        stream = self._stream
        if stream is None or stream.position > first or self._group_of(first) > stream.group:
            stream = self._stream = _RowStream(self, self._group_of(first))
        try:
            parts = stream.take(positions)
        except (pa.ArrowException, OSError) as e:
            self._stream = None
            raise WaymoFormatError(f"{self.path}: cannot read {self.tag} ({e})") from e
        return pa.Table.from_batches(parts)

    def all_rows(self) -> pa.Table:
        """Every row (for the per-segment components: calibrations, the vehicle poses)."""
        tables = []
        for group in range(self.num_row_groups):
            tables.append(self._read(lambda g=group: self.file.read_row_group(g, columns=self.columns)))
            self.reads[(self.tag, group)] += 1
        if not tables:
            return self.file.schema_arrow.empty_table().select(self.columns)
        return pa.concat_tables(tables)


class V2Segment:
    """One segment of a Waymo v2 root, read frame by frame.

    Construction checks the root and the segment's component files (existence, Parquet footer,
    expected columns) and indexes the frame timestamps; :meth:`frame_keys` reads every frame's
    pose (the vehicle_pose component, once) and :meth:`frame` then decodes the rows of one frame
    from each component's stream. ``row_group_reads`` counts how often each row group was started
    (read whole, or streamed from its first row), keyed by (component tag, group).

    Errors name the component file and the frame timestamp (and the row's camera, LiDAR or
    object); a value that only spoils one camera's or one LiDAR's data is put in the raw frame's
    ``invalid_sensors`` for the conversion's error policy.
    """

    def __init__(self, root: Path, segment: str) -> None:
        self.root, self.segment = Path(root), segment
        self.row_group_reads: Counter[tuple[str, int]] = Counter()
        self.files: dict[str, _ComponentFile] = {}
        for tag in _check_root(self.root):
            path = self.root / tag / f"{segment}.parquet"
            if not path.is_file():
                raise WaymoFormatError(f"segment {segment}: component {tag} has no file (expected {path})")
            self.files[tag] = _ComponentFile(tag, path, self.row_group_reads)
        self.timestamps: list[int] = sorted(self.files["vehicle_pose"].index)
        self._poses: dict[int, NDArray[np.float64]] | None = None
        self._camera_calibrations: list[RawCameraCalibration] | None = None
        self._laser_calibrations: list[RawLaserCalibration] | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def frame_keys(self) -> list[tuple[str, FrameKey | WaymoFormatError]]:
        """(where, :class:`~.raw.FrameKey` or the error that makes the frame unusable) for every
        frame timestamp in order: a timestamp with two vehicle_pose rows, or a pose that is not a
        rigid transform, is unusable. Raises if vehicle_pose has no rows."""
        file = self.files["vehicle_pose"]
        if not self.timestamps:
            raise WaymoFormatError(f"{file.path}: vehicle_pose has no rows: the segment has no frames")
        table = file.all_rows()
        ts = table.column(_TS).to_numpy().astype(np.int64)
        poses = _transforms(table, _c("vehicle_pose", "world_from_vehicle.transform"), file.path)
        rows: dict[int, list[int]] = {}
        for row, t in enumerate(ts.tolist()):
            rows.setdefault(t, []).append(row)
        out: list[tuple[str, FrameKey | WaymoFormatError]] = []
        self._poses = {}
        for t in self.timestamps:
            where = f"{file.path} frame {t}"
            if len(rows[t]) > 1:
                out.append(
                    (where, WaymoFormatError(f"{where}: rows {rows[t]} are all this frame's vehicle pose"))
                )
                continue
            try:
                pose = check_transform("world_from_vehicle", poses[rows[t][0]])
            except InvalidRecord as e:
                out.append((where, WaymoFormatError(f"{where} (row {rows[t][0]}): {e}")))
                continue
            self._poses[t] = pose
            out.append((where, FrameKey(t, pose)))
        return out

    def frame(self, index: int) -> RawFrame:
        """Frame ``index`` (in timestamp order) with every component of the root joined on its key."""
        ts = self.timestamps[index]
        if self._poses is None:
            self.frame_keys()
        assert self._poses is not None
        if ts not in self._poses:
            raise WaymoFormatError(
                f"{self.files['vehicle_pose'].path} frame {ts}: the frame's vehicle pose is invalid"
            )
        raw = RawFrame(
            segment=self.segment,
            timestamp_micros=ts,
            global_from_vehicle=self._poses[ts],
            camera_calibrations=self.camera_calibrations(),
            laser_calibrations=self.laser_calibrations(),
            images=[],
            lasers=[],
            labels=RawLabels.empty(),
            where=f"{self.root} segment {self.segment} frame {ts}",
            part_where={
                part: f"{self.files[tag].path} frame {ts}"
                for part, tag in (("camera", "camera_image"), ("laser", "lidar"), ("labels", "lidar_box"))
                if tag in self.files
            },
        )
        _mark_repeated(
            raw, raw.camera_calibrations, "camera_calibration", self.files["camera_calibration"].path
        )
        if "lidar_calibration" in self.files:
            _mark_repeated(
                raw, raw.laser_calibrations, "laser_calibration", self.files["lidar_calibration"].path
            )
        raw.images = self._images(ts, raw)
        raw.lasers = self._lasers(ts, raw)
        raw.labels = self._labels(ts)
        raw.projected_boxes = self._projected_boxes(ts)
        raw.stats = self._stats(ts)
        return raw

    def camera_calibrations(self) -> list[RawCameraCalibration]:
        """The segment's camera calibrations, sorted by camera code (read once)."""
        if self._camera_calibrations is None:
            file = self.files["camera_calibration"]
            self._camera_calibrations = _naming(file, None, lambda: _read_camera_calibrations(file))
        return self._camera_calibrations

    def laser_calibrations(self) -> list[RawLaserCalibration]:
        """The segment's LiDAR calibrations, sorted by laser code (read once; [] if absent)."""
        if self._laser_calibrations is None:
            cal = self.files.get("lidar_calibration")
            self._laser_calibrations = (
                [] if cal is None else _naming(cal, None, lambda: _read_laser_calibrations(cal))
            )
        return self._laser_calibrations

    def _images(self, ts: int, raw: RawFrame) -> list[RawCameraImage]:
        file = self.files.get("camera_image")
        if file is None:
            return []
        images = _naming(file, ts, lambda: _read_images(file, file.rows(ts)))
        calibrated = {c.name for c in self.camera_calibrations()}
        for image in images:
            if image.name not in calibrated:
                raw.mark_invalid(
                    "camera",
                    image.name,
                    WaymoFormatError(
                        f"{file.path} frame {ts}: camera {CAMERA_NAMES.get(image.name, image.name)} of "
                        f"segment {self.segment} has an image but no camera_calibration row"
                    ),
                )
        seg = self.files.get("camera_segmentation")
        if seg is not None:
            _naming(
                seg, ts, lambda: _attach_panoptic(images, seg, seg.rows(ts), f"{seg.path} frame {ts}", raw)
            )
        return sorted(images, key=lambda im: im.name)

    def _lasers(self, ts: int, raw: RawFrame) -> list[RawLaser]:
        file = self.files.get("lidar")
        if file is None:
            return []
        lasers = _naming(file, ts, lambda: _read_lasers(file, file.rows(ts), raw))
        pose_file = self.files["lidar_pose"]
        poses = _naming(pose_file, ts, lambda: _read_pixel_poses(pose_file, pose_file.rows(ts), raw))
        for laser in lasers:
            laser.pixel_pose = poses.get(laser.name)
        return sorted(lasers, key=lambda la: la.name)

    def _labels(self, ts: int) -> RawLabels:
        file = self.files.get("lidar_box")
        return RawLabels.empty() if file is None else _naming(file, ts, lambda: _read_labels(file.rows(ts)))

    def _projected_boxes(self, ts: int) -> RawProjectedBoxes:
        file = self.files.get("projected_lidar_box")
        if file is None:
            return RawProjectedBoxes.empty()
        return _naming(file, ts, lambda: _read_projected(file, file.rows(ts)))

    def _stats(self, ts: int) -> dict[str, str]:
        file = self.files.get("stats")
        if file is None:
            return {}
        table = file.rows(ts)
        if table.num_rows == 0:
            return {}
        stats = {}
        for key in ("time_of_day", "location", "weather"):
            name = _c("stats", key)
            value = table.column(name)[0].as_py() if name in table.column_names else None
            if value is not None:
                stats[key] = str(value)
        return stats


def _mark_repeated(raw: RawFrame, calibrations: list[Any], part: str, path: Path) -> None:
    """Marks every sensor with more than one calibration row invalid in ``raw``."""
    seen: set[int] = set()
    for c in calibrations:
        if c.name in seen:
            raw.mark_invalid(
                part, c.name, WaymoFormatError(f"{path}: sensor code {c.name} has two {part} rows")
            )
        seen.add(c.name)


def _naming(file: _ComponentFile, ts: int | None, read: Callable[[], _R]) -> _R:
    """``read()``, with a column value it cannot use reported as a :class:`WaymoFormatError`
    naming the component file and the frame (``ts``; None for the per-segment components)."""
    try:
        return read()
    except _ColumnError as e:
        where = f"{file.path}" if ts is None else f"{file.path} frame {ts}"
        raise WaymoFormatError(f"{where}: {e}") from None


def _read_camera_calibrations(file: _ComponentFile) -> list[RawCameraCalibration]:
    t, tag = file.all_rows(), "camera_calibration"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    intrinsics = np.stack([_floats(t, _c(tag, f"intrinsic.{k}")) for k in _INTRINSICS], axis=1)
    extrinsics = _transforms(t, _c(tag, "extrinsic.transform"), file.path)
    width, height = _ints(t, _c(tag, "width")), _ints(t, _c(tag, "height"))
    readout = _ints(t, _c(tag, "rolling_shutter_direction"), 0)
    cals = [
        RawCameraCalibration(
            int(names[i]), intrinsics[i], extrinsics[i], int(width[i]), int(height[i]), int(readout[i])
        )
        for i in range(t.num_rows)
    ]
    return sorted(cals, key=lambda c: c.name)


def _read_laser_calibrations(file: _ComponentFile) -> list[RawLaserCalibration]:
    t, tag = file.all_rows(), "lidar_calibration"
    names = _name_codes(t, _LASER, LASER_CODES, file.path)
    extrinsics = _transforms(t, _c(tag, "extrinsic.transform"), file.path)
    lo, hi = _floats(t, _c(tag, "beam_inclination.min")), _floats(t, _c(tag, "beam_inclination.max"))
    values = _list_values(t, _c(tag, "beam_inclination.values"), pa.float64())
    cals = [
        RawLaserCalibration(
            int(names[i]),
            extrinsics[i],
            None if v is None or v.size == 0 else v.astype(np.float64),
            float(lo[i]),
            float(hi[i]),
        )
        for i, v in enumerate(values)
    ]
    return sorted(cals, key=lambda c: c.name)


def _bytes_column(table: pa.Table, name: str) -> list[bytes | None]:
    """Binary column ``name`` as bytes per row (None for nulls)."""
    col = _column(table, name)
    if not (pa.types.is_binary(col.type) or pa.types.is_large_binary(col.type)):
        raise _ColumnError(f"column {name} is {col.type}, not binary")
    return col.to_pylist()


def _read_images(file: _ComponentFile, t: pa.Table) -> list[RawCameraImage]:
    tag = "camera_image"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    jpegs = _bytes_column(t, _c(tag, "image"))
    poses = _transforms(t, _c(tag, "pose.transform"), file.path)
    lin = np.stack([_floats(t, _c(tag, f"velocity.linear_velocity.{a}")) for a in _XYZ], axis=1)
    ang = np.stack([_floats(t, _c(tag, f"velocity.angular_velocity.{a}")) for a in _XYZ], axis=1)
    pose_ts = _floats(t, _c(tag, "pose_timestamp"))
    shutter, trigger, readout = (
        _floats(t, _c(tag, f"rolling_shutter_params.{k}"))
        for k in ("shutter", "camera_trigger_time", "camera_readout_done_time")
    )
    return [
        RawCameraImage(
            name=int(names[i]),
            jpeg=jpegs[i],
            global_from_vehicle=poses[i],
            velocity_linear=lin[i],
            velocity_angular=ang[i],
            pose_timestamp=float(pose_ts[i]),
            shutter=float(shutter[i]),
            trigger_time=float(trigger[i]),
            readout_done_time=float(readout[i]),
        )
        for i in range(t.num_rows)
    ]


def _attach_panoptic(
    images: list[RawCameraImage], file: _ComponentFile, t: pa.Table, where: str, raw: RawFrame
) -> None:
    """Sets the panoptic label fields of ``images`` from the camera_segmentation rows ``t``; a
    camera whose label rows are inconsistent is marked invalid in ``raw``."""
    tag = "camera_segmentation"
    names = _name_codes(t, _CAM, CAMERA_CODES, file.path)
    labels = _bytes_column(t, _c(tag, "panoptic_label"))
    divisors = _ints(t, _c(tag, "panoptic_label_divisor"), 0)
    local = _list_values(t, _c(tag, f"{_MAPPING}.local_instance_ids"), pa.int64())
    glob = _list_values(t, _c(tag, f"{_MAPPING}.global_instance_ids"), pa.int64())
    rows: dict[int, list[int]] = {}
    for i, n in enumerate(names.tolist()):
        rows.setdefault(int(n), []).append(i)
    for image in images:
        found = rows.get(image.name, [])
        camera = f"{where}: camera {CAMERA_NAMES.get(image.name, image.name)} panoptic label"
        if len(found) > 1:
            raw.mark_invalid("camera", image.name, WaymoFormatError(f"{camera}: rows {found} all label it"))
            continue
        if not found:
            continue
        i = found[0]
        image.panoptic_label = labels[i]
        image.panoptic_label_divisor = int(divisors[i])
        ids_local = [] if local[i] is None else local[i].tolist()
        ids_global = [] if glob[i] is None else glob[i].tolist()
        if len(ids_local) != len(ids_global):
            error = WaymoFormatError(
                f"{camera}: {_MAPPING} has {len(ids_local)} local, {len(ids_global)} global ids"
            )
            raw.mark_invalid("camera", image.name, error)
            continue
        image.instance_to_global = dict(zip(ids_local, ids_global, strict=True))


def _by_laser(
    file: _ComponentFile, t: pa.Table, columns: list[list[Any]], raw: RawFrame
) -> dict[int, list[Any]]:
    """Per laser code, its row's values of ``columns`` (one list per column, one value per row);
    a laser with two rows, or a value that is an error, marks that laser invalid in ``raw``."""
    names = _name_codes(t, _LASER, LASER_CODES, file.path)
    out: dict[int, list[Any]] = {}
    for row, code in enumerate(names.tolist()):
        values = [col[row] for col in columns]
        if code in out:
            error = WaymoFormatError(
                f"{file.path} frame {raw.timestamp_micros}: LiDAR {LASER_NAMES.get(code, code)} has two rows"
            )
            raw.mark_invalid("laser", code, error)
            continue
        errors = [v for v in values if isinstance(v, WaymoFormatError)]
        if errors:
            raw.mark_invalid("laser", code, errors[0])
            values = [None if isinstance(v, WaymoFormatError) else v for v in values]
        out[code] = values
    return out


def _read_lasers(file: _ComponentFile, t: pa.Table, raw: RawFrame) -> list[RawLaser]:
    r1 = _range_images(t, "lidar", 1, 4, file.path)
    r2 = _range_images(t, "lidar", 2, 4, file.path)
    return [RawLaser(code, a, b) for code, (a, b) in _by_laser(file, t, [r1, r2], raw).items()]


def _read_pixel_poses(
    file: _ComponentFile, t: pa.Table, raw: RawFrame
) -> dict[int, NDArray[np.float32] | None]:
    poses = _range_images(t, "lidar_pose", 1, 6, file.path)
    return {code: p for code, (p,) in _by_laser(file, t, [poses], raw).items()}


def _read_labels(t: pa.Table) -> RawLabels:
    tag = "lidar_box"
    box = np.stack(
        [_floats(t, _c(tag, f"box.center.{a}")) for a in _XYZ]
        + [_floats(t, _c(tag, f"box.size.{a}")) for a in _XYZ]
        + [_floats(t, _c(tag, "box.heading"))],
        axis=1,
    ).reshape(-1, 7)
    speed = np.stack([_floats(t, _c(tag, f"speed.{a}"), 0.0) for a in _XYZ], axis=1).reshape(-1, 3)
    accel = np.stack([_floats(t, _c(tag, f"acceleration.{a}"), 0.0) for a in _XYZ], axis=1).reshape(-1, 3)
    return RawLabels(
        ids=[str(x) for x in _column(t, _OBJ).to_pylist()],
        types=_ints(t, _c(tag, "type"), 0).astype(np.int32),
        box=box,
        speed=speed,
        accel=accel,
        num_lidar_points=_ints(t, _c(tag, "num_lidar_points_in_box")).astype(np.int32),
        num_top_lidar_points=_ints(t, _c(tag, "num_top_lidar_points_in_box")).astype(np.int32),
    )


def _read_projected(file: _ComponentFile, t: pa.Table) -> RawProjectedBoxes:
    tag = "projected_lidar_box"
    box = np.stack(
        [_floats(t, _c(tag, f"box.{p}.{a}")) for p in ("center", "size") for a in ("x", "y")], axis=1
    ).reshape(-1, 4)
    return RawProjectedBoxes(
        camera=_name_codes(t, _CAM, CAMERA_CODES, file.path),
        ids=[str(x) for x in _column(t, _OBJ).to_pylist()],
        box=box,
        types=_ints(t, _c(tag, "type"), 0).astype(np.int32),
    )


# ----------------------------------------------------------------------------------------------
# Writing

_Columns = dict[str, list[Any]]


def _name(code: int, names: dict[int, str], style: _Style) -> int | str:
    return names.get(code, str(code)) if style.names_as_strings else code


def _vehicle_pose_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    return {
        _SEG: [f.segment for f in frames],
        _TS: [f.timestamp_micros for f in frames],
        _c("vehicle_pose", "world_from_vehicle.transform"): [f.global_from_vehicle for f in frames],
    }


def _camera_calibration_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag, f = "camera_calibration", frames[0]
    cals = f.camera_calibrations
    cols: _Columns = {_SEG: [f.segment] * len(cals), _CAM: [_name(c.name, CAMERA_NAMES, style) for c in cals]}
    for k, key in enumerate(_INTRINSICS):
        cols[_c(tag, f"intrinsic.{key}")] = [float(c.intrinsic[k]) for c in cals]
    cols[_c(tag, "extrinsic.transform")] = [c.vehicle_from_camera for c in cals]
    cols[_c(tag, "width")] = [c.width for c in cals]
    cols[_c(tag, "height")] = [c.height for c in cals]
    cols[_c(tag, "rolling_shutter_direction")] = [c.rolling_shutter_direction for c in cals]
    return cols


def _lidar_calibration_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag, f = "lidar_calibration", frames[0]
    cals = f.laser_calibrations
    return {
        _SEG: [f.segment] * len(cals),
        _LASER: [_name(c.name, LASER_NAMES, style) for c in cals],
        _c(tag, "extrinsic.transform"): [c.vehicle_from_laser for c in cals],
        _c(tag, "beam_inclination.min"): [c.beam_inclination_min for c in cals],
        _c(tag, "beam_inclination.max"): [c.beam_inclination_max for c in cals],
        _c(tag, "beam_inclination.values"): [c.beam_inclinations for c in cals],
    }


def _camera_image_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "camera_image"
    rows = [(f, im) for f in frames for im in f.images]
    cols: _Columns = {
        _SEG: [f.segment for f, _ in rows],
        _TS: [f.timestamp_micros for f, _ in rows],
        _CAM: [_name(im.name, CAMERA_NAMES, style) for _, im in rows],
        _c(tag, "image"): [im.jpeg for _, im in rows],
        _c(tag, "pose.transform"): [im.global_from_vehicle for _, im in rows],
    }
    for k, a in enumerate(_XYZ):
        cols[_c(tag, f"velocity.linear_velocity.{a}")] = [float(im.velocity_linear[k]) for _, im in rows]
    for k, a in enumerate(_XYZ):
        cols[_c(tag, f"velocity.angular_velocity.{a}")] = [float(im.velocity_angular[k]) for _, im in rows]
    cols[_c(tag, "pose_timestamp")] = [im.pose_timestamp for _, im in rows]
    cols[_c(tag, "rolling_shutter_params.shutter")] = [im.shutter for _, im in rows]
    cols[_c(tag, "rolling_shutter_params.camera_trigger_time")] = [im.trigger_time for _, im in rows]
    cols[_c(tag, "rolling_shutter_params.camera_readout_done_time")] = [
        im.readout_done_time for _, im in rows
    ]
    return cols


def _camera_segmentation_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "camera_segmentation"
    rows = [(f, im) for f in frames for im in f.images if im.panoptic_label is not None]
    maps = [im.instance_to_global for _, im in rows]
    return {
        _SEG: [f.segment for f, _ in rows],
        _TS: [f.timestamp_micros for f, _ in rows],
        _CAM: [_name(im.name, CAMERA_NAMES, style) for _, im in rows],
        _c(tag, "panoptic_label_divisor"): [im.panoptic_label_divisor for _, im in rows],
        _c(tag, "panoptic_label"): [im.panoptic_label for _, im in rows],
        _c(tag, f"{_MAPPING}.local_instance_ids"): [np.array(list(m), np.int32) for m in maps],
        _c(tag, f"{_MAPPING}.global_instance_ids"): [np.array(list(m.values()), np.int32) for m in maps],
        _c(tag, f"{_MAPPING}.is_tracked"): [np.ones(len(m), bool) for m in maps],
        _c(tag, "sequence_id"): [f.segment for f, _ in rows],
        _c(tag, "num_cameras_covered"): [None for _ in rows],
    }


def _lidar_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "lidar"
    rows = [(f, la) for f in frames for la in f.lasers]
    cols: _Columns = {
        _SEG: [f.segment for f, _ in rows],
        _TS: [f.timestamp_micros for f, _ in rows],
        _LASER: [_name(la.name, LASER_NAMES, style) for _, la in rows],
    }
    for r in (1, 2):
        images = [getattr(la, f"return{r}") for _, la in rows]
        cols[_c(tag, f"range_image_return{r}.values")] = images
        cols[_c(tag, f"range_image_return{r}.shape")] = [None if im is None else im.shape for im in images]
    return cols


def _lidar_pose_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "lidar_pose"
    rows = [(f, la) for f in frames for la in f.lasers if la.pixel_pose is not None]
    return {
        _SEG: [f.segment for f, _ in rows],
        _TS: [f.timestamp_micros for f, _ in rows],
        _LASER: [_name(la.name, LASER_NAMES, style) for _, la in rows],
        _c(tag, "range_image_return1.values"): [la.pixel_pose for _, la in rows],
        _c(tag, "range_image_return1.shape"): [la.pixel_pose.shape for _, la in rows],  # type: ignore[union-attr]
    }


def _lidar_box_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "lidar_box"
    box = np.concatenate([np.asarray(f.labels.box, np.float64).reshape(-1, 7) for f in frames])
    speed = np.concatenate([np.asarray(f.labels.speed, np.float64).reshape(-1, 3) for f in frames])
    accel = np.concatenate([np.asarray(f.labels.accel, np.float64).reshape(-1, 3) for f in frames])
    cols: _Columns = {
        _SEG: [f.segment for f in frames for _ in range(len(f.labels))],
        _TS: [f.timestamp_micros for f in frames for _ in range(len(f.labels))],
        _OBJ: [i for f in frames for i in f.labels.ids],
    }
    for k, a in enumerate(_XYZ):
        cols[_c(tag, f"box.center.{a}")] = box[:, k]
        cols[_c(tag, f"box.size.{a}")] = box[:, 3 + k]
    cols[_c(tag, "box.heading")] = box[:, 6]
    cols[_c(tag, "type")] = np.concatenate([f.labels.types for f in frames])
    for key, attr in (
        ("num_lidar_points_in_box", "num_lidar_points"),
        ("num_top_lidar_points_in_box", "num_top_lidar_points"),
    ):
        counts = np.concatenate([getattr(f.labels, attr) for f in frames]).astype(np.int64)
        cols[_c(tag, key)] = [None if n < 0 else int(n) for n in counts]
    for k, a in enumerate(_XYZ):
        cols[_c(tag, f"speed.{a}")] = speed[:, k]
        cols[_c(tag, f"acceleration.{a}")] = accel[:, k]
    cols[_c(tag, "difficulty_level.detection")] = [None] * len(box)
    cols[_c(tag, "difficulty_level.tracking")] = [None] * len(box)
    return cols


def _projected_lidar_box_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "projected_lidar_box"
    box = np.concatenate([np.asarray(f.projected_boxes.box, np.float64).reshape(-1, 4) for f in frames])
    n_rows = [len(f.projected_boxes.ids) for f in frames]
    cols: _Columns = {
        _SEG: [f.segment for f, n in zip(frames, n_rows, strict=True) for _ in range(n)],
        _TS: [f.timestamp_micros for f, n in zip(frames, n_rows, strict=True) for _ in range(n)],
        _CAM: [_name(int(c), CAMERA_NAMES, style) for f in frames for c in f.projected_boxes.camera],
        _OBJ: [i for f in frames for i in f.projected_boxes.ids],
    }
    for k, key in enumerate(("center.x", "center.y", "size.x", "size.y")):
        cols[_c(tag, f"box.{key}")] = box[:, k]
    cols[_c(tag, "type")] = np.concatenate([f.projected_boxes.types for f in frames])
    return cols


def _stats_rows(frames: Sequence[RawFrame], style: _Style) -> _Columns:
    tag = "stats"
    cols: _Columns = {_SEG: [f.segment for f in frames], _TS: [f.timestamp_micros for f in frames]}
    for key in ("time_of_day", "location", "weather"):
        cols[_c(tag, key)] = [f.stats.get(key) for f in frames]
    counted = [np.unique(np.asarray(f.labels.types, np.int32), return_counts=True) for f in frames]
    cols[_c(tag, "lidar_object_counts.types")] = [t for t, _ in counted]
    cols[_c(tag, "lidar_object_counts.counts")] = [c for _, c in counted]
    cols[_c(tag, "camera_object_counts.types")] = [None] * len(frames)
    cols[_c(tag, "camera_object_counts.counts")] = [None] * len(frames)
    return cols


_ROW_BUILDERS: dict[str, Callable[[Sequence[RawFrame], _Style], _Columns]] = {
    "vehicle_pose": _vehicle_pose_rows,
    "camera_calibration": _camera_calibration_rows,
    "lidar_calibration": _lidar_calibration_rows,
    "camera_image": _camera_image_rows,
    "camera_segmentation": _camera_segmentation_rows,
    "lidar": _lidar_rows,
    "lidar_pose": _lidar_pose_rows,
    "lidar_box": _lidar_box_rows,
    "projected_lidar_box": _projected_lidar_box_rows,
    "stats": _stats_rows,
}


def _list_array(rows: Sequence[Any], type_: pa.DataType) -> pa.Array:
    """A list (or fixed-size list) array from per-row array-likes or None, without per-value loops."""
    arrays = [None if r is None else np.ravel(np.asarray(r)) for r in rows]
    mask = np.array([a is None for a in arrays], bool)
    value_type = type_.value_type
    if pa.types.is_fixed_size_list(type_):
        size = type_.list_size
        filled = [np.zeros(size) if a is None else a for a in arrays]
        flat = np.concatenate(filled) if filled else np.zeros(0)
        if flat.size != size * len(rows):
            raise ValueError(f"every row of a {type_} column needs {size} values")
        values = pa.array(flat.astype(value_type.to_pandas_dtype()), type=value_type)
        return pa.FixedSizeListArray.from_arrays(values, size, mask=pa.array(mask))
    lengths = np.array([0 if a is None else a.size for a in arrays], np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    present = [a for a in arrays if a is not None]
    flat = np.concatenate(present) if present else np.zeros(0)
    values = pa.array(flat.astype(value_type.to_pandas_dtype()), type=value_type)
    return pa.ListArray.from_arrays(pa.array(offsets), values, type=type_, mask=pa.array(mask))


def _table(columns: _Columns, schema: pa.Schema) -> pa.Table:
    arrays = []
    for field in schema:
        values = columns[field.name]
        if pa.types.is_list(field.type) or pa.types.is_fixed_size_list(field.type):
            arrays.append(_list_array(values, field.type))
        else:
            arrays.append(pa.array(values, type=field.type))
    return pa.Table.from_arrays(arrays, schema=schema)


def _write_atomic(path: Path, schema: pa.Schema, tables: Sequence[pa.Table]) -> None:
    """Writes the non-empty ``tables`` (one row group each) to a temporary file, then renames it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with pq.ParquetWriter(tmp, schema) as writer:
            for table in tables:
                if table.num_rows:
                    writer.write_table(table, row_group_size=table.num_rows)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _tags_to_write(frames: Sequence[RawFrame]) -> list[str]:
    tags = ["vehicle_pose", "camera_calibration", "camera_image"]
    if any(im.panoptic_label is not None for f in frames for im in f.images):
        tags.append("camera_segmentation")
    if any(f.lasers or f.laser_calibrations for f in frames):
        tags += ["lidar_calibration", "lidar", "lidar_pose"]
    tags.append("lidar_box")
    if any(len(f.projected_boxes.ids) for f in frames):
        tags.append("projected_lidar_box")
    if any(f.stats for f in frames):
        tags.append("stats")
    return tags


def write_v2(
    root: Path,
    frames: Sequence[RawFrame],
    *,
    camera_names_as_strings: bool = False,
    transforms_float32: bool = False,
    frames_per_row_group: int = FRAMES_PER_ROW_GROUP,
) -> list[Path]:
    """Writes ``frames`` as a Waymo v2 root: one file per component per segment, atomically.

    Frames are written in the given order, ``frames_per_row_group`` frames per row group;
    calibrations come from each segment's first frame. Optional components (camera_segmentation,
    projected_lidar_box, stats, and the LiDAR ones) are written for every segment when any frame has
    such data. The declared schema is used (int8 names, fixed_size_list<double>[16] transforms)
    unless ``camera_names_as_strings`` (camera and LiDAR names as "FRONT", "TOP", ...) or
    ``transforms_float32`` (float32 transforms) reproduce the quirks of real files.

    Returns:
        The paths written.
    """
    if frames_per_row_group < 1:
        raise ValueError(f"frames_per_row_group must be >= 1, got {frames_per_row_group}")
    root, style = Path(root), _Style(camera_names_as_strings, transforms_float32)
    segments: dict[str, list[RawFrame]] = {}
    for f in frames:
        segments.setdefault(f.segment, []).append(f)
    written = []
    for tag in _tags_to_write(frames):
        schema = _schema(tag, style)
        for segment, seg_frames in segments.items():
            step = len(seg_frames) if tag in _STATIC else frames_per_row_group
            chunks = [seg_frames[i : i + step] for i in range(0, len(seg_frames), step)]
            tables = [_table(_ROW_BUILDERS[tag](chunk, style), schema) for chunk in chunks]
            path = root / tag / f"{segment}.parquet"
            _write_atomic(path, schema, tables)
            written.append(path)
    return written
