"""The camera-table kernels (``csrc/camera_rays.c``) against their numpy and OpenCV references:
undistorted pixel rays, ego-frame ray directions and the range view's overlap map, on the real
Waymo calibrations (when the sample file is here) and on synthetic cameras with strong
distortion, including one whose distortion folds back inside the image."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from phigenesis import geometry
from phigenesis.data import camera_tables, native, rangeview
from phigenesis.data.records import CameraCalibration
from tests.test_waymo_real import PANOPTIC

KERNEL = native.load_camera_rays()
needs_kernel = pytest.mark.skipif(KERNEL is None, reason=f"no native kernels: {native.failure_reason()}")


def camera(
    name: str,
    yaw_deg: float,
    width: int,
    height: int,
    focal_px: float,
    distortion: tuple[float, ...] = (0.0,) * 5,
    pitch_deg: float = 0.0,
) -> CameraCalibration:
    """A camera at 1.5 m above the ego origin looking at azimuth ``yaw_deg`` (pitched down
    ``pitch_deg``), principal point off centre, OpenCV ``distortion`` (k1, k2, p1, p2, k3)."""
    k = geometry.intrinsic_matrix(focal_px, 1.02 * focal_px, 0.52 * width, 0.47 * height)
    p = np.radians(pitch_deg)
    pitch = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    body = geometry.rotation_z(np.radians(yaw_deg)) @ pitch
    return CameraCalibration(
        name,
        width,
        height,
        k,
        np.array(distortion, np.float64),
        geometry.make_transform(body @ geometry.BODY_FROM_OPENCV, [0.0, 0.0, 1.5]),
    )


@pytest.fixture(scope="module")
def real_calibrations() -> list[CameraCalibration]:
    """The five cameras of the real Waymo frame (1920 x 1280 and 1920 x 886, k1 ~ 0.04,
    k2 ~ -0.33, tangential ~ 1e-3)."""
    if not PANOPTIC.exists():
        pytest.skip(f"the real Waymo sample {PANOPTIC} is not here")
    from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource

    source = WaymoSource(WaymoConfig(input=str(PANOPTIC)))
    (scene_id,) = source.scene_ids()
    return list(source.load(scene_id).calibrations)


def native_rays(cal: CameraCalibration) -> tuple[np.ndarray, int]:
    """The kernel's (H * W, 3) rays and how many pixels it left unsolved."""
    rays = np.empty((cal.width * cal.height, 3))
    r_max = geometry.max_monotonic_radius(cal.distortion)
    unsolved = KERNEL.undistort_grid(cal.width, cal.height, cal.intrinsics, cal.distortion, r_max, rays)
    return rays, unsolved


@needs_kernel
def test_native_rays_equal_the_reference_on_the_real_waymo_calibrations(real_calibrations) -> None:
    """Worst case over the five cameras: 2.8e-16 normalised units (6e-13 px), every pixel solved."""
    assert len(real_calibrations) == 5
    for cal in real_calibrations:
        rays, unsolved = native_rays(cal)
        reference = camera_tables.undistorted_pixel_rays_reference(cal)
        assert unsolved == 0
        assert np.abs(rays - reference).max() < 1e-15, cal.name
        assert camera_tables.undistortion_residual(cal, rays[:, :2]).max() < 1e-15
        assert np.array_equal(camera_tables.undistorted_pixel_rays(cal), rays)


STRONG = [
    (-0.32, 0.11, 0.002, -0.0015, -0.018),  # wide-angle barrel, folds back at the corners
    (0.25, 0.08, -0.004, 0.003, 0.01),  # pincushion, monotonic everywhere
    (0.04, -0.33, 0.001, -0.0016, 0.0),  # Waymo-like on a wider field: folds back at the corners
    (-0.45, 0.0, 0.001, -0.001, 0.0),  # folds back over 60 % of the image
]


