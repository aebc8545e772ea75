"""The depth projection's native kernels against their numpy paths.

- ``camera_points.c`` (:func:`project.camera_pixels`) against :func:`project.camera_pixels_reference`:
  a distorted 1920 x 1280 camera rotated off every axis, points in front, behind, beyond the
  range, outside the view and on its border, an ego-body map and a vehicles' far-side map.
- ``plane_fits.c`` (:func:`project.fit_pixels`) against :func:`project.fit_occupied_numpy`:
  planes with range noise, pixels straddling a depth edge, lone points, the image's border.
"""

from __future__ import annotations

import numpy as np
import pytest

from phigenesis import geometry
from phigenesis.data import native
from phigenesis.data.records import CameraCalibration, CameraImage
from phigenesis.data.stages import aggregate, project

PARAMS = project.ProjectParams()


def _needs_kernels() -> None:
    if native.load_camera_points() is None or native.load_plane_fits() is None:
        pytest.skip(f"native kernels not built here: {native.failure_reason()}")


def _unit(q: list[float]) -> np.ndarray:
    return np.asarray(q) / np.linalg.norm(q)


def _distorted_camera() -> CameraImage:
    """A 1920 x 1280 camera with Waymo-like distortion, 1.7 m above a world origin far from
    zero (float32 world coordinates lose precision there), looking along a tilted direction."""
    cal = CameraCalibration(
        "FRONT",
        1920,
        1280,
        geometry.intrinsic_matrix(2055.0, 2052.0, 951.3, 641.7),
        np.array([-0.035, -0.012, 0.0004, -0.0008, 0.006]),
        geometry.make_transform(geometry.BODY_FROM_OPENCV, [1.5, 0.1, 1.7]),
    )
    world_from_ego = geometry.make_transform(
        geometry.quaternion_to_matrix(_unit([0.96, 0.02, -0.03, 0.27])),
        [1834.2, -912.6, 12.3],
    )
    return CameraImage(cal, 0, world_from_ego @ cal.ego_from_camera, None)


