"""Writes synthetic scenes in the Waymo Open Dataset's own formats (v1 TFRecord, v2 Parquet).

The exported files carry what real Waymo files carry, encoded as Waymo does: JPEG images with
per-image poses and shutter timing, camera calibrations in Waymo axes and pixel conventions, the
LiDAR as a TOP range image (float32 range, intensity, elongation, no-label-zone) with per-pixel
vehicle poses and explicit beam inclinations, laser labels in the vehicle frame, and panoptic
camera labels. Poses are moved into a "global" frame by :data:`GLOBAL_OFFSET_M`, so readers must
re-origin them as they must for real data. Reading the files back must reproduce the synthetic
truth: that is what the Waymo readers are tested against.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import CameraImage, Frame
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.waymo.convert import POSE_TIME_OFFSET_MICROS
from phigenesis.data.sources.waymo.raw import (
    CAMERA_CODES,
    READOUT_CODES,
    TOP_LASER,
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
)

#: The synthetic world's origin in the exported "global" frame (metres, east-north-up).
GLOBAL_OFFSET_M = np.array([1234.5, -2345.25, 12.0])
#: Panoptic labels use this divisor, as Waymo's do.
PANOPTIC_DIVISOR = 1000

#: Unified taxonomy -> Waymo camera segmentation class (the nearest; walls and fences are part of
#: Waymo's building class). Unlisted ids (ignore) -> 0, undefined.
UNIFIED_TO_WAYMO_SEGMENTATION: dict[int, int] = {
    tx.CAR: 2,
    tx.TRUCK: 3,
    tx.BUS: 4,
    tx.TRAIN: 5,
    tx.BICYCLE: 6,
    tx.MOTORCYCLE: 7,
    tx.PERSON: 9,
    tx.RIDER: 10,
    tx.POLE: 15,
    tx.TRAFFIC_SIGN: 17,
    tx.TRAFFIC_LIGHT: 18,
    tx.BUILDING: 19,
    tx.WALL: 19,
    tx.FENCE: 19,
    tx.ROAD: 20,
    tx.SIDEWALK: 23,
    tx.VEGETATION: 24,
    tx.SKY: 25,
    tx.TERRAIN: 26,
}
#: Unified taxonomy -> Waymo box type (vehicle 1, pedestrian 2, sign 3, cyclist 4; else unknown 0).
UNIFIED_TO_WAYMO_BOX_TYPE: dict[int, int] = {
    tx.CAR: 1,
    tx.TRUCK: 1,
    tx.BUS: 1,
    tx.TRAIN: 1,
    tx.PERSON: 2,
    tx.TRAFFIC_SIGN: 3,
    tx.RIDER: 4,
    tx.BICYCLE: 4,
    tx.MOTORCYCLE: 4,
}

WaymoVersion = Literal["v1", "v2"]


def _lut(mapping: dict[int, int], default: int) -> np.ndarray:
    lut = np.full(256, default, np.int64)
    for k, v in mapping.items():
        lut[k] = v
    return lut


_SEGMENTATION_LUT = _lut(UNIFIED_TO_WAYMO_SEGMENTATION, 0)
_BOX_TYPE_LUT = _lut(UNIFIED_TO_WAYMO_BOX_TYPE, 0)
_OPENCV_FROM_BODY = geometry.make_transform(geometry.BODY_FROM_OPENCV.T, np.zeros(3))


def _to_global(world_from_ego: np.ndarray) -> np.ndarray:
    out = np.array(world_from_ego, dtype=np.float64)
    out[..., :3, 3] += GLOBAL_OFFSET_M
    return out


def _panoptic_png(cam: CameraImage) -> tuple[bytes, dict[int, int]]:
    """The truth as a Waymo panoptic PNG: class * divisor + local instance, and local -> global."""
    assert cam.truth is not None
    semantic = _SEGMENTATION_LUT[cam.truth.semantic]
    instance = cam.truth.instance
    globals_ = np.unique(instance[instance > 0])
    if len(globals_) >= PANOPTIC_DIVISOR:
        raise ValueError(f"camera {cam.name}: {len(globals_)} instances do not fit the panoptic divisor")
    local = np.searchsorted(globals_, instance) + 1
    local[instance == 0] = 0
    ok, png = cv2.imencode(".png", (semantic * PANOPTIC_DIVISOR + local).astype(np.uint16))
    assert ok
    return png.tobytes(), {i + 1: int(g) for i, g in enumerate(globals_)}


def _camera(scene: SyntheticScene, cam: CameraImage) -> RawCameraImage:
    t_s = scene.seconds(cam.timestamp_micros)
    _, _, velocity, yaw_rate = scene.world.ego.state(t_s)
    png, mapping = _panoptic_png(cam) if cam.truth is not None else (None, {})
    seconds = cam.timestamp_micros * 1e-6
    return RawCameraImage(
        name=CAMERA_CODES[cam.name],
        jpeg=cam.image_bytes,
        global_from_vehicle=_to_global(cam.world_from_ego),
        velocity_linear=np.asarray(velocity, np.float64),
        velocity_angular=np.array([0.0, 0.0, float(yaw_rate)]),
        pose_timestamp=seconds,
        shutter=0.0,
        trigger_time=seconds,
        readout_done_time=seconds,
        panoptic_label=png,
        panoptic_label_divisor=PANOPTIC_DIVISOR,
        instance_to_global=mapping,
    )


def _camera_calibration(cam: CameraImage) -> RawCameraCalibration:
    cal = cam.calibration
    k, d = cal.intrinsics, cal.distortion
    return RawCameraCalibration(
        name=CAMERA_CODES[cal.name],
        # Waymo's pixel 0 spans [0, 1): its principal point is half a pixel further than OpenCV's.
        intrinsic=np.array([k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5, *d]),
        vehicle_from_camera=cal.ego_from_camera @ _OPENCV_FROM_BODY,
        width=cal.width,
        height=cal.height,
        rolling_shutter_direction=READOUT_CODES[cal.readout_direction],
    )


def _top_laser(scene: SyntheticScene, lidar: dict[str, np.ndarray]) -> tuple[RawLaserCalibration, RawLaser]:
    """The sweep as Waymo's TOP range image, with per-pixel poses and explicit inclinations."""
    spec = scene.config.lidar
    incl = spec.inclinations_rad()
    calibration = RawLaserCalibration(
        name=TOP_LASER,
        vehicle_from_laser=geometry.make_transform(np.eye(3), spec.position_m),
        beam_inclinations=incl[::-1].copy(),  # Waymo lists the lowest beam first
        beam_inclination_min=float(incl.min()),
        beam_inclination_max=float(incl.max()),
    )
    image = np.zeros((spec.beams, spec.columns, 4), np.float32)
    rows, cols = lidar["beam"].astype(np.int64), lidar["column"].astype(np.int64)
    image[rows, cols, 0] = lidar["range_m"]
    image[rows, cols, 1] = lidar["intensity"]
    sector_poses = _to_global(scene.world_from_ego_many(lidar["sector_micros"]))
    roll, pitch, yaw = geometry.matrix_to_euler_zyx(sector_poses[:, :3, :3])
    per_sector = np.stack([roll, pitch, yaw, *sector_poses[:, :3, 3].T], axis=1)
    pose = np.broadcast_to(per_sector[lidar["sector_of_column"]][None], (spec.beams, spec.columns, 6))
    laser = RawLaser(
        name=TOP_LASER,
        return1=image,
        return2=np.zeros_like(image),  # the synthetic LiDAR has no second returns
        pixel_pose=np.ascontiguousarray(pose, dtype=np.float32),
    )
    return calibration, laser


