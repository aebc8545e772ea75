"""Waymo v1: TFRecord files of ``Frame`` protos <-> :class:`~.raw.RawFrame`.

A v1 file holds one segment (about 200 frames at 10 Hz). :class:`V1File` indexes a file's records
from their headers and parses frames on demand; :func:`parse_frame` turns one record into a
:class:`RawFrame` (range images decompressed and decoded), :func:`serialize_frame` does the
reverse (range images compressed with zlib as the dataset does), for the test writers.

:class:`V1Segment` is what the source reads: the file's records with the frame-level fields
(``Frame.timestamp_micros`` and ``Frame.pose``) of every record read once from its top-level
fields, without parsing the rest, so that poses and time order are checked before any frame is
converted, and under ``--on-error skip`` a record with an invalid time or pose is left out of the
scene from the start.

Nothing here allocates more than the input declares: a range image inflates to at most
:data:`MAX_MATRIX_BYTES` (a few bytes of zlib can expand to gigabytes), and the protobuf
messages themselves are bounded by their record's length.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.records import InvalidRecord, check_transform
from phigenesis.data.sources.waymo import protos, tfrecord
from phigenesis.data.sources.waymo.raw import (
    CAMERA_NAMES,
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

#: Largest serialized matrix a compressed range image, pixel pose or projection may inflate to,
#: bytes: four times the largest in Waymo's data (TOP's pixel pose, 64 x 2650 x 6 float32 = 4 MB).
MAX_MATRIX_BYTES = 16 << 20


def _transform(msg: object, what: str) -> NDArray[np.float64]:
    values = np.asarray(msg.transform, dtype=np.float64)  # type: ignore[attr-defined]
    if values.size != 16:
        raise WaymoFormatError(f"{what}: transform has {values.size} values, expected 16")
    return values.reshape(4, 4)


def _declared_data_bytes(head: bytes) -> int | None:
    """The length a serialized matrix's first field declares for its packed data run, or None
    if the message does not start with one (other encodings are bounded by the cap alone)."""
    try:
        key, pos = protos.read_varint(head, 0)
        if key != 0x0A:  # field 1 (data), length-delimited
            return None
        length, _ = protos.read_varint(head, pos)
    except (ValueError, IndexError):
        return None
    return length


#: The zlib trailer: the Adler-32 of the inflated data.
_ADLER32_BYTES = 4


def _zlib_header_error(compressed: bytes) -> str | None:
    """What is wrong with the 2-byte zlib header (RFC 1950) of ``compressed``, or None."""
    if len(compressed) < 2 + _ADLER32_BYTES:
        return f"{len(compressed)} bytes are too few for a zlib stream"
    cmf, flg = compressed[0], compressed[1]
    if cmf & 0x0F != 8 or cmf >> 4 > 7:
        return "the zlib header names no deflate stream"
    if (cmf << 8 | flg) % 31:
        return "the zlib header's check bits are wrong"
    if flg & 0x20:
        return "the zlib stream needs a preset dictionary"
    return None


def inflate_matrix(compressed: bytes, what: str, adler32: bool = True) -> bytes:
    """The zlib stream of a compressed matrix, decompressed to at most :data:`MAX_MATRIX_BYTES`.

    ``adler32=False`` inflates the deflate data inside the zlib framing without recomputing the
    Adler-32 of the output (a tenth of the v1 reader's time with the system zlib): for a record
    whose CRC-32C was checked, which already covers these compressed bytes. The header is
    checked and the trailer must be there either way.

    Raises :class:`WaymoFormatError` naming ``what`` if the stream is not zlib, ends early, its
    data run declares more than the cap, or it inflates beyond it.
    """
    if not adler32 and (problem := _zlib_header_error(compressed)) is not None:
        raise WaymoFormatError(f"{what}: range image does not decompress ({problem})")
    # Raw deflate (negative window bits) starts after the 2-byte header.
    wbits, body = (zlib.MAX_WBITS, compressed) if adler32 else (-zlib.MAX_WBITS, memoryview(compressed)[2:])
    try:
        # The first bytes say how much data the matrix declares: refuse before inflating the rest.
        declared = _declared_data_bytes(zlib.decompressobj(wbits).decompress(body, 16))
        if declared is not None and declared > MAX_MATRIX_BYTES:
            raise WaymoFormatError(
                f"{what}: the matrix declares {declared} bytes of data, more than the {MAX_MATRIX_BYTES} "
                "a range image can hold"
            )
        # Then the whole stream again from its start, into one buffer (inflating the rest after
        # the head would cost a copy of the matrix to join the two).
        inflater = zlib.decompressobj(wbits)
        data = inflater.decompress(body, MAX_MATRIX_BYTES + 1)
    except zlib.error as e:
        raise WaymoFormatError(f"{what}: range image does not decompress ({e})") from None
    if len(data) > MAX_MATRIX_BYTES:
        raise WaymoFormatError(
            f"{what}: range image inflates beyond {MAX_MATRIX_BYTES} bytes from {len(compressed)} "
            "compressed bytes (refused: a decompression bomb or a corrupt stream)"
        )
    if not inflater.eof or (not adler32 and len(inflater.unused_data) < _ADLER32_BYTES):
        raise WaymoFormatError(f"{what}: range image does not decompress (the zlib stream is truncated)")
    return data


def _matrix(compressed: bytes, dtype: type, what: str, adler32: bool = True) -> NDArray | None:
    if not compressed:
        return None
    serialized = inflate_matrix(compressed, what, adler32)
    try:
        return protos.decode_matrix(serialized, dtype, what)
    except ValueError as e:
        raise WaymoFormatError(str(e)) from e


def _labels(labels: list) -> RawLabels:
    m = len(labels)
    box = np.empty((m, 7))
    speed = np.zeros((m, 3))
    accel = np.zeros((m, 3))
    types = np.empty(m, np.int32)
    n_points = np.full(m, -1, np.int32)
    n_top = np.full(m, -1, np.int32)
    ids = []
    for i, lab in enumerate(labels):
        b = lab.box
        box[i] = (b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading)
        md = lab.metadata
        speed[i] = (md.speed_x, md.speed_y, md.speed_z)
        accel[i] = (md.accel_x, md.accel_y, md.accel_z)
        types[i] = lab.type
        if lab.HasField("num_lidar_points_in_box"):
            n_points[i] = lab.num_lidar_points_in_box
        if lab.HasField("num_top_lidar_points_in_box"):
            n_top[i] = lab.num_top_lidar_points_in_box
        ids.append(lab.id)
    return RawLabels(ids, types, box, speed, accel, n_points, n_top)


def _projected(camera_labels: list) -> RawProjectedBoxes:
    cams, ids, boxes, types = [], [], [], []
    for cl in camera_labels:
        suffix = "_" + CAMERA_NAMES.get(cl.name, str(cl.name))
        for lab in cl.labels:
            b = lab.box
            cams.append(cl.name)
            # Ids are "<laser label id>_<CAMERA>"; strip the camera as a whole (ids contain '_').
            ids.append(lab.id[: -len(suffix)] if lab.id.endswith(suffix) else lab.id)
            boxes.append((b.center_x, b.center_y, b.length, b.width))
            types.append(lab.type)
    return RawProjectedBoxes(
        np.array(cams, np.int32), ids, np.array(boxes, np.float64).reshape(-1, 4), np.array(types, np.int32)
    )


def _camera_name(code: int) -> str:
    return CAMERA_NAMES.get(code, f"CAMERA_{code}")


def _laser_name(code: int) -> str:
    return LASER_NAMES.get(code, f"LIDAR_{code}")


def _camera_calibrations(ctx: object, raw: RawFrame, where: str) -> None:
    """Reads Context.camera_calibrations into ``raw``; a camera whose calibration cannot be read
    (or is given twice) is marked invalid, not dropped."""
    seen: set[int] = set()
    for c in ctx.camera_calibrations:  # type: ignore[attr-defined]
        what = f"{where}: camera {_camera_name(c.name)} calibration"
        if c.name in seen:
            error = WaymoFormatError(f"{what}: the camera is calibrated twice")
            raw.mark_invalid("camera_calibration", c.name, error)
            continue
        seen.add(c.name)
        try:
            intrinsic = np.asarray(c.intrinsic, np.float64)
            if intrinsic.size != 9:
                raise WaymoFormatError(f"{what}: {intrinsic.size} intrinsic values, expected 9")
            raw.camera_calibrations.append(
                RawCameraCalibration(
                    name=c.name,
                    intrinsic=intrinsic,
                    vehicle_from_camera=_transform(c.extrinsic, f"{what} extrinsic"),
                    width=c.width,
                    height=c.height,
                    rolling_shutter_direction=c.rolling_shutter_direction,
                )
            )
        except WaymoFormatError as e:
            raw.mark_invalid("camera_calibration", c.name, e)


def _laser_calibrations(ctx: object, raw: RawFrame, where: str) -> None:
    """Reads Context.laser_calibrations into ``raw``, marking unreadable or repeated ones invalid."""
    seen: set[int] = set()
    for c in ctx.laser_calibrations:  # type: ignore[attr-defined]
        what = f"{where}: LiDAR {_laser_name(c.name)} calibration"
        if c.name in seen:
            error = WaymoFormatError(f"{what}: the LiDAR is calibrated twice")
            raw.mark_invalid("laser_calibration", c.name, error)
            continue
        seen.add(c.name)
        try:
            raw.laser_calibrations.append(
                RawLaserCalibration(
                    name=c.name,
                    vehicle_from_laser=_transform(c.extrinsic, f"{what} extrinsic"),
                    beam_inclinations=np.asarray(c.beam_inclinations, np.float64)
                    if len(c.beam_inclinations)
                    else None,
                    beam_inclination_min=c.beam_inclination_min,
                    beam_inclination_max=c.beam_inclination_max,
                )
            )
        except WaymoFormatError as e:
            raw.mark_invalid("laser_calibration", c.name, e)


def _image(im: object, where: str) -> RawCameraImage:
    """One CameraImage message as a raw image (its pose checked for 16 values)."""
    seg = im.camera_segmentation_label if im.HasField("camera_segmentation_label") else None  # type: ignore[attr-defined]
    v = im.velocity  # type: ignore[attr-defined]
    return RawCameraImage(
        name=im.name,  # type: ignore[attr-defined]
        jpeg=im.image or None,  # type: ignore[attr-defined]
        global_from_vehicle=_transform(im.pose, f"{where}: camera {_camera_name(im.name)} pose"),  # type: ignore[attr-defined]
        velocity_linear=np.array([v.v_x, v.v_y, v.v_z], np.float64),
        velocity_angular=np.array([v.w_x, v.w_y, v.w_z], np.float64),
        pose_timestamp=im.pose_timestamp,  # type: ignore[attr-defined]
        shutter=im.shutter,  # type: ignore[attr-defined]
        trigger_time=im.camera_trigger_time,  # type: ignore[attr-defined]
        readout_done_time=im.camera_readout_done_time,  # type: ignore[attr-defined]
        panoptic_label=(seg.panoptic_label or None) if seg is not None else None,
        panoptic_label_divisor=seg.panoptic_label_divisor if seg is not None else 0,
        instance_to_global={
            m.local_instance_id: m.global_instance_id for m in seg.instance_id_to_global_id_mapping
        }
        if seg is not None
        else {},
    )


def _laser(laser: object, where: str, adler32: bool = True) -> RawLaser | None:
    """One Laser message's range images, decoded (None for a laser listed without any;
    ``adler32``: see :func:`inflate_matrix`)."""
    what = f"{where}: LiDAR {_laser_name(laser.name)}"  # type: ignore[attr-defined]
    r1 = laser.ri_return1  # type: ignore[attr-defined]
    r2 = laser.ri_return2  # type: ignore[attr-defined]
    ret1 = _matrix(r1.range_image_compressed, np.float32, f"{what} return 1", adler32)
    ret2 = _matrix(r2.range_image_compressed, np.float32, f"{what} return 2", adler32)
    pose = _matrix(r1.range_image_pose_compressed, np.float32, f"{what} pixel pose", adler32)
    if ret1 is None and ret2 is None:
        return None  # camera-only data: lasers are listed with no range images
    for name, arr, ch in (("return 1", ret1, 4), ("return 2", ret2, 4), ("pixel pose", pose, 6)):
        if arr is not None and (arr.ndim != 3 or arr.shape[2] != ch):
            raise WaymoFormatError(f"{what} {name}: shape {arr.shape}, expected (H, W, {ch})")
    return RawLaser(laser.name, ret1, ret2, pose)  # type: ignore[attr-defined]


def parse_frame(data: bytes, where: str, crc_checked: bool = False) -> RawFrame:
    """One serialized ``Frame`` as a :class:`RawFrame`; ``where`` (file and offset) names it in errors.

    ``crc_checked``: the record's CRC-32C was checked, so the range images' zlib streams are
    inflated without recomputing their Adler-32 (see :func:`inflate_matrix`).

    Raises for what makes the whole record unusable (not a Frame, no pose, context or timestamp);
    what is wrong with one camera or one LiDAR (a calibration or image pose without 16 values, a
    range image that does not decompress, a repeated message) goes into ``invalid_sensors``.
    """
    frame = protos.Frame()
    try:
        frame.ParseFromString(data)
    except Exception as e:
        raise WaymoFormatError(f"{where}: not a Waymo Frame protobuf ({e})") from e
    if not frame.HasField("pose") or not frame.HasField("context"):
        raise WaymoFormatError(f"{where}: record has no frame pose or context; not a Waymo v1 Frame")
    if not frame.HasField("timestamp_micros"):
        raise WaymoFormatError(f"{where}: record has no Frame.timestamp_micros")
    ctx = frame.context
    stats = ctx.stats
    raw = RawFrame(
        segment=ctx.name,
        timestamp_micros=frame.timestamp_micros,
        global_from_vehicle=_transform(frame.pose, f"{where}: frame pose"),
        camera_calibrations=[],
        laser_calibrations=[],
        images=[],
        lasers=[],
        labels=_labels(list(frame.laser_labels)),
        projected_boxes=_projected(list(frame.projected_lidar_labels)),
        stats={"time_of_day": stats.time_of_day, "location": stats.location, "weather": stats.weather},
        where=where,
    )
    _camera_calibrations(ctx, raw, where)
    _laser_calibrations(ctx, raw, where)
    for im in frame.images:
        try:
            raw.images.append(_image(im, where))
        except WaymoFormatError as e:
            raw.mark_invalid("camera", im.name, e)
    for laser in frame.lasers:
        if any(las.name == laser.name for las in raw.lasers):
            error = WaymoFormatError(f"{where}: LiDAR {_laser_name(laser.name)} has two Laser messages")
            raw.mark_invalid("laser", laser.name, error)
            continue
        try:
            decoded = _laser(laser, where, adler32=not crc_checked)
        except WaymoFormatError as e:
            raw.mark_invalid("laser", laser.name, e)
            continue
        if decoded is not None:
            raw.lasers.append(decoded)
    return raw


# --------------------------------------------------------------------------------------------
# Frame keys: what the index reads of each record without parsing it


class _NotScannable(Exception):
    """The record's top level is not plain wire format; the full parser decides."""


