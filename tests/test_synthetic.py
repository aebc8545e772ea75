"""Tests for the synthetic source: its truth is self-consistent, exact at any time, deterministic.

Frames are rendered once per module at the tiny size of ``tests.conftest.tiny_config`` (60 x 90
images, a 16-beam LiDAR). The checks compare independent routes to the same quantity: LiDAR range
against camera depth, one camera against another, finite differences against reported velocities,
rays cast here against the returned points.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from phigenesis import geometry as g
from phigenesis import taxonomy as tx
from phigenesis.data.records import CameraCalibration, CameraImage, Frame
from phigenesis.data.sources.synthetic import LIDAR_SPIN_PERIOD_S, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec, camera_calibrations
from phigenesis.data.sources.synthetic.world import World
from tests.conftest import TINY_LIDAR, tiny_config

RIG_NAMES = ("waymo5", "nuscenes6")
#: Frames of the tiny 3-frame scenes that the module renders.
FRAME_INDICES = (0, 2)
#: Seeds of the worlds whose content is checked (4 s scenes, as the default 40 frames at 10 Hz).
WORLD_SEEDS = (0, 1, 2, 3, 4, 5)
VEHICLE_CLASSES = (tx.CAR, tx.TRUCK, tx.BUS)


@dataclasses.dataclass
class Rendered:
    scene: SyntheticScene
    frames: list[Frame]


@pytest.fixture(scope="module")
def render_cache() -> dict[str, Rendered]:
    return {}


def _rendered(cache: dict[str, Rendered], rig: str) -> Rendered:
    """Scene 0 of the tiny config of ``rig`` and its frames, rendered once per module."""
    if rig not in cache:
        scene = SyntheticScene(tiny_config(rig=rig), 0)
        cache[rig] = Rendered(scene, [scene.render_frame(i) for i in FRAME_INDICES])
    return cache[rig]


@pytest.fixture(params=RIG_NAMES)
def rendered(request: pytest.FixtureRequest, render_cache: dict[str, Rendered]) -> Rendered:
    return _rendered(render_cache, request.param)


@pytest.fixture
def waymo(render_cache: dict[str, Rendered]) -> Rendered:
    return _rendered(render_cache, "waymo5")


@pytest.fixture(scope="module")
def worlds() -> list[World]:
    return [SyntheticScene(tiny_config(seed=s, frames=40), 0).world for s in WORLD_SEEDS]


# --------------------------------------------------------------------------------------------
# Helpers


def neighbourhood(a: np.ndarray) -> np.ndarray:
    """(9, H, W) stack of each pixel's 3 x 3 neighbourhood (edges repeated)."""
    pad = np.pad(a, 1, mode="edge")
    h, w = a.shape
    return np.stack([pad[i : i + h, j : j + w] for i in range(3) for j in range(3)])