def _points_around(camera: CameraImage, n: int, seed: int) -> project.CameraPoints:
    """``n`` world points around the camera: most in its view at 0.2 to 150 m, some behind it,
    some just past the image's border."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(n, 3)) * [0.6, 0.4, 1.0]
    direction[: n // 10, 2] *= -1.0  # behind the camera
    p_cam = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0.2, 150.0, (n, 1))
    world = geometry.transform_points(camera.world_from_camera, p_cam).astype(np.float32)
    return project.CameraPoints(world, np.ones(n, np.uint8), np.full(n, 0.02, np.float32))


@pytest.mark.parametrize("maps", ["none", "ego", "ego_and_vehicles"])
def test_native_camera_pixels_equal_the_numpy_reference(maps: str) -> None:
    _needs_kernels()
    camera = _distorted_camera()
    points = _points_around(camera, 400_000, seed=1)
    h, w = 1280, 1920
    rng = np.random.default_rng(2)
    ego = far = None
    if maps != "none":
        ego = np.full((h, w), np.inf, np.float32)
        ego[1000:, :] = rng.uniform(0.5, 3.0, (h - 1000, w)).astype(np.float32)
    if maps == "ego_and_vehicles":
        far = np.full((h, w), np.inf, np.float32)
        far[400:800, 300:1200] = rng.uniform(5.0, 40.0, (400, 900)).astype(np.float32)
    index, uv, z, pixel, counts = project.camera_pixels(camera, points, PARAMS, ego, far)
    r_index, r_uv, r_z, r_pixel, r_counts = project.camera_pixels_reference(camera, points, PARAMS, ego, far)
    assert r_counts["projected"] > 30_000
    if maps == "ego_and_vehicles":
        assert r_counts["behind_ego_body"] > 1_000 and r_counts["behind_vehicles"] > 1_000
    # The float32 rotation may round its last bit otherwise than BLAS: a point on a limit may
    # fall the other way, nothing more.
    assert len(set(index) ^ set(r_index)) <= 5
    for name in counts:
        assert abs(counts[name] - r_counts[name]) <= 5, (name, counts, r_counts)
    common, at, r_at = np.intersect1d(index, r_index, return_indices=True)
    assert len(common) >= len(r_index) - 5
    np.testing.assert_allclose(uv[at], r_uv[r_at], rtol=0, atol=1e-3)
    np.testing.assert_allclose(z[at], r_z[r_at], rtol=2e-7, atol=0)
    assert np.count_nonzero(pixel[at] != r_pixel[r_at]) <= 5  # a position on a pixel's border
    assert index.dtype == np.int64 and uv.dtype == np.float64 and z.dtype == np.float32
    assert np.all(np.diff(index) > 0)  # in the points' order


def test_native_camera_pixels_drop_points_behind_and_beyond_the_distortion_fold() -> None:
    _needs_kernels()
    camera = _distorted_camera()
    # In front on the axis (kept), behind the camera, on the camera plane, nearer than
    # min_depth_m and beyond max_range_m (all dropped).
    p_cam = np.array(
        [[0.0, 0.0, 10.0], [0.0, 0.0, -10.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.3], [0.0, 0.0, 130.0]]
    )
    world = geometry.transform_points(camera.world_from_camera, p_cam).astype(np.float32)
    points = project.CameraPoints(world, np.ones(5, np.uint8), np.full(5, 0.02, np.float32))
    index, uv, z, pixel, counts = project.camera_pixels(camera, points, PARAMS)
    assert list(index) == [0] and counts["projected"] == 1
    cal = camera.calibration
    # The principal point, to the float32 rounding of world coordinates 2 km from the origin.
    assert uv[0] == pytest.approx(cal.intrinsics[:2, 2], abs=0.02)
    assert z[0] == pytest.approx(10.0, abs=1e-4)
    assert pixel[0] == round(cal.intrinsics[1, 2]) * 1920 + round(cal.intrinsics[0, 2])
    empty = project.CameraPoints(world[:0], np.zeros(0, np.uint8), np.zeros(0, np.float32))
    assert len(project.camera_pixels(camera, empty, PARAMS)[0]) == 0


def _fit_inputs(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Visible points of a 120 x 160 image: a slanted plane with 1 cm range noise over most of
    it, a nearer surface over a block (its edge pixels hold both), lone far points, and points
    in the border rows and columns; with the depth of the point nearest each pixel's centre."""
    h, w = 120, 160
    rng = np.random.default_rng(seed)
    n = 120_000
    uv = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (n, 2))
    z = 20.0 + 0.05 * uv[:, 0] + 0.1 * uv[:, 1] + rng.normal(0.0, 0.01, n)
    block = (uv[:, 0] > 60.3) & (uv[:, 0] < 90.7) & (uv[:, 1] > 30.2) & (uv[:, 1] < 70.6)
    z[block] = 8.0 + rng.normal(0.0, 0.01, block.sum())
    lone = rng.uniform(size=n) < 0.002
    z[lone] = 90.0
    z = z.astype(np.float32)
    pixel = project._pixel_index(uv, 1, w, h)
    reference = np.full(h * w, np.inf, np.float32)
    np.minimum.at(reference, pixel, z)
    return pixel, uv, z, reference


@pytest.mark.parametrize("window", [0, 1, 2])
def test_native_plane_fits_equal_the_numpy_fits_exactly(window: int) -> None:
    _needs_kernels()
    pixel, uv, z, reference = _fit_inputs(seed=window)
    shape = (120, 160)
    params = project.ProjectParams(fit_window_px=window)
    fast = project.fit_pixels(pixel, uv, z, shape, reference, params)
    occupied, depth, count, mixed = project.fit_occupied_numpy(pixel, uv, z, shape, reference, params)
    assert 100 < np.count_nonzero(mixed) < len(occupied) // 10  # the block's edges and lone points
    assert np.isfinite(depth).mean() > 0.5
    np.testing.assert_array_equal(np.flatnonzero(fast.count), occupied)
    # The same arithmetic in the same order: the same doubles.
    np.testing.assert_array_equal(fast.depth_m[occupied], depth)
    np.testing.assert_array_equal(fast.count[occupied], count)
    np.testing.assert_array_equal(fast.mixed[occupied], mixed)
    assert np.all(np.isnan(np.delete(fast.depth_m, occupied)))
    # And the plane's depth at the centres of unmixed pixels is the surface's, within the noise.
    rows, cols = np.divmod(occupied, 160)
    truth = np.where(
        (cols > 60) & (cols < 91) & (rows > 30) & (rows < 71), 8.0, 20.0 + 0.05 * cols + 0.1 * rows
    )
    good = ~mixed & np.isfinite(depth) & (count >= 4)
    assert np.median(np.abs(depth[good] - truth[good])) < 0.01