_WIRE_VARINT, _WIRE_I64, _WIRE_LEN, _WIRE_I32 = 0, 1, 2, 5
_FIELD_TIMESTAMP, _FIELD_POSE = 2, 3


def _scan_top_level(f: BinaryIO, span: tfrecord.RecordSpan) -> tuple[int | None, bytes | None]:
    """(last Frame.timestamp_micros, concatenated Frame.pose payloads) from the top-level fields
    of the record at ``span``, skipping every other field by its length (a few small reads per
    field; the images and range images are never read). As protobuf does, the last timestamp
    wins and repeated pose messages merge. Raises _NotScannable for anything but plain fields."""
    pos, end = span.data_offset, span.data_offset + span.length
    timestamp: int | None = None
    pose: bytes | None = None
    while pos < end:
        f.seek(pos)
        head = f.read(min(22, end - pos))
        try:
            key, n = protos.read_varint(head, 0)
            wire, number = key & 7, key >> 3
            if wire == _WIRE_VARINT:
                value, n = protos.read_varint(head, n)
                if number == _FIELD_TIMESTAMP:
                    timestamp = value - (1 << 64) if value >= 1 << 63 else value
                pos += n
            elif wire == _WIRE_I64:
                pos += n + 8
            elif wire == _WIRE_I32:
                pos += n + 4
            elif wire == _WIRE_LEN:
                length, n = protos.read_varint(head, n)
                if number == _FIELD_POSE:
                    if pos + n + length > end:
                        raise _NotScannable
                    f.seek(pos + n)
                    pose = (pose or b"") + f.read(length)
                pos += n + length
            else:
                raise _NotScannable
        except (ValueError, IndexError):
            raise _NotScannable from None
        if number == 0 or pos > end:
            raise _NotScannable
    return timestamp, pose


