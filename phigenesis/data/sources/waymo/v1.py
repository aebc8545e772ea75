"""Waymo v1: TFRecord files of ``Frame`` protos <-> :class:`~.raw.RawFrame`.

A v1 file holds one segment (about 200 frames at 10 Hz). :class:`V1File` indexes a file's records
from their headers and parses frames on demand; :func:`parse_frame` turns one record into a
:class:`RawFrame` (range images decompressed and decoded), :func:`serialize_frame` does the
reverse (range images compressed with zlib as the dataset does), for the test writers.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.sources.waymo import protos, tfrecord
from phigenesis.data.sources.waymo.raw import (
    CAMERA_NAMES,
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    RawProjectedBoxes,
    WaymoFormatError,
)


def _transform(msg: object, what: str) -> NDArray[np.float64]:
    values = np.asarray(msg.transform, dtype=np.float64)  # type: ignore[attr-defined]
    if values.size != 16:
        raise WaymoFormatError(f"{what}: transform has {values.size} values, expected 16")
    return values.reshape(4, 4)


def _matrix(compressed: bytes, dtype: type, what: str) -> NDArray | None:
    if not compressed:
        return None
    try:
        return protos.decode_matrix(zlib.decompress(compressed), dtype, what)
    except zlib.error as e:
        raise WaymoFormatError(f"{what}: range image does not decompress ({e})") from e
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


def parse_frame(data: bytes, where: str) -> RawFrame:
    """One serialized ``Frame`` as a :class:`RawFrame`; ``where`` (file and offset) names it in errors."""
    frame = protos.Frame()
    try:
        frame.ParseFromString(data)
    except Exception as e:
        raise WaymoFormatError(f"{where}: not a Waymo Frame protobuf ({e})") from e
    if not frame.HasField("pose") or not frame.HasField("context"):
        raise WaymoFormatError(f"{where}: record has no frame pose or context; not a Waymo v1 Frame")
    ctx = frame.context
    cam_cals = [
        RawCameraCalibration(
            name=c.name,
            intrinsic=np.asarray(c.intrinsic, np.float64),
            vehicle_from_camera=_transform(c.extrinsic, f"{where}: camera {c.name} extrinsic"),
            width=c.width,
            height=c.height,
            rolling_shutter_direction=c.rolling_shutter_direction,
        )
        for c in ctx.camera_calibrations
    ]
    for c in cam_cals:
        if c.intrinsic.size != 9:
            raise WaymoFormatError(f"{where}: camera {c.name} has {c.intrinsic.size} intrinsics, expected 9")
    laser_cals = [
        RawLaserCalibration(
            name=c.name,
            vehicle_from_laser=_transform(c.extrinsic, f"{where}: LiDAR {c.name} extrinsic"),
            beam_inclinations=np.asarray(c.beam_inclinations, np.float64)
            if len(c.beam_inclinations)
            else None,
            beam_inclination_min=c.beam_inclination_min,
            beam_inclination_max=c.beam_inclination_max,
        )
        for c in ctx.laser_calibrations
    ]
    images = []
    for im in frame.images:
        seg = im.camera_segmentation_label if im.HasField("camera_segmentation_label") else None
        v = im.velocity
        images.append(
            RawCameraImage(
                name=im.name,
                jpeg=im.image or None,
                global_from_vehicle=_transform(im.pose, f"{where}: camera {im.name} pose"),
                velocity_linear=np.array([v.v_x, v.v_y, v.v_z], np.float64),
                velocity_angular=np.array([v.w_x, v.w_y, v.w_z], np.float64),
                pose_timestamp=im.pose_timestamp,
                shutter=im.shutter,
                trigger_time=im.camera_trigger_time,
                readout_done_time=im.camera_readout_done_time,
                panoptic_label=(seg.panoptic_label or None) if seg is not None else None,
                panoptic_label_divisor=seg.panoptic_label_divisor if seg is not None else 0,
                instance_to_global={
                    m.local_instance_id: m.global_instance_id for m in seg.instance_id_to_global_id_mapping
                }
                if seg is not None
                else {},
            )
        )
    lasers = []
    for laser in frame.lasers:
        what = f"{where}: LiDAR {laser.name}"
        r1 = laser.ri_return1
        r2 = laser.ri_return2
        ret1 = _matrix(r1.range_image_compressed, np.float32, f"{what} return 1")
        ret2 = _matrix(r2.range_image_compressed, np.float32, f"{what} return 2")
        pose = _matrix(r1.range_image_pose_compressed, np.float32, f"{what} pixel pose")
        if ret1 is None and ret2 is None:
            continue  # camera-only data: lasers are listed with no range images
        for name, arr, ch in (("return 1", ret1, 4), ("return 2", ret2, 4), ("pixel pose", pose, 6)):
            if arr is not None and (arr.ndim != 3 or arr.shape[2] != ch):
                raise WaymoFormatError(f"{what} {name}: shape {arr.shape}, expected (H, W, {ch})")
        lasers.append(RawLaser(laser.name, ret1, ret2, pose))
    stats = ctx.stats
    return RawFrame(
        segment=ctx.name,
        timestamp_micros=frame.timestamp_micros,
        global_from_vehicle=_transform(frame.pose, f"{where}: frame pose"),
        camera_calibrations=cam_cals,
        laser_calibrations=laser_cals,
        images=images,
        lasers=lasers,
        labels=_labels(list(frame.laser_labels)),
        projected_boxes=_projected(list(frame.projected_lidar_labels)),
        stats={"time_of_day": stats.time_of_day, "location": stats.location, "weather": stats.weather},
        where=where,
    )


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
        return parse_frame(self.record(index), self.where(index))


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
