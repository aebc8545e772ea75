"""Waymo Open Dataset v2 (Parquet): the declared schema of every component this toolkit reads and
writes, its column names (``key.<field>``, ``[ComponentClass].<path>``; the components of
https://github.com/waymo-research/waymo-open-dataset, ``src/waymo_open_dataset/v2/``), and which
columns the reader requires and which it takes if present.

Shared by the reader (:mod:`.v2`) and the writer (:mod:`.v2_writer`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import pyarrow as pa

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