@needs_kernel
@pytest.mark.parametrize("distortion", STRONG)
def test_native_rays_equal_the_reference_under_strong_distortion(distortion) -> None:
    """Where a pixel has an undistorted point (it distorts back within 1e-12) the kernel finds
    it to rounding level: within 1e-13 of the toolkit's Newton solver (4e-14 at |x| = 1.6) and
    within 2e-12 of the
    reference, whose OpenCV points are accepted at a residual of 1e-12 (worst seen 1.7e-12).
    Where none has (beyond the fold of the distortion: the distorted radius exceeds the peak of
    r * radial(r^2)) the kernel gives the reference's result, the Newton solver's last iterate
    (clamped to the monotonic radius): a ray inside the model's field, not a solution."""
    cal = camera("D", 0.0, 320, 240, 170.0, distortion)
    rays, unsolved = native_rays(cal)
    reference = camera_tables.undistorted_pixel_rays_reference(cal)
    newton = geometry.unproject_pixels(geometry.pixel_grid(320, 240), cal.intrinsics, cal.distortion)
    solved = camera_tables.undistortion_residual(cal, rays[:, :2]) <= camera_tables.UNDISTORT_TOLERANCE
    assert unsolved == (~solved).sum()
    assert camera_tables.undistortion_residual(cal, rays[:, :2])[solved].max() < 1e-15
    assert np.abs(rays[solved] - newton[solved]).max() < 1e-13
    assert np.abs(rays[solved] - reference[solved]).max() < 2e-12
    r_max = geometry.max_monotonic_radius(cal.distortion)
    if distortion[0] == 0.25:
        assert solved.all() and r_max == 10.0
    else:
        assert 0.0 < (~solved).mean() < 0.7
        reference_solved = camera_tables.undistortion_residual(cal, reference[:, :2]) <= 1e-12
        assert np.array_equal(reference_solved, solved)
        assert np.abs(rays[~solved] - reference[~solved]).max() < 1e-12
        assert np.hypot(rays[~solved, 0], rays[~solved, 1]).max() <= r_max + 1e-12


@needs_kernel
def test_where_the_distortion_folds_back_the_rays_match_cv2_where_it_converges() -> None:
    """k1 = -0.45: r (1 - 0.45 r^2) peaks at r = 0.861 (distorted radius 0.574), so the outer
    60 % of this wide image has no undistorted point. OpenCV's fixed point (20 iterations)
    converges (its point distorts back within 1e-12) on 26 % of the pixels, where the kernel
    gives its ray to OpenCV's own accuracy (1.6e-12); the kernel solves 40 %, every pixel that
    has a solution, and leaves the rest unsolved."""
    cal = camera("FOLD", 0.0, 320, 240, 170.0, (-0.45, 0.0, 0.001, -0.001, 0.0))
    rays, unsolved = native_rays(cal)
    uv = geometry.pixel_grid(cal.width, cal.height)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-15)
    opencv = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), cal.intrinsics, cal.distortion, None, np.eye(3), np.eye(3), criteria
    ).reshape(-1, 2)
    converged = camera_tables.undistortion_residual(cal, opencv) <= camera_tables.UNDISTORT_TOLERANCE
    solved = camera_tables.undistortion_residual(cal, rays[:, :2]) <= camera_tables.UNDISTORT_TOLERANCE
    assert 0.2 < converged.mean() < 0.3 and 0.35 < solved.mean() < 0.45
    assert not (converged & ~solved).any() and unsolved == (~solved).sum()
    assert np.abs(rays[converged, :2] - opencv[converged]).max() < 2e-12
    r_max = geometry.max_monotonic_radius(cal.distortion)
    assert r_max == pytest.approx(1 / np.sqrt(3 * 0.45))
    distorted_radius = np.hypot(*geometry.distort_normalized(rays[:, :2], cal.distortion).T)
    assert distorted_radius[solved].max() < r_max * (1 - 0.45 * r_max**2) + 5e-3  # tangential terms


def test_rays_on_the_fold_over_sheet_are_not_taken() -> None:
    """Strong tangential terms make the distortion two-to-one near the monotonic radius: two
    pixels of this camera have a second undistorted point, on the fold-over sheet (Jacobian
    determinant < 0). The rays are the ones on the image's own sheet, as the reference's."""
    cal = dataclasses.replace(
        camera("TWO", 0.0, 40, 30, 1.0, (-0.45, 0.2, 0.01, -0.01, -0.05)),
        intrinsics=geometry.intrinsic_matrix(16.78199262, 16.78199262, 19.5, 14.5),
    )
    rays = camera_tables.undistorted_pixel_rays(cal)
    reference = camera_tables.undistorted_pixel_rays_reference(cal)
    solved = camera_tables.undistortion_residual(cal, rays[:, :2]) <= camera_tables.UNDISTORT_TOLERANCE
    assert np.abs(rays[solved] - reference[solved]).max() < 2e-12
    assert np.abs(rays - reference).max() < 1e-10


def test_without_distortion_the_rays_are_the_pinhole_rays() -> None:
    cal = camera("P", 0.0, 40, 30, 35.0)
    rays = camera_tables.undistorted_pixel_rays(cal)
    k = cal.intrinsics
    uv = geometry.pixel_grid(40, 30)
    assert np.allclose(rays[:, 1], (uv[:, 1] - k[1, 2]) / k[1, 1], rtol=0, atol=1e-15)
    assert np.allclose(rays[:, 0], (uv[:, 0] - k[0, 2]) / k[0, 0], rtol=0, atol=1e-15)


