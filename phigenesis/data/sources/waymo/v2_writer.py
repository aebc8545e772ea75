"""Waymo Open Dataset v2 (Parquet) writer: :func:`write_v2` writes the records of :mod:`.raw` as a
v2 root, one file per component per segment, atomically, in the declared schema or with the quirks
of real files (names as strings, float32 transforms). The synthetic source's Waymo export uses it,
so that the reader (:mod:`.v2`) is tested end to end against known answers.

Frames and units are Waymo's own (:mod:`.raw`): 4x4 float64 ``target_from_source`` transforms,
metres, radians, microseconds for frame timestamps.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from phigenesis.data.sources.waymo.raw import (
    CAMERA_NAMES,
    LASER_NAMES,
    RawFrame,
)
from phigenesis.data.sources.waymo.v2_schema import (
    _CAM,
    _INTRINSICS,
    _LASER,
    _MAPPING,
    _OBJ,
    _SEG,
    _STATIC,
    _TS,
    _XYZ,
    FRAMES_PER_ROW_GROUP,
    _c,
    _schema,
    _Style,
)

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