def _key_by_parsing(data: bytes, where: str) -> tuple[int | None, bytes | None]:
    """(timestamp, serialized pose) of a record the scan could not read, from a full parse."""
    frame = protos.Frame()
    try:
        frame.ParseFromString(data)
    except Exception as e:
        raise WaymoFormatError(f"{where}: not a Waymo Frame protobuf ({e})") from e
    timestamp = frame.timestamp_micros if frame.HasField("timestamp_micros") else None
    return timestamp, frame.pose.SerializeToString() if frame.HasField("pose") else None


def read_frame_key(
    f: BinaryIO, path: Path, span: tfrecord.RecordSpan, where: str, check_crc: bool
) -> FrameKey:
    """The :class:`FrameKey` of the record at ``span`` of the open file ``f``.

    Reads the top-level fields only; a record whose top level is not plain wire format is read
    and parsed whole instead (the same answer as the parser's). Raises :class:`WaymoFormatError`
    naming ``where`` and the field if the record has no timestamp or pose, or an invalid pose.
    """
    try:
        timestamp, pose_bytes = _scan_top_level(f, span)
    except _NotScannable:
        timestamp, pose_bytes = _key_by_parsing(tfrecord.read_record(f, path, span, check_crc), where)
    if pose_bytes is None:
        raise WaymoFormatError(f"{where}: record has no frame pose or context; not a Waymo v1 Frame")
    if timestamp is None:
        raise WaymoFormatError(f"{where}: record has no Frame.timestamp_micros")
    pose = protos.Transform()
    try:
        pose.ParseFromString(pose_bytes)
    except Exception as e:
        raise WaymoFormatError(f"{where}: Frame.pose is not a Transform message ({e})") from e
    try:
        global_from_vehicle = check_transform("Frame.pose", _transform(pose, f"{where}: frame pose"))
    except InvalidRecord as e:
        raise WaymoFormatError(f"{where}: {e}") from None
    return FrameKey(int(timestamp), global_from_vehicle)