def test_voxel_merge_in_stages_equals_merging_at_once() -> None:
    rng = np.random.default_rng(3)
    # Ten chunks of one surface, each already down-sampled at 2 cm like the aggregation's.
    chunks = [
        aggregate.voxel_downsample(
            (rng.uniform([0, 0, 0], [4, 3, 0.1], (20_000, 3)) + np.array([812.0, -45.0, 2.0])).astype(
                np.float32
            ),
            0.02,
        )
        for _ in range(10)
    ]
    at_once = aggregate.voxel_downsample(np.concatenate(chunks), 0.02)
    # Weights of 1: the same keys, order and sums as voxel_downsample.
    plain, weights = aggregate.voxel_merge([(c, None) for c in chunks], 0.02)
    np.testing.assert_array_equal(plain, at_once)
    assert weights.sum() == sum(len(c) for c in chunks)
    staged = aggregate.voxel_merge([(c, None) for c in chunks[:4]], 0.02)
    staged = aggregate.voxel_merge([staged] + [(c, None) for c in chunks[4:8]], 0.02)
    staged_points, staged_weights = aggregate.voxel_merge([staged] + [(c, None) for c in chunks[8:]], 0.02)
    np.testing.assert_array_equal(staged_weights, weights)
    # Each merged centroid was stored as float32 once more: within a few float32 steps at 800 m.
    np.testing.assert_allclose(staged_points, at_once, rtol=0, atol=2e-4)


def test_column_wise_voxel_keys_equal_the_reference() -> None:
    rng = np.random.default_rng(4)
    points = (rng.normal(size=(50_000, 3)) * [500.0, 500.0, 20.0]).astype(np.float32)
    for voxel_m in (0.02, 0.05, 0.3):
        np.testing.assert_array_equal(
            aggregate._voxel_keys(points, voxel_m), aggregate._voxel_keys_reference(points, voxel_m)
        )


def test_dense_pixels_keep_their_front_band_thinned_to_the_cap() -> None:
    """A pixel of a far, dense surface with a sparse nearer one in front (a pole before a
    wall): points behind a pixel's front band go, the band keeps about ``max_per_pixel``, and
    pixels under the cap keep every point; native and numpy keep the same points."""
    _needs_kernels()
    camera = _distorted_camera()
    rng = np.random.default_rng(5)
    # Wall at 60 m: ~40 points a pixel over 20 x 20 pixels around the principal point; a nearer
    # surface at 20 m over its left half, 1 point in 4 pixels; a sparse patch elsewhere.
    cal = camera.calibration
    centre = np.asarray(cal.intrinsics[:2, 2])
    left, right, far = np.array([-10.0, 10.0]), np.array([0.0, 10.0]), np.array([200.0, 240.0])
    wall_uv = rng.uniform(centre - 10, centre + 10, (16_000, 2))
    front_uv = rng.uniform(centre + left[0], centre + right, (50, 2))
    sparse_uv = rng.uniform(centre + far[0], centre + far[1], (400, 2))
    uv = np.concatenate([wall_uv, front_uv, sparse_uv])
    depth = np.concatenate([np.full(16_000, 60.0), np.full(50, 20.0), np.full(400, 30.0)])
    rays = geometry.unproject_pixels(uv, cal.intrinsics, cal.distortion)
    world = geometry.transform_points(camera.world_from_camera, rays * depth[:, None]).astype(np.float32)
    points = project.CameraPoints(world, np.ones(len(world), np.uint8), np.full(len(world), 0.02, np.float32))
    params = project.ProjectParams(max_points_per_pixel=8)
    index, _, z, pixel, counts = project.camera_pixels(camera, points, params)
    r_index, *_, r_counts = project.camera_pixels_reference(camera, points, params)
    assert len(set(index) ^ set(r_index)) <= 5 and counts["thinned_in_pixels"] > 10_000
    assert abs(counts["thinned_in_pixels"] - r_counts["thinned_in_pixels"]) <= 5
    # Every point of the sparse patch stays; no wall point stays in a pixel the front covers.
    assert np.all(np.isin(np.arange(16_050, 16_450), index))
    front_pixels = set(pixel[z < 30.0])
    assert all(p not in front_pixels for p in pixel[z > 50.0])
    # The wall's own pixels keep about 8 of their ~40 points.
    per_pixel = np.bincount(pixel[z > 50.0])
    per_pixel = per_pixel[per_pixel > 0]
    assert 6.0 < per_pixel.mean() < 10.0, per_pixel.mean()
