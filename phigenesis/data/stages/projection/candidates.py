"""The points a camera may see: the static map's tiles in view, thinned to what the image can
resolve, the rigid object models and the non-rigid objects' own points, at the image's time.

The stage is :mod:`phigenesis.data.stages.project`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data.camera_tables import (
    per_calibration,
)
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.records import (
    CameraCalibration,
    CameraImage,
    Frame,
)
from phigenesis.data.stages.aggregate import (
    TILE_M,
    LidarMap,
    box_points_at_times,
    sweep_dt_s,
)
from phigenesis.data.stages.projection.params import ORIGIN_CODE, ProjectParams, supersample_of


@dataclass
class CameraPoints:
    """Points to project into one image, world frame, with what each represents.

    Attributes:
        points_world: (N, 3) float32 (float64 accepted).
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
            return cls(np.zeros((0, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32))
        return cls(
            np.concatenate([p.points_world for p in parts]),
            np.concatenate([p.origin for p in parts]),
            np.concatenate([p.spacing_m for p in parts]),
        )


def _points(points_world: NDArray, origin: str, spacing_m: float) -> CameraPoints:
    n = len(points_world)
    return CameraPoints(
        np.asarray(points_world, np.float32),
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
    points = np.asarray(points_world, np.float32)
    keep = np.ones(len(points), bool)
    if max_elevation_rad >= np.pi / 2 or len(points) == 0:
        return keep
    d = points - np.asarray(sensor_world, np.float32)
    dz = d @ np.asarray(world_from_ego[:3, 2], np.float32)
    # Only points above the sensor can lie above the field or in the band below its top (when
    # both are above the horizontal, as for any roof LiDAR); elevation tests are slopes
    # (dz <= tan(e) r): no arctan over millions of points.
    lowest = max_elevation_rad - band_rad
    candidates = np.flatnonzero(dz > 0) if lowest > 0 else np.arange(len(points))
    dc, zc = d[candidates], dz[candidates]
    r = np.sqrt(np.maximum(np.einsum("ij,ij->i", dc, dc) - zc * zc, 0.0))
    inside = zc <= np.tan(max_elevation_rad) * r
    if np.all(inside):
        return keep
    band = inside & (zc >= np.tan(lowest) * r)
    bins = int(np.ceil(2 * np.pi / bin_rad))
    # Azimuth in the ego's axes (only its x and y rows matter).
    axes = np.asarray(world_from_ego[:3, :2], np.float32)

    def azimuth_bin(index: NDArray[np.int64]) -> NDArray[np.int64]:
        xy = dc[index] @ axes
        return np.floor((np.arctan2(xy[:, 1], xy[:, 0]) + np.pi) / bin_rad).astype(np.int64) % bins

    profile = np.full(bins, np.inf)
    band_index = np.flatnonzero(band)
    np.minimum.at(profile, azimuth_bin(band_index), r[band_index])
    profile = np.minimum(profile, np.minimum(np.roll(profile, 1), np.roll(profile, -1)))
    outside = np.flatnonzero(~inside)
    keep[candidates[outside]] = r[outside] < profile[azimuth_bin(outside)]
    return keep


def normalized_bounds(camera: CameraImage, margin: float = 0.05) -> tuple[tuple[float, float], ...]:
    """((x_min, x_max), (y_min, y_max)) of x/z and y/z over rays through the image border (distortion
    undone), widened by ``margin`` of the span: points outside cannot land in the image. Computed
    once per calibration and margin (:func:`~phigenesis.data.camera_tables.per_calibration`)."""
    cal = camera.calibration
    return per_calibration(f"normalized_bounds {margin!r}", cal, lambda: _normalized_bounds(cal, margin))


def _normalized_bounds(cal: CameraCalibration, margin: float) -> tuple[tuple[float, float], ...]:
    w, h = cal.width, cal.height
    t = np.linspace(0.0, 1.0, 32)
    border = np.concatenate(
        [
            np.stack([t * w - 0.5, np.full_like(t, -0.5)], 1),
            np.stack([t * w - 0.5, np.full_like(t, h - 0.5)], 1),
            np.stack([np.full_like(t, -0.5), t * h - 0.5], 1),
            np.stack([np.full_like(t, w - 0.5), t * h - 0.5], 1),
        ]
    )
    rays = geometry.unproject_pixels(border, cal.intrinsics, cal.distortion)
    out = []
    for axis in (0, 1):
        lo, hi = float(rays[:, axis].min()), float(rays[:, axis].max())
        pad = margin * (hi - lo)
        out.append((lo - pad, hi + pad))
    return tuple(out)


def camera_wedge(camera: CameraImage) -> tuple[float, float] | None:
    """The azimuth range (world frame, about +z) that an image sees: (centre, half-width) in
    radians, from rays along the image border; None if it spans more than 160 degrees (a
    fisheye, or a camera looking straight up or down), where culling by azimuth is unsafe."""
    cal = camera.calibration
    rays = per_calibration("wedge_border_rays", cal, lambda: _border_rays(cal))
    d = rays @ camera.world_from_camera[:3, :3].T
    optical = camera.world_from_camera[:3, 2]
    if np.hypot(optical[0], optical[1]) < 1e-3:
        return None
    centre = float(np.arctan2(optical[1], optical[0]))
    half = float(np.max(np.abs(geometry.wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - centre))))
    return None if half > np.radians(80.0) else (centre, half)


def _border_rays(cal: CameraCalibration) -> NDArray[np.float64]:
    """(68, 3) camera-frame rays through 17 points along each side of the image (z = 1)."""
    w, h = cal.width, cal.height
    t = np.linspace(0.0, 1.0, 17)
    border = np.concatenate(
        [
            np.stack([t * (w - 1), np.zeros_like(t)], 1),
            np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
            np.stack([np.zeros_like(t), t * (h - 1)], 1),
            np.stack([np.full_like(t, w - 1), t * (h - 1)], 1),
        ]
    )
    return geometry.unproject_pixels(border, cal.intrinsics, cal.distortion)


def tiles_in_view(
    centres_xy: NDArray[np.float64], camera: CameraImage, wedge: tuple[float, float] | None
) -> NDArray[np.bool_]:
    """(K,) True for map tiles (x-y centres, world) that may hold points inside the image's
    azimuth wedge: a tile is a disc of radius ``TILE_M / sqrt(2)`` for this test."""
    if wedge is None:
        return np.ones(len(centres_xy), bool)
    centre, half = wedge
    d = centres_xy - camera.world_from_camera[:2, 3]
    dist = np.hypot(d[:, 0], d[:, 1])
    radius = TILE_M / np.sqrt(2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.arcsin(np.clip(radius / dist, 0.0, 1.0))
    off = np.abs(geometry.wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - centre))
    return (dist <= radius + 1.0) | (off <= half + spread)


def thinning_strides(
    centres_xy: NDArray[np.float64], position_xy: NDArray[np.float64], full_density_m: float
) -> NDArray[np.int64]:
    """(K,) the stride at which to take each tile's points: 1 within ``full_density_m`` of the
    position, ``floor((d / full_density_m)^2)`` at distance d (the tile's nearest corner) beyond,
    where a voxel's footprint in the image shrinks as 1/d: a uniform subset keeps the number of
    points per image cell about what it is at ``full_density_m``."""
    d = np.hypot(*(centres_xy - position_xy[:2]).T) - TILE_M / np.sqrt(2.0)
    ratio = np.maximum(d, 0.0) / max(full_density_m, 1e-6)
    return np.maximum(np.floor(ratio**2), 1).astype(np.int64)


def footprint_budgets(
    centres_xy: NDArray[np.float64],
    z_low: NDArray[np.float32],
    z_high: NDArray[np.float32],
    camera_xyz: NDArray[np.float64],
    focal_px: float,
    points_per_pixel: float,
) -> NDArray[np.int64]:
    """(K,) how many points each map tile (x-y centre, lowest and highest z, world frame,
    metres) needs to give about ``points_per_pixel`` per pixel it can cover in an image of
    focal length ``focal_px`` taken from ``camera_xyz`` (world).

    A surface's image area is at most the sum of those of its horizontal and vertical shadows:
    the tile's floor (``TILE_M^2`` at height difference h seen from slant distance r covers at
    most ``f^2 TILE_M^2 h / r^3`` pixels: a road far ahead is seen at a grazing angle) and a wall
    across the tile's diagonal as high as its height span (``f^2 sqrt(2) TILE_M dz / r^2``),
    with r the distance to the tile's nearest possible point, plus the outline of its image (a
    far floor only a few pixels high touches more pixels than its area). The bound is loose near the
    camera (every point is taken there) and tight on the far, flat tiles that hold most of a
    long segment's saturated map."""
    d = np.hypot(*(centres_xy - camera_xyz[:2]).T)
    near_m = np.maximum(d - TILE_M / np.sqrt(2.0), 0.0)
    dz_low = camera_xyz[2] - z_low.astype(np.float64)
    dz_high = z_high.astype(np.float64) - camera_xyz[2]
    height_m = np.maximum(np.maximum(np.abs(dz_low), np.abs(dz_high)), 0.5)
    span_m = np.maximum(z_high.astype(np.float64) - z_low, 0.0)
    slant_m = np.hypot(near_m, np.minimum(np.abs(dz_low), np.abs(dz_high)))
    slant_m = np.maximum(slant_m, 0.5)
    floor_px = focal_px**2 * TILE_M**2 * height_m / slant_m**3
    wall_px = focal_px**2 * np.sqrt(2.0) * TILE_M * span_m / slant_m**2
    # A shape thinner than a pixel touches more pixels than its area: add its outline.
    outline_px = 2.0 * focal_px * (np.sqrt(2.0) * TILE_M + span_m) / slant_m + 1.0
    budget = np.ceil(points_per_pixel * (floor_px + wall_px + outline_px))
    return np.minimum(budget, np.iinfo(np.int64).max // 2).astype(np.int64)


def tiles_reaching(
    centres_xy: NDArray[np.float64],
    z_high: NDArray[np.float32],
    sensor_world: NDArray[np.float64],
    world_from_ego: NDArray[np.float64],
    elevation_rad: float,
) -> NDArray[np.bool_]:
    """(K,) False for map tiles (x-y centres, highest z; world frame, metres) none of whose points
    can lie at or above ``elevation_rad`` seen from ``sensor_world`` in the ego's axes: the tile's
    top over its nearest horizontal distance, plus the ego's tilt from the world's vertical (the
    elevation of a point changes by at most that angle between the two frames)."""
    if elevation_rad <= 0:
        return np.ones(len(centres_xy), bool)
    tilt = float(np.arccos(np.clip(world_from_ego[2, 2], -1.0, 1.0)))
    near_m = np.hypot(*(centres_xy - sensor_world[:2]).T) - TILE_M / np.sqrt(2.0)
    rise_m = z_high.astype(np.float64) - sensor_world[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        elevation = np.where(near_m > 0, np.arctan2(rise_m, near_m), np.pi / 2)
    elevation = np.where(rise_m <= 0, 0.0, elevation)  # a tile below the sensor stays below it
    return elevation + tilt >= elevation_rad


def static_points_per_camera(
    frame: Frame, lidar_map: LidarMap, params: ProjectParams
) -> list[NDArray[np.float32]]:
    """For each image of the frame, the static map points that may appear in it: the tiles in
    range of the ego and in the image's azimuth wedge, thinned (when ``params.thin``) to about
    ``thin_points_per_cell`` points per cell of the visibility grid they can cover
    (:func:`thinning_strides` by distance, :func:`footprint_budgets` by the tile's shape; a
    thinned tile gives its first points, a uniform subset), minus points above the LiDAR's field
    that something unmeasured may hide (:func:`seen_past_lidar_top`, evaluated once per frame)."""
    position = frame.world_from_ego[:3, 3]
    tiles = lidar_map.tiles_near(position, params.max_range_m + TILE_M)
    centres = lidar_map.tile_centres(tiles)
    in_view = np.stack([tiles_in_view(centres, cam, camera_wedge(cam)) for cam in frame.cameras]).reshape(
        len(frame.cameras), len(tiles)
    )
    used = np.flatnonzero(in_view.any(axis=0))
    take = None
    if params.thin and frame.cameras:
        focals = [
            float(c.calibration.intrinsics[0, 0]) * supersample_of(params, c.calibration.width)
            for c in frame.cameras
        ]
        full_density_m = lidar_map.voxel_m * max(focals) * np.sqrt(params.thin_points_per_cell)
        counts = lidar_map.tile_counts(tiles[used])
        stride = thinning_strides(centres[used], position, full_density_m)
        take = -(-counts // stride)  # ceil: the first count / stride points of the hashed order
        z_low, z_high = lidar_map.tile_heights(tiles[used])
        budget = np.zeros(len(used), np.int64)
        for k, cam in enumerate(frame.cameras):
            seen = in_view[k, used]
            need = footprint_budgets(
                centres[used][seen],
                z_low[seen],
                z_high[seen],
                cam.world_from_camera[:3, 3],
                focals[k],
                params.thin_points_per_cell,
            )
            budget[seen] = np.maximum(budget[seen], need)
        take = lidar_map.uniform_takes(tiles[used], np.minimum(take, budget))
    points, counts = lidar_map.points_and_counts_of_tiles(tiles[used], take=take)
    if frame.lidar is not None and len(frame.lidar):
        sensor = geometry.transform_points(
            frame.world_from_ego, np.median(frame.lidar.origins_ego, axis=0)[None]
        )[0]
    else:
        sensor = position
    limit = lidar_map.max_elevation_rad + np.radians(params.elevation_margin_deg)
    band, bin_width = np.radians(params.top_band_deg), np.radians(params.top_bin_deg)
    # Only tiles that may hold a point at or above the band's bottom can change the test's outcome
    # (its profile is built from band points, and it drops only points above the field): a tile's
    # highest point seen from its nearest possible position bounds its points' elevations.
    high = tiles_reaching(
        centres[used], lidar_map.tile_heights(tiles[used])[1], sensor, frame.world_from_ego, limit - band
    )
    seen = np.ones(len(points), bool)
    if high.any():
        tested = np.repeat(high, counts)
        seen[tested] = seen_past_lidar_top(
            points[tested], sensor, frame.world_from_ego, limit, band, bin_width
        )
    # The test applied once; each tile's kept points stay contiguous, so every image takes its
    # tiles' slices (the same points in the same order as a mask per image over all of them,
    # without five masks and gathers over tens of millions of points on a long segment).
    bounds = np.r_[0, np.cumsum(seen)][np.r_[0, np.cumsum(counts)]]
    points = points[seen]
    out = []
    for view in in_view:
        parts = [points[bounds[i] : bounds[i + 1]] for i in np.flatnonzero(view[used])]
        out.append(np.concatenate(parts) if parts else points[:0])
    return out


def scene_points(
    frame: Frame,
    camera: CameraImage,
    lidar_map: LidarMap,
    params: ProjectParams,
    static: NDArray[np.float32] | None = None,
    people: NonRigidPoints | None = None,
) -> CameraPoints:
    """Static map, rigid object models and non-rigid own points, placed at the image's time.

    ``static``: the image's static map points from :func:`static_points_per_camera`; ``people``:
    the frame's :func:`non_rigid_points` (each computed here when not given)."""
    if static is None:
        index = next(i for i, c in enumerate(frame.cameras) if c is camera)
        static = static_points_per_camera(frame, lidar_map, params)[index]
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
    if people is None:
        people = non_rigid_points(frame, lidar_map)
    if len(people.points_world):
        # Move each point with its object from its measurement time to the image's time.
        shift = people.velocity_world * (dt_s - people.dt_s)[:, None]
        parts.append(_points(people.points_world + shift, "non_rigid_object", np.nan))
    return CameraPoints.concatenate(parts)


@dataclass
class NonRigidPoints:
    """The frame's own sweep points inside its non-rigid moving objects' boxes (people, riders).

    Attributes:
        points_world: (N, 3) float64 world points as measured.
        dt_s: (N,) float64 each point's measurement time minus the frame's, seconds.
        velocity_world: (N, 3) float64 its object's velocity, m/s, world frame.
    """

    points_world: NDArray[np.float64]
    dt_s: NDArray[np.float64]
    velocity_world: NDArray[np.float64]


def non_rigid_points(frame: Frame, lidar_map: LidarMap) -> NonRigidPoints:
    """The frame's :class:`NonRigidPoints` (boxes tested at each point's own time, above the
    map's ground clearance); computed once per frame, every image moves them to its own time."""
    boxes = frame.boxes
    people = [k for k, t in enumerate(boxes.track_id) if t in lidar_map.non_rigid_tracks]
    if not people or frame.lidar is None or len(frame.lidar) == 0:
        return NonRigidPoints(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    sub = boxes.select(np.array(people, np.int64))
    sweep = frame.lidar
    pts = sweep.points_world()
    point_dt = sweep_dt_s(sweep, frame.timestamp_micros)
    index, _ = box_points_at_times(pts, point_dt, sub, 1.0, 0.0, lidar_map.ground_clearance_m)
    inside = index >= 0
    return NonRigidPoints(pts[inside], point_dt[inside], sub.velocity_world[index[inside]])
