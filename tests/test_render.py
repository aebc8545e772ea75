"""``phigenesis-render``: a cache as another rig sees it (phigenesis.infer.rig_render)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.ipc as ipc
import pytest
import torch
import yaml

from phigenesis.cli.render import main as render_main
from phigenesis.data import records
from phigenesis.data.clips import Stage1Clips
from phigenesis.data.frame_truth import frame_truth
from phigenesis.data.shards import CacheReader, verify_cache
from phigenesis.errors import PrepError
from phigenesis.eval.stage1 import SyntheticTruth, target_views
from phigenesis.infer.rig_render import PoseTrack, render, scene_pose_track, source_rig
from phigenesis.infer.rigs import RigError, named_rig
from phigenesis.models.loading import load_stage1
from phigenesis.models.losses import psnr
from phigenesis.models.render import render_views
from tests.conftest import one_scene_cache, two_step_stage1

SIZE = (48, 72)
FRAMES = 3
SCENE = "synthetic-s7-0000"


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return one_scene_cache(tmp_path_factory, "render_cache", FRAMES, SIZE)


@pytest.fixture(scope="module")
def checkpoint(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return two_step_stage1(cache, tmp_path_factory)


def _images(cache_dir: Path, frame: int) -> list[np.ndarray]:
    f = CacheReader(cache_dir).frame(frame, decode_truth=False)
    return [c.decode_image() for c in f.cameras]


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        psnr(torch.from_numpy(a / 255.0).float()[None], torch.from_numpy(b / 255.0).float()[None])[0]
    )


def test_pose_track_is_exact_at_recorded_times_and_interpolates_between(cache: Path) -> None:
    reader = CacheReader(cache)
    frames = [reader.frame(i, decode_truth=False) for i in reader.frames_of(SCENE)]
    track = scene_pose_track(frames)
    for f in frames:
        np.testing.assert_array_equal(track.at(f.timestamp_micros), f.world_from_ego)
        for c in f.cameras:
            np.testing.assert_array_equal(track.at(c.timestamp_micros), c.world_from_ego)
    # Halfway between two poses a quarter-turn apart about z: the eighth-turn and the mean position.
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    b[:3, 3] = [2.0, 4.0, 0.0]
    mid = PoseTrack([(0, a), (1000, b)]).at(500)
    c = np.cos(np.pi / 4)
    np.testing.assert_allclose(mid[:3, :3], [[c, -c, 0], [c, c, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(mid[:3, 3], [1.0, 2.0, 0.0], atol=1e-12)
    assert PoseTrack([(0, a), (1000, b)]).outside_micros(1500) == 500


def test_the_own_rig_through_stage1_reproduces_the_models_own_render(
    cache: Path, checkpoint: Path, tmp_path: Path
) -> None:
    out = render(checkpoint, cache, "waymo5", tmp_path / "own", progress=False)
    assert out.frames == FRAMES and out.scenes == [SCENE]
    # The model's render of its input views, as the Stage 1 evaluation draws it.
    model = load_stage1(checkpoint)
    model.eval()
    data = Stage1Clips(cache, SIZE, 1, "auto")
    clip = data.clip(SCENE, 1, [], keep_frames=True)
    views = target_views(clip, 0, frame_truth(clip.frames[1], SIZE))  # type: ignore[index]
    with torch.no_grad():
        scene = model.predict(
            clip.context.images[None], clip.intrinsics[None], clip.context.world_from_camera[None],
            clip.context.time_s[None].float(), time_origin_micros=clip.time_origin_micros,
        )  # fmt: skip
        sky = model.background(views.world_from_camera.float(), views.intrinsics.float(), *SIZE)
        expected = render_views(scene, views, sky).rgb
    truth = _images(cache, 1)
    rendered = _images(tmp_path / "own", 1)
    # The named waymo5 rig at the cache's size is the cache's rig without its distortion: within
    # JPEG and distortion of the model's own render, and as far from the truth as that render.
    model_psnr = [_psnr((expected[c].numpy() * 255).round(), truth[c]) for c in range(5)]
    ours = [_psnr(rendered[c], truth[c]) for c in range(5)]
    assert np.mean(ours) == pytest.approx(np.mean(model_psnr), abs=0.5)


def test_truth_geometry_renders_the_own_rig_near_the_oracle_and_keeps_boxes_and_lidar(
    cache: Path, tmp_path: Path
) -> None:
    # The cache's own rig, lens distortion included, as a rig file.
    own = source_rig(CacheReader(cache).frame(0, decode_truth=False), "own")
    assert any(np.any(c.distortion) for c in own.cameras)
    rig_file = tmp_path / "own.yaml"
    rig_file.write_text(yaml.safe_dump(own.to_dict()))
    out_dir = tmp_path / "truth_geometry"
    render(None, cache, str(rig_file), out_dir, geometry="truth", progress=False)
    src, new = CacheReader(cache), CacheReader(out_dir)
    scores = []
    for i in range(FRAMES):
        a, b = src.frame(i), new.frame(i)
        assert b.timestamp_micros == a.timestamp_micros
        np.testing.assert_array_equal(b.world_from_ego, a.world_from_ego)
        np.testing.assert_array_equal(b.boxes.center_world, a.boxes.center_world)
        np.testing.assert_array_equal(b.lidar.points_ego, a.lidar.points_ego)  # type: ignore[union-attr]
        for ca, cb in zip(a.cameras, b.cameras, strict=True):
            assert cb.calibration.name == ca.calibration.name
            # The named rig fires when the synthetic rig does: each camera at its recorded time and pose.
            assert cb.timestamp_micros == ca.timestamp_micros
            np.testing.assert_allclose(cb.world_from_ego, ca.world_from_ego, atol=1e-9)
            scores.append(_psnr(cb.decode_image(), ca.decode_image()))
            # One Gaussian per pixel at the exact depth: the rendered depth is the truth to the
            # oracle's blending of neighbouring splats (its input-view AbsRel is 0.02, BENCHMARKS.md).
            assert cb.depth is not None and cb.depth.dense_m is not None and ca.truth is not None
            truth = ca.truth.depth_m
            both = (cb.depth.dense_m > 0) & (truth > 0)
            rel = np.abs(cb.depth.dense_m[both] / truth[both] - 1)
            assert both.mean() > 0.6 and np.median(rel) < 0.03
            assert set(np.unique(cb.depth.dense_origin)) <= {0, records.DENSE_ORIGINS.index("rendered")}
            # The sparse depth is the frame's LiDAR projected into the new camera: it agrees with
            # the rendered depth where both exist.
            sparse = cb.depth.sparse_m
            on = (sparse > 0) & (cb.depth.dense_m > 0)
            assert on.sum() > 20
            assert np.median(np.abs(sparse[on] / cb.depth.dense_m[on] - 1)) < 0.05
    # The oracle of the Stage 1 evaluation reaches about 26 dB on its input views at 48 x 72.
    assert np.mean(scores) > 24


def test_cache_geometry_lifts_the_dense_depth(cache: Path, tmp_path: Path) -> None:
    out_dir = tmp_path / "cache_geometry"
    render(None, cache, "waymo5", out_dir, geometry="cache", progress=False)
    a, b = CacheReader(cache).frame(1), CacheReader(out_dir).frame(1)
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        dense_a, dense_b = ca.depth.dense_m, cb.depth.dense_m  # type: ignore[union-attr]
        both = (dense_a > 0) & (dense_b > 0)  # type: ignore[operator]
        # Where the cache has depth, the render has it too, and the same.
        assert both.sum() > 0.8 * (dense_a > 0).sum()  # type: ignore[operator]
        assert np.median(np.abs(dense_b[both] / dense_a[both] - 1)) < 0.02  # type: ignore[index]


def test_a_nuscenes6_render_of_a_waymo5_cache_matches_the_exact_truth_of_that_rig(
    cache: Path, tmp_path: Path
) -> None:
    out_dir = tmp_path / "nusc"
    render(None, cache, "nuscenes6", out_dir, geometry="cache", progress=False)
    rig = named_rig("nuscenes6", *SIZE)
    reader = CacheReader(cache)
    truth = SyntheticTruth(reader.manifest.arguments, reader.manifest.source)
    frame = CacheReader(out_dir).frame(1)
    assert [c.calibration.name for c in frame.cameras] == [c.name for c in rig.cameras]
    front = 0
    for c in frame.cameras:
        _, tr = truth.render(SCENE, c.calibration, c.world_from_ego, c.timestamp_micros)
        both = (c.depth.dense_m > 0) & (tr.depth_m > 0)  # type: ignore[union-attr,operator]
        if both.sum() < 50:
            continue  # CAM_BACK and the back sides look where no waymo5 camera saw
        rel = np.abs(c.depth.dense_m[both] / tr.depth_m[both] - 1)  # type: ignore[union-attr,index]
        assert np.median(rel) < 0.03, c.calibration.name
        front += c.calibration.name == "CAM_FRONT"
    assert front == 1
    meta = json.loads(CacheReader(out_dir).shard(0).schema.metadata[b"phigenesis.scene_metadata"])
    assert meta["rendered_rig"]["name"] == "nuscenes6" and "ego_boxes" in meta


def test_the_rendered_cache_verifies_opens_with_plain_pyarrow_and_resumes(
    cache: Path, tmp_path: Path
) -> None:
    out_dir = tmp_path / "r"
    render(None, cache, "random", out_dir, geometry="cache", seed=3, progress=False)
    report = verify_cache(out_dir)
    assert report.ok, report
    manifest = json.loads((out_dir / "manifest.json").read_text())
    assert manifest["source"] == "rendered"
    args = manifest["arguments"]
    assert args["source_cache"] == str(cache.resolve()) and args["rig"] == "random" and args["seed"] == 3
    assert args["source_fingerprint"] == CacheReader(cache).manifest.fingerprint
    shard = out_dir / manifest["shards"][0]["path"]
    with pa.memory_map(str(shard)) as f:
        table = ipc.open_file(f).read_all()
    assert table.num_rows == FRAMES and "cameras" in table.column_names
    # A rerun of the same command resumes (nothing left to do), removing what an interrupted run
    # left; other arguments are refused.
    leftover = out_dir / "shards" / "x.arrow.tmp-123"
    leftover.write_bytes(b"partial")
    again = render(None, cache, "random", out_dir, geometry="cache", seed=3, progress=False)
    assert again.skipped == [SCENE] and again.frames == 0 and not leftover.exists()
    assert verify_cache(out_dir).ok
    with pytest.raises(PrepError, match=r"other arguments \(seed 3 -> 4\); choose another out$"):
        render(None, cache, "random", out_dir, geometry="cache", seed=4, progress=False)


def test_bad_rigs_and_inputs_are_refused_by_name(cache: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    rig = named_rig("waymo5", *SIZE).to_dict()
    rig["cameras"][1]["intrinsics"][0][0] = float("nan")
    bad = tmp_path / "nan_rig.yaml"
    bad.write_text(yaml.safe_dump(rig))
    with pytest.raises(RigError, match=r"nan_rig\.yaml.*FRONT_LEFT.*intrinsics"):
        render(None, cache, str(bad), tmp_path / "o1", geometry="cache", progress=False)
    inside = named_rig("waymo5", *SIZE).to_dict()
    inside["cameras"][0]["ego_from_camera"][2][3] = 0.8  # the FRONT camera lowered into the bonnet
    body = tmp_path / "in_body.yaml"
    body.write_text(yaml.safe_dump(inside))
    with pytest.raises(RigError, match=r"in_body\.yaml.*FRONT"):
        render(None, cache, str(body), tmp_path / "o2", geometry="cache", progress=False)
    assert not (tmp_path / "o1").exists() or not any((tmp_path / "o1").iterdir())
    with pytest.raises(ValueError, match="needs a Stage 1 checkpoint"):
        render(None, cache, "waymo5", tmp_path / "o3", progress=False)
    with pytest.raises(ValueError, match="4 frames one clip needs"):
        render(
            None,
            cache,
            "waymo5",
            tmp_path / "o6",
            geometry="cache",
            history_frames=FRAMES + 1,
            progress=False,
        )
    with pytest.raises(ValueError, match="no complete scene"):
        render(None, cache, "waymo5", tmp_path / "o4", geometry="cache", scenes=["nope"], progress=False)
    # The command line says the same in one line, exit status 2 or 1, no traceback.
    code = render_main(
        ["--shards", str(cache), "--rig", str(bad), "--geometry", "cache", "--out", str(tmp_path / "o5")]
    )
    err = capsys.readouterr().err
    assert code != 0 and "nan_rig.yaml" in err and "Traceback" not in err