class V1File:
    """The frames of one v1 TFRecord file, parsed on demand.

    Opening reads only the record headers (checking their CRCs); :meth:`frame` reads, checks and
    parses one record. A corrupt header stops the index there (later offsets cannot be trusted):
    ``error`` then says where, and the frames before it stay readable.
    """

    def __init__(self, path: str | os.PathLike[str], check_crc: bool = True):
        self.path = Path(path)
        self.check_crc = check_crc
        self.error: str | None = None
        try:
            self.spans, error = tfrecord.scan_records(self.path)
            self.error = None if error is None else str(error)
        except OSError as e:
            raise WaymoFormatError(f"{self.path}: cannot read ({e.strerror or e})") from e

    def __len__(self) -> int:
        return len(self.spans)

    def where(self, index: int) -> str:
        return f"{self.path} (record {index} at byte {self.spans[index].offset})"

    def record(self, index: int) -> bytes:
        with open(self.path, "rb") as f:
            return tfrecord.read_record(f, self.path, self.spans[index], self.check_crc)

    def frame(self, index: int) -> RawFrame:
        return parse_frame(self.record(index), self.where(index), crc_checked=self.check_crc)

    def keys(self) -> list[FrameKey | WaymoFormatError]:
        """Every record's :class:`FrameKey`, or the error that makes the record unusable."""
        out: list[FrameKey | WaymoFormatError] = []
        try:
            with open(self.path, "rb") as f:
                for k, span in enumerate(self.spans):
                    try:
                        out.append(read_frame_key(f, self.path, span, self.where(k), self.check_crc))
                    except WaymoFormatError as e:
                        out.append(e)
        except OSError as e:
            raise WaymoFormatError(f"{self.path}: cannot read ({e.strerror or e})") from e
        return out


