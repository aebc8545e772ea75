"""Sub-pixel plane fits, depth-edge bands, culling and thinning of the depth projection, and the
map's voxel centroids: unit tests against exact geometry."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis.data.records import TRUSTED_DEPTH_CONFIDENCE, CameraCalibration, CameraDepth, CameraImage
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.aggregate import TILE_M, LidarMap, _tile_sort, point_levels, voxel_downsample
from phigenesis.data.stages.project import (
    MOMENT_NAMES,
    CameraPoints,
    ProjectParams,
    depth_edge_band,
    fit_pixels,
    footprint_budgets,
    moments,
    normalized_bounds,
    project_camera,
    seen_past_lidar_top,
    silhouette_pixels,
    static_points_per_camera,
    thinning_strides,
    tiles_reaching,
    window_moments,
)
from tests.test_depth_stages import _camera, _wall


def _plane_points(n: int, normal_cam: np.ndarray, offset_m: float, cam: CameraImage, rng) -> np.ndarray:
    """``n`` points of the plane ``normal . p = offset`` (camera frame) seen at random pixels."""
    cal = cam.calibration
    uv = rng.uniform([-0.5, -0.5], [cal.width - 0.5, cal.height - 0.5], size=(n, 2))
    rays = geometry.unproject_pixels(uv, cal.intrinsics, cal.distortion)
    t = offset_m / (rays @ normal_cam)
    return (rays * t[:, None])[t > 0]


def _yaw(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _to_world(cam: CameraImage, p_cam: np.ndarray) -> np.ndarray:
    return geometry.transform_points(cam.world_from_camera, p_cam)


def test_window_moments_equal_brute_force_sums():
    rng = np.random.default_rng(0)
    h, w, n, r = 7, 9, 300, 2
    pixel = rng.integers(0, h * w, n)
    du, dv, y = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.01, 1.0, n)
    window = window_moments(moments(pixel, du, dv, y, h * w), (h, w), r)
    row, col = np.divmod(pixel, w)
    for p in range(h * w):
        pr, pc = divmod(p, w)
        sel = (np.abs(row - pr) <= r) & (np.abs(col - pc) <= r)
        u, v, yy = du[sel] + col[sel] - pc, dv[sel] + row[sel] - pr, y[sel]
        brute = {
            "n": sel.sum(),
            "u": u.sum(),
            "v": v.sum(),
            "uu": (u * u).sum(),
            "vv": (v * v).sum(),
            "uv": (u * v).sum(),
            "y": yy.sum(),
            "uy": (u * yy).sum(),
            "vy": (v * yy).sum(),
            "yy": (yy * yy).sum(),
        }
        for name in MOMENT_NAMES:
            assert window[name][p] == pytest.approx(brute[name], abs=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    tilt=st.floats(-1.2, 1.2),
    turn=st.floats(-0.8, 0.8),
    distance=st.floats(3.0, 60.0),
    window=st.integers(0, 2),
)
def test_plane_fit_is_exact_on_a_plane(tilt: float, turn: float, distance: float, window: int):
    """Inverse depth is affine in the pixel position on a plane, so the fit at each pixel centre
    equals the plane's depth there, wherever the points fall in the pixel."""
    cam = _camera()
    normal = np.array([np.sin(turn), np.sin(tilt), np.cos(tilt) * np.cos(turn)])
    normal /= np.linalg.norm(normal)
    rng = np.random.default_rng(1)
    pts = _plane_points(30000, normal, distance, cam, rng)
    pts = pts[pts[:, 2] < 1e4]  # rays nearly parallel to the plane
    cal = cam.calibration
    uv, _ = geometry.project_points(pts, cal.intrinsics)
    pixel = (np.rint(uv[:, 1]) * cal.width + np.rint(uv[:, 0])).astype(np.int64)
    params = ProjectParams(fit_window_px=window)
    fit = fit_pixels(
        pixel, uv, pts[:, 2], (cal.height, cal.width), np.full(cal.width * cal.height, np.nan), params
    )
    centres = geometry.unproject_pixels(geometry.pixel_grid(cal.width, cal.height), cal.intrinsics)
    truth = distance / (centres @ normal)
    # Pixels that the horizon crosses are not planar patches; leave them out.
    corners = [
        geometry.unproject_pixels(geometry.pixel_grid(cal.width, cal.height) + off, cal.intrinsics)
        for off in ([-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5])
    ]
    whole = np.all([(d > 0) & (d < 1e3) for d in (distance / (c @ normal) for c in corners)], axis=0)
    done = np.isfinite(fit.depth_m) & whole
    assert done.sum() > 0.5 * np.sum(np.bincount(pixel, minlength=len(truth)) > 0)
    rel = np.abs(fit.depth_m[done] / truth[done] - 1)
    # Exact, except where the points hug one corner and the clip to the pixel's own depth range
    # (widened by its span) stops a far extrapolation.
    assert np.mean(rel < 1e-6) > 0.99 and rel.max() < 0.05
    assert not fit.mixed[whole].any()


