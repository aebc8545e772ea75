"""The recording vehicles' bodies sit below and around every sensor of their rigs, and the depth
stages refuse a body that holds a camera centre or a LiDAR origin, naming the scene, the sensor and
the box (a body over a camera made every nuScenes pixel "ego body" and erased the depth)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from phigenesis import geometry
from phigenesis.data.ego_body import (
    NUSCENES_ZOE_BOXES,
    WAYMO_PACIFICA_BOXES,
    camera_centres,
    check_sensors_outside,
    lidar_origins,
)
from phigenesis.data.records import CameraCalibration, CameraImage, Scene
from phigenesis.data.sources.synthetic import EGO_BOXES, SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec, camera_calibrations
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.aggregate import DEFAULT_EGO_BOXES
from phigenesis.data.stages.project import ego_body_depth, pixel_rays, ray_box_depths
from phigenesis.errors import PrepError

#: nuScenes' LIDAR_TOP mount (calibrated_sensor of v1.0; 1.84 m above the road, devkit issue #161).
NUSCENES_LIDAR_TOP = (0.943713, 0.0, 1.84023)
#: The sensors of the Waymo sample frame (one_frame_five_cameras_panoptic.tfrecord in the shared
#: Waymo samples): the translations of its camera and laser calibrations, vehicle frame, metres.
WAYMO_SAMPLE_CAMERAS = {
    "FRONT": (1.539, -0.024, 2.115),
    "FRONT_LEFT": (1.493, 0.091, 2.115),
    "FRONT_RIGHT": (1.490, -0.094, 2.116),
    "SIDE_LEFT": (1.432, 0.111, 2.115),
    "SIDE_RIGHT": (1.428, -0.112, 2.116),
}
WAYMO_SAMPLE_LIDARS = {
    "TOP": (1.430, 0.0, 2.184),
    "FRONT": (4.070, 0.0, 0.689),
    "REAR": (-1.155, 0.0, 0.464),
    "SIDE_LEFT": (3.245, 1.025, 0.979),
    "SIDE_RIGHT": (3.245, -1.025, 0.979),
}
#: The body every nuScenes and Waymo scene got before: one 1.8 m box around the rear axle.
OLD_DEFAULT_BOXES = [{"center_ego": [1.4, 0.0, 0.9], "size_lwh": [5.0, 2.1, 1.8]}]
SMALL_LIDAR = LidarSpec(beams=16, columns=256, sectors=8)


def clearance_m(position: tuple[float, float, float], boxes: list[dict]) -> float:
    """Distance (metres) from a point to the nearest box of a body (0 inside)."""
    p = np.asarray(position, np.float64)
    gaps = [
        np.linalg.norm(np.maximum(np.abs(p - b["center_ego"]) - 0.5 * np.asarray(b["size_lwh"]), 0.0))
        for b in boxes
    ]
    return float(min(gaps))


def ego_pixels(calibration: CameraCalibration, boxes: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) True where the pixel's ray enters the body, and (H, W) True where the ray points
    at or above the ego's horizon (z of its ego-frame direction >= 0)."""
    camera = CameraImage(calibration, 0, np.eye(4), None)
    rays = pixel_rays(camera)
    body = np.isfinite(ego_body_depth(camera, boxes, rays))
    up = (rays @ calibration.ego_from_camera[:3, :3].T)[:, 2] >= 0
    return body, up.reshape(body.shape)


def nuscenes6_scene(ego_boxes: list[dict] | None) -> Scene:
    """A small nuScenes-rig synthetic scene with the given body in its metadata (None: none)."""
    cfg = SyntheticConfig(scenes=1, frames=2, seed=5, rig="nuscenes6", height=32, width=48, lidar=SMALL_LIDAR)
    scene = SyntheticScene(cfg, 0).scene()
    if ego_boxes is None:
        del scene.metadata["ego_boxes"]
    else:
        scene.metadata["ego_boxes"] = ego_boxes
    return scene


# --------------------------------------------------------------------------------------------
# The bodies