def smooth_static(depth: np.ndarray, semantic: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Pixels whose 3 x 3 neighbourhood is static world (no object, no ego) with continuous depth:
    a point projected to within half a pixel of them lands on the same surface."""
    d = neighbourhood(depth.astype(np.float64))
    return (
        (d.min(0) > 0)
        & (d.max(0) - d.min(0) <= 0.05 * depth)
        & (neighbourhood(instance).max(0) == 0)
        & (neighbourhood(semantic) != tx.IGNORE_ID).all(0)
    )


def pixel_points_world(cam: CameraImage, mask: np.ndarray) -> np.ndarray:
    """World points (N, 3) of the pixels in ``mask`` (row-major) from the camera's truth depth."""
    cal = cam.calibration
    sel = mask.reshape(-1)
    uv = g.pixel_grid(cal.width, cal.height)[sel]
    depth = cam.truth.depth_m.reshape(-1)[sel]
    return g.transform_points(
        cam.world_from_camera, g.unproject_pixels(uv, cal.intrinsics, cal.distortion, depth)
    )


def lidar_in_cameras(frame: Frame) -> dict[str, np.ndarray]:
    """Static LiDAR points of a frame seen by its cameras, with both sensors' truth per point.

    Points (instance 0, not the ego body) go ego(frame time) -> world -> each camera at its own
    time, are projected with distortion and read the nearest pixel, kept where the pixel is
    :func:`smooth_static` there.
    """
    lidar = frame.lidar
    assert lidar is not None and lidar.semantic is not None and lidar.instance is not None
    static = (lidar.instance == 0) & (lidar.semantic != tx.IGNORE_ID)
    points_world = g.transform_points(lidar.world_from_ego, lidar.points_ego[static].astype(np.float64))
    semantic = lidar.semantic[static]
    out: dict[str, list[np.ndarray]] = {"lidar_z": [], "map_depth": [], "lidar_sem": [], "map_sem": []}
    for cam in frame.cameras:
        cal, truth = cam.calibration, cam.truth
        assert truth is not None
        p_cam = g.transform_points(g.invert_transform(cam.world_from_camera), points_world)
        uv, valid = g.project_points(p_cam, cal.intrinsics, cal.distortion)
        valid &= g.in_image(uv, cal.width, cal.height)
        idx = np.flatnonzero(valid)
        u, v = np.rint(uv[idx]).astype(np.int64).T
        keep = smooth_static(truth.depth_m, truth.semantic, truth.instance)[v, u]
        idx, u, v = idx[keep], u[keep], v[keep]
        out["lidar_z"].append(p_cam[idx, 2])
        out["map_depth"].append(truth.depth_m[v, u].astype(np.float64))
        out["lidar_sem"].append(semantic[idx])
        out["map_sem"].append(truth.semantic[v, u])
    return {k: np.concatenate(vals) for k, vals in out.items()}


def footprint_corners(center_xy: np.ndarray, yaw: np.ndarray, length_width: np.ndarray) -> np.ndarray:
    """(M, 4, 2) corners of upright boxes seen from above."""
    u = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    v = np.stack([-u[:, 1], u[:, 0]], axis=-1)
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    half = 0.5 * length_width
    return (
        center_xy[:, None]
        + signs[None, :, :1] * half[:, None, :1] * u[:, None]
        + signs[None, :, 1:] * half[:, None, 1:] * v[:, None]
    )


def overlapping_pairs(corners: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs of the rectangles (M, 4, 2) whose interiors overlap (separating-axis test)."""
    edges = np.roll(corners, -1, axis=1) - corners  # (M, 4, 2)
    axes = np.stack([-edges[:, :2, 1], edges[:, :2, 0]], axis=-1)  # two edge normals per box
    proj = np.einsum("iad,jkd->iajk", axes, corners)  # box i's axes, box j's corners
    lo, hi = proj.min(-1), proj.max(-1)  # (M, 2, M)
    own_lo = np.einsum("iai->ia", lo)[:, :, None]
    own_hi = np.einsum("iai->ia", hi)[:, :, None]
    separated = np.any((hi <= own_lo) | (lo >= own_hi), axis=1)  # (M, M) by box i's axes
    overlap = ~(separated | separated.T)
    i, j = np.nonzero(np.triu(overlap, k=1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


# --------------------------------------------------------------------------------------------
# Truth self-consistency between sensors


def test_lidar_points_agree_with_every_cameras_truth_depth(rendered: Rendered) -> None:
    matches = [lidar_in_cameras(f) for f in rendered.frames]
    lidar_z = np.concatenate([m["lidar_z"] for m in matches])
    depth = np.concatenate([m["map_depth"] for m in matches])
    error = np.abs(lidar_z - depth)
    assert len(error) >= 1000, len(error)
    # LiDAR range noise is 0.02 m (median |noise| 0.013 m); nearest-pixel lookup adds a little.
    assert np.median(error) < 0.035, np.median(error)
    assert np.mean(error <= 0.1 + 0.01 * depth) > 0.97, np.mean(error <= 0.1 + 0.01 * depth)


def test_lidar_truth_semantics_match_the_camera_truth_on_shared_static_points(rendered: Rendered) -> None:
    matches = [lidar_in_cameras(f) for f in rendered.frames]
    lidar_z = np.concatenate([m["lidar_z"] for m in matches])
    depth = np.concatenate([m["map_depth"] for m in matches])
    same_point = np.abs(lidar_z - depth) <= 0.1 + 0.01 * depth
    lidar_sem = np.concatenate([m["lidar_sem"] for m in matches])[same_point]
    map_sem = np.concatenate([m["map_sem"] for m in matches])[same_point]
    assert len(lidar_sem) >= 1000
    assert np.mean(lidar_sem == map_sem) >= 0.99, np.mean(lidar_sem == map_sem)
    assert len(np.unique(lidar_sem)) >= 4  # road, sidewalk, buildings, terrain, ...


OVERLAPPING_PAIRS = {
    "waymo5": [("FRONT", "FRONT_LEFT"), ("FRONT", "FRONT_RIGHT"), ("FRONT_RIGHT", "SIDE_RIGHT")],
    "nuscenes6": [
        ("CAM_FRONT", "CAM_FRONT_LEFT"),
        ("CAM_FRONT", "CAM_FRONT_RIGHT"),
        ("CAM_FRONT_LEFT", "CAM_BACK_LEFT"),
        ("CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"),
        ("CAM_BACK", "CAM_BACK_LEFT"),
        ("CAM_BACK", "CAM_BACK_RIGHT"),
    ],
}


def test_pixels_reprojected_into_an_overlapping_camera_land_on_the_same_surface(rendered: Rendered) -> None:
    scene = rendered.scene
    cals = {c.name: c for c in scene.calibrations}
    compared = same = on_objects = 0
    for (a, b), t_micros in itertools.product(OVERLAPPING_PAIRS[scene.config.rig], scene.frame_micros[::2]):
        # Both cameras at one common time, so moving objects are where they are in both.
        t = scene.seconds(t_micros)
        world_from_ego = scene.world.world_from_ego(t)
        bodies = scene.renderer.bodies_at(t)
        truth = {n: scene.renderer.render_camera(cals[n], world_from_ego, t, bodies)[1] for n in (a, b)}
        ca, cb, ta, tb = cals[a], cals[b], truth[a], truth[b]
        # Source pixels inside a surface (uniform labels and continuous depth over 3 x 3), so a
        # reprojection that is exact to within half a target pixel stays on that surface.
        label = ta.semantic.astype(np.int64) << 16 | ta.instance
        depth = neighbourhood(ta.depth_m.astype(np.float64))
        interior = (
            (neighbourhood(label) == label).all(0)
            & (depth.min(0) > 0)
            & (depth.max(0) - depth.min(0) <= 0.05 * ta.depth_m)
        ).reshape(-1)
        uv = g.pixel_grid(ca.width, ca.height)[interior]
        p_a = g.unproject_pixels(uv, ca.intrinsics, ca.distortion, ta.depth_m.reshape(-1)[interior])
        b_from_a = (
            g.invert_transform(world_from_ego @ cb.ego_from_camera) @ world_from_ego @ ca.ego_from_camera
        )
        p_b = g.transform_points(b_from_a, p_a)
        uv_b, valid = g.project_points(p_b, cb.intrinsics, cb.distortion)
        valid &= g.in_image(uv_b, cb.width, cb.height)
        src = np.flatnonzero(interior)[valid]
        u, v = np.rint(uv_b[valid]).astype(np.int64).T
        # Visible in b: its depth there is the reprojected point's, not something in front.
        visible = np.abs(p_b[valid, 2] - tb.depth_m[v, u]) <= 0.02 + 0.02 * p_b[valid, 2]
        src, u, v = src[visible], u[visible], v[visible]
        sem_a, inst_a = ta.semantic.reshape(-1)[src], ta.instance.reshape(-1)[src]
        compared += len(src)
        same += int(np.sum((sem_a == tb.semantic[v, u]) & (inst_a == tb.instance[v, u])))
        on_objects += int(np.sum(inst_a > 0))
    assert compared >= 1000, compared
    assert on_objects >= 100, on_objects
    assert same / compared >= 0.99, same / compared


# --------------------------------------------------------------------------------------------
# Determinism


def test_same_config_renders_identical_frames_in_any_order(rendered: Rendered) -> None:
    again = SyntheticScene(rendered.scene.config, 0).render_frame(FRAME_INDICES[-1])  # skips frame 0
    first = rendered.frames[-1]
    assert again.timestamp_micros == first.timestamp_micros
    assert_array_equal(again.world_from_ego, first.world_from_ego)
    for cam_a, cam_b in zip(again.cameras, first.cameras, strict=True):
        assert cam_a.name == cam_b.name and cam_a.timestamp_micros == cam_b.timestamp_micros
        assert cam_a.image_bytes == cam_b.image_bytes
        assert cam_a.truth is not None and cam_b.truth is not None
        for field in ("depth_m", "semantic", "instance", "flow_world_mps"):
            assert_array_equal(getattr(cam_a.truth, field), getattr(cam_b.truth, field))
    assert again.lidar is not None and first.lidar is not None
    for field in (
        "points_ego",
        "intensity",
        "beam_index",
        "origins_ego",
        "time_offset_micros",
        "semantic",
        "instance",
    ):
        assert_array_equal(getattr(again.lidar, field), getattr(first.lidar, field))
    assert again.boxes.track_id == first.boxes.track_id
    for field in ("center_world", "size_lwh", "yaw_world", "velocity_world", "num_lidar_points"):
        assert_array_equal(getattr(again.boxes, field), getattr(first.boxes, field))


def test_different_seeds_and_scenes_give_different_worlds(worlds: list[World]) -> None:
    base = SyntheticScene(tiny_config(seed=7), 0).world
    for other in (SyntheticScene(tiny_config(seed=8), 0).world, SyntheticScene(tiny_config(seed=7), 1).world):
        assert other.static_mesh.vertices.shape != base.static_mesh.vertices.shape or not np.array_equal(
            other.static_mesh.vertices, base.static_mesh.vertices
        )
        assert not np.allclose(other.sun_direction, base.sun_direction)
        assert other.ego.speed.v0 != base.ego.speed.v0
    starts = {round(w.ego.speed.v0, 9) for w in worlds}
    assert len(starts) == len(worlds)  # every seed its own scene


# --------------------------------------------------------------------------------------------
# Exact truth at any time


def test_box_velocities_are_the_derivatives_of_box_positions(waymo: Rendered) -> None:
    scene = waymo.scene
    h = 1000  # micros
    times = [scene.config.start_micros + round(k * 1e6 / 12) for k in range(25)]  # 12 Hz for 2 s
    moving = np.array([not a.is_static for a in scene.world.agents])
    assert moving.sum() >= 5
    errors = []
    for t in times:
        box, before, after = scene.boxes_at(t), scene.boxes_at(t - h), scene.boxes_at(t + h)
        fd = (after.center_world - before.center_world) / (2 * h * 1e-6)
        errors.append(np.abs(fd - box.velocity_world)[moving].max(axis=1))
        assert_allclose(box.velocity_world[~moving], 0.0)
    errors = np.array(errors)
    # Exact to rounding, except where an acceleration step lies inside the stencil: |da| h / 4.
    assert np.median(errors) < 1e-6, np.median(errors)
    assert errors.max() < 8.0 * h * 1e-6 / 4, errors.max()


def test_box_yaw_is_wrapped_and_changes_at_the_trajectory_yaw_rate(worlds: list[World]) -> None:
    dt = 0.02
    t = np.arange(-30.0, 30.0, dt)
    wrapped = 0
    for world in worlds:
        for agent in world.agents:
            if agent.is_static:
                continue
            _, yaw, _, rate = agent.trajectory.state(t)
            assert np.all((yaw >= -np.pi) & (yaw < np.pi))
            step = g.angle_difference(yaw[1:], yaw[:-1])
            # The heading's rate is v * curvature, piecewise smooth: steps match the mean rate.
            assert np.all(
                np.abs(step - 0.5 * (rate[1:] + rate[:-1]) * dt)
                <= 0.5 * dt * np.abs(np.diff(rate)) + 1e-3 * dt
            )
            wrapped += int(np.any(np.abs(np.diff(yaw)) > np.pi))
    assert wrapped >= 1  # some agent drives through the +-pi wrap (e.g. oncoming traffic)
    # Boxes report the same wrapped yaw.
    world = worlds[0]
    boxes = world.boxes_at(1.234)
    yaws = np.array([a.trajectory.state(1.234)[1] for a in world.agents])
    assert_array_equal(boxes.yaw_world, yaws)


def test_ego_pose_derivatives_match_the_ego_velocity_and_yaw_rate(waymo: Rendered) -> None:
    scene = waymo.scene
    h = 500  # micros
    for k in range(0, 40):
        t = scene.config.start_micros + k * 25_000
        pose = scene.world_from_ego(t)
        before, after = scene.world_from_ego(t - h), scene.world_from_ego(t + h)
        _, _, vel, rate = scene.world.ego.state(scene.seconds(t))
        fd_vel = (after[:3, 3] - before[:3, 3]) / (2 * h * 1e-6)
        assert_allclose(fd_vel, vel, atol=2e-3)
        fd_rate = float(g.angle_difference(g.matrix_yaw(after), g.matrix_yaw(before))) / (2 * h * 1e-6)
        assert fd_rate == pytest.approx(float(rate), abs=1e-4)
        assert_allclose(pose[2], [0, 0, 1, 0], atol=1e-12)  # upright on flat ground
        assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)
    assert_allclose(scene.world_from_ego(scene.config.start_micros), np.eye(4), atol=1e-9)


def test_boxes_at_10_12_and_2_hz_are_samples_of_one_motion(waymo: Rendered) -> None:
    scene = waymo.scene
    start = scene.config.start_micros
    grids = {hz: [start + round(k * 1e6 / hz) for k in range(int(2 * hz) + 1)] for hz in (10, 12, 2)}
    boxes = {hz: {t: scene.boxes_at(t) for t in ts} for hz, ts in grids.items()}
    # Shared instants (every 0.5 s) give identical boxes whatever the rate that asked.
    for t in grids[2]:
        for hz in (10, 12):
            a, b = boxes[2][t], boxes[hz][t]
            assert a.track_id == b.track_id
            for field in ("center_world", "yaw_world", "velocity_world", "size_lwh", "instance_id"):
                assert_array_equal(getattr(a, field), getattr(b, field))
    # Between 10 Hz samples, the 12 Hz boxes lie on the same motion: linear interpolation of the
    # 10 Hz centres is off by at most |acceleration| dt^2 / 8 (< 10 m/s^2, centripetal included).
    t10 = np.array(grids[10], dtype=np.float64)
    centres10 = np.stack([boxes[10][t].center_world for t in grids[10]])  # (T, M, 3)
    velocities10 = np.stack([boxes[10][t].velocity_world for t in grids[10]])
    worst_position = worst_velocity = 0.0
    for t in grids[12]:
        i = min(int(np.searchsorted(t10, t, side="right")) - 1, len(t10) - 2)
        f = (t - t10[i]) / (t10[i + 1] - t10[i])
        lerp = (1 - f) * centres10[i] + f * centres10[i + 1]
        vlerp = (1 - f) * velocities10[i] + f * velocities10[i + 1]
        worst_position = max(worst_position, float(np.abs(boxes[12][t].center_world - lerp).max()))
        worst_velocity = max(worst_velocity, float(np.abs(boxes[12][t].velocity_world - vlerp).max()))
        assert boxes[12][t].track_id == boxes[10][grids[10][0]].track_id
    assert worst_position <= 10.0 * 0.1**2 / 8, worst_position
    assert worst_velocity <= 10.0 * 0.1 / 2, worst_velocity


def test_agent_meshes_fit_inside_their_boxes(worlds: list[World]) -> None:
    classes = set()
    for world in worlds:
        for agent in world.agents:
            extent = np.abs(agent.mesh.vertices).max(axis=0)  # body frame: origin at the box centre
            assert np.all(extent <= 0.5 * agent.size_lwh + 1e-9), (agent.kind, agent.class_id, extent)
            if agent.class_id in VEHICLE_CLASSES:  # vehicles fill their boxes
                assert np.all(extent >= 0.5 * agent.size_lwh - 1e-9), (agent.class_id, extent)
            classes.add(agent.class_id)
    assert {tx.CAR, tx.TRUCK, tx.BUS, tx.PERSON} <= classes


def test_agent_pixels_lie_inside_the_agents_box_at_the_camera_time(rendered: Rendered) -> None:
    scene = rendered.scene
    checked = stale_outside = 0
    for frame in rendered.frames:
        frame_boxes = scene.boxes_at(frame.timestamp_micros)
        for cam in frame.cameras:
            truth = cam.truth
            assert truth is not None
            boxes = scene.boxes_at(cam.timestamp_micros)
            row = {int(i): k for k, i in enumerate(boxes.instance_id)}
            for inst in np.unique(truth.instance[truth.instance > 0]):
                k = row[int(inst)]
                points = pixel_points_world(cam, truth.instance == inst)
                inside = g.points_in_box(
                    points, boxes.center_world[k], boxes.size_lwh[k], boxes.yaw_world[k], margin_m=0.01
                )
                assert inside.all(), (cam.name, int(inst), int((~inside).sum()))
                checked += len(points)
                # The camera's own time matters: the frame's boxes miss fast agents' pixels.
                if cam.timestamp_micros != frame.timestamp_micros:
                    k0 = int(np.flatnonzero(frame_boxes.instance_id == inst)[0])
                    stale_outside += int(
                        (
                            ~g.points_in_box(
                                points,
                                frame_boxes.center_world[k0],
                                frame_boxes.size_lwh[k0],
                                frame_boxes.yaw_world[k0],
                                margin_m=0.01,
                            )
                        ).sum()
                    )
    assert checked >= 2000, checked
    assert stale_outside > 50, stale_outside


# --------------------------------------------------------------------------------------------
# Truth flow


def test_flow_on_moving_objects_is_the_rigid_motion_of_their_box(rendered: Rendered) -> None:
    scene = rendered.scene
    h = 500  # micros
    moving = {a.instance_id for a in scene.world.agents if not a.is_static}
    compared, worst_fd, worst_formula, turning_part = 0, 0.0, 0.0, 0.0
    for frame in rendered.frames:
        for cam in frame.cameras:
            truth = cam.truth
            assert truth is not None
            t = cam.timestamp_micros
            boxes, before, after = scene.boxes_at(t), scene.boxes_at(t - h), scene.boxes_at(t + h)
            for k, inst in enumerate(boxes.instance_id):
                mask = truth.instance == inst
                if int(inst) not in moving or not mask.any():
                    continue
                p = pixel_points_world(cam, mask)
                flow = truth.flow_world_mps[mask].astype(np.float64)
                # Finite difference of the body-fixed point carried by the box pose.
                pose = g.yaw_pose_to_transform(boxes.center_world[k], boxes.yaw_world[k])
                body = g.transform_points(g.invert_transform(pose), p)
                p_before = g.transform_points(
                    g.yaw_pose_to_transform(before.center_world[k], before.yaw_world[k]), body
                )
                p_after = g.transform_points(
                    g.yaw_pose_to_transform(after.center_world[k], after.yaw_world[k]), body
                )
                fd = (p_after - p_before) / (2 * h * 1e-6)
                worst_fd = max(worst_fd, float(np.abs(flow - fd).max()))
                # v + omega x r with the yaw rate from the box yaws.
                omega = float(g.angle_difference(after.yaw_world[k], before.yaw_world[k])) / (2 * h * 1e-6)
                r = p - boxes.center_world[k]
                spin = omega * np.stack([-r[:, 1], r[:, 0], np.zeros(len(r))], axis=1)
                worst_formula = max(worst_formula, float(np.abs(flow - boxes.velocity_world[k] - spin).max()))
                turning_part = max(turning_part, float(np.abs(spin).max()))
                compared += int(mask.sum())
    assert compared >= 500, compared
    assert turning_part > 0.05  # the yaw-rate term is exercised, not only translation
    assert worst_fd < 1e-3, worst_fd
    assert worst_formula < 1e-3, worst_formula


def test_flow_is_zero_on_static_surfaces_and_sky(rendered: Rendered) -> None:
    static_ids = {a.instance_id for a in rendered.scene.world.agents if a.is_static}
    ego_pixels = static_pixels = 0
    for frame in rendered.frames:
        for cam in frame.cameras:
            truth = cam.truth
            assert truth is not None
            static = (truth.instance == 0) & (truth.semantic != tx.IGNORE_ID)
            static |= np.isin(truth.instance, list(static_ids))
            static_pixels += int(static.sum())
            assert np.all(truth.flow_world_mps[static] == 0.0)
            assert np.all(truth.flow_world_mps[truth.semantic == tx.SKY] == 0.0)
            # The ego's own body moves with the ego (seen by low cameras).
            ego = truth.semantic == tx.IGNORE_ID
            if ego.any():
                _, _, vel, rate = rendered.scene.world.ego.state(rendered.scene.seconds(cam.timestamp_micros))
                r = pixel_points_world(cam, ego) - cam.world_from_ego[:3, 3]
                spin = float(rate) * np.stack([-r[:, 1], r[:, 0], np.zeros(len(r))], axis=1)
                assert_allclose(truth.flow_world_mps[ego], vel + spin, atol=1e-4)
                ego_pixels += int(ego.sum())
    assert static_pixels > 10_000
    if rendered.scene.config.rig == "nuscenes6":
        assert ego_pixels > 0  # CAM_BACK sits low enough to see the ego's rear


# --------------------------------------------------------------------------------------------
# Camera timing


def test_cameras_fire_staggered_with_their_own_timestamps_and_poses(rendered: Rendered) -> None:
    scene = rendered.scene
    period = LIDAR_SPIN_PERIOD_S[scene.config.rig] * 1e6
    for frame in rendered.frames:
        stamps = [c.timestamp_micros for c in frame.cameras]
        assert len(set(stamps)) == len(stamps)
        for i, cam in enumerate(frame.cameras):
            assert cam.timestamp_micros == scene.camera_time_micros(frame.timestamp_micros, i)
            assert abs(cam.timestamp_micros - frame.timestamp_micros) <= period / 2
            assert_array_equal(cam.world_from_ego, scene.world_from_ego(cam.timestamp_micros))
            moved = np.linalg.norm(cam.world_from_ego[:3, 3] - frame.world_from_ego[:3, 3])
            if cam.timestamp_micros != frame.timestamp_micros:
                assert moved > 0.02  # the ego drives at >= 3 m/s: not the frame's pose
            else:
                assert moved == 0.0


def test_cameras_fire_in_the_order_the_lidar_sweeps_past_them(rendered: Rendered) -> None:
    frame = rendered.frames[0]
    order = [c.name for c in sorted(frame.cameras, key=lambda c: c.timestamp_micros)]
    expected = {
        "waymo5": ["SIDE_LEFT", "FRONT_LEFT", "FRONT", "FRONT_RIGHT", "SIDE_RIGHT"],
        "nuscenes6": [
            "CAM_BACK",
            "CAM_BACK_LEFT",
            "CAM_FRONT_LEFT",
            "CAM_FRONT",
            "CAM_FRONT_RIGHT",
            "CAM_BACK_RIGHT",
        ],
    }[rendered.scene.config.rig]
    assert order == expected
    # The LiDAR points in each camera's viewing direction were measured when that camera fired.
    lidar = frame.lidar
    assert lidar is not None
    spec = rendered.scene.config.lidar
    period_us = LIDAR_SPIN_PERIOD_S[rendered.scene.config.rig] * 1e6
    d = lidar.points_ego.astype(np.float64) - lidar.origins_ego
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    for spec_cam, cam in zip(rendered.scene.specs, frame.cameras, strict=True):
        near = np.abs(g.angle_difference(azimuth, np.radians(spec_cam.yaw_deg))) < np.radians(3.0)
        assert near.sum() >= 10
        dt = lidar.time_offset_micros[near] - (cam.timestamp_micros - frame.timestamp_micros)
        dt = np.mod(dt + period_us / 2, period_us) - period_us / 2  # the rear is swept twice
        assert np.abs(dt).max() <= period_us / spec.sectors / 2 + period_us * 4.0 / 360.0, (cam.name, dt)


def test_lidar_origins_are_the_mount_at_each_points_time(rendered: Rendered) -> None:
    scene = rendered.scene
    for frame in rendered.frames:
        lidar = frame.lidar
        assert lidar is not None
        ego_from_world = g.invert_transform(lidar.world_from_ego)
        mount = np.array(scene.config.lidar.position_m)
        for offset in np.unique(lidar.time_offset_micros):
            sel = lidar.time_offset_micros == offset
            pose = scene.world_from_ego(frame.timestamp_micros + int(offset))
            expected = g.transform_points(ego_from_world @ pose, mount[None])[0]
            assert_allclose(lidar.origins_ego[sel], np.broadcast_to(expected, (sel.sum(), 3)), atol=1e-4)
        assert len(np.unique(lidar.time_offset_micros)) == scene.config.lidar.sectors


# --------------------------------------------------------------------------------------------
# World content


def test_worlds_have_every_kind_of_agent(worlds: list[World]) -> None:
    kinds = {a.kind for w in worlds for a in w.agents}
    expected = {
        "parked",
        "lead",
        "follower",
        "oncoming",
        "turning",
        "stop_and_go",
        "walking",
        "standing",
        "crossing",
    }
    assert kinds == expected
    for world in worlds:
        classes = {a.class_id for a in world.agents}
        assert tx.CAR in classes and tx.PERSON in classes
        for a in world.agents:
            is_person = a.kind in ("walking", "standing", "crossing")
            assert (a.class_id == tx.PERSON) == is_person, (a.kind, a.class_id)
            assert a.is_static == (a.kind in ("parked", "standing")), a.kind


def test_parked_vehicles_and_standing_people_never_move(worlds: list[World]) -> None:
    t = np.linspace(-5.0, 10.0, 31)
    for world in worlds:
        for a in world.agents:
            if a.kind in ("parked", "standing"):
                pos, yaw, vel, rate = a.trajectory.state(t)
                assert_allclose(pos, np.broadcast_to(pos[0], pos.shape), atol=0)
                assert np.all(yaw == yaw[0]) and np.all(vel == 0) and np.all(rate == 0)


def test_lead_and_oncoming_vehicles_drive_straight_along_the_main_road(worlds: list[World]) -> None:
    """They keep to their lane of the main road through the junction (no turns) and head along it."""
    seen = set()
    for world in worlds:
        t = np.linspace(0.0, world.duration_s, 21)
        ego_pos, _, ego_vel, _ = world.ego.state(t)
        for a in world.agents:
            if a.kind not in ("lead", "oncoming"):
                continue
            seen.add(a.kind)
            pos, yaw, vel, _ = a.trajectory.state(t)
            lane = world.roads["main"].offset(-1.75 if a.kind == "lead" else 1.75)  # ego's / opposite
            _, lane_xy, lane_heading = lane.sample(0.05)
            d2 = np.sum((pos[:, None, :2] - lane_xy[None]) ** 2, axis=-1)
            nearest = np.argmin(d2, axis=1)
            assert np.sqrt(d2[np.arange(len(t)), nearest]).max() < 0.03
            expected = lane_heading[nearest] + (0.0 if a.kind == "lead" else np.pi)
            assert_allclose(g.angle_difference(yaw, expected), 0.0, atol=0.005)
            if a.kind == "lead":  # ahead of the ego and faster, so the gap only grows
                gap = np.linalg.norm(pos[:, :2] - ego_pos[:, :2], axis=1)
                assert np.all(np.diff(gap) > 0)
                assert np.all(np.linalg.norm(vel, axis=1) > np.linalg.norm(ego_vel, axis=1))
    assert seen == {"lead", "oncoming"}


def test_turning_vehicles_turn_by_a_right_angle_at_the_junction(worlds: list[World]) -> None:
    turning = [(w, a) for w in worlds for a in w.agents if a.kind == "turning"]
    assert len(turning) >= 2
    for world, a in turning:
        junction = world.roads["cross"].pose(np.array([world.roads["cross"].length / 2]))[0][0]
        t = np.linspace(-100.0, 100.0, 20001)
        pos, yaw, _, rate = a.trajectory.state(t)
        total = np.sum(g.angle_difference(yaw[1:], yaw[:-1]))
        assert abs(total) == pytest.approx(np.pi / 2, abs=1e-6)
        assert np.all(np.sign(rate[rate != 0]) == np.sign(total))  # turns one way only
        turning_now = rate != 0
        assert np.linalg.norm(pos[turning_now, :2] - junction, axis=1).max() < 20.0
        # And the turn happens around the scene (it starts within it).
        assert -1.0 < t[turning_now][0] < world.duration_s


def test_stop_and_go_vehicles_stop_then_drive_on(worlds: list[World]) -> None:
    count = 0
    for world in worlds:
        for a in world.agents:
            if a.kind != "stop_and_go":
                continue
            count += 1
            t = np.arange(-40.0, 40.0, 0.01)
            _, _, vel, _ = a.trajectory.state(t)
            speed = np.linalg.norm(vel, axis=1)
            stopped = np.flatnonzero(speed < 1e-6)
            assert stopped.size > 0
            assert speed[: stopped[0]].min() > 0 and speed[0] > 5.0  # drives up to the stop ...
            assert speed[stopped[-1] + 1 :].max() > 5.0  # ... and drives on after waiting
            wait = t[stopped[-1]] - t[stopped[0]]
            assert 1.4 < wait < 4.1
            assert 0.0 <= t[stopped[0]] <= world.duration_s  # the stop is within the scene
    assert count >= 3


def test_pedestrians_walk_stand_or_cross(worlds: list[World]) -> None:
    kinds = set()
    for world in worlds:
        t = np.linspace(-20.0, 30.0, 501)
        for a in world.agents:
            if a.class_id != tx.PERSON:
                continue
            kinds.add(a.kind)
            pos, _, vel, _ = a.trajectory.state(t)
            speed = np.linalg.norm(vel, axis=1)
            assert speed.max() <= 1.6
            if a.kind == "walking":
                assert speed[0] > 0.89
                assert_allclose(speed, speed[0], rtol=1e-12)
                assert_allclose(pos[:, 2], 0.15 + a.size_lwh[2] / 2)  # on the raised sidewalk
            elif a.kind == "standing":
                assert np.all(speed == 0)
            else:  # crossing: waits, walks over the road, stops on the far side
                assert speed[0] == 0 and speed[-1] == 0 and speed.max() > 1.0
                assert_allclose(pos[:, 2], a.size_lwh[2] / 2)  # on the road surface
                crossed = np.linalg.norm(pos[-1, :2] - pos[0, :2])
                assert 10.0 < crossed < 12.0  # the 12 m road, kerb to kerb
    assert kinds == {"walking", "standing", "crossing"}


def test_overlap_check_finds_overlapping_rectangles() -> None:
    """The separating-axis helper used below: touching or apart is fine, any overlap is found."""
    centers = np.array([[0.0, 0.0], [4.0, 0.0], [1.5, 1.5], [10.0, 0.0], [11.0, 1.0]])
    yaws = np.array([0.0, 0.0, np.pi / 4, 0.0, np.pi / 2])
    sizes = np.array([[4.0, 2.0], [4.0, 2.0], [1.0, 1.0], [4.0, 2.0], [4.0, 2.0]])
    # 0-1 touch at x = 2; the rotated square 2 pokes into box 0's corner; 3 and 4 cross.
    assert overlapping_pairs(footprint_corners(centers, yaws, sizes)) == [(0, 2), (3, 4)]


def test_no_boxes_overlap_each_other_or_the_ego_during_the_scene(worlds: list[World]) -> None:
    for world in worlds:
        t = np.arange(0.0, world.duration_s + 1e-9, 0.02)
        # Every agent's box over the scene at once (boxes_at(t) reads the same trajectories).
        states = [a.trajectory.state(t) for a in world.agents]
        centers = np.stack([s[0][:, :2] for s in states], axis=1)  # (T, M, 2)
        yaws = np.stack([s[1] for s in states], axis=1)
        sizes = np.array([a.size_lwh[:2] for a in world.agents])
        probe = world.boxes_at(float(t[7]))
        assert_array_equal(probe.center_world[:, :2], centers[7])
        assert_array_equal(probe.yaw_world, yaws[7])
        # The ego's box: the extent of its body mesh (ego frame).
        lo, hi = world.ego_mesh.vertices.min(axis=0), world.ego_mesh.vertices.max(axis=0)
        ego_pose = world.world_from_ego(t)
        ego_center = g.transform_points(ego_pose, np.broadcast_to(0.5 * (lo + hi), (len(t), 1, 3)))[:, 0, :2]
        all_sizes = np.vstack([sizes, (hi - lo)[:2]])
        for k in range(len(t)):
            corners = footprint_corners(
                np.vstack([centers[k], ego_center[k]]),
                np.append(yaws[k], g.matrix_yaw(ego_pose[k])),
                all_sizes,
            )
            pairs = overlapping_pairs(corners)
            assert not pairs, (float(t[k]), pairs)


def test_sky_pixels_have_zero_depth_and_the_sky_class(rendered: Rendered) -> None:
    sky_pixels = 0
    for frame in rendered.frames:
        for cam in frame.cameras:
            truth = cam.truth
            assert truth is not None
            sky = truth.semantic == tx.SKY
            assert_array_equal(sky, truth.depth_m == 0)
            assert np.all(truth.instance[sky] == 0)
            assert np.all(truth.depth_m[~sky] > 0)
            sky_pixels += int(sky.sum())
    assert sky_pixels > 500


def test_frames_show_cars_people_and_the_static_classes(rendered: Rendered) -> None:
    seen = set()
    for frame in rendered.frames:
        for cam in frame.cameras:
            seen |= set(np.unique(cam.truth.semantic).tolist())
    assert {tx.CAR, tx.PERSON, tx.ROAD, tx.SIDEWALK, tx.BUILDING, tx.SKY} <= seen


def _horizontal_fov_deg(cal: CameraCalibration) -> float:
    """Angle between the rays through the left and right image edges on the principal row."""
    k = cal.intrinsics
    uv = np.array([[-0.5, k[1, 2]], [cal.width - 0.5, k[1, 2]]])
    rays = g.unproject_pixels(uv, k, cal.distortion)
    cos = rays[0] @ rays[1] / np.linalg.norm(rays[0]) / np.linalg.norm(rays[1])
    return float(np.degrees(np.arccos(cos)))


def test_rigs_have_realistic_fields_of_view() -> None:
    waymo, _ = camera_calibrations("waymo5", 160, 240)
    for cal in waymo:
        assert 45.0 < _horizontal_fov_deg(cal) < 52.0, cal.name  # Waymo: 50.4 deg, distortion
        assert np.any(cal.distortion != 0)
    nuscenes, _ = camera_calibrations("nuscenes6", 160, 240)
    fov = {cal.name: _horizontal_fov_deg(cal) for cal in nuscenes}
    assert fov.pop("CAM_BACK") == pytest.approx(110.0, abs=0.01)
    assert_allclose(list(fov.values()), 70.0, atol=0.01)


def _horizon_seen(rig: str) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths (ego frame, 0.25 deg steps) and whether any camera of ``rig`` sees the horizon there."""
    cals, _ = camera_calibrations(rig, 160, 240)
    azimuth = g.wrap_angle(np.radians(np.arange(0.0, 360.0, 0.25)))
    far = 1000.0 * np.stack([np.cos(azimuth), np.sin(azimuth), np.full_like(azimuth, 0.0015)], axis=1)
    seen = np.zeros(len(azimuth), bool)
    for cal in cals:
        p = g.transform_points(g.invert_transform(cal.ego_from_camera), far)
        uv, valid = g.project_points(p, cal.intrinsics, cal.distortion)
        seen |= valid & g.in_image(uv, cal.width, cal.height)
    return azimuth, seen


def test_nuscenes6_cameras_cover_the_whole_horizon() -> None:
    _, seen = _horizon_seen("nuscenes6")
    assert seen.all()


def test_waymo5_cameras_cover_the_front_and_sides_but_not_the_rear() -> None:
    azimuth, seen = _horizon_seen("waymo5")
    assert seen[np.abs(azimuth) < np.radians(110.0)].all()
    assert not seen[np.abs(azimuth) > np.radians(120.0)].any()


# --------------------------------------------------------------------------------------------
# LiDAR


def test_lidar_returns_lie_within_the_configured_range(rendered: Rendered) -> None:
    scene = rendered.scene
    spec = dataclasses.replace(TINY_LIDAR, min_range_m=4.0, max_range_m=20.0)
    raw = scene.renderer.render_lidar(
        spec, scene.frame_micros[0], scene.config.start_micros, scene.spin_period_s, np.random.default_rng(3)
    )
    measured = np.linalg.norm(raw["points_world"] - raw["origins_world"], axis=1)
    assert measured.min() >= 4.0 and measured.max() <= 20.0, (measured.min(), measured.max())
    assert np.any(measured < 4.2) and np.any(measured > 19.8)  # both limits are exercised
    for frame in rendered.frames:
        lidar = frame.lidar
        assert lidar is not None
        r = np.linalg.norm(lidar.points_ego.astype(np.float64) - lidar.origins_ego, axis=1)
        lo, hi = scene.config.lidar.min_range_m, scene.config.lidar.max_range_m
        assert r.min() >= lo - 1e-4 and r.max() <= hi + 1e-4


def test_default_lidar_has_64_beams_whose_points_follow_their_inclinations(rendered: Rendered) -> None:
    spec = LidarSpec()
    incl = spec.inclinations_rad()
    assert spec.beams == 64 and incl.shape == (64,)
    assert incl[0] == pytest.approx(np.radians(2.5)) and incl[-1] == pytest.approx(np.radians(-22.0))
    assert np.all(np.diff(incl) < 0)  # row 0 highest
    assert np.diff(incl)[0] > np.diff(incl)[-1]  # denser near the horizon
    scene = rendered.scene
    raw = scene.renderer.render_lidar(
        spec, scene.frame_micros[0], scene.config.start_micros, scene.spin_period_s, np.random.default_rng(0)
    )
    d = raw["points_world"] - raw["origins_world"]
    elevation = np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1))
    assert len(np.unique(raw["beam"])) == 64
    # The ego drives on flat ground, so the sensor frame's elevation is the world's.
    assert np.abs(elevation - incl[raw["beam"]]).max() < 1e-9
    # The same in a frame's sweep (float32 ego-frame points).
    lidar = rendered.frames[0].lidar
    assert lidar is not None
    d32 = lidar.points_ego.astype(np.float64) - lidar.origins_ego
    elevation32 = np.arcsin(d32[:, 2] / np.linalg.norm(d32, axis=1))
    assert np.abs(elevation32 - TINY_LIDAR.inclinations_rad()[lidar.beam_index]).max() < 1e-5