def test_plane_fit_averages_range_noise_and_flags_mixed_pixels():
    cam = _camera()
    rng = np.random.default_rng(2)
    normal = np.array([0.0, -0.3, 1.0]) / np.hypot(0.3, 1.0)
    pts = _plane_points(20000, normal, 12.0, cam, rng)
    noisy = pts * (1 + rng.normal(0, 0.02, len(pts)) / np.linalg.norm(pts, axis=1))[:, None]
    origin = np.full(len(pts), 1, np.uint8)
    spacing = np.full(len(pts), 0.02, np.float32)
    world = CameraPoints(_to_world(cam, noisy), origin, spacing)
    centres = geometry.unproject_pixels(geometry.pixel_grid(64, 48), cam.calibration.intrinsics)
    truth = (12.0 / (centres @ normal)).reshape(48, 64)
    errors = {}
    for estimator in ("plane", "nearest_centre"):
        depth, _ = project_camera(cam, world, ProjectParams(estimator=estimator, edge_band_px=0))
        known = depth.sparse_m > 0
        assert known.mean() > 0.95
        errors[estimator] = np.median(np.abs(depth.sparse_m[known] - truth[known]))
    assert errors["nearest_centre"] > 0.01  # 2 cm range noise
    assert errors["plane"] < 0.4 * errors["nearest_centre"]
    # A pixel holding points of two surfaces 5 m apart is mixed and is dropped.
    pixel = np.array([10, 10, 10, 10, 11], np.int64)
    uv = np.array([[10.2, 0.0], [9.8, 0.1], [10.0, -0.2], [10.1, 0.2], [11.0, 0.0]])
    z = np.array([10.0, 10.0, 15.0, 10.0, 10.0])
    fit = fit_pixels(pixel, uv, z, (1, 20), np.full(20, 10.0), ProjectParams(fit_window_px=0))
    assert fit.mixed[10] and not fit.mixed[11]


def test_a_fit_extrapolating_to_negative_inverse_depth_gives_no_negative_depth():
    # One pixel holding points at 100 m near its centre and 1 m at its edge: the plane through them
    # reaches a negative inverse depth at the centre (a regression: it gave a depth of -0.5 m).
    uv = np.array([[10.3, -0.3], [10.3, 0.3], [10.45, -0.3], [10.45, 0.3]])
    z = np.array([100.0, 100.0, 1.0, 1.0])
    y = 1 / z
    slope = (y[2] - y[0]) / 0.15
    assert y[0] - 0.3 * slope < 0  # the fitted inverse depth at the centre is negative
    pixel = np.full(4, 10, np.int64)
    for window in (0, 2):
        fit = fit_pixels(pixel, uv, z, (1, 20), np.full(20, np.nan), ProjectParams(fit_window_px=window))
        depth = fit.depth_m[10]
        assert not depth < 0.5, depth  # NaN (no fit; the nearest point stands in) or >= half the nearest


def test_edge_band_marks_both_sides_of_a_silhouette_but_not_around_a_lone_leak():
    depth = np.full((30, 40), 10.0, np.float32)
    depth[:, 20:] = 30.0
    band = depth_edge_band(depth, 4, 0.1, 0.3)
    cols = np.flatnonzero(band.any(axis=0))
    assert cols.min() == 16 and cols.max() == 23  # 4 pixels on each side of the edge
    leak = np.full((30, 40), 10.0, np.float32)
    leak[15, 20] = 30.0
    band = depth_edge_band(leak, 4, 0.1, 0.3)
    assert band[15, 20] and band.sum() == 1
    assert not depth_edge_band(np.full((8, 8), 10.0, np.float32), 4, 0.1, 0.3).any()