def test_the_zoe_holds_no_nuscenes_camera_and_not_the_lidar():
    cameras = camera_centres(camera_calibrations("nuscenes6", 32, 48)[0])  # nuScenes' own mounts
    check_sensors_outside("nuScenes rig", NUSCENES_ZOE_BOXES, {**cameras, "LiDAR 0": NUSCENES_LIDAR_TOP})
    assert min(clearance_m(tuple(p), NUSCENES_ZOE_BOXES) for p in cameras.values()) > 0.07
    assert clearance_m(NUSCENES_LIDAR_TOP, NUSCENES_ZOE_BOXES) > 0.2
    # One box of the car's size (4.084 x 1.730 x 1.562 m) would hold every front camera.
    whole_car = [{"center_ego": [1.385, 0.0, 0.781], "size_lwh": [4.084, 1.730, 1.562]}]
    with pytest.raises(PrepError, match="camera CAM_FRONT"):
        check_sensors_outside("nuScenes rig", whole_car, cameras)


def test_the_pacifica_holds_no_waymo_sensor_and_its_perimeter_lidars_sit_on_its_faces():
    sensors = {f"camera {k}": v for k, v in WAYMO_SAMPLE_CAMERAS.items()}
    sensors |= {f"LiDAR {k}": v for k, v in WAYMO_SAMPLE_LIDARS.items()}
    check_sensors_outside("Waymo sample", WAYMO_PACIFICA_BOXES, sensors)
    for name in ("FRONT", "REAR", "SIDE_LEFT", "SIDE_RIGHT"):  # mounted on the bumpers and wings
        assert 0.0 < clearance_m(WAYMO_SAMPLE_LIDARS[name], WAYMO_PACIFICA_BOXES) < 0.05, name
    assert min(clearance_m(p, WAYMO_PACIFICA_BOXES) for p in WAYMO_SAMPLE_CAMERAS.values()) > 0.3
    # The old 1.8 m box held both side LiDARs.
    with pytest.raises(PrepError, match="LiDAR SIDE_LEFT"):
        check_sensors_outside("Waymo sample", OLD_DEFAULT_BOXES, sensors)


@pytest.mark.parametrize(
    ("rig", "boxes", "max_share"),
    [
        # The 110-degree CAM_BACK of the nuscenes6 rig sees the Zoe's tailgate and rear roof.
        ("nuscenes6", NUSCENES_ZOE_BOXES, {"CAM_BACK": 0.3, "other": 0.02}),
        ("waymo5", WAYMO_PACIFICA_BOXES, {"other": 0.0}),
        ("nuscenes6", EGO_BOXES, {"CAM_BACK": 0.12, "other": 0.0}),
        ("waymo5", EGO_BOXES, {"other": 0.0}),
    ],
)
def test_bodies_stay_below_every_cameras_horizon(rig: str, boxes: list[dict], max_share: dict) -> None:
    for cal in camera_calibrations(rig, 96, 160)[0]:
        body, up = ego_pixels(cal, boxes)
        assert not np.any(body & up), cal.name
        assert body.mean() <= max_share.get(cal.name, max_share["other"]), (cal.name, body.mean())


def test_the_zoes_tailgate_fills_the_bottom_hundred_rows_of_cam_back_as_in_nuscenes_images():
    """nuScenes' CAM_BACK (1600 x 900, f = 809 px, calibrated_sensor of v1.0) sees the tailgate in
    its bottom ~100 rows (nerfstudio pull request #1679 masks them); CAM_FRONT sees no bonnet."""
    rows = np.arange(900) + 0.0
    for name, position, yaw, f, want in (
        ("CAM_BACK", (0.02833, 0.00345, 1.57910), np.pi, 809.2, (85, 115)),
        ("CAM_FRONT", (1.70079, 0.01595, 1.51096), 0.0, 1266.4, (0, 0)),
    ):
        rotation = geometry.rotation_z(yaw) @ geometry.BODY_FROM_OPENCV
        camera_from_ego = geometry.invert_transform(geometry.make_transform(rotation, position))
        rays = np.stack([np.zeros(900), (rows - 449.5) / f, np.ones(900)], axis=1)  # centre column
        entry = np.full(900, np.inf)
        for b in NUSCENES_ZOE_BOXES:
            camera_from_box = camera_from_ego @ geometry.make_transform(np.eye(3), b["center_ego"])
            t_in, _ = ray_box_depths(rays, camera_from_box, 0.5 * np.asarray(b["size_lwh"]))
            entry = np.minimum(entry, t_in)
        body_rows = int(np.isfinite(entry).sum())
        assert want[0] <= body_rows <= want[1], (name, body_rows)
        assert np.all(np.isfinite(entry[900 - body_rows :])), name  # the bottom rows, contiguous


