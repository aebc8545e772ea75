"""The Waymo v1 reader on the two real frames (read in place, never copied; see SAMPLES_ENV below).

The frames are optional data: two single frames of the Waymo Open Dataset's public test data
(https://github.com/waymo-research/waymo-open-dataset, non-commercial licence), which the project
does not redistribute. Point $PHIGENESIS_WAYMO_SAMPLES at a folder holding them; without them
every test here is skipped, naming the places it looked."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from phigenesis import geometry, prep
from phigenesis.data.shards import CacheReader
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource
from phigenesis.data.sources.waymo.raw import CAMERA_NAMES
from phigenesis.data.sources.waymo.v1 import V1File

#: Where the real samples are looked for, in order: $PHIGENESIS_WAYMO_SAMPLES (when set), the
#: checkout's ../shared/data/waymo, then /work/shared/data/waymo.
SAMPLES_ENV = "PHIGENESIS_WAYMO_SAMPLES"
CHECKOUT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "waymo"
MACHINE_SHARED = Path("/work/shared/data/waymo")
PANOPTIC_NAME = "one_frame_five_cameras_panoptic.tfrecord"


def _sample_places() -> list[Path]:
    env = os.environ.get(SAMPLES_ENV)
    return [*([Path(env)] if env else []), CHECKOUT_SHARED, MACHINE_SHARED]


def _skip_reason() -> str:
    """Why the tests are skipped: the file they need and every place they looked for it."""
    env = os.environ.get(SAMPLES_ENV)
    return (
        f"real Waymo samples ({PANOPTIC_NAME}) not found in ${SAMPLES_ENV} ({env or 'unset'}), "
        f"in {CHECKOUT_SHARED} (../shared/data/waymo next to the checkout) or in {MACHINE_SHARED}"
    )


DATA = next((p for p in _sample_places() if (p / PANOPTIC_NAME).exists()), CHECKOUT_SHARED)
PANOPTIC = DATA / PANOPTIC_NAME
LABELS_ONLY = DATA / "one_frame_labels_only.tfrecord"
pytestmark = pytest.mark.skipif(not PANOPTIC.exists(), reason=_skip_reason())


def _frame(path: Path):
    source = WaymoSource(WaymoConfig(input=str(path)))
    (scene_id,) = source.scene_ids()
    scene = source.load(scene_id)
    return scene, scene.frames[0]


def test_panoptic_frame_has_five_cameras_at_their_calibrated_sizes_and_75_boxes() -> None:
    scene, frame = _frame(PANOPTIC)
    sizes = {c.name: (c.calibration.width, c.calibration.height) for c in frame.cameras}
    assert sizes == {
        "FRONT": (1920, 1280),
        "FRONT_LEFT": (1920, 1280),
        "FRONT_RIGHT": (1920, 1280),
        "SIDE_LEFT": (1920, 886),
        "SIDE_RIGHT": (1920, 886),
    }
    # Rig order is by camera code, although the file lists the images as 1, 2, 4, 3, 5.
    assert [c.name for c in frame.cameras] == [
        "FRONT",
        "FRONT_LEFT",
        "FRONT_RIGHT",
        "SIDE_LEFT",
        "SIDE_RIGHT",
    ]
    for cam in frame.cameras:
        rgb = cam.decode_image()
        assert rgb.shape == (cam.calibration.height, cam.calibration.width, 3)
        assert cam.calibration.readout_direction == "left_to_right"
        # Timing as in the sample: ~2.6-3.9 ms shutter, ~44 ms readout, image time ~ mid readout.
        assert 2000 < cam.shutter_micros < 4000 and 40_000 < cam.readout_micros < 48_000
        mid = cam.pixel_time_micros(np.array([cam.calibration.width / 2 - 0.5]), np.array([0.0]))[0]
        assert abs(mid - cam.timestamp_micros) < 5000
    assert len(frame.boxes) == 75
    assert frame.lidar is None  # the sample's lasers carry no range images
    assert frame.source_timestamp_micros == 1553735853462203
    assert frame.timestamp_micros == frame.source_timestamp_micros + 50_000
    assert scene.scene_id == "one_frame_five_cameras_panoptic"
    assert scene.metadata["context_name"] == "1024360143612057520_3580_000_3600_000"
    # World = global shifted to the first pose: the frame sits at the origin, axes unchanged.
    np.testing.assert_allclose(frame.world_from_ego[:3, 3], 0.0, atol=1e-9)
    global_from_world = np.array(scene.metadata["global_from_world"]).reshape(4, 4)
    np.testing.assert_allclose(global_from_world[:3, 3], [-25211.2589, 42391.0813, -160.618], atol=1e-3)


def _projected_box_errors(path: Path) -> np.ndarray:
    """Max-abs difference (px) between the dataset's projected_lidar_labels and the axis-aligned
    box of the 8 corners projected with the toolkit's camera model and each image's own pose."""
    raw = V1File(path).frame(0)
    _, frame = _frame(path)
    index = {t: i for i, t in enumerate(frame.boxes.track_id)}
    corners = frame.boxes.corners_world()
    errors = []
    proj = raw.projected_boxes
    for k in range(len(proj.ids)):
        cam = frame.camera(CAMERA_NAMES[int(proj.camera[k])])
        cal = cam.calibration
        camera_from_world = geometry.invert_transform(cam.world_from_camera)
        pc = geometry.transform_points(camera_from_world, corners[index[proj.ids[k]]])
        uv, valid = geometry.project_points(pc, cal.intrinsics, cal.distortion)
        if not valid.all():
            continue  # corners behind the camera: the dataset clips those boxes in 3D
        uv = uv + 0.5  # Waymo's pixel coordinates put 0 at the first pixel's left edge
        size = np.array([cal.width, cal.height])
        lo, hi = np.clip(uv.min(0), 0, size), np.clip(uv.max(0), 0, size)
        ours = np.concatenate([(lo + hi) / 2, hi - lo])
        errors.append(np.abs(ours - proj.box[k]).max())
    return np.array(errors)


def test_boxes_project_onto_the_datasets_own_2d_boxes() -> None:
    errors = _projected_box_errors(PANOPTIC)
    assert len(errors) >= 50  # 62 projected boxes, a few with corners behind a camera
    assert np.median(errors) < 0.5
    assert np.percentile(errors, 90) < 0.5


def test_panoptic_labels_map_into_the_unified_taxonomy() -> None:
    from phigenesis import taxonomy as tx

    _, frame = _frame(PANOPTIC)
    for cam in frame.cameras:
        labels = cam.labels
        assert labels is not None and labels.semantic.shape == (cam.calibration.height, cam.calibration.width)
        classes = set(np.unique(labels.semantic).tolist())
        assert classes <= set(range(tx.NUM_CLASSES)) | {tx.IGNORE_ID}
        # Street scene in daylight: road and sky everywhere, the top row mostly sky or buildings.
        assert tx.ROAD in classes
        things = labels.instance > 0
        assert things.any()
        # Instances only on thing classes.
        assert set(np.unique(labels.semantic[things]).tolist()) <= set(tx.THING_IDS) | {tx.IGNORE_ID}
    front = frame.camera("FRONT").labels
    assert front is not None
    assert np.mean(front.semantic[-100:] == tx.ROAD) > 0.5  # the bottom of the front image is road


def test_labels_only_frame_has_boxes_and_calibrations_and_says_it_has_no_images(tmp_path: Path) -> None:
    scene, frame = _frame(LABELS_ONLY)
    assert len(frame.boxes) == 18
    assert [c.name for c in scene.calibrations] == [
        "FRONT",
        "FRONT_LEFT",
        "FRONT_RIGHT",
        "SIDE_LEFT",
        "SIDE_RIGHT",
    ]
    assert all(c.image_bytes is None for c in frame.cameras)
    with pytest.raises(ValueError, match="has no image"):
        frame.cameras[0].decode_image()
    # Converted through the command's library function, the cache row says the same.
    summary = prep.waymo(tmp_path / "cache", input=LABELS_ONLY, progress=False)
    assert summary.frames_written == 1
    row = CacheReader(tmp_path / "cache").frame(0)
    assert [c.image_bytes for c in row.cameras] == [None] * 5
    assert len(row.boxes) == 18 and row.lidar is None
    assert row.cameras[3].calibration.height == 886


def test_a_folder_of_both_files_converts_to_two_scenes_and_segment_filters_pick_one(tmp_path: Path) -> None:
    summary = prep.waymo(tmp_path / "all", input=DATA, progress=False)
    assert sorted(summary.scenes_written) == ["one_frame_five_cameras_panoptic", "one_frame_labels_only"]
    picked = prep.waymo(tmp_path / "one", input=DATA, segments=["*labels_only"], progress=False)
    assert picked.scenes_written == ["one_frame_labels_only"]
    reader = CacheReader(tmp_path / "all")
    frames = [reader.frame(i) for i in range(len(reader))]
    assert sorted(len(f.boxes) for f in frames) == [18, 75]
