"""nuScenes records -> the scene model: poses, calibrations, LiDAR sweeps, annotated boxes.

nuScenes terms (see shared/reference/nuscenes.md): ``global`` frame (map, z up), ego poses
``global <- ego`` and sensor extrinsics ``ego <- sensor`` as translation + quaternion (w, x, y, z);
LIDAR_TOP's frame is x right, y forward, z up; camera frames are OpenCV's (x right, y down, z
forward) and images are undistorted; box ``size`` is (width, length, height); time is
microseconds. The toolkit's ``world`` is the global frame shifted by ``origin_global`` (the first
frame's ego position; no rotation, so it stays gravity-aligned, as for Waymo).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import Boxes, CameraCalibration, KeyframeBoxes, LidarSweep
from phigenesis.data.sources.nuscenes.tables import NuScenesError, NuScenesTables, Record

log = logging.getLogger("phigenesis.nuscenes")
OnError = Literal["raise", "skip"]
#: Floats per LiDAR point in a ``.pcd.bin``: x, y, z, intensity (raw 0..255), ring index.
PCD_FLOATS = 5
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
    ``skip`` logs it, records it (``items``, stored in the scene metadata) and lets the caller
    leave the faulty record out."""

    def __init__(self, on_error: OnError, scene_name: str):
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        self.on_error = on_error
        self.scene_name = scene_name
        self.items: list[dict[str, str]] = []

    def report(self, what: str, error: Exception | str) -> None:
        """Raises (``raise``) or records that ``what`` is left out because of ``error``."""
        message = str(error)
        if self.on_error == "raise":
            raise error if isinstance(error, NuScenesError) else NuScenesError(message)
        log.warning("scene %s: skipped %s: %s", self.scene_name, what, message)
        self.items.append({"skipped": what, "reason": message})

    def attempt(self, what: str, fn: Callable[[], Any]) -> Any:
        """``fn()``, or None after reporting its :class:`NuScenesError`."""
        try:
            return fn()
        except NuScenesError as e:
            self.report(what, e)
            return None


def pose(record: Record) -> NDArray[np.float64]:
    """(4, 4) ``target_from_source`` of a record with ``translation`` and ``rotation`` (w, x, y, z)."""
    try:
        t = np.asarray(record["translation"], np.float64).reshape(3)
        q = np.asarray(record["rotation"], np.float64).reshape(4)
    except (KeyError, ValueError) as e:
        raise NuScenesError(f"record {record.get('token')!r}: bad translation/rotation ({e})") from None
    if not np.isfinite(t).all() or not np.isfinite(q).all() or np.linalg.norm(q) < 1e-9:
        raise NuScenesError(f"record {record.get('token')!r}: non-finite or zero pose")
    return geometry.pose_to_transform(t, geometry.quaternion_normalize(q))


def camera_calibration(channel: str, cs: Record, width: int, height: int) -> CameraCalibration:
    """A camera's calibration from its calibrated_sensor record (images are undistorted)."""
    k = np.asarray(cs.get("camera_intrinsic") or [], np.float64)
    if k.shape != (3, 3):
        raise NuScenesError(f"calibrated_sensor {cs['token']!r} ({channel}): camera_intrinsic is not 3x3")
    return CameraCalibration(
        name=channel,
        width=int(width),
        height=int(height),
        intrinsics=k,
        distortion=np.zeros(5),
        ego_from_camera=pose(cs),
    )


def read_pcd_bin(path: Path) -> NDArray[np.float32]:
    """(N, 5) float32 points of a ``.pcd.bin`` (x, y, z, intensity, ring) in the sensor frame."""
    try:
        data = np.fromfile(path, dtype="<f4")
    except OSError as e:
        raise NuScenesError(f"{path}: cannot read the LiDAR file ({e})") from None
    if data.size % PCD_FLOATS:
        raise NuScenesError(f"{path}: {data.size * 4} bytes is not a whole number of 5-float points")
    return data.reshape(-1, PCD_FLOATS)


