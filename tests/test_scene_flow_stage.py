"""The scene_flow stage: rigid box motion per LiDAR point and per pixel, against exact references and
the synthetic truth flow."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis.data.pipeline import PipelineSpec, PrepError, load_pipeline
from phigenesis.data.records import (
    BOX_STATUSES,
    Boxes,
    CameraCalibration,
    CameraDepth,
    CameraFlow,
    CameraImage,
    Frame,
)
from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch, row_to_frame
from phigenesis.data.sources.synthetic import SyntheticConfig, synthetic_scene
from phigenesis.data.stages import run_stage
from phigenesis.data.stages.flow import (
    BoxMotion,
    BoxTrackTable,
    SceneFlowParams,
    camera_flow,
    flow_frame,
    points_flow,
    rigid_flow,
    yaw_rates,
)
from phigenesis.options import ConfigError
from tests.conftest import TINY_LIDAR

P = SceneFlowParams()
#: Camera axes (OpenCV) in the ego frame: z forward (ego +x), x right (ego -y), y down (ego -z).
EGO_FROM_CAMERA = np.eye(4)
EGO_FROM_CAMERA[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]


def one_box(center, yaw, velocity, size=(4.0, 2.0, 1.5), track="car", status="annotated") -> Boxes:
    return Boxes(
        track_id=[track],
        class_id=np.array([13], np.uint8),
        center_world=np.array([center], float),
        size_lwh=np.array([size], float),
        yaw_world=np.array([yaw], float),
        velocity_world=np.array([velocity], float),
        status=np.array([BOX_STATUSES.index(status)], np.uint8),
        instance_id=np.array([1], np.uint16),
        num_lidar_points=np.array([-1], np.int32),
    )


def moving(yaw_rate: float, confidence: float = 1.0) -> BoxMotion:
    return BoxMotion(np.array([yaw_rate]), np.array([True]), np.array([confidence], np.float32))


def reference_flow(p, c, v, omega):
    """The rigid motion's velocity, written independently: v + (0, 0, omega) x (p - c)."""
    return np.asarray(v, float) + np.cross([0.0, 0.0, omega], np.asarray(p, float) - np.asarray(c, float))


coordinate = st.floats(-200, 200)
speed = st.floats(-30, 30)
rate = st.floats(-2.0, 2.0)
unit = st.floats(-0.45, 0.45)


@settings(max_examples=200, deadline=None)
@given(
    cx=coordinate, cy=coordinate, cz=st.floats(-5, 5), yaw=st.floats(-np.pi, np.pi),
    vx=speed, vy=speed, vz=st.floats(-2, 2), omega=rate,
    ux=unit, uy=unit, uz=unit, dt_s=st.floats(-0.1, 0.1),
)  # fmt: skip
def test_a_point_on_a_rotating_translating_box_moves_with_the_rigid_motion(
    cx, cy, cz, yaw, vx, vy, vz, omega, ux, uy, uz, dt_s
):
    size = np.array([4.5, 1.9, 1.6])
    c, v = np.array([cx, cy, cz]), np.array([vx, vy, vz])
    boxes = one_box(c, yaw, v, size)
    # The point sits at box coordinates (u * size) on the box as it is dt_s later: centre moved by
    # v dt, box and velocity turned by omega dt about +z.
    turn = geometry.quaternion_to_matrix(geometry.yaw_to_quaternion(omega * dt_s))
    c_t = c + v * dt_s
    p = c_t + turn @ geometry.quaternion_to_matrix(geometry.yaw_to_quaternion(yaw)) @ (
        np.array([ux, uy, uz]) * size
    )
    got = points_flow(p[None], np.array([dt_s]), boxes, moving(omega), SceneFlowParams(clearance_m=0.0))
    want = reference_flow(p, c_t, turn @ v, omega)
    np.testing.assert_allclose(got[0], want, rtol=0, atol=2e-5 * (1 + np.abs(want).max()))
    # The library's rigid motion itself, at dt 0, is exactly the cross product.
    np.testing.assert_allclose(
        rigid_flow(p[None], c_t, v, omega)[0], reference_flow(p, c_t, v, omega), atol=1e-9
    )


