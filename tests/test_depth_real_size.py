"""The optimised depth stages equal their plain reference functions at Waymo's full size.

One synthetic scene at full resolution (1920 x 1280 FRONT camera, geometry only: no image is
rendered), its 128 x 2650 LiDAR aggregated over 3 frames: the FRONT camera's sparse depth from
:func:`project.project_camera` (plane fits on the occupied pixels only, the splat test's
occluders and the edge bands on cropped rectangles, per-pixel values on the pixels that take a
point) against :func:`project.project_camera_reference` (every step over the whole image); the
moving vehicles' far sides (:func:`project.vehicle_far_depth`, footprint only, native kernel or
numpy) against :func:`project.vehicle_far_depth_reference` (whole image for a box beside the
camera); the aggregation's box test on a grid against every box against every point.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data import camera_tables, native
from phigenesis.data.ego_body import WAYMO_PACIFICA_BOXES
from phigenesis.data.records import Boxes, Frame
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.data.stages import project
from phigenesis.data.stages.aggregate import (
    AggregateParams,
    aggregate_scene,
    box_points_at_times,
    box_points_at_times_reference,
    in_ego_body,
)
from phigenesis.data.stages.projection import occluders

PARAMS = project.ProjectParams()


@pytest.fixture(scope="module")
def full_size() -> tuple[Frame, project.LidarMap]:
    # A 128 x 2650 LiDAR (about Waymo's top LiDAR's columns, twice its beams).
    lidar = LidarSpec(beams=128, columns=2650)
    config = SyntheticConfig(scenes=1, frames=3, seed=0, height=1280, width=1920, lidar=lidar)
    scene = SyntheticScene(config, 0).scene()
    lidar_map = aggregate_scene(scene, AggregateParams(voxel_m=0.02, outlier_neighbors=0))
    frame = scene.frames.geometry(1)
    frame.cameras = frame.cameras[:1]  # FRONT, 1920 x 1280
    return frame, lidar_map


def test_full_size_camera_sparse_depth_equals_the_reference(
    full_size: tuple[Frame, project.LidarMap],
) -> None:
    frame, lidar_map = full_size
    camera = frame.cameras[0]
    assert (camera.calibration.width, camera.calibration.height) == (1920, 1280)
    static = project.static_points_per_camera(frame, lidar_map, PARAMS)[0]
    points = project.scene_points(frame, camera, lidar_map, PARAMS, static)
    ego = project.ego_body_depth(camera, lidar_map.ego_boxes)
    fast, counts = project.project_camera(camera, points, PARAMS, ego)
    slow, slow_counts = project.project_camera_reference(camera, points, PARAMS, ego)
    assert counts == slow_counts
    assert counts["projected"] > 50_000
    known = slow.sparse_m > 0
    assert known.sum() > 10_000
    np.testing.assert_array_equal(fast.sparse_m > 0, known)
    # The moments are summed in another order: depths agree to float32 rounding.
    np.testing.assert_allclose(fast.sparse_m, slow.sparse_m, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(fast.sparse_confidence, slow.sparse_confidence)
    np.testing.assert_array_equal(fast.sparse_origin, slow.sparse_origin)


def test_occluder_depth_on_cropped_rectangles_equals_the_whole_image() -> None:
    rng = np.random.default_rng(5)
    h, w = 300, 400
    for n in (1, 50, 3000):
        rows, cols = rng.integers(40, 200, n), rng.integers(0, w, n)
        pixel = rows * w + cols
        z = rng.uniform(1.0, 80.0, n).astype(np.float32)
        radius = rng.choice([0, 1, 3, 12], n)
        fast = project.occluder_depth(pixel, z, radius, (h, w))
        np.testing.assert_array_equal(fast, project.occluder_depth_reference(pixel, z, radius, (h, w)))
        assert np.isfinite(fast).sum() >= len(np.unique(pixel))


def test_edge_bands_on_the_known_box_equal_the_whole_image() -> None:
    """Depth-edge and silhouette bands computed on the known pixels' bounding box equal the
    whole-image references, known pixels touching the image's border or not."""
    rng = np.random.default_rng(2)
    h, w = 240, 320
    rgb = rng.integers(0, 256, (h, w, 3), np.uint8)
    rgb[:, 150:] //= 4  # a strong vertical image edge
    for rows, cols in (
        (slice(100, 200), slice(40, 300)),
        (slice(0, h), slice(0, 90)),
        (slice(5, 6), slice(7, 8)),
    ):
        depth = np.zeros((h, w), np.float32)
        patch = depth[rows, cols]
        patch[...] = rng.choice([5.0, 5.2, 30.0], patch.shape) * (rng.random(patch.shape) < 0.3)
        for band, near in ((4, None), (2, 6), (0, None)):
            np.testing.assert_array_equal(
                project.depth_edge_band(depth, band, 0.1, 0.3, 0.05, near),
                project.depth_edge_band_reference(depth, band, 0.1, 0.3, 0.05, near),
            )
        np.testing.assert_array_equal(
            project.silhouette_pixels(rgb, depth, 150.0),
            project.silhouette_pixels_reference(rgb, depth, 150.0),
        )
    assert project.depth_edge_band(np.zeros((h, w)), 4, 0.1, 0.3).sum() == 0