def lidar_sweep(
    path: Path,
    timestamp_micros: int,
    world_from_ego: NDArray[np.float64],
    ego_from_lidar: NDArray[np.float64],
) -> LidarSweep:
    """A LIDAR_TOP sweep moved into the ego frame of its own timestamp.

    nuScenes stores no per-point times, so every point's ``time_offset_micros`` is 0 and its ray
    origin is the sensor's mount position; the ring index becomes ``beam_index``.
    """
    raw = read_pcd_bin(path)
    n = len(raw)
    points = geometry.transform_points(ego_from_lidar, raw[:, :3].astype(np.float64))
    return LidarSweep(
        timestamp_micros=timestamp_micros,
        world_from_ego=world_from_ego,
        points_ego=points.astype(np.float32),
        intensity=raw[:, 3].copy(),
        beam_index=np.clip(np.rint(raw[:, 4]), 0, 65535).astype(np.uint16),
        origins_ego=np.broadcast_to(ego_from_lidar[:3, 3].astype(np.float32), (n, 3)).copy(),
        time_offset_micros=np.zeros(n, np.int32),
        lidar_id=np.zeros(n, np.uint8),
    )


def _category_name(tables: NuScenesTables, ann: Record) -> str:
    instance = tables.follow("sample_annotation", ann, "instance_token", "instance")
    category = tables.follow("instance", instance, "category_token", "category")
    name = str(category.get("name", ""))
    if name not in tx.NUSCENES_CATEGORY_IDS:
        raise NuScenesError(
            f"category {category['token']!r} has the unknown name {name!r} "
            f"(used by sample_annotation {ann['token']!r})"
        )
    return name


def annotation_velocity(
    tables: NuScenesTables, ann: Record, attribute_names: list[str]
) -> tuple[NDArray[np.float64], bool]:
    """Global-frame velocity (m/s) of an annotated box, and whether the data gave it.

    Central difference between the instance's previous and next annotations (one-sided at the
    ends of its track), with the samples' timestamps. An instance annotated once has no motion in
    the data: its velocity is 0, and counts as given only if an attribute says it stands still
    (parked, stopped, standing, sitting, cycle without rider); otherwise it is reported unknown.
    """
    ends = []
    for link in ("prev", "next"):
        token = ann.get(link) or ""
        other = tables["sample_annotation"].get(token) if token else None
        ends.append(other if other is not None else ann)
    first, last = ends
    if first is last:
        return np.zeros(3), bool(STATIONARY_ATTRIBUTES.intersection(attribute_names))
    t0 = tables.follow("sample_annotation", first, "sample_token", "sample")["timestamp"]
    t1 = tables.follow("sample_annotation", last, "sample_token", "sample")["timestamp"]
    dt = (int(t1) - int(t0)) * 1e-6
    if dt <= 0:
        raise NuScenesError(
            f"sample_annotation {first['token']!r} and {last['token']!r} of one instance "
            "are not in time order"
        )
    p0, p1 = (np.asarray(a["translation"], np.float64) for a in (first, last))
    return (p1 - p0) / dt, True


def keyframe_boxes(
    tables: NuScenesTables,
    sample: Record,
    origin_global: NDArray[np.float64],
    problems: Problems,
    unknown_velocity: list[str],
) -> KeyframeBoxes:
    """The annotated boxes of one sample in the world frame (``track_id`` = instance token)."""
    rows = []
    for ann in sorted(tables.annotations_by_sample.get(sample["token"], []), key=lambda a: a["token"]):

        def convert(ann: Record = ann) -> tuple[Any, ...]:
            name = _category_name(tables, ann)
            attributes = [
                str(
                    tables.get("attribute", t, f"sample_annotation {ann['token']!r}.attribute_tokens")["name"]
                )
                for t in ann.get("attribute_tokens") or []
            ]
            box_pose = pose(ann)
            w, length, h = (float(x) for x in ann["size"])
            velocity, known = annotation_velocity(tables, ann, attributes)
            return name, box_pose, (length, w, h), velocity, known, int(ann.get("num_lidar_pts", -1))

        row = problems.attempt(f"sample_annotation {ann['token']}", convert)
        if row is None:
            continue
        if not row[4]:
            unknown_velocity.append(ann["token"])
        rows.append((ann["instance_token"], *row))
    m = len(rows)
    rotation = np.array([r[2][:3, :3] for r in rows]).reshape(m, 3, 3)
    boxes = Boxes(
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
    return KeyframeBoxes(timestamp_micros=int(sample["timestamp"]), boxes=boxes, token=sample["token"])
