"""Pseudo-semantic labels for every image: a trained segmenter, refined by geometry.

Entry points: :func:`label_camera` (one image) and the stage ``pseudo_semantics``, which runs it
for every camera of every frame, lazily, and stores a :class:`CameraSemantics` on each image
(class, confidence and source per pixel; sources in :data:`records.PSEUDO_SOURCES`).
:func:`label_camera_reference` is the plain whole-image version :func:`label_camera` is tested
against (same labels; the plain version works on whole-image float64 points, this one on
per-calibration ray planes and box footprints: docs/design/semantics.md).

As in the paper, a SegFormer fine-tuned on labelled frames (``phigenesis-train segmenter``) is run
over every image. Its labels are then refined where the scene's geometry knows better:

- **box** (source 2): a pixel whose 3D point (the pixel's ray at its depth: the depth stages'
  dense depth, else their sparse depth, else the frame's own LiDAR sweep projected) lies inside a
  box of a vehicle, person or cyclist at the image's own time (the camera's ``boxes``, else the
  frame's moved by their velocity) takes the box's class. Boxes are grown by ``box_margin_m`` and
  points less than ``box_clearance_m`` above a box's bottom are left out (the road under a car).
  Always replaces the segmenter.
- **ground plane** (source 3): a plane fitted to the sweep's low points by RANSAC (near the ego,
  outside boxes); pixels whose points lie within ``ground_tolerance_m + ground_tolerance_rel *
  range`` of it, nearer than ``ground_max_range_m``, are on the ground. Grass verges and car parks
  are level with the road too, so only on-ground regions (8-connected in the image) that reach
  the ego's own corridor (``|y_ego| <= ground_seed_half_width_m``) are road: a raised kerb or
  anything standing cuts a region off. Replaces segmenter classes other than the flat ones (road,
  sidewalk, terrain) that are less confident than ``keep_segmenter_above``.
- **sky** (source 4): above the horizon, a pixel with no depth whose direction the LiDAR swept
  without a return (inside its vertical field; of several LiDARs only the long-range ones count,
  :func:`long_range_points`) is sky; so is every depth-less pixel above such a
  pixel at the top of the LiDAR's field in its column (the LiDAR cannot see higher; a column whose
  top-of-field pixel hit something, such as a facade, stays unlabelled there). Buildings beyond
  the LiDAR's range look the same, so the rule only replaces segmenter labels less confident than
  ``sky_keep_segmenter_above`` (a trained segmenter knows sky better: BENCHMARKS.md).

Without a checkpoint the stage gives the geometric labels alone (255 and source 0 elsewhere) and
logs that it did. Confidences: the segmenter's softmax maximum; :data:`RULE_CONFIDENCE` for rules
(a rule that agrees with the segmenter keeps source 1 and the larger confidence).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.camera_tables import RayComponents, pixel_rays_cam, ray_components_of
from phigenesis.data.native import load_box_labels
from phigenesis.data.records import (
    PSEUDO_SOURCES,
    Boxes,
    CameraImage,
    CameraSemantics,
    Frame,
    LazyFrames,
    LidarSweep,
    Scene,
)
from phigenesis.data.segmenter import Segmenter, SegmenterOutput
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.densify import sweep_sparse_depth
from phigenesis.data.stages.project import pixel_rays
from phigenesis.options import check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

Rule = Literal["boxes", "ground", "sky"]
RULES: tuple[Rule, ...] = get_args(Rule)
SOURCE = {name: i for i, name in enumerate(PSEUDO_SOURCES)}
#: Confidence of each geometric rule's labels ("sky_above": above the LiDAR's field).
RULE_CONFIDENCE = {"box": 0.9, "ground_plane": 0.8, "sky": 0.9, "sky_above": 0.7}
#: Classes whose boxes label pixels (things with 3D boxes).
BOX_CLASSES = tx.THING_IDS
#: Flat classes the ground-plane rule never replaces.
FLAT_IDS = frozenset({tx.ROAD, tx.SIDEWALK, tx.TERRAIN})


@dataclass(frozen=True)
class PseudoSemanticsParams:
    """Parameters of ``pseudo_semantics`` (lengths in metres, angles in degrees).

    Attributes:
        checkpoint: path of a segmenter checkpoint (``phigenesis-train segmenter``); None: the
            geometric labels alone.
        model: the model variant the checkpoint must hold (e.g. ``segformer_tiny``); None: any.
        rules: geometric rules to apply, any of "boxes", "ground", "sky" (empty: segmenter only).
        input_height: images are resized to this height (aspect kept) before the segmenter, and
            its probabilities back to the image's size; None: the image's own size.
        device: torch device of the segmenter.
        box_margin_m: boxes are grown by this on every side for the point-in-box test.
        box_clearance_m: points less than this above a box's bottom are not the object.
        ground_tolerance_m, ground_tolerance_rel: a point is on the ground plane within
            ``ground_tolerance_m + ground_tolerance_rel * range``.
        ground_max_range_m: the ground rule labels points nearer than this (camera distance).
        ground_fit_range_m: LiDAR points within this horizontal distance of the ego, and between
            ``-ground_fit_height_m`` and ``+ground_fit_height_m`` of its ground, feed the fit.
        ground_fit_height_m: see ``ground_fit_range_m``.
        ground_seed_half_width_m: on-ground regions reaching points this close to the ego's x axis
            (at the image's pose) are road.
        sky_min_elevation_deg: the sky rule only labels pixels looking at least this far above
            the horizontal.
        sky_bin_deg: angular bins (azimuth and elevation) in which LiDAR returns are looked for.
        keep_segmenter_above: the ground rule does not replace segmenter labels at least this
            confident.
        sky_keep_segmenter_above: the sky rule does not replace segmenter labels at least this
            confident.
        seed: seed of the RANSAC plane fit.
    """

    checkpoint: str | None = option(None)
    model: str | None = option(None)
    rules: tuple[Rule, ...] = option(RULES)
    input_height: int | None = option(None, ge=8, le=100_000)
    device: str = option("cpu")
    box_margin_m: float = option(0.1, ge=0, le=100)
    box_clearance_m: float = option(0.1, ge=0, le=100)
    ground_tolerance_m: float = option(0.06, ge=0, le=100)
    ground_tolerance_rel: float = option(0.002, ge=0, le=10)
    ground_max_range_m: float = option(40.0, gt=0, le=1000)
    ground_fit_range_m: float = option(30.0, gt=0, le=1000)
    ground_fit_height_m: float = option(0.5, gt=0, le=100)
    ground_seed_half_width_m: float = option(3.0, ge=0, le=1000)
    sky_min_elevation_deg: float = option(0.5, ge=-90, le=90)
    sky_bin_deg: float = option(1.0, gt=0, le=90)
    keep_segmenter_above: float = option(0.9, ge=0, le=1)
    sky_keep_segmenter_above: float = option(0.5, ge=0, le=1)
    seed: int = option(0, ge=0, le=2**32 - 1)

    def __post_init__(self) -> None:
        check_options(self, "PseudoSemanticsParams")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PseudoSemanticsParams:
        return from_mapping(cls, values, "pseudo_semantics")


# --------------------------------------------------------------------------------------------
# Geometry


def camera_boxes(frame: Frame, camera: CameraImage) -> Boxes:
    """The boxes at the image's own capture time: the camera's where a stage made them, else the
    frame's moved by their velocity (world frame)."""
    if camera.boxes is not None:
        return camera.boxes
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    if dt_s == 0 or len(boxes) == 0:
        return boxes
    return dataclasses.replace(boxes, center_world=boxes.center_world + boxes.velocity_world * dt_s)


def pixel_depth(frame: Frame, camera: CameraImage) -> NDArray[np.float32]:
    """(H, W) z-depth in metres, 0 where unknown: the depth stages' dense depth, else their
    sparse depth, else the frame's own LiDAR sweep projected (nearest point), else zeros."""
    cal = camera.calibration
    if camera.depth is not None:
        return camera.depth.dense_m if camera.depth.dense_m is not None else camera.depth.sparse_m
    if frame.lidar is not None and len(frame.lidar):
        return sweep_sparse_depth(frame, camera)
    return np.zeros((cal.height, cal.width), np.float32)


def box_labels(
    points_world: NDArray[np.float64],
    valid: NDArray[np.bool_],
    boxes: Boxes,
    margin_m: float,
    clearance_m: float,
    regions: list[NDArray[np.int64] | None] | None = None,
) -> NDArray[np.uint8]:
    """(P,) class of the thing box holding each point ((P, 3) world; only ``valid`` ones tested),
    255 where none. Boxes grow by ``margin_m`` per side; the bottom ``clearance_m`` is left out.
    Where boxes overlap, the one whose centre is nearest the point wins. ``regions``: for each
    box, the indices of the only points that can be inside it (None: any; :func:`box_regions`)."""
    labels = np.full(len(points_world), tx.IGNORE_ID, np.uint8)
    best = np.full(len(points_world), np.inf)
    all_valid = np.flatnonzero(valid)
    # The valid points by world x: a box's candidates (without regions) are the run within its
    # radius in x, found by bisection, not a pass over every point per box.
    by_x = xs = all_valid
    if regions is None or any(r is None for r in regions):
        by_x = all_valid[np.argsort(points_world[all_valid, 0], kind="stable")]
        xs = points_world[by_x, 0]
    rotations = geometry.quaternion_to_matrix(boxes.orientation_world).reshape(-1, 3, 3)
    for k in range(len(boxes)):
        cls = int(boxes.class_id[k])
        if cls not in BOX_CLASSES:
            continue
        half = 0.5 * boxes.size_lwh[k]
        radius = np.linalg.norm(half + abs(margin_m)) + abs(clearance_m)  # holds the grown box
        region = None if regions is None else regions[k]
        if region is None:
            cx = boxes.center_world[k, 0]
            lo, hi = np.searchsorted(xs, cx - radius, "left"), np.searchsorted(xs, cx + radius, "right")
            candidates = by_x[lo:hi]
        else:
            candidates = region[valid[region]]
        if candidates.size == 0:
            continue
        offset = points_world[candidates] - boxes.center_world[k]  # [P', 3] world
        dist2 = np.einsum("ij,ij->i", offset, offset)
        near = dist2 <= radius**2
        if not near.any():
            continue
        local = offset[near] @ rotations[k]  # box frame: R^T p
        inside = (
            (np.abs(local[:, 0]) <= half[0] + margin_m)
            & (np.abs(local[:, 1]) <= half[1] + margin_m)
            & (local[:, 2] <= half[2] + margin_m)
            & (local[:, 2] >= -half[2] + clearance_m)
        )
        index = candidates[near][inside]
        closer = dist2[near][inside] < best[index]
        labels[index[closer]] = cls
        best[index[closer]] = dist2[near][inside][closer]
    return labels


def box_rectangles(
    camera: CameraImage, boxes: Boxes, margin_m: float
) -> list[tuple[int, int, int, int] | None]:
    """For each box (grown by ``margin_m``), the image rectangle ``(v0, v1, u0, u1)`` (rows
    ``v0:v1``, columns ``u0:u1``) holding its projected corners plus one pixel, clipped to the
    image: the only pixels whose rays can pass through it. The whole image where a corner lies
    behind the camera and another in front (any pixel may see it); None where none can (all
    corners behind the camera, or the rectangle outside the image)."""
    return [None if f is None else f[0] for f in _box_footprints(camera, boxes, margin_m)]


def _box_footprints(
    camera: CameraImage, boxes: Boxes, margin_m: float
) -> list[tuple[tuple[int, int, int, int], float, float] | None]:
    """For each box (grown by ``margin_m``): its :func:`box_rectangles` rectangle and the range
    of camera z (metres) its corners span (a point inside the box has its z, the pixel's depth,
    in that range: the box is convex); None where no pixel can see it. Where every corner lies in
    front of the camera but some beyond the distortion's valid radius (the whole image for
    :func:`box_regions`), the rectangle of the pixels whose rays pass within the corners' ray
    bounds (:meth:`~phigenesis.data.camera_tables.RayComponents.rectangle`): no pixel outside it
    can see the box."""
    cal = camera.calibration
    tables = ray_components_of(cal)
    h, w = cal.height, cal.width
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    grown = boxes.size_lwh + 2 * abs(margin_m)
    corners = geometry.rotated_box_corners(
        boxes.center_world, grown, geometry.quaternion_to_matrix(boxes.orientation_world).reshape(-1, 3, 3)
    )  # [M, 8, 3] world
    out: list[tuple[tuple[int, int, int, int], float, float] | None] = []
    for k in range(len(boxes)):
        c_cam = geometry.transform_points(camera_from_world, corners[k])
        z = (float(c_cam[:, 2].min()), float(c_cam[:, 2].max()))
        uv, ok = geometry.project_points(c_cam, cal.intrinsics, cal.distortion)
        if not ok.all():
            if np.all(c_cam[:, 2] > 0):  # in front, beyond the distortion's valid radius
                xy = c_cam[:, :2] / c_cam[:, 2:]  # the box's rays pass within these bounds
                lo, hi = xy.min(axis=0), xy.max(axis=0)
                rect = tables.rectangle(lo[0], hi[0], lo[1], hi[1])
            else:
                rect = (0, h, 0, w) if np.any(c_cam[:, 2] > 0) else None
            out.append(None if rect is None else (rect, *z))
            continue
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, (w - 1, h - 1))
        if u0 > u1 or v0 > v1:
            out.append(None)
        else:
            out.append(((int(v0), int(v1) + 1, int(u0), int(u1) + 1), *z))
    return out


