"""Occlusion-aware projection of LiDAR into every camera: sparse depth and its confidence.

Entry point: :func:`project_camera` (one image); the stage ``project_depth`` runs it for every
camera of every frame, lazily, and stores a :class:`CameraDepth` on each image.

What is projected into an image, all at that image's own capture time and pose:

- with an aggregated map (stage ``aggregate_lidar`` ran first): the static map's points near the
  camera, each rigid moving object's model at its box pose moved to the image's time (constant
  velocity from the frame's box), and each non-rigid moving object's points from the frame's own
  sweep, moved the same way;
- without one: the frame's own sweep (``single_sweep``).

Occlusion: a min-depth z-buffer keeps the nearest point per pixel, but sparse foreground points
leave gaps through which background points show ("see-through"). The visibility test removes
them; ``visibility`` picks one of:

- ``splat`` (default): each point occludes a disc of radius ``splat_scale * f * spacing / z`` pixels
  (its footprint: a map voxel, or the LiDAR's angular step for sweep points); a point survives if
  it is no deeper than ``(1 + tau) * z_occluder + slack_m`` for every disc covering its pixel.
- ``local_min``: a point survives if it is within ``(1 + tau)`` of the minimum depth in a
  ``window x window`` neighbourhood (the classic test; it also removes slanted ground far away).
- ``none``: the z-buffer only.

The ego car's body (boxes in the ego frame, :func:`aggregate.ego_boxes_of`) is an occluder too:
pixels whose ray meets it get no depth (confidence 0), and nothing behind it is projected.

Confidence of a sparse pixel: the origin's weight (static map or own sweep 1.0, non-rigid own
points 0.9, rigid object models 0.8: their pose is extrapolated to the image time) times 0.75 if
a single point supports the pixel, 1.0 if two or more agree within ``tau``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import DEPTH_ORIGINS, CameraDepth, CameraImage, Frame, LazyFrames, Scene
from phigenesis.data.stages import params_from_dict, register_stage
from phigenesis.data.stages.aggregate import (
    LidarMap,
    box_points_at_times,
    ego_boxes_of,
    lidar_angular_step,
    sweep_dt_s,
)

log = logging.getLogger("phigenesis.prep")

VISIBILITY_TESTS = ("splat", "local_min", "none")
ORIGIN_WEIGHT = {"static_map": 1.0, "single_sweep": 1.0, "non_rigid_object": 0.9, "rigid_object": 0.8}
ORIGIN_CODE = {name: i for i, name in enumerate(DEPTH_ORIGINS)}
#: ORIGIN_WEIGHT indexed by origin code (0 for "none").
ORIGIN_WEIGHTS = np.array([ORIGIN_WEIGHT.get(name, 0.0) for name in DEPTH_ORIGINS], np.float32)
#: Classes whose boxes are solid enough to hide what lies behind them.
VEHICLE_IDS = frozenset({tx.CAR, tx.TRUCK, tx.BUS, tx.TRAIN})
#: People are far from box-shaped: only their core (this share of length and width) occludes.
PERSON_IDS = frozenset({tx.PERSON, tx.RIDER})


@dataclass(frozen=True)
class ProjectParams:
    """Parameters of the projection (lengths in metres).

    Attributes:
        visibility: "splat", "local_min" or "none" (see the module docstring).
        tau: relative depth tolerance of the visibility test and of agreeing points.
        slack_m: absolute depth tolerance of the splat test.
        window: neighbourhood size of ``local_min`` (pixels, odd).
        splat_scale: a point's disc has radius ``splat_scale * f * spacing / z`` pixels: 0.5
            would make touching discs on a square grid, which leaves gaps at the corners;
            0.75 covers a grid of voxel centroids.
        max_splat_px: cap on a splat's radius in pixels.
        max_range_m: points farther than this from the camera are not projected.
        min_depth_m: points nearer than this (z) are not projected.
        sweep_spacing_rad: angular footprint of a single sweep's points; None: the LiDAR's
            measured angular step (:func:`aggregate.lidar_angular_step`).
        object_spacing_m: footprint of object model points.
        elevation_margin_deg: map points up to this much above the LiDAR's highest return
            elevation (seen from the current sensor position) count as inside its field.
        top_band_deg, top_bin_deg: the band below that limit whose surfaces decide, per azimuth
            bin of this width, which map points above the field are kept (:func:`seen_past_lidar_top`).
        vehicle_occluders: moving vehicles' boxes (shrunk by ``occluder_shrink``, their bottom
            raised by ``occluder_clearance_m``) and moving people's box cores (``person_core``
            of their length and width) hide whatever lies beyond their far side.
        supersample: the visibility test and z-buffer run on a grid this many times finer than
            the image (odd; 1 = the image's own pixels); None: 3 for images up to 640 pixels
            wide, where a pixel holds several map points, else 1.
        max_offset_px: a pixel takes the depth of a visible point at most this far from its
            centre (in pixels, on the fine grid; 0.71 reaches the corners).
        use_map: project the aggregated map when the scene has one (False: own sweep only).
    """

    visibility: str = "splat"
    tau: float = 0.05
    slack_m: float = 0.1
    window: int = 7
    splat_scale: float = 0.75
    max_splat_px: int = 12
    max_range_m: float = 120.0
    min_depth_m: float = 0.5
    sweep_spacing_rad: float | None = None
    object_spacing_m: float = 0.05
    elevation_margin_deg: float = 0.5
    top_band_deg: float = 1.5
    top_bin_deg: float = 0.5
    vehicle_occluders: bool = True
    occluder_shrink: float = 0.9
    occluder_clearance_m: float = 0.35
    person_core: float = 0.5
    supersample: int | None = None
    max_offset_px: float = 1.0
    use_map: bool = True

    def __post_init__(self) -> None:
        if self.visibility not in VISIBILITY_TESTS:
            raise ValueError(
                f"project_depth: visibility must be one of {VISIBILITY_TESTS}, got {self.visibility!r}"
            )
        if self.supersample is not None and (self.supersample < 1 or self.supersample % 2 == 0):
            raise ValueError(
                f"project_depth: supersample must be a positive odd number, got {self.supersample}"
            )
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"project_depth: window must be a positive odd number, got {self.window}")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ProjectParams:
        return params_from_dict(cls, values, "project_depth")


@dataclass
class CameraPoints:
    """Points to project into one image, world frame, with what each represents.

    Attributes:
        points_world: (N, 3) float64.
        origin: (N,) uint8 index into :data:`DEPTH_ORIGINS`.
        spacing_m: (N,) float32 footprint size in metres at the point (NaN: use the sweep's
            angular step).
    """

    points_world: NDArray[np.float64]
    origin: NDArray[np.uint8]
    spacing_m: NDArray[np.float32]

    @classmethod
    def concatenate(cls, parts: list[CameraPoints]) -> CameraPoints:
        if not parts:
            return cls(np.zeros((0, 3)), np.zeros(0, np.uint8), np.zeros(0, np.float32))
        return cls(
            np.concatenate([p.points_world for p in parts]),
            np.concatenate([p.origin for p in parts]),
            np.concatenate([p.spacing_m for p in parts]),
        )


def _points(points_world: NDArray, origin: str, spacing_m: float) -> CameraPoints:
    n = len(points_world)
    return CameraPoints(
        np.asarray(points_world, np.float64),
        np.full(n, ORIGIN_CODE[origin], np.uint8),
        np.full(n, spacing_m, np.float32),
    )


def sweep_points(frame: Frame) -> CameraPoints:
    """The frame's own sweep in the world, as measured (``single_sweep``)."""
    if frame.lidar is None:
        return CameraPoints.concatenate([])
    return _points(frame.lidar.points_world(), "single_sweep", np.nan)


def seen_past_lidar_top(
    points_world: NDArray[np.floating],
    sensor_world: NDArray[np.float64],
    world_from_ego: NDArray[np.float64],
    max_elevation_rad: float,
    band_rad: float,
    bin_rad: float,
) -> NDArray[np.bool_]:
    """(N,) False for map points that something the LiDAR never measured may hide.

    Seen from the current sensor position (ego axes), a point within the LiDAR's vertical field
    (elevation <= ``max_elevation_rad``) is fine: whatever could hide it lies in that field too
    and is in the map. A point above it (the top of a facade, a tree crown) is kept only if, in its
    azimuth, the surfaces the top beams reach (elevation within ``band_rad`` below the limit) are
    farther away than it, or absent: a nearer wall seen by the top beams probably goes on upwards
    and hides it.
    """
    d = (np.asarray(points_world, np.float64) - sensor_world) @ world_from_ego[:3, :3]
    r = np.hypot(d[:, 0], d[:, 1])
    elevation = np.arctan2(d[:, 2], r)
    inside = elevation <= max_elevation_rad
    if np.all(inside):
        return inside
    bins = int(np.ceil(2 * np.pi / bin_rad))
    az_bin = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / bin_rad).astype(np.int64) % bins
    band = inside & (elevation >= max_elevation_rad - band_rad)
    profile = np.full(bins, np.inf)
    np.minimum.at(profile, az_bin[band], r[band])
    profile = np.minimum(profile, np.minimum(np.roll(profile, 1), np.roll(profile, -1)))
    return inside | (r < profile[az_bin])


