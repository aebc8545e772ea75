"""Waymo raw records -> the toolkit's scene model (one conversion for v1 and v2).

Conventions applied here (see ../../records.py for the scene model's):

- World frame: Waymo's global frame shifted so the segment's first frame pose sits at the origin
  (translation only, so the world stays east-north-up and gravity-aligned; the shift is kept in
  the scene metadata as ``global_from_world``).
- Frame time: Waymo's ``frame_timestamp_micros`` is the start of the TOP scan and its pose holds
  at roughly the middle of the 100 ms scan, so ``Frame.timestamp_micros`` = key + 50 ms, and the
  key is kept as ``source_timestamp_micros``.
- Cameras: OpenCV axes (``vehicle_from_camera @ BODY_FROM_OPENCV``) and pixel centres at integer
  coordinates (Waymo's pixel 0 spans [0, 1), so c_u and c_v move by -0.5). Each image keeps its
  own pose at ``pose_timestamp`` and its rolling-shutter timing.
- LiDAR: every laser and both returns, in the vehicle frame of the frame pose; TOP uses its
  per-pixel poses (ego motion during the scan). Per-point times are estimated from the column
  (the scan sweeps the columns at a constant rate over 100 ms).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraImage,
    CameraLabels,
    Frame,
    LidarSweep,
)
from phigenesis.data.sources.waymo.raw import (
    CAMERA_NAMES,
    LASER_NAMES,
    READOUT_DIRECTIONS,
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    WaymoFormatError,
)

#: The TOP LiDAR spins at 10 Hz; a frame's scan takes this long.
SCAN_PERIOD_MICROS = 100_000
#: Frame.timestamp_micros - Waymo's frame_timestamp_micros: the pose holds mid-scan.
POSE_TIME_OFFSET_MICROS = SCAN_PERIOD_MICROS // 2

#: Waymo box types (Label.Type) -> unified taxonomy. A cyclist box holds rider and bicycle; it is
#: filed as rider (non-rigid). Unknown -> ignore.
BOX_CLASS_IDS: dict[int, int] = {0: tx.IGNORE_ID, 1: tx.CAR, 2: tx.PERSON, 3: tx.TRAFFIC_SIGN, 4: tx.RIDER}

#: Waymo camera segmentation classes (camera_segmentation.proto, 0-28) -> unified taxonomy.
CAMERA_SEGMENTATION_CLASS_IDS: dict[int, int] = {
    0: tx.IGNORE_ID,  # undefined
    1: tx.IGNORE_ID,  # ego vehicle
    2: tx.CAR,
    3: tx.TRUCK,
    4: tx.BUS,
    5: tx.TRUCK,  # other large vehicle
    6: tx.BICYCLE,
    7: tx.MOTORCYCLE,
    8: tx.IGNORE_ID,  # trailer (void in Cityscapes)
    9: tx.PERSON,
    10: tx.RIDER,  # cyclist (bicycle with rider)
    11: tx.RIDER,  # motorcyclist
    12: tx.IGNORE_ID,  # bird
    13: tx.IGNORE_ID,  # ground animal
    14: tx.IGNORE_ID,  # construction cone or pole
    15: tx.POLE,
    16: tx.IGNORE_ID,  # pedestrian object
    17: tx.TRAFFIC_SIGN,
    18: tx.TRAFFIC_LIGHT,
    19: tx.BUILDING,  # includes walls and solid fences
    20: tx.ROAD,
    21: tx.ROAD,  # lane marker
    22: tx.ROAD,  # road marker
    23: tx.SIDEWALK,
    24: tx.VEGETATION,
    25: tx.SKY,
    26: tx.IGNORE_ID,  # other drivable or walkable ground (manholes, gravel): no Cityscapes class
    27: tx.IGNORE_ID,  # dynamic
    28: tx.IGNORE_ID,  # static
}
_SEGMENTATION_LUT = np.full(65536, tx.IGNORE_ID, np.uint8)
for _code, _cid in CAMERA_SEGMENTATION_CLASS_IDS.items():
    _SEGMENTATION_LUT[_code] = _cid

_EGO_FROM_OPENCV_CAMERA = geometry.make_transform(geometry.BODY_FROM_OPENCV, np.zeros(3))


def camera_calibration(raw: RawCameraCalibration) -> CameraCalibration:
    """A Waymo camera calibration in the toolkit's conventions (OpenCV axes and pixel centres)."""
    f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 = raw.intrinsic
    name = CAMERA_NAMES.get(raw.name, f"CAMERA_{raw.name}")
    if raw.width <= 0 or raw.height <= 0:
        raise WaymoFormatError(f"camera {name}: calibration has no image size ({raw.width}x{raw.height})")
    return CameraCalibration(
        name=name,
        width=int(raw.width),
        height=int(raw.height),
        intrinsics=geometry.intrinsic_matrix(f_u, f_v, c_u - 0.5, c_v - 0.5),
        distortion=np.array([k1, k2, p1, p2, k3]),
        ego_from_camera=raw.vehicle_from_camera @ _EGO_FROM_OPENCV_CAMERA,
        readout_direction=READOUT_DIRECTIONS.get(raw.rolling_shutter_direction, "unknown"),  # type: ignore[arg-type]
    )