def test_edge_pixels_keep_their_depth_below_the_trusted_confidence():
    """A sparse wall leaks background through its gaps on the image's own grid: the leaks and the
    pixels beside them stay in the sparse map, but below the confidence densification uses."""
    cam = _camera()
    front, back = _wall(10.0, 0.25), _wall(30.0, 0.1)
    pts = CameraPoints(
        np.concatenate([front, back]),
        np.full(len(front) + len(back), 1, np.uint8),
        np.concatenate([np.full(len(front), 0.25, np.float32), np.full(len(back), 0.1, np.float32)]),
    )
    depth, counts = project_camera(cam, pts, ProjectParams(supersample=1))
    trusted = depth.sparse_confidence >= TRUSTED_DEPTH_CONFIDENCE
    assert counts["edge_pixels"] > 0
    assert np.isclose(depth.sparse_m, 30.0).any()  # leaks are kept, untrusted
    assert not np.isclose(depth.sparse_m[trusted], 30.0).any()
    assert trusted.sum() > 0.25 * trusted.size


def test_densify_stage_seeds_only_from_trusted_depths():
    cam = _camera(32, 24)
    sparse = np.zeros((24, 32), np.float32)
    sparse[::3, ::3] = 10.0
    conf = np.where(sparse > 0, 1.0, 0.0).astype(np.float32)
    sparse[12, 15], conf[12, 15] = 50.0, 0.2  # an untrusted outlier
    cam.depth = CameraDepth(sparse, conf, (sparse > 0).astype(np.uint8))
    from phigenesis.data.records import Boxes, Frame, Scene

    frame = Frame("s", 0, 0, np.eye(4), [cam], None, Boxes.empty())
    scene = Scene("s", "synthetic", [cam.calibration], [frame])
    out = get_stage("densify_depth")(scene, {"method": "ipbasic"}).frames[0].cameras[0].depth
    assert out.dense_m.max() < 11.0  # the untrusted 50 m seed was not spread
    with_all = get_stage("densify_depth")(
        Scene("s", "synthetic", [cam.calibration], [frame]), {"method": "ipbasic", "min_confidence": 0.1}
    )
    assert with_all.frames[0].cameras[0].depth.dense_m.max() > 40.0


def _slow_seen_past_lidar_top(points, sensor, world_from_ego, limit, band, bin_rad):
    """The rule of :func:`seen_past_lidar_top` written out with angles, as the reference."""
    d = (points - sensor) @ world_from_ego[:3, :3]
    r = np.hypot(d[:, 0], d[:, 1])
    elevation = np.arctan2(d[:, 2], r)
    bins = int(np.ceil(2 * np.pi / bin_rad))
    az = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / bin_rad).astype(int) % bins
    inside = elevation <= limit
    in_band = inside & (elevation >= limit - band)
    profile = np.full(bins, np.inf)
    np.minimum.at(profile, az[in_band], r[in_band])
    profile = np.minimum(profile, np.minimum(np.roll(profile, 1), np.roll(profile, -1)))
    return inside | (r < profile[az])


@settings(max_examples=20, deadline=None)
@given(yaw=st.floats(-3.1, 3.1), limit_deg=st.floats(0.5, 10.0), seed=st.integers(0, 100))
def test_seen_past_lidar_top_matches_the_angle_formulation(yaw: float, limit_deg: float, seed: int):
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-60, -60, -3], [60, 60, 12], size=(3000, 3)).astype(np.float32)
    world_from_ego = geometry.make_transform(_yaw(yaw), [1.0, 2.0, 0.0])
    sensor = np.array([1.5, 2.0, 1.9])
    args = (np.radians(limit_deg), np.radians(1.5), np.radians(0.5))
    fast = seen_past_lidar_top(pts, sensor, world_from_ego, *args)
    slow = _slow_seen_past_lidar_top(pts.astype(np.float64), sensor, world_from_ego, *args)
    # float32 differences only move points lying on a bin or elevation boundary.
    assert np.mean(fast != slow) < 0.002


