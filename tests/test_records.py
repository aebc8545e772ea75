"""The scene model rejects malformed records with messages that name the field and the shapes."""

from __future__ import annotations

import numpy as np
import pytest

from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraImage,
    CameraTruth,
    Frame,
    LazyFrames,
    LidarSweep,
    decode_rgb,
    encode_rgb,
)


def _calibration(name: str = "FRONT", width: int = 8, height: int = 6) -> CameraCalibration:
    k = np.array([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]])
    return CameraCalibration(name, width, height, k, np.zeros(5), np.eye(4))


def test_calibration_rejects_a_wrong_intrinsics_shape_naming_it():
    with pytest.raises(ValueError, match=r"intrinsics must have shape \(3, 3\), got \(9,\)"):
        CameraCalibration("FRONT", 8, 6, np.zeros(9), np.zeros(5), np.eye(4))


def test_calibration_rejects_a_non_rigid_transform():
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(ValueError, match="ego_from_camera is not a rigid transform"):
        CameraCalibration("FRONT", 8, 6, np.eye(3), np.zeros(5), bad)


def test_camera_image_rejects_truth_of_another_size():
    truth = CameraTruth(
        np.zeros((5, 8), np.float32),
        np.zeros((5, 8), np.uint8),
        np.zeros((5, 8), np.uint16),
        np.zeros((5, 8, 3), np.float32),
    )
    with pytest.raises(ValueError, match=r"truth is \(5, 8\), calibration says \(6, 8\)"):
        CameraImage(_calibration(), 0, np.eye(4), None, truth=truth)


def test_camera_image_without_image_says_so_when_decoded():
    cam = CameraImage(_calibration(), 123, np.eye(4), None)
    with pytest.raises(ValueError, match="has no image"):
        cam.decode_image()


def test_png_images_round_trip_exactly_and_garbage_does_not_decode():
    rgb = np.random.default_rng(0).integers(0, 255, size=(6, 8, 3), dtype=np.uint8)
    assert np.array_equal(decode_rgb(encode_rgb(rgb, "png"), "test"), rgb)
    with pytest.raises(ValueError, match=r"^camera X image_bytes holds 12 bytes that are neither a JPEG"):
        decode_rgb(b"not an image", "camera X")
    with pytest.raises(ValueError, match=r"^camera X image_bytes holds 4 bytes that do not decode$"):
        decode_rgb(b"\xff\xd8\xff\xd9", "camera X")


def test_lidar_sweep_checks_per_point_arrays_against_the_point_count():
    n = 4
    with pytest.raises(ValueError, match=r"intensity must have shape \(4\), got \(3,\)"):
        LidarSweep(
            0,
            np.eye(4),
            np.zeros((n, 3)),
            np.zeros(3),
            np.zeros(n),
            np.zeros((n, 3)),
            np.zeros(n),
            np.zeros(n),
        )


def test_empty_lidar_sweep_has_no_points_and_valid_world_points():
    sweep = LidarSweep.empty(5, np.eye(4))
    assert len(sweep) == 0 and sweep.points_world().shape == (0, 3)


def test_boxes_wrap_yaw_and_select_by_mask_and_index():
    boxes = Boxes(
        ["a", "b", "c"],
        np.array([13, 11, 13]),
        np.zeros((3, 3)),
        np.ones((3, 3)),
        np.array([np.pi, 3 * np.pi / 2, 0.1]),
        np.zeros((3, 3)),
        np.array([0, 1, 2]),
        np.array([1, 2, 3]),
        np.full(3, -1),
    )
    assert boxes.yaw_world[0] == pytest.approx(-np.pi)
    assert boxes.yaw_world[1] == pytest.approx(-np.pi / 2)
    assert boxes.select(np.array([True, False, True])).track_id == ["a", "c"]
    assert boxes.select(np.array([1])).status_names() == ["interpolated"]
    assert boxes.corners_world().shape == (3, 8, 3)


def test_boxes_reject_unknown_status_codes_and_sizes_that_are_not_positive():
    args = dict(
        track_id=["a"],
        class_id=np.array([13]),
        center_world=np.zeros((1, 3)),
        yaw_world=np.zeros(1),
        velocity_world=np.zeros((1, 3)),
        instance_id=np.array([1]),
        num_lidar_points=np.array([0]),
    )
    with pytest.raises(ValueError, match="status codes"):
        Boxes(size_lwh=np.ones((1, 3)), status=np.array([7]), **args)
    with pytest.raises(
        ValueError, match=r"box 'a' size_lwh \[-1, -1, -1\] must be finite and in \(0, 1000\] m"
    ):
        Boxes(size_lwh=-np.ones((1, 3)), status=np.array([0]), **args)


def test_frame_rejects_duplicate_camera_names_and_finds_cameras_by_name():
    cams = [
        CameraImage(_calibration("FRONT"), 0, np.eye(4), None),
        CameraImage(_calibration("SIDE"), 0, np.eye(4), None),
    ]
    frame = Frame("s", 0, 0, np.eye(4), cams, None, Boxes.empty())
    assert frame.camera("SIDE") is cams[1]
    with pytest.raises(KeyError, match="no camera 'REAR'"):
        frame.camera("REAR")
    with pytest.raises(ValueError, match="duplicate camera names"):
        Frame("s", 0, 0, np.eye(4), [cams[0], cams[0]], None, Boxes.empty())


def test_lazy_frames_load_on_access_and_map_lazily():
    loaded: list[int] = []

    def load(i: int) -> Frame:
        loaded.append(i)
        return Frame("s", i, i * 100, np.eye(4), [], None, Boxes.empty())

    frames = LazyFrames(3, load)
    shifted = frames.map(
        lambda f: Frame(
            f.scene_id, f.frame_index, f.timestamp_micros + 1, f.world_from_ego, [], None, f.boxes
        )
    )
    assert loaded == []
    assert shifted[-1].timestamp_micros == 201 and loaded == [2]
    assert [f.frame_index for f in frames[0:2]] == [0, 1]
    with pytest.raises(IndexError):
        frames[3]


def test_dropped_values_count_each_frame_once_however_often_it_loads():
    from phigenesis.data.records import DroppedValues

    dropped = DroppedValues()
    what = "LiDAR points with non-finite coordinates"
    dropped.add(what, 0, 5)
    dropped.add(what, 0, 5)  # frame 0 loaded a second time (geometry pass, then the full frame)
    dropped.add(what, 2, 1)
    dropped.add("boxes with a non-finite field", 1, 0)  # nothing dropped: not recorded
    assert dropped.totals() == {what: 6}
    assert dropped.describe() == f"6 {what} (2 frames)"