def box_regions(camera: CameraImage, boxes: Boxes, margin_m: float) -> list[NDArray[np.int64] | None]:
    """For each box (grown by ``margin_m``), the flat (row-major) indices of the pixels inside its
    projected bounding rectangle in ``camera``; None where a corner lies behind the camera (any
    pixel may see it)."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    grown = boxes.size_lwh + 2 * abs(margin_m)
    corners = geometry.rotated_box_corners(
        boxes.center_world, grown, geometry.quaternion_to_matrix(boxes.orientation_world).reshape(-1, 3, 3)
    )  # [M, 8, 3] world
    out: list[NDArray[np.int64] | None] = []
    for k in range(len(boxes)):
        c_cam = geometry.transform_points(camera_from_world, corners[k])
        uv, ok = geometry.project_points(c_cam, cal.intrinsics, cal.distortion)
        if not ok.all():
            out.append(None if np.any(c_cam[:, 2] > 0) else np.zeros(0, np.int64))
            continue
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, (w - 1, h - 1))
        if u0 > u1 or v0 > v1:
            out.append(np.zeros(0, np.int64))
            continue
        vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
        out.append((vv * w + uu).ravel())
    return out


@dataclass(frozen=True)
class GroundPlane:
    """A plane ``normal . p + offset = 0`` in the world frame, ``normal`` a unit vector pointing up."""

    normal: NDArray[np.float64]
    offset: float
    inliers: int

    def height(self, points_world: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N,) signed distance of (N, 3) world points above the plane, metres."""
        return points_world @ self.normal + self.offset


