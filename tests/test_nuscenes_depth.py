"""Depth of the nuScenes and Waymo conversions against the exact synthetic truth.

The synthetic world written as nuScenes (``phigenesis-synth --format nuscenes``) and as Waymo v1
(``--format waymo-v1``) and converted with the bundled pipelines must carry the vehicle's own body
and depth on what the cameras see, matching the truth rendered from the same world at each
camera's own time and pose (the nuScenes caches of before had none: the default body held every
camera). Prep logs each camera's coverage once per scene and warns about empty ones; Stage 1
refuses a cache whose dense depth is (nearly) empty.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from phigenesis import prep
from phigenesis.data.clips import Stage1Clips
from phigenesis.data.ego_body import NUSCENES_ZOE_BOXES, WAYMO_PACIFICA_BOXES
from phigenesis.data.pipeline import PipelineSpec, load_pipeline
from phigenesis.data.records import DENSE_ORIGINS, TRUSTED_DEPTH_CONFIDENCE, Frame
from phigenesis.data.shards import CacheReader
from phigenesis.data.sources.synthetic import SyntheticScene
from phigenesis.data.sources.synthetic.nuscenes_export import nuscenes_scene_config
from phigenesis.synth import synth
from phigenesis.train.stage1 import train_stage1
from tests.conftest import NUSCENES_CONFIG, NUSCENES_KEYFRAMES, TINY_PREP_ARGS, tiny_config
from tests.test_stage1 import SIZE, tiny_train_config

NUSCENES_CAMERAS = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
#: Frames of the nuScenes cache compared with the rendered truth: the keyframes and one between.
TRUTH_FRAMES = (0, 3, 6, 12)


@contextmanager
def prep_log() -> Iterator[list[logging.LogRecord]]:
    """The records the ``phigenesis.prep`` logger emits (INFO and up) inside the block."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("phigenesis.prep")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def scene_metadata(cache: Path) -> dict:
    """The scene metadata stored in the first shard's schema."""
    manifest = json.loads((cache / "manifest.json").read_text())
    with pa.memory_map(str(cache / manifest["shards"][0]["path"])) as f:
        meta = pa.ipc.open_file(f).schema.metadata
    return json.loads(meta[b"phigenesis.scene_metadata"])


def coverage_lines(records: list[logging.LogRecord]) -> list[str]:
    return [r.getMessage() for r in records if "depth coverage over" in r.getMessage()]


@pytest.fixture(scope="module")
def nuscenes_cache(
    nuscenes_dataroot: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, list[logging.LogRecord]]:
    """The shared nuScenes export converted with the bundled nuScenes pipeline, and its prep log."""
    out = tmp_path_factory.mktemp("nuscenes_depth") / "cache"
    with prep_log() as records:
        prep.nuscenes(out, dataroot=nuscenes_dataroot, progress=False)
    return out, records


@pytest.fixture(scope="module")
def truth_scene() -> SyntheticScene:
    """The synthetic world the export rendered (its 12 Hz frames are the export's camera steps)."""
    return SyntheticScene(nuscenes_scene_config(NUSCENES_CONFIG, NUSCENES_KEYFRAMES), 0)


def truth_depth(scene: SyntheticScene, frame: Frame) -> dict[str, np.ndarray]:
    """Exact z-depth (H, W, metres; 0 = sky) of each camera of a cache frame, rendered from the
    synthetic world at that camera's own capture time and the ego pose then."""
    calibrations = {c.name: c for c in scene.calibrations}
    out = {}
    for cam in frame.cameras:
        t = cam.timestamp_micros
        _, truth = scene.renderer.render_camera(
            calibrations[cam.name], scene.world_from_ego(t), scene.seconds(t)
        )
        out[cam.name] = truth.depth_m
    return out


def test_nuscenes_scenes_carry_the_zoe_body(nuscenes_cache):
    cache, _ = nuscenes_cache
    assert scene_metadata(cache)["ego_boxes"] == NUSCENES_ZOE_BOXES