def _beside_camera(frame: Frame, camera_world: np.ndarray) -> Boxes:
    """A moving car whose box straddles the camera's image plane (2 m to its right, from 3 m
    behind to 2 m ahead), and one 15 m ahead."""
    axes = camera_world[:3, :3]
    centres = [
        camera_world[:3, 3] + axes @ np.array([2.5, 0.3, -0.5]),
        camera_world[:3, 3] + axes @ np.array([0.5, 0.5, 15.0]),
    ]
    forward = axes @ np.array([0.0, 0.0, 1.0])
    yaw = float(np.arctan2(forward[1], forward[0]))
    return Boxes(
        track_id=["beside", "ahead"],
        class_id=np.array([tx.CAR, tx.CAR], np.uint8),
        center_world=np.array(centres),
        size_lwh=np.array([[5.0, 2.0, 1.8], [4.5, 1.9, 1.6]]),
        yaw_world=np.array([yaw, yaw]),
        velocity_world=np.array([[3.0, 0.0, 0.0], [5.0, 1.0, 0.0]]),
        status=np.zeros(2, np.uint8),
        instance_id=np.array([1, 2], np.uint16),
        num_lidar_points=np.full(2, -1, np.int32),
    )


@pytest.mark.parametrize("kernel", ["native", "numpy"])
def test_vehicle_far_depth_on_the_footprint_equals_the_whole_image_reference(
    full_size: tuple[Frame, project.LidarMap], kernel: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    frame, _ = full_size
    camera = frame.cameras[0]
    boxes = _beside_camera(frame, camera.world_from_camera)
    frame = dataclasses.replace(frame, boxes=boxes)
    rays = project.pixel_rays(camera)
    tracks = frozenset(boxes.track_id)
    if kernel == "numpy":
        monkeypatch.setattr(occluders, "load_ray_box", lambda: None)
    elif native.load_ray_box() is None:
        pytest.skip(f"native kernels not built here: {native.failure_reason()}")
    fast = project.vehicle_far_depth(frame, camera, tracks, PARAMS, rays)
    slow = project.vehicle_far_depth_reference(frame, camera, tracks, PARAMS, rays)
    assert fast.dtype == np.float32 and fast.shape == (1280, 1920)
    hit = np.isfinite(slow)
    assert 0.01 < hit.mean() < 0.9  # both boxes are in view
    np.testing.assert_array_equal(np.isfinite(fast), hit)
    # The kernel sums the rotation's products in its own order: float32 rounding at most.
    np.testing.assert_allclose(fast[hit], slow[hit], rtol=1e-6, atol=0)


def test_footprint_pixels_hold_every_ray_in_the_bounds() -> None:
    """Rows and columns from the per-calibration ray extents cover every pixel whose ray lies in
    the given bounds, on a strongly distorted camera (the extents are computed once)."""
    config = SyntheticConfig(scenes=1, frames=1, seed=3, height=96, width=160)
    cal = SyntheticScene(config, 0).calibrations[0]
    cal = dataclasses.replace(cal, distortion=np.array([-0.3, 0.1, 0.001, -0.002, 0.0]))
    camera_tables.clear()
    before = camera_tables.COMPUTED["ray_extents"]
    rays = camera_tables.pixel_rays_cam(cal)
    rng = np.random.default_rng(0)
    for _ in range(50):
        x0, y0 = rng.uniform(-1.0, 0.8, 2)
        bounds = ((x0, x0 + rng.uniform(0.01, 0.5)), (y0, y0 + rng.uniform(0.01, 0.5)))
        inside = (
            (rays[:, 0] >= bounds[0][0])
            & (rays[:, 0] <= bounds[0][1])
            & (rays[:, 1] >= bounds[1][0])
            & (rays[:, 1] <= bounds[1][1])
        ).reshape(cal.height, cal.width)
        region = camera_tables.footprint_pixels(cal, *bounds)
        if region is None:
            assert not inside.any()
            continue
        mask = np.zeros_like(inside)
        mask[region] = True
        assert not (inside & ~mask).any()
    assert camera_tables.COMPUTED["ray_extents"] == before + 1


def test_normalized_footprint_of_a_box_behind_and_across_the_camera() -> None:
    corners = 0.5 * np.array([4.0, 2.0, 2.0]) * geometry.BOX_CORNER_SIGNS
    assert project.normalized_footprint(corners - np.array([0.0, 0.0, 5.0])) is None  # wholly behind
    (x0, x1), (y0, y1) = project.normalized_footprint(corners + np.array([0.0, 0.0, 5.0]))
    # Nearest face at z = 4 m: x from -2/4 to 2/4, y from -1/4 to 1/4.
    np.testing.assert_allclose([x0, x1, y0, y1], [-0.5, 0.5, -0.25, 0.25])
    (x0, x1), _ = project.normalized_footprint(corners + np.array([3.0, 0.0, 0.5]))
    assert x0 > 0 and x1 > 1e5  # reaches the image plane: unbounded to the right only


def test_box_points_by_x_slab_equal_every_box_against_every_point() -> None:
    """The aggregation's box test on x-sorted slabs against the all-pairs reference, on a
    Waymo-sized frame: 200k points, 120 moving boxes (some overlapping)."""
    rng = np.random.default_rng(11)
    n, m = 200_000, 120
    points = np.column_stack([rng.uniform(-75, 75, n), rng.uniform(-75, 75, n), rng.uniform(-2, 4, n)])
    dt = rng.uniform(-0.05, 0.05, n)
    centres = np.column_stack([rng.uniform(-60, 60, m), rng.uniform(-60, 60, m), rng.uniform(0, 1.5, m)])
    centres[1] = centres[0] + [1.0, 0.5, 0.0]  # overlapping: the first box holding a point wins
    boxes = Boxes(
        track_id=[f"t{i}" for i in range(m)],
        class_id=np.full(m, tx.CAR, np.uint8),
        center_world=centres,
        size_lwh=np.column_stack([rng.uniform(0.5, 12, m), rng.uniform(0.5, 3, m), rng.uniform(1, 4, m)]),
        yaw_world=rng.uniform(-np.pi, np.pi, m),
        velocity_world=np.column_stack([rng.uniform(-15, 15, (m, 2)), np.zeros(m)]),
        status=np.zeros(m, np.uint8),
        instance_id=np.arange(1, m + 1).astype(np.uint16),
        num_lidar_points=np.full(m, -1, np.int32),
    )
    for args in ((1.1, 0.15, None), (1.0, 0.0, 0.1)):
        fast, fast_local = box_points_at_times(points, dt, boxes, *args)
        slow, slow_local = box_points_at_times_reference(points, dt, boxes, *args)
        assert (slow >= 0).sum() > 3_000
        np.testing.assert_array_equal(fast, slow)
        np.testing.assert_array_equal(fast_local, slow_local)


def test_ego_body_test_equals_points_in_box_at_yaw_zero() -> None:
    """The aggregation's ego-body test (axis-aligned boxes, no matrix product) against
    ``geometry.points_in_box`` at yaw 0, on a Waymo-sized sweep around the Pacifica's body."""
    rng = np.random.default_rng(4)
    points = rng.uniform([-3, -2, -0.5], [6, 2, 2.5], (300_000, 3)).astype(np.float32)
    want = np.zeros(len(points), bool)
    for b in WAYMO_PACIFICA_BOXES:
        want |= geometry.points_in_box(points, b["center_ego"], b["size_lwh"], 0.0, 0.1)
    got = in_ego_body(points, WAYMO_PACIFICA_BOXES, 0.1)
    assert 0.1 < want.mean() < 0.9
    np.testing.assert_array_equal(got, want)


def test_border_tables_are_computed_once_per_calibration(full_size: tuple[Frame, project.LidarMap]) -> None:
    frame, _ = full_size
    camera = frame.cameras[0]
    camera_tables.clear()
    before = dict(camera_tables.COMPUTED)
    bounds = [project.normalized_bounds(camera) for _ in range(3)]
    wedges = [project.camera_wedge(camera) for _ in range(3)]
    assert bounds[0] == bounds[2] and wedges[0] == wedges[2]
    (x0, x1), (y0, y1) = bounds[0]
    assert x0 < -0.5 < 0.5 < x1 and y0 < -0.3 < 0.3 < y1  # a ~50 degree wide, 1920 x 1280 view
    for kind in ("normalized_bounds 0.05", "wedge_border_rays"):
        assert camera_tables.COMPUTED[kind] == before.get(kind, 0) + 1


def test_native_ego_body_depth_equals_the_numpy_reference() -> None:
    """The ego body's depth from the native ray-box kernel against
    ``camera_tables.ego_body_depth_from_rays``, on a full-size camera tilted down at the Waymo
    Pacifica's body (so that a good share of its rays meet it)."""
    if native.load_ray_box() is None:
        pytest.skip(f"native kernels not built here: {native.failure_reason()}")
    config = SyntheticConfig(scenes=1, frames=1, seed=0, height=1280, width=1920)
    cal = SyntheticScene(config, 0).calibrations[0]
    c, s = np.cos(np.radians(-35.0)), np.sin(np.radians(-35.0))
    # About the camera's x axis: the optical axis turns 35 degrees down (+y in OpenCV axes).
    tilt = geometry.make_transform(np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), np.zeros(3))
    cal = dataclasses.replace(cal, ego_from_camera=cal.ego_from_camera @ tilt)
    rays = camera_tables.undistorted_pixel_rays(cal)
    slow = camera_tables.ego_body_depth_from_rays(cal, WAYMO_PACIFICA_BOXES, rays)
    fast = camera_tables.ego_body_depth_native(cal, WAYMO_PACIFICA_BOXES, rays)
    assert fast is not None and fast.dtype == np.float32
    hit = np.isfinite(slow)
    assert 0.05 < hit.mean() < 0.95
    np.testing.assert_array_equal(np.isfinite(fast), hit)
    np.testing.assert_allclose(fast[hit], slow[hit], rtol=1e-6, atol=0)