def _shift(
    global_from_vehicle: NDArray[np.float64], global_origin: NDArray[np.float64]
) -> NDArray[np.float64]:
    """world_from_vehicle for a world frame at ``global_origin`` with the global axes."""
    out = np.array(global_from_vehicle, dtype=np.float64)
    out[:3, 3] -= global_origin
    return out


def _micros(seconds: float) -> int:
    return round(seconds * 1e6)


def camera_labels(image: RawCameraImage, height: int, width: int, where: str) -> CameraLabels | None:
    """The image's panoptic label as unified-taxonomy classes and cross-camera instance ids."""
    if image.panoptic_label is None:
        return None
    panoptic = cv2.imdecode(np.frombuffer(image.panoptic_label, np.uint8), cv2.IMREAD_UNCHANGED)
    if panoptic is None or panoptic.shape != (height, width):
        got = "undecodable bytes" if panoptic is None else f"shape {panoptic.shape}"
        raise WaymoFormatError(f"{where}: panoptic label of the image is {got}, expected ({height}, {width})")
    divisor = int(image.panoptic_label_divisor)
    if divisor <= 0:
        raise WaymoFormatError(f"{where}: panoptic label has divisor {divisor}")
    panoptic = panoptic.astype(np.int64)
    semantic = _SEGMENTATION_LUT[np.minimum(panoptic // divisor, 65535)]
    local = panoptic % divisor
    instance = local
    if image.instance_to_global:
        lut = np.zeros(int(max(local.max(), max(image.instance_to_global))) + 1, np.int64)
        for k, g in image.instance_to_global.items():
            lut[k] = g
        instance = lut[local]
    if instance.max(initial=0) > np.iinfo(np.uint16).max:
        raise WaymoFormatError(f"{where}: instance id {instance.max()} does not fit in 16 bits")
    return CameraLabels(semantic, instance.astype(np.uint16))


def camera_image(
    image: RawCameraImage, calibration: CameraCalibration, global_origin: NDArray[np.float64], where: str
) -> CameraImage:
    readout_s = image.readout_done_time - image.trigger_time - image.shutter
    return CameraImage(
        calibration=calibration,
        timestamp_micros=_micros(image.pose_timestamp),
        world_from_ego=_shift(image.global_from_vehicle, global_origin),
        image_bytes=image.jpeg,
        image_format="jpeg",
        labels=camera_labels(
            image, calibration.height, calibration.width, f"{where} camera {calibration.name}"
        ),
        trigger_micros=_micros(image.trigger_time) if image.trigger_time > 0 else None,
        shutter_micros=max(image.shutter, 0.0) * 1e6,
        readout_micros=max(readout_s, 0.0) * 1e6,
        velocity_world_mps=image.velocity_linear,
        angular_velocity_world_radps=image.velocity_angular,
    )


# --------------------------------------------------------------------------------------------
# LiDAR


def beam_inclinations(cal: RawLaserCalibration, rows: int) -> NDArray[np.float64]:
    """(rows,) elevation of each range-image row, radians, row 0 the highest beam."""
    if cal.beam_inclinations is not None:
        incl = np.asarray(cal.beam_inclinations, np.float64)
        if len(incl) != rows:
            raise WaymoFormatError(
                f"LiDAR {LASER_NAMES.get(cal.name, cal.name)}: {len(incl)} beam inclinations for a range "
                f"image of {rows} rows"
            )
    else:
        lo, hi = cal.beam_inclination_min, cal.beam_inclination_max
        incl = lo + (np.arange(rows) + 0.5) / rows * (hi - lo)
    return incl[::-1]


def column_azimuths(vehicle_from_laser: NDArray[np.float64], columns: int) -> NDArray[np.float64]:
    """(columns,) azimuth of each column in the laser frame: column 0 at the vehicle's rear,
    decreasing (clockwise seen from above), corrected by the laser's mounting yaw."""
    yaw = np.arctan2(vehicle_from_laser[1, 0], vehicle_from_laser[0, 0])
    return np.pi * (1.0 - (2.0 * np.arange(columns) + 1.0) / columns) - yaw


def column_time_offsets_micros(columns: int) -> NDArray[np.int32]:
    """(columns,) estimated measurement time of each column relative to the pose time (mid-scan)."""
    fraction = (np.arange(columns) + 0.5) / columns - 0.5
    return np.round(fraction * SCAN_PERIOD_MICROS).astype(np.int32)


def _pose_matrices(
    pose: NDArray[np.float32], vehicle_from_global: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(rotation (..., 3, 3), translation (..., 3)) of frame-vehicle <- pixel-time vehicle for
    Waymo pixel poses (..., 6) = roll, pitch, yaw, x, y, z (global <- vehicle)."""
    p = pose.astype(np.float64)
    rot = geometry.euler_zyx_to_matrix(p[..., 0], p[..., 1], p[..., 2])
    r0, t0 = vehicle_from_global[:3, :3], vehicle_from_global[:3, 3]
    # Rotate first, then translate in float64: the global translations are kilometres.
    return np.einsum("ij,...jk->...ik", r0, rot), p[..., 3:] @ r0.T + t0


@dataclass
class _RayGeometry:
    """The rays of a range image in the frame's vehicle frame, factored per row and column: the
    unit direction of pixel (h, w) is ``cos_incl[h] * along[w] + sin_incl[h] * up[w]`` and its
    origin ``origin[w]``."""

    cos_incl: NDArray[np.float64]
    sin_incl: NDArray[np.float64]
    along: NDArray[np.float64]
    up: NDArray[np.float64]
    origin: NDArray[np.float64]

    def points(self, rows: NDArray, cols: NDArray, range_m: NDArray) -> tuple[NDArray, NDArray]:
        c, s = self.cos_incl[rows, None], self.sin_incl[rows, None]
        origins = self.origin[cols]
        return (c * self.along[cols] + s * self.up[cols]) * range_m[:, None] + origins, origins


def _laser_geometry(
    laser: RawLaser,
    cal: RawLaserCalibration,
    shape: tuple[int, int],
    vehicle_from_global: NDArray[np.float64],
) -> _RayGeometry | None:
    """The laser's rays, shared by both returns; None if the pixel poses vary within a column (then
    :func:`laser_points` transforms point by point)."""
    h, w = shape
    e = cal.vehicle_from_laser
    incl = beam_inclinations(cal, h)
    az = column_azimuths(e, w)
    pose = laser.pixel_pose
    if pose is None:
        rot, origin = np.broadcast_to(e[:3, :3], (w, 3, 3)), np.broadcast_to(e[:3, 3], (w, 3))
    else:
        if pose.shape[:2] != (h, w):
            raise WaymoFormatError(
                f"LiDAR {LASER_NAMES.get(cal.name, cal.name)}: pixel pose is {pose.shape[:2]}, "
                f"range image ({h}, {w})"
            )
        if not np.array_equal(pose, np.broadcast_to(pose[:1], pose.shape)):
            return None
        # Waymo's pixel poses change only from column to column: one transform per column.
        column_rot, t = _pose_matrices(pose[0], vehicle_from_global)
        rot, origin = column_rot @ e[:3, :3], column_rot @ e[:3, 3] + t
    # Laser-frame direction (cos i cos a, cos i sin a, sin i), rotated per column.
    along = rot[:, :, 0] * np.cos(az)[:, None] + rot[:, :, 1] * np.sin(az)[:, None]
    # float32 from here: the stored points are float32, and the rays are already relative to the
    # frame (no kilometre-scale values left), so this loses nothing measurable (< 1e-5 m at 75 m).
    f32 = np.float32
    return _RayGeometry(
        np.cos(incl).astype(f32),
        np.sin(incl).astype(f32),
        along.astype(f32),
        rot[:, :, 2].astype(f32),
        np.asarray(origin, f32),
    )


def laser_points(
    laser: RawLaser, cal: RawLaserCalibration, vehicle_from_global: NDArray[np.float64]
) -> dict[str, NDArray]:
    """The returns of one laser as points in the frame's vehicle frame.

    Returns a dict of arrays over the valid returns (range > 0) of return 1 then return 2:
    ``points`` (N, 3) and ``origins`` (N, 3) (float32; float64 where poses vary per pixel),
    ``intensity``, ``elongation`` (N,) float32, ``beam`` (N,) uint16 row, ``time_offset`` (N,) int32,
    ``return_index`` (N,) uint8.
    """
    e = cal.vehicle_from_laser
    returns = [(i, ri) for i, ri in enumerate((laser.return1, laser.return2)) if ri is not None]
    if not returns:
        return {}
    h, w, _ = returns[0][1].shape
    if any(ri.shape[:2] != (h, w) for _, ri in returns):
        raise WaymoFormatError(
            f"LiDAR {LASER_NAMES.get(cal.name, cal.name)}: the two returns differ in shape"
        )
    shared = _laser_geometry(laser, cal, (h, w), vehicle_from_global)
    parts = []
    for ret_index, ri in returns:
        rows, cols = np.nonzero(ri[..., 0] > 0)
        rng = ri[rows, cols, 0]
        if shared is not None:
            points, origins = shared.points(rows, cols, rng)
        else:
            incl, az = beam_inclinations(cal, h), column_azimuths(e, w)
            ci = np.cos(incl)[rows]
            xyz = np.stack([ci * np.cos(az)[cols], ci * np.sin(az)[cols], np.sin(incl)[rows]], axis=1)
            rot, t = _pose_matrices(laser.pixel_pose[rows, cols], vehicle_from_global)  # type: ignore[index]
            points = (
                np.einsum("nij,nj->ni", rot, xyz * rng[:, None].astype(np.float64) @ e[:3, :3].T + e[:3, 3])
                + t
            )
            origins = np.einsum("nij,j->ni", rot, e[:3, 3]) + t
        parts.append(
            {
                "points": points,
                "origins": origins,
                "intensity": ri[rows, cols, 1],
                "elongation": ri[rows, cols, 2],
                "beam": rows.astype(np.uint16),
                "time_offset": column_time_offsets_micros(w)[cols],
                "return_index": np.full(len(rows), ret_index, np.uint8),
            }
        )
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def lidar_sweep(
    raw: RawFrame, timestamp_micros: int, world_from_ego: NDArray[np.float64]
) -> LidarSweep | None:
    """All lasers' returns of a frame (TOP first), or None if the frame has no range images."""
    if not raw.lasers:
        return None
    vehicle_from_global = geometry.invert_transform(raw.global_from_vehicle)
    arrays, ids = [], []
    for laser in sorted(raw.lasers, key=lambda las: las.name):
        calibration = raw.laser_calibration(laser.name)  # raises, naming the frame, if missing
        try:
            pts = laser_points(laser, calibration, vehicle_from_global)
        except WaymoFormatError as e:
            raise WaymoFormatError(f"{raw.where}: {e}") from None
        if pts:
            arrays.append(pts)
            ids.append(np.full(len(pts["beam"]), laser.name - 1, np.uint8))
    if not arrays:
        return LidarSweep.empty(timestamp_micros, world_from_ego)
    cat = {k: np.concatenate([a[k] for a in arrays]) for k in arrays[0]}
    return LidarSweep(
        timestamp_micros=timestamp_micros,
        world_from_ego=world_from_ego,
        points_ego=cat["points"].astype(np.float32),
        intensity=cat["intensity"],
        beam_index=cat["beam"],
        origins_ego=cat["origins"].astype(np.float32),
        time_offset_micros=cat["time_offset"],
        lidar_id=np.concatenate(ids),
        elongation=cat["elongation"],
        return_index=cat["return_index"],
    )


# --------------------------------------------------------------------------------------------
# Boxes and frames


def boxes(labels: RawLabels, world_from_vehicle: NDArray[np.float64]) -> Boxes:
    """Laser labels (vehicle frame of the frame pose) as world-frame boxes."""
    m = len(labels)
    rot = world_from_vehicle[:3, :3]
    heading = labels.box[:, 6]
    # Waymo boxes are upright in the (pitched, rolled) vehicle frame: keep that tilt.
    world_from_box = rot @ geometry.rotation_z(heading)
    direction = world_from_box[:, :, 0]
    class_lut = np.vectorize(lambda t: BOX_CLASS_IDS.get(int(t), tx.IGNORE_ID), otypes=[np.uint8])
    return Boxes(
        track_id=list(labels.ids),
        class_id=class_lut(labels.types) if m else np.zeros(0, np.uint8),
        center_world=geometry.transform_points(world_from_vehicle, labels.box[:, :3]),
        size_lwh=labels.box[:, 3:6],
        yaw_world=np.arctan2(direction[:, 1], direction[:, 0]),
        velocity_world=labels.speed @ rot.T,
        status=np.zeros(m, np.uint8),
        instance_id=np.zeros(m, np.uint16),
        num_lidar_points=labels.num_lidar_points,
        acceleration_world=labels.accel @ rot.T,
        orientation_world=geometry.matrix_to_quaternion(world_from_box).reshape(m, 4),
    )


def rig_calibrations(raw: RawFrame) -> list[CameraCalibration]:
    """The frame's camera calibrations in camera-code order (FRONT first), matched by name."""
    return [camera_calibration(c) for c in sorted(raw.camera_calibrations, key=lambda c: c.name)]


def frame(raw: RawFrame, frame_index: int, global_origin: NDArray[np.float64]) -> Frame:
    """One raw Waymo frame as a :class:`Frame` (world frame = global shifted to ``global_origin``).

    Every calibrated camera gets an entry; a camera with no image in this frame (labels-only
    data) has ``image_bytes=None`` and the frame's time and pose.
    """
    world_from_ego = _shift(raw.global_from_vehicle, global_origin)
    t_micros = raw.timestamp_micros + POSE_TIME_OFFSET_MICROS
    images = {}
    for im in raw.images:
        if im.name in images:
            raise WaymoFormatError(f"{raw.where}: two images of camera {CAMERA_NAMES.get(im.name, im.name)}")
        images[im.name] = im
    calibrations = {c.name: c for c in raw.camera_calibrations}
    for name in images:
        raw.camera_calibration(name)  # raises, naming the frame, if the camera is not calibrated
    cameras = []
    for code in sorted(calibrations):
        try:
            cal = camera_calibration(calibrations[code])
        except WaymoFormatError as e:
            raise WaymoFormatError(f"{raw.where}: {e}") from None
        if code in images:
            cameras.append(camera_image(images[code], cal, global_origin, raw.where))
        else:
            cameras.append(CameraImage(cal, t_micros, world_from_ego, None))
    return Frame(
        scene_id=raw.segment,
        frame_index=frame_index,
        timestamp_micros=t_micros,
        world_from_ego=world_from_ego,
        cameras=cameras,
        lidar=lidar_sweep(raw, t_micros, world_from_ego),
        boxes=boxes(raw.labels, world_from_ego),
        source_timestamp_micros=raw.timestamp_micros,
    )
