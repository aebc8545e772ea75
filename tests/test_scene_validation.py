"""The scene model refuses invalid values at construction, naming the field, and gives sources the
helpers that leave out (and count) what may be left out: LiDAR points and boxes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from phigenesis import geometry
from phigenesis.data import records
from phigenesis.errors import PhiGenesisError

T0 = 1_600_000_000_000_000


def _calibration(
    name: str = "FRONT", width: int = 8, height: int = 6, **changes: object
) -> records.CameraCalibration:
    values: dict[str, object] = {
        "name": name,
        "width": width,
        "height": height,
        "intrinsics": geometry.intrinsic_matrix(10.0, 10.0, 3.5, 2.5),
        "distortion": np.zeros(5),
        "ego_from_camera": np.eye(4),
    }
    values.update(changes)
    return records.CameraCalibration(**values)  # type: ignore[arg-type]


def _jpeg(width: int, height: int) -> bytes:
    return cv2.imencode(".jpg", np.zeros((height, width, 3), np.uint8))[1].tobytes()


def _box_fields(m: int = 3) -> dict[str, object]:
    return {
        "track_id": [f"t{i}" for i in range(m)],
        "class_id": np.full(m, 13, np.uint8),
        "center_world": np.arange(3 * m, dtype=np.float64).reshape(m, 3),
        "size_lwh": np.tile([4.0, 2.0, 1.5], (m, 1)),
        "yaw_world": np.zeros(m),
        "velocity_world": np.zeros((m, 3)),
        "status": np.zeros(m, np.uint8),
        "instance_id": np.arange(1, m + 1, dtype=np.uint16),
        "num_lidar_points": np.full(m, -1, np.int32),
    }


def _sweep_fields(n: int = 5) -> dict[str, object]:
    return {
        "timestamp_micros": T0,
        "world_from_ego": np.eye(4),
        "points_ego": np.arange(3 * n, dtype=np.float32).reshape(n, 3),
        "intensity": np.linspace(0, 1, n, dtype=np.float32),
        "beam_index": np.arange(n, dtype=np.uint16),
        "origins_ego": np.zeros((n, 3), np.float32),
        "time_offset_micros": np.arange(n, dtype=np.int32),
        "lidar_id": np.zeros(n, np.uint8),
        "elongation": np.full(n, 0.5, np.float32),
        "return_index": np.zeros(n, np.uint8),
    }


def _frame(t: int = T0, cameras: list | None = None, **changes: object) -> records.Frame:
    values: dict[str, object] = {
        "scene_id": "s",
        "frame_index": 0,
        "timestamp_micros": t,
        "world_from_ego": np.eye(4),
        "cameras": cameras or [],
        "lidar": None,
        "boxes": records.Boxes.empty(),
    }
    values.update(changes)
    return records.Frame(**values)  # type: ignore[arg-type]


def _pose(rotation: np.ndarray, translation: tuple[float, float, float] = (1.0, 2.0, 3.0)) -> np.ndarray:
    return geometry.make_transform(rotation, np.array(translation))


# --------------------------------------------------------------------------------------------
# Poses


def test_a_pose_with_a_nan_entry_is_refused_naming_the_field() -> None:
    pose = np.eye(4)
    pose[0, 3] = np.nan
    with pytest.raises(ValueError, match=r"^world_from_ego has non-finite entries \[1, 0, 0, nan"):
        _frame(world_from_ego=pose)


def test_a_pose_scaled_by_a_million_is_not_a_rigid_transform() -> None:
    with pytest.raises(
        ValueError, match=r"world_from_ego is not a rigid transform: its rotation is not orthonormal"
    ):
        _frame(world_from_ego=_pose(np.eye(3) * 1e6))


def test_a_mirroring_pose_is_not_a_rigid_transform() -> None:
    with pytest.raises(
        ValueError, match=r"camera FRONT ego_from_camera is not a rigid transform: .*reflection"
    ):
        _calibration(ego_from_camera=_pose(np.diag([1.0, 1.0, -1.0])))


def test_a_rotation_stored_as_float32_is_rigid_within_the_tolerance() -> None:
    rotation = geometry.euler_zyx_to_matrix(0.01, -0.02, 2.5).astype(np.float32).astype(np.float64)
    frame = _frame(world_from_ego=_pose(rotation))
    np.testing.assert_array_equal(frame.world_from_ego[:3, :3], rotation)


def test_a_translation_beyond_ten_thousand_kilometres_is_refused() -> None:
    with pytest.raises(
        ValueError, match=r"world_from_ego has a translation \[1e\+08, 2, 3\] m beyond 1e\+07 m"
    ):
        _frame(world_from_ego=_pose(np.eye(3), (1e8, 2.0, 3.0)))


def test_check_transform_names_a_lidar_extrinsic_for_sources() -> None:
    bad = np.eye(4)
    bad[:3, :3] *= 2.0
    with pytest.raises(records.InvalidRecord, match="LiDAR TOP extrinsic is not a rigid transform") as err:
        records.check_transform("LiDAR TOP extrinsic", bad)
    assert err.value.field == "LiDAR TOP extrinsic" and not isinstance(err.value, PhiGenesisError)


# --------------------------------------------------------------------------------------------
# Cameras


@pytest.mark.parametrize(
    ("intrinsics", "words"),
    [
        (geometry.intrinsic_matrix(np.nan, 10.0, 3.5, 2.5), "has non-finite entries"),
        (
            geometry.intrinsic_matrix(0.0, 10.0, 3.5, 2.5),
            r"has focal length fx = 0 px, not in \[0.1, 1e\+06\]",
        ),
        (geometry.intrinsic_matrix(10.0, -10.0, 3.5, 2.5), r"has focal length fy = -10 px"),
        (geometry.intrinsic_matrix(10.0, 10.0, 1e9, 2.5), r"has a principal point or skew beyond 1e\+06 px"),
    ],
)
def test_camera_intrinsics_must_be_finite_and_positive(intrinsics: np.ndarray, words: str) -> None:
    with pytest.raises(ValueError, match=rf"camera FRONT intrinsics {words}"):
        _calibration(intrinsics=intrinsics)


def test_an_image_size_must_be_between_one_and_the_maximum_side() -> None:
    with pytest.raises(ValueError, match=r"camera FRONT width is 0 pixels, not in \[1, 8192\]"):
        _calibration(width=0)
    with pytest.raises(ValueError, match=r"camera FRONT height is 100000 pixels"):
        _calibration(height=100_000)


def test_a_nan_distortion_coefficient_is_refused() -> None:
    with pytest.raises(ValueError, match=r"camera FRONT distortion \[nan, 0, 0, 0, 0\] must be finite"):
        _calibration(distortion=np.array([np.nan, 0, 0, 0, 0]))


def test_a_jpeg_whose_size_differs_from_its_calibration_is_refused() -> None:
    cal = _calibration(width=8, height=6)
    records.CameraImage(cal, T0, np.eye(4), _jpeg(8, 6))  # the right size is fine
    with pytest.raises(
        ValueError, match=r"camera FRONT image_bytes is a 10x6 JPEG, the calibration says 8x6"
    ):
        records.CameraImage(cal, T0, np.eye(4), _jpeg(10, 6))


def test_image_bytes_that_are_not_an_image_are_refused_before_anything_decodes_them() -> None:
    cal = _calibration()
    with pytest.raises(ValueError, match="camera FRONT image_bytes holds 4 bytes that are not a JPEG image"):
        records.CameraImage(cal, T0, np.eye(4), b"\xff\xd8\xff\xe0")
    png = cv2.imencode(".png", np.zeros((6, 8, 3), np.uint8))[1].tobytes()
    with pytest.raises(ValueError, match="not a JPEG image"):
        records.CameraImage(cal, T0, np.eye(4), png, "jpeg")
    assert records.CameraImage(cal, T0, np.eye(4), png, "png").image_bytes == png


def test_encoded_image_size_reads_the_headers_of_jpeg_and_png() -> None:
    assert records.encoded_image_size(_jpeg(37, 11), "jpeg") == (37, 11)
    progressive = cv2.imencode(".jpg", np.zeros((5, 9, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1]
    assert records.encoded_image_size(progressive.tobytes(), "jpeg") == (9, 5)
    png16 = cv2.imencode(".png", np.zeros((3, 70000 // 1000, 1), np.uint16))[1].tobytes()
    assert records.encoded_image_size(png16, "png") == (70, 3)
    # A header that declares a gigapixel image is read, not decoded: the caller compares it.
    huge = bytearray(png16)
    huge[16:20] = (60000).to_bytes(4, "big")
    assert records.encoded_image_size(bytes(huge), "png") == (60000, 3)


@pytest.mark.parametrize(
    ("name", "value", "words"),
    [
        ("shutter_micros", np.nan, r"shutter_micros is nan us, not in \[0, 5000000\]"),
        ("readout_micros", 1e18, r"readout_micros is 1e\+18 us"),
        ("velocity_world_mps", np.array([np.inf, 0, 0]), r"velocity_world_mps has non-finite entries \[inf"),
        (
            "angular_velocity_world_radps",
            np.array([0, np.nan, 0]),
            "angular_velocity_world_radps has non-finite",
        ),
        (
            "trigger_micros",
            T0 + 10_000_000,
            r"trigger_micros is 1600000010000000 us, \+10 s from the image's time",
        ),
    ],
)
def test_camera_timing_and_velocity_must_be_finite_and_plausible(
    name: str, value: object, words: str
) -> None:
    with pytest.raises(ValueError, match=rf"camera FRONT {words}"):
        records.CameraImage(_calibration(), T0, np.eye(4), None, **{name: value})  # type: ignore[arg-type]


def test_a_camera_far_from_its_frames_time_is_refused_and_a_near_one_is_not() -> None:
    near = records.CameraImage(_calibration(), T0 + 40_000, np.eye(4), None)
    assert _frame(cameras=[near]).cameras == [near]
    far = records.CameraImage(_calibration(), 10**18, np.eye(4), None)
    with pytest.raises(
        ValueError, match=r"camera FRONT timestamp_micros is 1000000000000000000 us, \+9\.984e\+11 s"
    ):
        _frame(cameras=[far])
    late = records.CameraImage(_calibration(), T0 + 6_000_000, np.eye(4), None)
    with pytest.raises(ValueError, match=r"\+6 s from its frame's time 1600000000000000 us \(at most 5 s\)"):
        _frame(cameras=[late])


# --------------------------------------------------------------------------------------------
# Frames and their order


def test_a_negative_frame_time_is_refused() -> None:
    with pytest.raises(ValueError, match=r"^timestamp_micros is -5 us, negative"):
        _frame(t=-5)


def test_check_frame_times_names_the_first_repeated_or_earlier_time() -> None:
    records.check_frame_times([0, 100, 200])
    with pytest.raises(
        records.InvalidRecord, match=r"frame 2 timestamp_micros is 100 us, the same as frame 1's"
    ) as err:
        records.check_frame_times([0, 100, 100, 300])
    assert err.value.index == 2
    with pytest.raises(
        records.InvalidRecord, match=r"keyframe 1 timestamp_micros is 50 us, before keyframe 0's 100"
    ):
        records.check_frame_times([100, 50], "keyframe")
    with pytest.raises(records.InvalidRecord, match="frame 0 timestamp_micros is -1 us, negative") as err:
        records.check_frame_times([-1, 5])
    assert err.value.index == 0


def test_increasing_frames_loses_one_frame_per_bad_time_not_every_frame_after_it() -> None:
    times = [0, 100, 100, 50, 300, 10**15, 400, -7, 500]
    assert records.increasing_frames(times) == [0, 1, 4, 6, 8]
    assert records.increasing_frames([]) == []
    assert records.increasing_frames([5, 4, 3]) == [0]


def test_lazy_frames_refuse_an_index_out_of_order_and_a_frame_that_disagrees_with_it() -> None:
    def load(i: int) -> records.Frame:
        return _frame(t=T0 + 100 * i if i != 2 else T0 + 5, frame_index=i)

    with pytest.raises(records.InvalidRecord, match=r"frame 1 timestamp_micros .* the same as frame 0's"):
        records.LazyFrames(3, load, timestamps_micros=[T0, T0, T0 + 1])
    frames = records.LazyFrames(3, load, timestamps_micros=[T0, T0 + 100, T0 + 200])
    assert frames[1].timestamp_micros == T0 + 100
    with pytest.raises(
        records.InvalidRecord, match=r"frame 2 timestamp_micros was loaded as 1600000000000005 us"
    ):
        frames[2]


def test_lazy_frames_without_an_index_compare_each_frame_with_its_loaded_neighbours() -> None:
    times = [T0, T0 + 100, T0 + 100, T0 + 300]
    frames = records.LazyFrames(4, lambda i: _frame(t=times[i], frame_index=i))
    assert frames[0].timestamp_micros == T0 and frames[3].timestamp_micros == T0 + 300
    assert frames[1].timestamp_micros == T0 + 100
    with pytest.raises(
        records.InvalidRecord, match=r"frame 2 timestamp_micros is 1600000000000100 us, not after frame 1's"
    ):
        frames[2]
    # Stages wrapping the frames see the same check.
    mapped = records.LazyFrames(4, lambda i: _frame(t=times[i], frame_index=i)).map(lambda f: f)
    with pytest.raises(records.InvalidRecord, match="not after frame 1's"):
        list(mapped)


def test_a_scene_refuses_frames_and_keyframes_out_of_order_and_two_cameras_of_one_name() -> None:
    frames = [_frame(t=T0 + 100), _frame(t=T0)]
    with pytest.raises(records.InvalidRecord, match=r"frame 1 timestamp_micros .* before frame 0's"):
        records.Scene("s", "x", [], frames)
    keyframes = [
        records.KeyframeBoxes(T0, records.Boxes.empty()),
        records.KeyframeBoxes(T0, records.Boxes.empty()),
    ]
    with pytest.raises(
        records.InvalidRecord, match=r"keyframe 1 timestamp_micros .* the same as keyframe 0's"
    ):
        records.Scene("s", "x", [], [], keyframes=keyframes)
    with pytest.raises(records.InvalidRecord, match="scene s calibrations have duplicate camera names"):
        records.Scene("s", "x", [_calibration(), _calibration()], [])


# --------------------------------------------------------------------------------------------
# Boxes


@pytest.mark.parametrize(
    ("field", "row", "words"),
    [
        ("size_lwh", [np.nan, 2.0, 1.5], r"size_lwh \[nan, 2, 1.5\] must be finite and in \(0, 1000\] m"),
        ("size_lwh", [4.0, 0.0, 1.5], r"size_lwh \[4, 0, 1.5\] must be finite and in \(0, 1000\] m"),
        ("size_lwh", [4.0, 2.0, 1e6], "size_lwh"),
        (
            "center_world",
            [np.inf, 0.0, 0.0],
            r"center_world \[inf, 0, 0\] must be finite and within 1e\+07 m",
        ),
        ("velocity_world", [0.0, -np.inf, 0.0], r"velocity_world \[0, -inf, 0\] must be finite"),
        (
            "acceleration_world",
            [np.inf, 0.0, 0.0],
            r"acceleration_world \[inf, 0, 0\] must be finite \(or NaN",
        ),
        ("orientation_world", [0.0, 0.0, 0.0, 0.0], "orientation_world .* finite, non-zero quaternion"),
    ],
)
def test_a_box_with_an_invalid_field_is_refused_naming_its_track_and_field(
    field: str, row: list, words: str
) -> None:
    values = _box_fields()
    defaults = {"orientation_world": np.tile([1.0, 0, 0, 0], (3, 1)), "acceleration_world": np.zeros((3, 3))}
    array = np.array(values.get(field, defaults.get(field)), np.float64)
    array[1] = row
    values[field] = array
    with pytest.raises(ValueError, match=rf"^box 't1' {words}"):
        records.Boxes(**values)  # type: ignore[arg-type]


def test_a_nan_yaw_is_refused_and_nan_acceleration_means_unknown() -> None:
    values = _box_fields()
    values["yaw_world"] = np.array([0.0, 0.0, np.nan])
    with pytest.raises(ValueError, match=r"box 't2' yaw_world \[nan\] must be finite"):
        records.Boxes(**values)  # type: ignore[arg-type]
    boxes = records.Boxes(**_box_fields(), acceleration_world=np.full((3, 3), np.nan))  # type: ignore[arg-type]
    assert np.isnan(boxes.acceleration_world).all()


def test_without_invalid_leaves_out_only_the_bad_boxes_and_says_which() -> None:
    values = _box_fields(4)
    values["size_lwh"][1, 0] = np.nan  # type: ignore[index]
    values["velocity_world"][3] = np.nan  # type: ignore[index]
    boxes, problems = records.Boxes.without_invalid(**values)
    assert boxes.track_id == ["t0", "t2"]
    np.testing.assert_array_equal(boxes.center_world, np.arange(12, dtype=np.float64).reshape(4, 3)[[0, 2]])
    np.testing.assert_array_equal(boxes.instance_id, [1, 3])
    assert [(p.index, p.field) for p in problems] == [(1, "box 't1'"), (3, "box 't3'")]
    assert "size_lwh [nan, 2, 1.5]" in str(problems[0]) and "velocity_world [nan, nan, nan]" in str(
        problems[1]
    )
    # Keyframe annotations may leave the velocity unknown (interpolate_boxes fills it in).
    kept, problems = records.Boxes.without_invalid(
        velocity_known=False, **_box_fields(4) | {"velocity_world": values["velocity_world"]}
    )
    assert len(kept) == 4 and not problems


# --------------------------------------------------------------------------------------------
# LiDAR sweeps


def test_a_sweep_with_non_finite_points_is_refused_and_says_how_to_leave_them_out() -> None:
    values = _sweep_fields()
    values["points_ego"][2, 1] = np.nan  # type: ignore[index]
    with pytest.raises(
        ValueError,
        match=r"lidar points_ego has 1 of 5 points with non-finite values .*point 2.*without_invalid_points",
    ):
        records.LidarSweep(**values)  # type: ignore[arg-type]


def test_without_invalid_points_drops_bad_points_with_all_their_fields_and_counts_them() -> None:
    values = _sweep_fields(6)
    values["points_ego"][0, 0] = np.inf  # type: ignore[index]
    values["points_ego"][2, 2] = 2e4  # beyond MAX_POINT_DISTANCE_M  # type: ignore[index]
    values["origins_ego"][3, 1] = np.nan  # type: ignore[index]
    values["intensity"][4] = np.nan  # type: ignore[index]
    sweep, dropped = records.LidarSweep.without_invalid_points(**values)
    assert dropped == 4 and len(sweep) == 2
    np.testing.assert_array_equal(sweep.beam_index, [1, 5])
    np.testing.assert_array_equal(sweep.time_offset_micros, [1, 5])
    np.testing.assert_array_equal(sweep.points_ego, np.arange(18, dtype=np.float32).reshape(6, 3)[[1, 5]])
    assert sweep.elongation is not None and len(sweep.elongation) == 2
    assert sweep.semantic is None
    clean, none = records.LidarSweep.without_invalid_points(**_sweep_fields(3))
    assert none == 0 and len(clean) == 3


def test_float64_points_beyond_float32_are_dropped_not_stored_as_inf() -> None:
    values = _sweep_fields(2)
    values["points_ego"] = np.array([[1e39, 0, 0], [1.0, 2.0, 3.0]])
    sweep, dropped = records.LidarSweep.without_invalid_points(**values)
    assert dropped == 1 and sweep.points_ego.tolist() == [[1.0, 2.0, 3.0]]


def test_a_sweep_with_an_invalid_pose_still_raises_from_the_helper() -> None:
    values = _sweep_fields()
    values["world_from_ego"] = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(records.InvalidRecord, match="lidar world_from_ego is not a rigid transform"):
        records.LidarSweep.without_invalid_points(**values)