def _labels(frame: Frame) -> RawLabels:
    b = frame.boxes
    vehicle_from_world = geometry.invert_transform(frame.world_from_ego)
    rot = vehicle_from_world[:3, :3]
    box_rot = rot @ geometry.quaternion_to_matrix(b.orientation_world)
    heading = np.arctan2(box_rot[:, 1, 0], box_rot[:, 0, 0])
    centers = geometry.transform_points(vehicle_from_world, b.center_world)
    return RawLabels(
        ids=list(b.track_id),
        types=_BOX_TYPE_LUT[b.class_id].astype(np.int32),
        box=np.concatenate([centers, b.size_lwh, heading[:, None]], axis=1),
        speed=b.velocity_world @ rot.T,
        accel=np.nan_to_num(b.acceleration_world) @ rot.T,
        num_lidar_points=b.num_lidar_points.copy(),
        num_top_lidar_points=b.num_lidar_points.copy(),
    )


def raw_frame(scene: SyntheticScene, frame_index: int) -> RawFrame:
    """Synthetic frame ``frame_index`` as a Waymo raw frame (rendered now)."""
    if scene.config.rig != "waymo5":
        raise ValueError(f"Waymo export needs the waymo5 rig, not {scene.config.rig!r}")
    frame, lidar = scene.render_frame_and_lidar(frame_index)
    laser_cal, laser = _top_laser(scene, lidar)
    return RawFrame(
        segment=scene.scene_id,
        timestamp_micros=frame.timestamp_micros - POSE_TIME_OFFSET_MICROS,
        global_from_vehicle=_to_global(frame.world_from_ego),
        camera_calibrations=[_camera_calibration(c) for c in frame.cameras],
        laser_calibrations=[laser_cal],
        images=[_camera(scene, c) for c in frame.cameras],
        lasers=[laser],
        labels=_labels(frame),
        stats={"time_of_day": "Day", "location": "synthetic", "weather": "sunny"},
        where=f"synthetic scene {scene.scene_id} frame {frame_index}",
    )


def export_waymo(
    config: SyntheticConfig, out: str | os.PathLike[str], version: WaymoVersion = "v1"
) -> list[Path]:
    """Renders every scene of ``config`` and writes it under ``out`` in Waymo ``version``.

    v1: one ``segment-<scene id>_with_camera_labels.tfrecord`` per scene; v2: one
    ``<component>/<scene id>.parquet`` per component and scene. Returns the files written.
    """
    from phigenesis.data.sources.waymo import tfrecord, v1, v2

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for index in range(config.scenes):
        scene = SyntheticScene(config, index)
        frames = (raw_frame(scene, k) for k in range(config.frames))
        if version == "v1":
            path = out / f"segment-{scene.scene_id}_with_camera_labels.tfrecord"
            tfrecord.write_records(path, (v1.serialize_frame(f) for f in frames))
            written.append(path)
        elif version == "v2":
            written.extend(v2.write_v2(out, list(frames)))
        else:
            raise ValueError(f"unknown Waymo format version {version!r}; choose v1 or v2")
    return written