def test_the_synthetic_body_passes_the_sensor_check_on_both_rigs():
    for rig in ("waymo5", "nuscenes6"):
        sensors = camera_centres(camera_calibrations(rig, 32, 48)[0]) | {"LiDAR 0": LidarSpec().position_m}
        check_sensors_outside(rig, EGO_BOXES, sensors)


def test_the_default_body_holds_no_camera_of_either_rig():
    for rig in ("waymo5", "nuscenes6"):
        check_sensors_outside(rig, DEFAULT_EGO_BOXES, camera_centres(camera_calibrations(rig, 32, 48)[0]))


def test_lidar_origins_are_the_median_per_lidar():
    origins = np.array(
        [[1.0, 0, 2.0], [1.2, 0, 2.0], [1.1, 0, 2.0], [4.0, 0, 0.7], [4.0, 0, 0.7]], np.float32
    )
    got = lidar_origins(origins, np.array([0, 0, 0, 1, 1], np.uint8))
    assert sorted(got) == ["LiDAR (lidar_id 0)", "LiDAR (lidar_id 1)"]
    np.testing.assert_allclose(got["LiDAR (lidar_id 0)"], [1.1, 0, 2.0], atol=1e-6)
    np.testing.assert_allclose(got["LiDAR (lidar_id 1)"], [4.0, 0, 0.7], atol=1e-6)


# --------------------------------------------------------------------------------------------
# The depth stages refuse a body over a sensor


def test_the_old_default_body_holds_every_nuscenes_camera_and_is_refused_by_name():
    cameras = camera_centres(camera_calibrations("nuscenes6", 32, 48)[0])
    with pytest.raises(PrepError) as info:
        check_sensors_outside("scene-0001", OLD_DEFAULT_BOXES, cameras, "the default body")
    message = str(info.value)
    assert "scene scene-0001" in message and "camera CAM_FRONT" in message
    assert "ego box 0" in message and "[5.0, 2.1, 1.8]" in message and "the default body" in message


def test_aggregation_refuses_a_body_over_a_camera_naming_the_scene_camera_and_box():
    scene = nuscenes6_scene(OLD_DEFAULT_BOXES)
    with pytest.raises(PrepError, match=rf"scene {scene.scene_id}: the camera CAM_FRONT .* ego box 0"):
        get_stage("aggregate_lidar")(scene, {})


def test_projection_from_the_own_sweep_refuses_a_body_over_a_camera():
    scene = nuscenes6_scene(OLD_DEFAULT_BOXES)
    with pytest.raises(PrepError, match=rf"scene {scene.scene_id}: the camera CAM_FRONT"):
        get_stage("project_depth")(scene, {})


def test_aggregation_refuses_a_body_over_the_lidar_naming_it():
    scene = nuscenes6_scene([{"center_ego": [1.2, 0.0, 2.15], "size_lwh": [0.3, 0.3, 0.3]}])
    with pytest.raises(
        PrepError, match=rf"scene {scene.scene_id}: the LiDAR \(lidar_id 0\) at \(1\.2\d*, .* ego box 0"
    ):
        get_stage("aggregate_lidar")(scene, {})


def test_a_scene_without_a_body_gets_the_low_default_and_a_warning(caplog: pytest.LogCaptureFixture):
    scene = nuscenes6_scene(None)
    with caplog.at_level(logging.WARNING, logger="phigenesis.prep"):
        scene = get_stage("aggregate_lidar")(scene, {})
    assert "gives no ego body" in caplog.text
    assert scene.products["lidar_map"].ego_boxes == DEFAULT_EGO_BOXES
