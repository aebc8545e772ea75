"""The in-memory scene model: what every source produces and every stage consumes.

Frames and units (see ../geometry.py for the conventions):

- ``world``: a fixed frame per scene with its origin at the first frame's ego pose; metres.
- ``ego``: x forward, y left, z up, origin on the ground below the rear axle; metres.
- ``camera``: OpenCV axes (x right, y down, z forward).
- Time: int64 microseconds (``*_micros``). Transforms: 4x4 float64 ``target_from_source``.
- Boxes: upright, centre/size/yaw in the world frame, size as (length, width, height).
- Semantic ids: the unified taxonomy in :mod:`phigenesis.data.taxonomy` (uint8, 255 = ignore).

Records validate their shapes and dtypes on construction and say which field is wrong.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.range_records import LidarRangeImage, RangeViewLayout

BoxStatus = Literal["annotated", "interpolated", "extrapolated"]
BOX_STATUSES: tuple[BoxStatus, ...] = ("annotated", "interpolated", "extrapolated")
ImageFormat = Literal["jpeg", "png"]
#: How a camera reads its pixels out: all at once ("global"), or line by line in a direction.
ReadoutDirection = Literal[
    "global", "top_to_bottom", "left_to_right", "bottom_to_top", "right_to_left", "unknown"
]
READOUT_DIRECTIONS: tuple[ReadoutDirection, ...] = (
    "global",
    "top_to_bottom",
    "left_to_right",
    "bottom_to_top",
    "right_to_left",
    "unknown",
)


def _check_array(
    name: str, value: Any, shape: tuple[int | None, ...], dtype: type | None = None
) -> np.ndarray:
    """Returns ``value`` as an array after checking its shape (None = any size) and dtype."""
    arr = np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _check_transform(name: str, value: Any) -> NDArray[np.float64]:
    t = _check_array(name, value, (4, 4), np.float64)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} has non-finite entries")
    if not np.allclose(t[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} is not a rigid transform: last row is {t[3]}")
    return t


@dataclass(frozen=True)
class CameraCalibration:
    """A camera's fixed calibration.

    Attributes:
        name: the camera's name in its dataset (``FRONT``, ``CAM_FRONT_LEFT``); cameras are matched
            by name, never by position.
        width, height: image size in pixels.
        intrinsics: (3, 3) float64 OpenCV K for images of this size.
        distortion: (5,) float64 OpenCV coefficients (k1, k2, p1, p2, k3).
        ego_from_camera: (4, 4) float64, camera axes OpenCV (x right, y down, z forward).
        readout_direction: "global" for a global shutter, else the rolling shutter's direction
            (see :meth:`CameraImage.pixel_time_micros`).
    """

    name: str
    width: int
    height: int
    intrinsics: NDArray[np.float64]
    distortion: NDArray[np.float64]
    ego_from_camera: NDArray[np.float64]
    readout_direction: ReadoutDirection = "global"

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(
                f"camera {self.name}: image size must be positive, got {self.width}x{self.height}"
            )
        if self.readout_direction not in READOUT_DIRECTIONS:
            raise ValueError(
                f"camera {self.name}: readout_direction must be one of {READOUT_DIRECTIONS}, "
                f"got {self.readout_direction!r}"
            )
        object.__setattr__(
            self, "intrinsics", _check_array("intrinsics", self.intrinsics, (3, 3), np.float64)
        )
        object.__setattr__(self, "distortion", _check_array("distortion", self.distortion, (5,), np.float64))
        object.__setattr__(self, "ego_from_camera", _check_transform("ego_from_camera", self.ego_from_camera))

    def key(self) -> tuple:
        """A hashable key, equal for equal calibrations (name, size and the matrices' bytes): for
        caching what depends only on the camera (pixel rays, range-view layouts)."""
        return (
            self.name,
            self.width,
            self.height,
            self.intrinsics.tobytes(),
            self.distortion.tobytes(),
            self.ego_from_camera.tobytes(),
        )


@dataclass
class CameraTruth:
    """Exact per-pixel truth of one image (synthetic sources), all (H, W) at the image's size.

    Attributes:
        depth_m: float32 z-depth along the camera's +z in metres; 0 where no surface (sky).
        semantic: uint8 class id per pixel (unified taxonomy, 255 = ignore, e.g. the ego body).
        instance: uint16 object instance id (the box's ``instance_id``), 0 for stuff.
        flow_world_mps: float32 (H, W, 3) velocity of the visible surface point in the world frame,
            m/s (0 for static surfaces and sky).
    """

    depth_m: NDArray[np.float32]
    semantic: NDArray[np.uint8]
    instance: NDArray[np.uint16]
    flow_world_mps: NDArray[np.float32]

    def __post_init__(self) -> None:
        self.depth_m = _check_array("depth_m", self.depth_m, (None, None), np.float32)
        h, w = self.depth_m.shape
        self.semantic = _check_array("semantic", self.semantic, (h, w), np.uint8)
        self.instance = _check_array("instance", self.instance, (h, w), np.uint16)
        self.flow_world_mps = _check_array("flow_world_mps", self.flow_world_mps, (h, w, 3), np.float32)


@dataclass
class CameraLabels:
    """Human per-pixel labels of one image (a dataset's panoptic labels), (H, W) at the image's size.

    Attributes:
        semantic: uint8 class id per pixel, mapped into the unified taxonomy (255 = unlabelled).
        instance: uint16 instance id per pixel (the dataset's id, consistent across the cameras and
            frames of a scene where the dataset says so), 0 for stuff and unlabelled pixels.
    """

    semantic: NDArray[np.uint8]
    instance: NDArray[np.uint16]

    def __post_init__(self) -> None:
        self.semantic = _check_array("semantic", self.semantic, (None, None), np.uint8)
        self.instance = _check_array("instance", self.instance, self.semantic.shape, np.uint16)


#: What a sparse depth pixel came from (:attr:`CameraDepth.sparse_origin`).
DEPTH_ORIGINS: tuple[str, ...] = ("none", "static_map", "rigid_object", "non_rigid_object", "single_sweep")
#: Sparse depths with at least this confidence are the ones to train on: densification seeds only
#: from them and the depth benchmark scores them (pixels at depth edges fall below it).
TRUSTED_DEPTH_CONFIDENCE = 0.5


@dataclass
class CameraDepth:
    """Depth ground truth built from LiDAR for one image, (H, W) at the image's size.

    Depths are metres along the camera's +z (z-depth, as :attr:`CameraTruth.depth_m`), 0 where
    unknown; confidences are in [0, 1] and 0 exactly where the depth is unknown.

    Attributes:
        sparse_m: float32 LiDAR points projected into the image at its own capture time and pose
            (nearest point per pixel, after the visibility test).
        sparse_confidence: float32 confidence of ``sparse_m``.
        sparse_origin: uint8 index into :data:`DEPTH_ORIGINS` per pixel (what the point came from).
        dense_m: float32 densified depth, or None before densification.
        dense_confidence: float32 confidence of ``dense_m`` (None with it).
    """

    sparse_m: NDArray[np.float32]
    sparse_confidence: NDArray[np.float32]
    sparse_origin: NDArray[np.uint8]
    dense_m: NDArray[np.float32] | None = None
    dense_confidence: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        self.sparse_m = _check_array("sparse_m", self.sparse_m, (None, None), np.float32)
        shape = self.sparse_m.shape
        self.sparse_confidence = _check_array("sparse_confidence", self.sparse_confidence, shape, np.float32)
        self.sparse_origin = _check_array("sparse_origin", self.sparse_origin, shape, np.uint8)
        if (self.dense_m is None) != (self.dense_confidence is None):
            raise ValueError("dense_m and dense_confidence come together (both or neither)")
        if self.dense_m is not None:
            self.dense_m = _check_array("dense_m", self.dense_m, shape, np.float32)
            self.dense_confidence = _check_array("dense_confidence", self.dense_confidence, shape, np.float32)

    @classmethod
    def empty(cls, height: int, width: int) -> CameraDepth:
        """No depth anywhere (zero confidence): what an image without LiDAR gets."""
        zeros = np.zeros((height, width), np.float32)
        return cls(zeros, zeros.copy(), np.zeros((height, width), np.uint8))


#: Where a pseudo-semantic label came from (:attr:`CameraSemantics.source`).
PSEUDO_SOURCES: tuple[str, ...] = ("none", "segmenter", "box", "ground_plane", "sky")


@dataclass
class CameraSemantics:
    """Pseudo-semantic labels of one image (stage ``pseudo_semantics``), (H, W) at the image's size.

    Attributes:
        semantic: uint8 class per pixel (unified taxonomy), 255 where no label was given.
        confidence: float32 in [0, 1], 0 exactly where no label was given.
        source: uint8 index into :data:`PSEUDO_SOURCES` (0 = none).
    """

    semantic: NDArray[np.uint8]
    confidence: NDArray[np.float32]
    source: NDArray[np.uint8]

    def __post_init__(self) -> None:
        self.semantic = _check_array("semantic", self.semantic, (None, None), np.uint8)
        self.confidence = _check_array("confidence", self.confidence, self.semantic.shape, np.float32)
        self.source = _check_array("source", self.source, self.semantic.shape, np.uint8)


@dataclass
class CameraImage:
    """One image of one camera.

    Attributes:
        calibration: the camera's calibration.
        timestamp_micros: capture time: the centre of the exposure (for a rolling shutter, of the
            image's middle line; Waymo gives the time of its image pose, within a few ms of it).
        world_from_ego: (4, 4) ego pose at ``timestamp_micros`` (not the frame's pose).
        image_bytes: the image encoded as stored (``image_format``), or None if the source has none.
        image_format: "jpeg" or "png".
        truth: exact per-pixel truth where the source has it.
        labels: human per-pixel labels where the dataset has them.
        depth: depth ground truth built from LiDAR by the depth stages, where they ran.
        trigger_micros: when the sensor was triggered (None: taken as ``timestamp_micros``).
        shutter_micros: exposure time of each line, microseconds (0 for an instantaneous capture).
        readout_micros: time from the first to the last line's readout, microseconds (0 for a
            global shutter).
        velocity_world_mps: (3,) ego velocity at ``timestamp_micros`` in the world frame, or None.
        angular_velocity_world_radps: (3,) ego angular velocity (world axes), or None.
        boxes: the boxes at this camera's own ``timestamp_micros`` where a stage made them
            (``interpolate_boxes`` for nuScenes' staggered cameras); None: use the frame's boxes.
        pseudo: pseudo-semantic labels from the ``pseudo_semantics`` stage, where it ran.
    """

    calibration: CameraCalibration
    timestamp_micros: int
    world_from_ego: NDArray[np.float64]
    image_bytes: bytes | None
    image_format: ImageFormat = "jpeg"
    truth: CameraTruth | None = None
    labels: CameraLabels | None = None
    depth: CameraDepth | None = None
    trigger_micros: int | None = None
    shutter_micros: float = 0.0
    readout_micros: float = 0.0
    velocity_world_mps: NDArray[np.float64] | None = None
    angular_velocity_world_radps: NDArray[np.float64] | None = None
    boxes: Boxes | None = None
    pseudo: CameraSemantics | None = None
    # The decoded image with the bytes it came from: several stages read one frame's images
    # (projection, densification, labels), and each JPEG should be decoded once.
    _decoded: tuple[bytes, NDArray[np.uint8]] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.timestamp_micros = int(self.timestamp_micros)
        self.world_from_ego = _check_transform("world_from_ego", self.world_from_ego)
        size = (self.calibration.height, self.calibration.width)
        for what, shape in (
            ("truth", None if self.truth is None else self.truth.semantic.shape),
            ("labels", None if self.labels is None else self.labels.semantic.shape),
            ("depth", None if self.depth is None else self.depth.sparse_m.shape),
            ("pseudo", None if self.pseudo is None else self.pseudo.semantic.shape),
        ):
            if shape is not None and shape != size:
                raise ValueError(
                    f"camera {self.calibration.name}: {what} is {shape}, calibration says {size}"
                )
        if self.trigger_micros is not None:
            self.trigger_micros = int(self.trigger_micros)
        self.shutter_micros = float(self.shutter_micros)
        self.readout_micros = float(self.readout_micros)
        if self.shutter_micros < 0 or self.readout_micros < 0:
            raise ValueError(
                f"camera {self.calibration.name}: shutter and readout must be >= 0, "
                f"got {self.shutter_micros} and {self.readout_micros}"
            )
        if self.velocity_world_mps is not None:
            self.velocity_world_mps = _check_array(
                "velocity_world_mps", self.velocity_world_mps, (3,), np.float64
            )
        if self.angular_velocity_world_radps is not None:
            self.angular_velocity_world_radps = _check_array(
                "angular_velocity_world_radps", self.angular_velocity_world_radps, (3,), np.float64
            )

    def pixel_time_micros(self, u: NDArray[np.floating], v: NDArray[np.floating]) -> NDArray[np.float64]:
        """Capture time (microseconds) of pixels at (u, v) (OpenCV pixel-centre coordinates).

        A line's time is the centre of its exposure: ``trigger + shutter / 2 + readout * f`` with
        ``f`` the line's position along the readout direction (0 first line, 1 last). A global
        shutter (or no timing) gives ``timestamp_micros`` everywhere.
        """
        u, v = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64))
        cal = self.calibration
        direction = cal.readout_direction
        if self.trigger_micros is None or direction in ("global", "unknown") or self.readout_micros == 0:
            return np.full(u.shape, float(self.timestamp_micros))
        position = {
            "top_to_bottom": (v + 0.5) / cal.height,
            "bottom_to_top": 1.0 - (v + 0.5) / cal.height,
            "left_to_right": (u + 0.5) / cal.width,
            "right_to_left": 1.0 - (u + 0.5) / cal.width,
        }[direction]
        return self.trigger_micros + 0.5 * self.shutter_micros + self.readout_micros * position

    @property
    def name(self) -> str:
        return self.calibration.name

    @property
    def world_from_camera(self) -> NDArray[np.float64]:
        """(4, 4) camera pose in the world at the capture time."""
        return self.world_from_ego @ self.calibration.ego_from_camera

    def decode_image(self) -> NDArray[np.uint8]:
        """The image as (H, W, 3) uint8 RGB; raises if there is none or it does not decode."""
        if self.image_bytes is None:
            raise ValueError(f"camera {self.name} at {self.timestamp_micros}: this frame has no image")
        if self._decoded is None or self._decoded[0] is not self.image_bytes:
            rgb = decode_rgb(self.image_bytes, f"camera {self.name} at {self.timestamp_micros}")
            self._decoded = (self.image_bytes, rgb)
        return self._decoded[1].copy()


def decode_rgb(data: bytes, what: str) -> NDArray[np.uint8]:
    """Decodes JPEG/PNG bytes to (H, W, 3) uint8 RGB; ``what`` names the image in errors."""
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{what}: image bytes do not decode ({len(data)} bytes)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def encode_rgb(rgb: NDArray[np.uint8], image_format: ImageFormat = "jpeg", jpeg_quality: int = 95) -> bytes:
    """Encodes (H, W, 3) uint8 RGB as JPEG or PNG bytes."""
    rgb = _check_array("rgb", rgb, (None, None, 3), np.uint8)
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if image_format == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ValueError(f"could not encode a {rgb.shape} image as {image_format}")
    return buf.tobytes()


@dataclass
class LidarSweep:
    """One sweep of the LiDAR(s), points in the ego frame at the sweep's reference time.

    Attributes (N points):
        timestamp_micros: reference time; ``points_ego`` are in the ego frame at this time
            (motion-compensated, as Waymo provides them).
        world_from_ego: (4, 4) ego pose at ``timestamp_micros``.
        points_ego: (N, 3) float32 metres.
        intensity: (N,) float32, in [0, 1] for synthetic data, raw for datasets.
        beam_index: (N,) uint16 laser row (0 = highest beam).
        origins_ego: (N, 3) float32 position of the sensor when the point was measured, in the same
            ego frame (ray origin; differs from the mount position when the ego moves).
        time_offset_micros: (N,) int32 measurement time minus ``timestamp_micros``.
        lidar_id: (N,) uint8 which sensor (0 for a single LiDAR).
        semantic: (N,) uint8 truth class per point, or None.
        instance: (N,) uint16 truth instance per point (0 = stuff), or None.
        elongation: (N,) float32 pulse elongation per point (Waymo), or None.
        return_index: (N,) uint8 0 for the strongest (first) return, 1 for the second; None =
            all first returns.
    """

    timestamp_micros: int
    world_from_ego: NDArray[np.float64]
    points_ego: NDArray[np.float32]
    intensity: NDArray[np.float32]
    beam_index: NDArray[np.uint16]
    origins_ego: NDArray[np.float32]
    time_offset_micros: NDArray[np.int32]
    lidar_id: NDArray[np.uint8]
    semantic: NDArray[np.uint8] | None = None
    instance: NDArray[np.uint16] | None = None
    elongation: NDArray[np.float32] | None = None
    return_index: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        self.timestamp_micros = int(self.timestamp_micros)
        self.world_from_ego = _check_transform("world_from_ego", self.world_from_ego)
        self.points_ego = _check_array("points_ego", self.points_ego, (None, 3), np.float32)
        n = len(self.points_ego)
        self.intensity = _check_array("intensity", self.intensity, (n,), np.float32)
        self.beam_index = _check_array("beam_index", self.beam_index, (n,), np.uint16)
        self.origins_ego = _check_array("origins_ego", self.origins_ego, (n, 3), np.float32)
        self.time_offset_micros = _check_array("time_offset_micros", self.time_offset_micros, (n,), np.int32)
        self.lidar_id = _check_array("lidar_id", self.lidar_id, (n,), np.uint8)
        if self.semantic is not None:
            self.semantic = _check_array("semantic", self.semantic, (n,), np.uint8)
        if self.instance is not None:
            self.instance = _check_array("instance", self.instance, (n,), np.uint16)
        if self.elongation is not None:
            self.elongation = _check_array("elongation", self.elongation, (n,), np.float32)
        if self.return_index is not None:
            self.return_index = _check_array("return_index", self.return_index, (n,), np.uint8)

    def __len__(self) -> int:
        return len(self.points_ego)

    def points_world(self) -> NDArray[np.float64]:
        """(N, 3) float64 points in the world frame."""
        return geometry.transform_points(self.world_from_ego, self.points_ego)

    @classmethod
    def empty(cls, timestamp_micros: int, world_from_ego: NDArray[np.float64]) -> LidarSweep:
        """A sweep with no points (the LiDAR saw nothing or the frame has none)."""
        return cls(
            timestamp_micros=timestamp_micros,
            world_from_ego=world_from_ego,
            points_ego=np.zeros((0, 3), np.float32),
            intensity=np.zeros(0, np.float32),
            beam_index=np.zeros(0, np.uint16),
            origins_ego=np.zeros((0, 3), np.float32),
            time_offset_micros=np.zeros(0, np.int32),
            lidar_id=np.zeros(0, np.uint8),
        )


@dataclass
class Boxes:
    """The 3D boxes of one timestamp, as parallel arrays (M boxes), in the world frame.

    Attributes:
        track_id: M strings, stable for an object within its scene.
        class_id: (M,) uint8 unified-taxonomy class.
        center_world: (M, 3) float64 box centre, metres.
        size_lwh: (M, 3) float64 length (along heading), width, height, metres.
        yaw_world: (M,) float64 heading about +z, radians in [-pi, pi).
        velocity_world: (M, 3) float64 velocity of the centre, m/s.
        status: (M,) uint8 index into :data:`BOX_STATUSES` (annotated, interpolated, extrapolated).
        instance_id: (M,) uint16 id used in instance maps, 0 if the source has none.
        num_lidar_points: (M,) int32 LiDAR points inside the box in its frame's sweep, -1 if unknown.
        acceleration_world: (M, 3) float64 acceleration of the centre, m/s^2; NaN where unknown
            (None on construction means unknown for all).
        orientation_world: (M, 4) float64 wxyz quaternion world <- box. Boxes are upright in the
            world unless a dataset tilts them (Waymo labels are upright in the tilted ego frame);
            None on construction means upright at ``yaw_world``. ``yaw_world`` is the heading of
            the box's +x axis in the ground plane either way.
    """

    track_id: list[str]
    class_id: NDArray[np.uint8]
    center_world: NDArray[np.float64]
    size_lwh: NDArray[np.float64]
    yaw_world: NDArray[np.float64]
    velocity_world: NDArray[np.float64]
    status: NDArray[np.uint8]
    instance_id: NDArray[np.uint16]
    num_lidar_points: NDArray[np.int32]
    acceleration_world: NDArray[np.float64] | None = None
    orientation_world: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        self.track_id = [str(t) for t in self.track_id]
        m = len(self.track_id)
        self.class_id = _check_array("class_id", self.class_id, (m,), np.uint8)
        self.center_world = _check_array("center_world", self.center_world, (m, 3), np.float64)
        self.size_lwh = _check_array("size_lwh", self.size_lwh, (m, 3), np.float64)
        self.yaw_world = geometry.wrap_angle(_check_array("yaw_world", self.yaw_world, (m,), np.float64))
        self.velocity_world = _check_array("velocity_world", self.velocity_world, (m, 3), np.float64)
        self.status = _check_array("status", self.status, (m,), np.uint8)
        self.instance_id = _check_array("instance_id", self.instance_id, (m,), np.uint16)
        self.num_lidar_points = _check_array("num_lidar_points", self.num_lidar_points, (m,), np.int32)
        if self.acceleration_world is None:
            self.acceleration_world = np.full((m, 3), np.nan)
        self.acceleration_world = _check_array(
            "acceleration_world", self.acceleration_world, (m, 3), np.float64
        )
        if self.orientation_world is None:
            self.orientation_world = geometry.yaw_to_quaternion(self.yaw_world).reshape(m, 4)
        self.orientation_world = geometry.quaternion_normalize(
            _check_array("orientation_world", self.orientation_world, (m, 4), np.float64)
        )
        if np.any(self.status >= len(BOX_STATUSES)):
            raise ValueError(f"box status codes must be < {len(BOX_STATUSES)}, got {np.unique(self.status)}")
        if np.any(self.size_lwh < 0):
            raise ValueError("box sizes must be non-negative")

    def __len__(self) -> int:
        return len(self.track_id)

    @classmethod
    def empty(cls) -> Boxes:
        return cls(
            track_id=[],
            class_id=np.zeros(0, np.uint8),
            center_world=np.zeros((0, 3)),
            size_lwh=np.zeros((0, 3)),
            yaw_world=np.zeros(0),
            velocity_world=np.zeros((0, 3)),
            status=np.zeros(0, np.uint8),
            instance_id=np.zeros(0, np.uint16),
            num_lidar_points=np.zeros(0, np.int32),
        )

    @classmethod
    def concatenate(cls, parts: Sequence[Boxes]) -> Boxes:
        """All boxes of ``parts`` in order as one :class:`Boxes` (empty if there are none)."""
        if not parts:
            return cls.empty()
        arrays = [f.name for f in fields(cls) if f.name != "track_id"]
        return cls(
            track_id=[t for b in parts for t in b.track_id],
            **{name: np.concatenate([getattr(b, name) for b in parts]) for name in arrays},
        )

    def select(self, index: NDArray[np.bool_] | NDArray[np.integer]) -> Boxes:
        """The subset of boxes given by a boolean mask or an index array."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=np.int64)
        return Boxes(
            track_id=[self.track_id[i] for i in idx],
            class_id=self.class_id[idx],
            center_world=self.center_world[idx],
            size_lwh=self.size_lwh[idx],
            yaw_world=self.yaw_world[idx],
            velocity_world=self.velocity_world[idx],
            status=self.status[idx],
            instance_id=self.instance_id[idx],
            num_lidar_points=self.num_lidar_points[idx],
            acceleration_world=self.acceleration_world[idx],
            orientation_world=self.orientation_world[idx],
        )

    def corners_world(self) -> NDArray[np.float64]:
        """(M, 8, 3) corners in the world frame (Waymo corner order), tilt included."""
        rotation = geometry.quaternion_to_matrix(self.orientation_world)
        return geometry.rotated_box_corners(self.center_world, self.size_lwh, rotation)

    def status_names(self) -> list[BoxStatus]:
        return [BOX_STATUSES[s] for s in self.status]


@dataclass
class Frame:
    """One time step of a scene: a LiDAR sweep (if any), the images near it, and the boxes.

    Attributes:
        scene_id: the scene this frame belongs to.
        frame_index: 0-based position in the scene.
        timestamp_micros: the frame's reference time (the LiDAR sweep's reference time).
        world_from_ego: (4, 4) ego pose at ``timestamp_micros``.
        cameras: the images of this frame, one per camera, each at its own capture time.
        lidar: the sweep, or None if the frame has no LiDAR.
        boxes: the boxes at ``timestamp_micros``.
        source_timestamp_micros: the frame's timestamp as its dataset keys it (Waymo's
            ``frame_timestamp_micros`` is the start of the LiDAR scan, 50 ms before the pose's
            time); None means ``timestamp_micros``.
        range_view: where each camera view sits in the frame's range view, and the overlap map
            (stage ``range_view``; the pixels are the cameras' own: ``rangeview.pack_range_view``).
        lidar_range_image: the sweep as a beams x azimuth image (stage ``lidar_range_image``).
    """

    scene_id: str
    frame_index: int
    timestamp_micros: int
    world_from_ego: NDArray[np.float64]
    cameras: list[CameraImage]
    lidar: LidarSweep | None
    boxes: Boxes
    source_timestamp_micros: int | None = None
    range_view: RangeViewLayout | None = None
    lidar_range_image: LidarRangeImage | None = None

    def __post_init__(self) -> None:
        self.timestamp_micros = int(self.timestamp_micros)
        self.source_timestamp_micros = int(
            self.timestamp_micros if self.source_timestamp_micros is None else self.source_timestamp_micros
        )
        self.world_from_ego = _check_transform("world_from_ego", self.world_from_ego)
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"frame {self.scene_id}/{self.frame_index}: duplicate camera names {names}")

    def camera(self, name: str) -> CameraImage:
        """The image of the camera called ``name``."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"frame {self.scene_id}/{self.frame_index} has no camera {name!r}")


class LazyFrames(Sequence[Frame]):
    """A sequence of frames produced on demand by ``load(index)`` (nothing is cached).

    Sources use it so a scene of hundreds of frames never sits in memory at once; stages can wrap
    one lazily with :meth:`map`. A source that can produce a frame's geometry (poses, LiDAR,
    boxes, calibrations, but no image bytes or per-pixel maps) much more cheaply than the whole
    frame passes ``load_geometry``; scene-wide stages (LiDAR aggregation) read frames that way.
    """

    def __init__(
        self, count: int, load: Callable[[int], Frame], load_geometry: Callable[[int], Frame] | None = None
    ):
        self._count = int(count)
        self._load = load
        self._load_geometry = load_geometry or load

    def __len__(self) -> int:
        return self._count

    @overload
    def __getitem__(self, index: int) -> Frame: ...

    @overload
    def __getitem__(self, index: slice) -> list[Frame]: ...

    def __getitem__(self, index: int | slice) -> Frame | list[Frame]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._count))]
        return self._load(self._check(index))

    def _check(self, index: int) -> int:
        if index < 0:
            index += self._count
        if not 0 <= index < self._count:
            raise IndexError(f"frame index {index} out of range for {self._count} frames")
        return index

    def __iter__(self) -> Iterator[Frame]:
        for i in range(self._count):
            yield self._load(i)

    def geometry(self, index: int) -> Frame:
        """Frame ``index`` without image bytes or per-pixel maps where the source can skip them
        (the whole frame otherwise); stages applied with :meth:`map` apply here too."""
        return self._load_geometry(self._check(index))

    def map(self, fn: Callable[[Frame], Frame]) -> LazyFrames:
        """A lazy sequence that applies ``fn`` to each frame when it is loaded (``fn`` must
        accept geometry-only frames as well)."""
        return LazyFrames(self._count, lambda i: fn(self._load(i)), lambda i: fn(self._load_geometry(i)))


def frame_geometry(frames: Sequence[Frame], index: int) -> Frame:
    """Frame ``index`` of any frame sequence, geometry only where the sequence can skip the rest."""
    return frames.geometry(index) if isinstance(frames, LazyFrames) else frames[index]


@dataclass
class KeyframeBoxes:
    """The annotated boxes of one keyframe (nuScenes' 2 Hz samples), in the world frame.

    Sources whose annotations are sparser than their frames (nuScenes) put every keyframe's
    boxes in :attr:`Scene.keyframes`; the ``interpolate_boxes`` stage turns them into boxes at
    every frame's and every camera's own timestamp.

    Attributes:
        timestamp_micros: the keyframe's time (nuScenes: the LIDAR_TOP keyframe time).
        boxes: the annotations, status "annotated"; ``track_id`` is the instance token.
        token: the source's id of the keyframe (nuScenes sample token), "" if none.
    """

    timestamp_micros: int
    boxes: Boxes
    token: str = ""


class DroppedValues:
    """What a source left out of a scene because it was invalid (LiDAR points with non-finite
    coordinates, ...), counted once per frame however often a lazy frame is loaded.

    Sources call :meth:`add` as they build frames; the pipeline records :meth:`totals` in the
    manifest's scene entry and logs them once the scene is written.
    """

    def __init__(self) -> None:
        self._counts: dict[tuple[str, int], int] = {}

    def add(self, what: str, frame_index: int, count: int) -> None:
        """Records that ``count`` items of kind ``what`` (a plural noun phrase, e.g. "LiDAR points
        with non-finite coordinates") were left out of frame ``frame_index``."""
        if count:
            self._counts[(what, int(frame_index))] = int(count)

    def totals(self) -> dict[str, int]:
        """Count per kind over the frames loaded so far."""
        out: dict[str, int] = {}
        for (what, _frame), n in sorted(self._counts.items()):
            out[what] = out.get(what, 0) + n
        return out

    def describe(self) -> str:
        """One line, e.g. ``12 LiDAR points with non-finite coordinates (3 frames)``; "" if none."""
        frames: dict[str, int] = {}
        for what, _frame in self._counts:
            frames[what] = frames.get(what, 0) + 1
        return "; ".join(f"{n} {what} ({frames[what]} frames)" for what, n in self.totals().items())


@dataclass
class Scene:
    """A driving sequence: its frames and what is fixed across them.

    Attributes:
        scene_id: unique within a cache (e.g. ``synthetic-s7-0003``, a Waymo segment name).
        source: which source produced it ("synthetic", "waymo", "nuscenes").
        calibrations: the cameras of the rig, in the rig's order.
        frames: the frames in time order (often a :class:`LazyFrames`).
        metadata: JSON-serialisable facts about the scene (rig name, seed, location, ...); stored
            in the cache.
        products: in-memory results of scene-wide stages for later stages (the aggregated LiDAR
            map), keyed by name; never stored.
        keyframes: annotated keyframes where annotations are sparser than frames (nuScenes), in
            time order; empty where every frame carries its own boxes (Waymo, synthetic).
        dropped: what the source left out because it was invalid (see :class:`DroppedValues`).
    """

    scene_id: str
    source: str
    calibrations: list[CameraCalibration]
    frames: Sequence[Frame]
    metadata: dict[str, Any] = field(default_factory=dict)
    products: dict[str, Any] = field(default_factory=dict)
    keyframes: list[KeyframeBoxes] = field(default_factory=list)
    dropped: DroppedValues = field(default_factory=DroppedValues, compare=False)

    def __len__(self) -> int:
        return len(self.frames)

    def calibration(self, name: str) -> CameraCalibration:
        for cal in self.calibrations:
            if cal.name == name:
                return cal
        raise KeyError(f"scene {self.scene_id} has no camera {name!r}")