def test_points_outside_moving_boxes_and_points_of_static_boxes_have_zero_flow():
    boxes = one_box([10.0, 0.0, 1.0], 0.3, [5.0, 0.0, 0.0])
    # Inside; 10 m beyond it; 5 cm above its bottom face (the road under a car: clearance_m 0.1).
    pts = np.array([[10.0, 0.0, 1.0], [20.0, 0.0, 1.0], [10.0, 0.0, 0.3]])
    flow = points_flow(pts, np.zeros(3), boxes, moving(0.2), P)
    np.testing.assert_allclose(flow[0], [5.0, 0.0, 0.0], atol=1e-6)
    assert not flow[1:].any()
    no_clearance = points_flow(pts, np.zeros(3), boxes, moving(0.2), SceneFlowParams(clearance_m=0.0))
    np.testing.assert_allclose(no_clearance[2], [5.0, 0.0, 0.0], atol=1e-6)
    static = BoxMotion(np.zeros(1), np.array([False]), np.ones(1, np.float32))
    assert not points_flow(pts, np.zeros(3), boxes, static, P).any()


def pinhole_camera(width: int = 64, height: int = 48, f: float = 40.0) -> CameraImage:
    k = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    cal = CameraCalibration("FRONT", width, height, k, np.zeros(5), EGO_FROM_CAMERA)
    return CameraImage(cal, 0, np.eye(4), None)


@settings(max_examples=60, deadline=None)
@given(
    yaw=st.floats(-np.pi, np.pi), vx=speed, vy=speed, omega=rate, depth=st.floats(7.5, 12.5),
    cy=st.floats(-1.5, 1.5),
)  # fmt: skip
def test_every_pixel_seeing_a_moving_box_gets_its_rigid_flow_and_no_other_pixel_any(
    yaw, vx, vy, omega, depth, cy
):
    cam = pinhole_camera()
    c, v = np.array([10.0, cy, 1.0]), np.array([vx, vy, 0.0])
    boxes = one_box(c, yaw, v)
    depth_m = np.full((48, 64), depth, np.float32)
    depth_m[:, :4] = 0.0  # no depth: unknown, confidence 0
    out = camera_flow(cam, boxes, moving(omega, 0.75), depth_m, P, backend="numpy")
    # Independent back-projection of every pixel: pinhole rays at the depth, camera -> ego = world.
    uv = geometry.pixel_grid(64, 48)
    rays = geometry.unproject_pixels(uv, cam.calibration.intrinsics, np.zeros(5))
    p = geometry.transform_points(EGO_FROM_CAMERA, rays * depth_m.reshape(-1, 1))
    local = (p - c) @ geometry.quaternion_to_matrix(geometry.yaw_to_quaternion(yaw))
    half = np.array([2.0, 1.0, 0.75])
    inside = (
        (np.abs(local[:, :2]) <= half[:2] + P.margin_m).all(axis=1)
        & (local[:, 2] <= half[2] + P.margin_m)
        & (local[:, 2] >= -half[2] + P.clearance_m)
        & (depth_m.reshape(-1) > 0)
    )
    np.testing.assert_array_equal(out.dynamic.reshape(-1), inside)
    want = np.where(inside[:, None], reference_flow(p, c, v, omega), 0.0)
    np.testing.assert_allclose(out.flow_world_mps.reshape(-1, 3), want, atol=1e-4 * (1 + np.abs(want).max()))
    conf = out.confidence.reshape(-1)
    np.testing.assert_array_equal(conf[inside], 0.75)
    known = depth_m.reshape(-1) > 0
    assert (conf[~inside & known] == 1).all() and (conf[~known] == 0).all()
    native = camera_flow(cam, boxes, moving(omega, 0.75), depth_m, P)  # the C pass where it builds
    for name in ("flow_world_mps", "dynamic", "confidence"):
        np.testing.assert_array_equal(getattr(native, name), getattr(out, name))


def track_frames(times_s, yaws, track="car") -> list[Frame]:
    """Frames of one track at ``times_s`` (seconds after 1 s) with the given yaws."""
    frames = []
    for i, (t, y) in enumerate(zip(times_s, yaws, strict=True)):
        box = one_box([10.0, 0, 1], y, [5, 0, 0], track=track)
        frames.append(Frame("s", i, int(1_000_000 + t * 1e6), np.eye(4), [], None, box))
    return frames


