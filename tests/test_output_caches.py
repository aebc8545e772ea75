"""Every command that writes a cache (prep, render, generate, Stage 2's latents) takes the cache's
lock, resumes after a kill or a full disk, and ``verify`` tells complete, incomplete and damaged
caches apart (phigenesis.data.cache_run, phigenesis.data.shards.verify_cache)."""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
import torch
import yaml

from phigenesis import prep
from phigenesis.cli.prep import main as prep_main
from phigenesis.data.cache_lock import LOCK_NAME, CacheLock
from phigenesis.data.cache_run import writing_cache
from phigenesis.data.pipeline import load_pipeline
from phigenesis.data.shards import (
    MANIFEST_NAME,
    CacheError,
    CacheReader,
    Manifest,
    ShardWriter,
    verify_cache,
)
from phigenesis.errors import PrepError
from phigenesis.infer.generate import GENERATED_SUFFIX, generate
from phigenesis.infer.rig_render import render
from phigenesis.models.loading import load_stage1
from phigenesis.rollout.config import Stage2DataConfig, Stage2TrainConfig
from phigenesis.rollout.runner import GenerateOptions
from phigenesis.train.stage2 import train_stage2
from phigenesis.train.stage2_data import precompute_stage2
from tests.conftest import TINY_PREP_ARGS, two_step_stage1

SCENES = ["synthetic-s7-0000", "synthetic-s7-0001"]
#: Frames rendered per scene (the scenes have 6: one Stage 2 window of 1 + 5 frames each).
RENDER_FRAMES = 3
STEPS = GenerateOptions(steps=1)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 scenes x 6 frames at 48 x 72 (read-only for the tests)."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("frames")
    prep.synthetic(out, progress=False, **{**TINY_PREP_ARGS, "frames": 6, "height": 48, "width": 72})  # type: ignore[arg-type]
    return out


