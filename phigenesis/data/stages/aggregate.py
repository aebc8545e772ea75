"""Static LiDAR aggregation: every sweep of a scene in the world frame, split into a static map and
per-object models, for the depth stages.

Entry point: :func:`aggregate_scene` (the stage ``aggregate_lidar`` calls it and leaves the result
in ``scene.products["lidar_map"]``).

- **Moving or not** is decided from each track's motion over the scene (its box centres spread
  more than ``moving_threshold_m`` around their median), never from its class: a parked car is
  static scenery, a walking person is not.
- **Static map**: the points outside the boxes of moving objects and outside the ego car's body
  (the source's own vehicle, :mod:`phigenesis.data.ego_body`; a box holding a camera centre or a
  LiDAR origin is an error naming the scene, the sensor and the box: :func:`checked_ego_boxes`),
  voxel down-sampled (``voxel_m``, the speed/accuracy knob; each voxel's centroid, by sorted
  voxel keys or Open3D: ``voxel_backend``) and, where real LiDAR needs it, cleaned by Open3D's
  statistical outlier removal. Boxes are tested at each point's own
  measurement time (centre + velocity x time offset), so a fast car's points do not smear into the
  map across the ~100 ms of a revolution; the removal boxes are enlarged (``box_scale`` and
  ``box_margin_m``).
- **Rigid moving objects** accumulate their points over the scene in box coordinates (strictly
  inside the box, above a ground clearance so the road under them is not carried along), kept
  where ``object_min_sweeps`` sweeps hit the same ``object_voxel_m`` voxel and down-sampled at
  ``object_point_m``; the projection puts them back at each image's box pose.
- **Non-rigid classes** (people, riders) keep no model: the projection uses only the points of
  the frame's own sweep.

Frames are read with :func:`frame_geometry` (no images), one sweep at a time; static points are
down-sampled in chunks of ``chunk_sweeps`` sweeps, and every :data:`MERGE_CHUNKS` chunks are
merged into one with the count of chunk centroids behind each voxel (:func:`voxel_merge`: the
same centroids as merging them all at the end), so memory stays bounded by the map, not the
scene: a 200-frame Waymo segment's 20 chunks (about 50 million points) were sorted at once.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis._open3d import open3d
from phigenesis.data.ego_body import camera_centres, check_sensors_outside, lidar_name, lidar_origins
from phigenesis.data.records import Boxes, LidarSweep, Scene, frame_geometry
from phigenesis.data.stages import register_stage
from phigenesis.options import check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

#: The ego body where a source gives none (ego frame): a mid-size car's lower body around the rear
#: axle, up to 1 m, below any roof or windscreen sensor. (Its earlier 1.8 m top held every
#: nuScenes camera, which then saw nothing but the body; sources give their own vehicle's body,
#: :mod:`phigenesis.data.ego_body`.)
DEFAULT_EGO_BOXES: list[dict[str, list[float]]] = [
    {"center_ego": [1.4, 0.0, 0.5], "size_lwh": [5.0, 2.1, 1.0]}
]
#: How the static map is voxel down-sampled (:func:`voxel_downsample`).
VoxelBackend = Literal["numpy", "open3d"]
VOXEL_BACKENDS: tuple[VoxelBackend, ...] = get_args(VoxelBackend)
#: Tile size of the static map's spatial index, metres.
TILE_M = 8.0
#: Cell size of the grid that finds the points near a box (:func:`box_points_at_times`), metres.
BOX_CELL_M = 4.0
#: Down-sampled chunks of the static map kept before they are merged into one (:func:`voxel_merge`):
#: a long segment's chunks would otherwise add up to several times its map (20 chunks of 2.5
#: million points for a 200-frame Waymo segment) and be sorted all at once at the end.
MERGE_CHUNKS = 4


@dataclass(frozen=True)
class AggregateParams:
    """Parameters of :func:`aggregate_scene` (all lengths in metres, times in seconds).

    Attributes:
        voxel_m: static map voxel size; 0 keeps every point.
        object_voxel_m: voxel size of the rigid object models' repeat test (``object_min_sweeps``).
        object_point_m: voxel size the kept model points are then down-sampled to (finer: a
            car beside the camera needs dense points; Open3D's grid, anchored elsewhere than
            the repeat test's, used to split voxels and hid how sparse 5 cm models are).
        object_min_sweeps: an object model keeps the voxels hit by at least this many sweeps.
        moving_threshold_m: a track whose box centres spread more than this around their median
            position is moving.
        box_scale: moving boxes are scaled by this for removing points from the static map ...
        box_margin_m: ... and grown by this on every side.
        ground_clearance_m: object models keep points this far above their box's bottom face.
        voxel_backend: "numpy" (sorted voxel keys; the faster, see BENCHMARKS.md, "Dense depth
            ground truth") or "open3d" (its ``voxel_down_sample``).
        outlier_neighbors, outlier_std_ratio: Open3D statistical outlier removal (0 neighbours
            turns it off). It is for real LiDAR's spurious returns (dust, rain, multipath); on
            synthetic scenes, which have none, it only removes sparse far surfaces, so
            pipelines/synthetic.yaml turns it off (docs/design/depth.md).
        ego_margin_m: points within this of the ego body boxes are dropped.
        chunk_sweeps: sweeps gathered before each intermediate voxel down-sampling.
    """

    voxel_m: float = option(0.02, ge=0, le=10)
    voxel_backend: VoxelBackend = option("numpy")
    object_voxel_m: float = option(0.05, ge=0, le=10)
    object_point_m: float = option(0.02, ge=0, le=10)
    object_min_sweeps: int = option(2, ge=1, le=10_000)
    moving_threshold_m: float = option(0.5, ge=0, le=1000)
    box_scale: float = option(1.1, gt=0, le=10)
    box_margin_m: float = option(0.15, ge=0, le=100)
    ground_clearance_m: float = option(0.1, ge=0, le=100)
    outlier_neighbors: int = option(8, ge=0, le=1000)
    outlier_std_ratio: float = option(3.0, gt=0, le=100)
    ego_margin_m: float = option(0.1, ge=0, le=100)
    chunk_sweeps: int = option(10, ge=1, le=100_000)

    def __post_init__(self) -> None:
        check_options(self, "AggregateParams")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> AggregateParams:
        return from_mapping(cls, values, "aggregate_lidar")


@dataclass
class ObjectModel:
    """A rigid moving object's points accumulated over the scene, in its box frame.

    Attributes:
        track_id: the track.
        class_id: unified taxonomy class.
        points_box: (N, 3) float32 metres, box frame (x forward, y left, z up, origin at the
            box centre).
        sweeps: how many sweeps contributed points.
    """

    track_id: str
    class_id: int
    points_box: NDArray[np.float32]
    sweeps: int


@dataclass
class LidarMap:
    """What :func:`aggregate_scene` found in a scene.

    Size: 12 bytes per static point (float32 x, y, z) plus 16 per occupied 8 m tile, and 12 per
    object model point; it is all a scene keeps between frames (the frames stream). While it is
    built, ``chunk_sweeps`` sweeps' points wait for their down-sampling (about 60 bytes per raw
    point at its peak: one float64 column, sort keys and order) and at most
    :data:`MERGE_CHUNKS` down-sampled chunks wait beside the merged map. Sizes of real scenes:
    BENCHMARKS.md, "Dense depth ground truth: the whole stage on a long scene".

    Attributes:
        points_world: (N, 3) float32 static points, world frame, sorted by :data:`TILE_M` tile.
        tile_keys: (T,) int64 sorted keys of the occupied tiles; ``tile_start`` (T + 1,) int64
            offsets into ``points_world``.
        voxel_m: the static map's voxel size (a point's footprint).
        moving_tracks: the tracks judged moving.
        non_rigid_tracks: the moving tracks whose class deforms (no model; own sweep only).
        objects: the rigid moving objects' models by track id.
        ego_boxes: the ego body boxes used (centre and size in the ego frame).
        max_elevation_rad: the highest elevation (above the ego's x-y plane, seen from the
            sensor) at which the LiDAR returned points (99.9th percentile over the scene): map
            points above it seen from the current sensor position are not projected, as their
            occluders could never have been measured.
        angular_step_rad: the LiDAR's angular spacing (the coarser of beam and azimuth steps):
            the footprint of a point that a single sweep measured.
        ground_clearance_m: object points lie at least this far above their box's bottom (for
            the projection's own-sweep points of non-rigid objects too).
        stats: counts and timings (JSON-serialisable).
    """

    points_world: NDArray[np.float32]
    tile_keys: NDArray[np.int64]
    tile_start: NDArray[np.int64]
    voxel_m: float
    moving_tracks: frozenset[str]
    non_rigid_tracks: frozenset[str]
    objects: dict[str, ObjectModel]
    ego_boxes: list[dict[str, list[float]]]
    max_elevation_rad: float = float(np.pi / 2)
    angular_step_rad: float = float(np.radians(0.5))
    ground_clearance_m: float = 0.1
    stats: dict[str, Any] = field(default_factory=dict)
    _tile_z: tuple[NDArray[np.float32], NDArray[np.float32]] | None = field(
        default=None, repr=False, compare=False
    )
    _tile_levels: NDArray[np.int64] | None = field(default=None, repr=False, compare=False)

    def uniform_takes(self, tiles: NDArray[np.int64], wanted: NDArray[np.int64]) -> NDArray[np.int64]:
        """(K,) for each of the given tiles, the fewest first points, at least ``wanted`` (or the
        whole tile), that are a uniform subset of it: whole levels (:func:`_tile_sort`), so at
        most about twice ``wanted``."""
        if self._tile_levels is None:
            self._tile_levels = tile_level_counts(self.points_world, self.tile_start)
        counts = self._tile_levels[tiles]
        deepest = (counts >= np.asarray(wanted, np.int64)[:, None]).sum(axis=1) - 1
        return counts[np.arange(len(tiles)), np.maximum(deepest, 0)]

    def tile_heights(self, tiles: NDArray[np.int64]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(K,) float32 lowest and highest z (world, metres) of the given tiles' points
        (:func:`tile_height_ranges`, computed on first use)."""
        if self._tile_z is None:
            self._tile_z = tile_height_ranges(self.points_world, self.tile_start)
        return self._tile_z[0][tiles], self._tile_z[1][tiles]

    def tile_counts(self, tiles: NDArray[np.int64]) -> NDArray[np.int64]:
        """(K,) number of points in each of the given tiles."""
        return self.tile_start[tiles + 1] - self.tile_start[tiles]

    def tiles_near(self, xy_world: NDArray[np.float64], radius_m: float) -> NDArray[np.int64]:
        """Indices (into ``tile_keys``) of the occupied tiles within the square of half-side
        ``radius_m`` (x-y) around a world position."""
        if len(self.tile_keys) == 0:
            return np.zeros(0, np.int64)
        lo = np.floor((np.asarray(xy_world[:2]) - radius_m) / TILE_M).astype(np.int64)
        hi = np.floor((np.asarray(xy_world[:2]) + radius_m) / TILE_M).astype(np.int64)
        tx_, ty_ = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
        keys = np.sort(_tile_key(tx_.ravel(), ty_.ravel()))
        pos = np.searchsorted(self.tile_keys, keys)
        hit = pos < len(self.tile_keys)
        hit[hit] = self.tile_keys[pos[hit]] == keys[hit]
        return pos[hit].astype(np.int64)

    def tile_centres(self, tiles: NDArray[np.int64]) -> NDArray[np.float64]:
        """(K, 2) world x-y centres of the given tiles."""
        keys = self.tile_keys[tiles]
        tx_ = keys >> 32
        ty_ = (keys & 0xFFFFFFFF) - (1 << 31)
        return (np.stack([tx_, ty_], axis=1).astype(np.float64) + 0.5) * TILE_M

    def points_of_tiles(
        self, tiles: NDArray[np.int64], stride: NDArray[np.int64] | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """The static points of the given tiles (every ``stride[k]``-th point of tile k, all
        if None) and, per point, the position of its tile in ``tiles``."""
        if stride is None:
            stride = np.ones(len(tiles), np.int64)
        parts = [
            self.points_world[self.tile_start[i] : self.tile_start[i + 1] : int(k)]
            for i, k in zip(tiles, stride, strict=True)
        ]
        counts = np.array([len(p) for p in parts], np.int64)
        if counts.sum() == 0:
            return self.points_world[:0], np.zeros(0, np.int64)
        return np.concatenate(parts), np.repeat(np.arange(len(tiles)), counts)

    def points_and_counts_of_tiles(
        self, tiles: NDArray[np.int64], take: NDArray[np.int64] | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """:meth:`points_of_tiles`' points with, instead of a label per point, the (K,) number
        taken from each tile (each tile's points are contiguous, in ``tiles``' order). ``take``:
        at most this many of each tile's points, its first ones (whole levels are a uniform
        subset: :func:`_tile_sort`, :meth:`uniform_takes`); None: every point."""
        if take is None:
            take = self.tile_counts(tiles)
        parts = [
            self.points_world[self.tile_start[i] : self.tile_start[i] + int(n)]
            for i, n in zip(tiles, np.minimum(take, self.tile_counts(tiles)), strict=True)
        ]
        counts = np.array([len(p) for p in parts], np.int64)
        if counts.sum() == 0:
            return self.points_world[:0], counts
        return np.concatenate(parts), counts

    def points_near(self, xy_world: NDArray[np.float64], radius_m: float) -> NDArray[np.float32]:
        """(K, 3) static points in the tiles within ``radius_m`` (x-y) of a world position."""
        return self.points_of_tiles(self.tiles_near(xy_world, radius_m))[0]


def _tile_key(tx_: NDArray[np.int64], ty_: NDArray[np.int64]) -> NDArray[np.int64]:
    return (tx_.astype(np.int64) << 32) + (ty_.astype(np.int64) + (1 << 31))


def ego_boxes_of(scene: Scene, override: list[dict[str, list[float]]] | None = None) -> list[dict]:
    """The ego body boxes: ``override``, else the scene's metadata ``ego_boxes``, else a default car."""
    boxes = override if override is not None else scene.metadata.get("ego_boxes", DEFAULT_EGO_BOXES)
    for b in boxes:
        if len(b.get("center_ego", ())) != 3 or len(b.get("size_lwh", ())) != 3:
            raise ValueError(
                f"scene {scene.scene_id}: an ego box needs center_ego and size_lwh (3 values): {b}"
            )
    return list(boxes)


def ego_boxes_from(scene: Scene) -> str:
    """Where :func:`ego_boxes_of` takes the scene's boxes from, for messages."""
    if "ego_boxes" in scene.metadata:
        return f"the {scene.source} source's body (scene metadata ego_boxes)"
    return "the default body (DEFAULT_EGO_BOXES; the source gives none)"


def checked_ego_boxes(scene: Scene) -> list[dict]:
    """The scene's ego body (:func:`ego_boxes_of`), checked against its cameras' centres.

    Raises :class:`~phigenesis.errors.PrepError` naming the scene, the camera and the box when a
    box holds a camera centre (the camera would see nothing but the body); logs a warning when the
    scene gives no body of its own and the default one is used."""
    boxes = ego_boxes_of(scene)
    check_sensors_outside(scene.scene_id, boxes, camera_centres(scene.calibrations), ego_boxes_from(scene))
    if "ego_boxes" not in scene.metadata:
        log.warning(
            "scene %s: the source gives no ego body (metadata ego_boxes); using the default %s",
            scene.scene_id,
            DEFAULT_EGO_BOXES,
        )
    return boxes


class LidarOriginCheck:
    """Checks each LiDAR's origin against the ego body, on the first sweep that LiDAR appears in
    (the origins are its mount position; every later sweep would repeat the same test)."""

    def __init__(self, scene: Scene, ego_boxes: list[dict]):
        self.scene_id = scene.scene_id
        self.ego_boxes = ego_boxes
        self.boxes_from = ego_boxes_from(scene)
        self.checked: set[int] = set()

    def __call__(self, sweep: LidarSweep) -> None:
        """Raises :class:`~phigenesis.errors.PrepError` naming the scene, the LiDAR and the box
        if a box holds the median ray origin of a LiDAR of ``sweep`` not checked before."""
        present = np.flatnonzero(np.bincount(sweep.lidar_id, minlength=1))
        new = [int(k) for k in present if int(k) not in self.checked]
        if not new:
            return
        origins = lidar_origins(sweep.origins_ego, sweep.lidar_id)
        sensors = {lidar_name(k): origins[lidar_name(k)] for k in new}
        check_sensors_outside(self.scene_id, self.ego_boxes, sensors, self.boxes_from)
        self.checked.update(new)


def in_ego_body(
    points_ego: NDArray[np.floating], ego_boxes: list[dict], margin_m: float
) -> NDArray[np.bool_]:
    """(N,) True for ego-frame points inside any ego body box grown by ``margin_m``.

    The boxes are axis-aligned in the ego frame: ``geometry.points_in_box`` at yaw 0 (its
    rotation is the identity, which changes no coordinate), without its matrix product."""
    p = np.asarray(points_ego, np.float64)
    inside = np.zeros(len(p), bool)
    for b in ego_boxes:
        half = 0.5 * np.asarray(b["size_lwh"], np.float64) + margin_m + 1e-9  # points_in_box's slack
        inside |= np.all(np.abs(p - np.asarray(b["center_ego"], np.float64)) <= half, axis=1)
    return inside


def box_points_at_times(
    points_world: NDArray[np.float64],
    dt_s: NDArray[np.float64],
    boxes: Boxes,
    scale: float = 1.0,
    margin_m: float = 0.0,
    bottom_clearance_m: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Which box (if any) holds each point at its own measurement time.

    Box ``i`` at a point's time is the frame's box moved by ``velocity_world * dt_s``; its half
    size is ``0.5 * size * scale + margin_m``. With ``bottom_clearance_m``, points lower than the
    (unscaled) bottom face plus the clearance do not count.

    Args:
        points_world: (N, 3) float64 world points.
        dt_s: (N,) point time minus the boxes' time, seconds.
        boxes: M boxes (orientation from ``orientation_world``).

    Returns:
        ``(index, local)``: (N,) index of the first box holding the point or -1, and (N, 3) the
        point in that box's frame (undefined where the index is -1).
    """
    n = len(points_world)
    index = np.full(n, -1, np.int64)
    local = np.zeros((n, 3))
    if n == 0 or len(boxes) == 0:
        return index, local
    rotations = geometry.quaternion_to_matrix(boxes.orientation_world)
    speed = np.linalg.norm(boxes.velocity_world, axis=1)
    max_dt = float(np.max(np.abs(dt_s))) if n else 0.0
    half = 0.5 * boxes.size_lwh * scale + margin_m
    reach = np.linalg.norm(half, axis=1) + speed * max_dt + 1e-6
    # Points sorted once by a grid of BOX_CELL_M cells (x-major): each box tests only the cells
    # its reach overlaps, instead of every box against every point of a sweep (a real frame has
    # hundreds of thousands of points and about a hundred boxes); box_points_at_times_reference
    # is that plain version, the reference the tests hold this to.
    cells = np.floor(points_world[:, :2] / BOX_CELL_M).astype(np.int64)
    low = cells.min(axis=0)
    cells -= low
    rows = int(cells[:, 1].max()) + 1
    keys = cells[:, 0] * rows + cells[:, 1]
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    for i in range(len(boxes)):
        c = boxes.center_world[i, :2]
        (x0, y0), (x1, y1) = (
            np.floor((np.stack([c - reach[i], c + reach[i]])) / BOX_CELL_M).astype(np.int64) - low
        )
        y0, y1 = max(int(y0), 0), min(int(y1), rows - 1)
        if y0 > y1:
            continue
        starts = np.arange(max(int(x0), 0), int(x1) + 1) * rows
        lo = np.searchsorted(keys, starts + y0)
        hi = np.searchsorted(keys, starts + y1, side="right")
        if not len(lo) or not (hi > lo).any():
            continue
        slab = np.concatenate([order[a:b] for a, b in zip(lo, hi, strict=True) if b > a])
        close = np.sum((points_world[slab] - boxes.center_world[i]) ** 2, axis=1) <= reach[i] ** 2
        near = slab[close]
        near = near[index[near] < 0]
        if near.size == 0:
            continue
        centre = boxes.center_world[i] + boxes.velocity_world[i] * dt_s[near, None]
        q = (points_world[near] - centre) @ rotations[i]  # world -> box: R^T p
        inside = np.all(np.abs(q) <= half[i], axis=1)
        if bottom_clearance_m is not None:
            inside &= q[:, 2] >= -0.5 * boxes.size_lwh[i, 2] + bottom_clearance_m
        index[near[inside]] = i
        local[near[inside]] = q[inside]
    return index, local


def box_points_at_times_reference(
    points_world: NDArray[np.float64],
    dt_s: NDArray[np.float64],
    boxes: Boxes,
    scale: float = 1.0,
    margin_m: float = 0.0,
    bottom_clearance_m: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The reference :func:`box_points_at_times`: every box's reach tested against every point.
    Kept for the tests."""
    n = len(points_world)
    index = np.full(n, -1, np.int64)
    local = np.zeros((n, 3))
    if n == 0 or len(boxes) == 0:
        return index, local
    rotations = geometry.quaternion_to_matrix(boxes.orientation_world)
    speed = np.linalg.norm(boxes.velocity_world, axis=1)
    max_dt = float(np.max(np.abs(dt_s))) if n else 0.0
    half = 0.5 * boxes.size_lwh * scale + margin_m
    reach = np.linalg.norm(half, axis=1) + speed * max_dt + 1e-6
    for i in range(len(boxes)):
        near = np.flatnonzero(np.sum((points_world - boxes.center_world[i]) ** 2, axis=1) <= reach[i] ** 2)
        near = near[index[near] < 0]
        if near.size == 0:
            continue
        centre = boxes.center_world[i] + boxes.velocity_world[i] * dt_s[near, None]
        q = (points_world[near] - centre) @ rotations[i]
        inside = np.all(np.abs(q) <= half[i], axis=1)
        if bottom_clearance_m is not None:
            inside &= q[:, 2] >= -0.5 * boxes.size_lwh[i, 2] + bottom_clearance_m
        index[near[inside]] = i
        local[near[inside]] = q[inside]
    return index, local


def moving_tracks(centres_by_track: dict[str, list[NDArray[np.float64]]], threshold_m: float) -> set[str]:
    """Tracks whose centres spread more than ``threshold_m`` (3D) around their median position."""
    moving = set()
    for track, centres in centres_by_track.items():
        c = np.asarray(centres, np.float64).reshape(-1, 3)
        if np.max(np.linalg.norm(c - np.median(c, axis=0), axis=1)) > threshold_m:
            moving.add(track)
    return moving


def repeated_points(
    sweeps: list[NDArray[np.float32]], voxel_m: float, min_sweeps: int
) -> NDArray[np.float32]:
    """The points (of all ``sweeps``, box frame) whose voxel was hit by at least ``min_sweeps``
    sweeps (fewer if the object was seen by fewer). The object's own surface is hit again and
    again at the same place in its box frame; anything else that passed through its box (a pole
    it drove by, another road user) is not."""
    need = min(min_sweeps, len(sweeps))
    if need <= 1 or voxel_m <= 0:
        return np.concatenate(sweeps)
    keys = [np.unique(_voxel_keys(q, voxel_m)) for q in sweeps]
    unique, hits = np.unique(np.concatenate(keys), return_counts=True)
    good = unique[hits >= need]
    points = np.concatenate(sweeps)
    return points[np.isin(_voxel_keys(points, voxel_m), good)]


def _voxel_keys(points: NDArray[np.floating], voxel_m: float) -> NDArray[np.int64]:
    """One int64 key per point for its voxel (21 bits per axis: +-1e6 voxels).

    Axis by axis, so that the float64 temporaries are one column (8 bytes a point, not the
    whole (N, 3) array's 24 several times over): :func:`_voxel_keys_reference`'s keys."""
    keys = np.zeros(len(points), np.int64)
    for axis, shift in ((0, 42), (1, 21), (2, 0)):
        column = np.floor(np.asarray(points[:, axis], np.float64) / voxel_m).astype(np.int64)
        column += 1 << 20
        if shift:
            column <<= shift
        keys |= column
    return keys


def _voxel_keys_reference(points: NDArray[np.floating], voxel_m: float) -> NDArray[np.int64]:
    """The reference :func:`_voxel_keys` (whole-array arithmetic). Kept for the tests."""
    v = np.floor(np.asarray(points, np.float64) / voxel_m).astype(np.int64) + (1 << 20)
    return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]


def voxel_downsample(
    points: NDArray[np.floating], voxel_m: float, backend: str = "numpy"
) -> NDArray[np.float32]:
    """(K, 3) float32 centroids of the points in each occupied voxel (a grid anchored at the
    origin for ``numpy``, at the points' minimum for ``open3d``); all points if ``voxel_m`` is 0.

    ``numpy`` sorts 64-bit voxel keys and sums each run, much faster than Open3D's
    ``voxel_down_sample`` and with the same centroids up to the grid's anchor (this grid is
    anchored at the origin, Open3D's at the points' minimum)."""
    if voxel_m <= 0 or len(points) == 0:
        return np.asarray(points, np.float32)
    if backend == "open3d":
        o3d = open3d()
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
        return np.asarray(cloud.voxel_down_sample(voxel_m).points, np.float32)
    if backend != "numpy":
        raise ValueError(f"voxel backend must be one of {VOXEL_BACKENDS}, got {backend!r}")
    keys = _voxel_keys(points, voxel_m)
    order = np.argsort(keys)
    keys = keys[order]
    start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    del keys
    counts = np.diff(np.r_[start, len(order)])
    out = np.empty((len(start), 3), np.float32)
    # Column by column (the same sums, in the same order, as over the (N, 3) float64 array):
    # the float64 copies are 8 bytes a point at a time, not 48.
    for axis in range(3):
        column = np.asarray(points[:, axis], np.float64)[order]
        out[:, axis] = np.add.reduceat(column, start) / counts
    return out


def voxel_merge(
    parts: list[tuple[NDArray[np.float32], NDArray[np.float64] | None]], voxel_m: float
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Weighted voxel centroids of several down-sampled parts: each part is (points (N, 3)
    float32, weights (N,) float64 or None for 1 each); returns the (K, 3) float32 centroids, each
    the weighted mean of the points in its voxel, and (K,) their summed weights.

    With every weight 1 this is :func:`voxel_downsample` (numpy backend): the same keys, order
    and sums. A part merged earlier enters with the number of points each of its centroids
    stands for, so merging in stages gives the centroids of merging at once (to the float32
    rounding of the stored centroids)."""
    points = np.concatenate([q for q, _ in parts]) if parts else np.zeros((0, 3), np.float32)
    weights = (
        np.concatenate([np.ones(len(q)) if w is None else w for q, w in parts]) if parts else np.zeros(0)
    )
    if len(points) == 0 or voxel_m <= 0:
        return np.asarray(points, np.float32), weights
    keys = _voxel_keys(points, voxel_m)
    order = np.argsort(keys)
    keys = keys[order]
    start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    del keys
    ordered_weights = weights[order]
    total = np.add.reduceat(ordered_weights, start)
    out = np.empty((len(start), 3), np.float32)
    for axis in range(3):
        column = np.asarray(points[:, axis], np.float64)[order]
        out[:, axis] = np.add.reduceat(column * ordered_weights, start) / total
    return out, total


def remove_outliers(points: NDArray[np.float32], neighbors: int, std_ratio: float) -> NDArray[np.float32]:
    """Open3D statistical outlier removal: drops points whose mean distance to their
    ``neighbors`` nearest neighbours is more than ``std_ratio`` deviations above the average."""
    if neighbors <= 0 or len(points) <= neighbors:
        return points
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    _, keep = cloud.remove_statistical_outlier(nb_neighbors=neighbors, std_ratio=std_ratio)
    return points[np.asarray(keep, np.int64)]


@dataclass
class _Accumulator:
    """Gathers sweep points while the pass over the scene runs."""

    params: AggregateParams
    static_chunks: list[NDArray[np.float32]] = field(default_factory=list)
    # The chunks merged so far: voxel centroids and how many chunk centroids each stands for.
    merged: tuple[NDArray[np.float32], NDArray[np.float64]] | None = None
    pending: list[NDArray[np.float32]] = field(default_factory=list)
    pending_sweeps: int = 0
    # Per track: points inside the enlarged box (world) and strictly inside (box frame).
    boxed_world: dict[str, list[NDArray[np.float32]]] = field(default_factory=dict)
    strict_box: dict[str, list[NDArray[np.float32]]] = field(default_factory=dict)
    centres: dict[str, list[NDArray[np.float64]]] = field(default_factory=dict)
    classes: dict[str, int] = field(default_factory=dict)
    elevations: list[NDArray[np.float64]] = field(default_factory=list)
    angular_steps: list[float] = field(default_factory=list)

    def add_static(self, points_world: NDArray[np.float32]) -> None:
        self.pending.append(points_world)
        self.pending_sweeps += 1
        if self.pending_sweeps >= self.params.chunk_sweeps:
            self.flush()

    def flush(self) -> None:
        if self.pending:
            self.static_chunks.append(
                voxel_downsample(np.concatenate(self.pending), self.params.voxel_m, self.params.voxel_backend)
            )
        self.pending, self.pending_sweeps = [], 0
        if len(self.static_chunks) >= MERGE_CHUNKS and self.params.voxel_backend == "numpy":
            self.merge()

    def merge(self) -> None:
        """Folds the down-sampled chunks into ``merged``: each voxel's centroid with the number
        of chunk centroids it stands for (:func:`voxel_merge`), so the map's final centroids are
        those of the chunks' centroids as if no chunk had been merged (to float32 rounding)."""
        parts = ([self.merged] if self.merged is not None else []) + [(c, None) for c in self.static_chunks]
        self.static_chunks = []
        self.merged = voxel_merge(parts, self.params.voxel_m)

    def static_map(self) -> NDArray[np.float32]:
        """(N, 3) float32: the static map's voxel centroids over every chunk (the chunks are
        released as they are read)."""
        p = self.params
        if self.merged is not None:
            self.merge()
            assert self.merged is not None
            points, _ = self.merged
            self.merged = None
            return points
        if not self.static_chunks:
            return np.zeros((0, 3), np.float32)
        static = np.concatenate(self.static_chunks)
        self.static_chunks = []
        return voxel_downsample(static, p.voxel_m, p.voxel_backend)


def return_elevations(sweep: LidarSweep) -> NDArray[np.float64]:
    """(N,) elevation of each return seen from its ray origin, radians, ego axes."""
    d = sweep.points_ego.astype(np.float64) - sweep.origins_ego
    return np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))


def lidar_angular_step(sweep: LidarSweep) -> float:
    """A sweep's angular sampling step, radians: the larger of the median step between adjacent
    beams (by their median elevation) and the median azimuth step along a beam."""
    if len(sweep) < 2:
        return float(np.radians(0.5))
    d = sweep.points_ego.astype(np.float64) - sweep.origins_ego
    elevation = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    key = sweep.lidar_id.astype(np.int64) * 65536 + sweep.beam_index
    order = np.lexsort((azimuth, key))
    same = key[order][1:] == key[order][:-1]
    az_steps = np.diff(azimuth[order])[same]
    az_steps = az_steps[az_steps > 1e-6]
    beams, inverse = np.unique(key, return_inverse=True)
    beam_elev = np.array([np.median(elevation[inverse == b]) for b in range(len(beams))])
    el_steps = np.abs(np.diff(np.sort(beam_elev)))
    el_steps = el_steps[el_steps > 1e-6]
    steps = [np.median(x) for x in (az_steps, el_steps) if len(x)]
    return float(max(steps)) if steps else float(np.radians(0.5))


def sweep_dt_s(sweep: LidarSweep, boxes_micros: int) -> NDArray[np.float64]:
    """(N,) each point's measurement time minus ``boxes_micros``, seconds."""
    return (sweep.time_offset_micros.astype(np.float64) + (sweep.timestamp_micros - boxes_micros)) * 1e-6


def aggregate_scene(scene: Scene, params: AggregateParams | None = None) -> LidarMap:
    """Aggregates all LiDAR sweeps of ``scene`` into a static world map and rigid object models.

    Reads each frame's geometry once (images are not loaded). A scene without any LiDAR gives an
    empty map (and a warning), not an error.
    """
    p = params or AggregateParams()
    t0 = time.perf_counter()
    ego_boxes = checked_ego_boxes(scene)
    check_lidar = LidarOriginCheck(scene, ego_boxes)
    acc = _Accumulator(p)
    counts = {"sweeps": 0, "points": 0, "ego_body_points": 0, "boxed_points": 0}
    for i in range(len(scene.frames)):
        frame = frame_geometry(scene.frames, i)
        boxes = frame.boxes
        for k, track in enumerate(boxes.track_id):
            acc.centres.setdefault(track, []).append(boxes.center_world[k])
            acc.classes[track] = int(boxes.class_id[k])
        sweep = frame.lidar
        if sweep is None or len(sweep) == 0:
            continue
        check_lidar(sweep)
        counts["sweeps"] += 1
        counts["points"] += len(sweep)
        if counts["sweeps"] % 10 == 1:  # the sensor's geometry needs a sample, not every sweep
            acc.elevations.append(return_elevations(sweep))
            acc.angular_steps.append(lidar_angular_step(sweep))
        body = in_ego_body(sweep.points_ego, ego_boxes, p.ego_margin_m)
        counts["ego_body_points"] += int(body.sum())
        pts = sweep.points_world()[~body]
        dt = sweep_dt_s(sweep, frame.timestamp_micros)[~body]
        enlarged, _ = box_points_at_times(pts, dt, boxes, p.box_scale, p.box_margin_m)
        strict, local = box_points_at_times(pts, dt, boxes, 1.0, 0.0, p.ground_clearance_m)
        acc.add_static(pts[enlarged < 0].astype(np.float32))
        counts["boxed_points"] += int(np.sum(enlarged >= 0))
        for k in np.unique(enlarged[enlarged >= 0]):
            track = boxes.track_id[k]
            acc.boxed_world.setdefault(track, []).append(pts[enlarged == k].astype(np.float32))
            acc.strict_box.setdefault(track, []).append(local[strict == k].astype(np.float32))
    acc.flush()
    moving = moving_tracks(acc.centres, p.moving_threshold_m)
    non_rigid = {t for t in moving if acc.classes[t] in tx.NON_RIGID_IDS}
    # Static tracks' points are scenery after all (parked cars, standing people).
    for track, parts in acc.boxed_world.items():
        if track not in moving:
            acc.static_chunks.append(voxel_downsample(np.concatenate(parts), p.voxel_m, p.voxel_backend))
    static = acc.static_map()
    before_outliers = len(static)
    static = remove_outliers(static, p.outlier_neighbors, p.outlier_std_ratio)
    objects = {}
    for track in sorted(moving - non_rigid):
        parts = [q for q in acc.strict_box.get(track, []) if len(q)]
        if parts:
            points = repeated_points(parts, p.object_voxel_m, p.object_min_sweeps)
            objects[track] = ObjectModel(
                track,
                acc.classes[track],
                voxel_downsample(points, p.object_point_m, p.voxel_backend),
                len(parts),
            )
    if counts["sweeps"] == 0:
        log.warning("scene %s: no LiDAR in any frame; the depth maps will be empty", scene.scene_id)
    points, keys, start = _tile_sort(static)
    stats = {
        **counts,
        "static_points": len(points),
        "outliers_removed": before_outliers - len(points),
        "moving_tracks": len(moving),
        "non_rigid_tracks": len(non_rigid),
        "object_models": len(objects),
        "object_points": int(sum(len(o.points_box) for o in objects.values())),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    elevations = np.concatenate(acc.elevations) if acc.elevations else np.zeros(0)
    max_elevation = float(np.percentile(elevations, 99.9)) if len(elevations) else float(np.pi / 2)
    step = float(np.median(acc.angular_steps)) if acc.angular_steps else float(np.radians(0.5))
    stats["max_elevation_deg"] = round(float(np.degrees(max_elevation)), 3)
    stats["angular_step_deg"] = round(float(np.degrees(step)), 4)
    return LidarMap(
        points,
        keys,
        start,
        p.voxel_m,
        frozenset(moving),
        frozenset(non_rigid),
        objects,
        ego_boxes,
        max_elevation_rad=max_elevation,
        angular_step_rad=step,
        ground_clearance_m=p.ground_clearance_m,
        stats=stats,
    )


#: Thinning levels of the map's points: a point's level is k with probability 2^-(k + 1) (the last
#: level takes the rest), from a hash of its coordinates (:func:`point_levels`).
LEVELS = 16


def point_levels(points: NDArray[np.float32]) -> NDArray[np.uint8]:
    """(N,) uint8 level of each point, 0 to ``LEVELS - 1``: the number of trailing one bits of a
    hash of its float32 coordinates, so a point's level depends on where it is, not on its place
    in an array, and the points of levels >= k are a uniform 2^-k subset of any region."""
    bits = np.ascontiguousarray(points, np.float32).view(np.uint32).astype(np.uint64)
    h = _mix64((bits[:, 0] ^ (bits[:, 1] << np.uint64(21)) ^ (bits[:, 2] << np.uint64(42))).view(np.int64))
    level = np.zeros(len(points), np.uint8)
    for k in range(LEVELS - 1):
        level += ((h >> np.uint64(k)) & np.uint64(1)).astype(bool) & (level == k)
    return level


def _tile_sort(
    points: NDArray[np.float32],
) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.int64]]:
    """Points sorted by tile, the sorted occupied tile keys and their start offsets.

    Within a tile the points come by decreasing :func:`point_levels`, each level in the order they
    came (the map's voxel order, which keeps neighbours near each other in memory): the tile's
    first points up to a level boundary are a uniform subset of it (:meth:`LidarMap.uniform_takes`),
    so the projection takes a far tile's first points rather than every k-th, which on a saturated
    voxel grid sorted by key would keep whole rows and drop the rows between them."""
    tiles = np.floor(points[:, :2] / TILE_M).astype(np.int64)
    keys = _tile_key(tiles[:, 0], tiles[:, 1])
    del tiles
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    unique, first = np.unique(keys, return_index=True)
    start = np.append(first, len(keys)).astype(np.int64)
    del keys
    points = points[order]
    del order
    # Tile by tile, so the temporaries stay the size of a tile, not of the map.
    for a, b in zip(start[:-1].tolist(), start[1:].tolist(), strict=True):
        if b - a > 1:
            by_level = np.argsort(LEVELS - 1 - point_levels(points[a:b]), kind="stable")
            points[a:b] = points[a:b][by_level]
    return points, unique, start