def test_yaw_rate_is_the_wrapped_difference_of_the_neighbours_yaws_across_pi():
    omega = 0.8
    times = np.array([0.0, 0.1, 0.2, 0.3])
    frames = track_frames(times, geometry.wrap_angle(np.pi - 0.1 + omega * times))  # crosses +pi
    table = BoxTrackTable(frames)
    rate, support = yaw_rates(frames[1].boxes, frames[1].timestamp_micros, table.at(0), table.at(2), 0.3)
    np.testing.assert_allclose(rate, [omega], atol=1e-9)
    assert support.tolist() == [1.0]
    rate, support = yaw_rates(frames[3].boxes, frames[3].timestamp_micros, table.at(2), table.at(4), 0.3)
    np.testing.assert_allclose(rate, [omega], atol=1e-9)  # one-sided at the scene's end
    assert support.tolist() == [0.75]


def test_a_track_seen_once_or_across_a_gap_turns_at_zero_with_lower_confidence():
    frames = track_frames([0.0, 0.1, 1.0], [0.0, 0.05, 0.5])
    table = BoxTrackTable(frames)
    rate, support = yaw_rates(frames[2].boxes, frames[2].timestamp_micros, table.at(1), table.at(3), 0.3)
    assert rate.tolist() == [0.0] and support.tolist() == [0.5]


def test_a_heading_flipped_by_pi_between_frames_is_not_taken_for_a_turn():
    frames = track_frames([0.0, 0.1, 0.2], [0.1, 0.1 + np.pi, 0.1])  # frame 1's label flipped
    table = BoxTrackTable(frames)
    # At the scene's end only the flipped neighbour is there: a one-sided difference of pi in 0.1 s.
    rate, support = yaw_rates(frames[2].boxes, frames[2].timestamp_micros, table.at(1), None, 0.3, 2.0)
    assert rate.tolist() == [0.0] and support.tolist() == [0.5]
    rate, _ = yaw_rates(frames[2].boxes, frames[2].timestamp_micros, table.at(1), None, 0.3)  # no limit
    np.testing.assert_allclose(np.abs(rate), [10 * np.pi])


def test_extrapolated_boxes_and_interpolated_ones_far_from_keyframes_have_lower_confidence():
    from phigenesis.data.stages.flow import status_confidence

    keyframes = np.array([0, 500_000, 1_000_000], np.int64)
    extrapolated = one_box([0, 0, 0], 0, [1, 0, 0], status="extrapolated")
    assert status_confidence(extrapolated, 0, keyframes).tolist() == [0.5]
    between = one_box([0, 0, 0], 0, [1, 0, 0], status="interpolated")
    np.testing.assert_allclose(status_confidence(between, 250_000, keyframes), [0.5])
    np.testing.assert_allclose(status_confidence(between, 100_000, keyframes), [0.8])


def test_a_box_with_a_nan_velocity_is_refused_naming_it():
    boxes = one_box([10.0, 0.0, 1.0], 0.0, [np.nan, 0.0, 0.0], track="abc")
    frame = Frame("s", 0, 0, np.eye(4), [], None, boxes)
    with pytest.raises(ValueError, match=r"scene s frame 0: box 'abc' has velocity_world \[nan, 0.0, 0.0\]"):
        flow_frame(frame, BoxTrackTable([frame]), np.zeros(0, np.int64), P)


def test_a_depth_map_with_nan_inside_a_moving_box_is_refused_naming_the_camera():
    depth = np.full((48, 64), 10.0, np.float32)
    depth[24, 32] = np.nan
    with pytest.raises(ValueError, match="camera FRONT at 0: the depth map holds non-finite values"):
        camera_flow(pinhole_camera(), one_box([10.0, 0, 1], 0, [5, 0, 0]), moving(0.0), depth, P)


def test_a_typo_in_the_stage_parameters_fails_when_the_spec_loads():
    spec = load_pipeline("waymo").to_dict()
    for stage in spec["stages"]:
        if stage["name"] == "scene_flow":
            stage["params"] = {"margin": 0.2}
    with pytest.raises(PrepError, match=r"stage \d+ \(scene_flow\): unknown keys \['margin'\]"):
        PipelineSpec.from_dict(spec)
    with pytest.raises(ConfigError, match=r"moving_mps = -1.0"):
        SceneFlowParams(moving_mps=-1.0)