def test_thinning_keeps_near_tiles_whole_and_thins_far_ones_quadratically():
    centres = np.array([[0.0, 0.0], [30.0, 0.0], [100.0, 0.0], [0.0, -200.0]])
    stride = thinning_strides(centres, np.zeros(3), 40.0)
    half = TILE_M / np.sqrt(2)
    assert stride[0] == 1 and stride[1] == 1
    assert stride[2] == int(((100 - half) / 40) ** 2)
    assert stride[3] == int(((200 - half) / 40) ** 2)


def test_culling_keeps_every_map_point_that_lands_in_the_image():
    """Tiles outside an image's azimuth wedge are skipped: no point that projects into the image
    may be lost (thinning off)."""
    rng = np.random.default_rng(3)
    pts = rng.uniform([-100, -100, -1], [100, 100, 1], size=(200000, 3)).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(pts)
    lidar_map = LidarMap(
        sorted_pts, keys, start, 0.05, frozenset(), frozenset(), {}, [], max_elevation_rad=np.pi / 2
    )
    from phigenesis.data.records import Boxes, Frame

    cameras = []
    for k, yaw in enumerate((0.0, 1.2, 2.9, -1.9)):
        rotation = _yaw(yaw) @ geometry.BODY_FROM_OPENCV
        ego_from_camera = geometry.make_transform(rotation, [1.0, 0.0, 1.5])
        intrinsics = geometry.intrinsic_matrix(40.0, 40.0, 31.5, 23.5)
        cal = CameraCalibration(f"C{k}", 64, 48, intrinsics, np.zeros(5), ego_from_camera)
        cameras.append(CameraImage(cal, 0, geometry.make_transform(_yaw(0.4), [5.0, -3.0, 0.0]), None))
    frame = Frame("s", 0, 0, cameras[0].world_from_ego, cameras, None, Boxes.empty())
    params = ProjectParams(thin=False, max_range_m=80.0)
    culled = static_points_per_camera(frame, lidar_map, params)
    for cam, kept in zip(cameras, culled, strict=True):
        p_cam = geometry.transform_points(np.linalg.inv(cam.world_from_camera), sorted_pts)
        uv, valid = geometry.project_points(p_cam, cam.calibration.intrinsics)
        seen = valid & geometry.in_image(uv, 64, 48) & (np.linalg.norm(p_cam, axis=1) < 80.0)
        assert seen.sum() > 100
        kept_set = {tuple(p) for p in kept.tolist()}
        assert all(tuple(p) in kept_set for p in sorted_pts[seen].tolist())
        assert len(kept) < 0.6 * len(sorted_pts)  # and most of the map was skipped
        (x0, x1), (y0, y1) = normalized_bounds(cam)
        z = p_cam[seen, 2]
        assert np.all((p_cam[seen, 0] / z >= x0) & (p_cam[seen, 0] / z <= x1))
        assert np.all((p_cam[seen, 1] / z >= y0) & (p_cam[seen, 1] / z <= y1))


def test_numpy_voxel_centroids_are_each_voxels_mean():
    rng = np.random.default_rng(4)
    voxel = 0.1
    pts = rng.uniform(-2.0, 2.0, size=(5000, 3))
    cells = np.floor(pts / voxel).astype(np.int64)
    groups: dict[tuple, list[np.ndarray]] = {}
    for cell, p in zip(map(tuple, cells), pts, strict=True):
        groups.setdefault(cell, []).append(p)
    reference = np.array([np.mean(g, axis=0) for g in groups.values()])
    got = voxel_downsample(pts, voxel, "numpy")
    assert len(got) == len(reference)
    order = lambda a: a[np.lexsort(np.round(a, 4).T)]  # noqa: E731
    np.testing.assert_allclose(order(got), order(reference), atol=1e-6)
    # Open3D's grid is anchored at the points' minimum: other voxels, same bounds and spacing.
    o3d_points = voxel_downsample(pts, voxel, "open3d")
    assert abs(len(o3d_points) - len(got)) < 0.1 * len(got)
    with pytest.raises(ValueError, match="voxel_backend"):
        get_stage("aggregate_lidar")(None, {"voxel_backend": "pcl"})  # type: ignore[arg-type]