def fit_ground_plane(
    frame: Frame, params: PseudoSemanticsParams, boxes: Boxes | None = None
) -> GroundPlane | None:
    """The ground plane of the frame's sweep: RANSAC (threshold 5 cm, normals within 20 deg of
    the ego's up axis) over low points near the ego outside boxes, refined by least squares on
    the inliers. None without a sweep or with fewer than 30 candidate points."""
    sweep = frame.lidar
    if sweep is None or len(sweep) < 30:
        return None
    p_ego = sweep.points_ego.astype(np.float64)
    keep = (np.hypot(p_ego[:, 0], p_ego[:, 1]) < params.ground_fit_range_m) & (
        np.abs(p_ego[:, 2]) < params.ground_fit_height_m
    )
    p_world = geometry.transform_points(sweep.world_from_ego, p_ego[keep])
    if boxes is not None and len(boxes):
        in_box = box_labels(p_world, np.ones(len(p_world), bool), boxes, 0.3, -0.3) != tx.IGNORE_ID
        p_world = p_world[~in_box]
    if len(p_world) < 30:
        return None
    up = sweep.world_from_ego[:3, 2]
    rng = np.random.default_rng(params.seed)
    sample = p_world[rng.choice(len(p_world), min(len(p_world), 4000), replace=False)]
    best_count, best = 0, None
    for _ in range(64):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n = n / norm * np.sign(n @ up or 1.0)
        if n @ up < np.cos(np.radians(20.0)):
            continue
        count = int(np.sum(np.abs((sample - a) @ n) < 0.05))
        if count > best_count:
            best_count, best = count, (n, -float(n @ a))
    if best is None:
        return None
    n, d = best
    inliers = p_world[np.abs(p_world @ n + d) < 0.05]
    if len(inliers) >= 3:
        centre = inliers.mean(axis=0)
        _, _, vt = np.linalg.svd(inliers - centre, full_matrices=False)
        n = vt[2] * np.sign(vt[2] @ up or 1.0)
        d = -float(n @ centre)
    return GroundPlane(n, d, len(inliers))


