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
pixels whose ray meets it get no depth (confidence 0), and nothing behind it is projected. A box
holding a camera centre or a LiDAR origin is an error naming the scene, the sensor and the box
(:func:`phigenesis.data.ego_body.check_sensors_outside`): it would blank the camera's depth.

Cost: the first pass over the points (transform, cull, distort, project, the ego-body and
vehicle tests) and the per-pixel plane fits run in C (``csrc/camera_points.c``,
``csrc/plane_fits.c``, :mod:`phigenesis.data.native`), with their numpy twins as the fallback
where no compiler is present (:func:`camera_pixels_reference`, :func:`fit_occupied_numpy`). A
long segment's map saturates its 2 cm voxels: a pixel holding more than
``max_points_per_pixel`` points keeps its front band thinned to about that many
(:func:`thin_in_pixels`), so the work after the first pass is bounded by the image.

Confidence of a sparse pixel: the origin's weight (static map or own sweep 1.0, non-rigid own
points 0.9, rigid object models 0.8: their pose is extrapolated to the image time) times 0.75 if
a single point supports the pixel, 1.0 if two or more agree within ``tau``.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.camera_tables import (
    ego_body_depth_from_rays,
    ego_body_depth_of,
    footprint_pixels,
    per_calibration,
    pixel_rays_cam,
)
from phigenesis.data.camera_tables import ray_box_depths as ray_box_depths  # re-exported
from phigenesis.data.ego_body import camera_centres, check_sensors_outside
from phigenesis.data.native import load_camera_points, load_plane_fits, load_ray_box
from phigenesis.data.records import (
    DEPTH_ORIGINS,
    CameraCalibration,
    CameraDepth,
    CameraImage,
    Frame,
    LazyFrames,
    Scene,
)
from phigenesis.data.stages import register_stage
from phigenesis.data.stages.aggregate import (
    TILE_M,
    LidarMap,
    LidarOriginCheck,
    box_points_at_times,
    checked_ego_boxes,
    ego_boxes_from,
    lidar_angular_step,
    sweep_dt_s,
)
from phigenesis.options import ConfigError, check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