def scene_points(
    frame: Frame, camera: CameraImage, lidar_map: LidarMap, params: ProjectParams
) -> CameraPoints:
    """Static map, rigid object models and non-rigid own points, placed at the image's time."""
    position = camera.world_from_camera[:3, 3]
    static = lidar_map.points_near(position, params.max_range_m)
    if frame.lidar is not None and len(frame.lidar):
        sensor = geometry.transform_points(
            frame.world_from_ego, np.median(frame.lidar.origins_ego, axis=0)[None]
        )[0]
    else:
        sensor = position
    limit = lidar_map.max_elevation_rad + np.radians(params.elevation_margin_deg)
    band, bin_width = np.radians(params.top_band_deg), np.radians(params.top_bin_deg)
    static = static[seen_past_lidar_top(static, sensor, frame.world_from_ego, limit, band, bin_width)]
    parts = [_points(static, "static_map", lidar_map.voxel_m)]
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    for k, track in enumerate(boxes.track_id):
        model = lidar_map.objects.get(track)
        if model is None or len(model.points_box) == 0:
            continue
        rotation = geometry.quaternion_to_matrix(boxes.orientation_world[k])
        centre = boxes.center_world[k] + boxes.velocity_world[k] * dt_s
        parts.append(_points(model.points_box @ rotation.T + centre, "rigid_object", params.object_spacing_m))
    if lidar_map.non_rigid_tracks and frame.lidar is not None and len(frame.lidar):
        people = [k for k, t in enumerate(boxes.track_id) if t in lidar_map.non_rigid_tracks]
        if people:
            sub = boxes.select(np.array(people, np.int64))
            sweep = frame.lidar
            pts = sweep.points_world()
            point_dt = sweep_dt_s(sweep, frame.timestamp_micros)
            index, _ = box_points_at_times(pts, point_dt, sub, 1.0, 0.0, lidar_map.ground_clearance_m)
            inside = index >= 0
            # Move each point with its object from its measurement time to the image's time.
            shift = sub.velocity_world[index[inside]] * (dt_s - point_dt[inside])[:, None]
            parts.append(_points(pts[inside] + shift, "non_rigid_object", np.nan))
    return CameraPoints.concatenate(parts)