#: A sensor of a multi-LiDAR sweep counts for the sky rule if its returns reach this share of the
#: farthest-reaching sensor's range (both the 99th percentile of their ranges).
SKY_MIN_REACH_SHARE = 0.5


def long_range_points(sweep: LidarSweep) -> NDArray[np.bool_] | None:
    """(N,) which points of a multi-LiDAR sweep come from its long-range sensors: those whose
    returns reach :data:`SKY_MIN_REACH_SHARE` of the farthest-reaching one's range (99th
    percentiles of the ranges from each point's own origin). None for a single sensor (all count).

    Waymo's four short-range LiDARs see up to 30 deg above the horizon but only ~20 m: a facade
    beyond that gives them no return, so directions they swept without a return are not open sky
    (with them, the sky rule labelled 1.8 M building pixels of 3 real-size frames sky)."""
    ids = sweep.lidar_id
    counts = np.bincount(ids) if len(ids) else np.zeros(0, np.int64)
    present = np.flatnonzero(counts)
    if len(present) <= 1:
        return None
    ranges = np.linalg.norm(sweep.points_ego - sweep.origins_ego, axis=1)
    reach = np.zeros(len(counts))
    for k in present.tolist():
        reach[k] = np.percentile(ranges[ids == k], 99)
    keep = reach >= SKY_MIN_REACH_SHARE * reach.max()
    return keep[ids]


def lidar_returns_grid(frame: Frame, bin_deg: float) -> tuple[NDArray[np.bool_], float] | None:
    """Where the sweep got returns, as an (elevation, azimuth) occupancy grid of ``bin_deg`` bins
    around the sensor's mean position (world axes; row 0 at -90 deg, column 0 at -180 deg),
    dilated by one bin, and the field's top elevation (degrees, the 99.9th percentile of return
    elevations). Of a multi-LiDAR sweep only the long-range sensors count
    (:func:`long_range_points`). None without a sweep."""
    sweep = frame.lidar
    if sweep is None or len(sweep) == 0:
        return None
    keep = long_range_points(sweep)
    origins = sweep.origins_ego if keep is None else sweep.origins_ego[keep]
    origin = geometry.transform_points(sweep.world_from_ego, origins.astype(np.float64)).mean(axis=0)
    points = sweep.points_world() if keep is None else sweep.points_world()[keep]
    rays = points - origin
    azimuth = np.degrees(np.arctan2(rays[:, 1], rays[:, 0]))
    elevation = np.degrees(np.arctan2(rays[:, 2], np.hypot(rays[:, 0], rays[:, 1])))
    top = float(np.percentile(elevation, 99.9))
    rows, cols = int(np.ceil(180 / bin_deg)), int(np.ceil(360 / bin_deg))
    grid = np.zeros((rows, cols), bool)
    grid[_bin(elevation + 90, bin_deg, rows), _bin(azimuth + 180, bin_deg, cols)] = True
    grid = grid | np.roll(grid, 1, 1) | np.roll(grid, -1, 1)
    grid[1:] |= grid[:-1].copy()
    grid[:-1] |= grid[1:].copy()
    return grid, top


