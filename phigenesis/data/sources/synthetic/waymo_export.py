"""Writes synthetic scenes in the Waymo Open Dataset's own formats (v1 TFRecord, v2 Parquet).

The exported files carry what real Waymo files carry, encoded as Waymo does: JPEG images with
per-image poses and shutter timing, camera calibrations in Waymo axes and pixel conventions, the
LiDARs as range images (float32 range, intensity, elongation, no-label-zone; both returns,
range 0 where a cell has none): TOP with per-pixel vehicle poses and explicit beam inclinations,
the short-range LiDARs (with the ``waymo`` preset) with uniform inclinations from their minimum
and maximum and no poses, as real files hold them; laser labels in the vehicle frame, and panoptic
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
from phigenesis import taxonomy as tx
from phigenesis.data.records import CameraImage, Frame
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.data.sources.waymo.convert import POSE_TIME_OFFSET_MICROS
from phigenesis.data.sources.waymo.raw import (
    CAMERA_CODES,
    LASER_CODES,
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


def _laser(
    scene: SyntheticScene, spec: LidarSpec, lidar: dict[str, np.ndarray]
) -> tuple[RawLaserCalibration, RawLaser]:
    """One LiDAR's sweep as Waymo's range images (return 1, return 2; cells without a return
    hold range 0), with its calibration: explicit beam inclinations (lowest first) or, for the
    "min_max" layout, only the minimum and maximum from which readers space the rows uniformly.
    TOP, and any LiDAR cast in several sectors, gets per-pixel vehicle poses (Waymo stores them
    for TOP only; the short-range LiDARs of the presets are snapshots at the frame pose)."""
    if spec.name not in LASER_CODES:
        raise ValueError(f"LiDAR {spec.name!r} is not a Waymo laser; name it one of {sorted(LASER_CODES)}")
    code = LASER_CODES[spec.name]
    incl = spec.inclinations_rad()
    explicit = spec.inclinations == "explicit"
    if explicit:
        lo, hi = float(incl.min()), float(incl.max())
    else:
        lo, hi = float(np.radians(spec.inclination_bottom_deg)), float(np.radians(spec.inclination_top_deg))
    calibration = RawLaserCalibration(
        name=code,
        vehicle_from_laser=spec.ego_from_sensor(),
        beam_inclinations=incl[::-1].copy() if explicit else None,  # Waymo lists the lowest beam first
        beam_inclination_min=lo,
        beam_inclination_max=hi,
    )
    returns = lidar.get("return_index", np.zeros(len(lidar["beam"]), np.uint8))
    images = []
    for r in (0, 1):
        image = np.zeros((spec.beams, spec.columns, 4), np.float32)
        m = returns == r
        rows, cols = lidar["beam"][m].astype(np.int64), lidar["column"][m].astype(np.int64)
        image[rows, cols, 0] = lidar["range_m"][m]
        image[rows, cols, 1] = lidar["intensity"][m]
        images.append(image)
    pose = None
    if code == TOP_LASER or spec.sectors > 1:
        sector_poses = _to_global(scene.world_from_ego_many(lidar["sector_micros"]))
        roll, pitch, yaw = geometry.matrix_to_euler_zyx(sector_poses[:, :3, :3])
        per_sector = np.stack([roll, pitch, yaw, *sector_poses[:, :3, 3].T], axis=1)
        pose = np.broadcast_to(per_sector[lidar["sector_of_column"]][None], (spec.beams, spec.columns, 6))
        pose = np.ascontiguousarray(pose, dtype=np.float32)
    laser = RawLaser(name=code, return1=images[0], return2=images[1], pixel_pose=pose)
    return calibration, laser


def _labels(frame: Frame, top_points: np.ndarray | None = None) -> RawLabels:
    """The frame's boxes as laser labels; ``top_points`` (M,): the TOP LiDAR's points per box
    where it is not the only LiDAR (else all points are TOP's)."""
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
        num_top_lidar_points=(b.num_lidar_points if top_points is None else top_points).copy(),
    )


def raw_frame(scene: SyntheticScene, frame_index: int) -> RawFrame:
    """Synthetic frame ``frame_index`` as a Waymo raw frame (rendered now)."""
    if scene.config.rig != "waymo5":
        raise ValueError(f"Waymo export needs the waymo5 rig, not {scene.config.rig!r}")
    frame, raws = scene.render_frame_and_lidar(frame_index)
    lasers = [_laser(scene, spec, raw) for spec, raw in zip(scene.config.lidars, raws, strict=True)]
    top_points = None
    if len(raws) > 1 and len(frame.boxes):
        counts = np.bincount(raws[0]["instance"], minlength=int(frame.boxes.instance_id.max()) + 1)
        top_points = counts[frame.boxes.instance_id].astype(np.int32)
    return RawFrame(
        segment=scene.scene_id,
        timestamp_micros=frame.timestamp_micros - POSE_TIME_OFFSET_MICROS,
        global_from_vehicle=_to_global(frame.world_from_ego),
        camera_calibrations=[_camera_calibration(c) for c in frame.cameras],
        laser_calibrations=[cal for cal, _ in lasers],
        images=[_camera(scene, c) for c in frame.cameras],
        lasers=[laser for _, laser in lasers],
        labels=_labels(frame, top_points),
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
    # the Waymo readers (protobuf, Parquet) load only to check an export
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