def distorted_rig() -> list[CameraCalibration]:
    """Six distorted cameras around the car, overlapping, one across the rear (azimuth +-pi)
    and one pitched down."""
    d = (-0.3, 0.09, 0.001, -0.002, -0.01)
    return [
        camera("F", 0.0, 96, 64, 60.0, d),
        camera("FL", 55.0, 96, 64, 60.0, d),
        camera("FR", -55.0, 80, 48, 52.0, d, pitch_deg=12.0),
        camera("BL", 125.0, 96, 64, 60.0, d),
        camera("BR", -125.0, 96, 64, 60.0, d),
        camera("B", 180.0, 96, 64, 60.0, (0.0,) * 5),
    ]


def overlap_both_ways(cals: list[CameraCalibration]) -> None:
    """The kernel's owner and coverage of every view equal the reference's."""
    layout = rangeview.range_view_layout(cals)
    by_name = {c.name: c for c in cals}
    ordered = [by_name[n] for n in layout.camera_names]
    shared = 0
    for k, cal in enumerate(ordered):
        rays = rangeview.camera_rays_ego(cal).reshape(-1, 3)
        owner, count = rangeview._overlap(k, rays, ordered, layout.views)
        owner_ref, count_ref = rangeview._overlap_reference(k, rays, ordered, layout.views)
        assert np.array_equal(owner, owner_ref) and np.array_equal(count, count_ref), cal.name
        # From the camera-frame rays, the directions made on the way (what the layout does).
        owner_cam, count_cam = rangeview._overlap(k, camera_tables.pixel_rays_cam(cal), ordered, layout.views)
        assert np.array_equal(owner_cam, owner_ref) and np.array_equal(count_cam, count_ref), cal.name
        view = layout.views[k]
        assert np.array_equal(layout.owner[view.rows, view.cols].ravel(), owner_ref)
        assert np.array_equal(layout.coverage[view.rows, view.cols].ravel(), count_ref)
        shared += int((count > 1).sum())
    assert shared > 0


@needs_kernel
def test_native_ego_rays_and_overlap_equal_the_reference_on_a_distorted_rig() -> None:
    cals = distorted_rig()
    for cal in cals:
        np.testing.assert_array_max_ulp(
            rangeview.camera_rays_ego(cal), rangeview.camera_rays_ego_reference(cal), maxulp=1
        )
    overlap_both_ways(cals)


@needs_kernel
def test_native_ego_rays_and_overlap_equal_the_reference_on_the_real_rig(real_calibrations) -> None:
    for cal in real_calibrations:
        np.testing.assert_array_max_ulp(
            rangeview.camera_rays_ego(cal), rangeview.camera_rays_ego_reference(cal), maxulp=1
        )
    overlap_both_ways(real_calibrations)


def test_the_layout_without_native_kernels_is_the_layout_with_them(monkeypatch) -> None:
    cals = distorted_rig()

    def layout_and_rays() -> tuple:
        camera_tables.clear()
        rangeview._layout.cache_clear()
        rangeview._rays.cache_clear()
        layout = rangeview.range_view_layout(cals)
        return layout, [rangeview.camera_rays_ego(c).copy() for c in cals]

    layout, rays = layout_and_rays()
    monkeypatch.setattr(native, "load_camera_rays", lambda: None)
    monkeypatch.setattr(rangeview, "load_camera_rays", lambda: None)
    plain, plain_rays = layout_and_rays()
    monkeypatch.undo()
    camera_tables.clear()
    rangeview._layout.cache_clear()
    rangeview._rays.cache_clear()
    for view, plain_view in zip(layout.views, plain.views, strict=True):
        a, b = dataclasses.astuple(view), dataclasses.astuple(plain_view)
        assert a[:5] == b[:5] and np.allclose(a[5:], b[5:], rtol=0, atol=1e-12)
    assert np.array_equal(layout.owner, plain.owner) and np.array_equal(layout.coverage, plain.coverage)
    for a, b in zip(rays, plain_rays, strict=True):
        np.testing.assert_array_max_ulp(a, b, maxulp=1)
    shared = layout.coverage >= 2
    assert shared.any() and (layout.owner[shared] != layout.view_index()[shared]).any()


def test_a_distorted_calibration_copy_gets_its_own_rays() -> None:
    """The per-calibration cache keys on the distortion: changing it gives new rays."""
    cal = camera("K", 0.0, 40, 30, 35.0, (-0.2, 0.05, 0.0, 0.0, 0.0))
    other = dataclasses.replace(cal, distortion=np.array([0.1, 0.0, 0.0, 0.0, 0.0]))
    a, b = camera_tables.pixel_rays_cam(cal), camera_tables.pixel_rays_cam(other)
    assert np.abs(a - b).max() > 1e-3