# --------------------------------------------------------------------------------------------
# Writing (for the synthetic exporter and tests)


def _set_transform(msg: object, matrix: NDArray) -> None:
    msg.transform.extend(np.asarray(matrix, np.float64).reshape(16).tolist())  # type: ignore[attr-defined]


def _compress(values: NDArray | None, level: int) -> bytes:
    return b"" if values is None else zlib.compress(protos.encode_matrix(values), level)


def serialize_frame(raw: RawFrame, zlib_level: int = 6) -> bytes:
    """A :class:`RawFrame` as a serialized v1 ``Frame`` (range images zlib-compressed)."""
    frame = protos.Frame()
    frame.timestamp_micros = raw.timestamp_micros
    _set_transform(frame.pose, raw.global_from_vehicle)
    ctx = frame.context
    ctx.name = raw.segment
    for key in ("time_of_day", "location", "weather"):
        if key in raw.stats:
            setattr(ctx.stats, key, raw.stats[key])
    for c in raw.camera_calibrations:
        m = ctx.camera_calibrations.add(name=c.name, width=c.width, height=c.height)
        m.rolling_shutter_direction = c.rolling_shutter_direction
        m.intrinsic.extend(np.asarray(c.intrinsic, np.float64).tolist())
        _set_transform(m.extrinsic, c.vehicle_from_camera)
    for c in raw.laser_calibrations:
        m = ctx.laser_calibrations.add(name=c.name)
        if c.beam_inclinations is not None:
            m.beam_inclinations.extend(np.asarray(c.beam_inclinations, np.float64).tolist())
        m.beam_inclination_min = c.beam_inclination_min
        m.beam_inclination_max = c.beam_inclination_max
        _set_transform(m.extrinsic, c.vehicle_from_laser)
    for im in raw.images:
        m = frame.images.add(name=im.name)
        if im.jpeg is not None:
            m.image = im.jpeg
        _set_transform(m.pose, im.global_from_vehicle)
        m.velocity.v_x, m.velocity.v_y, m.velocity.v_z = (float(x) for x in im.velocity_linear)
        m.velocity.w_x, m.velocity.w_y, m.velocity.w_z = (float(x) for x in im.velocity_angular)
        m.pose_timestamp = im.pose_timestamp
        m.shutter = im.shutter
        m.camera_trigger_time = im.trigger_time
        m.camera_readout_done_time = im.readout_done_time
        if im.panoptic_label is not None:
            seg = m.camera_segmentation_label
            seg.panoptic_label = im.panoptic_label
            seg.panoptic_label_divisor = im.panoptic_label_divisor
            for local, glob in sorted(im.instance_to_global.items()):
                seg.instance_id_to_global_id_mapping.add(local_instance_id=local, global_instance_id=glob)
    for laser in raw.lasers:
        m = frame.lasers.add(name=laser.name)
        m.ri_return1.range_image_compressed = _compress(laser.return1, zlib_level)
        if laser.pixel_pose is not None:
            m.ri_return1.range_image_pose_compressed = _compress(laser.pixel_pose, zlib_level)
        m.ri_return2.range_image_compressed = _compress(laser.return2, zlib_level)
    labels = raw.labels
    for i in range(len(labels)):
        lab = frame.laser_labels.add(id=labels.ids[i], type=int(labels.types[i]))
        cx, cy, cz, length, width, height, heading = (float(x) for x in labels.box[i])
        b = lab.box
        b.center_x, b.center_y, b.center_z = cx, cy, cz
        b.length, b.width, b.height, b.heading = length, width, height, heading
        md = lab.metadata
        md.speed_x, md.speed_y, md.speed_z = (float(x) for x in labels.speed[i])
        md.accel_x, md.accel_y, md.accel_z = (float(x) for x in labels.accel[i])
        if labels.num_lidar_points[i] >= 0:
            lab.num_lidar_points_in_box = int(labels.num_lidar_points[i])
        if labels.num_top_lidar_points[i] >= 0:
            lab.num_top_lidar_points_in_box = int(labels.num_top_lidar_points[i])
    proj = raw.projected_boxes
    for cam in sorted(set(proj.camera.tolist())):
        cl = frame.projected_lidar_labels.add(name=cam)
        for k in np.flatnonzero(proj.camera == cam):
            lab = cl.labels.add(
                id=f"{proj.ids[k]}_{CAMERA_NAMES.get(cam, str(cam))}", type=int(proj.types[k])
            )
            lab.box.center_x, lab.box.center_y, lab.box.length, lab.box.width = (
                float(x) for x in proj.box[k]
            )
    return frame.SerializeToString()
