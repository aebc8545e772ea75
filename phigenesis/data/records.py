"""The in-memory scene model: what every source produces and every stage consumes.

Frames and units (see ../geometry.py for the conventions):

- ``world``: a fixed frame per scene with its origin at the first frame's ego pose; metres.
- ``ego``: x forward, y left, z up, origin on the ground below the rear axle; metres.
- ``camera``: OpenCV axes (x right, y down, z forward).
- Time: int64 microseconds (``*_micros``). Transforms: 4x4 float64 ``target_from_source``.
- Boxes: upright, centre/size/yaw in the world frame, size as (length, width, height).
- Semantic ids: the unified taxonomy in :mod:`phigenesis.taxonomy` (uint8, 255 = ignore).

Validation: nothing invalid enters a scene
------------------------------------------
Records check their shapes, dtypes and values on construction and raise :class:`InvalidRecord`
(a ``ValueError``) naming the field: a transform that is not finite and rigid (rotation
orthonormal with determinant +1 within :data:`RIGID_TOLERANCE`, translation within
:data:`MAX_COORDINATE_M`), a box with a non-finite or out-of-range field (named by its track id),
camera intrinsics that are not finite and positive, an encoded image whose size is not its
calibration's, a capture time more than :data:`MAX_SENSOR_OFFSET_MICROS` from its frame's time,
a negative frame time, frame times that do not strictly increase, LiDAR points with non-finite
or out-of-range values. A source catches :class:`InvalidRecord` and raises its own
:class:`~phigenesis.errors.SourceError` with the file and record in front::

    try:
        frame = Frame(...)
    except InvalidRecord as e:
        raise MySourceError(f"{path} (record {k}): {e}") from None

For data it may leave out (``--on-error skip``), a source builds with the helpers that drop and
count instead of raising: :meth:`LidarSweep.without_invalid_points` (returns the sweep and the
number of points dropped, recorded as :data:`INVALID_POINTS` in :attr:`Scene.dropped`) and
:meth:`Boxes.without_invalid` (returns the boxes and one :class:`InvalidRecord` per box left
out, counted as :data:`INVALID_BOXES`); :func:`check_capture_time` checks one sensor's time
before the frame is built, and :func:`check_frame_times` / :func:`increasing_frames` check a
source's index of frame times once, before any frame is loaded. :class:`LazyFrames` checks
each frame it loads against the index it was given (or, without one, against the frames loaded
before it), so no source can hand a stage frames out of time order. A constructor reads an
encoded image's header only; a source calls :meth:`CameraImage.check_image` once for each image
it reads (it costs a decode), so that nothing downstream meets an image that does not decode.
"""

from __future__ import annotations

import bisect
import io
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import image_headers
from phigenesis.data.range_records import LidarRangeImage, RangeViewLayout

BoxStatus = Literal["annotated", "interpolated", "extrapolated"]
BOX_STATUSES: tuple[BoxStatus, ...] = ("annotated", "interpolated", "extrapolated")
ImageFormat = Literal["jpeg", "png"]
IMAGE_FORMATS: tuple[ImageFormat, ...] = ("jpeg", "png")
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

# --------------------------------------------------------------------------------------------
# Validation limits: values beyond them are not physical and would overflow later arithmetic
# (float32 LiDAR columns, squared distances), so the records refuse them.

#: Largest ``max |R^T R - I|`` of a rigid transform's rotation block (float32-stored rotations
#: are ~1e-7 off; a scaled or sheared one is far beyond).
RIGID_TOLERANCE = 1e-4
#: Largest coordinate of any position (transform translations, box centres), metres (10,000 km).
MAX_COORDINATE_M = 1e7
#: Largest coordinate of a LiDAR point or ray origin in the ego frame, metres.
MAX_POINT_DISTANCE_M = 1e4
#: Largest box side, metres.
MAX_BOX_SIZE_M = 1e3
#: Largest image side, pixels (bounds what decoding an image or allocating its maps can cost).
MAX_IMAGE_SIDE = 8192
#: Focal lengths lie in this range, pixels.
FOCAL_RANGE_PX = (0.1, 1e6)
#: Largest |principal point| and |skew|, pixels, and largest |distortion coefficient|.
MAX_INTRINSIC_PX = 1e6
MAX_DISTORTION = 1e3
#: A capture (camera image, LiDAR sweep, trigger) lies within this of its frame's (or image's)
#: time, and an exposure or readout lasts at most this long, microseconds.
MAX_SENSOR_OFFSET_MICROS = 5_000_000
#: Times are int64 microseconds.
INT64_MAX = 2**63 - 1
#: Largest |time| a user-given time (a path's keyframe, a trajectory's frame) may have, microseconds
#: (about 146,000 years after 1970): sums and differences of two such times stay within int64.
MAX_USER_MICROS = 2**62

#: :class:`DroppedValues` kinds of the records' own helpers (sources use the same words).
INVALID_POINTS = "LiDAR points with non-finite or out-of-range values"
INVALID_BOXES = "boxes with invalid fields"


