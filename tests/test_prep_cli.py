"""Tests for ``phigenesis-prep`` and phigenesis.prep: bad --out, resume, kill, executors, errors, preview."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest

from phigenesis import prep
from phigenesis.cli.prep import main
from phigenesis.data.pipeline import PipelineSpec, PrepError, StageSpec, load_pipeline
from phigenesis.data.records import Scene
from phigenesis.data.shards import MANIFEST_NAME, SHARDS_DIR, TMP_MARKER, CacheReader, Manifest, verify_cache
from phigenesis.data.stages import register_stage
from tests.conftest import TINY_PREP_ARGS

# A pipeline spec for command-line runs: tiny LiDAR, one row per shard (so a scene spans several
# shard files and a killed run can leave complete shards of an unfinished scene behind).
TINY_PIPELINE_YAML = """\
name: synthetic-tiny
source:
  name: synthetic
  params:
    rig: waymo5
    lidar: {beams: 16, columns: 256, sectors: 8}
stages: []
output:
  camera_truth: [depth, semantic, instance, flow]
  lidar: true
  lidar_truth: true
  shard_max_bytes: 1
"""
CLI_SCENES, CLI_FRAMES, CLI_SEED = 3, 5, 3


# --------------------------------------------------------------------------------------------
# Helpers and fixtures


def prep_command() -> list[str]:
    exe = Path(sys.executable).with_name("phigenesis-prep")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "phigenesis.cli.prep"]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def shard_state(cache: Path) -> dict[str, tuple[str, int]]:
    """Every file under shards/ with its SHA-256 and mtime."""
    return {p.name: (sha256(p), p.stat().st_mtime_ns) for p in sorted((cache / SHARDS_DIR).iterdir())}


def rows(cache: Path) -> list[pa.RecordBatch]:
    return list(CacheReader(cache))


def row_keys(cache: Path) -> list[tuple[str, int]]:
    return [(b.column("scene_id")[0].as_py(), b.column("frame_index")[0].as_py()) for b in rows(cache)]


def assert_same_rows(cache: Path, reference: Path) -> None:
    got, want = rows(cache), rows(reference)
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.schema.equals(b.schema, check_metadata=True)
        assert a.equals(b), (a.column("scene_id")[0], a.column("frame_index")[0])


@pytest.fixture(scope="module")
def tiny_pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("pipeline") / "tiny.yaml"
    path.write_text(TINY_PIPELINE_YAML)
    return path


def cli_args(out: Path, pipeline: Path, scenes: int = CLI_SCENES, frames: int = CLI_FRAMES) -> list[str]:
    return [
        "synthetic",
        "--out",
        str(out),
        "--scenes",
        str(scenes),
        "--frames",
        str(frames),
        "--seed",
        str(CLI_SEED),
        "--height",
        "32",
        "--width",
        "48",
        "--pipeline",
        str(pipeline),
        "--no-progress",
    ]


@pytest.fixture(scope="module")
def cli_cache(tiny_pipeline: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache made by one uninterrupted ``phigenesis-prep synthetic`` run (read-only for tests)."""
    out = tmp_path_factory.mktemp("cli") / "cache"
    proc = subprocess.run(
        [*prep_command(), *cli_args(out, tiny_pipeline)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def copy_cache(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)  # copy2: keeps the mtimes
    return dst


# --------------------------------------------------------------------------------------------
# Resume and kill


def test_rerunning_the_same_command_skips_finished_scenes_and_leaves_shards_untouched(
    cli_cache: Path, tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cache = copy_cache(cli_cache, tmp_path / "cache")
    before = shard_state(cache)
    assert main(cli_args(cache, tiny_pipeline)) == 0
    out = capsys.readouterr().out
    assert "wrote 0 scenes (0 frames" in out
    assert f"{CLI_SCENES} scenes were already complete and were skipped" in out
    assert shard_state(cache) == before


def _manifest_state(cache: Path) -> tuple[list[str], set[str]]:
    """Complete scenes and listed shards of the manifest as it is on disk now."""
    try:
        d = json.loads((cache / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return [], set()
    return [s["id"] for s in d["scenes"] if s["status"] == "complete"], {s["path"] for s in d["shards"]}


def _final_shards(cache: Path) -> set[str]:
    shard_dir = cache / SHARDS_DIR
    return {f"{SHARDS_DIR}/{p.name}" for p in shard_dir.glob("*.arrow")} if shard_dir.is_dir() else set()


@pytest.mark.slow
def test_a_run_killed_part_way_resumes_to_exactly_the_frames_of_an_uninterrupted_run(
    cli_cache: Path, tiny_pipeline: Path, tmp_path: Path
) -> None:
    cache = tmp_path / "cache"
    command = [*prep_command(), *cli_args(cache, tiny_pipeline)]
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    caught_mid_run = False
    try:
        # Kill once a scene is recorded complete and the next scene has renamed a shard into
        # place that the manifest does not list yet (mid-scene, deterministic with 1 row/shard).
        # Shards are listed before the manifest is read: a listed set only grows during a run.
        while proc.poll() is None and time.monotonic() < deadline:
            finals = _final_shards(cache)
            complete, listed = _manifest_state(cache)
            if complete and finals - listed:
                caught_mid_run = True
                break
            time.sleep(0.005)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert caught_mid_run, f"the run ended (rc={proc.returncode}) or stalled before it could be killed"
    assert proc.returncode == -signal.SIGKILL
    complete, listed = _manifest_state(cache)
    assert 1 <= len(complete) < CLI_SCENES
    unfinished = (_final_shards(cache) - listed) | {
        f"{SHARDS_DIR}/{p.name}" for p in (cache / SHARDS_DIR).glob(f"*{TMP_MARKER}*")
    }

    rerun = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert f"{len(complete)} scenes were already complete and were skipped" in rerun.stdout
    if unfinished:
        assert "unfinished files left by an interrupted run" in rerun.stderr

    keys = row_keys(cache)
    want = [(f"synthetic-s{CLI_SEED}-{s:04d}", k) for s in range(CLI_SCENES) for k in range(CLI_FRAMES)]
    assert keys == want  # none missing, none duplicated, in order
    assert row_keys(cli_cache) == want
    assert_same_rows(cache, cli_cache)
    assert sorted(p.name for p in (cache / SHARDS_DIR).iterdir()) == sorted(
        p.name for p in (cli_cache / SHARDS_DIR).iterdir()
    )
    report = verify_cache(cache)
    assert report.ok, report.errors
    assert report.warnings == []


# --------------------------------------------------------------------------------------------
# Bad --out


def test_a_cache_made_otherwise_is_refused_in_the_callers_language(
    tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Python callers read the keyword to pass (``overwrite=True``), the command line the flag."""
    out = tmp_path / "cache"
    assert main(cli_args(out, tiny_pipeline, scenes=1, frames=2)) == 0
    capsys.readouterr()
    with pytest.raises(PrepError) as refused:
        prep.synthetic(
            out, scenes=1, frames=2, seed=CLI_SEED + 1, height=32, width=48, pipeline=tiny_pipeline
        )
    message = str(refused.value)
    assert "use overwrite=True to replace it or choose another out" in message and "--" not in message
    args = cli_args(out, tiny_pipeline, scenes=1, frames=2)
    args[args.index("--seed") + 1] = str(CLI_SEED + 1)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "use --overwrite to replace it or choose another --out" in err and "overwrite=True" not in err
    assert "\x1f" not in err and "\x1f" not in message


def test_out_that_is_an_existing_file_is_refused_and_the_file_untouched(
    tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "notes.txt"
    target.write_text("keep me")
    assert main(cli_args(target, tiny_pipeline)) == 2
    err = capsys.readouterr().err
    assert f"--out {target} is a file, not a directory" in err
    assert target.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_out_in_an_unwritable_location_is_refused_naming_the_path(
    tiny_pipeline: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = Path("/sys/phigenesis-test-cache")  # /sys refuses new entries even to root
    if not Path("/sys").is_dir() or target.exists():
        pytest.skip("needs a /sys that refuses new directories")
    assert main(cli_args(target, tiny_pipeline)) == 2
    err = capsys.readouterr().err
    assert f"--out {target} cannot be created" in err
    assert "Traceback" not in err
    assert not target.exists()


def test_out_below_a_file_cannot_be_created_and_the_error_names_it(
    tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("keep me")
    target = blocker / "cache"
    assert main(cli_args(target, tiny_pipeline)) == 2
    err = capsys.readouterr().err
    assert f"--out {target} cannot be created" in err and "Traceback" not in err
    assert blocker.read_text() == "keep me"


def test_out_that_is_an_existing_unwritable_directory_is_refused_naming_the_path(
    tiny_pipeline: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = Path("/sys/kernel")
    if not target.is_dir():
        pytest.skip("needs /sys/kernel")
    assert main(cli_args(target, tiny_pipeline)) == 2
    assert f"--out {target} is not writable" in capsys.readouterr().err


def test_out_that_is_a_non_empty_directory_without_a_cache_is_refused_and_left_untouched(
    tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "notes.txt").write_text("keep me")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x.arrow").write_bytes(b"not ours")
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in tmp_path.rglob("*") if p.is_file()}
    assert main(cli_args(tmp_path, tiny_pipeline)) == 2
    err = capsys.readouterr().err
    assert f"--out {tmp_path} is not empty and holds no phigenesis cache" in err
    after = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "notes.txt"]


def test_shard_files_without_a_manifest_are_not_ours_and_are_left_untouched(
    tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "shards").mkdir()
    (tmp_path / "shards" / "someone-elses.arrow").write_bytes(b"keep me")
    assert main(cli_args(tmp_path, tiny_pipeline)) == 2
    assert "is not empty and holds no phigenesis cache" in capsys.readouterr().err
    assert (tmp_path / "shards" / "someone-elses.arrow").read_bytes() == b"keep me"


def test_existing_cache_made_with_other_arguments_is_refused_naming_what_differs(
    cli_cache: Path, tiny_pipeline: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cache = copy_cache(cli_cache, tmp_path / "cache")
    before = shard_state(cache)
    manifest_before = (cache / MANIFEST_NAME).read_bytes()
    assert main(cli_args(cache, tiny_pipeline, frames=CLI_FRAMES + 1)) == 2
    err = capsys.readouterr().err
    assert "holds a cache made with other arguments" in err
    assert f"frames {CLI_FRAMES} -> {CLI_FRAMES + 1}" in err
    # only what really differs is named
    assert "lidar" not in err
    assert "scenes" not in err
    assert "pipeline" not in err
    assert shard_state(cache) == before
    assert (cache / MANIFEST_NAME).read_bytes() == manifest_before


def test_overwrite_replaces_a_cache_made_with_other_arguments(
    cli_cache: Path, tiny_pipeline: Path, tmp_path: Path
) -> None:
    cache = copy_cache(cli_cache, tmp_path / "cache")
    assert main([*cli_args(cache, tiny_pipeline, scenes=1, frames=1), "--overwrite"]) == 0
    manifest = Manifest.load(cache)
    assert (manifest.arguments["scenes"], manifest.arguments["frames"]) == (1, 1)
    assert row_keys(cache) == [(f"synthetic-s{CLI_SEED}-0000", 0)]
    assert sorted(p.name for p in (cache / SHARDS_DIR).iterdir()) == [
        f"synthetic-s{CLI_SEED}-0000-00000.arrow"
    ]
    report = verify_cache(cache)
    assert report.ok and report.warnings == []


def test_prep_rerun_on_a_truncated_manifest_exits_2_naming_it_without_a_traceback(
    cli_cache: Path, tiny_pipeline: Path, tmp_path: Path
) -> None:
    cache = copy_cache(cli_cache, tmp_path / "cache")
    path = cache / MANIFEST_NAME
    path.write_bytes(path.read_bytes()[:100])
    before = shard_state(cache)
    proc = subprocess.run(
        [*prep_command(), *cli_args(cache, tiny_pipeline)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert f"{path}: manifest is truncated" in proc.stderr
    assert "--overwrite" in proc.stderr
    assert shard_state(cache) == before


# --------------------------------------------------------------------------------------------
# Executors


@pytest.mark.slow
def test_local_pool_with_two_workers_writes_the_same_rows_as_the_inline_run(
    tiny_cache: Path, tmp_path: Path
) -> None:
    summary = prep.synthetic(tmp_path, workers=2, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]
    assert sorted(summary.scenes_written) == sorted(s.id for s in Manifest.load(tiny_cache).scenes)
    assert_same_rows(tmp_path, tiny_cache)


@pytest.mark.slow
def test_ray_executor_writes_the_same_rows_as_the_inline_run(tiny_cache: Path, tmp_path: Path) -> None:
    pytest.importorskip("ray")
    summary = prep.synthetic(tmp_path, executor="ray", workers=2, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]
    assert sorted(summary.scenes_written) == sorted(s.id for s in Manifest.load(tiny_cache).scenes)
    assert_same_rows(tmp_path, tiny_cache)


# --------------------------------------------------------------------------------------------
# --on-error

FAILING_STAGE = "tests-fail-one-scene"


@register_stage(FAILING_STAGE)
def _fail_one_scene(scene: Scene, params: dict[str, Any]) -> Scene:
    if scene.scene_id == params["scene_id"]:
        raise RuntimeError(f"deliberate failure of {scene.scene_id}")
    return scene


ON_ERROR_ARGS: dict[str, Any] = {**TINY_PREP_ARGS, "scenes": 3, "frames": 1}
SCENES = [f"synthetic-s{TINY_PREP_ARGS['seed']}-{i:04d}" for i in range(3)]


def failing_pipeline(scene_id: str) -> PipelineSpec:
    return dataclasses.replace(
        load_pipeline("synthetic"), stages=(StageSpec(FAILING_STAGE, {"scene_id": scene_id}),)
    )


def test_on_error_raise_stops_at_the_failing_scene_naming_it_and_keeps_finished_scenes(
    tmp_path: Path,
) -> None:
    with pytest.raises(PrepError, match=f"scene {SCENES[1]} failed: RuntimeError: deliberate failure"):
        prep.synthetic(
            tmp_path, pipeline=failing_pipeline(SCENES[1]), on_error="raise", progress=False, **ON_ERROR_ARGS
        )
    manifest = Manifest.load(tmp_path)
    assert manifest.scene(SCENES[0]).status == "complete"
    assert manifest.scene(SCENES[1]).status == "failed"
    assert "deliberate failure" in manifest.scene(SCENES[1]).error
    assert manifest.scene(SCENES[2]) is None
    assert row_keys(tmp_path) == [(SCENES[0], 0)]
    assert verify_cache(tmp_path).ok


def test_on_error_skip_converts_the_other_scenes_and_records_the_skipped_one(tmp_path: Path) -> None:
    summary = prep.synthetic(
        tmp_path, pipeline=failing_pipeline(SCENES[1]), on_error="skip", progress=False, **ON_ERROR_ARGS
    )
    assert summary.scenes_written == [SCENES[0], SCENES[2]]
    assert list(summary.scenes_skipped) == [SCENES[1]]
    manifest = Manifest.load(tmp_path)
    skipped = manifest.scene(SCENES[1])
    assert skipped.status == "skipped"
    assert "RuntimeError: deliberate failure" in skipped.error
    assert row_keys(tmp_path) == [(SCENES[0], 0), (SCENES[2], 0)]
    report = verify_cache(tmp_path)
    assert report.ok, report.errors
    assert any(SCENES[1] in w and "skipped" in w for w in report.warnings)


# --------------------------------------------------------------------------------------------
# Preview


def test_preview_writes_a_non_blank_png_of_the_expected_size(
    tiny_cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sub" / "frame.png"
    scale = 2
    assert main(["preview", str(tiny_cache), "--frame", "4", "--out", str(out), "--scale", str(scale)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.dtype == np.uint8
    cameras = len(CacheReader(tiny_cache).frame(4).cameras)
    h, w = TINY_PREP_ARGS["height"], TINY_PREP_ARGS["width"]
    rows = 3 * h * scale  # images, truth depth, truth semantics
    assert image.shape[1:] == (cameras * w * scale + rows, 3)  # + a square bird's-eye view
    assert image.shape[0] > rows  # the depth colour bar and the class legend below (issue 14)
    assert image.std() > 10
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 100
