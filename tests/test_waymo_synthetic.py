"""Synthetic scenes written as Waymo v1 and v2 and read back must give the synthetic truth; bad
inputs must fail naming the file and record (or component), and --on-error skip must go on."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from phigenesis import prep
from phigenesis.cli import prep as prep_cli
from phigenesis.cli import synth as synth_cli
from phigenesis.data.pipeline import PrepError
from phigenesis.data.sources.synthetic import SyntheticScene
from phigenesis.data.sources.synthetic.waymo_export import (
    UNIFIED_TO_WAYMO_BOX_TYPE,
    UNIFIED_TO_WAYMO_SEGMENTATION,
    export_waymo,
    raw_frame,
)
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource, convert, tfrecord, v1
from tests.conftest import tiny_config

CONFIG = tiny_config(scenes=1, frames=3)
#: The synthetic LiDAR casts each sector at one time; the reader estimates times per column.
HALF_SECTOR_MICROS = 100_000 / CONFIG.lidar.sectors / 2


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("waymo_export")
    export_waymo(CONFIG, root / "v1", "v1")
    export_waymo(CONFIG, root / "v2", "v2")
    return {"v1": root / "v1", "v2": root / "v2"}


@pytest.fixture(scope="module")
def truth() -> list:
    scene = SyntheticScene(CONFIG, 0)
    return [scene.render_frame(k) for k in range(CONFIG.frames)]


def _expected_segmentation(semantic: np.ndarray) -> np.ndarray:
    waymo = np.array([UNIFIED_TO_WAYMO_SEGMENTATION.get(c, 0) for c in range(256)])
    back = np.array([convert.CAMERA_SEGMENTATION_CLASS_IDS[w] for w in waymo], np.uint8)
    return back[semantic]


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_written_scenes_read_back_as_the_synthetic_truth(
    exported: dict[str, Path], truth: list, version: str
) -> None:
    source = WaymoSource(WaymoConfig(input=str(exported[version])))
    assert source.format == version
    assert source.scene_ids() == [CONFIG.scene_ids()[0]]
    scene = source.load(source.scene_ids()[0])
    assert len(scene) == CONFIG.frames
    for k, want in enumerate(truth):
        got = scene.frames[k]
        assert got.timestamp_micros == want.timestamp_micros
        assert got.source_timestamp_micros == want.timestamp_micros - 50_000
        np.testing.assert_allclose(got.world_from_ego, want.world_from_ego, atol=1e-9)

        assert [c.name for c in got.cameras] == [c.name for c in want.cameras]
        for g, w in zip(got.cameras, want.cameras, strict=True):
            gc, wc = g.calibration, w.calibration
            assert (gc.width, gc.height) == (wc.width, wc.height)
            np.testing.assert_allclose(gc.intrinsics, wc.intrinsics, atol=1e-9)
            np.testing.assert_allclose(gc.distortion, wc.distortion, atol=1e-12)
            np.testing.assert_allclose(gc.ego_from_camera, wc.ego_from_camera, atol=1e-12)
            assert gc.readout_direction == "global"
            assert g.timestamp_micros == w.timestamp_micros
            np.testing.assert_allclose(g.world_from_ego, w.world_from_ego, atol=1e-9)
            assert g.image_bytes == w.image_bytes  # kept as stored, never re-encoded
            assert g.labels is not None and w.truth is not None
            np.testing.assert_array_equal(g.labels.semantic, _expected_segmentation(w.truth.semantic))
            np.testing.assert_array_equal(g.labels.instance, w.truth.instance)

        # LiDAR: same returns in the same (row-major) order, positions within float32 precision
        # of the stored ranges and of the global-frame pixel poses.
        gl, wl = got.lidar, want.lidar
        assert gl is not None and wl is not None and len(gl) == len(wl) > 500
        np.testing.assert_allclose(gl.points_ego, wl.points_ego, atol=2e-4)
        np.testing.assert_allclose(gl.origins_ego, wl.origins_ego, atol=2e-4)
        np.testing.assert_array_equal(gl.beam_index, wl.beam_index)
        np.testing.assert_array_equal(gl.intensity, wl.intensity)
        assert np.abs(gl.time_offset_micros - wl.time_offset_micros).max() <= HALF_SECTOR_MICROS + 1
        assert set(np.unique(gl.lidar_id)) == {0} and set(np.unique(gl.return_index)) == {0}

        gb, wb = got.boxes, want.boxes
        assert gb.track_id == wb.track_id
        np.testing.assert_allclose(gb.center_world, wb.center_world, atol=1e-9)
        np.testing.assert_allclose(gb.size_lwh, wb.size_lwh)
        np.testing.assert_allclose(np.cos(gb.yaw_world - wb.yaw_world), 1.0, atol=1e-12)
        np.testing.assert_allclose(gb.velocity_world, wb.velocity_world, atol=1e-9)
        np.testing.assert_allclose(gb.acceleration_world, wb.acceleration_world, atol=1e-9)
        np.testing.assert_array_equal(gb.num_lidar_points, wb.num_lidar_points)
        waymo_type = [UNIFIED_TO_WAYMO_BOX_TYPE.get(int(c), 0) for c in wb.class_id]
        np.testing.assert_array_equal(gb.class_id, [convert.BOX_CLASS_IDS[t] for t in waymo_type])


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_geometry_frames_skip_the_images_and_keep_the_rest(
    exported: dict[str, Path], version: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scene-wide pass (LazyFrames.geometry) reads no image bytes or labels and decodes no
    JPEG; poses, camera times, LiDAR and boxes equal the whole frame's."""
    from phigenesis.data.records import CameraImage, LazyFrames

    source = WaymoSource(WaymoConfig(input=str(exported[version])))
    scene = source.load(source.scene_ids()[0])
    assert isinstance(scene.frames, LazyFrames)
    checks = []
    original = CameraImage.check_image
    monkeypatch.setattr(CameraImage, "check_image", lambda self: checks.append(self.name) or original(self))
    for k in range(CONFIG.frames):
        geo = scene.frames.geometry(k)
        assert checks == []
        full = scene.frames[k]
        assert len(checks) == len(full.cameras) == len(geo.cameras) == 5
        checks.clear()
        assert all(c.image_bytes is None and c.labels is None for c in geo.cameras)
        assert all(c.image_bytes is not None and c.labels is not None for c in full.cameras)
        for g, f in zip(geo.cameras, full.cameras, strict=True):
            assert (g.name, g.timestamp_micros) == (f.name, f.timestamp_micros)
            np.testing.assert_array_equal(g.world_from_ego, f.world_from_ego)
        assert geo.timestamp_micros == full.timestamp_micros
        np.testing.assert_array_equal(geo.lidar.points_ego, full.lidar.points_ego)
        np.testing.assert_array_equal(geo.boxes.center_world, full.boxes.center_world)


