"""The few Waymo v1 protobuf messages the reader needs, declared from their field numbers.

The messages are built at import time in a private descriptor pool from the table below (the
field numbers and types of ``dataset.proto`` and ``label.proto``, package ``waymo.open_dataset``,
proto2), so neither TensorFlow, nor the Waymo devkit, nor generated ``_pb2`` files are needed, and
an installed devkit cannot clash with these. Enum fields are declared as int32 (same wire format;
unknown codes stay readable). Fields the toolkit does not use are left out: the parser keeps them
as unknown fields.

:func:`decode_matrix` reads a serialized ``MatrixFloat`` / ``MatrixInt32`` straight into numpy
(the packed data is one contiguous run of little-endian values), falling back to the protobuf
parser for unusual encodings.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from numpy.typing import NDArray

_T = descriptor_pb2.FieldDescriptorProto
_TYPES = {
    "double": _T.TYPE_DOUBLE,
    "float": _T.TYPE_FLOAT,
    "int32": _T.TYPE_INT32,
    "int64": _T.TYPE_INT64,
    "bool": _T.TYPE_BOOL,
    "string": _T.TYPE_STRING,
    "bytes": _T.TYPE_BYTES,
}
_PACKAGE = "waymo.open_dataset"

# message -> [(field name, number, type or message name, label)]; label: "" optional, "*" repeated,
# "*p" repeated packed.
_MESSAGES: dict[str, list[tuple[str, int, str, str]]] = {
    "MatrixShape": [("dims", 1, "int32", "*")],
    "MatrixFloat": [("data", 1, "float", "*p"), ("shape", 2, "MatrixShape", "")],
    "MatrixInt32": [("data", 1, "int32", "*p"), ("shape", 2, "MatrixShape", "")],
    "Transform": [("transform", 1, "double", "*")],
    "Velocity": [
        ("v_x", 1, "float", ""),
        ("v_y", 2, "float", ""),
        ("v_z", 3, "float", ""),
        ("w_x", 4, "double", ""),
        ("w_y", 5, "double", ""),
        ("w_z", 6, "double", ""),
    ],
    "CameraCalibration": [
        ("name", 1, "int32", ""),
        ("intrinsic", 2, "double", "*"),
        ("extrinsic", 3, "Transform", ""),
        ("width", 4, "int32", ""),
        ("height", 5, "int32", ""),
        ("rolling_shutter_direction", 6, "int32", ""),
    ],
    "LaserCalibration": [
        ("name", 1, "int32", ""),
        ("beam_inclinations", 2, "double", "*"),
        ("beam_inclination_min", 3, "double", ""),
        ("beam_inclination_max", 4, "double", ""),
        ("extrinsic", 5, "Transform", ""),
    ],
    "Stats": [("time_of_day", 2, "string", ""), ("location", 3, "string", ""), ("weather", 4, "string", "")],
    "Context": [
        ("name", 1, "string", ""),
        ("camera_calibrations", 2, "CameraCalibration", "*"),
        ("laser_calibrations", 3, "LaserCalibration", "*"),
        ("stats", 4, "Stats", ""),
    ],
    "RangeImage": [
        ("range_image_compressed", 2, "bytes", ""),
        ("camera_projection_compressed", 3, "bytes", ""),
        ("range_image_pose_compressed", 4, "bytes", ""),
        ("range_image_flow_compressed", 5, "bytes", ""),
        ("segmentation_label_compressed", 6, "bytes", ""),
    ],
    "InstanceIDToGlobalIDMapping": [
        ("local_instance_id", 1, "int32", ""),
        ("global_instance_id", 2, "int32", ""),
        ("is_tracked", 3, "bool", ""),
    ],
    "CameraSegmentationLabel": [
        ("panoptic_label_divisor", 1, "int32", ""),
        ("panoptic_label", 2, "bytes", ""),
        ("instance_id_to_global_id_mapping", 3, "InstanceIDToGlobalIDMapping", "*"),
        ("sequence_id", 4, "string", ""),
        ("num_cameras_covered", 5, "bytes", ""),
    ],
    "CameraImage": [
        ("name", 1, "int32", ""),
        ("image", 2, "bytes", ""),
        ("pose", 3, "Transform", ""),
        ("velocity", 4, "Velocity", ""),
        ("pose_timestamp", 5, "double", ""),
        ("shutter", 6, "double", ""),
        ("camera_trigger_time", 7, "double", ""),
        ("camera_readout_done_time", 8, "double", ""),
        ("camera_segmentation_label", 10, "CameraSegmentationLabel", ""),
    ],
    "Laser": [
        ("name", 1, "int32", ""),
        ("ri_return1", 2, "RangeImage", ""),
        ("ri_return2", 3, "RangeImage", ""),
    ],
    "Box": [
        ("center_x", 1, "double", ""),
        ("center_y", 2, "double", ""),
        ("center_z", 3, "double", ""),
        ("width", 4, "double", ""),
        ("length", 5, "double", ""),
        ("height", 6, "double", ""),
        ("heading", 7, "double", ""),
    ],
    "Metadata": [
        ("speed_x", 1, "double", ""),
        ("speed_y", 2, "double", ""),
        ("accel_x", 3, "double", ""),
        ("accel_y", 4, "double", ""),
        ("speed_z", 5, "double", ""),
        ("accel_z", 6, "double", ""),
    ],
    "Label": [
        ("box", 1, "Box", ""),
        ("metadata", 2, "Metadata", ""),
        ("type", 3, "int32", ""),
        ("id", 4, "string", ""),
        ("detection_difficulty_level", 5, "int32", ""),
        ("tracking_difficulty_level", 6, "int32", ""),
        ("num_lidar_points_in_box", 7, "int32", ""),
        ("num_top_lidar_points_in_box", 13, "int32", ""),
    ],
    "CameraLabels": [("name", 1, "int32", ""), ("labels", 2, "Label", "*")],
    "Frame": [
        ("context", 1, "Context", ""),
        ("timestamp_micros", 2, "int64", ""),
        ("pose", 3, "Transform", ""),
        ("images", 4, "CameraImage", "*"),
        ("lasers", 5, "Laser", "*"),
        ("laser_labels", 6, "Label", "*"),
        ("camera_labels", 8, "CameraLabels", "*"),
        ("projected_lidar_labels", 9, "CameraLabels", "*"),
    ],
}


def _build() -> dict[str, Any]:
    file = descriptor_pb2.FileDescriptorProto(
        name="phigenesis/waymo_v1_subset.proto", package=_PACKAGE, syntax="proto2"
    )
    for msg_name, fields in _MESSAGES.items():
        msg = file.message_type.add(name=msg_name)
        for name, number, kind, label in fields:
            f = msg.field.add(name=name, number=number)
            f.label = _T.LABEL_REPEATED if label.startswith("*") else _T.LABEL_OPTIONAL
            if kind in _TYPES:
                f.type = _TYPES[kind]
            else:
                f.type = _T.TYPE_MESSAGE
                f.type_name = f".{_PACKAGE}.{kind}"
            if label == "*p":
                f.options.packed = True
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file)
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.{name}"))
        for name in _MESSAGES
    }


_CLASSES = _build()
Frame = _CLASSES["Frame"]
MatrixFloat = _CLASSES["MatrixFloat"]
MatrixInt32 = _CLASSES["MatrixInt32"]
Label = _CLASSES["Label"]
Transform = _CLASSES["Transform"]


def read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    """(value, position after it) of the protobuf varint at ``buf[pos]``; raises ValueError for one
    longer than 10 bytes (64 bits) and IndexError where ``buf`` ends inside it."""
    value = shift = 0
    while shift < 70:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, pos
        shift += 7
    raise ValueError("varint longer than 10 bytes")


_varint = read_varint


def _int32(value: int) -> int:
    """A varint as the int32 it encodes (negative int32s are sign-extended to 64 bits)."""
    return value - (1 << 64) if value >= 1 << 63 else value


def decode_matrix(serialized: bytes, dtype: type, what: str) -> NDArray:
    """A serialized MatrixFloat (``dtype`` float32) or MatrixInt32 (int32) as an array of its shape.

    Fast path for floats: the usual encoding (one packed run of fixed 4-byte values, and the shape)
    is read with ``np.frombuffer``. Anything else (and int32, whose packed values are varints) goes
    through the protobuf parser. ``what`` names the matrix in errors.
    """
    itemsize = np.dtype(dtype).itemsize
    try:
        if np.dtype(dtype) != np.float32:
            raise ValueError("int32 matrices are varint-packed")
        pos, n = 0, len(serialized)
        data: NDArray | None = None
        dims: list[int] = []
        while pos < n:
            key, pos = _varint(serialized, pos)
            if key == 0x0A and data is None:  # field 1, length-delimited: the packed run
                size, pos = _varint(serialized, pos)
                if size % itemsize or pos + size > n:
                    raise ValueError("packed data is not whole values")
                data = np.frombuffer(serialized, dtype="<f4", count=size // itemsize, offset=pos)
                pos += size
            elif key == 0x12:  # field 2: MatrixShape
                size, pos = _varint(serialized, pos)
                end = pos + size
                while pos < end:
                    k, pos = _varint(serialized, pos)
                    if k == 0x08:  # dims, unpacked varint
                        v, pos = _varint(serialized, pos)
                        dims.append(_int32(v))
                    elif k == 0x0A:  # dims, packed
                        sz, pos = _varint(serialized, pos)
                        stop = pos + sz
                        while pos < stop:
                            v, pos = _varint(serialized, pos)
                            dims.append(_int32(v))
                    else:
                        raise ValueError("unexpected field in MatrixShape")
            else:
                raise ValueError("unexpected field")
        if data is None:
            data = np.zeros(0, dtype)
    except (ValueError, IndexError):
        msg = (MatrixFloat if np.dtype(dtype) == np.float32 else MatrixInt32)()
        try:
            msg.ParseFromString(serialized)
        except Exception as e:
            raise ValueError(f"{what}: not a valid matrix message ({e})") from e
        data = np.asarray(msg.data, dtype=dtype)
        dims = list(msg.shape.dims)
    if not dims or any(d < 0 or d > max(data.size, 1) for d in dims) or math.prod(dims) != data.size:
        raise ValueError(f"{what}: matrix shape {dims} does not hold its {data.size} values")
    return data.astype(dtype, copy=False).reshape(dims)


def encode_matrix(values: NDArray) -> bytes:
    """Serializes an array as MatrixFloat (float dtypes, stored as float32) or MatrixInt32."""
    values = np.asarray(values)
    if not np.issubdtype(values.dtype, np.floating):
        msg = MatrixInt32()
        msg.data.extend(values.astype(np.int32).ravel().tolist())
        msg.shape.dims.extend(int(d) for d in values.shape)
        return msg.SerializeToString()
    msg = MatrixFloat()
    msg.shape.dims.extend(int(d) for d in values.shape)
    # Building the packed run of fixed 4-byte floats directly is much faster than extending the
    # repeated field; field order does not matter on the wire.
    packed = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return _length_delimited(1, packed) + msg.SerializeToString()


def _length_delimited(field_number: int, payload: bytes) -> bytes:
    return _encode_varint((field_number << 3) | 2) + _encode_varint(len(payload)) + payload


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        b = value & 0x7F
        value >>= 7
        if value:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)