def tile_level_counts(points: NDArray[np.float32], start: NDArray[np.int64]) -> NDArray[np.int64]:
    """(T, LEVELS + 1) int64: entry [t, k] counts tile t's points of level >= k (the first ones in
    the tile, :func:`_tile_sort`); [t, 0] is the tile's size and [t, LEVELS] is 0."""
    counts = np.zeros((len(start) - 1, LEVELS + 1), np.int64)
    if len(start) < 2 or start[-1] == 0:
        return counts
    for t, (a, b) in enumerate(zip(start[:-1].tolist(), start[1:].tolist(), strict=True)):
        counts[t, :LEVELS] = np.bincount(point_levels(points[a:b]), minlength=LEVELS)
    counts[:, :LEVELS] = np.cumsum(counts[:, :LEVELS][:, ::-1], axis=1)[:, ::-1]
    counts[:, LEVELS] = 0
    return counts


def _mix64(x: NDArray[np.int64]) -> NDArray[np.uint64]:
    """splitmix64's finaliser of ``x`` + its increment (uint64, wrapping): a cheap hash."""
    z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def tile_height_ranges(
    points: NDArray[np.float32], start: NDArray[np.int64]
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(T,) float32 lowest and highest z (world, metres) of each tile's points (``start``: the
    tiles' (T + 1,) offsets into the tile-sorted ``points``)."""
    if len(start) < 2:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    z = np.ascontiguousarray(points[:, 2])
    return np.minimum.reduceat(z, start[:-1]), np.maximum.reduceat(z, start[:-1])


@register_stage("aggregate_lidar", params=AggregateParams)
def aggregate_lidar(scene: Scene, params: AggregateParams) -> Scene:
    """Stage: aggregates the scene's LiDAR (:func:`aggregate_scene`) into
    ``scene.products["lidar_map"]`` and records its statistics in the scene metadata."""
    lidar_map = aggregate_scene(scene, params)
    scene.products["lidar_map"] = lidar_map
    # Timings stay out of the metadata: the rows of a cache must not depend on the machine.
    stats = {k: v for k, v in lidar_map.stats.items() if k != "seconds"}
    scene.metadata["lidar_map"] = {"voxel_m": lidar_map.voxel_m, **stats}
    log.info("scene %s: LiDAR map %s", scene.scene_id, lidar_map.stats)
    return scene
