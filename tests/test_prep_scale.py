"""Prep at real size: per-scene work done once per scene (counted), every part of a scene timed,
and the log saying what the written rows hold."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from phigenesis import prep
from phigenesis import taxonomy as tx
from phigenesis.data import camera_tables
from phigenesis.data.coverage import SceneCoverage
from phigenesis.data.records import Boxes, CameraCalibration, CameraDepth, CameraImage, CameraSemantics, Frame
from phigenesis.data.shards import CacheReader
from phigenesis.data.stages import SETUP_RUNS
from tests.conftest import TINY_PREP_ARGS

STAGES = (
    "box_tracks",
    "aggregate_lidar",
    "project_depth",
    "densify_depth",
    "pseudo_semantics",
    "complete_depth",
    "scene_flow",
    "range_view",
)


@pytest.fixture(scope="module")
def counted_run(tmp_path_factory: pytest.TempPathFactory):
    """A 2-scene x 3-frame synthetic prep (inline: one process) with the counters zeroed first,
    and its log."""
    camera_tables.clear()
    camera_tables.COMPUTED.clear()
    SETUP_RUNS.clear()
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("phigenesis.prep")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        summary = prep.synthetic(tmp_path_factory.mktemp("counted"), progress=False, **TINY_PREP_ARGS)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    return summary, dict(camera_tables.COMPUTED), dict(SETUP_RUNS), [r.getMessage() for r in records]


def test_per_calibration_tables_are_computed_once_for_all_stages_and_frames(counted_run):
    summary, computed, setups, _ = counted_run
    assert summary.frames_written == 6
    # Both scenes use the same five calibrations: five of each table in all, shared by the
    # projection, the labels, the completion and the range view of all six frames.
    assert {"pixel_rays", "ego_body_depth", "ray_components", "ray_extents"} <= set(computed)
    assert computed == dict.fromkeys(computed, 5), computed
    assert setups == {"project_depth": 2, "range_view": 2}  # the stages' declared setups: once per scene


def test_every_part_of_a_scene_is_timed(counted_run):
    summary, _, _, messages = counted_run
    assert sorted(summary.timings) == sorted(summary.scenes_written)
    for timing in summary.timings.values():
        assert timing["frames"] == 3
        assert list(timing["frame_s"]) == ["read", *STAGES, "write"]
        assert list(timing["scene_s"]) == ["load", *STAGES]
        assert all(v >= 0 for v in [*timing["frame_s"].values(), *timing["scene_s"].values()])
        # The aggregation reads every frame's geometry when the stage is called: per-scene work.
        assert timing["scene_s"]["aggregate_lidar"] > timing["frame_s"]["aggregate_lidar"]
    lines = [m for m in messages if "CPU-s per frame over 3 frames" in m]
    assert len(lines) == 2 and "per frame: read " in lines[0] and "complete_depth" in lines[0]


def test_the_log_gives_the_coverage_of_what_was_written_after_completion(counted_run):
    summary, _, _, messages = counted_run
    lines = [m for m in messages if "what the cache holds over 3 frames" in m]
    assert len(lines) == 2
    reader = CacheReader(summary.cache_dir)
    for scene_id, line in zip(summary.scenes_written, lines, strict=True):
        assert line.startswith(f"scene {scene_id}:")
        frames = [reader.frame(i) for i in range(len(reader)) if reader.frame(i).scene_id == scene_id]
        for name in ("FRONT", "SIDE_LEFT"):
            dense = np.mean([np.mean(f.camera(name).depth.dense_m > 0) for f in frames])
            pseudo = np.mean([np.mean(f.camera(name).pseudo.semantic != tx.IGNORE_ID) for f in frames])
            assert f"{name} (sparse " in line
            logged = line.split(f"{name} (")[1].split(")")[0]
            assert f"dense {100 * dense:.1f} %" in logged and f"pseudo labels {100 * pseudo:.1f} %" in logged
    # The densifier's own line gives only the sparse share: completion fills more after it.
    assert all("dense" not in m for m in messages if "sparse depth coverage over" in m)


def _labelled_frame(index: int, labelled_pixels: int) -> Frame:
    cal = CameraCalibration(
        "CAM", 100, 50, np.array([[50.0, 0, 49.5], [0, 50.0, 24.5], [0, 0, 1]]), np.zeros(5), np.eye(4)
    )
    semantic = np.full((50, 100), tx.IGNORE_ID, np.uint8)
    semantic.reshape(-1)[:labelled_pixels] = tx.ROAD
    cam = CameraImage(cal, index * 100_000, np.eye(4), None)
    cam.pseudo = CameraSemantics(
        semantic, (semantic != tx.IGNORE_ID).astype(np.float32), np.zeros_like(semantic)
    )
    sparse = np.zeros((50, 100), np.float32)
    sparse[:10] = 5.0
    cam.depth = CameraDepth(sparse, (sparse > 0).astype(np.float32), np.zeros((50, 100), np.uint8))
    return Frame("s", index, index * 100_000, np.eye(4), [cam], None, Boxes.empty())


def test_the_coverage_line_counts_each_map_over_the_frames_written(caplog):
    coverage = SceneCoverage("s")
    for i in range(2):
        coverage.add(_labelled_frame(i, 20 + 40 * i))
    with caplog.at_level(logging.INFO, logger="phigenesis.prep"):
        coverage.report()
    (info,) = [r.getMessage() for r in caplog.records]
    # 20 + 60 labelled pixels of 10,000; 1,000 sparse depths per frame; no dense map.
    assert info == (
        "scene s: what the cache holds over 2 frames, share of pixels: "
        "CAM (sparse 20.0 %, dense 0.0 %; pseudo labels 0.8 %)"
    )