def test_prep_waymo_on_v1_and_v2_gives_the_same_cache_rows(exported: dict[str, Path], tmp_path: Path) -> None:
    a = prep.waymo(tmp_path / "a", input=exported["v1"], progress=False)
    b = prep.waymo(tmp_path / "b", input=exported["v2"], progress=False)
    assert a.frames_written == b.frames_written == CONFIG.frames
    assert prep.verify(tmp_path / "a").ok and prep.verify(tmp_path / "b").ok
    from phigenesis.data.shards import CacheReader

    ra, rb = CacheReader(tmp_path / "a"), CacheReader(tmp_path / "b")
    for k in range(CONFIG.frames):
        fa, fb = ra.frame(k), rb.frame(k)
        np.testing.assert_array_equal(fa.lidar.points_ego, fb.lidar.points_ego)
        assert [c.image_bytes for c in fa.cameras] == [c.image_bytes for c in fb.cameras]
        np.testing.assert_array_equal(fa.boxes.center_world, fb.boxes.center_world)


# --------------------------------------------------------------------------------------------
# Bad input


def _v1_file(exported: dict[str, Path]) -> Path:
    (path,) = sorted(exported["v1"].glob("*.tfrecord"))
    return path


def _copy_as(src: Path, folder: Path, segment: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    dst = folder / f"segment-{segment}_with_camera_labels.tfrecord"
    shutil.copyfile(src, dst)
    return dst


def test_truncated_file_names_the_file_and_record_and_skip_converts_the_rest(
    exported: dict[str, Path], tmp_path: Path
) -> None:
    good = _copy_as(_v1_file(exported), tmp_path / "in", "good")
    bad = _copy_as(_v1_file(exported), tmp_path / "in", "bad")
    spans = tfrecord.index_records(bad)
    with open(bad, "r+b") as f:
        f.truncate(spans[2].offset + 100)
    with pytest.raises(PrepError, match=rf"{bad}: record at byte {spans[2].offset}: file is truncated"):
        prep.waymo(tmp_path / "stop", input=tmp_path / "in", progress=False)
    summary = prep.waymo(tmp_path / "skip", input=tmp_path / "in", on_error="skip", progress=False)
    assert summary.scenes_written == ["good"] and list(summary.scenes_skipped) == ["bad"]
    manifest = json.loads((tmp_path / "skip" / "manifest.json").read_text())
    entries = {s["id"]: s for s in manifest["scenes"]}
    assert entries["good"]["status"] == "complete" and entries["good"]["frames"] == CONFIG.frames
    assert entries["bad"]["status"] == "skipped"
    assert str(bad) in entries["bad"]["error"] and f"byte {spans[2].offset}" in entries["bad"]["error"]
    assert good.exists()


def test_flipped_byte_is_a_crc_mismatch_naming_the_record(exported: dict[str, Path], tmp_path: Path) -> None:
    bad = _copy_as(_v1_file(exported), tmp_path / "in", "flipped")
    spans = tfrecord.index_records(bad)
    data = bytearray(bad.read_bytes())
    data[spans[1].data_offset + spans[1].length // 2] ^= 0x10
    bad.write_bytes(bytes(data))
    with pytest.raises(PrepError, match=rf"{bad}: record at byte {spans[1].offset}: data CRC mismatch"):
        prep.waymo(tmp_path / "out", input=bad, progress=False)
    # The cache keeps nothing of the failed scene, and the manifest says why.
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["shards"] == []
    assert (
        manifest["scenes"][0]["status"] == "failed" and "data CRC mismatch" in manifest["scenes"][0]["error"]
    )


def test_a_file_that_is_not_a_tfrecord_is_refused_by_name(tmp_path: Path) -> None:
    bad = tmp_path / "segment-notes_with_camera_labels.tfrecord"
    bad.write_text("these are my notes, not a TFRecord file\n" * 10)
    with pytest.raises(PrepError, match=rf"{bad}: record at byte 0: length CRC mismatch"):
        prep.waymo(tmp_path / "out", input=bad, progress=False)


def test_a_camera_without_calibration_names_the_camera_file_and_record(tmp_path: Path) -> None:
    raw = [raw_frame(SyntheticScene(CONFIG, 0), 0)]
    raw[0].camera_calibrations = [c for c in raw[0].camera_calibrations if c.name != 4]  # no SIDE_LEFT
    path = tmp_path / "segment-uncalibrated.tfrecord"
    tfrecord.write_records(path, [v1.serialize_frame(raw[0])])
    with pytest.raises(
        PrepError, match=rf"{path} \(record 0 at byte 0\): camera SIDE_LEFT has an image but no calibration"
    ):
        prep.waymo(tmp_path / "out", input=path, progress=False)


def test_a_v2_root_with_a_missing_component_names_it(exported: dict[str, Path], tmp_path: Path) -> None:
    root = tmp_path / "v2"
    shutil.copytree(exported["v2"], root)
    shutil.rmtree(root / "camera_calibration")
    with pytest.raises(PrepError, match="camera_calibration"):
        prep.waymo(tmp_path / "out", input=root, progress=False)
    assert not (tmp_path / "out").exists()  # a bad input leaves nothing behind


def test_missing_input_and_unmatched_segment_filter_are_clear_errors(
    exported: dict[str, Path], tmp_path: Path
) -> None:
    with pytest.raises(PrepError, match="no such file or directory"):
        prep.waymo(tmp_path / "out", input=tmp_path / "nowhere", progress=False)
    with pytest.raises(PrepError, match=r"no segment matches \['nothing\*'\]"):
        prep.waymo(tmp_path / "out", input=exported["v1"], segments=["nothing*"], progress=False)


# --------------------------------------------------------------------------------------------
# Commands


def test_synth_and_prep_commands_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--out", str(tmp_path / "v1"), "--frames", "2", "--height", "40", "--width", "60"]
    assert synth_cli.main(["--format", "waymo-v1", *args]) == 0
    (written,) = (tmp_path / "v1").glob("*.tfrecord")
    assert len(tfrecord.index_records(written)) == 2
    with pytest.raises(SystemExit) as exit_info:  # not a format phigenesis-synth writes (yet)
        synth_cli.main(["--format", "kitti", *args])
    assert exit_info.value.code == 2
    code = prep_cli.main(
        ["waymo", "--input", str(tmp_path / "v1"), "--out", str(tmp_path / "cache"), "--no-progress"]
    )
    assert code == 0
    assert "wrote 1 scenes (2 frames" in capsys.readouterr().out
    assert prep_cli.main(["verify", str(tmp_path / "cache")]) == 0
    code = prep_cli.main(["waymo", "--input", str(tmp_path / "missing"), "--out", str(tmp_path / "c2")])
    assert code == 2
    assert "no such file or directory" in capsys.readouterr().err