def pixel_rays(camera: CameraImage) -> NDArray[np.float64]:
    """(H * W, 3) camera-frame rays through the pixel centres with z = 1 (distortion undone)."""
    cal = camera.calibration
    return geometry.unproject_pixels(
        geometry.pixel_grid(cal.width, cal.height), cal.intrinsics, cal.distortion
    )


def ray_box_depths(
    rays_cam: NDArray[np.float64], camera_from_box: NDArray[np.float64], half_size: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where rays from the camera centre (z = 1, so the parameter is the z-depth) enter and leave
    a box (slab test in the box frame). Returns (P,) entry and exit depths, inf where a ray
    misses or the box is behind the camera; an entry of 0 means the camera is inside."""
    box_from_camera = geometry.invert_transform(camera_from_box)
    d = rays_cam @ box_from_camera[:3, :3].T
    o = box_from_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half_size - o) / d, (half_size - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = np.isfinite(t_near) & np.isfinite(t_far) & (t_far >= np.maximum(t_near, 0.0))
    return np.where(hit, np.maximum(t_near, 0.0), np.inf), np.where(hit, t_far, np.inf)


def ego_body_depth(
    camera: CameraImage, ego_boxes: list[dict], rays: NDArray[np.float64] | None = None
) -> NDArray[np.float32]:
    """(H, W) z-depth at which each pixel's ray enters the ego body boxes (ego frame), inf where
    it misses."""
    cal = camera.calibration
    rays = pixel_rays(camera) if rays is None else rays
    camera_from_ego = geometry.invert_transform(cal.ego_from_camera)
    entry = np.full(len(rays), np.inf)
    for b in ego_boxes:
        camera_from_box = camera_from_ego @ geometry.make_transform(np.eye(3), b["center_ego"])
        t_in, _ = ray_box_depths(rays, camera_from_box, 0.5 * np.asarray(b["size_lwh"], np.float64))
        np.minimum(entry, t_in, out=entry)
    return entry.reshape(cal.height, cal.width).astype(np.float32)


def vehicle_far_depth(
    frame: Frame,
    camera: CameraImage,
    moving_tracks: frozenset[str],
    params: ProjectParams,
    rays: NDArray[np.float64],
) -> NDArray[np.float32]:
    """(H, W) depth of the far side of the nearest moving vehicle box (shrunk, bottom raised) on
    each pixel's ray at the image's time, inf where none: nothing beyond it can be visible."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    far = np.full(h * w, np.inf)
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    for k, track in enumerate(boxes.track_id):
        cls = int(boxes.class_id[k])
        if track not in moving_tracks or cls not in VEHICLE_IDS | PERSON_IDS:
            continue
        clearance = params.occluder_clearance_m if cls in VEHICLE_IDS else 0.0
        shrink = params.occluder_shrink if cls in VEHICLE_IDS else params.person_core
        size = boxes.size_lwh[k] * np.array([shrink, shrink, 1.0])
        size[2] -= clearance
        if np.any(size <= 0):
            continue
        rotation = geometry.quaternion_to_matrix(boxes.orientation_world[k])
        centre = boxes.center_world[k] + boxes.velocity_world[k] * dt_s + rotation[:, 2] * 0.5 * clearance
        camera_from_box = camera_from_world @ geometry.make_transform(rotation, centre)
        corners = geometry.transform_points(camera_from_box, 0.5 * size * geometry.BOX_CORNER_SIGNS)
        if np.all(corners[:, 2] <= 0):
            continue
        region = np.arange(h * w)
        if np.all(corners[:, 2] > params.min_depth_m):
            uv, ok = geometry.project_points(corners, cal.intrinsics, cal.distortion)
            if ok.all():
                u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 1
                u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 1
                u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
                if u0 > u1 or v0 > v1:
                    continue
                vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
                region = (vv * w + uu).ravel()
        _, t_out = ray_box_depths(rays[region], camera_from_box, 0.5 * size)
        far[region] = np.minimum(far[region], t_out)
    return far.reshape(h, w).astype(np.float32)


def _disc(radius: int) -> NDArray[np.uint8]:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _zbuffer(pixel: NDArray[np.int64], z: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    buf = np.full(size, np.inf, np.float32)
    np.minimum.at(buf, pixel, z)
    return buf


def occluder_depth(
    pixel: NDArray[np.int64], z: NDArray[np.float32], radius_px: NDArray[np.int64], shape: tuple[int, int]
) -> NDArray[np.float32]:
    """(H, W) nearest depth of any point whose disc of ``radius_px`` covers each pixel (inf: none)."""
    h, w = shape
    occ = np.full((h, w), np.inf, np.float32)
    for r in np.unique(radius_px):
        sel = radius_px == r
        buf = _zbuffer(pixel[sel], z[sel], h * w).reshape(h, w)
        if r > 0:
            buf = cv2.erode(buf, _disc(int(r)), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.minimum(occ, buf, out=occ)
    return occ


def _pixel_index(uv: NDArray[np.float64], scale: int, width: int, height: int) -> NDArray[np.int64]:
    """Flat index of the pixel holding each (u, v) on a grid ``scale`` times finer than the image."""
    col = np.clip(np.rint((uv[:, 0] + 0.5) * scale - 0.5), 0, width - 1).astype(np.int64)
    row = np.clip(np.rint((uv[:, 1] + 0.5) * scale - 0.5), 0, height - 1).astype(np.int64)
    return row * width + col


def _centre_first(fine_depth: NDArray[np.float32], max_offset_px: float = 1.0) -> NDArray[np.int64]:
    """For (H, s, W, s) sub-pixel depths (inf = empty), the (H, W) flat fine index of the filled
    sub-pixel nearest each pixel's centre (no farther than ``max_offset_px`` pixels from it),
    -1 where there is none."""
    h, ss, w, _ = fine_depth.shape
    centre = (ss - 1) / 2
    offsets = [
        (i, j)
        for i in range(ss)
        for j in range(ss)
        if np.hypot(i - centre, j - centre) <= max_offset_px * ss + 1e-9
    ]
    offsets.sort(key=lambda o: (o[0] - centre) ** 2 + (o[1] - centre) ** 2)
    rows = np.arange(h)[:, None] * ss
    cols = np.arange(w)[None, :] * ss
    chosen = np.full((h, w), -1, np.int64)
    for i, j in offsets:
        take = (chosen < 0) & np.isfinite(fine_depth[:, i, :, j])
        chosen[take] = ((rows + i) * (w * ss) + cols + j)[take]
    return chosen


def project_camera(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
    sweep_step_rad: float = float(np.radians(0.5)),
) -> tuple[CameraDepth, dict[str, int]]:
    """Projects world points into one image with occlusion handling.

    Args:
        camera: the image (its calibration, capture time pose).
        points: world points with their origins and footprints.
        ego_depth: (H, W) depth where each pixel's ray enters the ego body (inf: misses); pixels
            on the body get no depth, points behind it are dropped.
        occluder_far: (H, W) depth beyond which nothing is visible (moving vehicles' far sides).
        sweep_step_rad: angular footprint of points measured by a single sweep (NaN spacing).

    Returns the image's :class:`CameraDepth` (sparse only) and counts: ``projected`` (points in
    the image), ``removed_by_visibility``, ``behind_ego_body`` and ``behind_vehicles``.
    """
    cal = camera.calibration
    h, w = cal.height, cal.width
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    p_cam = geometry.transform_points(camera_from_world, points.points_world)
    z_all = p_cam[:, 2]
    near = (z_all > params.min_depth_m) & (np.linalg.norm(p_cam, axis=1) <= params.max_range_m)
    p_cam = p_cam[near]
    uv, valid = geometry.project_points(p_cam, cal.intrinsics, cal.distortion, params.min_depth_m)
    valid &= geometry.in_image(uv, w, h)
    idx = np.flatnonzero(near)[valid]
    z = p_cam[valid, 2].astype(np.float32)
    uv = uv[valid]
    pixel = _pixel_index(uv, 1, w, h)
    counts = {
        "projected": len(z),
        "removed_by_visibility": 0,
        "behind_ego_body": 0,
        "behind_vehicles": 0,
    }
    for name, limit, slack in (
        ("behind_ego_body", ego_depth, 0.0),
        ("behind_vehicles", occluder_far, params.slack_m),
    ):
        if limit is not None:
            front = z < limit.reshape(-1)[pixel] + slack
            counts[name] = int(np.sum(~front))
            pixel, z, idx, uv = pixel[front], z[front], idx[front], uv[front]
    origin = points.origin[idx]
    # Visibility and the z-buffer work on a grid `s` times finer than the image, so a point
    # occludes (and fills) only the part of a pixel it covers; each pixel then takes the visible
    # point nearest its centre, not the nearest in depth, so edge pixels keep the surface at
    # their centre.
    ss = params.supersample or (3 if w <= 640 else 1)
    hf, wf = h * ss, w * ss
    fine = _pixel_index(uv, ss, wf, hf)
    keep = np.ones(len(z), bool)
    if params.visibility == "splat" and len(z):
        focal = float(cal.intrinsics[0, 0]) * ss
        spacing = points.spacing_m[idx]
        footprint = np.where(np.isnan(spacing), z * sweep_step_rad, spacing)
        radius = np.rint(params.splat_scale * focal * footprint / z)
        radius = np.clip(radius, 0, params.max_splat_px * ss).astype(np.int64)
        occ = occluder_depth(fine, z, radius, (hf, wf)).reshape(-1)
        keep = z <= occ[fine] * (1 + params.tau) + params.slack_m
    elif params.visibility == "local_min" and len(z):
        buf = _zbuffer(pixel, z, h * w).reshape(h, w)
        kernel = np.ones((params.window, params.window), np.uint8)
        local = cv2.erode(buf, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf).reshape(-1)
        keep = z <= local[pixel] * (1 + params.tau)
    counts["removed_by_visibility"] = int(np.sum(~keep))
    pixel, fine, z, origin = pixel[keep], fine[keep], z[keep], origin[keep]
    fine_depth = _zbuffer(fine, z, hf * wf)
    fine_origin = np.zeros(hf * wf, np.uint8)
    nearest = np.flatnonzero(z == fine_depth[fine])
    fine_origin[fine[nearest]] = origin[nearest]
    chosen = _centre_first(fine_depth.reshape(h, ss, w, ss), params.max_offset_px).reshape(-1)
    hit = chosen >= 0
    sparse = np.where(hit, fine_depth[np.maximum(chosen, 0)], np.inf)
    origin_map = np.where(hit, fine_origin[np.maximum(chosen, 0)], 0).astype(np.uint8)
    # Support: points in the pixel agreeing with its depth within tau.
    agree = np.abs(z - sparse[pixel]) <= sparse[pixel] * params.tau
    support = np.bincount(pixel[agree], minlength=h * w)
    confidence = np.where(hit, ORIGIN_WEIGHTS[origin_map] * np.where(support >= 2, 1.0, 0.75), 0.0).astype(
        np.float32
    )
    depth = np.where(hit, sparse, 0.0).astype(np.float32)
    if ego_depth is not None:
        body = np.isfinite(ego_depth.reshape(-1))
        depth[body], confidence[body], origin_map[body] = 0.0, 0.0, 0
    return (
        CameraDepth(depth.reshape(h, w), confidence.reshape(h, w), origin_map.reshape(h, w)),
        counts,
    )


class _Projector:
    """Runs :func:`project_camera` over a scene's frames, caching per-camera rays and ego body."""

    def __init__(self, scene: Scene, params: ProjectParams):
        self.scene_id = scene.scene_id
        self.params = params
        self.lidar_map: LidarMap | None = scene.products.get("lidar_map") if params.use_map else None
        self.ego_boxes = self.lidar_map.ego_boxes if self.lidar_map is not None else ego_boxes_of(scene)
        self._rays: dict[tuple, tuple[NDArray[np.float64], NDArray[np.float32]]] = {}
        self._warned = False

    def rays_and_ego_depth(self, camera: CameraImage) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
        cal = camera.calibration
        key = (
            cal.name,
            cal.width,
            cal.height,
            cal.intrinsics.tobytes(),
            cal.distortion.tobytes(),
            cal.ego_from_camera.tobytes(),
        )
        if key not in self._rays:
            rays = pixel_rays(camera)
            self._rays[key] = (rays, ego_body_depth(camera, self.ego_boxes, rays))
        return self._rays[key]

    def sweep_step(self, frame: Frame) -> float:
        if self.params.sweep_spacing_rad is not None:
            return self.params.sweep_spacing_rad
        if self.lidar_map is not None:
            return self.lidar_map.angular_step_rad
        return lidar_angular_step(frame.lidar) if frame.lidar is not None else float(np.radians(0.5))

    def __call__(self, frame: Frame) -> Frame:
        has_sweep = frame.lidar is not None and len(frame.lidar) > 0
        if self.lidar_map is None and not has_sweep and not self._warned:
            log.warning(
                "scene %s frame %d: no LiDAR; its depth maps are empty", self.scene_id, frame.frame_index
            )
            self._warned = True
        step = self.sweep_step(frame)
        for camera in frame.cameras:
            rays, ego_depth = self.rays_and_ego_depth(camera)
            occluders = None
            if self.lidar_map is not None:
                pts = scene_points(frame, camera, self.lidar_map, self.params)
                if self.params.vehicle_occluders:
                    occluders = vehicle_far_depth(
                        frame, camera, self.lidar_map.moving_tracks, self.params, rays
                    )
            else:
                pts = sweep_points(frame)
            camera.depth, _ = project_camera(camera, pts, self.params, ego_depth, occluders, step)
        return frame


@register_stage("project_depth")
def project_depth(scene: Scene, params: dict[str, Any]) -> Scene:
    """Stage: sparse depth and confidence for every image (see the module docstring); uses the
    aggregated map from ``aggregate_lidar`` when it ran, else each frame's own sweep."""
    projector = _Projector(scene, ProjectParams.from_dict(params))
    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(projector)
    else:
        scene.frames = [projector(f) for f in scene.frames]
    return scene