def test_silhouette_pixels_need_both_a_rim_of_the_known_region_and_an_image_edge():
    rgb = np.zeros((40, 60, 3), np.uint8)
    rgb[10:30, 20:40] = 220  # a bright object on a dark background
    depth = np.zeros((40, 60), np.float32)
    depth[10:30, 20:40] = 8.0  # known on the object only (the background has no depth)
    depth[10:30, 50:58] = 20.0  # a known patch with no image edge at its rim
    flagged = silhouette_pixels(rgb, depth, 150.0)
    rim = np.zeros_like(flagged)
    rim[10:30, 20:40] = True
    rim[11:29, 21:39] = False
    assert flagged[rim].all()  # the object's outline
    assert not flagged[12:28, 22:38].any()  # its interior
    assert not flagged[:, 45:].any()  # a rim where the image is flat


def _covered_pixels(points_world: np.ndarray, camera_xyz: np.ndarray, focal_px: float) -> int:
    """Pixels (of an unbounded pinhole looking along +x from ``camera_xyz``) that hold a point."""
    rel = points_world.astype(np.float64) - camera_xyz
    ahead = rel[:, 0] > 0.1
    u = np.floor(focal_px * -rel[ahead, 1] / rel[ahead, 0]).astype(np.int64)
    v = np.floor(focal_px * -rel[ahead, 2] / rel[ahead, 0]).astype(np.int64)
    return len(np.unique(u * 1_000_003 + v))


@pytest.mark.parametrize("distance_m", [20.0, 60.0, 110.0])
@pytest.mark.parametrize("surface", ["floor", "wall", "floor and wall"])
def test_footprint_budget_bounds_the_pixels_a_tile_covers(distance_m: float, surface: str):
    """The budget is ``points_per_pixel`` times an upper bound on the pixels the tile's surfaces
    can cover: a saturated 2 cm floor, a wall across the tile, or both, seen from 2 m up."""
    focal, camera = 2000.0, np.array([0.0, 0.0, 2.0])
    x0, y0 = distance_m, -TILE_M / 2
    grid = np.arange(0.01, TILE_M, 0.02)
    parts = []
    if "floor" in surface:
        gx, gy = np.meshgrid(grid, grid, indexing="ij")
        parts.append(np.stack([x0 + gx.ravel(), y0 + gy.ravel(), np.zeros(gx.size)], axis=1))
    if "wall" in surface:
        gy, gz = np.meshgrid(grid, np.arange(0.01, 6.0, 0.02), indexing="ij")
        parts.append(np.stack([np.full(gy.size, x0 + 1.0), y0 + gy.ravel(), gz.ravel()], axis=1))
    points = np.concatenate(parts).astype(np.float32)
    centre = np.array([[x0 + TILE_M / 2, 0.0]])
    z = points[:, 2]
    budget = footprint_budgets(centre, z.min(keepdims=True), z.max(keepdims=True), camera, focal, 1.0)[0]
    covered = _covered_pixels(points, camera, focal)
    assert budget >= covered
    if surface == "floor":
        # Tight where it matters: a far floor is seen at a grazing angle, and the bound follows.
        assert budget <= 8 * covered
        assert budget < len(points) / 20 or distance_m < 60
    stride = thinning_strides(centre, camera, 0.02 * focal * 3.0)[0]
    if surface == "floor" and distance_m >= 60:
        assert stride == 1  # the distance rule alone would take every point of this tile