def _bin(angle_deg: NDArray[np.float64], bin_deg: float, count: int) -> NDArray[np.int64]:
    return np.clip((angle_deg // bin_deg).astype(np.int64), 0, count - 1)


def sky_mask(
    returns: tuple[NDArray[np.bool_], float],
    rays_world: NDArray[np.float64],
    depth: NDArray[np.float32],
    params: PseudoSemanticsParams,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(H, W) masks of sky inside the LiDAR's field and sky above it (see the module docstring).

    ``returns``: :func:`lidar_returns_grid`'s grid and top elevation; ``rays_world``: (H * W, 3)
    pixel ray directions in world axes; ``depth``: (H, W) metres, 0 unknown.
    """
    h, w = depth.shape
    grid, top_deg = returns
    elevation = np.degrees(np.arctan2(rays_world[:, 2], np.hypot(rays_world[:, 0], rays_world[:, 1])))
    azimuth = np.degrees(np.arctan2(rays_world[:, 1], rays_world[:, 0]))
    rows, cols = grid.shape
    hit = grid[_bin(elevation + 90, params.sky_bin_deg, rows), _bin(azimuth + 180, params.sky_bin_deg, cols)]
    elevation, hit = elevation.reshape(h, w), hit.reshape(h, w)
    no_depth = depth <= 0
    in_field = (elevation >= params.sky_min_elevation_deg) & (elevation <= top_deg)
    sky_in = in_field & no_depth & ~hit
    # Above the field: a column whose highest in-field pixel is open sky is sky above it too.
    above = elevation > top_deg
    has_field = in_field.any(axis=0)
    first_in = np.argmax(in_field, axis=0)  # topmost in-field row per column (rows go down)
    open_top = has_field & sky_in[first_in, np.arange(w)]
    sky_above = above & no_depth & open_top[None, :] & (np.arange(h)[:, None] < first_in[None, :])
    return sky_in, sky_above


def connected_to(mask: NDArray[np.bool_], seeds: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(H, W) the 8-connected regions of ``mask`` that contain a ``seeds`` pixel."""
    count, regions = cv2.connectedComponents(mask.view(np.uint8), connectivity=8)
    keep = np.zeros(count, bool)
    keep[regions[seeds & mask]] = True
    keep[0] = False
    return keep[regions]


@dataclass(frozen=True)
class LidarEvidence:
    """What a frame's sweep says for all its cameras: the ground plane and where it got returns
    (:func:`lidar_returns_grid`); None where the frame has no sweep or the rule is off."""

    plane: GroundPlane | None
    returns: tuple[NDArray[np.bool_], float] | None

    @classmethod
    def of(cls, frame: Frame, params: PseudoSemanticsParams) -> LidarEvidence:
        return cls(
            fit_ground_plane(frame, params, frame.boxes) if "ground" in params.rules else None,
            lidar_returns_grid(frame, params.sky_bin_deg) if "sky" in params.rules else None,
        )


# --------------------------------------------------------------------------------------------
# Labelling one image


@dataclass
class RayCache:
    """Pixel rays (camera frame, z = 1, (H * W, 3)) by camera name, reused across frames (for
    :func:`label_camera_reference`; :func:`label_camera` uses the per-calibration tables)."""

    rays_cam: dict[str, NDArray[np.float64]] = field(default_factory=dict)

    def rays(self, camera: CameraImage) -> NDArray[np.float64]:
        key = camera.name
        if (
            key not in self.rays_cam
            or len(self.rays_cam[key]) != camera.calibration.width * camera.calibration.height
        ):
            self.rays_cam[key] = pixel_rays(camera)
        return self.rays_cam[key]


def label_camera_reference(
    frame: Frame,
    camera: CameraImage,
    params: PseudoSemanticsParams,
    segmentation: SegmenterOutput | None = None,
    evidence: LidarEvidence | None = None,
    rays_cam: NDArray[np.float64] | None = None,
) -> CameraSemantics:
    """Pseudo labels of one image (see the module docstring): the plain version, every rule on
    (H * W, 3) float64 world points of the whole image. :func:`label_camera` gives the same labels
    (tests/test_semantics_stage.py) several times faster; this one is kept as its reference.

    ``segmentation``: the segmenter's output, or None for geometric labels alone;
    ``evidence``: the frame's :class:`LidarEvidence` and ``rays_cam``: (H * W, 3) camera-frame
    pixel rays (z = 1), both computed if None.
    """
    cal = camera.calibration
    h, w = cal.height, cal.width
    label = np.full((h, w), tx.IGNORE_ID, np.uint8)
    confidence = np.zeros((h, w), np.float32)
    source = np.zeros((h, w), np.uint8)
    if segmentation is not None:
        assert segmentation.label.shape == (h, w), (segmentation.label.shape, h, w)
        label[:] = segmentation.label
        confidence[:] = segmentation.confidence
        source[:] = SOURCE["segmenter"]
    if not params.rules:
        return CameraSemantics(label, confidence, source)
    rays_cam = pixel_rays(camera) if rays_cam is None else rays_cam
    evidence = LidarEvidence.of(frame, params) if evidence is None else evidence
    depth = pixel_depth(frame, camera)
    world_from_camera = camera.world_from_camera
    rays_world = rays_cam @ world_from_camera[:3, :3].T  # [H*W, 3]
    has_depth = depth.reshape(-1) > 0
    points = world_from_camera[:3, 3] + rays_world * depth.reshape(-1, 1)  # [H*W, 3] world

    def apply(mask: NDArray[np.bool_], cls: int, rule: str, replace: NDArray[np.bool_]) -> None:
        """Labels ``mask`` pixels ``cls`` from ``rule`` where ``replace`` allows it; where the
        segmenter already says ``cls`` it keeps its source and takes the larger confidence."""
        conf = RULE_CONFIDENCE[rule]
        agree = mask & (label == cls) & (source == SOURCE["segmenter"])
        confidence[agree] = np.maximum(confidence[agree], conf)
        take = mask & ~agree & replace
        label[take], confidence[take] = cls, conf
        source[take] = SOURCE["sky" if rule.startswith("sky") else rule]

    unlabelled = source == SOURCE["none"]
    weak = unlabelled | (confidence < params.keep_segmenter_above)
    if "sky" in params.rules and evidence.returns is not None:
        sky_in, sky_above = sky_mask(evidence.returns, rays_world, depth, params)
        unsure = unlabelled | (confidence < params.sky_keep_segmenter_above)
        apply(sky_in, tx.SKY, "sky", unsure)
        apply(sky_above, tx.SKY, "sky_above", unsure)
    plane = evidence.plane
    if "ground" in params.rules and plane is not None:
        rng = np.linalg.norm(rays_cam, axis=1) * depth.reshape(-1)
        tol = params.ground_tolerance_m + params.ground_tolerance_rel * rng
        on = has_depth & (np.abs(plane.height(points)) <= tol) & (rng <= params.ground_max_range_m)
        lateral = geometry.transform_points(geometry.invert_transform(camera.world_from_ego), points)[:, 1]
        seeds = on & (np.abs(lateral) <= params.ground_seed_half_width_m)
        road = connected_to(on.reshape(h, w), seeds.reshape(h, w))
        not_flat = ~np.isin(label, list(FLAT_IDS))
        apply(road, tx.ROAD, "ground_plane", weak & not_flat)
    if "boxes" in params.rules:
        boxes = camera_boxes(frame, camera)
        if len(boxes):
            regions = box_regions(camera, boxes, params.box_margin_m)
            cls = box_labels(points, has_depth, boxes, params.box_margin_m, params.box_clearance_m, regions)
            cls = cls.reshape(h, w)
            for c in np.unique(cls[cls != tx.IGNORE_ID]):
                apply(cls == c, int(c), "box", np.ones((h, w), bool))
    return CameraSemantics(label, confidence, source)


def _new_labels(
    h: int, w: int, segmentation: SegmenterOutput | None
) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.uint8]]:
    """(label, confidence, source) (H, W) of an image before any rule: the segmenter's, or none."""
    if segmentation is None:
        return (
            np.full((h, w), tx.IGNORE_ID, np.uint8),
            np.zeros((h, w), np.float32),
            np.zeros((h, w), np.uint8),
        )
    assert segmentation.label.shape == (h, w), (segmentation.label.shape, h, w)
    return (
        segmentation.label.astype(np.uint8, copy=True),
        segmentation.confidence.astype(np.float32, copy=True),
        np.full((h, w), SOURCE["segmenter"], np.uint8),
    )


#: FLAT_LUT[c]: whether class c is flat (road, sidewalk, terrain).
_FLAT_LUT = np.isin(np.arange(256), list(FLAT_IDS))


def _linear(rc: RayComponents, coeff: NDArray[np.float64]) -> NDArray[np.float32]:
    """(H, W) float32 ``coeff . (x, y, 1)`` of every pixel's ray."""
    out = rc.x * np.float32(coeff[0])
    out += rc.y * np.float32(coeff[1])
    out += np.float32(coeff[2])
    return out


def label_camera(
    frame: Frame,
    camera: CameraImage,
    params: PseudoSemanticsParams,
    segmentation: SegmenterOutput | None = None,
    evidence: LidarEvidence | None = None,
) -> CameraSemantics:
    """Pseudo labels of one image (see the module docstring).

    ``segmentation``: the segmenter's output, or None for geometric labels alone; ``evidence``:
    the frame's :class:`LidarEvidence`, computed if None.

    The labels of :func:`label_camera_reference`, computed from what the scene needs: the
    per-calibration ray tables (:func:`~phigenesis.data.camera_tables.ray_components_of`); each
    rule's world quantity (height above the ground plane, lateral offset, elevation) as a
    per-frame linear function of the ray, in float32 (H, W) maps; the LiDAR-bin lookup of the sky
    rule only on pixels that can be sky, in float64; each box tested only on the pixels of its
    projected rectangle (:func:`box_rectangles`) within its depth range, in float64
    (:func:`box_labels_in_rectangles`, a C kernel where one can be built). Pixels may differ from the
    reference only where a float32 quantity lies within float32 rounding (~1e-6 relative) of a
    rule's threshold (tests/test_semantics_stage.py measures the share).
    """
    cal = camera.calibration
    h, w = cal.height, cal.width
    label, confidence, source = _new_labels(h, w, segmentation)
    if not params.rules:
        return CameraSemantics(label, confidence, source)
    evidence = LidarEvidence.of(frame, params) if evidence is None else evidence
    rc = ray_components_of(cal)
    depth = np.asarray(pixel_depth(frame, camera), np.float32)
    has_depth = depth > 0
    world_from_camera = camera.world_from_camera
    rot, t = world_from_camera[:3, :3], world_from_camera[:3, 3]
    segmenter_source = np.uint8(SOURCE["segmenter"])
    with_segmenter = segmentation is not None

    def apply(mask: NDArray[np.bool_], cls: int, rule: str, replace: NDArray[np.bool_] | None) -> None:
        """Labels ``mask`` pixels ``cls`` from ``rule`` where ``replace`` allows it (None:
        everywhere); where the segmenter already says ``cls`` it keeps its source and takes the
        larger confidence."""
        conf = np.float32(RULE_CONFIDENCE[rule])
        take = mask if replace is None else mask & replace
        if with_segmenter:
            agree = mask & (label == cls) & (source == segmenter_source)
            np.maximum(confidence, conf, out=confidence, where=agree)
            take &= ~agree
        label[take] = cls
        confidence[take] = conf
        source[take] = SOURCE["sky" if rule.startswith("sky") else rule]

    def apply_at(index: NDArray[np.intp], cls: NDArray[np.uint8], rule: str) -> None:
        """:func:`apply` on the flat pixel indices ``index``, each with its class, everywhere."""
        conf = np.float32(RULE_CONFIDENCE[rule])
        lab, con, src = label.reshape(-1), confidence.reshape(-1), source.reshape(-1)
        if with_segmenter:
            agree = (lab[index] == cls) & (src[index] == segmenter_source)
            con[index[agree]] = np.maximum(con[index[agree]], conf)
            index, cls = index[~agree], cls[~agree]
        lab[index], con[index], src[index] = cls, conf, SOURCE[rule]

    weak = unsure = None  # without a segmenter every pixel is unlabelled: the rules replace all
    if with_segmenter:
        unlabelled = source == SOURCE["none"]
        weak = unlabelled | (confidence < params.keep_segmenter_above)
        unsure = unlabelled | (confidence < params.sky_keep_segmenter_above)
    if "sky" in params.rules and evidence.returns is not None:
        sky_in, sky_above = _sky_masks(evidence.returns, rc, camera, depth, has_depth, params)
        apply(sky_in, tx.SKY, "sky", unsure)
        apply(sky_above, tx.SKY, "sky_above", unsure)
        del sky_in, sky_above
    plane = evidence.plane
    if "ground" in params.rules and plane is not None:
        # height above the plane: n . (t + d R r) + offset = h0 + d (R^T n) . r
        height = _linear(rc, rot.T @ plane.normal)
        height *= depth
        height += np.float32(plane.normal @ t + plane.offset)
        rng = rc.norm * depth
        tol = rng * np.float32(params.ground_tolerance_rel)
        tol += np.float32(params.ground_tolerance_m)
        on = has_depth & (np.abs(height, out=height) <= tol) & (rng <= np.float32(params.ground_max_range_m))
        del height, tol, rng
        # lateral offset (ego y at the image's pose): e . (t + d R r) + e_3, e the ego's y row
        ego_from_world = geometry.invert_transform(camera.world_from_ego)
        lateral = _linear(rc, rot.T @ ego_from_world[1, :3])
        lateral *= depth
        lateral += np.float32(ego_from_world[1, :3] @ t + ego_from_world[1, 3])
        seeds = on & (np.abs(lateral, out=lateral) <= np.float32(params.ground_seed_half_width_m))
        del lateral
        road = connected_to(on, seeds)
        replace = ~_FLAT_LUT[label]
        if weak is not None:
            replace &= weak
        apply(road, tx.ROAD, "ground_plane", replace)
    if "boxes" in params.rules:
        boxes = camera_boxes(frame, camera)
        if len(boxes):
            index, cls = box_labels_in_rectangles(
                camera, depth, boxes, params.box_margin_m, params.box_clearance_m
            )
            apply_at(index, cls, "box")
    return CameraSemantics(label, confidence, source)


def _sky_masks(
    returns: tuple[NDArray[np.bool_], float],
    rc: RayComponents,
    camera: CameraImage,
    depth: NDArray[np.float32],
    has_depth: NDArray[np.bool_],
    params: PseudoSemanticsParams,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """:func:`sky_mask` from the ray tables: the elevation tests on ``sin(elevation)`` (the world
    ray's z over its length, linear in the ray: float32), the LiDAR-bin lookup (float64 angles,
    as :func:`sky_mask`) only on the pixels in the field without depth."""
    h, w = depth.shape
    grid, top_deg = returns
    rot = camera.world_from_camera[:3, :3]
    sin_elevation = _linear(rc, rot[2])
    sin_elevation /= rc.norm
    sin_min = np.float32(np.sin(np.radians(params.sky_min_elevation_deg)))
    sin_top = np.float32(np.sin(np.radians(min(max(top_deg, -90.0), 90.0))))
    in_field = (sin_elevation >= sin_min) & (sin_elevation <= sin_top)
    above = sin_elevation > sin_top
    del sin_elevation
    no_depth = ~has_depth
    sky_in = in_field & no_depth
    candidates = np.flatnonzero(sky_in)
    if candidates.size:
        rays = pixel_rays_cam(camera.calibration)[candidates] @ rot.T  # [P', 3] world axes
        elevation = np.degrees(np.arctan2(rays[:, 2], np.hypot(rays[:, 0], rays[:, 1])))
        azimuth = np.degrees(np.arctan2(rays[:, 1], rays[:, 0]))
        rows, cols = grid.shape
        hit = grid[
            _bin(elevation + 90, params.sky_bin_deg, rows), _bin(azimuth + 180, params.sky_bin_deg, cols)
        ]
        sky_in.reshape(-1)[candidates[hit]] = False
    # Above the field: a column whose highest in-field pixel is open sky is sky above it too.
    has_field = in_field.any(axis=0)
    first_in = np.argmax(in_field, axis=0)  # topmost in-field row per column (rows go down)
    open_top = has_field & sky_in[first_in, np.arange(w)]
    top_rows = int(first_in[open_top].max()) if open_top.any() else 0
    sky_above = np.zeros((h, w), bool)
    sub = slice(0, top_rows)
    sky_above[sub] = (
        above[sub] & no_depth[sub] & open_top[None, :] & (np.arange(top_rows)[:, None] < first_in[None, :])
    )
    return sky_in, sky_above


def box_labels_in_rectangles(
    camera: CameraImage,
    depth: NDArray[np.float32],
    boxes: Boxes,
    margin_m: float,
    clearance_m: float,
    native: bool = True,
) -> tuple[NDArray[np.intp], NDArray[np.uint8]]:
    """The pixels whose point (the pixel's ray at ``depth``, (H, W) z-depth in metres, 0 unknown)
    lies in a thing box, and the box's class: :func:`box_labels` on the image's points, but each
    box tested only on the pixels of its rectangle (:func:`box_rectangles`) whose depth lies in
    the z range of its corners, with the same float64 arithmetic. Returns (flat row-major pixel
    indices, their classes); where boxes overlap, the one whose centre is nearest the point wins
    (the first of equally near ones).

    ``native``: use the C kernel (``csrc/box_labels.c``, one pass over each rectangle) where it
    can be built; the numpy path (``native=False``, or without a compiler) is its reference."""
    w = depth.shape[1]
    kernel = load_box_labels() if native else None
    flat_depth = depth.reshape(-1)
    rays = pixel_rays_cam(camera.calibration)
    rot, t = camera.world_from_camera[:3, :3], camera.world_from_camera[:3, 3]
    rotations = geometry.quaternion_to_matrix(boxes.orientation_world).reshape(-1, 3, 3)
    labels: NDArray[np.uint8] | None = None
    best: NDArray[np.float64] | None = None
    for k, found in enumerate(_box_footprints(camera, boxes, margin_m)):
        cls = int(boxes.class_id[k])
        if found is None or cls not in BOX_CLASSES:
            continue
        (v0, v1, u0, u1), z_lo, z_hi = found
        pad = 1e-3 * max(1.0, abs(z_hi))  # rounding of the corners' z
        half = 0.5 * boxes.size_lwh[k]
        if kernel is not None:
            if labels is None or best is None:
                labels = np.full(depth.size, tx.IGNORE_ID, np.uint8)
                best = np.full(depth.size, np.inf)
            limits = np.array(
                [half[0] + margin_m, half[1] + margin_m, half[2] + margin_m, -half[2] + clearance_m]
            )
            kernel(
                np.ascontiguousarray(depth, np.float32),
                rays,
                (v0, v1, u0, u1),
                (z_lo - pad, z_hi + pad),
                camera.world_from_camera,
                boxes.center_world[k],
                rotations[k],
                limits,
                cls,
                labels,
                best,
            )
            continue
        window = depth[v0:v1, u0:u1]
        rows, cols = np.nonzero((window > 0) & (window >= z_lo - pad) & (window <= z_hi + pad))
        if rows.size == 0:
            continue
        index = (rows + v0) * w + (cols + u0)
        del rows, cols
        points = t + (rays[index] @ rot.T) * flat_depth[index, None].astype(np.float64)  # [P', 3] world
        offset = points - boxes.center_world[k]
        local = offset @ rotations[k]  # box frame: R^T p
        inside = (
            (np.abs(local[:, 0]) <= half[0] + margin_m)
            & (np.abs(local[:, 1]) <= half[1] + margin_m)
            & (local[:, 2] <= half[2] + margin_m)
            & (local[:, 2] >= -half[2] + clearance_m)
        )
        if not inside.any():
            continue
        index, offset = index[inside], offset[inside]
        dist2 = np.einsum("ij,ij->i", offset, offset)
        if labels is None or best is None:
            labels = np.full(depth.size, tx.IGNORE_ID, np.uint8)
            best = np.full(depth.size, np.inf)
        closer = dist2 < best[index]  # the nearest centre wins; the first of equally near ones
        labels[index[closer]] = cls
        best[index[closer]] = dist2[closer]
    if labels is None:
        return np.zeros(0, np.intp), np.zeros(0, np.uint8)
    index = np.flatnonzero(labels != tx.IGNORE_ID)
    return index, labels[index]


def label_frame(
    frame: Frame,
    params: PseudoSemanticsParams,
    segmenter: Segmenter | None = None,
    cache: RayCache | None = None,
) -> Frame:
    """The frame with ``pseudo`` labels on every camera that has an image. ``cache`` is not used
    (the pixel rays are per-calibration tables now: :mod:`phigenesis.data.camera_tables`); it is
    kept for callers that pass one."""
    cams = [c for c in frame.cameras if c.image_bytes is not None]
    if not cams:
        return frame
    segmented: dict[str, SegmenterOutput] = {}
    if segmenter is not None:
        outputs = segmenter.segment([c.decode_image() for c in cams])
        segmented = {c.name: p for c, p in zip(cams, outputs, strict=True)}
    evidence = LidarEvidence.of(frame, params)
    cameras = [
        c
        if c.image_bytes is None
        else dataclasses.replace(
            c,
            pseudo=label_camera(frame, c, params, segmented.get(c.name), evidence),
        )
        for c in frame.cameras
    ]
    return dataclasses.replace(frame, cameras=cameras)


#: A camera whose pseudo labels cover less than this share of its pixels over a scene is warned
#: about (:class:`LabelCoverage`).
MIN_LABEL_COVERAGE = 0.01


class LabelCoverage:
    """Per-camera share of pixels given a pseudo label (source other than none) over a scene.

    Each frame counts once however often a lazy frame is loaded (the last load wins). Once every
    frame of the scene has been seen, :meth:`add` logs a WARNING per camera under ``min_share``
    (once per scene; the shares themselves are in the pipeline's line on what the cache holds,
    :class:`~phigenesis.data.coverage.SceneCoverage`): nearly empty labels usually mean no
    segmenter and neither boxes, ground nor open sky in view (a camera facing the ego body, a
    frame without LiDAR or boxes), so the semantic targets of that view are missing.
    """

    def __init__(self, scene_id: str, frames: int, segmenter: bool, min_share: float = MIN_LABEL_COVERAGE):
        self.scene_id = scene_id
        self.frames = frames
        self.segmenter = segmenter
        self.min_share = min_share
        self.reported = False
        self._counts: dict[int, dict[str, tuple[int, int]]] = {}

    def add(self, frame: Frame) -> None:
        """Counts the frame's labelled cameras' (pixels, labelled pixels); reports when the
        scene is complete."""
        self._counts[frame.frame_index] = {
            c.name: (int(c.pseudo.source.size), int(np.count_nonzero(c.pseudo.source)))
            for c in frame.cameras
            if c.pseudo is not None
        }
        if len(self._counts) >= self.frames:
            self.report()

    def shares(self) -> dict[str, float]:
        """Share of pixels labelled, by camera (in the order first seen), over the frames seen."""
        totals: dict[str, list[int]] = {}
        for counts in self._counts.values():
            for name, (pixels, labelled) in counts.items():
                t = totals.setdefault(name, [0, 0])
                t[0] += pixels
                t[1] += labelled
        return {name: labelled / max(pixels, 1) for name, (pixels, labelled) in totals.items()}

    def report(self) -> None:
        """Logs a WARNING per camera below ``min_share``, once."""
        if self.reported:
            return
        self.reported = True
        shares = self.shares()
        if not shares:
            return
        for name, share in shares.items():
            if share < self.min_share:
                log.warning(
                    "scene %s camera %s: pseudo labels cover only %.2f %% of its pixels over the scene "
                    "(under %.0f %%): %s, so its semantic targets are (nearly) empty. Does the view show "
                    "no boxed things, no ground and no open sky (the ego body, a wall), or does the "
                    "scene lack LiDAR or boxes?",
                    self.scene_id,
                    name,
                    100 * share,
                    100 * self.min_share,
                    "a segmenter labelled it"
                    if self.segmenter
                    else "no segmenter checkpoint, geometric rules only",
                )


@register_stage("pseudo_semantics", params=PseudoSemanticsParams)
def pseudo_semantics(scene: Scene, p: PseudoSemanticsParams) -> Scene:
    """Stage: pseudo-semantic labels for every image (see the module docstring). Runs after the
    depth stages when they are in the pipeline (it uses their depth); frames are labelled lazily
    when the scene's frames are a :class:`LazyFrames`. Once every frame is labelled, a camera whose
    labels cover under :data:`MIN_LABEL_COVERAGE` of its pixels is warned about (:class:`LabelCoverage`)."""
    segmenter = None
    if p.checkpoint is not None:
        segmenter = Segmenter.load(p.checkpoint, p.model, p.input_height, p.device)
    else:
        log.info(
            "pseudo_semantics: scene %s: no segmenter checkpoint, geometric labels only (rules: %s)",
            scene.scene_id,
            ", ".join(p.rules) or "none",
        )
    coverage = LabelCoverage(scene.scene_id, len(scene.frames), segmenter is not None)

    def run(frame: Frame) -> Frame:
        labelled = label_frame(frame, p, segmenter)
        coverage.add(labelled)
        return labelled

    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(run)
    else:
        scene.frames = [run(f) for f in scene.frames]
        coverage.report()
    return scene