class InvalidRecord(ValueError):
    """A record was given an invalid value: the message is ``"<field> <problem>"``, e.g.
    ``box 'abc' size_lwh [nan, 1.8, 1.5] must be finite and in (0, 1000] m``.

    Attributes:
        field: what is invalid, as the record names it (``world_from_ego``, ``box 'abc'``,
            ``camera FRONT timestamp_micros``).
        problem: what is wrong with it, with the offending value (a predicate of ``field``).
        index: the position in the checked sequence (the frame of :func:`check_frame_times`,
            the box of :meth:`Boxes.without_invalid`), None where there is none.

    It is not a :class:`~phigenesis.errors.PhiGenesisError`: it names no file. A source catches
    it and raises its ``SourceError`` naming the file and record; one that escapes a source is
    reported as a toolkit bug.
    """

    def __init__(self, field: str, problem: str, index: int | None = None):
        super().__init__(f"{field} {problem}")
        self.field = field
        self.problem = problem
        self.index = index


def _check_array(
    name: str, value: Any, shape: tuple[int | None, ...], dtype: type | None = None
) -> np.ndarray:
    """Returns ``value`` as an array after checking its shape (None = any size) and dtype."""
    try:
        arr = np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRecord(name, f"is not an array of {np.dtype(dtype).name} ({e})") from None
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InvalidRecord(name, f"must have shape {want}, got {arr.shape}")
    return arr