def _recast_static(scene: SyntheticScene, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """Measured ranges of a frame's static points and the noiseless ranges cast along their rays."""
    lidar = frame.lidar
    assert lidar is not None and lidar.instance is not None
    static = (lidar.instance == 0) & (lidar.semantic != tx.IGNORE_ID)
    origins = g.transform_points(lidar.world_from_ego, lidar.origins_ego[static].astype(np.float64))
    points = g.transform_points(lidar.world_from_ego, lidar.points_ego[static].astype(np.float64))
    measured = np.linalg.norm(points - origins, axis=1)
    hits = scene.renderer.cast_static(origins, (points - origins) / measured[:, None])
    return measured, hits.t


def test_lidar_range_noise_has_the_configured_spread(rendered: Rendered) -> None:
    scene = rendered.scene
    errors = np.concatenate([np.subtract(*_recast_static(scene, f)) for f in rendered.frames])
    assert len(errors) >= 2000
    assert np.all(np.isfinite(errors))
    sigma = scene.config.lidar.range_noise_m
    assert abs(np.mean(errors)) < 0.1 * sigma
    assert np.std(errors) == pytest.approx(sigma, rel=0.1)
    assert np.abs(errors).max() < 6 * sigma  # Gaussian, no outliers


def test_noiseless_lidar_returns_the_exact_ray_cast_distance(waymo: Rendered) -> None:
    scene = waymo.scene
    spec = dataclasses.replace(TINY_LIDAR, range_noise_m=0.0)
    raw = scene.renderer.render_lidar(
        spec, scene.frame_micros[0], scene.config.start_micros, scene.spin_period_s, np.random.default_rng(1)
    )
    static = raw["instance"] == 0
    o, p = raw["origins_world"][static], raw["points_world"][static]
    r = np.linalg.norm(p - o, axis=1)
    hits = scene.renderer.cast_static(o, (p - o) / r[:, None])
    assert static.sum() > 1000
    assert np.abs(hits.t - r).max() < 1e-3
    assert_array_equal(hits.semantic, raw["semantic"][static])


# --------------------------------------------------------------------------------------------
# Images


#: Median |luminance - 3x3 mean| (8-bit levels) that textured surfaces exceed. Rendered with flat
#: albedo instead, these frames give road 0.6-0.73 (paint edges, perspective) and buildings <= 0.04;
#: textured, road 2.0-2.6 and buildings 1.1-2.9.
TEXTURE_MEDIAN = {tx.ROAD: 1.2, tx.BUILDING: 0.5}


def test_images_have_texture_on_roads_and_buildings(rendered: Rendered) -> None:
    """Surfaces are not flat colour: pixels differ from their neighbours' mean within one class."""
    detail: dict[int, list[np.ndarray]] = {cls: [] for cls in TEXTURE_MEDIAN}
    for frame in rendered.frames:
        for cam in frame.cameras:
            lum = luminance(cam.decode_image())
            local_mean = neighbourhood(lum).mean(axis=0)
            sem = neighbourhood(cam.truth.semantic)
            for cls, values in detail.items():
                interior = (sem == cls).all(axis=0)
                values.append(np.abs(lum - local_mean)[interior])
    for cls, values in detail.items():
        v = np.concatenate(values)
        name = tx.CLASS_NAMES[cls]
        assert len(v) >= 1000, (name, len(v))
        assert np.median(v) > TEXTURE_MEDIAN[cls], (name, np.median(v))
        assert np.mean(v > 3.0) > 0.3, (name, np.mean(v > 3.0))  # flat albedo: <= 0.25


def test_shadowed_road_is_darker_than_sunlit_road(rendered: Rendered) -> None:
    scene = rendered.scene
    sun = scene.world.sun_direction
    lit_lum, shadow_lum = [], []
    for frame in rendered.frames:
        for cam in frame.cameras:
            truth = cam.truth
            road = (truth.semantic == tx.ROAD) & (truth.instance == 0)
            if not road.any():
                continue
            points = pixel_points_world(cam, road)
            origins = points + np.array([0.0, 0.0, 0.03])
            bodies = scene.renderer.bodies_at(scene.seconds(cam.timestamp_micros))
            shadowed = scene.renderer.cast(origins, np.tile(sun, (len(origins), 1)), bodies).hit
            lum = luminance(cam.decode_image())[road]
            lit_lum.append(lum[~shadowed])
            shadow_lum.append(lum[shadowed])
    lit, shadow = np.concatenate(lit_lum), np.concatenate(shadow_lum)
    assert len(lit) >= 200 and len(shadow) >= 50, (len(lit), len(shadow))
    assert np.median(lit) > 1.3 * np.median(shadow), (np.median(lit), np.median(shadow))
