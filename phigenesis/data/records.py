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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.box_records import (
    Boxes,
)
from phigenesis.data.camera_records import (  # noqa: F401 (re-exported: the scene model's one import path)
    DENSE_ORIGINS,
    DEPTH_ORIGINS,
    PSEUDO_SOURCES,
    TRUSTED_DEPTH_CONFIDENCE,
    CameraCalibration,
    CameraDepth,
    CameraFlow,
    CameraImage,
    CameraLabels,
    CameraSemantics,
    CameraTruth,
    check_image_decodes,
    decode_rgb,
    decode_whole,
    dense_origin_of,
    encode_rgb,
)
from phigenesis.data.lidar_records import (  # noqa: F401 (re-exported: the scene model's one import path)
    _POINT_FIELDS,
    LidarSweep,
)
from phigenesis.data.range_records import LidarRangeImage, RangeViewLayout
from phigenesis.data.record_checks import (  # noqa: F401 (re-exported: the scene model's one import path)
    _LAST_ROW,
    BOX_STATUSES,
    FOCAL_RANGE_PX,
    IMAGE_FORMATS,
    INT64_MAX,
    INVALID_BOXES,
    INVALID_POINTS,
    MAX_BOX_SIZE_M,
    MAX_COORDINATE_M,
    MAX_DISTORTION,
    MAX_IMAGE_SIDE,
    MAX_INTRINSIC_PX,
    MAX_POINT_DISTANCE_M,
    MAX_SENSOR_OFFSET_MICROS,
    MAX_USER_MICROS,
    READOUT_DIRECTIONS,
    RIGID_TOLERANCE,
    BoxStatus,
    ImageFormat,
    InvalidRecord,
    ReadoutDirection,
    _check_array,
    _check_intrinsics,
    _check_micros,
    _listed,
    check_capture_time,
    check_frame_times,
    check_transform,
    encoded_image_size,
    increasing_frames,
)


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