def test_bundled_pipelines_run_scene_flow_after_completion_and_store_it():
    for name in ("synthetic", "waymo", "nuscenes"):
        spec = load_pipeline(name)
        names = [s.name for s in spec.stages]
        assert names.index("box_tracks") < names.index("aggregate_lidar")
        assert names.index("complete_depth") < names.index("scene_flow")
        assert spec.contents.scene_flow


# --------------------------------------------------------------------------------------------
# Against the synthetic truth


@pytest.fixture(scope="module")
def synthetic_flow() -> list[Frame]:
    """Four frames of a synthetic scene (two cars at about 8 m/s) whose cameras' depth is the exact
    truth depth, through box_tracks and scene_flow."""
    config = SyntheticConfig(scenes=1, frames=4, seed=3, height=96, width=144, lidar=TINY_LIDAR)
    scene = synthetic_scene(config, 0)

    def truth_depth(frame: Frame) -> Frame:
        for cam in frame.cameras:
            d = cam.truth.depth_m
            known = (d > 0).astype(np.float32)
            cam.depth = CameraDepth(d, known, np.zeros(d.shape, np.uint8), d, known)
        return frame

    scene = run_stage("box_tracks", scene, {})
    scene.frames = scene.frames.map(truth_depth)
    return list(run_stage("scene_flow", scene, {}).frames)


def test_flow_maps_from_exact_depth_match_the_synthetic_truth_on_moving_pixels(synthetic_flow):
    # With exact depth and exact boxes, what is left is the yaw rate's finite difference and the
    # pixels where the box (grown by margin_m) and the rendered mesh disagree: the mean end-point
    # error over the truth's moving pixels stays below 0.05 m/s (1 % of the cars' speed; measured
    # 0.006), and 99 % of them lie within 0.1 m/s (STORM's Acc10 threshold).
    errors, moving_px, dynamic_px, both = [], 0, 0, 0
    for frame in synthetic_flow:
        for cam in frame.cameras:
            truth = cam.truth.flow_world_mps
            is_moving = np.linalg.norm(truth, axis=-1) > P.moving_mps
            errors.append(np.linalg.norm(cam.flow.flow_world_mps - truth, axis=-1)[is_moving])
            moving_px += int(is_moving.sum())
            dynamic_px += int(cam.flow.dynamic.sum())
            both += int((cam.flow.dynamic & is_moving).sum())
    e = np.concatenate(errors)
    assert moving_px > 2000  # the cars are in view
    assert e.mean() < 0.05 and np.mean(e < 0.1) > 0.99, (e.mean(), np.mean(e < 0.1))
    assert both / moving_px > 0.99 and both / dynamic_px > 0.9, (both / moving_px, both / dynamic_px)


def test_static_pixels_and_static_lidar_points_get_zero_flow(synthetic_flow):
    for frame in synthetic_flow:
        for cam in frame.cameras:
            static = (np.linalg.norm(cam.truth.flow_world_mps, axis=-1) == 0) & (cam.truth.depth_m > 0)
            assert not cam.flow.flow_world_mps[static].any()
        sweep = frame.lidar
        on_stuff = sweep.instance == 0
        assert on_stuff.sum() > 100 and not sweep.flow_world_mps[on_stuff].any()


def test_lidar_points_on_moving_cars_take_their_boxes_velocity(synthetic_flow):
    hits = 0
    for frame in synthetic_flow:
        sweep, boxes = frame.lidar, frame.boxes
        for k in np.flatnonzero(np.linalg.norm(boxes.velocity_world[:, :2], axis=1) > 5):
            mine = sweep.instance == boxes.instance_id[k]
            hits += int(mine.sum())
            # A car's points move at its centre's velocity plus omega x r: within 0.1 m/s of it
            # for the slight turns of the synthetic roads.
            diff = sweep.flow_world_mps[mine, :2] - boxes.velocity_world[k, :2]
            assert np.abs(diff).max(initial=0.0) < 0.1
    assert hits > 20


# --------------------------------------------------------------------------------------------
# Cache columns


