"""Waymo frames as the dataset defines them, before conversion to the scene model.

Both formats read into these records (v1 TFRecord in :mod:`.v1`, v2 Parquet in :mod:`.v2`) and the
writers write from them, so one conversion (:mod:`.convert`) serves both. Everything is kept in
Waymo's own terms:

- Frames: ``vehicle`` (x forward, y left, z up, Waymo's ego frame), ``global`` (Waymo's world frame,
  east-north-up with a large offset), ``camera`` in Waymo axes (x forward along the optical axis,
  y left, z up), ``laser`` the LiDAR's own frame.
- Transforms: 4x4 float64 ``target_from_source`` (Waymo calls ``vehicle_from_camera`` the camera
  extrinsic and ``global_from_vehicle`` the pose).
- Times: camera times in seconds since the Unix epoch (float64), as Waymo stores them; frame
  timestamps in microseconds.
- Enums are Waymo's integer codes (:data:`CAMERA_NAMES`, :data:`LASER_NAMES`, ...).

Readers never drop data on their own: what they cannot read about one camera or one LiDAR they
put in :attr:`RawFrame.invalid_sensors`, and :mod:`.convert` applies the segment's error policy
(:class:`Problems`) to it, as to every invalid value it finds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis.errors import SourceError

log = logging.getLogger("phigenesis.prep")

#: The error policy of a segment: "raise" stops at the first invalid record, "skip" leaves out
#: the smallest part that keeps the rest correct (a box, a camera, a LiDAR, a frame).
OnError = Literal["raise", "skip"]
#: What a segment leaves out under ``skip``, as counted in ``Scene.dropped`` (besides the scene
#: model's own ``INVALID_POINTS`` and ``INVALID_BOXES``).
FRAMES_LEFT_OUT = "frames left out as invalid records"
CAMERAS_LEFT_OUT = "camera images left out as invalid"
LIDARS_LEFT_OUT = "LiDAR range images left out as invalid"

#: CameraName codes (dataset.proto). Perception data has 1-5; 6-8 exist in v1 only.
CAMERA_NAMES: dict[int, str] = {
    1: "FRONT",
    2: "FRONT_LEFT",
    3: "FRONT_RIGHT",
    4: "SIDE_LEFT",
    5: "SIDE_RIGHT",
    6: "REAR_LEFT",
    7: "REAR",
    8: "REAR_RIGHT",
}
CAMERA_CODES: dict[str, int] = {v: k for k, v in CAMERA_NAMES.items()}
#: LaserName codes (dataset.proto).
LASER_NAMES: dict[int, str] = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
LASER_CODES: dict[str, int] = {v: k for k, v in LASER_NAMES.items()}
TOP_LASER = 1
#: CameraCalibration.RollingShutterReadOutDirection codes -> the scene model's readout directions.
READOUT_DIRECTIONS: dict[int, str] = {
    0: "unknown",
    1: "top_to_bottom",
    2: "left_to_right",
    3: "bottom_to_top",
    4: "right_to_left",
    5: "global",
}
READOUT_CODES: dict[str, int] = {v: k for k, v in READOUT_DIRECTIONS.items()}
#: Label.Type codes.
BOX_TYPES: dict[int, str] = {0: "UNKNOWN", 1: "VEHICLE", 2: "PEDESTRIAN", 3: "SIGN", 4: "CYCLIST"}


class WaymoFormatError(SourceError):
    """Input that is not valid Waymo data; the message names the file and where in it."""


class Problems:
    """The error policy of one segment (``on_error``).

    ``raise``: :meth:`report` raises the error. ``skip``: it logs the error (each message once),
    counts the part left out under ``kind`` in ``left_out``, and the caller leaves it out.
    """

    def __init__(self, on_error: OnError = "raise"):
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        self.on_error: OnError = on_error
        self._logged: set[str] = set()

    @property
    def skip(self) -> bool:
        return self.on_error == "skip"

    def report(self, error: WaymoFormatError, kind: str, left_out: dict[str, int]) -> None:
        """Raises ``error`` (``raise``), or records that one part of ``kind`` is left out."""
        if not self.skip:
            raise error
        left_out[kind] = left_out.get(kind, 0) + 1
        message = str(error)
        if message not in self._logged:
            self._logged.add(message)
            log.warning("%s; left out (--on-error skip)", message)


@dataclass(frozen=True)
class FrameKey:
    """What a segment's index knows of a frame before reading it: Waymo's frame timestamp
    (microseconds) and the frame pose ``global_from_vehicle`` (checked to be rigid)."""

    timestamp_micros: int
    global_from_vehicle: NDArray[np.float64]


@dataclass
class RawCameraCalibration:
    """CameraCalibration: ``intrinsic`` is (9,) [f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3] for pixel
    coordinates whose 0 is the left/top edge of the first pixel; ``vehicle_from_camera`` in Waymo
    camera axes."""

    name: int
    intrinsic: NDArray[np.float64]
    vehicle_from_camera: NDArray[np.float64]
    width: int
    height: int
    rolling_shutter_direction: int = 0


@dataclass
class RawLaserCalibration:
    """LaserCalibration: ``beam_inclinations`` (rad, as stored: lowest beam first) or None for a
    uniform spacing between ``beam_inclination_min`` and ``beam_inclination_max``."""

    name: int
    vehicle_from_laser: NDArray[np.float64]
    beam_inclinations: NDArray[np.float64] | None
    beam_inclination_min: float
    beam_inclination_max: float


@dataclass
class RawCameraImage:
    """CameraImage: the JPEG as stored, the vehicle pose at ``pose_timestamp`` and the shutter timing.

    Attributes:
        velocity_linear: (3,) vehicle velocity at ``pose_timestamp``, global frame, m/s.
        velocity_angular: (3,) angular velocity, rad/s (dR/dt = [w]x R, so global axes).
        panoptic_label: uint16 PNG of ``semantic * panoptic_label_divisor + instance``, or None.
        instance_to_global: local instance id -> id consistent across cameras and frames.
    """

    name: int
    jpeg: bytes | None
    global_from_vehicle: NDArray[np.float64]
    velocity_linear: NDArray[np.float64]
    velocity_angular: NDArray[np.float64]
    pose_timestamp: float
    shutter: float
    trigger_time: float
    readout_done_time: float
    panoptic_label: bytes | None = None
    panoptic_label_divisor: int = 0
    instance_to_global: dict[int, int] = field(default_factory=dict)


@dataclass
class RawLaser:
    """One LiDAR's range images, decoded.

    Attributes:
        return1, return2: (H, W, 4) float32 [range m, intensity, elongation, in no-label zone];
            range <= 0 means no return. None if the laser has none.
        pixel_pose: (H, W, 6) float32 [roll, pitch, yaw, x, y, z] global_from_vehicle of each
            pixel (TOP only, shared by both returns), or None ("virtual" range images).
    """

    name: int
    return1: NDArray[np.float32] | None
    return2: NDArray[np.float32] | None
    pixel_pose: NDArray[np.float32] | None = None


@dataclass
class RawLabels:
    """Laser labels (M boxes) in the vehicle frame of the frame's pose.

    Attributes:
        box: (M, 7) float64 [center_x, center_y, center_z, length, width, height, heading];
            length is along the heading.
        speed, accel: (M, 3) float64 m/s and m/s^2 in the vehicle frame (z is 0 when missing).
        num_lidar_points, num_top_lidar_points: (M,) int32 (-1 when missing).
    """

    ids: list[str]
    types: NDArray[np.int32]
    box: NDArray[np.float64]
    speed: NDArray[np.float64]
    accel: NDArray[np.float64]
    num_lidar_points: NDArray[np.int32]
    num_top_lidar_points: NDArray[np.int32]

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls) -> RawLabels:
        return cls(
            [], np.zeros(0, np.int32), *(np.zeros((0, k)) for k in (7, 3, 3)), *(np.zeros(0, np.int32),) * 2
        )


@dataclass
class RawProjectedBoxes:
    """2D boxes in camera images (projected_lidar_labels): K boxes.

    Attributes:
        camera: (K,) int32 camera code.
        ids: the laser label's id per box (the ``_<CAMERA>`` suffix removed).
        box: (K, 4) float64 [center_x, center_y, size_x, size_y] in pixels (0 = left/top edge of
            the first pixel); size_x is the extent along the image width.
        types: (K,) int32 Label.Type.
    """

    camera: NDArray[np.int32]
    ids: list[str]
    box: NDArray[np.float64]
    types: NDArray[np.int32]

    @classmethod
    def empty(cls) -> RawProjectedBoxes:
        return cls(np.zeros(0, np.int32), [], np.zeros((0, 4)), np.zeros(0, np.int32))


@dataclass
class RawFrame:
    """One Waymo frame (v1 ``Frame`` / the v2 components at one ``frame_timestamp_micros``).

    Attributes:
        segment: the segment (context) name.
        timestamp_micros: Waymo's frame timestamp, the start of the first TOP scan.
        global_from_vehicle: (4, 4) vehicle pose, roughly at the middle of the scan; laser labels
            and the returned points are in this vehicle frame.
        where: the file (and record offset) the frame came from, for error messages.
        stats: time_of_day, location, weather.
        invalid_sensors: what the reader could not read about one sensor, keyed by (part, code)
            with part "camera" (its image), "camera_calibration", "laser" (its range images) or
            "laser_calibration": the first error for it.
        part_where: where a part of the frame came from when it is not ``where`` (v2: the
            component file and frame), keyed by "camera", "laser" and "labels".
    """

    segment: str
    timestamp_micros: int
    global_from_vehicle: NDArray[np.float64]
    camera_calibrations: list[RawCameraCalibration]
    laser_calibrations: list[RawLaserCalibration]
    images: list[RawCameraImage]
    lasers: list[RawLaser]
    labels: RawLabels
    projected_boxes: RawProjectedBoxes = field(default_factory=RawProjectedBoxes.empty)
    stats: dict[str, str] = field(default_factory=dict)
    where: str = ""
    invalid_sensors: dict[tuple[str, int], WaymoFormatError] = field(default_factory=dict)
    part_where: dict[str, str] = field(default_factory=dict)

    def where_of(self, part: str) -> str:
        """Where ``part`` ("camera", "laser", "labels") of the frame came from, for messages."""
        return self.part_where.get(part, self.where)

    def mark_invalid(self, sensor: str, code: int, error: WaymoFormatError) -> None:
        """Records the first problem of sensor ``(sensor, code)``; conversion applies the policy."""
        self.invalid_sensors.setdefault((sensor, int(code)), error)

    def camera_calibration(self, name: int) -> RawCameraCalibration:
        """The calibration of camera ``name``, matched by name; raises naming the frame if absent."""
        return _by_name(self.camera_calibrations, name, CAMERA_NAMES, f"{self.where}: camera", "an image")

    def laser_calibration(self, name: int) -> RawLaserCalibration:
        """The calibration of LiDAR ``name``, matched by name; raises naming the frame if absent."""
        return _by_name(self.laser_calibrations, name, LASER_NAMES, f"{self.where}: LiDAR", "range images")


def _by_name(calibrations: list, name: int, names: dict[int, str], what: str, has: str) -> Any:
    for cal in calibrations:
        if cal.name == name:
            return cal
    have = ", ".join(sorted(names.get(c.name, str(c.name)) for c in calibrations)) or "none"
    raise WaymoFormatError(
        f"{what} {names.get(name, name)} has {has} but no calibration (calibrated: {have})"
    )
