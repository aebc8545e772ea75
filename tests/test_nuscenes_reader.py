"""A synthetic nuScenes export read back must give the synthetic truth: ego poses, calibrations,
camera timestamps, LiDAR points (within float32), keyframe boxes; the 12 Hz frame model must
handle a dropped camera sweep; bad input must fail naming the table, token or file, and
``on_error="skip"`` must convert the rest and say what it skipped."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from phigenesis import geometry, prep
from phigenesis import taxonomy as tx
from phigenesis.cli import prep as prep_cli
from phigenesis.data.pipeline import PipelineSpec, PrepError, load_pipeline
from phigenesis.data.sources.nuscenes import NuScenesConfig, NuScenesError, NuScenesSource
from phigenesis.data.sources.synthetic import SyntheticScene
from phigenesis.data.sources.synthetic.nuscenes_export import (
    GLOBAL_OFFSET_M,
    UNIFIED_TO_NUSCENES_CATEGORY,
    camera_timestamp,
    export_nuscenes,
    lidar_timestamp,
    nuscenes_scene_config,
    render_lidar_sweep,
)
from phigenesis.data.stages import STAGES, get_stage
from tests.conftest import NUSCENES_CONFIG, NUSCENES_DROPPED, NUSCENES_KEYFRAMES, tiny_config

CONFIG, KEYFRAMES, DROPPED = NUSCENES_CONFIG, NUSCENES_KEYFRAMES, NUSCENES_DROPPED
STEPS = 6 * (KEYFRAMES - 1) + 1


@pytest.fixture(scope="module")
def dataroot(nuscenes_dataroot: Path) -> Path:
    return nuscenes_dataroot


@pytest.fixture(scope="module")
def truth() -> SyntheticScene:
    return SyntheticScene(nuscenes_scene_config(CONFIG, KEYFRAMES), 0)


def _scene(dataroot: Path, on_error: str = "raise"):
    source = NuScenesSource(NuScenesConfig(dataroot=str(dataroot), on_error=on_error))  # type: ignore[arg-type]
    (scene_id,) = source.scene_ids()
    return source.load(scene_id)


def _world_shift(scene) -> np.ndarray:
    """Synthetic world -> reader world translation (the reader's origin is frame 0's ego)."""
    return GLOBAL_OFFSET_M - np.array(scene.metadata["global_from_world"]).reshape(4, 4)[:3, 3]


def _shifted(world_from_x: np.ndarray, shift: np.ndarray) -> np.ndarray:
    out = np.array(world_from_x)
    out[..., :3, 3] += shift
    return out


def test_frames_poses_calibrations_and_camera_times_are_the_truth(
    dataroot: Path, truth: SyntheticScene
) -> None:
    scene = _scene(dataroot)
    shift = _world_shift(scene)
    assert len(scene) == STEPS
    assert [c.name for c in scene.calibrations] == [c.name for c in truth.calibrations]
    for got, want in zip(scene.calibrations, truth.calibrations, strict=True):
        assert (got.width, got.height) == (want.width, want.height) == (160, 96)
        np.testing.assert_allclose(got.intrinsics, want.intrinsics, atol=1e-12)
        np.testing.assert_allclose(got.ego_from_camera, want.ego_from_camera, atol=1e-12)
        np.testing.assert_array_equal(got.distortion, 0.0)
    # Frame 0's ego is the world origin; the world is not rotated.
    np.testing.assert_allclose(scene.frames[0].world_from_ego[:3, 3], 0.0, atol=1e-9)
    times = []
    for s in range(STEPS):
        frame = scene.frames[s]
        times.append(frame.timestamp_micros)
        np.testing.assert_allclose(
            frame.world_from_ego, _shifted(truth.world_from_ego(frame.timestamp_micros), shift), atol=1e-9
        )
        for cam in frame.cameras:
            i = [c.name for c in truth.calibrations].index(cam.name)
            assert cam.timestamp_micros == camera_timestamp(truth, s, i)
            np.testing.assert_allclose(
                cam.world_from_ego, _shifted(truth.world_from_ego(cam.timestamp_micros), shift), atol=1e-9
            )
            assert cam.image_bytes is not None and cam.image_bytes[:2] == b"\xff\xd8"
    assert np.all(np.diff(times) > 0)
    # Keyframe frames sit exactly at their sample's (LiDAR keyframe's) time.
    for k in range(KEYFRAMES):
        assert times[6 * k] == lidar_timestamp(truth, 10 * k) == scene.keyframes[k].timestamp_micros
    # Each camera's own keyframe image (its is_key_frame sample_data) is on the keyframe, taken
    # as the LiDAR revolution ending at the sample passed the camera: 1-43 ms before it.
    for k, kf in enumerate(scene.keyframes):
        images = {c.name: c.timestamp_micros for c in scene.frames[6 * k].cameras}
        assert kf.camera_timestamps_micros == images and len(images) == 6
        offsets = {name: t - kf.timestamp_micros for name, t in images.items()}
        assert offsets == {
            "CAM_FRONT_LEFT": -43_056,
            "CAM_FRONT": -35_417,
            "CAM_FRONT_RIGHT": -27_778,
            "CAM_BACK_RIGHT": -20_139,
            "CAM_BACK": -10_417,
            "CAM_BACK_LEFT": -694,
        }


def test_lidar_points_in_the_ego_frame_are_the_truth_within_float32(
    dataroot: Path, truth: SyntheticScene
) -> None:
    scene = _scene(dataroot)
    shift = _world_shift(scene)
    stamps = [lidar_timestamp(truth, j) for j in range(10 * (KEYFRAMES - 1) + 1)]
    for s in (0, 1, 7):
        frame = scene.frames[s]
        sweep = frame.lidar
        assert sweep is not None and sweep.timestamp_micros == frame.timestamp_micros
        raw = render_lidar_sweep(truth, stamps.index(sweep.timestamp_micros))
        assert len(sweep) == len(raw["beam"]) > 500
        # float32 sensor-frame coordinates under 80 m: < 1e-5 m after the (float64) transforms.
        np.testing.assert_allclose(sweep.points_world(), raw["points_world"] + shift, atol=1e-5)
        np.testing.assert_array_equal(sweep.intensity, (raw["intensity"] * 255.0).astype(np.float32))
        np.testing.assert_array_equal(sweep.beam_index, raw["beam"])
        np.testing.assert_allclose(sweep.origins_ego[0], CONFIG.lidar.position_m, atol=1e-6)


def test_keyframe_boxes_are_the_truth_with_instance_tokens_as_track_ids(
    dataroot: Path, truth: SyntheticScene
) -> None:
    scene = _scene(dataroot)
    shift = _world_shift(scene)
    assert len(scene.keyframes) == KEYFRAMES
    tracks: dict[str, str] = {}
    for k, kf in enumerate(scene.keyframes):
        want = truth.boxes_at(kf.timestamp_micros, CONFIG.box_range_m)
        got = kf.boxes
        assert len(got) == len(want) > 5
        assert np.all(got.status == 0) and kf.token
        order = np.argsort([np.round(c, 6).tolist() for c in got.center_world - shift], axis=0)[:, 0]
        ref = np.argsort([np.round(c, 6).tolist() for c in want.center_world], axis=0)[:, 0]
        g, w = got.select(order), want.select(ref)
        np.testing.assert_allclose(g.center_world - shift, w.center_world, atol=1e-9)
        np.testing.assert_allclose(g.size_lwh, w.size_lwh, atol=1e-12)
        np.testing.assert_allclose(np.cos(g.yaw_world - w.yaw_world), 1.0, atol=1e-12)
        np.testing.assert_array_equal(g.class_id, w.class_id)
        assert set(w.class_id.tolist()) <= set(UNIFIED_TO_NUSCENES_CATEGORY)
        for tid, sid in zip(g.track_id, w.track_id, strict=True):
            assert len(tid) == 32 and tracks.setdefault(sid, tid) == tid  # one token per object
        # Central differences over the neighbouring keyframes where the object is annotated
        # (one-sided at the ends of its track, zero if annotated once).
        near = [truth.boxes_at(kf2.timestamp_micros, CONFIG.box_range_m) for kf2 in scene.keyframes]
        for i, sid in enumerate(w.track_id):
            seen = [j for j in (k - 1, k, k + 1) if 0 <= j < KEYFRAMES and sid in near[j].track_id]
            j0, j1 = seen[0], seen[-1]
            p0 = near[j0].center_world[near[j0].track_id.index(sid)]
            p1 = near[j1].center_world[near[j1].track_id.index(sid)]
            dt = (scene.keyframes[j1].timestamp_micros - scene.keyframes[j0].timestamp_micros) * 1e-6
            want_v = (p1 - p0) / dt if j1 > j0 else np.zeros(3)
            np.testing.assert_allclose(g.velocity_world[i], want_v, atol=1e-9)
        assert np.median(np.linalg.norm(g.velocity_world - w.velocity_world, axis=1)) < 0.2
    frame_boxes = [len(scene.frames[s].boxes) for s in range(STEPS)]
    assert frame_boxes == [len(scene.keyframes[s // 6].boxes) if s % 6 == 0 else 0 for s in range(STEPS)]


def test_a_dropped_camera_sweep_leaves_the_camera_out_of_that_frame_only(dataroot: Path) -> None:
    scene = _scene(dataroot)
    names = [c.name for c in scene.calibrations]
    back_times = []
    for s in range(STEPS):
        got = [c.name for c in scene.frames[s].cameras]
        assert got == ([n for n in names if n != DROPPED[0]] if s == DROPPED[1] else names)
        back_times += [c.timestamp_micros for c in scene.frames[s].cameras if c.name == DROPPED[0]]
    assert len(set(back_times)) == STEPS - 1  # no image reused
    assert [(g["step"], g["camera"]) for g in scene.metadata["camera_gaps"]] == [(DROPPED[1], DROPPED[0])]


def test_every_nuscenes_category_maps_into_the_taxonomy() -> None:
    assert len(tx.NUSCENES_CATEGORY_IDS) == 32
    assert all(v == tx.IGNORE_ID or 0 <= v < tx.NUM_CLASSES for v in tx.NUSCENES_CATEGORY_IDS.values())
    assert tx.NUSCENES_CATEGORY_IDS["vehicle.car"] == tx.CAR
    assert tx.NUSCENES_CATEGORY_IDS["human.pedestrian.child"] == tx.PERSON


# --------------------------------------------------------------------------------------------
# Bad input


def _copy(dataroot: Path, tmp_path: Path) -> Path:
    root = tmp_path / "data"
    shutil.copytree(dataroot, root)
    return root


def _edit(root: Path, table: str, index: int, **values: object) -> dict:
    path = root / "v1.0-mini" / f"{table}.json"
    rows = json.loads(path.read_text())
    rows[index].update(values)
    path.write_text(json.dumps(rows))
    return rows[index]


def _sample_data(root: Path, channel_part: str, key: bool) -> tuple[int, dict]:
    rows = json.loads((root / "v1.0-mini" / "sample_data.json").read_text())
    return next(
        (i, r) for i, r in enumerate(rows) if channel_part in r["filename"] and r["is_key_frame"] == key
    )


def test_a_missing_table_is_named(dataroot: Path, tmp_path: Path) -> None:
    root = _copy(dataroot, tmp_path)
    (root / "v1.0-mini" / "instance.json").unlink()
    with pytest.raises(NuScenesError, match=r"instance.json: table 'instance' is missing"):
        NuScenesSource(NuScenesConfig(dataroot=str(root))).scene_ids()
    with pytest.raises(PrepError, match="table 'instance' is missing"):
        prep.nuscenes(tmp_path / "out", dataroot=root, progress=False)


def test_a_dangling_token_is_named_and_skip_leaves_out_that_sweep(dataroot: Path, tmp_path: Path) -> None:
    root = _copy(dataroot, tmp_path)
    i, sd = _sample_data(root, "sweeps/CAM_FRONT_LEFT", key=False)
    _edit(root, "sample_data", i, ego_pose_token="f" * 32)
    with pytest.raises(
        NuScenesError,
        match=rf"sample_data.json: sample_data '{sd['token']}': 'ego_pose_token': "
        rf"table 'ego_pose' has no record with token '{'f' * 32}'",
    ):
        _scene(root)
    scene = _scene(root, "skip")
    assert [s["skipped"] for s in scene.metadata["skipped"]] == [f"sample_data {sd['token']}"]
    stamps = [c.timestamp_micros for f in scene.frames for c in f.cameras if c.name == "CAM_FRONT_LEFT"]
    assert len(stamps) == STEPS - 1 and sd["timestamp"] not in stamps


@pytest.mark.parametrize("channel", ["CAM_BACK_RIGHT", "LIDAR_TOP"])
def test_a_missing_file_is_named_and_skip_converts_the_rest(
    dataroot: Path, tmp_path: Path, channel: str
) -> None:
    root = _copy(dataroot, tmp_path)
    _, sd = _sample_data(root, f"sweeps/{channel}", key=False)
    (root / sd["filename"]).unlink()
    with pytest.raises(NuScenesError, match=rf"{root / sd['filename']}: file of sample_data '{sd['token']}'"):
        _scene(root)
    scene = _scene(root, "skip")
    assert scene.metadata["skipped"][0]["skipped"] == f"sample_data {sd['token']}"
    assert sd["filename"] in scene.metadata["skipped"][0]["reason"]
    frames = [scene.frames[s] for s in range(STEPS)]
    if channel == "LIDAR_TOP":
        assert sd["timestamp"] not in [f.lidar.timestamp_micros for f in frames if f.lidar is not None]
    else:
        assert len([c for f in frames for c in f.cameras if c.name == channel]) == STEPS - 1


def test_an_unknown_category_is_named_and_skip_drops_its_boxes(dataroot: Path, tmp_path: Path) -> None:
    root = _copy(dataroot, tmp_path)
    rows = json.loads((root / "v1.0-mini" / "category.json").read_text())
    i = next(i for i, c in enumerate(rows) if c["name"] == "vehicle.car")
    _edit(root, "category", i, name="vehicle.hovercraft")
    with pytest.raises(
        NuScenesError,
        match=r"category.json: category '[0-9a-f]+': 'name' is the unknown category 'vehicle.hovercraft'",
    ):
        _scene(root)
    full, scene = _scene(dataroot), _scene(root, "skip")
    cars = sum(int(np.sum(kf.boxes.class_id == tx.CAR)) for kf in full.keyframes)
    assert cars > 0 and len(scene.metadata["skipped"]) == cars
    assert all(np.all(kf.boxes.class_id != tx.CAR) for kf in scene.keyframes)
    assert sum(len(kf.boxes) for kf in scene.keyframes) == sum(len(kf.boxes) for kf in full.keyframes) - cars


# --------------------------------------------------------------------------------------------
# The command


def _pipeline(tmp_path: Path) -> Path:
    """The bundled nuscenes pipeline; without ``interpolate_boxes`` while that stage is not
    registered yet (it is written separately)."""
    spec = load_pipeline("nuscenes") if _has_interpolation() else None
    if spec is None:
        import yaml

        d = yaml.safe_load((Path(__file__).parents[1] / "pipelines" / "nuscenes.yaml").read_text())
        assert d["stages"][0]["name"] == "interpolate_boxes"
        d["stages"] = d["stages"][1:]
        spec = PipelineSpec.from_dict(d)
    path = tmp_path / "nuscenes.yaml"
    import yaml

    path.write_text(yaml.safe_dump(spec.to_dict()))
    return path


def _has_interpolation() -> bool:
    try:
        get_stage("interpolate_boxes")
    except KeyError:
        return False
    return "interpolate_boxes" in STAGES


def test_prep_nuscenes_end_to_end_gives_a_verified_cache(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    export_nuscenes(tiny_config(scenes=2, height=32, width=48), root, keyframes=2)
    _, sd = _sample_data(root, "sweeps/LIDAR_TOP", key=False)
    (root / sd["filename"]).unlink()
    pipeline = str(_pipeline(tmp_path))
    args = ["nuscenes", "--dataroot", str(root), "--pipeline", pipeline, "--no-progress"]
    assert prep_cli.main([*args, "--out", str(tmp_path / "stop")]) == 2
    assert sd["filename"] in capsys.readouterr().err
    assert prep_cli.main([*args, "--out", str(tmp_path / "cache"), "--on-error", "skip"]) == 0
    assert "wrote 2 scenes (14 frames" in capsys.readouterr().out
    assert prep_cli.main(["verify", str(tmp_path / "cache")]) == 0
    manifest = json.loads((tmp_path / "cache" / "manifest.json").read_text())
    skipped = []
    for shard in manifest["shards"]:
        with pa.memory_map(str(tmp_path / "cache" / shard["path"])) as f:
            meta = pa.ipc.open_file(f).schema.metadata
        skipped += json.loads(meta[b"phigenesis.scene_metadata"])["skipped"]
    assert [s["skipped"] for s in skipped] == [f"sample_data {sd['token']}"]
    from phigenesis.data.shards import CacheReader

    frame = CacheReader(tmp_path / "cache").frame(0)
    assert len(frame.cameras) == 6 and frame.lidar is not None and len(frame.boxes) > 0
    assert geometry.quaternion_normalize(frame.boxes.orientation_world).shape == (len(frame.boxes), 4)