@needs_kernel
def test_native_ego_body_depth_equals_the_reference_inside_across_and_along_the_boxes() -> None:
    """Three boxes around a camera pitched down 40 degrees: one holds the camera (entry depth
    0), one is straddled by the image plane, one has faces parallel to the pixel rays' axes (a
    ray along a slab's plane: 0/0 in the slab test). The one-pass kernel equals the numpy
    reference and the one-box-a-pass kernel (ray_box.c) exactly."""
    cal = camera("DOWN", 0.0, 64, 48, 40.0, (-0.2, 0.05, 0.001, 0.0, 0.0), pitch_deg=40.0)
    boxes = [
        {"center_ego": [0.0, 0.0, 1.5], "size_lwh": [0.4, 0.4, 0.4]},  # holds the camera
        {"center_ego": [2.0, 0.0, 0.6], "size_lwh": [3.0, 2.0, 1.2]},
        {"center_ego": [1.0, 1.0, 1.0], "size_lwh": [2.0, 2.0, 1.0]},  # a face through the camera
    ]
    rays = camera_tables.undistorted_pixel_rays(cal)
    reference = camera_tables.ego_body_depth_from_rays(cal, boxes, rays)
    fast = camera_tables.ego_body_depth_native(cal, boxes, rays)
    assert fast is not None and np.array_equal(fast, reference)
    assert (reference == 0).all()  # the camera is inside the first box
    outside = boxes[1:]
    reference = camera_tables.ego_body_depth_from_rays(cal, outside, rays)
    fast = camera_tables.ego_body_depth_native(cal, outside, rays)
    hit = np.isfinite(reference)
    assert 0.1 < hit.mean() < 1.0 and (reference[hit] < 1e-6).any() and (reference[hit] > 0.5).any()
    assert np.array_equal(fast, reference)
    one_box_a_pass = np.full((cal.height, cal.width), np.inf, np.float32)
    camera_from_ego = geometry.invert_transform(cal.ego_from_camera)
    for b in outside:
        box_from_camera = geometry.invert_transform(
            camera_from_ego @ geometry.make_transform(np.eye(3), b["center_ego"])
        )
        half = 0.5 * np.asarray(b["size_lwh"], np.float64)
        native.load_ray_box().near_side(rays, box_from_camera, half, one_box_a_pass)
    assert np.array_equal(fast, one_box_a_pass)


@needs_kernel
@pytest.mark.parametrize("distortion", STRONG)
def test_native_point_unprojection_equals_the_toolkit_newton_solver(distortion) -> None:
    """Pixels along and beyond the border of a strongly distorted camera (the range view's
    azimuth ranges sample the border every half pixel): rays within 1e-13 of
    geometry.unproject_pixels where one exists, its last iterate where none does."""
    cal = camera("D", 0.0, 320, 240, 170.0, distortion)
    t = np.linspace(-0.5, 320.5, 1283)
    uv = np.concatenate([np.stack([t, np.full_like(t, v)], 1) for v in (-0.5, 60.0, 239.5, 250.0)])
    rays = rangeview.unproject_points(uv, cal)
    reference = geometry.unproject_pixels(uv, cal.intrinsics, cal.distortion)
    k = cal.intrinsics
    y = (uv[:, 1] - k[1, 2]) / k[1, 1]
    target = np.stack([(uv[:, 0] - k[0, 2]) / k[0, 0], y], axis=-1)
    solved = np.abs(geometry.distort_normalized(rays[:, :2], cal.distortion) - target).max(axis=1) <= 1e-12
    assert np.abs(rays[solved] - reference[solved]).max() < 1e-13
    assert np.abs(rays[~solved] - reference[~solved]).max(initial=0.0) < 1e-12


@needs_kernel
def test_native_ray_components_equal_the_reference_nan_rays_included() -> None:
    cal = camera("C", 30.0, 96, 64, 60.0, (-0.3, 0.09, 0.001, -0.002, -0.01))
    rays = camera_tables.undistorted_pixel_rays(cal).copy()
    rays[5 * 96 + 7, :2] = np.nan  # row 5, column 7
    fast = camera_tables.ray_components_from_rays(cal, rays)
    slow = camera_tables.ray_components_reference(cal, rays)
    for name in ("x", "y", "norm", "column_x", "row_y"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name), equal_nan=True), name
    assert np.isnan(fast.row_y[:, 5]).all() and np.isnan(fast.column_x[:, 7]).all()
    assert np.isfinite(fast.row_y[:, 6]).all() and np.isfinite(fast.column_x[:, 8]).all()