def test_tile_sort_orders_each_tile_by_level_so_whole_levels_are_uniform_and_keep_voxel_order():
    """A saturated 2 cm floor tile in voxel (row) order: its first points up to a level boundary,
    about 2 % of it, spread evenly over the tile (the first 2 % of a key-sorted tile, or every 50th
    point, would keep whole rows), and each level keeps the voxel order (neighbours stay near in
    memory)."""
    grid = np.arange(0.01, TILE_M, 0.02)
    gx, gy = np.meshgrid(grid, grid, indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(points)
    assert len(keys) == 1 and start.tolist() == [0, len(points)]
    assert {tuple(p) for p in sorted_pts.tolist()} == {tuple(p) for p in points.tolist()}
    lidar_map = LidarMap(sorted_pts, keys, start, 0.02, frozenset(), frozenset(), {}, [])
    wanted = len(points) // 50
    (take,) = lidar_map.uniform_takes(np.array([0]), np.array([wanted]))
    assert wanted <= take <= 2.2 * wanted
    prefix = sorted_pts[:take]
    for axis in (0, 1):
        counts = np.histogram(prefix[:, axis], bins=32, range=(0.0, TILE_M))[0]
        expected = len(prefix) / 32
        assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))
    levels = point_levels(sorted_pts)
    assert np.all(np.diff(levels.astype(int)) <= 0)
    for level in np.unique(levels):
        run = sorted_pts[levels == level]
        assert np.all(np.diff(run[:, 0]) >= 0)  # the rows' order, as they came
    # Sorted again, the same order: the cache's rows do not depend on the run.
    again, _, _ = _tile_sort(points[::-1].copy())
    np.testing.assert_array_equal(point_levels(again), levels)


def test_tile_heights_are_each_tiles_lowest_and_highest_point():
    rng = np.random.default_rng(5)
    pts = rng.uniform([-30, -30, -2], [30, 30, 9], size=(20000, 3)).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(pts)
    lidar_map = LidarMap(sorted_pts, keys, start, 0.05, frozenset(), frozenset(), {}, [])
    tiles = np.arange(len(keys))
    low, high = lidar_map.tile_heights(tiles)
    for t in tiles:
        z = sorted_pts[start[t] : start[t + 1], 2]
        assert low[t] == z.min() and high[t] == z.max()
    assert lidar_map.tile_counts(tiles).sum() == len(pts)


def test_thinned_static_points_take_a_uniform_prefix_of_each_far_flat_tile():
    """On a saturated floor a camera 2 m up gets every point of the tiles near it and a uniform
    subset of about ``thin_points_per_cell`` per covered pixel of the far ones."""
    grid = np.arange(0.01, 96.0, 0.04)
    gx, gy = np.meshgrid(grid, np.arange(-8.0, 8.0, 0.04), indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(pts)
    lidar_map = LidarMap(sorted_pts, keys, start, 0.04, frozenset(), frozenset(), {}, [])
    from phigenesis.data.records import Boxes, Frame

    rotation = geometry.BODY_FROM_OPENCV
    intrinsics = geometry.intrinsic_matrix(2000.0, 2000.0, 959.5, 639.5)
    ego_from_camera = geometry.make_transform(rotation, [0.0, 0.0, 2.0])
    cal = CameraCalibration("F", 1920, 1280, intrinsics, np.zeros(5), ego_from_camera)
    cam = CameraImage(cal, 0, np.eye(4), None)
    frame = Frame("s", 0, 0, np.eye(4), [cam], None, Boxes.empty())
    whole = static_points_per_camera(frame, lidar_map, ProjectParams(thin=False))[0]
    thinned = static_points_per_camera(frame, lidar_map, ProjectParams())[0]
    near = lambda p: p[:, 0] < 16.0  # noqa: E731
    far_of = lambda p: p[(p[:, 0] > 72.0) & (p[:, 0] < 80.0)]  # noqa: E731
    assert near(thinned).sum() == near(whole).sum()
    assert len(far_of(thinned)) < 0.6 * len(far_of(whole))  # whole levels: at most twice the budget
    # Far away, each kept point stands for the same share of the floor across the road.
    far = thinned[(thinned[:, 0] > 72.0) & (thinned[:, 0] < 80.0)]
    counts = np.histogram(far[:, 1], bins=8, range=(-8.0, 8.0))[0]
    assert counts.min() > 0.7 * counts.mean()


@settings(max_examples=25, deadline=None)
@given(
    tilt_deg=st.floats(0.0, 3.0),
    yaw=st.floats(-3.1, 3.1),
    limit_deg=st.floats(5.0, 9.0),
    seed=st.integers(0, 1000),
)
def test_skipping_tiles_below_the_band_keeps_the_lidar_top_test_exact(
    tilt_deg: float, yaw: float, limit_deg: float, seed: int
):
    """Points of tiles that cannot reach the band's bottom take no part in the test: the result on
    the others equals the test over all points, the ego pitched and rolled."""
    rng = np.random.default_rng(seed)
    ground = rng.uniform([-120, -120, -0.3], [120, 120, 0.3], size=(20000, 3))
    towers = rng.uniform([-120, -120, 0.0], [120, 120, 25.0], size=(60, 3))
    pts = np.concatenate([ground, towers]).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(pts)
    lidar_map = LidarMap(sorted_pts, keys, start, 0.05, frozenset(), frozenset(), {}, [])
    tilt = np.radians(tilt_deg)
    rotation = _yaw(yaw) @ np.array(
        [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]]
    )
    world_from_ego = geometry.make_transform(rotation, [3.0, -2.0, 0.1])
    sensor = geometry.transform_points(world_from_ego, np.array([[1.0, 0.0, 2.0]]))[0]
    tiles = np.arange(len(keys))
    limit, band = np.radians(limit_deg), np.radians(1.5)
    high = tiles_reaching(
        lidar_map.tile_centres(tiles), lidar_map.tile_heights(tiles)[1], sensor, world_from_ego, limit - band
    )
    assert 0 < high.sum() < len(tiles)
    full = seen_past_lidar_top(sorted_pts, sensor, world_from_ego, limit, band, np.radians(0.5))
    tested = np.repeat(high, lidar_map.tile_counts(tiles))
    part = np.ones(len(sorted_pts), bool)
    part[tested] = seen_past_lidar_top(
        sorted_pts[tested], sensor, world_from_ego, limit, band, np.radians(0.5)
    )
    np.testing.assert_array_equal(part, full)