def test_nuscenes_dense_depth_covers_the_views_and_matches_the_exact_truth(nuscenes_cache, truth_scene):
    """Before the Zoe's body, every pixel was "ego body": coverage 0 on every camera."""
    cache, _ = nuscenes_cache
    reader = CacheReader(cache)
    sparse, known, truth_pixels, errors, trusted_errors, densified_pixels = {}, 0, 0, [], [], 0
    for index in TRUTH_FRAMES:
        frame = reader.frame(index)
        truth = truth_depth(truth_scene, frame)
        for cam in frame.cameras:
            d, t = cam.depth, truth[cam.name]
            sparse.setdefault(cam.name, []).append(np.mean(d.sparse_m > 0))
            both = (d.dense_m > 0) & (t > 0)
            known += int(both.sum())
            truth_pixels += int((t > 0).sum())
            errors.append(np.abs(d.dense_m[both] - t[both]) / t[both])
            # The densifier's own pixels (complete_depth's completions are below trusted by design).
            densified = both & (d.dense_origin <= DENSE_ORIGINS.index("densified"))
            densified_pixels += int(densified.sum())
            trusted = densified & (d.dense_confidence >= TRUSTED_DEPTH_CONFIDENCE)
            trusted_errors.append(np.abs(d.dense_m[trusted] - t[trusted]) / t[trusted])
    assert sorted(sparse) == sorted(NUSCENES_CAMERAS)
    # Measured on these frames (16-beam LiDAR, 96 x 160 images): sparse on 6-27 % of a camera's
    # pixels per frame, 10-25 % per camera; dense on 9.7 % of the pixels with a truth depth (the
    # densifier seeds from trusted depths only, and at this size most lie near a depth edge).
    assert min(np.mean(v) for v in sparse.values()) > 0.05, sparse
    assert known / truth_pixels > 0.05, known / truth_pixels
    # Measured: AbsRel median 0.00065 (p90 0.009) on every dense pixel; 59 % of them are trusted,
    # median 0.00044 (p90 0.006).
    errors, trusted_errors = np.concatenate(errors), np.concatenate(trusted_errors)
    assert np.median(errors) < 0.005 and np.percentile(errors, 90) < 0.05
    assert len(trusted_errors) > 0.4 * densified_pixels and np.median(trusted_errors) < 0.003


def test_prep_logs_each_cameras_coverage_once_per_scene_and_no_warning_when_it_is_fine(nuscenes_cache):
    _, records = nuscenes_cache
    (line,) = coverage_lines(records)
    assert "over 13 frames" in line and "share of pixels with a sparse depth" in line
    for name in NUSCENES_CAMERAS:
        assert f"{name} " in line
    assert not [r for r in records if r.levelno >= logging.WARNING and "sparse depth" in r.getMessage()]


def test_stage1_accepts_the_nuscenes_cache(nuscenes_cache):
    cache, _ = nuscenes_cache
    assert len(Stage1Clips(cache, SIZE).windows()) == 13


@pytest.fixture(scope="module")
def blind_cache(
    nuscenes_dataroot: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, list[logging.LogRecord]]:
    """The nuScenes export converted with a pipeline that projects nothing (every point beyond
    ``max_range_m``): empty depth, as the default body gave every nuScenes cache before."""
    spec = load_pipeline("nuscenes").to_dict()
    for stage in spec["stages"]:
        if stage["name"] == "project_depth":
            stage["params"]["max_range_m"] = 0.6
    cache = tmp_path_factory.mktemp("blind") / "blind"
    with prep_log() as records:
        prep.nuscenes(
            cache, dataroot=nuscenes_dataroot, pipeline=PipelineSpec.from_dict(spec), progress=False
        )
    return cache, records


def test_prep_warns_naming_each_camera_whose_depth_is_empty(blind_cache):
    _, records = blind_cache
    warned = [
        r.getMessage() for r in records if r.levelno == logging.WARNING and "sparse depth" in r.getMessage()
    ]
    assert len(warned) == len(NUSCENES_CAMERAS)
    for name, message in zip(NUSCENES_CAMERAS, warned, strict=True):
        assert f"camera {name}: only 0.00 % of its pixels have a sparse depth" in message
    (line,) = coverage_lines(records)
    assert "CAM_FRONT 0.0 %" in line


def test_stage1_training_refuses_a_cache_whose_dense_depth_is_empty_naming_it_and_its_coverage(
    blind_cache, tmp_path: Path
) -> None:
    cache, _ = blind_cache
    with pytest.raises(
        ValueError, match=r"blind: the cache's dense depth is \(nearly\) empty: 0\.00 %"
    ) as info:
        train_stage1(cache, tmp_path / "run", tiny_train_config(steps=1), progress=False)
    assert "CAM_BACK 0.00 %" in str(info.value) and "of 8 frames" in str(info.value)
    assert not (tmp_path / "run" / "model.safetensors").exists()


def test_waymo_v1_export_converts_with_the_pacifica_body_and_has_depth(tmp_path: Path) -> None:
    config = tiny_config(scenes=1, frames=3)
    synth(
        "waymo-v1",
        tmp_path / "v1",
        frames=3,
        seed=config.seed,
        height=60,
        width=90,
        lidar=TINY_PREP_ARGS["lidar"],
    )
    cache = tmp_path / "cache"
    with prep_log() as records:
        prep.waymo(cache, input=tmp_path / "v1", progress=False)
    assert scene_metadata(cache)["ego_boxes"] == WAYMO_PACIFICA_BOXES
    (line,) = coverage_lines(records)
    assert "over 3 frames" in line
    reader = CacheReader(cache)
    for index in range(len(reader)):
        for cam in reader.frame(index).cameras:
            # Measured: sparse on 1.8-20 % of a camera's pixels per frame, dense on 7-9 % of all.
            assert np.mean(cam.depth.sparse_m > 0) > 0.01, (index, cam.name)
        dense = np.mean([np.mean(c.depth.dense_m > 0) for c in reader.frame(index).cameras])
        assert dense > 0.04, (index, dense)