Visibility = Literal["splat", "local_min", "none"]
Estimator = Literal["plane", "nearest_centre"]
MixedPixels = Literal["drop", "keep"]
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
        estimator: how a pixel's depth comes from the visible points that fall in it:
            "plane" fits inverse depth as an affine function of the sub-pixel position (exact for
            a planar surface under a pinhole) to pixels holding at least ``plane_min_points``
            spread-out points and evaluates it at the pixel centre, averaging the LiDAR's range
            noise; other pixels, and every pixel with "nearest_centre", take the visible point
            nearest the centre (``max_offset_px``).
        fit_window_px: the plane is fitted to the points of the pixel's ``(2 r + 1)^2`` window
            where they lie on one plane (more points average more noise; 0: the pixel's own).
        fit_tolerance_m, fit_tolerance_rel: a pixel is mixed (it straddles a depth edge: a pole's
            side, a roof line) if one of its points lies farther than ``fit_tolerance_m +
            fit_tolerance_rel * z`` from the fitted plane, or, with too few points for a fit,
            from the nearest one.
        mixed_pixels: "drop" leaves mixed pixels unknown (the densifier fills them from the
            image's edges); "keep" gives them the point nearest the centre at half confidence.
        edge_band_px, edge_confidence: pixels this close (Chebyshev distance) to a depth edge of
            the sparse map (a neighbour nearer or farther by more than ``edge_tolerance_rel * z +
            edge_tolerance_m``) keep their depth at ``edge_confidence`` times their confidence,
            below ``records.TRUSTED_DEPTH_CONFIDENCE``: a silhouette's pixel centres fall on
            either surface, and whether a point landing near one belongs to it is a guess (most
            are right, but they hold most of the large errors; a thin pole is all edge). 0: no
            band. The near side of an edge counts only where at least ``edge_min_share`` of the
            known pixels around are on its far side (:func:`depth_edge_band`), so a lone
            background leak does not mark the surface around it; ``edge_near_band_px`` (default
            ``edge_band_px``) is the near side's band.
        image_edge_threshold: pixels on the rim of the known region that sit on a strong image
            edge (:func:`silhouette_pixels`) get ``edge_confidence`` too; None turns it off.
        thin, thin_points_per_cell: far map tiles contribute a uniform subset of their points,
            about this many per cell of the visibility grid (:func:`thinning_strides`; the plane
            fits need several per pixel).
        max_points_per_pixel: on the image's own grid (``supersample`` 1), a pixel holding more
            points keeps those in its front band (the splat test's bound over its nearest point,
            which no other could pass) and, of these, a uniform subset of about this many
            (:func:`thin_in_pixels`): a long segment's map saturates its 2 cm voxels, and at a
            grazing angle a far pixel of road holds hundreds. 0: no cap.
        threads: cameras projected in parallel threads (1: one after the other).
        use_map: project the aggregated map when the scene has one (False: own sweep only).
    """

    visibility: Visibility = option("splat")
    tau: float = option(0.05, ge=0, le=10)
    slack_m: float = option(0.1, ge=0, le=100)
    window: int = option(7, ge=1, le=255)
    splat_scale: float = option(0.75, ge=0, le=100)
    max_splat_px: int = option(12, ge=0, le=10_000)
    max_range_m: float = option(120.0, gt=0, le=1000)
    min_depth_m: float = option(0.5, ge=0, le=1000)
    sweep_spacing_rad: float | None = option(None, gt=0, le=1)
    object_spacing_m: float = option(0.02, ge=0, le=10)
    elevation_margin_deg: float = option(0.5, ge=-90, le=90)
    top_band_deg: float = option(1.5, ge=0, le=90)
    top_bin_deg: float = option(0.5, gt=0, le=90)
    vehicle_occluders: bool = option(True)
    occluder_shrink: float = option(0.9, gt=0, le=10)
    occluder_clearance_m: float = option(0.35, ge=0, le=100)
    person_core: float = option(0.8, ge=0, le=1)
    supersample: int | None = option(None, ge=1, le=15)
    max_offset_px: float = option(1.0, ge=0, le=100)
    estimator: Estimator = option("plane")
    plane_min_points: int = option(4, ge=3, le=10_000)
    fit_window_px: int = option(2, ge=0, le=100)
    window_tolerance_m: float = option(0.05, ge=0, le=100)
    window_tolerance_rel: float = option(0.005, ge=0, le=10)
    fit_tolerance_m: float = option(0.1, ge=0, le=100)
    fit_tolerance_rel: float = option(0.01, ge=0, le=10)
    mixed_pixels: MixedPixels = option("drop")
    edge_band_px: int = option(4, ge=0, le=1000)
    edge_tolerance_rel: float = option(0.1, ge=0, le=10)
    edge_tolerance_m: float = option(0.3, ge=0, le=100)
    edge_min_share: float = option(0.05, ge=0, le=1)
    edge_near_band_px: int | None = option(None, ge=0, le=1000)
    edge_confidence: float = option(0.25, ge=0, le=1)
    image_edge_threshold: float | None = option(150.0, ge=0, le=10_000)
    thin: bool = option(True)
    threads: int = option(2, ge=1, le=256)
    thin_points_per_cell: float = option(9.0, gt=0, le=10_000)
    max_points_per_pixel: int = option(8, ge=0, le=1_000_000)
    use_map: bool = option(True)

    def __post_init__(self) -> None:
        check_options(self, "ProjectParams")
        if self.supersample is not None and self.supersample % 2 == 0:
            raise ConfigError(f"ProjectParams: supersample = {self.supersample}: must be odd")
        if self.window % 2 == 0:
            raise ConfigError(f"ProjectParams: window = {self.window}: must be odd")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ProjectParams:
        return from_mapping(cls, values, "project_depth")


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
        take = np.minimum(take, budget)
    points, counts = lidar_map.points_and_counts_of_tiles(tiles[used], take=take)
    if frame.lidar is not None and len(frame.lidar):
        sensor = geometry.transform_points(
            frame.world_from_ego, np.median(frame.lidar.origins_ego, axis=0)[None]
        )[0]
    else:
        sensor = position
    limit = lidar_map.max_elevation_rad + np.radians(params.elevation_margin_deg)
    band, bin_width = np.radians(params.top_band_deg), np.radians(params.top_bin_deg)
    seen = seen_past_lidar_top(points, sensor, frame.world_from_ego, limit, band, bin_width)
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


def supersample_of(params: ProjectParams, width: int) -> int:
    """The visibility grid's refinement for an image ``width`` pixels wide."""
    return params.supersample or (3 if width <= 640 else 1)


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


def pixel_rays(camera: CameraImage) -> NDArray[np.float64]:
    """(H * W, 3) camera-frame rays through the pixel centres with z = 1 (distortion undone),
    read-only, computed once per calibration (:func:`~phigenesis.data.camera_tables.pixel_rays_cam`)."""
    return pixel_rays_cam(camera.calibration)


def ego_body_depth(
    camera: CameraImage, ego_boxes: list[dict], rays: NDArray[np.float64] | None = None
) -> NDArray[np.float32]:
    """(H, W) z-depth at which each pixel's ray enters the ego body boxes (ego frame), inf where
    it misses: read-only and computed once per calibration and body without ``rays``
    (:func:`~phigenesis.data.camera_tables.ego_body_depth_of`), from ``rays`` otherwise."""
    if rays is None:
        return ego_body_depth_of(camera.calibration, ego_boxes)
    return ego_body_depth_from_rays(camera.calibration, ego_boxes, rays)


#: Boxes are clipped to z >= this (metres, camera frame) before their footprint is taken.
_CLIP_Z_M = 1e-6
#: The 12 edges of a box, as pairs of indices into ``geometry.BOX_CORNER_SIGNS``.
_BOX_EDGES = [
    (i, j)
    for i in range(8)
    for j in range(i + 1, 8)
    if np.sum(geometry.BOX_CORNER_SIGNS[i] != geometry.BOX_CORNER_SIGNS[j]) == 1
]


def normalized_footprint(corners_cam: NDArray[np.float64]) -> tuple[tuple[float, float], ...] | None:
    """((x0, x1), (y0, y1)): bounds of x/z and y/z over a box (its 8 corners, camera frame)
    clipped to z >= :data:`_CLIP_Z_M`, None if nothing of it lies in front of the camera. A
    convex solid's pinhole image is the hull of its vertices' images, so every ray (x, y, 1)
    that meets the clipped box lies in these bounds."""
    z = corners_cam[:, 2]
    vertices = [corners_cam[z >= _CLIP_Z_M]]
    for i, j in _BOX_EDGES:
        if (z[i] - _CLIP_Z_M) * (z[j] - _CLIP_Z_M) < 0:
            t = (_CLIP_Z_M - z[i]) / (z[j] - z[i])
            vertices.append((corners_cam[i] + t * (corners_cam[j] - corners_cam[i]))[None])
    points = np.concatenate(vertices)
    if len(points) == 0:
        return None
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    return (float(x.min()), float(x.max())), (float(y.min()), float(y.max()))


def vehicle_far_depth(
    frame: Frame,
    camera: CameraImage,
    moving_tracks: frozenset[str],
    params: ProjectParams,
    rays: NDArray[np.float64],
) -> NDArray[np.float32]:
    """(H, W) depth of the far side of the nearest moving vehicle box (shrunk, bottom raised) on
    each pixel's ray at the image's time, inf where none: nothing beyond it can be visible.

    Each box's rays are tested only over its footprint: the rows and columns whose rays' extents
    (:func:`~phigenesis.data.camera_tables.footprint_pixels`) meet the bounds of its
    :func:`normalized_footprint`, also for a box that reaches behind the camera (a car alongside),
    where :func:`vehicle_far_depth_reference` tested every pixel; in one pass per box with the
    native kernel (:func:`~phigenesis.data.native.load_ray_box`), else with numpy."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    far = np.full((h, w), np.inf, np.float32)
    boxes = frame.boxes
    dt_s = (camera.timestamp_micros - frame.timestamp_micros) * 1e-6
    camera_from_world = geometry.invert_transform(camera.world_from_camera)
    grid = rays.reshape(h, w, 3)
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
        bounds = normalized_footprint(corners)
        region = None if bounds is None else footprint_pixels(cal, *bounds)
        if region is None:
            continue
        kernel = load_ray_box() if rays.flags.c_contiguous else None
        if kernel is not None:
            kernel.far_side(rays, region, geometry.invert_transform(camera_from_box), 0.5 * size, far)
            continue
        rows, cols = region
        sub = grid[rows, cols]
        _, t_out = ray_box_depths(sub.reshape(-1, 3), camera_from_box, 0.5 * size)
        np.minimum(far[rows, cols], t_out.reshape(sub.shape[:2]), out=far[rows, cols])
    return far


def vehicle_far_depth_reference(
    frame: Frame,
    camera: CameraImage,
    moving_tracks: frozenset[str],
    params: ProjectParams,
    rays: NDArray[np.float64],
) -> NDArray[np.float32]:
    """The reference :func:`vehicle_far_depth`: each box's rays over the bounding box of its
    projected corners, or over the whole image when a corner lies nearer than ``min_depth_m``.
    Kept for the tests.

    (H, W) depth of the far side of the nearest moving vehicle box (shrunk, bottom raised) on
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
    """(H, W) nearest depth of any point whose disc of ``radius_px`` covers each pixel (inf: none).

    Each radius's z-buffer and erosion cover only the rectangle around that radius's points
    that their discs reach (the LiDAR fills a band of rows, the sky and the cameras' edges
    nothing): the same values as over the whole image (:func:`occluder_depth_reference`)."""
    h, w = shape
    occ = np.full((h, w), np.inf, np.float32)
    for r in np.unique(radius_px):
        sel = pixel[radius_px == r]
        zs = z[radius_px == r]
        rows, cols = sel // w, sel % w
        r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, h)
        c0, c1 = max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, w)
        cw = c1 - c0
        buf = _zbuffer((rows - r0) * cw + (cols - c0), zs, (r1 - r0) * cw).reshape(r1 - r0, cw)
        if r > 0:
            buf = cv2.erode(buf, _disc(int(r)), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.minimum(occ[r0:r1, c0:c1], buf, out=occ[r0:r1, c0:c1])
    return occ


def occluder_depth_reference(
    pixel: NDArray[np.int64], z: NDArray[np.float32], radius_px: NDArray[np.int64], shape: tuple[int, int]
) -> NDArray[np.float32]:
    """The reference :func:`occluder_depth`: every radius's z-buffer and erosion over the whole
    image. Kept for the tests."""
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


@dataclass
class PixelFit:
    """Per-pixel result of :func:`fit_pixels` (flat arrays over the image's pixels).

    Attributes:
        depth_m: (P,) float64 depth at the pixel centre from a plane fit, NaN where none fits.
        count: (P,) int64 visible points in the pixel itself.
        mixed: (P,) bool: the pixel's own points do not lie on one surface.
    """

    depth_m: NDArray[np.float64]
    count: NDArray[np.int64]
    mixed: NDArray[np.bool_]


#: Moments of a pixel's points: n, sums of du, dv, du², dv², du dv, y, du y, dv y, y².
MOMENT_NAMES = ("n", "u", "v", "uu", "vv", "uv", "y", "uy", "vy", "yy")


def moments(
    pixel: NDArray[np.int64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
    y: NDArray[np.float64],
    size: int,
) -> dict[str, NDArray[np.float64]]:
    """Per-pixel sums (:data:`MOMENT_NAMES`) over points in pixel ``pixel`` (flat index, ``size``
    pixels) at offsets ``du``, ``dv`` from its centre (pixels) with inverse depth ``y`` (1/m)."""
    values = {
        "n": None,
        "u": du,
        "v": dv,
        "uu": du * du,
        "vv": dv * dv,
        "uv": du * dv,
        "y": y,
        "uy": du * y,
        "vy": dv * y,
        "yy": y * y,
    }
    return {k: np.bincount(pixel, weights=v, minlength=size).astype(np.float64) for k, v in values.items()}


def window_moments(m: dict[str, NDArray[np.float64]], shape: tuple[int, int], radius: int) -> dict:
    """Moments of the points in each pixel's (2r+1)^2 window, offsets taken from that pixel's
    centre. A neighbour at offset (dx, dy) contributes its moments shifted by it (du -> du + dx,
    ...), so each window moment is a sum of separable correlations of the per-pixel moments."""
    h, w = shape
    ones = np.ones(2 * radius + 1)
    ramp = np.arange(-radius, radius + 1, dtype=np.float64)

    def corr(name: str, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
        src = m[name].reshape(h, w)
        return cv2.sepFilter2D(src, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT).reshape(-1)

    box = {k: corr(k, ones, ones) for k in MOMENT_NAMES}
    return {
        "n": box["n"],
        "u": box["u"] + corr("n", ramp, ones),
        "v": box["v"] + corr("n", ones, ramp),
        "uu": box["uu"] + 2 * corr("u", ramp, ones) + corr("n", ramp**2, ones),
        "vv": box["vv"] + 2 * corr("v", ones, ramp) + corr("n", ones, ramp**2),
        "uv": box["uv"] + corr("v", ramp, ones) + corr("u", ones, ramp) + corr("n", ramp, ramp),
        "y": box["y"],
        "uy": box["uy"] + corr("y", ramp, ones),
        "vy": box["vy"] + corr("y", ones, ramp),
        "yy": box["yy"],
    }


def _plane_at_centre(m: dict, min_points: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Least-squares ``y = a + b du + c dv`` from moments: (a, b, c, rms residual of y); a is NaN
    where there are too few points or they are not spread in both directions."""
    with np.errstate(divide="ignore", invalid="ignore"):
        n = m["n"]
        mu, mv, my = m["u"] / n, m["v"] / n, m["y"] / n
        cuu = m["uu"] / n - mu * mu
        cvv = m["vv"] / n - mv * mv
        cuv = m["uv"] / n - mu * mv
        cuy = m["uy"] / n - mu * my
        cvy = m["vy"] / n - mv * my
        cyy = m["yy"] / n - my * my
        det = cuu * cvv - cuv * cuv
        # Points spread over at least ~a fifth of a pixel in both directions.
        ok = (n >= min_points) & (det > 1.6e-5)
        b = np.where(ok, (cvv * cuy - cuv * cvy) / det, 0.0)
        c = np.where(ok, (cuu * cvy - cuv * cuy) / det, 0.0)
        a = np.where(ok, my - b * mu - c * mv, np.nan)
        rms = np.sqrt(np.maximum(cyy - b * cuy - c * cvy, 0.0))
    return a, b, c, rms


def occupied_window_moments(
    occupied: NDArray[np.int64], own: NDArray[np.float64], shape: tuple[int, int], radius: int
) -> NDArray[np.float64]:
    """(K, 10) moments (:data:`MOMENT_NAMES` order) of the ``(2r+1)^2`` window of each occupied
    pixel, offsets taken from that pixel's centre: :func:`window_moments` evaluated only at the
    ``occupied`` pixels (sorted flat indices; ``own`` their (K, 10) per-pixel moments).

    Only occupied pixels contribute to a window and only their windows are used, so this is the
    same sum over at most (2r+1)^2 neighbours per occupied pixel (found by binary search), not
    ten whole-image filters: about 1 % of a full-size image's pixels hold a point."""
    h, w = shape
    k = len(occupied)
    out = np.zeros((k, len(MOMENT_NAMES)))
    if k == 0:
        return out
    row, col = occupied // w, occupied % w
    n, u, v, uu, vv, uv, y, uy, vy, yy = own.T
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            inside = (col + dx >= 0) & (col + dx < w) & (row + dy >= 0) & (row + dy < h)
            target = occupied + dy * w + dx
            j = np.minimum(np.searchsorted(occupied, target), k - 1)
            at = np.flatnonzero(inside & (occupied[j] == target))
            if at.size == 0:
                continue
            nb = j[at]
            # A neighbour at (dx, dy) has offsets du + dx, dv + dy from this pixel's centre.
            out[at] += np.stack(
                [
                    n[nb],
                    u[nb] + dx * n[nb],
                    v[nb] + dy * n[nb],
                    uu[nb] + 2 * dx * u[nb] + dx * dx * n[nb],
                    vv[nb] + 2 * dy * v[nb] + dy * dy * n[nb],
                    uv[nb] + dx * v[nb] + dy * u[nb] + dx * dy * n[nb],
                    y[nb],
                    uy[nb] + dx * y[nb],
                    vy[nb] + dy * y[nb],
                    yy[nb],
                ],
                axis=1,
            )
    return out


def fit_pixels(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> PixelFit:
    """Depth at each pixel centre from the visible points (image pixel ``pixel``, position
    ``uv``, depth ``z``): ``1/z = a + b du + c dv`` (du, dv: offset from the centre, pixels)
    fitted to the points of the pixel's ``(2 fit_window_px + 1)^2`` window where they lie on
    one plane (RMS residual within ``fit_tolerance``/2), else to the pixel's own points. The
    pixel is mixed if one of its own points lies farther than the tolerance from its own
    fit or, with too few points for one, from ``reference_m`` (the point nearest its centre).

    The moments and fits are computed for the occupied pixels only, by the native kernel
    (:func:`~phigenesis.data.native.load_plane_fits`: the same arithmetic in the same order, so
    the same doubles, in a few passes: 0.36 CPU-s against 5.6 for the 1.9 million points of the
    camera above) where it is built, else with numpy
    (:func:`fit_occupied_numpy`); :func:`fit_pixels_reference` is the same on whole-image maps
    (equal to rounding: the sums are taken in another order)."""
    h, w = shape
    size = h * w
    kernel = load_plane_fits()
    if kernel is not None and len(pixel):
        occupied, depth, count_k, mixed = kernel(
            pixel,
            uv,
            np.asarray(z, np.float32),
            shape,
            np.asarray(reference_m, np.float32),
            params.plane_min_points,
            (params.fit_tolerance_m, params.fit_tolerance_rel),
            params.fit_window_px,
            (params.window_tolerance_m, params.window_tolerance_rel),
        )
    else:
        occupied, depth, count_k, mixed = fit_occupied_numpy(pixel, uv, z, shape, reference_m, params)
    depth_full = np.full(size, np.nan)
    depth_full[occupied] = depth
    count_full = np.zeros(size, np.int64)
    count_full[occupied] = count_k
    mixed_full = np.zeros(size, bool)
    mixed_full[occupied] = mixed
    return PixelFit(depth_full, count_full, mixed_full)


def fit_occupied_numpy(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    """:func:`fit_pixels` on the occupied pixels with numpy (the native kernel's fallback and
    reference): their sorted flat indices (K,), depth at the centre (K,) float64 (NaN: no fit),
    point count (K,) int64 and mixed flag (K,) bool."""
    w = shape[1]
    z = np.asarray(z, np.float64)
    du = uv[:, 0] - pixel % w
    dv = uv[:, 1] - pixel // w
    y = 1.0 / z
    occupied, inverse = np.unique(pixel, return_inverse=True)
    k = len(occupied)
    values = (None, du, dv, du * du, dv * dv, du * dv, y, du * y, dv * y, y * y)
    sums = [np.bincount(inverse, weights=v, minlength=k) for v in values]
    own_k = np.stack(sums, axis=1).astype(np.float64)
    own = dict(zip(MOMENT_NAMES, own_k.T, strict=True))
    count_k = own["n"].astype(np.int64)
    a, b, c, _ = _plane_at_centre(own, params.plane_min_points)
    zmin = np.full(k, np.inf)
    zmax = np.zeros(k)
    np.minimum.at(zmin, inverse, z)
    np.maximum.at(zmax, inverse, z)
    reference = np.asarray(reference_m)[occupied]
    with np.errstate(divide="ignore", invalid="ignore"):
        # As in fit_pixels_reference: the centre's depth stays within the pixel's own depth range
        # widened by its span, and at least half the nearest point's depth.
        span = zmax - zmin
        depth = np.where(a > 0, np.clip(1.0 / a, np.maximum(zmin - span, 0.5 * zmin), zmax + span), np.nan)
        fitted = np.isfinite(a)[inverse]
        plane_z = 1.0 / (a[inverse] + b[inverse] * du + c[inverse] * dv)
        expected = np.where(fitted, plane_z, reference[inverse])
        deviation = np.nan_to_num(np.abs(z - expected), nan=np.inf)
    worst = np.zeros(k)
    np.maximum.at(worst, inverse, deviation)
    base = np.where(np.isfinite(depth), depth, reference)
    tolerance = params.fit_tolerance_m + params.fit_tolerance_rel * base
    mixed = worst > tolerance
    if params.fit_window_px > 0 and k:
        window = occupied_window_moments(occupied, own_k, shape, params.fit_window_px)
        window_fit = dict(zip(MOMENT_NAMES, window.T, strict=True))
        wa, _, _, rms = _plane_at_centre(window_fit, params.plane_min_points)
        with np.errstate(divide="ignore", invalid="ignore"):
            window_z = 1.0 / wa
            window_tolerance = params.window_tolerance_m + params.window_tolerance_rel * window_z
            good = np.isfinite(window_z) & (window_z > 0) & (rms * window_z**2 <= window_tolerance)
            good &= np.abs(window_z - base) <= tolerance
        depth = np.where(good, window_z, depth)
    return occupied, depth, count_k, mixed


def fit_pixels_reference(
    pixel: NDArray[np.int64],
    uv: NDArray[np.float64],
    z: NDArray[np.floating],
    shape: tuple[int, int],
    reference_m: NDArray[np.floating],
    params: ProjectParams,
) -> PixelFit:
    """The reference :func:`fit_pixels`: the same arithmetic on whole-image moment maps (ten
    (H * W) float64 maps, filtered over every row that holds a point). Kept for the tests.

    Depth at each pixel centre from the visible points (image pixel ``pixel``, position
    ``uv``, depth ``z``): ``1/z = a + b du + c dv`` (du, dv: offset from the centre, pixels)
    fitted to the points of the pixel's ``(2 fit_window_px + 1)^2`` window where they lie on
    one plane (RMS residual within ``fit_tolerance``/2), else to the pixel's own points. The
    pixel is mixed if one of its own points lies farther than the tolerance from its own
    fit or, with too few points for one, from ``reference_m`` (the point nearest its centre)."""
    h, w = shape
    size = h * w
    z = np.asarray(z, np.float64)
    du = uv[:, 0] - pixel % w
    dv = uv[:, 1] - pixel // w
    y = 1.0 / z
    own = moments(pixel, du, dv, y, size)
    count = own["n"].astype(np.int64)
    a, b, c, _ = _plane_at_centre(own, params.plane_min_points)
    zmin = np.full(size, np.inf)
    zmax = np.zeros(size)
    np.minimum.at(zmin, pixel, z)
    np.maximum.at(zmax, pixel, z)
    with np.errstate(divide="ignore", invalid="ignore"):
        # The extrapolation to the centre stays within the pixel's own depth range widened by its
        # span on either side (points in one corner of a planar pixel need up to that).
        # Half the nearest point's depth at least: a steep fit can extrapolate to a negative inverse
        # depth (points near 1 m and 100 m in one pixel), which is no depth at all.
        span = zmax - zmin
        depth = np.where(a > 0, np.clip(1.0 / a, np.maximum(zmin - span, 0.5 * zmin), zmax + span), np.nan)
        fitted = np.isfinite(a)[pixel]
        plane_z = 1.0 / (a[pixel] + b[pixel] * du + c[pixel] * dv)
        expected = np.where(fitted, plane_z, reference_m[pixel])
        deviation = np.nan_to_num(np.abs(z - expected), nan=np.inf)
    worst = np.zeros(size)
    np.maximum.at(worst, pixel, deviation)
    base = np.where(np.isfinite(depth), depth, reference_m)
    tolerance = params.fit_tolerance_m + params.fit_tolerance_rel * base
    mixed = (worst > tolerance) & (count > 0)
    if params.fit_window_px > 0 and len(pixel):
        # Only the rows that hold points (and the window's reach around them) are filtered: the
        # sky and whatever lies above the LiDAR's field stay out of the work.
        r = params.fit_window_px
        rows = pixel // w
        r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, h)
        band = {k: v[r0 * w : r1 * w] for k, v in own.items()}
        wa_band, _, _, rms_band = _plane_at_centre(
            window_moments(band, (r1 - r0, w), r), params.plane_min_points
        )
        wa, rms = np.full(size, np.nan), np.zeros(size)
        wa[r0 * w : r1 * w], rms[r0 * w : r1 * w] = wa_band, rms_band
        with np.errstate(divide="ignore", invalid="ignore"):
            window_z = 1.0 / wa
            window_tolerance = params.window_tolerance_m + params.window_tolerance_rel * window_z
            good = np.isfinite(window_z) & (window_z > 0) & (rms * window_z**2 <= window_tolerance)
            good &= count > 0
            good &= np.abs(window_z - np.where(np.isfinite(depth), depth, reference_m)) <= tolerance
        depth = np.where(good, window_z, depth)
    return PixelFit(depth, count, mixed)


def _known_box(known: NDArray[np.bool_], margin: int) -> tuple[slice, slice] | None:
    """The rows and columns of the known pixels' bounding box widened by ``margin`` (clipped to
    the image), None if none is known."""
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if rows.size == 0:
        return None
    h, w = known.shape
    return (
        slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)),
        slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + margin + 1, w)),
    )


def depth_edge_band(
    depth_m: NDArray[np.floating],
    band_px: int,
    rel: float,
    abs_m: float,
    min_share: float = 0.05,
    near_band_px: int | None = None,
) -> NDArray[np.bool_]:
    """(H, W) True for known pixels (depth > 0) near a depth edge: within ``band_px`` (Chebyshev)
    of a known pixel nearer by more than ``rel * z + abs_m`` (the far side of an edge, or a
    background point seen through a gap), or within ``near_band_px`` (default ``band_px``) of a
    farther one when at least ``min_share`` of the known pixels around are such far-side pixels
    (the near side of a silhouette; a lone leak of background among foreground pixels does not
    make them edge pixels).

    Computed on the known pixels' bounding box: outside it every filter's input already holds
    its border value, so the result equals :func:`depth_edge_band_reference`'s."""
    out = np.zeros(depth_m.shape, bool)
    box = _known_box(depth_m > 0, 0)
    if box is not None:
        out[box] = depth_edge_band_reference(depth_m[box], band_px, rel, abs_m, min_share, near_band_px)
    return out


def silhouette_pixels(
    rgb: NDArray[np.uint8], depth_m: NDArray[np.floating], threshold: float
) -> NDArray[np.bool_]:
    """(H, W) True for known pixels (depth > 0) on the rim of the known region (an unknown
    8-neighbour) that lie within a pixel of a strong image edge (Sobel magnitude of the grey image,
    0-255 scale, above ``threshold``).

    A foreground point landing in a pixel whose centre sees the background beyond a silhouette
    cannot be caught by comparing depths when the background has no depth there (above the
    LiDAR's field, beyond its range): the image still shows the silhouette.

    Computed on the known pixels' bounding box widened by 3 pixels (the Sobel and the 3 x 3
    dilation reach 2, the rim test 1, and the replicated border then repeats unknown pixels):
    equal to :func:`silhouette_pixels_reference`."""
    out = np.zeros(depth_m.shape, bool)
    box = _known_box(depth_m > 0, 3)
    if box is not None:
        out[box] = silhouette_pixels_reference(rgb[box], depth_m[box], threshold)
    return out


def depth_edge_band_reference(
    depth_m: NDArray[np.floating],
    band_px: int,
    rel: float,
    abs_m: float,
    min_share: float = 0.05,
    near_band_px: int | None = None,
) -> NDArray[np.bool_]:
    """The reference :func:`depth_edge_band`, over the whole image. Kept for the tests."""
    known = depth_m > 0
    if band_px <= 0 or not known.any():
        return np.zeros(depth_m.shape, bool)
    near_band_px = band_px if near_band_px is None else near_band_px
    z = depth_m.astype(np.float32)
    far_size = 2 * band_px + 1
    nearest = cv2.erode(
        np.where(known, z, np.inf).astype(np.float32),
        np.ones((far_size, far_size), np.uint8),
        borderValue=np.inf,
    )
    far_side = known & (nearest * (1 + rel) + abs_m < z)
    if near_band_px <= 0:
        return far_side
    size = 2 * near_band_px + 1
    farthest = cv2.dilate(
        np.where(known, z, 0).astype(np.float32), np.ones((size, size), np.uint8), borderValue=0
    )
    counts = [
        cv2.boxFilter(
            m.astype(np.float32), -1, (far_size, far_size), normalize=False, borderType=cv2.BORDER_CONSTANT
        )
        for m in (far_side, known)
    ]
    share = counts[0] / np.maximum(counts[1], 1.0)
    near_side = known & (farthest > z * (1 + rel) + abs_m) & (share >= min_share)
    return far_side | near_side


def silhouette_pixels_reference(
    rgb: NDArray[np.uint8], depth_m: NDArray[np.floating], threshold: float
) -> NDArray[np.bool_]:
    """The reference :func:`silhouette_pixels`, over the whole image. Kept for the tests."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    magnitude = np.hypot(
        cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    )
    near_edge = cv2.dilate((magnitude > threshold).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    known = depth_m > 0
    neighbours = cv2.boxFilter(
        known.astype(np.float32), -1, (3, 3), normalize=False, borderType=cv2.BORDER_REPLICATE
    )
    return known & (neighbours < 9) & near_edge


#: What :func:`camera_pixels` gives: indices into the points, (u, v), z, flat pixel, counts.
CameraPixels = tuple[
    NDArray[np.int64], NDArray[np.float64], NDArray[np.float32], NDArray[np.int64], dict[str, int]
]


def _projection_counts(projected: int, behind_ego: int, behind_vehicles: int, thinned: int) -> dict[str, int]:
    return {
        "projected": projected,
        "removed_by_visibility": 0,
        "behind_ego_body": behind_ego,
        "behind_vehicles": behind_vehicles,
        "thinned_in_pixels": thinned,
        "mixed_pixels": 0,
        "edge_pixels": 0,
    }


def _cap_of(params: ProjectParams, width: int) -> int:
    """The per-pixel cap in force (0: none): only on the image's own grid."""
    return params.max_points_per_pixel if supersample_of(params, width) == 1 else 0


def _mix64(x: NDArray[np.int64]) -> NDArray[np.uint64]:
    """splitmix64's finaliser of ``x`` + its increment (uint64, wrapping): ``camera_points.c``'s
    hash of a point's index."""
    z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def thin_in_pixels(
    index: NDArray[np.int64],
    z: NDArray[np.float32],
    pixel: NDArray[np.int64],
    size: int,
    max_per_pixel: int,
    params: ProjectParams,
) -> NDArray[np.bool_]:
    """(K,) True for the points (``index`` into the scene's points, camera ``z`` float32 metres,
    flat ``pixel`` of a ``size``-pixel image) that a pixel holding more than ``max_per_pixel``
    keeps: those no deeper than ``zmin * (1 + tau) + slack_m`` (its nearest point's splat bound:
    the visibility test removes the others, whatever else covers the pixel) and, where more than
    ``max_per_pixel`` lie in that band, a uniform subset of about ``max_per_pixel``: point i stays
    if ``(hash(i) >> 40) * in_band < max_per_pixel * 2^24`` (a hash of its index, so the same
    points stay whichever order they come in). Pixels with fewer points keep all.

    The numpy twin of the thinning in ``camera_points.c`` (same float32 bound, same hash)."""
    total = np.bincount(pixel, minlength=size)
    dense = total[pixel] > max_per_pixel
    zmin = np.full(size, np.inf, np.float32)
    np.minimum.at(zmin, pixel[dense], z[dense])
    band = z <= zmin[pixel] * (1 + params.tau) + params.slack_m
    in_band = np.bincount(pixel[dense & band], minlength=size)[pixel]
    draw = (_mix64(index) >> np.uint64(40)).astype(np.int64)
    return ~dense | (band & ((in_band <= max_per_pixel) | (draw * in_band < max_per_pixel << 24)))


def camera_pixels(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
) -> CameraPixels:
    """The points (world frame) that land in the image in front of the ego body and the vehicles.

    Returns ``(index, uv, z, pixel, counts)``: (K,) int64 indices into ``points``, (K, 2) float64
    pixel positions (u along the width), (K,) float32 camera z in metres, (K,) int64 flat pixel
    indices (row * W + column) and the counts ``projected`` (points in the image),
    ``behind_ego_body``, ``behind_vehicles`` and ``thinned_in_pixels`` (the per-pixel cap,
    :func:`thin_in_pixels`; the later steps' counts at 0), in the points' order.

    One pass of the native kernel (:func:`~phigenesis.data.native.load_camera_points`) over the
    points, where the numpy path (:func:`camera_pixels_reference`) makes a dozen over millions
    of map points: 0.09 CPU-s against 0.94 for the FRONT camera (1920 x 1280) of the 50-frame
    Waymo segment's first frame, 3.1 million candidate points (1.9 million kept). The
    same arithmetic in the same precision, except the float32 rotation's last bit (BLAS may sum
    in another order): a point on a pixel's border or on a limit may fall the other way."""
    kernel = load_camera_points()
    world = points.points_world
    if kernel is None or len(world) == 0:
        return camera_pixels_reference(camera, points, params, ego_depth, occluder_far)
    cal = camera.calibration
    distortion = np.zeros(5) if cal.distortion is None else np.asarray(cal.distortion, np.float64)
    radius = geometry.max_monotonic_radius(distortion) if np.any(distortion != 0.0) else np.inf
    maps = [
        None if m is None else np.ascontiguousarray(m, np.float32).reshape(cal.height, cal.width)
        for m in (ego_depth, occluder_far)
    ]
    cap = _cap_of(params, cal.width)
    index, uv, z, pixel, (projected, ego, vehicles, thinned) = kernel(
        np.ascontiguousarray(world, np.float32),
        camera.world_from_camera,
        np.asarray(cal.intrinsics, np.float64),
        distortion,
        radius**2,
        (cal.width, cal.height),
        (params.min_depth_m, params.max_range_m),
        normalized_bounds(camera),
        maps[0],
        maps[1],
        params.slack_m,
        cap,
        (1 + params.tau, params.slack_m),
    )
    return index, uv, z, pixel, _projection_counts(projected, ego, vehicles, thinned)


def camera_pixels_reference(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
) -> CameraPixels:
    """The numpy :func:`camera_pixels` (its fallback where no C compiler is present, and the
    reference of the tests)."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    # float32 relative to the camera centre: millions of map points, and world coordinates of a
    # scene (up to a few km) keep ~0.1 mm precision once the centre is subtracted.
    centre = camera.world_from_camera[:3, 3]
    rotation = camera.world_from_camera[:3, :3].astype(np.float32)
    p_cam = (np.asarray(points.points_world, np.float32) - centre.astype(np.float32)) @ rotation
    z_all = p_cam[:, 2]
    near = (z_all > params.min_depth_m) & (np.einsum("ij,ij->i", p_cam, p_cam) <= params.max_range_m**2)
    # A cheap test on the undistorted view directions before the exact projection.
    (x0, x1), (y0, y1) = normalized_bounds(camera)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = p_cam[:, 0] / z_all, p_cam[:, 1] / z_all
    near &= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    p_cam = p_cam[near]
    uv, valid = geometry.project_points(p_cam, cal.intrinsics, cal.distortion, params.min_depth_m)
    valid &= geometry.in_image(uv, w, h)
    idx = np.flatnonzero(near)[valid]
    z = p_cam[valid, 2].astype(np.float32)
    uv = uv[valid]
    pixel = _pixel_index(uv, 1, w, h)
    counts = _projection_counts(len(z), 0, 0, 0)
    for name, limit, slack in (
        ("behind_ego_body", ego_depth, 0.0),
        ("behind_vehicles", occluder_far, params.slack_m),
    ):
        if limit is not None:
            front = z < limit.reshape(-1)[pixel] + slack
            counts[name] = int(np.sum(~front))
            pixel, z, idx, uv = pixel[front], z[front], idx[front], uv[front]
    cap = _cap_of(params, w)
    if cap > 0 and len(z):
        keep = thin_in_pixels(idx, z, pixel, h * w, cap, params)
        counts["thinned_in_pixels"] = int(np.sum(~keep))
        pixel, z, idx, uv = pixel[keep], z[keep], idx[keep], uv[keep]
    return idx, uv, z, pixel, counts


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
    idx, uv, z, pixel, counts = camera_pixels(camera, points, params, ego_depth, occluder_far)
    origin = points.origin[idx]
    # Visibility and the z-buffer work on a grid `s` times finer than the image, so a point
    # occludes (and fills) only the part of a pixel it covers; each pixel then takes the visible
    # point nearest its centre, not the nearest in depth, so edge pixels keep the surface at
    # their centre.
    ss = supersample_of(params, w)
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
    # Every per-pixel value below is computed on the pixels that take a point (``known``, about
    # 1 % of a full-size image), then scattered into the (H, W) maps.
    if ss == 1:
        known = np.flatnonzero(np.isfinite(fine_depth))  # _centre_first on a 1 x 1 grid
        chosen = known
    else:
        chosen = _centre_first(fine_depth.reshape(h, ss, w, ss), params.max_offset_px).reshape(-1)
        known = np.flatnonzero(chosen >= 0)
        chosen = chosen[known]
    sparse_k = fine_depth[chosen]
    origin_k = fine_origin[chosen]
    if params.estimator == "plane":
        sparse = np.full(h * w, np.inf, np.float32)
        sparse[known] = sparse_k
        fit = fit_pixels(pixel, uv[keep], z, (h, w), sparse, params)
        fit_depth, fit_count, mixed = fit.depth_m[known], fit.count[known], fit.mixed[known]
        plane = np.isfinite(fit_depth) & ~mixed
        sparse_k = np.where(plane, fit_depth, sparse_k)
        support = np.where(plane, 2, np.minimum(fit_count, 1))
    else:
        # Support: points in the pixel agreeing with its depth within tau.
        sparse = np.full(h * w, np.inf, np.float32)
        sparse[known] = sparse_k
        agree = np.abs(z - sparse[pixel]) <= sparse[pixel] * params.tau
        support = np.bincount(pixel[agree], minlength=h * w)[known]
        mixed = np.zeros(len(known), bool)
    confidence_k = ORIGIN_WEIGHTS[origin_k] * np.where(support >= 2, 1.0, 0.75)
    confidence_k = np.where(mixed, 0.5 * confidence_k, confidence_k)
    counts["mixed_pixels"] = int(mixed.sum())
    if params.mixed_pixels == "drop":
        kept = ~mixed
        known, sparse_k, confidence_k, origin_k = (
            known[kept],
            sparse_k[kept],
            confidence_k[kept],
            origin_k[kept],
        )
    depth = np.zeros(h * w, np.float32)
    depth[known] = sparse_k
    confidence = np.zeros(h * w, np.float32)
    confidence[known] = confidence_k
    origin_map = np.zeros(h * w, np.uint8)
    origin_map[known] = origin_k
    edge = depth_edge_band(
        depth.reshape(h, w),
        params.edge_band_px,
        params.edge_tolerance_rel,
        params.edge_tolerance_m,
        params.edge_min_share,
        params.edge_near_band_px,
    ).reshape(-1)
    if params.image_edge_threshold is not None and camera.image_bytes is not None:
        edge |= silhouette_pixels(
            camera.decode_image(), depth.reshape(h, w), params.image_edge_threshold
        ).reshape(-1)
    counts["edge_pixels"] = int(edge.sum())
    confidence[edge] *= params.edge_confidence
    if ego_depth is not None:
        body = np.isfinite(ego_depth.reshape(-1))
        depth[body], confidence[body], origin_map[body] = 0.0, 0.0, 0
    return (
        CameraDepth(depth.reshape(h, w), confidence.reshape(h, w), origin_map.reshape(h, w)),
        counts,
    )


def project_camera_reference(
    camera: CameraImage,
    points: CameraPoints,
    params: ProjectParams,
    ego_depth: NDArray[np.float32] | None = None,
    occluder_far: NDArray[np.float32] | None = None,
    sweep_step_rad: float = float(np.radians(0.5)),
) -> tuple[CameraDepth, dict[str, int]]:
    """The reference :func:`project_camera`: the same steps with the plain reference functions
    (:func:`occluder_depth_reference`, :func:`fit_pixels_reference`,
    :func:`depth_edge_band_reference`, :func:`silhouette_pixels_reference`) and every per-pixel
    value computed over the whole image. Kept for the tests."""
    cal = camera.calibration
    h, w = cal.height, cal.width
    idx, uv, z, pixel, counts = camera_pixels_reference(camera, points, params, ego_depth, occluder_far)
    origin = points.origin[idx]
    # Visibility and the z-buffer work on a grid `s` times finer than the image, so a point
    # occludes (and fills) only the part of a pixel it covers; each pixel then takes the visible
    # point nearest its centre, not the nearest in depth, so edge pixels keep the surface at
    # their centre.
    ss = supersample_of(params, w)
    hf, wf = h * ss, w * ss
    fine = _pixel_index(uv, ss, wf, hf)
    keep = np.ones(len(z), bool)
    if params.visibility == "splat" and len(z):
        focal = float(cal.intrinsics[0, 0]) * ss
        spacing = points.spacing_m[idx]
        footprint = np.where(np.isnan(spacing), z * sweep_step_rad, spacing)
        radius = np.rint(params.splat_scale * focal * footprint / z)
        radius = np.clip(radius, 0, params.max_splat_px * ss).astype(np.int64)
        occ = occluder_depth_reference(fine, z, radius, (hf, wf)).reshape(-1)
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
    if params.estimator == "plane":
        fit = fit_pixels_reference(pixel, uv[keep], z, (h, w), sparse, params)
        plane = np.isfinite(fit.depth_m) & hit & ~fit.mixed
        sparse = np.where(plane, fit.depth_m, sparse)
        support = np.where(plane, 2, np.minimum(fit.count, 1))
        mixed = fit.mixed & hit
    else:
        # Support: points in the pixel agreeing with its depth within tau.
        agree = np.abs(z - sparse[pixel]) <= sparse[pixel] * params.tau
        support = np.bincount(pixel[agree], minlength=h * w)
        mixed = np.zeros(h * w, bool)
    confidence = ORIGIN_WEIGHTS[origin_map] * np.where(support >= 2, 1.0, 0.75)
    confidence = np.where(mixed, 0.5 * confidence, confidence)
    if params.mixed_pixels == "drop":
        hit &= ~mixed
    counts["mixed_pixels"] = int(mixed.sum())
    confidence = np.where(hit, confidence, 0.0).astype(np.float32)
    origin_map = np.where(hit, origin_map, 0).astype(np.uint8)
    depth = np.where(hit, sparse, 0.0).astype(np.float32)
    edge = depth_edge_band_reference(
        depth.reshape(h, w),
        params.edge_band_px,
        params.edge_tolerance_rel,
        params.edge_tolerance_m,
        params.edge_min_share,
        params.edge_near_band_px,
    ).reshape(-1)
    if params.image_edge_threshold is not None and camera.image_bytes is not None:
        edge |= silhouette_pixels_reference(
            camera.decode_image(), depth.reshape(h, w), params.image_edge_threshold
        ).reshape(-1)
    counts["edge_pixels"] = int(edge.sum())
    confidence[edge] *= params.edge_confidence
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
        # The aggregation checked the body against the cameras and LiDARs already.
        self.ego_boxes = self.lidar_map.ego_boxes if self.lidar_map is not None else checked_ego_boxes(scene)
        self.boxes_from = ego_boxes_from(scene)
        self.check_lidar = None if self.lidar_map is not None else LidarOriginCheck(scene, self.ego_boxes)
        self._rays: dict[tuple, tuple[NDArray[np.float64], NDArray[np.float32]]] = {}
        self._warned = False

    def rays_and_ego_depth(self, camera: CameraImage) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
        """The camera's pixel rays and ego body depth, computed once per calibration (a new
        calibration is checked against the body first: PrepError if a box holds its centre)."""
        key = camera.calibration.key()
        if key not in self._rays:
            sensors = camera_centres([camera.calibration])
            check_sensors_outside(self.scene_id, self.ego_boxes, sensors, self.boxes_from)
            self._rays[key] = (pixel_rays(camera), ego_body_depth(camera, self.ego_boxes))
        return self._rays[key]

    def sweep_step(self, frame: Frame) -> float:
        if self.params.sweep_spacing_rad is not None:
            return self.params.sweep_spacing_rad
        if self.lidar_map is not None:
            return self.lidar_map.angular_step_rad
        return lidar_angular_step(frame.lidar) if frame.lidar is not None else float(np.radians(0.5))

    def __call__(self, frame: Frame) -> Frame:
        has_sweep = frame.lidar is not None and len(frame.lidar) > 0
        if self.check_lidar is not None and has_sweep:
            self.check_lidar(frame.lidar)
        if self.lidar_map is None and not has_sweep and not self._warned:
            log.warning(
                "scene %s frame %d: no LiDAR; its depth maps are empty", self.scene_id, frame.frame_index
            )
            self._warned = True
        step = self.sweep_step(frame)
        static = people = None
        if self.lidar_map is not None:
            static = static_points_per_camera(frame, self.lidar_map, self.params)
            people = non_rigid_points(frame, self.lidar_map)
        for camera in frame.cameras:  # the per-scene tables, filled before any thread runs
            self.rays_and_ego_depth(camera)

        def one_camera(k: int) -> None:
            camera = frame.cameras[k]
            rays, ego_depth = self.rays_and_ego_depth(camera)
            occluders = None
            if self.lidar_map is not None:
                pts = scene_points(frame, camera, self.lidar_map, self.params, static[k], people)
                if self.params.vehicle_occluders:
                    occluders = vehicle_far_depth(
                        frame, camera, self.lidar_map.moving_tracks, self.params, rays
                    )
            else:
                pts = sweep_points(frame)
            camera.depth, _ = project_camera(camera, pts, self.params, ego_depth, occluders, step)

        if self.params.threads > 1 and len(frame.cameras) > 1:
            # Cameras are independent and numpy/OpenCV release the GIL on large arrays.
            with ThreadPoolExecutor(max_workers=self.params.threads) as pool:
                list(pool.map(one_camera, range(len(frame.cameras))))
        else:
            for k in range(len(frame.cameras)):
                one_camera(k)
        return frame


def _camera_tables_once(scene: Scene, params: ProjectParams) -> None:
    """Per-scene setup: every camera's pixel rays and ego-body depth
    (:mod:`~phigenesis.data.camera_tables`), so no frame pays for them."""
    lidar_map = scene.products.get("lidar_map") if params.use_map else None
    ego_boxes = lidar_map.ego_boxes if lidar_map is not None else checked_ego_boxes(scene)
    for cal in scene.calibrations:
        ego_body_depth_of(cal, ego_boxes)


@register_stage("project_depth", params=ProjectParams, setup=_camera_tables_once)
def project_depth(scene: Scene, params: ProjectParams) -> Scene:
    """Stage: sparse depth and confidence for every image (see the module docstring); uses the
    aggregated map from ``aggregate_lidar`` when it ran, else each frame's own sweep."""
    projector = _Projector(scene, params)
    if isinstance(scene.frames, LazyFrames):
        scene.frames = scene.frames.map(projector)
    else:
        scene.frames = [projector(f) for f in scene.frames]
    return scene