def _listed(values: NDArray) -> str:
    """A short text of an array's values for messages (at most 16 shown)."""
    flat = np.asarray(values).ravel()
    shown = ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in flat[:16].tolist())
    return f"[{shown}{', ...' if flat.size > 16 else ''}]"


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def check_transform(name: str, value: Any) -> NDArray[np.float64]:
    """``value`` as a (4, 4) float64 rigid transform ``target_from_source``.

    Raises :class:`InvalidRecord` naming ``name`` if an entry is not finite, the last row is not
    (0, 0, 0, 1), the rotation block is not orthonormal with determinant +1 (within
    :data:`RIGID_TOLERANCE`: a scaled, sheared or mirrored matrix is refused), or the translation
    exceeds :data:`MAX_COORDINATE_M` metres. Sources use it for transforms the scene model does
    not hold (LiDAR extrinsics).
    """
    t = _check_array(name, value, (4, 4), np.float64)
    if not np.all(np.isfinite(t)):
        raise InvalidRecord(name, f"has non-finite entries {_listed(t)}")
    # np.allclose's test (|a - b| <= 1e-8 + 1e-5 |b|) written out: allclose itself costs 0.2 ms a
    # call, and a Waymo frame checks 17 transforms.
    if not (np.abs(t[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all():
        raise InvalidRecord(name, f"is not a rigid transform: last row is {_listed(t[3])}")
    rotation = t[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if not error <= RIGID_TOLERANCE:
        raise InvalidRecord(
            name,
            f"is not a rigid transform: its rotation is not orthonormal (max |R^T R - I| = {error:.3g}, "
            f"tolerance {RIGID_TOLERANCE:g}; rows {_listed(rotation)})",
        )
    if np.linalg.det(rotation) < 0:
        raise InvalidRecord(name, "is not a rigid transform: its rotation is a reflection (determinant -1)")
    if np.abs(t[:3, 3]).max() > MAX_COORDINATE_M:
        raise InvalidRecord(name, f"has a translation {_listed(t[:3, 3])} m beyond {MAX_COORDINATE_M:g} m")
    return t


def _check_micros(name: str, value: Any, minimum: int = -INT64_MAX) -> int:
    """``value`` as int microseconds in [minimum, INT64_MAX]; raises naming ``name`` otherwise."""
    if isinstance(value, (float, np.floating)) and not np.isfinite(value):
        raise InvalidRecord(name, f"is {value}, not a time")
    try:
        micros = int(value)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRecord(name, f"is {value!r}, not a time in microseconds ({e})") from None
    if not minimum <= micros <= INT64_MAX:
        what = "negative" if micros < 0 <= minimum else "outside int64"
        raise InvalidRecord(name, f"is {micros} us, {what}")
    return micros


def check_capture_time(
    name: str, timestamp_micros: int, reference_micros: int, reference: str = "its frame's time"
) -> None:
    """Raises :class:`InvalidRecord` naming ``name`` if a capture at ``timestamp_micros`` lies more
    than :data:`MAX_SENSOR_OFFSET_MICROS` from ``reference_micros`` (``reference`` says what that
    is: the frame's time, or for a trigger the image's)."""
    offset = int(timestamp_micros) - int(reference_micros)
    if abs(offset) > MAX_SENSOR_OFFSET_MICROS:
        raise InvalidRecord(
            name,
            f"is {int(timestamp_micros)} us, {offset / 1e6:+.6g} s from {reference} "
            f"{int(reference_micros)} us (at most {MAX_SENSOR_OFFSET_MICROS / 1e6:g} s)",
        )


def check_frame_times(times_micros: Sequence[int], what: str = "frame") -> None:
    """Raises :class:`InvalidRecord` (``index`` = the first bad position) unless the times are
    non-negative int64 microseconds that strictly increase (no duplicates, no steps back).

    ``what`` names an element in the message ("frame", "keyframe"). Sources call it once on their
    index of frame times, before any frame is loaded.
    """
    previous: int | None = None
    for i, t in enumerate(times_micros):
        try:
            micros = _check_micros(f"{what} {i} timestamp_micros", t, minimum=0)
        except InvalidRecord as e:
            raise InvalidRecord(e.field, e.problem, index=i) from None
        if previous is not None and micros <= previous:
            same = "the same as" if micros == previous else "before"
            raise InvalidRecord(
                f"{what} {i} timestamp_micros",
                f"is {micros} us, {same} {what} {i - 1}'s {previous} us (times must strictly increase)",
                index=i,
            )
        previous = micros


def increasing_frames(times_micros: Sequence[int]) -> list[int]:
    """The positions to keep so that the times strictly increase: the longest strictly increasing
    subsequence of the valid (non-negative int64) times, the earliest such positions on ties.

    For ``--on-error skip``: one corrupt time (a duplicate, a step back, a jump far ahead) loses
    that frame only, not every frame after it.
    """
    valid = []
    for i, t in enumerate(times_micros):
        try:
            valid.append((i, _check_micros("t", t, minimum=0)))
        except InvalidRecord:
            continue
    # From the right: longest[j] = length of the longest increasing run that starts at valid[j].
    longest = [0] * len(valid)
    tails: list[int] = []  # negated first times of runs of each length, ascending
    for j in range(len(valid) - 1, -1, -1):
        k = bisect.bisect_left(tails, -valid[j][1])
        if k == len(tails):
            tails.append(-valid[j][1])
        else:
            tails[k] = -valid[j][1]
        longest[j] = k + 1
    # From the left: take the first element that can still start a run of the length needed.
    keep: list[int] = []
    need, previous = max(longest, default=0), -1
    for j, (i, t) in enumerate(valid):
        if need and longest[j] == need and t > previous:
            keep.append(i)
            need, previous = need - 1, t
    return keep


def encoded_image_size(data: bytes, image_format: ImageFormat, name: str = "image_bytes") -> tuple[int, int]:
    """(width, height) in pixels that encoded image bytes declare, read from the header alone.

    Raises :class:`InvalidRecord` naming ``name`` if the bytes are not a ``image_format`` image
    whose header says its size. Sources compare it with the calibration before anything decodes
    the image (a crafted header can declare gigapixels).
    """
    if image_format not in IMAGE_FORMATS:
        raise InvalidRecord(name, f"has image format {image_format!r}, not one of {IMAGE_FORMATS}")
    data = bytes(data)
    read_size = image_headers.jpeg_size if image_format == "jpeg" else image_headers.png_size
    try:
        return read_size(io.BytesIO(data).read)
    except ValueError as e:
        what = f"a {image_format.upper()} image with a readable size"
        raise InvalidRecord(name, f"holds {len(data)} bytes that are not {what} ({e})") from None


def _check_intrinsics(name: str, k: NDArray[np.float64]) -> None:
    """Raises unless ``k`` is an OpenCV K: focal lengths in :data:`FOCAL_RANGE_PX`, finite
    principal point and skew within :data:`MAX_INTRINSIC_PX`, bottom rows (0, fy, cy), (0, 0, 1)."""
    if not np.all(np.isfinite(k)):
        raise InvalidRecord(name, f"has non-finite entries {_listed(k)}")
    lo, hi = FOCAL_RANGE_PX
    for label, f in (("fx", k[0, 0]), ("fy", k[1, 1])):
        if not lo <= f <= hi:
            raise InvalidRecord(name, f"has focal length {label} = {f:.6g} px, not in [{lo:g}, {hi:g}]")
    if max(abs(k[0, 1]), abs(k[0, 2]), abs(k[1, 2])) > MAX_INTRINSIC_PX:
        raise InvalidRecord(
            name, f"has a principal point or skew beyond {MAX_INTRINSIC_PX:g} px: {_listed(k)}"
        )
    if k[1, 0] != 0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        raise InvalidRecord(name, f"is not an upper-triangular K with last row (0, 0, 1): {_listed(k)}")


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
        for side in ("width", "height"):
            value = getattr(self, side)
            if not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_IMAGE_SIDE:
                raise InvalidRecord(
                    f"camera {self.name} {side}", f"is {value!r} pixels, not in [1, {MAX_IMAGE_SIDE}]"
                )
            object.__setattr__(self, side, int(value))
        if self.readout_direction not in READOUT_DIRECTIONS:
            raise InvalidRecord(
                f"camera {self.name} readout_direction",
                f"must be one of {READOUT_DIRECTIONS}, got {self.readout_direction!r}",
            )
        intrinsics = _check_array(f"camera {self.name} intrinsics", self.intrinsics, (3, 3), np.float64)
        _check_intrinsics(f"camera {self.name} intrinsics", intrinsics)
        object.__setattr__(self, "intrinsics", intrinsics)
        distortion = _check_array(f"camera {self.name} distortion", self.distortion, (5,), np.float64)
        if not (np.all(np.isfinite(distortion)) and np.abs(distortion).max() <= MAX_DISTORTION):
            raise InvalidRecord(
                f"camera {self.name} distortion",
                f"{_listed(distortion)} must be finite and at most {MAX_DISTORTION:g} in magnitude",
            )
        object.__setattr__(self, "distortion", distortion)
        object.__setattr__(
            self,
            "ego_from_camera",
            check_transform(f"camera {self.name} ego_from_camera", self.ego_from_camera),
        )

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
#: What a dense depth pixel came from (:attr:`CameraDepth.dense_origin`): "lidar", a trusted
#: measurement kept as measured; "densified", filled or corrected by ``densify_depth``; "plane",
#: a plane of its image segment (``complete_depth``); "vertical", a thin vertical structure at its
#: base's depth (``complete_depth``); "rendered", the expected depth of Gaussians (a cache that
#: ``phigenesis-generate`` wrote: the depth of the scene it generated).
DENSE_ORIGINS: tuple[str, ...] = ("none", "lidar", "densified", "plane", "vertical", "rendered")


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
        dense_m: float32 densified (and completed) depth, or None before densification.
        dense_confidence: float32 confidence of ``dense_m`` (None with it).
        dense_origin: uint8 index into :data:`DENSE_ORIGINS` per pixel, 0 exactly where
            ``dense_m`` is 0 (None with it). Given as None with a ``dense_m``, it is derived:
            "lidar" where ``dense_m`` equals a sparse depth of positive confidence, "densified"
            at every other pixel with a depth (:func:`dense_origin_of`).
    """

    sparse_m: NDArray[np.float32]
    sparse_confidence: NDArray[np.float32]
    sparse_origin: NDArray[np.uint8]
    dense_m: NDArray[np.float32] | None = None
    dense_confidence: NDArray[np.float32] | None = None
    dense_origin: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        self.sparse_m = _check_array("sparse_m", self.sparse_m, (None, None), np.float32)
        shape = self.sparse_m.shape
        self.sparse_confidence = _check_array("sparse_confidence", self.sparse_confidence, shape, np.float32)
        self.sparse_origin = _check_array("sparse_origin", self.sparse_origin, shape, np.uint8)
        if (self.dense_m is None) != (self.dense_confidence is None):
            raise InvalidRecord("dense_m", "and dense_confidence come together (both or neither)")
        if self.dense_m is None:
            if self.dense_origin is not None:
                raise InvalidRecord("dense_origin", "is given without dense_m")
            return
        self.dense_m = _check_array("dense_m", self.dense_m, shape, np.float32)
        self.dense_confidence = _check_array("dense_confidence", self.dense_confidence, shape, np.float32)
        if self.dense_origin is None:
            self.dense_origin = dense_origin_of(self.sparse_m, self.sparse_confidence, self.dense_m)
            return
        self.dense_origin = _check_array("dense_origin", self.dense_origin, shape, np.uint8)
        if self.dense_origin.size and int(self.dense_origin.max()) >= len(DENSE_ORIGINS):
            raise InvalidRecord(
                "dense_origin",
                f"holds code {int(self.dense_origin.max())}; codes are 0..{len(DENSE_ORIGINS) - 1} "
                f"{DENSE_ORIGINS}",
            )
        mismatched = int(np.count_nonzero((self.dense_origin == 0) != (self.dense_m <= 0)))
        if mismatched:
            raise InvalidRecord(
                "dense_origin", f"is 0 ('none') at {mismatched} pixels where dense_m is not 0, or the reverse"
            )

    @classmethod
    def empty(cls, height: int, width: int) -> CameraDepth:
        """No depth anywhere (zero confidence): what an image without LiDAR gets."""
        zeros = np.zeros((height, width), np.float32)
        return cls(zeros, zeros.copy(), np.zeros((height, width), np.uint8))


def dense_origin_of(
    sparse_m: NDArray[np.float32], sparse_confidence: NDArray[np.float32], dense_m: NDArray[np.float32]
) -> NDArray[np.uint8]:
    """(H, W) uint8 :data:`DENSE_ORIGINS` codes of a densified depth: "lidar" where ``dense_m``
    is exactly a sparse depth of positive confidence (kept as measured), "densified" at every
    other pixel with a depth, "none" where ``dense_m`` is 0."""
    measured = (sparse_m > 0) & (sparse_confidence > 0) & (dense_m == sparse_m)
    code = np.where(measured, DENSE_ORIGINS.index("lidar"), DENSE_ORIGINS.index("densified"))
    return (code * (dense_m > 0)).astype(np.uint8)


#: Where a pseudo-semantic label came from (:attr:`CameraSemantics.source`); "rendered": the class
#: probabilities of generated Gaussians (``phigenesis-generate``).
PSEUDO_SOURCES: tuple[str, ...] = ("none", "segmenter", "box", "ground_plane", "sky", "rendered")


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
class CameraFlow:
    """Scene flow of one image from its boxes and dense depth (stage ``scene_flow``), (H, W) at the
    image's size.

    Attributes:
        flow_world_mps: float32 (H, W, 3) velocity of the surface point each pixel sees (its
            depth's back-projection), world frame, m/s, at the image's capture time: the rigid
            motion ``v + omega x (p - c)`` of the moving box holding the point, 0 elsewhere.
        dynamic: bool (H, W): the pixel's point lies inside a moving box (grown by the stage's
            margin).
        confidence: float32 (H, W) in [0, 1]: how far the flow can be trusted: the box's motion
            confidence on dynamic pixels, 1 on static pixels with a depth, 0 where the pixel has
            no depth (its flow is unknown).
    """

    flow_world_mps: NDArray[np.float32]
    dynamic: NDArray[np.bool_]
    confidence: NDArray[np.float32]

    def __post_init__(self) -> None:
        self.flow_world_mps = _check_array("flow_world_mps", self.flow_world_mps, (None, None, 3), np.float32)
        shape = self.flow_world_mps.shape[:2]
        self.dynamic = _check_array("flow dynamic", self.dynamic, shape, bool)
        self.confidence = _check_array("flow confidence", self.confidence, shape, np.float32)


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
        flow: scene flow, dynamic mask and confidence from the ``scene_flow`` stage, where it ran.
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
    flow: CameraFlow | None = None
    # The decoded image with the bytes it came from: several stages read one frame's images
    # (projection, densification, labels), and each JPEG should be decoded once.
    _decoded: tuple[bytes, NDArray[np.uint8]] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        cam = f"camera {self.calibration.name}"
        self.timestamp_micros = _check_micros(f"{cam} timestamp_micros", self.timestamp_micros)
        self.world_from_ego = check_transform(f"{cam} world_from_ego", self.world_from_ego)
        size = (self.calibration.height, self.calibration.width)
        for what, shape in (
            ("truth", None if self.truth is None else self.truth.semantic.shape),
            ("labels", None if self.labels is None else self.labels.semantic.shape),
            ("depth", None if self.depth is None else self.depth.sparse_m.shape),
            ("pseudo", None if self.pseudo is None else self.pseudo.semantic.shape),
            ("flow", None if self.flow is None else self.flow.dynamic.shape),
        ):
            if shape is not None and shape != size:
                raise InvalidRecord(f"{cam} {what}", f"is {shape}, calibration says {size}")
        if self.image_bytes is not None:
            if self.image_format not in IMAGE_FORMATS:
                raise InvalidRecord(
                    f"{cam} image_format", f"must be one of {IMAGE_FORMATS}, got {self.image_format!r}"
                )
            width, height = encoded_image_size(self.image_bytes, self.image_format, f"{cam} image_bytes")
            if (width, height) != (self.calibration.width, self.calibration.height):
                raise InvalidRecord(
                    f"{cam} image_bytes",
                    f"is a {width}x{height} {self.image_format.upper()}, the calibration says "
                    f"{self.calibration.width}x{self.calibration.height}",
                )
        if self.trigger_micros is not None:
            self.trigger_micros = _check_micros(f"{cam} trigger_micros", self.trigger_micros)
            check_capture_time(
                f"{cam} trigger_micros", self.trigger_micros, self.timestamp_micros, "the image's time"
            )
        for name in ("shutter_micros", "readout_micros"):
            value = float(getattr(self, name))
            if not 0.0 <= value <= MAX_SENSOR_OFFSET_MICROS:
                raise InvalidRecord(f"{cam} {name}", f"is {value} us, not in [0, {MAX_SENSOR_OFFSET_MICROS}]")
            setattr(self, name, value)
        for name in ("velocity_world_mps", "angular_velocity_world_radps"):
            value = getattr(self, name)
            if value is not None:
                value = _check_array(f"{cam} {name}", value, (3,), np.float64)
                if not np.all(np.isfinite(value)):
                    raise InvalidRecord(f"{cam} {name}", f"has non-finite entries {_listed(value)}")
                setattr(self, name, value)

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

    def check_image(self) -> None:
        """Raises :class:`InvalidRecord` naming the camera unless ``image_bytes`` (where there are
        any) are a whole image that decodes (:func:`check_image_decodes`).

        The constructor reads the header only (the size against the calibration); a source calls
        this once for each image it reads, so that an image the stages, the loader or a preview
        could not decode is an error naming its file and record, or left out under a skip policy.
        """
        if self.image_bytes is not None:
            check_image_decodes(self.image_bytes, f"camera {self.name} image_bytes")

    def decode_image(self) -> NDArray[np.uint8]:
        """The image as (H, W, 3) uint8 RGB; raises if there is none, or :class:`InvalidRecord`
        if it is not a whole image that decodes."""
        if self.image_bytes is None:
            raise ValueError(f"camera {self.name} at {self.timestamp_micros}: this frame has no image")
        if self._decoded is None or self._decoded[0] is not self.image_bytes:
            rgb = decode_rgb(self.image_bytes, f"camera {self.name} at {self.timestamp_micros}")
            self._decoded = (self.image_bytes, rgb)
        return self._decoded[1].copy()


def decode_whole(data: bytes | NDArray[np.uint8], flags: int, name: str = "image_bytes") -> NDArray[np.uint8]:
    """``cv2.imdecode(data, flags)`` of JPEG/PNG bytes that are a whole stream.

    Raises :class:`InvalidRecord` naming ``name`` if the bytes do not end with their format's
    end marker (:func:`~phigenesis.data.image_headers.end_problem`: a stream cut short, which a
    decoder may fill with grey) or do not decode.
    """
    problem = image_headers.end_problem(data)
    image = None if problem else cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise InvalidRecord(name, f"holds {len(data)} bytes that {problem or 'do not decode'}")
    return image


def check_image_decodes(data: bytes, name: str = "image_bytes") -> None:
    """Raises :class:`InvalidRecord` naming ``name`` unless JPEG/PNG ``data`` is a whole stream
    that decodes (see :func:`decode_whole`).

    It decodes at 1/8 scale: the decoder still parses every marker and entropy-decodes every
    block, which is where a damaged stream fails, but skips most of the inverse DCT and the
    colour conversion (a real 1920 x 1280 Waymo JPEG: 4 ms against 12 ms, 1920 x 886: 2.4 ms
    against 4.5 ms). On 6,200 damaged JPEGs (cut, bytes overwritten, bits flipped, spans deleted;
    baseline and progressive, up to 1920 x 1280) it failed exactly where the full decode fails.
    """
    decode_whole(data, cv2.IMREAD_REDUCED_COLOR_8, name)


def decode_rgb(data: bytes, what: str) -> NDArray[np.uint8]:
    """Decodes JPEG/PNG bytes to (H, W, 3) uint8 RGB; raises :class:`InvalidRecord` naming
    ``what`` (the camera and time) if they are not a whole stream that decodes."""
    return cv2.cvtColor(decode_whole(data, cv2.IMREAD_COLOR, f"{what} image_bytes"), cv2.COLOR_BGR2RGB)


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


#: The per-point fields of :class:`LidarSweep`: (name, shape after N, dtype, optional).
_POINT_FIELDS: tuple[tuple[str, tuple[int, ...], type, bool], ...] = (
    ("points_ego", (3,), np.float32, False),
    ("intensity", (), np.float32, False),
    ("beam_index", (), np.uint16, False),
    ("origins_ego", (3,), np.float32, False),
    ("time_offset_micros", (), np.int32, False),
    ("lidar_id", (), np.uint8, False),
    ("semantic", (), np.uint8, True),
    ("instance", (), np.uint16, True),
    ("elongation", (), np.float32, True),
    ("return_index", (), np.uint8, True),
    ("flow_world_mps", (3,), np.float32, True),
)


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
        flow_world_mps: (N, 3) float32 velocity of each point's surface at its measurement time,
            world frame, m/s (stage ``scene_flow``: its box's rigid motion, 0 for static points),
            or None.
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
    flow_world_mps: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        self._convert()
        bad = self._invalid_points()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidRecord(
                "lidar points_ego",
                f"has {int(bad.sum())} of {len(bad)} points with non-finite values or coordinates beyond "
                f"{MAX_POINT_DISTANCE_M:g} m (first: point {i} at {_listed(self.points_ego[i])} from "
                f"{_listed(self.origins_ego[i])}); build the sweep with "
                "LidarSweep.without_invalid_points to leave them out",
            )

    def _convert(self) -> None:
        """Checks the sweep-wide fields and every per-point array's shape, and sets the dtypes."""
        self.timestamp_micros = _check_micros("lidar timestamp_micros", self.timestamp_micros)
        self.world_from_ego = check_transform("lidar world_from_ego", self.world_from_ego)
        with np.errstate(over="ignore"):  # float64 beyond float32's range becomes inf: refused below
            self.points_ego = _check_array("lidar points_ego", self.points_ego, (None, 3), np.float32)
            n = len(self.points_ego)
            for name, shape, dtype, optional in _POINT_FIELDS[1:]:
                value = getattr(self, name)
                if value is not None or not optional:
                    setattr(self, name, _check_array(f"lidar {name}", value, (n, *shape), dtype))

    def _invalid_points(self) -> NDArray[np.bool_]:
        """(N,) which points have a non-finite value or a coordinate beyond MAX_POINT_DISTANCE_M."""
        bad = np.zeros(len(self.points_ego), bool)
        for name in ("points_ego", "origins_ego"):
            xyz = getattr(self, name)
            # One flat pass first (a NaN makes the maximum NaN, which compares False); the per-point
            # mask only when something fails.
            if not np.abs(xyz).max(initial=0.0) <= MAX_POINT_DISTANCE_M:
                bad |= ~(np.abs(xyz) <= MAX_POINT_DISTANCE_M).all(axis=1)
        for name in ("intensity", "elongation"):
            value = getattr(self, name)
            if value is not None:
                bad |= ~np.isfinite(value)
        return bad

    @classmethod
    def without_invalid_points(cls, **values: Any) -> tuple[LidarSweep, int]:
        """A sweep from the constructor's arguments with every point that has a non-finite value
        (coordinates, ray origin, intensity, elongation) or a coordinate beyond
        :data:`MAX_POINT_DISTANCE_M` left out, with all its per-point fields; and how many were
        left out (record it as ``scene.dropped.add(INVALID_POINTS, frame_index, count)``).

        Sweep-wide problems (the pose, the time, array shapes) still raise :class:`InvalidRecord`.
        """
        sweep = cls.__new__(cls)
        for f in fields(cls):
            setattr(sweep, f.name, values.get(f.name, f.default))
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"LidarSweep has no fields {unknown}")
        sweep._convert()
        bad = sweep._invalid_points()
        return sweep.select(~bad), int(bad.sum())

    def select(self, index: NDArray[np.bool_] | NDArray[np.integer]) -> LidarSweep:
        """The points given by a boolean mask or an index array, with all their per-point fields."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=np.int64)
        per_point = {
            name: None if getattr(self, name) is None else getattr(self, name)[idx]
            for name, *_ in _POINT_FIELDS
        }
        return LidarSweep(
            timestamp_micros=self.timestamp_micros, world_from_ego=self.world_from_ego, **per_point
        )

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
        velocity_world: (M, 3) float64 velocity of the centre, m/s; NaN where unknown (keyframe
            annotations, which ``interpolate_boxes`` fills; sources build their boxes with
            :meth:`without_invalid`, which refuses NaN by default, so caches hold known ones).
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
        self._convert()
        problems = self._problems(velocity_known=False)
        if problems:
            raise problems[0]
        self.yaw_world = geometry.wrap_angle(self.yaw_world)
        self.orientation_world = geometry.quaternion_normalize(self.orientation_world)

    def _convert(self) -> None:
        """Checks every array's shape against the track ids, sets the dtypes, fills the defaults."""
        self.track_id = [str(t) for t in self.track_id]
        m = len(self.track_id)
        self.class_id = _check_array("boxes class_id", self.class_id, (m,), np.uint8)
        self.center_world = _check_array("boxes center_world", self.center_world, (m, 3), np.float64)
        self.size_lwh = _check_array("boxes size_lwh", self.size_lwh, (m, 3), np.float64)
        self.yaw_world = _check_array("boxes yaw_world", self.yaw_world, (m,), np.float64)
        self.velocity_world = _check_array("boxes velocity_world", self.velocity_world, (m, 3), np.float64)
        self.status = _check_array("boxes status", self.status, (m,), np.uint8)
        self.instance_id = _check_array("boxes instance_id", self.instance_id, (m,), np.uint16)
        self.num_lidar_points = _check_array("boxes num_lidar_points", self.num_lidar_points, (m,), np.int32)
        if self.acceleration_world is None:
            self.acceleration_world = np.full((m, 3), np.nan)
        self.acceleration_world = _check_array(
            "boxes acceleration_world", self.acceleration_world, (m, 3), np.float64
        )
        if self.orientation_world is None:
            self.orientation_world = geometry.yaw_to_quaternion(self.yaw_world).reshape(m, 4)
        self.orientation_world = _check_array(
            "boxes orientation_world", self.orientation_world, (m, 4), np.float64
        )
        if np.any(self.status >= len(BOX_STATUSES)):
            raise InvalidRecord(
                "boxes status", f"codes must be < {len(BOX_STATUSES)}, got {np.unique(self.status).tolist()}"
            )

    def _problems(self, velocity_known: bool) -> list[InvalidRecord]:
        """One error per invalid box (its first invalid field), naming the box by its track id:
        centre finite within MAX_COORDINATE_M, size finite in (0, MAX_BOX_SIZE_M], yaw and
        orientation (non-zero) finite, velocity finite (or NaN = unknown unless
        ``velocity_known``), acceleration finite or NaN (unknown)."""
        with np.errstate(invalid="ignore", over="ignore"):
            norms = np.linalg.norm(self.orientation_world, axis=1)
            checks = (
                (
                    "center_world",
                    ~(np.abs(self.center_world) <= MAX_COORDINATE_M).all(axis=1),
                    f"must be finite and within {MAX_COORDINATE_M:g} m",
                ),
                (
                    "size_lwh",
                    ~((self.size_lwh > 0) & (self.size_lwh <= MAX_BOX_SIZE_M)).all(axis=1),
                    f"must be finite and in (0, {MAX_BOX_SIZE_M:g}] m",
                ),
                ("yaw_world", ~np.isfinite(self.yaw_world), "must be finite"),
                (
                    "orientation_world",
                    ~(np.isfinite(norms) & (norms > geometry.QUATERNION_ZERO_NORM)),
                    "must be a finite, non-zero quaternion",
                ),
                (
                    "velocity_world",
                    ~np.isfinite(self.velocity_world).all(axis=1)
                    if velocity_known
                    else np.isinf(self.velocity_world).any(axis=1),
                    "must be finite" if velocity_known else "must be finite (or NaN where unknown)",
                ),
                (
                    "acceleration_world",
                    np.isinf(self.acceleration_world).any(axis=1),
                    "must be finite (or NaN where unknown)",
                ),
            )
        problems: dict[int, InvalidRecord] = {}
        for name, bad, rule in checks:
            for i in np.flatnonzero(bad).tolist():
                if i not in problems:
                    value = getattr(self, name)[i]
                    problems[i] = InvalidRecord(
                        f"box {self.track_id[i]!r}", f"{name} {_listed(value)} {rule}", index=i
                    )
        return [problems[i] for i in sorted(problems)]

    @classmethod
    def without_invalid(
        cls, *, velocity_known: bool = True, **values: Any
    ) -> tuple[Boxes, list[InvalidRecord]]:
        """Boxes from the constructor's arguments with every invalid box left out, and one
        :class:`InvalidRecord` per box left out (naming its track id and field; ``index`` is its
        position in the arguments). Sources raise the first under ``--on-error raise``, and
        under ``skip`` log them and count them as :data:`INVALID_BOXES`.

        ``velocity_known``: a NaN velocity is invalid (the boxes of a frame, which the cache
        stores), or, if False, unknown (keyframe annotations that ``interpolate_boxes`` fills).
        Problems of the arrays as a whole (shapes, status codes) still raise.
        """
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"Boxes has no fields {unknown}")
        boxes = cls.__new__(cls)
        for f in fields(cls):
            setattr(boxes, f.name, values.get(f.name, f.default))
        boxes._convert()
        problems = boxes._problems(velocity_known)
        keep = np.ones(len(boxes.track_id), bool)
        keep[[p.index for p in problems]] = False
        return boxes.select(keep), problems

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
        self.timestamp_micros = _check_micros("timestamp_micros", self.timestamp_micros, minimum=0)
        self.source_timestamp_micros = _check_micros(
            "source_timestamp_micros",
            self.timestamp_micros if self.source_timestamp_micros is None else self.source_timestamp_micros,
        )
        self.world_from_ego = check_transform("world_from_ego", self.world_from_ego)
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise InvalidRecord(
                f"frame {self.scene_id}/{self.frame_index}", f"has duplicate camera names {names}"
            )
        for cam in self.cameras:
            check_capture_time(
                f"camera {cam.name} timestamp_micros", cam.timestamp_micros, self.timestamp_micros
            )
        if self.lidar is not None:
            check_capture_time("lidar timestamp_micros", self.lidar.timestamp_micros, self.timestamp_micros)

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

    Frame times: a source that knows them from its index passes ``timestamps_micros`` (checked
    once here with :func:`check_frame_times`, and each loaded frame must carry its own); without
    them, each loaded frame is compared with the nearest frames loaded before it on either side,
    so a sequential pass checks every neighbouring pair. Either way a frame out of time order
    raises :class:`InvalidRecord` when it is loaded. Sources check their index themselves first,
    so that their errors name the file and record.
    """

    def __init__(
        self,
        count: int,
        load: Callable[[int], Frame],
        load_geometry: Callable[[int], Frame] | None = None,
        timestamps_micros: Sequence[int] | None = None,
    ):
        self._count = int(count)
        self._load = load
        self._load_geometry = load_geometry or load
        self._times: list[int] | None = None
        if timestamps_micros is not None:
            times = [int(t) for t in timestamps_micros]
            if len(times) != self._count:
                raise InvalidRecord("timestamps_micros", f"has {len(times)} times for {self._count} frames")
            check_frame_times(times)
            self._times = times
        self._seen: dict[int, int] = {}  # frame index -> time, of the frames loaded so far
        self._seen_order: list[int] = []  # their indices, sorted

    def __len__(self) -> int:
        return self._count

    @overload
    def __getitem__(self, index: int) -> Frame: ...

    @overload
    def __getitem__(self, index: slice) -> list[Frame]: ...

    def __getitem__(self, index: int | slice) -> Frame | list[Frame]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._count))]
        i = self._check(index)
        return self._in_order(i, self._load(i))

    def _check(self, index: int) -> int:
        if index < 0:
            index += self._count
        if not 0 <= index < self._count:
            raise IndexError(f"frame index {index} out of range for {self._count} frames")
        return index

    def _in_order(self, index: int, frame: Frame) -> Frame:
        """``frame`` (loaded as ``index``) after checking its time against the index or the
        frames loaded before it."""
        t = frame.timestamp_micros
        field_name = f"frame {index} timestamp_micros"
        if self._times is not None:
            if t != self._times[index]:
                raise InvalidRecord(
                    field_name,
                    f"was loaded as {t} us, the source's index says {self._times[index]} us",
                    index,
                )
            return frame
        if index in self._seen:
            if self._seen[index] != t:
                raise InvalidRecord(
                    field_name, f"was loaded as {t} us, earlier as {self._seen[index]} us", index
                )
            return frame
        pos = bisect.bisect_left(self._seen_order, index)
        if pos > 0:
            before = self._seen_order[pos - 1]
            if self._seen[before] >= t:
                raise InvalidRecord(
                    field_name, f"is {t} us, not after frame {before}'s {self._seen[before]} us", index
                )
        if pos < len(self._seen_order):
            after = self._seen_order[pos]
            if self._seen[after] <= t:
                raise InvalidRecord(
                    field_name, f"is {t} us, not before frame {after}'s {self._seen[after]} us", index
                )
        self._seen[index] = t
        self._seen_order.insert(pos, index)
        return frame

    def __iter__(self) -> Iterator[Frame]:
        for i in range(self._count):
            yield self._in_order(i, self._load(i))

    def geometry(self, index: int) -> Frame:
        """Frame ``index`` without image bytes or per-pixel maps where the source can skip them
        (the whole frame otherwise); stages applied with :meth:`map` apply here too."""
        i = self._check(index)
        return self._in_order(i, self._load_geometry(i))

    def map(self, fn: Callable[[Frame], Frame]) -> LazyFrames:
        """A lazy sequence that applies ``fn`` to each frame when it is loaded (``fn`` must
        accept geometry-only frames as well)."""
        return LazyFrames(
            self._count,
            lambda i: fn(self[i]),
            lambda i: fn(self.geometry(i)),
        )


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
        camera_timestamps_micros: camera name -> capture time of that camera's own image of this
            keyframe (nuScenes: the channel's ``is_key_frame`` sample_data of the sample, taken
            as the LiDAR revolution ending at ``timestamp_micros`` passed the camera, so 0-50 ms
            before it); empty where the source does not say (ASAP's baseline then takes the
            sweep nearest ``timestamp_micros``).
    """

    timestamp_micros: int
    boxes: Boxes
    token: str = ""
    camera_timestamps_micros: dict[str, int] = field(default_factory=dict)


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
        frames: the frames in strictly increasing time order (often a :class:`LazyFrames`, which
            checks the order as frames load; a list is checked here).
        metadata: JSON-serialisable facts about the scene (rig name, seed, location, ...); stored
            in the cache.
        products: in-memory results of scene-wide stages for later stages (the aggregated LiDAR
            map), keyed by name; never stored.
        keyframes: annotated keyframes where annotations are sparser than frames (nuScenes), in
            strictly increasing time order (checked); empty where every frame carries its own
            boxes (Waymo, synthetic).
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

    def __post_init__(self) -> None:
        names = [c.name for c in self.calibrations]
        if len(set(names)) != len(names):
            raise InvalidRecord(f"scene {self.scene_id} calibrations", f"have duplicate camera names {names}")
        if not isinstance(self.frames, LazyFrames):  # a LazyFrames checks the frames it loads
            check_frame_times([f.timestamp_micros for f in self.frames])
        check_frame_times([k.timestamp_micros for k in self.keyframes], "keyframe")

    def __len__(self) -> int:
        return len(self.frames)

    def calibration(self, name: str) -> CameraCalibration:
        for cal in self.calibrations:
            if cal.name == name:
                return cal
        raise KeyError(f"scene {self.scene_id} has no camera {name!r}")