def test_flow_maps_round_trip_through_the_cache_and_old_caches_read_without_them(synthetic_flow):
    frame = synthetic_flow[1]
    with_flow = frame_schema(CacheContents(scene_flow=True, camera_truth=()))
    back = row_to_frame(frame_to_batch(frame, "synthetic", with_flow))
    for a, b in zip(frame.cameras, back.cameras, strict=True):
        np.testing.assert_allclose(b.flow.flow_world_mps, a.flow.flow_world_mps, atol=0.5 / 256)
        np.testing.assert_array_equal(b.flow.dynamic, a.flow.dynamic)
        np.testing.assert_allclose(b.flow.confidence, a.flow.confidence, atol=0.5 / 255)
    np.testing.assert_allclose(back.lidar.flow_world_mps, frame.lidar.flow_world_mps)
    old = row_to_frame(frame_to_batch(frame, "synthetic", frame_schema(CacheContents(camera_truth=()))))
    assert all(c.flow is None for c in old.cameras) and old.lidar.flow_world_mps is None


def test_camera_flow_records_refuse_maps_of_another_size():
    with pytest.raises(ValueError, match="flow dynamic must have shape"):
        CameraFlow(np.zeros((4, 5, 3), np.float32), np.zeros((4, 6), bool), np.zeros((4, 5), np.float32))
    cam = pinhole_camera()
    small = CameraFlow(np.zeros((4, 5, 3), np.float32), np.zeros((4, 5), bool), np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError, match="camera FRONT flow is"):
        dataclasses.replace(cam, flow=small)


# --------------------------------------------------------------------------------------------
# Stage 1's targets


def test_stage1_takes_moving_pixels_from_the_flow_maps_leaving_unconfident_ones_unknown():
    import torch

    from phigenesis.data.clips import MIN_FLOW_CONFIDENCE, _stage_flow_pixels

    flow = torch.zeros(1, 3, 2, 3)
    flow[0, :, 0, 0] = torch.tensor([4.0, 1.0, 0.0])
    flow[0, :, 0, 1] = torch.tensor([2.0, 0.0, 0.0])
    frame = {
        "flow_world": flow,
        "flow_dynamic": torch.tensor([[[1, 1, 0], [0, 0, 0]]], dtype=torch.uint8),
        "flow_confidence": torch.tensor([[[1.0, MIN_FLOW_CONFIDENCE / 2, 1.0], [1.0, 1.0, 0.0]]]),
    }
    depth = torch.tensor([[[5.0, 5.0, 5.0], [5.0, 5.0, 0.0]]])
    moving, velocity = _stage_flow_pixels(frame, depth, (2, 3))
    assert moving.tolist() == [[[1.0, -1.0, 0.0], [0.0, 0.0, -1.0]]]
    assert velocity[0, 0, 0].tolist() == [4.0, 1.0, 0.0] and not velocity[0, 0, 1:].any()
    assert _stage_flow_pixels({}, depth, (2, 3)) is None  # a cache without the stage's maps


def test_the_native_pixel_pass_agrees_with_the_numpy_reference_on_a_synthetic_frame(synthetic_flow):
    from phigenesis.data.native import load_scene_flow_pixels
    from phigenesis.data.stages.flow import boxes_moved, frame_motion

    if load_scene_flow_pixels() is None:
        pytest.skip("the native kernels do not build here")
    table = BoxTrackTable(synthetic_flow)
    dynamic = 0
    for frame in synthetic_flow:
        kf = np.zeros(0, np.int64)
        motion = frame_motion(frame, frame.boxes, frame.timestamp_micros, table, kf, P, "f")
        for cam in frame.cameras:
            dt_s = (cam.timestamp_micros - frame.timestamp_micros) * 1e-6
            boxes = boxes_moved(frame.boxes, motion.yaw_rate_radps, dt_s)
            ref = camera_flow(cam, boxes, motion, cam.depth.dense_m, P, backend="numpy")
            fast = camera_flow(cam, boxes, motion, cam.depth.dense_m, P)
            np.testing.assert_array_equal(fast.dynamic, ref.dynamic)
            np.testing.assert_allclose(fast.flow_world_mps, ref.flow_world_mps, rtol=0, atol=1e-5)
            np.testing.assert_array_equal(fast.confidence, ref.confidence)
            np.testing.assert_array_equal(fast.flow_world_mps, cam.flow.flow_world_mps)  # the stage's
            dynamic += int(ref.dynamic.sum())
    assert dynamic > 2000
