"""nuScenes records -> the scene model: poses, calibrations, LiDAR sweeps, annotated boxes.

nuScenes terms (the schema of https://github.com/nutonomy/nuscenes-devkit,
``docs/schema_nuscenes.md``): ``global`` frame (map, z up), ego poses ``global <- ego`` and sensor
extrinsics ``ego <- sensor`` as translation + quaternion (w, x, y, z); LIDAR_TOP's frame is x right,
y forward, z up; camera frames are OpenCV's (x right, y down, z forward) and images are undistorted;
box ``size`` is (width, length, height); time is microseconds. The toolkit's ``world`` is the global
frame shifted by ``origin_global`` (the first frame's ego position; no rotation, so it stays
gravity-aligned, as for Waymo).

Every field is read typed through :meth:`NuScenesTables.field`, so a bad value is an error naming
the table's file, the record and the field; what the scene model refuses on top
(:class:`~phigenesis.data.records.InvalidRecord`) is reported the same way. LiDAR points with
non-finite or out-of-range values are dropped and counted in the scene's
:class:`~phigenesis.data.records.DroppedValues`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data import image_headers
from phigenesis.data.records import (
    INVALID_POINTS,
    Boxes,
    CameraCalibration,
    DroppedValues,
    InvalidRecord,
    KeyframeBoxes,
    LidarSweep,
)
from phigenesis.data.sources.nuscenes.tables import NuScenesError, NuScenesTables, Record

log = logging.getLogger("phigenesis.nuscenes")
OnError = Literal["raise", "skip"]
T = TypeVar("T")
#: Floats per LiDAR point in a ``.pcd.bin``: x, y, z, intensity (raw 0..255), ring index.
PCD_FLOATS = 5
#: Largest ``.pcd.bin`` read, bytes (a 128-beam sweep is about 10 MB).
MAX_PCD_BYTES = 256 * 2**20
#: What :class:`~phigenesis.data.records.DroppedValues` counts for images and sweeps left out of
#: a frame as it loads (a file that cannot be read any more, or one the scene model refuses).
DROPPED_FILES = "camera images and LiDAR sweeps left out of their frame"
#: Attributes that say an object stands still (its velocity is zero when no neighbour gives it).
STATIONARY_ATTRIBUTES = frozenset(
    {
        "vehicle.parked",
        "vehicle.stopped",
        "pedestrian.standing",
        "pedestrian.sitting_lying_down",
        "cycle.without_rider",
    }
)


class Problems:
    """The error policy of one scene: ``raise`` turns a problem into a :class:`NuScenesError`;
    ``skip`` logs it, records it and lets the caller leave the faulty record out.

    Records left out while the scene is read (a sample_data, an annotation, a sample, a frame)
    are listed in ``items`` (stored in the scene metadata as ``skipped``); images and sweeps
    left out while a frame is loaded are counted in ``dropped`` (the scene's
    :class:`DroppedValues`, which the pipeline records once the frames are written).
    """

    def __init__(self, on_error: OnError, scene_name: str, dropped: DroppedValues | None = None):
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        self.on_error = on_error
        self.scene_name = scene_name
        self.items: list[dict[str, str]] = []
        self.dropped = dropped if dropped is not None else DroppedValues()
        self._logged: set[str] = set()

    def report(self, what: str, error: Exception | str) -> None:
        """Raises (``raise``) or records that ``what`` is left out because of ``error``."""
        message = str(error)
        if self.on_error == "raise":
            raise error if isinstance(error, NuScenesError) else NuScenesError(message)
        log.warning("scene %s: skipped %s: %s", self.scene_name, what, message)
        self.items.append({"skipped": what, "reason": message})

    def attempt(self, what: str, fn: Callable[[], T]) -> T | None:
        """``fn()``, or None after reporting its :class:`NuScenesError`."""
        try:
            return fn()
        except NuScenesError as e:
            self.report(what, e)
            return None

    def in_frame(self, frame_index: int, errors: list[NuScenesError]) -> None:
        """Images and sweeps of frame ``frame_index`` that could not be used as it loaded
        (``errors``): ``raise`` raises the first; ``skip`` counts them in ``dropped`` (once per
        frame, however often the frame is loaded) and logs each once."""
        if errors and self.on_error == "raise":
            raise errors[0]
        self.dropped.add(DROPPED_FILES, frame_index, len(errors))
        for e in errors:
            if str(e) not in self._logged:
                self._logged.add(str(e))
                log.warning("scene %s: frame %d: left out %s", self.scene_name, frame_index, e)


def pose(tables: NuScenesTables, table: str, record: Record) -> NDArray[np.float64]:
    """(4, 4) ``target_from_source`` of a record with ``translation`` (metres) and ``rotation``
    (w, x, y, z), both checked (finite, a unit quaternion; a calibrated sensor's translation is a
    mount on the vehicle)."""
    kind = "mount" if table == "calibrated_sensor" else "position"
    translation = tables.field(table, record, "translation", kind)
    rotation = tables.field(table, record, "rotation", "quaternion")
    return geometry.pose_to_transform(translation, rotation)


def scene_model_error(where: NuScenesError, error: InvalidRecord) -> NuScenesError:
    """``where`` (an error naming the file and record a value came from) with what the scene
    model refused about it appended."""
    return NuScenesError(f"{where}: {error}")


def camera_calibration(
    tables: NuScenesTables,
    cs: Record,
    channel: str,
    width: int,
    height: int,
) -> CameraCalibration:
    """The calibration of camera ``channel`` from its calibrated_sensor record ``cs``, for images
    of ``width`` x ``height`` pixels (nuScenes images are undistorted)."""
    intrinsics = tables.field("calibrated_sensor", cs, "camera_intrinsic", "intrinsics")
    ego_from_camera = pose(tables, "calibrated_sensor", cs)
    try:
        return CameraCalibration(
            name=channel,
            width=width,
            height=height,
            intrinsics=intrinsics,
            distortion=np.zeros(5),
            ego_from_camera=ego_from_camera,
        )
    except InvalidRecord as e:
        raise scene_model_error(
            tables.error("calibrated_sensor", cs, f"as the {channel} calibration"), e
        ) from None


def file_error(path: Path, problem: str, named_by: str) -> NuScenesError:
    """The error for ``problem`` with the data file ``path``, which the record and field
    ``named_by`` (e.g. ``sample_data 'abc' 'filename' in .../sample_data.json``) name."""
    return NuScenesError(f"{path}: {problem} (named by {named_by})")


def _check_pcd_size(path: Path, size_bytes: int, named_by: str) -> None:
    if size_bytes % (4 * PCD_FLOATS):
        raise file_error(path, f"{size_bytes} bytes is not a whole number of 5-float points", named_by)
    if size_bytes > MAX_PCD_BYTES:
        raise file_error(
            path, f"{size_bytes} bytes is more than a LiDAR sweep ({MAX_PCD_BYTES} at most)", named_by
        )


def check_pcd_bin(path: Path, named_by: str) -> None:
    """Raises unless the ``.pcd.bin`` at ``path`` can be read and holds whole 5-float points."""
    try:
        size = path.stat().st_size
    except OSError as e:
        raise file_error(path, f"cannot read the LiDAR file ({e.strerror or e})", named_by) from None
    _check_pcd_size(path, size, named_by)


def read_pcd_bin(path: Path, named_by: str) -> NDArray[np.float32]:
    """(N, 5) float32 points of a ``.pcd.bin`` (x, y, z, intensity, ring) in the sensor frame."""
    check_pcd_bin(path, named_by)
    try:
        data = np.fromfile(path, dtype="<f4")
    except OSError as e:
        raise file_error(path, f"cannot read the LiDAR file ({e.strerror or e})", named_by) from None
    _check_pcd_size(path, data.size * 4, named_by)
    return data.reshape(-1, PCD_FLOATS)


def read_image(path: Path, named_by: str) -> bytes:
    """The bytes of an image file."""
    try:
        return path.read_bytes()
    except OSError as e:
        raise file_error(path, f"cannot read the image ({e.strerror or e})", named_by) from None


def jpeg_size(path: Path, named_by: str) -> tuple[int, int]:
    """(width, height) in pixels from a JPEG file's frame header; raises unless the file also ends
    with the end-of-image marker (a file cut short does not). Reads the headers and the last bytes."""
    try:
        with path.open("rb") as f:
            size = image_headers.jpeg_size(f.read)
            f.seek(-len(image_headers.JPEG_END), os.SEEK_END)
            if f.read() != image_headers.JPEG_END:
                raise ValueError("it ends without the end-of-image marker FF D9: cut short")
            return size
    except OSError as e:
        raise file_error(path, f"cannot read the image ({e.strerror or e})", named_by) from None
    except ValueError as e:
        raise file_error(path, f"not a readable JPEG ({e})", named_by) from None


def lidar_sweep(
    path: Path,
    named_by: str,
    timestamp_micros: int,
    world_from_ego: NDArray[np.float64],
    ego_from_lidar: NDArray[np.float64],
    dropped: DroppedValues,
    frame_index: int,
) -> LidarSweep:
    """A LIDAR_TOP sweep moved into the ego frame of its own timestamp.

    nuScenes stores no per-point times, so every point's ``time_offset_micros`` is 0 and its ray
    origin is the sensor's mount position; the ring index becomes ``beam_index`` (a non-finite
    ring becomes 0). Points with a non-finite coordinate or intensity, or beyond the scene model's
    range, are left out and counted in ``dropped`` for ``frame_index`` (as
    :data:`~phigenesis.data.records.INVALID_POINTS`).
    """
    raw = read_pcd_bin(path, named_by)
    n = len(raw)
    with np.errstate(invalid="ignore", over="ignore"):
        points = geometry.transform_points(ego_from_lidar, raw[:, :3].astype(np.float64))
        ring = np.clip(np.nan_to_num(np.rint(raw[:, 4]), nan=0.0), 0, 65535).astype(np.uint16)
    try:
        sweep, left_out = LidarSweep.without_invalid_points(
            timestamp_micros=timestamp_micros,
            world_from_ego=world_from_ego,
            points_ego=points,
            intensity=raw[:, 3].copy(),
            beam_index=ring,
            origins_ego=np.broadcast_to(ego_from_lidar[:3, 3].astype(np.float32), (n, 3)).copy(),
            time_offset_micros=np.zeros(n, np.int32),
            lidar_id=np.zeros(n, np.uint8),
        )
    except InvalidRecord as e:
        raise file_error(path, str(e), named_by) from None
    dropped.add(INVALID_POINTS, frame_index, left_out)
    return sweep


def _category_name(tables: NuScenesTables, ann: Record) -> str:
    instance = tables.follow("sample_annotation", ann, "instance_token", "instance")
    category = tables.follow("instance", instance, "category_token", "category")
    name = tables.field("category", category, "name", "text")
    if name not in tx.NUSCENES_CATEGORY_IDS:
        raise tables.error(
            "category",
            category,
            f"'name' is the unknown category {name!r} (used by sample_annotation {ann['token']!r})",
        )
    return name


def _attribute_names(tables: NuScenesTables, ann: Record) -> list[str]:
    tokens = tables.field("sample_annotation", ann, "attribute_tokens", "tokens", [])
    return [
        tables.field(
            "attribute",
            tables.link("sample_annotation", ann, "attribute_tokens", t, "attribute"),
            "name",
            "text",
        )
        for t in tokens
    ]


def _neighbour(tables: NuScenesTables, ann: Record, link: str) -> tuple[NDArray[np.float64], int] | None:
    """(global position, sample time) of the annotation ``ann[link]`` (prev or next) points to,
    or None where there is none, it is invalid, or its sample is out of time order."""
    token = tables.field("sample_annotation", ann, link, "token", "")
    other = tables["sample_annotation"].get(token) if token else None
    if other is None:
        return None
    position = tables.valid("sample_annotation", other, "translation", "position")
    sample_token = tables.valid("sample_annotation", other, "sample_token", "token")
    time = tables.sample_time(sample_token) if sample_token is not None else None
    return None if position is None or time is None else (position, time)


def annotation_velocity(
    tables: NuScenesTables,
    ann: Record,
    position: NDArray[np.float64],
    time_micros: int,
    attribute_names: list[str],
) -> tuple[NDArray[np.float64], bool]:
    """Global-frame velocity (m/s) of an annotated box at ``position`` (global, metres) and
    ``time_micros``, and whether the data gave it.

    Central difference between the instance's previous and next annotations (one-sided at the
    ends of its track, or where a neighbour is invalid), with the samples' timestamps. An instance
    annotated once has no motion in the data: its velocity is 0, and counts as given only if an
    attribute says it stands still (parked, stopped, standing, sitting, cycle without rider).
    """
    own = (position, time_micros)
    first = _neighbour(tables, ann, "prev") or own
    last = _neighbour(tables, ann, "next") or own
    if first is own and last is own:
        return np.zeros(3), bool(STATIONARY_ATTRIBUTES.intersection(attribute_names))
    dt = (last[1] - first[1]) * 1e-6
    if dt <= 0:
        raise tables.error(
            "sample_annotation", ann, "'prev'/'next': the annotations around it are not in time order"
        )
    return (last[0] - first[0]) / dt, True


def _box_row(tables: NuScenesTables, ann: Record, time_micros: int) -> tuple[Any, ...]:
    """(instance token, category, global_from_box, (l, w, h), velocity, velocity known,
    LiDAR points) of one annotation, every field checked."""
    instance = tables.field("sample_annotation", ann, "instance_token", "token")
    name = _category_name(tables, ann)
    attributes = _attribute_names(tables, ann)
    box_pose = pose(tables, "sample_annotation", ann)
    w, length, h = tables.field("sample_annotation", ann, "size", "size")
    velocity, known = annotation_velocity(tables, ann, box_pose[:3, 3], time_micros, attributes)
    points = tables.field("sample_annotation", ann, "num_lidar_pts", "count", -1)
    return instance, name, box_pose, (length, w, h), velocity, known, points


def keyframe_boxes(
    tables: NuScenesTables,
    sample: Record,
    origin_global: NDArray[np.float64],
    problems: Problems,
    unknown_velocity: list[str],
) -> KeyframeBoxes:
    """The annotated boxes of one sample (in time order in its scene) in the world frame
    (``track_id`` = instance token); a bad annotation is reported to ``problems`` and left out."""
    time_micros = tables.sample_time(sample["token"])
    if time_micros is None:
        raise tables.error("sample", sample, "'timestamp' is invalid or out of time order")
    rows, anns = [], []
    for ann in sorted(tables.annotations_by_sample.get(sample["token"], []), key=lambda a: a["token"]):
        row = problems.attempt(
            f"sample_annotation {ann['token']}", lambda ann=ann: _box_row(tables, ann, time_micros)
        )
        if row is not None:
            rows.append(row)
            anns.append(ann)
    m = len(rows)
    rotation = np.array([r[2][:3, :3] for r in rows]).reshape(m, 3, 3)
    boxes, refused = Boxes.without_invalid(
        velocity_known=False,
        track_id=[r[0] for r in rows],
        class_id=np.array([tx.NUSCENES_CATEGORY_IDS[r[1]] for r in rows], np.uint8),
        center_world=np.array([r[2][:3, 3] - origin_global for r in rows]).reshape(m, 3),
        size_lwh=np.array([r[3] for r in rows]).reshape(m, 3),
        yaw_world=geometry.matrix_yaw(rotation) if m else np.zeros(0),
        velocity_world=np.array([r[4] for r in rows]).reshape(m, 3),
        status=np.zeros(m, np.uint8),
        instance_id=np.zeros(m, np.uint16),
        num_lidar_points=np.array([r[6] for r in rows], np.int32),
        orientation_world=geometry.matrix_to_quaternion(rotation) if m else None,
    )
    for problem in refused:  # what the scene model refuses beyond the fields' own checks
        ann = anns[problem.index]
        where = tables.error("sample_annotation", ann, "as a box")
        problems.report(f"sample_annotation {ann['token']}", scene_model_error(where, problem))
    refused_at = {problem.index for problem in refused}
    kept = [(a, r) for i, (a, r) in enumerate(zip(anns, rows, strict=True)) if i not in refused_at]
    unknown_velocity.extend(a["token"] for a, r in kept if not r[5])
    return KeyframeBoxes(timestamp_micros=time_micros, boxes=boxes, token=sample["token"])