def test_the_tile_skip_counts_the_egos_tilt():
    """Nose down by 3 deg, a far facade top 5.5 deg up in the ego's axes (above a 5 deg field) is
    only 2.5 deg up in the world's, and the nearer wall hiding it 1 deg: both tiles must be tested."""
    pitch = np.radians(3.0)
    pitch_down = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    world_from_ego = geometry.make_transform(pitch_down, [0.0, 0.0, 0.0])
    sensor_ego = np.array([0.0, 0.0, 2.0])

    def ahead(range_m: float, elevation_deg: float, lateral_m: float = 0.0) -> list[float]:
        return [range_m, lateral_m, sensor_ego[2] + range_m * np.tan(np.radians(elevation_deg))]

    ego_points = [ahead(100.0, 5.5)] + [ahead(30.0, 4.0, y) for y in np.linspace(-1, 1, 9)]
    ego_points += [[x, y, 0.0] for x in np.arange(5.0, 120.0, 4.0) for y in (-6.0, 6.0)]
    pts = geometry.transform_points(world_from_ego, np.array(ego_points)).astype(np.float32)
    sorted_pts, keys, start = _tile_sort(pts)
    lidar_map = LidarMap(sorted_pts, keys, start, 0.05, frozenset(), frozenset(), {}, [])
    sensor = geometry.transform_points(world_from_ego, sensor_ego[None])[0]
    limit, band, step = np.radians(5.0), np.radians(1.5), np.radians(0.5)
    full = seen_past_lidar_top(sorted_pts, sensor, world_from_ego, limit, band, step)
    far = np.flatnonzero(np.isclose(sorted_pts[:, 0], pts[0, 0]) & np.isclose(sorted_pts[:, 2], pts[0, 2]))
    assert not full[far].any()  # hidden by the wall the top beams see
    tiles = np.arange(len(keys))
    high = tiles_reaching(
        lidar_map.tile_centres(tiles), lidar_map.tile_heights(tiles)[1], sensor, world_from_ego, limit - band
    )
    tested = np.repeat(high, lidar_map.tile_counts(tiles))
    part = np.ones(len(sorted_pts), bool)
    part[tested] = seen_past_lidar_top(sorted_pts[tested], sensor, world_from_ego, limit, band, step)
    np.testing.assert_array_equal(part, full)
    assert not high.all()
