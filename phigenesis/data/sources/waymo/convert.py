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

Invalid data: every value goes through the scene model's checks (``records.InvalidRecord``),
turned here into a :class:`WaymoFormatError` that names the file, the record and the field.
The segment's :class:`~.raw.Problems` decides what follows: ``raise`` stops at the first, ``skip``
leaves out the smallest part that keeps the rest correct and counts it in ``Scene.dropped``: a
box (``INVALID_BOXES``), a camera image (``CAMERAS_LEFT_OUT``), one LiDAR's range images
(``LIDARS_LEFT_OUT``), single LiDAR points with non-finite or out-of-range values
(``INVALID_POINTS``, dropped under either policy: a range image marks missing returns that way).
A frame-level problem (its pose, its time) always raises here; the source's index checks those
before any frame is converted (see :mod:`phigenesis.data.sources.waymo`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.native import load_range_points
from phigenesis.data.records import (
    INT64_MAX,
    INVALID_BOXES,
    INVALID_POINTS,
    Boxes,
    CameraCalibration,
    CameraImage,
    CameraLabels,
    DroppedValues,
    Frame,
    InvalidRecord,
    LidarSweep,
    check_capture_time,
    check_transform,
    encoded_image_size,
)
from phigenesis.data.sources.waymo.raw import (
    CAMERA_NAMES,
    CAMERAS_LEFT_OUT,
    LASER_NAMES,
    LIDARS_LEFT_OUT,
    READOUT_DIRECTIONS,
    Problems,
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


_T = TypeVar("_T")


def _record(what: str, build: Callable[[], _T]) -> _T:
    """``build()``, with a scene-model :class:`InvalidRecord` turned into a :class:`WaymoFormatError`
    prefixed by ``what`` (the file and record; "" where the caller adds them)."""
    try:
        return build()
    except InvalidRecord as e:
        raise WaymoFormatError(f"{what}: {e}" if what else str(e)) from None


def _camera_name(code: int) -> str:
    return CAMERA_NAMES.get(code, f"CAMERA_{code}")


def camera_calibration(raw: RawCameraCalibration) -> CameraCalibration:
    """A Waymo camera calibration in the toolkit's conventions (OpenCV axes and pixel centres).

    Raises :class:`WaymoFormatError` naming the camera and the field if it is invalid (no image
    size, intrinsics that are not finite and positive, an extrinsic that is not rigid).
    """
    name = _camera_name(raw.name)
    intrinsic = np.asarray(raw.intrinsic, np.float64).reshape(-1)
    if intrinsic.size != 9:
        raise WaymoFormatError(f"camera {name}: calibration has {intrinsic.size} intrinsics, expected 9")
    f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 = intrinsic.tolist()
    if raw.width <= 0 or raw.height <= 0:
        raise WaymoFormatError(f"camera {name}: calibration has no image size ({raw.width}x{raw.height})")
    return _record(
        "",
        lambda: CameraCalibration(
            name=name,
            width=int(raw.width),
            height=int(raw.height),
            intrinsics=geometry.intrinsic_matrix(f_u, f_v, c_u - 0.5, c_v - 0.5),
            distortion=np.array([k1, k2, p1, p2, k3]),
            ego_from_camera=np.asarray(raw.vehicle_from_camera, np.float64) @ _EGO_FROM_OPENCV_CAMERA,
            readout_direction=READOUT_DIRECTIONS.get(raw.rolling_shutter_direction, "unknown"),  # type: ignore[arg-type]
        ),
    )


def _shift(
    global_from_vehicle: NDArray[np.float64], global_origin: NDArray[np.float64]
) -> NDArray[np.float64]:
    """world_from_vehicle for a world frame at ``global_origin`` with the global axes."""
    out = np.array(global_from_vehicle, dtype=np.float64)
    out[:3, 3] -= global_origin
    return out


def _micros(seconds: float, what: str) -> int:
    """Waymo seconds as integer microseconds; raises naming ``what`` for a value that is not a
    time (NaN, infinite, beyond int64 microseconds)."""
    if not math.isfinite(seconds) or abs(seconds) * 1e6 >= INT64_MAX:
        raise WaymoFormatError(f"{what} is {seconds} s, not a time")
    return round(seconds * 1e6)


#: Largest instance id a camera label may hold (they are stored as 16-bit PNGs).
MAX_INSTANCE_ID = int(np.iinfo(np.uint16).max)


def _instance_ids(local: NDArray[np.int64], mapping: dict[int, int], where: str) -> NDArray[np.int64]:
    """Local instance ids mapped to global ones (unmapped ids -> 0; without a mapping the local
    ids stand). The lookup table covers the ids a 16-bit label can hold, however large the ids
    in the mapping are; a mapped id outside [0, 65535] that the image uses is an error."""
    if not mapping:
        return local
    size = int(local.max(initial=0)) + 1  # <= 65536: local ids come from a 16-bit PNG
    lut = np.zeros(size, np.int64)
    for k, g in mapping.items():
        if 0 <= k < size:
            lut[k] = g
    instance = lut[local]
    bad = (instance < 0) | (instance > MAX_INSTANCE_ID)
    if bad.any():
        k = int(local[bad].flat[0])
        raise WaymoFormatError(
            f"{where}: instance_id_to_global_id_mapping maps local id {k} to {int(lut[k])}, "
            f"not an instance id in [0, {MAX_INSTANCE_ID}]"
        )
    return instance


def camera_labels(image: RawCameraImage, height: int, width: int, where: str) -> CameraLabels | None:
    """The image's panoptic label as unified-taxonomy classes and cross-camera instance ids.

    The PNG's header is checked against the calibrated size before it is decoded, so a label
    that declares a huge image costs nothing.
    """
    if image.panoptic_label is None:
        return None
    try:
        size = encoded_image_size(image.panoptic_label, "png", "panoptic_label")
    except InvalidRecord as e:
        raise WaymoFormatError(f"{where}: {e}") from None
    if size != (width, height):
        raise WaymoFormatError(
            f"{where}: panoptic label of the image is shape ({size[1]}, {size[0]}) by its PNG header, "
            f"expected ({height}, {width})"
        )
    panoptic = cv2.imdecode(np.frombuffer(image.panoptic_label, np.uint8), cv2.IMREAD_UNCHANGED)
    if panoptic is None or panoptic.shape != (height, width):
        got = "undecodable bytes" if panoptic is None else f"shape {panoptic.shape}"
        raise WaymoFormatError(f"{where}: panoptic label of the image is {got}, expected ({height}, {width})")
    divisor = int(image.panoptic_label_divisor)
    if divisor <= 0:
        raise WaymoFormatError(f"{where}: panoptic label has divisor {divisor}")
    # A 16-bit label holds at most 65536 codes and an image millions of pixels: the class and
    # instance of each code the image uses are found once, then looked up per pixel (one uint16
    # gather each instead of int64 divisions over the whole image).
    codes = np.flatnonzero(np.bincount(panoptic.ravel()))
    semantic_of = _SEGMENTATION_LUT[np.minimum(codes // divisor, 65535)]
    instance_of = _instance_ids(codes % divisor, image.instance_to_global, where)
    if instance_of.max(initial=0) > MAX_INSTANCE_ID:
        raise WaymoFormatError(f"{where}: instance id {instance_of.max()} does not fit in 16 bits")
    semantic_lut = np.full(int(codes[-1]) + 1, tx.IGNORE_ID, np.uint8)
    semantic_lut[codes] = semantic_of
    instance_lut = np.zeros(int(codes[-1]) + 1, np.uint16)
    instance_lut[codes] = instance_of
    return CameraLabels(semantic_lut[panoptic], instance_lut[panoptic])


def camera_image(
    image: RawCameraImage,
    calibration: CameraCalibration,
    global_origin: NDArray[np.float64],
    where: str,
    frame_time_micros: int | None = None,
    images: bool = True,
) -> CameraImage:
    """One raw image as a :class:`CameraImage`; raises :class:`WaymoFormatError` naming ``where``,
    the camera and the field if any value is invalid (including a capture time more than a few
    seconds from ``frame_time_micros``, when given, and a JPEG that is cut short or does not
    decode: :meth:`CameraImage.check_image`). ``images=False``: the image's time, pose and
    timing only (no bytes, labels or decode check), for the scene-wide geometry pass."""
    what = f"{where}: camera {calibration.name}"
    readout_s = image.readout_done_time - image.trigger_time - image.shutter
    timestamp = _micros(image.pose_timestamp, f"{what} pose_timestamp")
    trigger = (
        _micros(image.trigger_time, f"{what} camera_trigger_time")
        if image.trigger_time > 0 and math.isfinite(image.trigger_time)
        else None
    )
    if frame_time_micros is not None:
        name = f"camera {calibration.name} pose_timestamp"
        _record(where, lambda: check_capture_time(name, timestamp, frame_time_micros))

    def build() -> CameraImage:
        built = CameraImage(
            calibration=calibration,
            timestamp_micros=timestamp,
            world_from_ego=_shift(image.global_from_vehicle, global_origin),
            image_bytes=image.jpeg if images else None,
            image_format="jpeg",
            labels=camera_labels(image, calibration.height, calibration.width, what) if images else None,
            trigger_micros=trigger,
            shutter_micros=max(image.shutter, 0.0) * 1e6 if math.isfinite(image.shutter) else image.shutter,
            readout_micros=max(readout_s, 0.0) * 1e6 if math.isfinite(readout_s) else readout_s,
            velocity_world_mps=image.velocity_linear,
            angular_velocity_world_radps=image.velocity_angular,
        )
        if images:
            built.check_image()
        return built

    return _record(where, build)


# --------------------------------------------------------------------------------------------
# LiDAR


def _laser_name(code: int) -> str:
    return LASER_NAMES.get(code, f"LIDAR_{code}")


def beam_inclinations(cal: RawLaserCalibration, rows: int) -> NDArray[np.float64]:
    """(rows,) elevation of each range-image row, radians, row 0 the highest beam.

    Raises :class:`WaymoFormatError` naming the LiDAR and the field unless there is one finite
    inclination per row, each within [-pi/2, pi/2].
    """
    name = _laser_name(cal.name)
    if cal.beam_inclinations is not None:
        incl = np.asarray(cal.beam_inclinations, np.float64)
        if len(incl) != rows:
            raise WaymoFormatError(
                f"LiDAR {name}: {len(incl)} beam inclinations for a range image of {rows} rows"
            )
        field_name = "beam_inclinations"
    else:
        lo, hi = cal.beam_inclination_min, cal.beam_inclination_max
        incl = lo + (np.arange(rows) + 0.5) / rows * (hi - lo)
        field_name = f"beam_inclination_min/max ({lo}, {hi})"
    bad = ~(np.abs(incl) <= np.pi / 2)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise WaymoFormatError(
            f"LiDAR {name}: {field_name} gives row {k} the inclination {incl[k]} rad, "
            "not a finite angle in [-pi/2, pi/2]"
        )
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
    unit direction of pixel (h, w) is ``cos_incl[h] * along[:, w] + sin_incl[h] * up[:, w]`` and its
    origin ``origin[:, w]``. Per column as (3, W), so that the arithmetic over a return's N pixels
    runs along N (on (N, 3) arrays numpy's inner loops would run along the 3)."""

    cos_incl: NDArray[np.float32]  # (H,)
    sin_incl: NDArray[np.float32]  # (H,)
    along: NDArray[np.float32]  # (3, W)
    up: NDArray[np.float32]  # (3, W)
    origin: NDArray[np.float32]  # (3, W)

    def points(self, rows: NDArray, cols: NDArray, range_m: NDArray) -> tuple[NDArray, NDArray]:
        """(points, origins), each (N, 3) (transposed views of (3, N) arrays), of the pixels
        (rows[i], cols[i]) at ranges range_m[i]."""
        points = self.along.take(cols, axis=1)  # (3, N)
        points *= self.cos_incl.take(rows)
        up = self.up.take(cols, axis=1)  # (3, N)
        up *= self.sin_incl.take(rows)
        points += up
        points *= range_m
        origins = self.origin.take(cols, axis=1)  # (3, N)
        points += origins
        return points.T, origins.T


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
        np.ascontiguousarray(along.T, f32),
        np.ascontiguousarray(rot[:, :, 2].T, f32),
        np.ascontiguousarray(np.asarray(origin).T, f32),
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
    parts = _laser_parts(laser, cal, vehicle_from_global)
    if not parts:
        return {}
    out = _concatenate(parts)
    out.pop("lidar_id", None)
    return out


_Part = dict[str, NDArray]


def _concatenate(parts: list[_Part]) -> dict[str, NDArray]:
    """Each field of ``parts`` concatenated into one array, allocated once; (N, 3) fields in C
    order, as the scene model's other sources give them (the numpy parts' points and origins are
    transposed views of (3, N) arrays)."""
    total = sum(len(p["beam"]) for p in parts)
    keys = list(parts[0])
    layout = {}
    for key in keys:
        dtype = np.result_type(*(p[key].dtype for p in parts))
        layout[key] = ((total, 3) if key in ("points", "origins") else (total,), dtype)
    out = _one_block(layout)
    start = 0
    for part in parts:
        n = len(part["beam"])
        for key in keys:
            out[key][start : start + n] = part[key]
        start += n
    return out


def _one_block(layout: dict[str, tuple[tuple[int, ...], np.dtype]]) -> dict[str, NDArray]:
    """Empty C-order arrays of the given shapes and dtypes, carved out of one allocation (each
    64-byte aligned). A sweep's fields are 6-7 MB together but 0.2-2 MB each: as one block numpy
    asks the kernel for huge pages, and the first write faults in a few of them instead of
    thousands of 4 KiB pages."""
    sizes = {k: int(np.prod(shape)) * np.dtype(dtype).itemsize for k, (shape, dtype) in layout.items()}
    offsets, end = {}, 0
    for k, size in sizes.items():
        offsets[k] = end
        end += -(-size // 64) * 64
    block = np.empty(end + 64, np.uint8)
    base = (-block.ctypes.data) % 64
    return {
        k: block[base + offsets[k] : base + offsets[k] + sizes[k]].view(dtype).reshape(shape)
        for k, (shape, dtype) in layout.items()
    }


def _laser_parts(
    laser: RawLaser, cal: RawLaserCalibration, vehicle_from_global: NDArray[np.float64]
) -> list[_Part]:
    """:func:`laser_points` before concatenation: one part per return present (return 1 first),
    so that a sweep concatenates every laser's returns once. A part is a dict of numpy arrays,
    written by the native kernel (:mod:`phigenesis.data.native`) where it is built and the pixel
    poses are per column, else by numpy (the reference the tests hold the kernel against)."""
    e = cal.vehicle_from_laser
    returns = [(i, ri) for i, ri in enumerate((laser.return1, laser.return2)) if ri is not None]
    if not returns:
        return []
    h, w, _ = returns[0][1].shape
    if any(ri.shape[:2] != (h, w) for _, ri in returns):
        raise WaymoFormatError(
            f"LiDAR {LASER_NAMES.get(cal.name, cal.name)}: the two returns differ in shape"
        )
    shared = _laser_geometry(laser, cal, (h, w), vehicle_from_global)
    time_offsets = column_time_offsets_micros(w)
    kernel = load_range_points() if shared is not None else None
    parts: list[_Part] = []
    for ret_index, ri in returns:
        if kernel is not None and shared is not None and ri.dtype == np.float32 and ri.shape[2] >= 3:
            r = shared
            part = kernel.gather(
                np.ascontiguousarray(ri), r.cos_incl, r.sin_incl, r.along, r.up, r.origin, time_offsets
            )
            part["return_index"] = np.full(len(part["beam"]), ret_index, np.uint8)
            parts.append(part)
            continue
        # range > 0 is a return; a non-finite range is kept here so that the sweep drops and
        # counts it (LidarSweep.without_invalid_points), while 0 and negatives mean no return.
        rng_all = ri[..., 0]
        keep = ~(rng_all <= 0)  # positive, NaN or +inf
        keep |= rng_all == -np.inf
        pixels = np.flatnonzero(keep)
        rows, cols = np.divmod(pixels, w)
        values = ri.reshape(h * w, -1).take(pixels, axis=0)  # (N, C): range, intensity, elongation, ...
        rng = values[:, 0]
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
                "intensity": values[:, 1],
                "elongation": values[:, 2],
                "beam": rows.astype(np.uint16),
                "time_offset": time_offsets.take(cols),
                "return_index": np.full(len(rows), ret_index, np.uint8),
            }
        )
    return parts


def _checked_laser_calibration(laser: RawLaser, raw: RawFrame) -> RawLaserCalibration:
    """The calibration of ``laser``, checked: a known LiDAR name, a rigid extrinsic. Raises
    :class:`WaymoFormatError` naming the frame, the LiDAR and the field otherwise."""
    where = raw.where_of("laser")
    for part in ("laser", "laser_calibration"):
        error = raw.invalid_sensors.get((part, laser.name))
        if error is not None:
            raise error
    if laser.name not in LASER_NAMES:
        raise WaymoFormatError(f"{where}: LiDAR name code {laser.name} is not one of {sorted(LASER_NAMES)}")
    calibration = raw.laser_calibration(laser.name)  # raises, naming the frame, if missing
    name = f"LiDAR {_laser_name(laser.name)} extrinsic"
    _record(where, lambda: check_transform(name, calibration.vehicle_from_laser))
    return calibration


def _laser_arrays(laser: RawLaser, raw: RawFrame, vehicle_from_global: NDArray[np.float64]) -> list[_Part]:
    """:func:`_laser_parts` of one laser with its calibration checked and each part's
    ``lidar_id``; errors name the frame."""
    calibration = _checked_laser_calibration(laser, raw)
    try:
        parts = _laser_parts(laser, calibration, vehicle_from_global)
    except WaymoFormatError as e:
        raise WaymoFormatError(f"{raw.where_of('laser')}: {e}") from None
    for part in parts:
        part["lidar_id"] = np.full(len(part["beam"]), laser.name - 1, np.uint8)
    return parts


def _sweep_without_invalid_points(**values: Any) -> tuple[LidarSweep, int]:
    """:meth:`LidarSweep.without_invalid_points`, built directly when no point is invalid.

    The constructor makes every check that method makes and refuses a sweep with invalid points;
    only then is the sweep rebuilt without them. So the usual sweep (every point valid) is checked
    once and not copied, instead of checked, copied point by point and checked again.
    """
    try:
        return LidarSweep(**values), 0
    except InvalidRecord:
        return LidarSweep.without_invalid_points(**values)  # raises again for a sweep-wide problem


def lidar_sweep(
    raw: RawFrame,
    timestamp_micros: int,
    world_from_ego: NDArray[np.float64],
    problems: Problems | None = None,
    left_out: dict[str, int] | None = None,
) -> LidarSweep | None:
    """All lasers' returns of a frame (TOP first), or None if the frame has no range images.

    A laser whose data is invalid (no or a bad calibration, a bad range image) raises, or under
    ``skip`` is left out (``LIDARS_LEFT_OUT`` in ``left_out``); points with non-finite or
    out-of-range values are left out under either policy (``INVALID_POINTS``).
    """
    problems = problems or Problems()
    left_out = {} if left_out is None else left_out
    lasers = sorted(raw.lasers, key=lambda las: las.name)
    listed = {las.name for las in lasers}
    for (part, code), error in sorted(raw.invalid_sensors.items(), key=lambda item: item[0]):
        if part == "laser" and code not in listed:
            problems.report(error, LIDARS_LEFT_OUT, left_out)  # a laser the reader could not decode
    if not lasers and not any(part == "laser" for part, _ in raw.invalid_sensors):
        return None
    vehicle_from_global = geometry.invert_transform(raw.global_from_vehicle)
    arrays = []
    for laser in lasers:
        try:
            arrays += _laser_arrays(laser, raw, vehicle_from_global)
        except WaymoFormatError as e:
            problems.report(e, LIDARS_LEFT_OUT, left_out)
            continue
    if not arrays:
        return LidarSweep.empty(timestamp_micros, world_from_ego)
    cat = _concatenate(arrays)
    with np.errstate(invalid="ignore", over="ignore"):
        sweep, dropped = _record(
            raw.where_of("laser"),
            lambda: _sweep_without_invalid_points(
                timestamp_micros=timestamp_micros,
                world_from_ego=world_from_ego,
                points_ego=cat["points"],
                intensity=cat["intensity"],
                beam_index=cat["beam"],
                origins_ego=cat["origins"],
                time_offset_micros=cat["time_offset"],
                lidar_id=cat["lidar_id"],
                elongation=cat["elongation"],
                return_index=cat["return_index"],
            ),
        )
    if dropped:
        left_out[INVALID_POINTS] = left_out.get(INVALID_POINTS, 0) + dropped
    return sweep


# --------------------------------------------------------------------------------------------
# Boxes and frames


def _repeated_ids(ids: list[str]) -> dict[int, InvalidRecord]:
    """Errors for the labels whose id an earlier label of the frame already has, by position."""
    first: dict[str, int] = {}
    out: dict[int, InvalidRecord] = {}
    for i, track in enumerate(ids):
        if track in first:
            out[i] = InvalidRecord(f"box {track!r}", f"repeats the id of laser label {first[track]}", index=i)
        else:
            first[track] = i
    return out


def boxes(
    labels: RawLabels,
    world_from_vehicle: NDArray[np.float64],
    where: str = "",
    problems: Problems | None = None,
    left_out: dict[str, int] | None = None,
) -> Boxes:
    """Laser labels (vehicle frame of the frame pose) as world-frame boxes.

    A label with an invalid field (a non-finite centre, size, heading or speed, a size <= 0, an
    id another label of the frame has) raises naming ``where``, the label's id and the field,
    or under ``skip`` is left out (``INVALID_BOXES`` in ``left_out``).
    """
    problems = problems or Problems()
    left_out = {} if left_out is None else left_out
    m = len(labels)
    rot = world_from_vehicle[:3, :3]
    heading = labels.box[:, 6]
    with np.errstate(invalid="ignore", over="ignore"):
        # Waymo boxes are upright in the (pitched, rolled) vehicle frame: keep that tilt.
        world_from_box = rot @ geometry.rotation_z(heading)
        direction = world_from_box[:, :, 0]
        class_lut = np.vectorize(lambda t: BOX_CLASS_IDS.get(int(t), tx.IGNORE_ID), otypes=[np.uint8])
        fields = {
            "track_id": list(labels.ids),
            "class_id": class_lut(labels.types) if m else np.zeros(0, np.uint8),
            "center_world": geometry.transform_points(world_from_vehicle, labels.box[:, :3]),
            "size_lwh": labels.box[:, 3:6],
            "yaw_world": np.arctan2(direction[:, 1], direction[:, 0]),
            "velocity_world": labels.speed @ rot.T,
            "status": np.zeros(m, np.uint8),
            "instance_id": np.zeros(m, np.uint16),
            "num_lidar_points": labels.num_lidar_points,
            "acceleration_world": labels.accel @ rot.T,
            "orientation_world": geometry.matrix_to_quaternion(world_from_box).reshape(m, 4),
        }
    repeated = _repeated_ids(fields["track_id"])
    unique = np.array([i not in repeated for i in range(m)], bool)
    kept = np.flatnonzero(unique)
    subset = {k: [v[i] for i in kept] if k == "track_id" else v[unique] for k, v in fields.items()}
    built, invalid = Boxes.without_invalid(**subset)
    errors = dict(repeated)
    errors.update({int(kept[e.index]): e for e in invalid if e.index is not None})
    for i in sorted(errors):
        problems.report(WaymoFormatError(f"{where}: laser label {i}: {errors[i]}"), INVALID_BOXES, left_out)
    return built


def rig_calibrations(raw: RawFrame, problems: Problems | None = None) -> list[CameraCalibration]:
    """The frame's camera calibrations in camera-code order (FRONT first), matched by name.

    An invalid calibration raises naming the frame, or under ``skip`` leaves that camera out of
    the rig (and so out of every frame of the segment).
    """
    problems = problems or Problems()
    rig = []
    for c in sorted(raw.camera_calibrations, key=lambda c: c.name):
        try:
            error = raw.invalid_sensors.get(("camera_calibration", c.name))
            if error is not None:
                raise error
            rig.append(_calibration_of(raw, c))
        except WaymoFormatError as e:
            problems.report(e, CAMERAS_LEFT_OUT, {})
    for (part, code), error in raw.invalid_sensors.items():
        if part == "camera_calibration" and all(c.name != code for c in raw.camera_calibrations):
            problems.report(error, CAMERAS_LEFT_OUT, {})  # given twice, or unreadable
    return rig


def _calibration_of(raw: RawFrame, calibration: RawCameraCalibration) -> CameraCalibration:
    """:func:`camera_calibration` with errors naming the frame."""
    try:
        return camera_calibration(calibration)
    except WaymoFormatError as e:
        raise WaymoFormatError(f"{raw.where}: {e}") from None


@dataclass
class _FrameContext:
    """What converting one frame's cameras needs besides the raw frame."""

    raw: RawFrame
    global_origin: NDArray[np.float64]
    time_micros: int
    world_from_ego: NDArray[np.float64]
    rig: frozenset[str] | None
    images: bool = True


def _camera(ctx: _FrameContext, code: int, images: dict[int, RawCameraImage]) -> CameraImage:
    """Camera ``code`` of the frame; raises :class:`WaymoFormatError` naming the frame, the camera
    and the field if anything about it is invalid."""
    raw = ctx.raw
    for part in ("camera_calibration", "camera"):
        error = raw.invalid_sensors.get((part, code))
        if error is not None:
            raise error
    calibration = _calibration_of(raw, raw.camera_calibration(code))  # raises if not calibrated
    if ctx.rig is not None and calibration.name not in ctx.rig:
        raise WaymoFormatError(
            f"{raw.where}: camera {calibration.name} is not in the segment's rig (the first frame "
            f"calibrates {sorted(ctx.rig)})"
        )
    if code in images:
        return camera_image(
            images[code], calibration, ctx.global_origin, raw.where_of("camera"), ctx.time_micros, ctx.images
        )
    return _record(raw.where, lambda: CameraImage(calibration, ctx.time_micros, ctx.world_from_ego, None))


def _cameras(ctx: _FrameContext, problems: Problems, left_out: dict[str, int]) -> list[CameraImage]:
    """Every camera of the frame that has a calibration or an image, in camera-code order."""
    raw = ctx.raw
    images: dict[int, RawCameraImage] = {}
    for im in raw.images:
        if im.name in images:
            error = WaymoFormatError(
                f"{raw.where_of('camera')}: two images of camera {_camera_name(im.name)}"
            )
            raw.mark_invalid("camera", im.name, error)
        images[im.name] = im
    codes = {c.name for c in raw.camera_calibrations} | set(images)
    codes |= {code for part, code in raw.invalid_sensors if part in ("camera", "camera_calibration")}
    cameras = []
    for code in sorted(codes):
        try:
            cameras.append(_camera(ctx, code, images))
        except WaymoFormatError as e:
            problems.report(e, CAMERAS_LEFT_OUT, left_out)
    return cameras


def frame(
    raw: RawFrame,
    frame_index: int,
    global_origin: NDArray[np.float64],
    problems: Problems | None = None,
    dropped: DroppedValues | None = None,
    rig: frozenset[str] | None = None,
    images: bool = True,
) -> Frame:
    """One raw Waymo frame as a :class:`Frame` (world frame = global shifted to ``global_origin``).

    Every calibrated camera gets an entry; a camera with no image in this frame (labels-only
    data) has ``image_bytes=None`` and the frame's time and pose. ``rig``: the names of the
    segment's cameras (a camera outside it is invalid). Invalid parts raise naming the file,
    record and field, or under ``problems`` = skip are left out and counted in ``dropped``
    (once per frame however often it is converted).

    ``images=False`` gives the frame's geometry (poses, LiDAR, boxes; cameras with their times
    and poses): no image bytes or labels, and no JPEG decoded to check it, for scene-wide
    stages (:meth:`LazyFrames.geometry`).
    """
    problems = problems or Problems()
    left_out: dict[str, int] = {}
    world_from_ego = _shift(raw.global_from_vehicle, global_origin)
    t_micros = raw.timestamp_micros + POSE_TIME_OFFSET_MICROS
    ctx = _FrameContext(raw, global_origin, t_micros, world_from_ego, rig, images)
    cameras = _cameras(ctx, problems, left_out)
    lidar = lidar_sweep(raw, t_micros, world_from_ego, problems, left_out)
    frame_boxes = boxes(raw.labels, world_from_ego, raw.where_of("labels"), problems, left_out)
    out = _record(
        raw.where,
        lambda: Frame(
            scene_id=raw.segment,
            frame_index=frame_index,
            timestamp_micros=t_micros,
            world_from_ego=world_from_ego,
            cameras=cameras,
            lidar=lidar,
            boxes=frame_boxes,
            source_timestamp_micros=raw.timestamp_micros,
        ),
    )
    if dropped is not None:
        for kind, count in left_out.items():
            dropped.add(kind, frame_index, count)
    return out