@pytest.fixture(scope="module")
def rendered(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The render of ``cache`` that no kill interrupted (the reference; it also builds the native
    rasterizer, if any, before the child processes load it)."""
    out = tmp_path_factory.mktemp("rendered") / "r"
    render(None, cache, "waymo5", out, geometry="cache", max_frames=RENDER_FRAMES, progress=False)
    return out


@pytest.fixture(scope="module")
def stage1_checkpoint(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return two_step_stage1(cache, tmp_path_factory)


@pytest.fixture(scope="module")
def latents(cache: Path, stage1_checkpoint: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The latent cache that no kill interrupted (the reference)."""
    out = tmp_path_factory.mktemp("latents") / "latents"
    precompute_latents(cache, out, stage1_checkpoint)
    return out


@pytest.fixture(scope="module")
def stage2_checkpoint(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    config = Stage2TrainConfig(steps=2, batch_size=2, warmup_steps=1, checkpoint_every=2, threads=1)
    folder = tmp_path_factory.mktemp("s2")
    run = train_stage2(cache, folder, config, stage1=stage1_checkpoint, latents=latents, progress=False)
    assert run.checkpoint is not None
    return run.checkpoint


# --------------------------------------------------------------------------------------------
# Helpers


def precompute_latents(cache: Path, out: Path, stage1_checkpoint: Path) -> Path:
    """The latent cache of ``cache`` with the default window options, into ``out``."""
    model = load_stage1(stage1_checkpoint)
    return precompute_stage2(cache, out, model, Stage2DataConfig(), stage1_checkpoint=str(stage1_checkpoint))


#: Prepended to a child's script: the child kills itself (SIGKILL, as ``kill -9`` does) as it is
#: about to write shard row number $KILL_AT_ROW (0-based, counted over the whole run).
KILLED_AT_ROW = r"""
import os, signal
from phigenesis.data import shards
limit, rows = int(os.environ["KILL_AT_ROW"]), []
real_write = shards.ShardWriter.write
def write(self, batch):
    if len(rows) == limit:
        os.kill(os.getpid(), signal.SIGKILL)
    rows.append(self.scene_id)
    real_write(self, batch)
shards.ShardWriter.write = write
"""

RENDER_CLI = "import sys\nfrom phigenesis.cli.render import main\nsys.exit(main(sys.argv[1:]))\n"
GENERATE_CLI = "import sys\nfrom phigenesis.cli.generate import main\nsys.exit(main(sys.argv[1:]))\n"
PREP_CLI = "import sys\nfrom phigenesis.cli.prep import main\nsys.exit(main(sys.argv[1:]))\n"
LATENTS = r"""
import sys
from phigenesis.models.loading import load_stage1
from phigenesis.train.stage2_data import precompute_stage2
from phigenesis.rollout.config import Stage2DataConfig
cache, out, ckpt = sys.argv[1:4]
precompute_stage2(cache, out, load_stage1(ckpt), Stage2DataConfig(), stage1_checkpoint=ckpt)
"""


def child(
    script: str,
    *args: object,
    env: dict[str, str] | None = None,
    preexec_fn: Callable[[], None] | None = None,
) -> subprocess.CompletedProcess[str]:
    """Runs ``script`` with ``args`` in a new Python process (one torch thread, ``env`` added to
    this one's environment); waits for it."""
    return subprocess.run(
        [sys.executable, "-c", script, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
        preexec_fn=preexec_fn,
    )


def killed_at_row(row: int, script: str, *args: object) -> None:
    """Runs ``script`` in a child killed as it is about to write shard row ``row``."""
    proc = child(KILLED_AT_ROW + script, *args, env={"KILL_AT_ROW": str(row)})
    assert proc.returncode == -9, f"not killed (exit {proc.returncode}):\n{proc.stdout}{proc.stderr}"


def render_argv(cache: Path, out: Path) -> list[str]:
    return [
        "--shards", str(cache), "--rig", "waymo5", "--geometry", "cache", "--out", str(out),
        "--max-frames", str(RENDER_FRAMES), "--no-progress",
    ]  # fmt: skip


def generate_argv(ckpt: Path, cache: Path, out: Path) -> list[str]:
    return [
        "--ckpt", str(ckpt), "--shards", str(cache), "--scene", SCENES[0], "--start", "1", "--frames", "5",
        "--steps", "1", "--out", str(out), "--no-progress",
    ]  # fmt: skip


def contents(cache: Path) -> dict[str, Any]:
    """What a cache holds, byte for byte: each finished scene and its shards' names, rows, sizes
    and whole-file CRC-32Cs (paths of the folder itself left out)."""
    manifest = Manifest.load(cache)
    return {
        "scenes": [(s.id, s.status, s.frames, s.shards) for s in manifest.scenes],
        "shards": [(sh.path, sh.rows, sh.bytes, sh.file_crc32c) for sh in manifest.shards],
        "expected": manifest.scenes_expected,
    }


def verify_command(cache: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``phigenesis-prep verify CACHE``: (exit status, stdout)."""
    capsys.readouterr()
    code = prep_main(["verify", str(cache)])
    return code, capsys.readouterr().out


def leftovers(cache: Path) -> list[str]:
    """Files under ``cache`` that a finished run does not leave (temporaries, the lock)."""
    return sorted(p.name for p in cache.rglob("*") if ".tmp-" in p.name or p.name == LOCK_NAME)


# --------------------------------------------------------------------------------------------
# One lock for every cache writer


@pytest.mark.parametrize("writer", ["render", "generate", "latents"])
def test_every_cache_writer_is_refused_while_another_run_holds_the_caches_lock(
    writer: str, cache: Path, stage1_checkpoint: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    write: dict[str, Callable[[], object]] = {
        "render": lambda: render(None, cache, "waymo5", out, geometry="cache", progress=False),
        "generate": lambda: generate(
            stage2_checkpoint, cache, SCENES[0], 1, 5, out, options=STEPS, progress=False
        ),
        "latents": lambda: precompute_stage2(cache, out, load_stage1(stage1_checkpoint), Stage2DataConfig()),
    }
    with (
        CacheLock(out, "other"),
        pytest.raises(PrepError, match=rf"another other run is writing this cache \(PID {os.getpid()} on "),
    ):
        write[writer]()
    assert sorted(p.name for p in out.iterdir()) == []


# --------------------------------------------------------------------------------------------
# Every output cache resumes after a kill or a full disk


def test_a_render_killed_in_its_first_scene_is_incomplete_and_the_same_command_resumes_it(
    cache: Path, rendered: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r"
    killed_at_row(1, RENDER_CLI, *render_argv(cache, out))
    code, text = verify_command(out, capsys)
    assert code == 3, text
    assert "0 of the 2 scenes its run asked for are finished" in text and "INCOMPLETE" in text
    assert f"missing: {', '.join(SCENES)}" in text and "resumes" in text

    from phigenesis.cli.render import main as render_main

    assert render_main(render_argv(cache, out)) == 0
    assert contents(out) == contents(rendered)
    assert verify_command(out, capsys)[0] == 0 and leftovers(out) == []


def _file_size_limit(limit: int) -> Callable[[], None]:
    """A child's ``preexec_fn``: files of at most ``limit`` bytes (writes past it fail with
    EFBIG, as on a full disk; Python ignores SIGXFSZ, so the write fails rather than the process)."""

    def limit_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return limit_files


def test_a_render_stopped_by_a_full_disk_names_the_file_and_the_same_command_resumes(
    cache: Path, rendered: Path, tmp_path: Path
) -> None:
    out = tmp_path / "r"
    # Room for the manifest and the lock, not for a shard (each is over 30 kB).
    proc = child(RENDER_CLI, *render_argv(cache, out), preexec_fn=_file_size_limit(12_000))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    shard = out / "shards" / f"{SCENES[0]}-00000.arrow"
    assert f"phigenesis-render: error: {shard}: cannot write (" in proc.stderr
    assert f"finished scenes are kept in {out}; rerun the same command to resume" in proc.stderr
    assert "unexpected" not in proc.stderr and leftovers(out) == []

    from phigenesis.cli.render import main as render_main

    assert render_main(render_argv(cache, out)) == 0
    assert contents(out) == contents(rendered)


def test_a_generate_killed_while_writing_is_redone_by_the_same_command_to_the_same_cache(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, whole = tmp_path / "killed", tmp_path / "whole"
    killed_at_row(2, GENERATE_CLI, *generate_argv(stage2_checkpoint, cache, out))
    code, text = verify_command(out, capsys)
    assert (
        code == 3
        and f"0 of the 1 scenes its run asked for are finished (missing: {SCENES[0]}{GENERATED_SUFFIX})"
        in text
    ), text

    from phigenesis.cli.generate import main as generate_main

    assert generate_main(generate_argv(stage2_checkpoint, cache, out)) == 0
    assert generate_main(generate_argv(stage2_checkpoint, cache, whole)) == 0
    assert contents(out) == contents(whole)
    assert verify_cache(out).status == "OK" and leftovers(out) == []
    assert (out / "strip.png").is_file() and (out / "generate.json").is_file()
    # A rerun of a finished rollout has nothing to do, and says so.
    capsys.readouterr()
    assert generate_main(generate_argv(stage2_checkpoint, cache, out)) == 0
    assert "already holds this rollout" in capsys.readouterr().out
    assert contents(out) == contents(whole)


def test_a_latent_cache_killed_in_its_first_scene_is_incomplete_and_a_rerun_resumes_it(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "latents"
    killed_at_row(0, LATENTS, cache, out, stage1_checkpoint)
    code, text = verify_command(out, capsys)
    assert code == 3, text
    assert f"0 of the 2 scenes its run asked for are finished (missing: {', '.join(SCENES)})" in text

    precompute_latents(cache, out, stage1_checkpoint)
    assert contents(out) == contents(latents)
    assert verify_command(out, capsys)[0] == 0 and leftovers(out) == []


# --------------------------------------------------------------------------------------------
# verify: complete, incomplete, damaged


def test_verify_calls_a_killed_prep_incomplete_naming_the_missing_scene_and_a_damaged_one_damaged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = load_pipeline("synthetic")
    quick = dataclasses.replace(
        spec, stages=(), source_params={**spec.source_params, "lidar": TINY_PREP_ARGS["lidar"]}
    )
    (tmp_path / "quick.yaml").write_text(yaml.safe_dump(quick.to_dict()))
    out = tmp_path / "cache"
    args = ["synthetic", "--scenes", "2", "--frames", "2", "--seed", "7", "--height", "32", "--width", "48"]
    args += ["--pipeline", str(tmp_path / "quick.yaml"), "--out", str(out), "--no-progress"]
    killed_at_row(2, PREP_CLI, *args)  # scene 1 is complete, scene 2 has begun
    code, text = verify_command(out, capsys)
    assert code == 3, text
    assert text.splitlines()[-1] == f"{out}: 1 shards, 2 frames verified: INCOMPLETE"
    assert f"1 of the 2 scenes its run asked for are finished (missing: {SCENES[1]})" in text

    damaged = tmp_path / "damaged"
    shutil.copytree(out, damaged)
    shard = next((damaged / "shards").glob("*.arrow"))
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0x40
    shard.write_bytes(bytes(data))
    code, text = verify_command(damaged, capsys)
    assert code == 1 and text.splitlines()[-1].startswith(
        f"{damaged}: 1 shards, 0 frames verified: DAMAGED ("
    ), text

    assert prep_main(args) == 0  # the same command resumes
    code, text = verify_command(out, capsys)
    assert code == 0 and "all 2 scenes its run asked for are finished" in text and text.endswith("OK\n"), text


def test_a_cache_written_before_manifests_recorded_their_scenes_still_verifies_and_says_so(
    cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = tmp_path / "old"
    shutil.copytree(cache, old)
    document = json.loads((old / MANIFEST_NAME).read_text())
    del document["scenes_expected"]
    (old / MANIFEST_NAME).write_text(json.dumps(document))
    report = verify_cache(old)
    assert report.ok and report.complete is None and report.status == "OK"
    code, text = verify_command(old, capsys)
    assert code == 0 and "whether the cache is complete cannot be checked" in text, text


def test_the_verify_help_documents_its_exit_statuses(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        prep_main(["verify", "--help"])
    text = capsys.readouterr().out
    for line in ("0  OK", "1  DAMAGED", "3  INCOMPLETE"):
        assert line in text


# --------------------------------------------------------------------------------------------
# Caches and names that are not what they claim


def test_preview_of_a_latent_cache_says_it_holds_no_frames(
    latents: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(
        CacheError, match=r"manifest\.json: a cache of source 'stage2-latents' whose rows are not frames"
    ):
        CacheReader(latents).frame(0)
    assert prep_main(["preview", str(latents), "--out", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err
    assert "preview" in err and "stage2-latents" in err and "unexpected" not in err


def _edited(cache: Path, tmp_path: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    copy = tmp_path / "edited"
    shutil.copytree(cache, copy)
    document = json.loads((copy / MANIFEST_NAME).read_text())
    edit(document)
    (copy / MANIFEST_NAME).write_text(json.dumps(document))
    return copy


def _long_shard_name(d: dict[str, Any]) -> None:
    long = "shards/" + "a" * 5000 + ".arrow"
    d["shards"][0]["path"] = long
    d["scenes"][0]["shards"][0] = long


def _long_scene_id(d: dict[str, Any]) -> None:
    d["scenes"][0]["id"] = d["shards"][0]["scene_id"] = d["scenes_expected"][0] = "b" * 5000


@pytest.mark.parametrize(
    ("edit", "field"),
    [(_long_shard_name, r"shards\[0\]\.path"), (_long_scene_id, r"shards\[0\]\.scene_id")],
    ids=["shard-name", "scene-id"],
)
def test_a_5000_character_name_in_a_manifest_is_an_error_naming_the_manifest_and_field(
    edit: Callable[[dict[str, Any]], None],
    field: str,
    cache: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bad = _edited(cache, tmp_path, edit)
    with pytest.raises(CacheError, match=rf"manifest\.json: {field}: .* at most"):
        CacheReader(bad).frame(0)
    code, text = verify_command(bad, capsys)
    assert code == 1 and "BAD: " in text and len(text) < 2000, text


def test_a_scene_id_a_cache_cannot_name_files_after_is_refused_before_anything_is_written(
    tmp_path: Path,
) -> None:
    with (
        pytest.raises(
            PrepError, match=r"scene id 'c{57}\.\.\.' has 5000 characters; a scene id has at most 200"
        ),
        writing_cache(tmp_path / "out", "synthetic", {}, {}, ["c" * 5000], "prep"),
    ):
        pass
    assert [p.name for p in (tmp_path / "out").iterdir()] == []
    with pytest.raises(PrepError, match="cannot write its shards"):
        ShardWriter(tmp_path / "w", "d" * 5000, pa.schema([("x", pa.int32())]))


def test_a_manifest_that_is_a_symbolic_link_out_of_the_cache_is_refused_and_left_alone(
    cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    linked = tmp_path / "linked"
    shutil.copytree(cache, linked)
    outside = tmp_path / "elsewhere.json"
    (linked / MANIFEST_NAME).rename(outside)
    (linked / MANIFEST_NAME).symlink_to(outside)
    before = outside.read_bytes()
    with pytest.raises(CacheError, match=r"manifest\.json: the manifest is a symbolic link"):
        CacheReader(linked)
    code, text = verify_command(linked, capsys)
    assert code == 1 and "symbolic link" in text
    with pytest.raises(PrepError, match="symbolic link"):
        prep.synthetic(linked, progress=False, **{**TINY_PREP_ARGS, "frames": 6, "height": 48, "width": 72})  # type: ignore[arg-type]
    assert outside.read_bytes() == before


def test_a_generated_scene_numbers_its_frames_from_0_and_records_the_frame_it_starts_at(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    out = tmp_path / "gen"
    generate(stage2_checkpoint, cache, SCENES[0], 2, 3, out, options=STEPS, progress=False)
    reader = CacheReader(out)
    assert [reader.frame(i, decode_truth=False).frame_index for i in range(len(reader))] == [0, 1, 2]
    metadata = json.loads(reader.shard(0).schema.metadata[b"phigenesis.scene_metadata"])
    assert metadata == {"generated_from": SCENES[0], "start": 2}
