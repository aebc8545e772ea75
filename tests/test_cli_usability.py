"""The commands as a user meets them: Ctrl-C ends in one line saying what was kept (exit 130), errors
read as their own message, help text has no Sphinx markup, and the README's and the guide's promises
about the checkout (ignored folders, where the real samples are looked for) hold."""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import phigenesis.eval.stage1
import phigenesis.export.stage1
import phigenesis.prep
import phigenesis.train.segmenter
import phigenesis.train.stage1
import phigenesis.train.vae
from phigenesis.cli import eval as eval_cli
from phigenesis.cli import export as export_cli
from phigenesis.cli import prep as prep_cli
from phigenesis.cli import synth as synth_cli
from phigenesis.cli import train as train_cli
from phigenesis.cli.common import plain_text
from phigenesis.data.shards import verify_cache
from phigenesis.errors import CacheError, CheckpointError, PrepError, SourceError
from phigenesis.train.runner import latest_checkpoint, read_metrics

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: The README and the guide's pages (docs/guide/), whose commands a user copies as well.
DOCS = "\n".join([README, *(p.read_text() for p in sorted((ROOT / "docs" / "guide").glob("*.md")))])
BIN = Path(sys.executable).parent
TINY_CONFIG = ROOT / "configs" / "stage1" / "tiny.yaml"

#: A pipeline for command-line runs that renders a scene in about a second: tiny LiDAR, no stages.
TINY_PIPELINE_YAML = """\
name: synthetic-tiny
source:
  name: synthetic
  params:
    rig: waymo5
    lidar: {beams: 16, columns: 256, sectors: 8}
stages: []
output:
  camera_truth: [depth, semantic]
  lidar: true
"""
MARKUP = re.compile(r"``|:(?:func|class|meth|mod|data|attr):")


def command(name: str) -> list[str]:
    exe = BIN / f"phigenesis-{name}"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", f"phigenesis.cli.{name}"]


def interrupt_when(
    argv: list[str], ready: Callable[[], bool], timeout_s: float = 240, again_after_s: float = 20
) -> subprocess.CompletedProcess[str]:
    """Runs a command in its own process group and sends the group SIGINT (what Ctrl-C in a terminal
    does) once ``ready()``; fails if the command ends or stalls before. A command still running
    ``again_after_s`` later gets a second SIGINT, as a user presses Ctrl-C again (tensorboard's
    writer thread can miss its wake-up when the first lands inside a write: its close then waits up
    to its 120 s flush period)."""
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + timeout_s
    try:
        while not ready():
            assert proc.poll() is None, f"ended before it could be interrupted: {proc.communicate()}"
            assert time.monotonic() < deadline, "stalled before it could be interrupted"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=again_after_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGINT)
            out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def complete_scene_count(cache: Path) -> int:
    try:
        manifest = json.loads((cache / "manifest.json").read_text())
    except (OSError, ValueError):
        return 0
    return sum(s["status"] == "complete" for s in manifest["scenes"])


def messages(stderr: str) -> list[str]:
    """The lines of stderr that are not log records (``INFO name: ...``)."""
    return [
        line for line in stderr.splitlines() if line.strip() and not re.match(r"(INFO|DEBUG) \S+: ", line)
    ]


# --------------------------------------------------------------------------------------------
# Ctrl-C


@pytest.mark.slow
def test_ctrl_c_during_prep_says_in_one_line_which_scenes_are_kept_and_a_rerun_resumes(
    tmp_path: Path,
) -> None:
    pipeline = tmp_path / "tiny.yaml"
    pipeline.write_text(TINY_PIPELINE_YAML)
    cache = tmp_path / "cache"
    argv = [*command("prep"), "synthetic", "--out", str(cache), "--scenes", "4", "--frames", "2"]
    argv += ["--height", "32", "--width", "48", "--pipeline", str(pipeline), "--no-progress"]

    proc = interrupt_when(argv, lambda: complete_scene_count(cache) >= 1)

    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr
    done = complete_scene_count(cache)
    assert 1 <= done < 4
    (line,) = messages(proc.stderr)
    assert line.startswith("phigenesis-prep: interrupted")
    assert f"{done} of 4 scenes" in line and str(cache) in line and "rerun the same command" in line
    assert verify_cache(cache).ok
    rerun = subprocess.run(argv, capture_output=True, text=True, timeout=240)
    assert rerun.returncode == 0, rerun.stderr
    assert f"{done} scenes were already complete and were skipped" in rerun.stdout
    assert complete_scene_count(cache) == 4 and verify_cache(cache).ok


@pytest.mark.slow
def test_ctrl_c_during_training_names_the_kept_checkpoint_and_resume_continues_from_it(
    tmp_path: Path,
) -> None:
    pipeline = tmp_path / "tiny.yaml"
    pipeline.write_text(TINY_PIPELINE_YAML)
    cache = tmp_path / "cache"
    prep = [*command("prep"), "synthetic", "--out", str(cache), "--scenes", "2", "--frames", "2"]
    prep += ["--height", "32", "--width", "48", "--pipeline", str(pipeline), "--no-progress"]
    subprocess.run(prep, check=True, capture_output=True, timeout=240)
    run = tmp_path / "run"
    argv = [*command("train"), "vae", "--shards", str(cache), "--out", str(run), "--steps", "100000"]
    argv += ["--batch-size", "1", "--frames", "1", "--size", "16x24", "--checkpoint-every", "3"]
    argv += ["--threads", "1"]

    proc = interrupt_when(argv, lambda: (run / "checkpoints" / "latest").is_file())

    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr
    (line,) = messages(proc.stderr)
    found = re.fullmatch(
        rf"phigenesis-train: interrupted after step (\d+); the checkpoint of step (\d+) is kept in "
        rf"{re.escape(str(run))} \(rerun with --resume to continue\)",
        line,
    )
    assert found, line
    reached, kept = int(found[1]), int(found[2])
    assert kept % 3 == 0 and kept <= reached
    folder = latest_checkpoint(run)
    assert folder is not None
    before = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    resumed = subprocess.run(
        [*argv, "--resume", "--stop-after", str(kept + 2)], capture_output=True, text=True, timeout=240
    )
    assert resumed.returncode == 0, resumed.stderr
    assert f"stopped at step {kept + 2}" in resumed.stdout
    # It went on from the kept checkpoint (a restart would have rewritten it) and logged each step once.
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == before
    assert [int(r["step"]) for r in read_metrics(run)] == list(range(1, kept + 3))


def _interrupt(*args: object, **kwargs: object) -> None:
    raise KeyboardInterrupt


def run_main(main: Callable[[list[str]], int], argv: list[str]) -> int:
    """``main(argv)``; an interrupt that escapes it fails the test instead of stopping pytest."""
    try:
        return main(argv)
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped the command as a KeyboardInterrupt (a traceback for the user)")


#: (main, argv, library function the command calls, what it says on Ctrl-C); {tmp} is tmp_path.
CTRL_C_CASES = [
    pytest.param(
        prep_cli.main,
        ["synthetic", "--out", "{tmp}/c", "--scenes", "3"],
        (phigenesis.prep, "synthetic"),
        "interrupted; 0 of 3 scenes are complete in {tmp}/c (rerun the same command to resume)",
        id="prep-synthetic",
    ),
    pytest.param(
        prep_cli.main,
        ["waymo", "--input", "{tmp}", "--out", "{tmp}/c"],
        (phigenesis.prep, "waymo"),
        "interrupted; 0 scenes are complete in {tmp}/c (rerun the same command to resume)",
        id="prep-waymo",
    ),
    pytest.param(
        prep_cli.main,
        ["nuscenes", "--dataroot", "{tmp}", "--out", "{tmp}/c"],
        (phigenesis.prep, "nuscenes"),
        "interrupted; 0 scenes are complete in {tmp}/c (rerun the same command to resume)",
        id="prep-nuscenes",
    ),
    pytest.param(
        prep_cli.main,
        ["verify", "{tmp}"],
        (phigenesis.prep, "verify"),
        "interrupted; nothing was changed",
        id="prep-verify",
    ),
    pytest.param(
        prep_cli.main,
        ["preview", "{cache}", "--out", "{tmp}/p.png"],
        (phigenesis.prep, "preview"),
        "interrupted; {tmp}/p.png was not written",
        id="prep-preview",
    ),
    pytest.param(
        synth_cli.main,
        ["--format", "waymo-v1", "--out", "{tmp}/w"],
        (synth_cli, "synth"),
        "interrupted; the files under {tmp}/w are incomplete (rerun the same command to write them)",
        id="synth",
    ),
    pytest.param(
        train_cli.main,
        ["segmenter", "--shards", "{tmp}", "--out", "{tmp}/r"],
        (phigenesis.train.segmenter, "train_segmenter"),
        "interrupted before the first evaluation; nothing is kept in {tmp}/r",
        id="train-segmenter",
    ),
    pytest.param(
        train_cli.main,
        ["vae", "--shards", "{tmp}", "--out", "{tmp}/r"],
        (phigenesis.train.vae, "train_vae"),
        "interrupted before the first step, before the first checkpoint; nothing to resume in {tmp}/r "
        "(rerun without --resume to start again)",
        id="train-vae",
    ),
    pytest.param(
        train_cli.main,
        ["stage1", "--shards", "{tmp}", "--config", str(TINY_CONFIG), "--out", "{tmp}/r"],
        (phigenesis.train.stage1, "train_stage1"),
        "interrupted before the first step, before the first checkpoint; nothing to resume in {tmp}/r "
        "(rerun without --resume to start again)",
        id="train-stage1",
    ),
    pytest.param(
        eval_cli.main,
        ["stage1", "--ckpt", "{tmp}/m", "--shards", "{tmp}"],
        (phigenesis.eval.stage1, "evaluate_stage1"),
        "interrupted before every clip was scored; no results were written (rerun the same command)",
        id="eval",
    ),
    pytest.param(
        export_cli.main,
        ["ply", "--ckpt", "{tmp}/m", "--shards", "{tmp}", "--frame", "0", "--out", "{tmp}/x.ply"],
        (phigenesis.export.stage1, "export_ply"),
        "interrupted; nothing was written to {tmp}/x.ply (rerun the same command)",
        id="export",
    ),
]


@pytest.mark.parametrize(("main", "argv", "target", "says"), CTRL_C_CASES)
def test_every_command_answers_ctrl_c_with_one_line_and_exit_130(
    main: Callable[[list[str]], int],
    argv: list[str],
    target: tuple[object, str],
    says: str,
    tiny_cache: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(*target, _interrupt)
    argv = [a.replace("{tmp}", str(tmp_path)).replace("{cache}", str(tiny_cache)) for a in argv]
    assert run_main(main, argv) == 130
    err = capsys.readouterr().err
    prog = "phigenesis-" + main.__module__.rsplit(".", 1)[1]
    assert messages(err) == [f"{prog}: {says.replace('{tmp}', str(tmp_path))}"]


def test_an_interrupt_that_says_what_it_kept_is_printed_as_it_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    class Stopped(KeyboardInterrupt):
        pass

    def stop(*args: object, **kwargs: object) -> None:
        raise Stopped("interrupted: the cache in c/ is unchanged; rerun the same command to resume")

    monkeypatch.setattr(phigenesis.prep, "synthetic", stop)
    assert run_main(prep_cli.main, ["synthetic", "--out", str(tmp_path / "c")]) == 130
    assert capsys.readouterr().err.splitlines() == [
        "phigenesis-prep: interrupted: the cache in c/ is unchanged; rerun the same command to resume"
    ]


def test_ctrl_c_after_a_segmenter_evaluation_names_the_weights_it_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def train_then_interrupt(shards: str, out: str, **kwargs: object) -> None:
        Path(out).mkdir()
        (Path(out) / "last.pt").write_bytes(b"weights")
        (Path(out) / "metrics.json").write_text(json.dumps({"history": [{"step": 250}]}))
        raise KeyboardInterrupt

    monkeypatch.setattr(phigenesis.train.segmenter, "train_segmenter", train_then_interrupt)
    run = tmp_path / "run"
    assert run_main(train_cli.main, ["segmenter", "--shards", str(tmp_path), "--out", str(run)]) == 130
    assert messages(capsys.readouterr().err) == [
        f"phigenesis-train: interrupted; {run / 'last.pt'} (step 250) and best.pt are kept (the segmenter "
        f"does not resume: rerun to train again, with --init {run / 'last.pt'} to start from its weights)"
    ]


def test_ctrl_c_in_a_torchrun_process_other_than_rank_0_prints_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(phigenesis.train.vae, "train_vae", _interrupt)
    monkeypatch.setenv("RANK", "1")
    assert run_main(train_cli.main, ["vae", "--shards", str(tmp_path), "--out", str(tmp_path / "r")]) == 130
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------------------------
# Error messages


#: (main, argv, library function the command calls); {tmp} is tmp_path.
ERROR_CASES = [
    pytest.param(prep_cli.main, ["synthetic", "--out", "{tmp}/c"], (phigenesis.prep, "synthetic"), id="prep"),
    pytest.param(
        synth_cli.main, ["--format", "nuscenes", "--out", "{tmp}/n"], (synth_cli, "synth"), id="synth"
    ),
    pytest.param(
        train_cli.main,
        ["vae", "--shards", "{tmp}", "--out", "{tmp}/r"],
        (phigenesis.train.vae, "train_vae"),
        id="train",
    ),
    pytest.param(
        eval_cli.main,
        ["stage1", "--ckpt", "{tmp}/m", "--shards", "{tmp}"],
        (phigenesis.eval.stage1, "evaluate_stage1"),
        id="eval",
    ),
    pytest.param(
        export_cli.main,
        ["ply", "--ckpt", "{tmp}/m", "--shards", "{tmp}", "--frame", "0", "--out", "{tmp}/x"],
        (phigenesis.export.stage1, "export_ply"),
        id="export",
    ),
]


@pytest.mark.parametrize("error", [PrepError, SourceError, CacheError, CheckpointError])
@pytest.mark.parametrize(("main", "argv", "target"), ERROR_CASES)
def test_a_toolkit_error_reads_as_its_own_message_with_exit_2(
    main: Callable[[list[str]], int],
    argv: list[str],
    target: tuple[object, str],
    error: type[Exception],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def fail(*args: object, **kwargs: object) -> None:
        raise error("/data/seg.tfrecord: record at byte 1024: field 'pose' has non-finite entries")

    monkeypatch.setattr(*target, fail)
    assert main([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 2
    prog = "phigenesis-" + main.__module__.rsplit(".", 1)[1]
    assert capsys.readouterr().err.splitlines() == [
        f"{prog}: error: /data/seg.tfrecord: record at byte 1024: field 'pose' has non-finite entries"
    ]


def test_train_stage1_with_a_missing_vae_names_the_config_key_and_the_flag_and_leaves_no_run_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Run from another directory, the tiny config's relative VAE path finds nothing."""
    monkeypatch.chdir(tmp_path)
    config = Path(__file__).resolve().parents[1] / "configs/stage1/tiny.yaml"
    argv = ["stage1", "--shards", str(tmp_path / "cache"), "--out", "run", "--config", str(config)]
    assert train_cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "runs/vae-tiny/model.safetensors: VAE checkpoint not found" in err
    assert "the config's vae_checkpoint" in err and str(tmp_path) in err and "pass --vae" in err
    assert not (tmp_path / "run").exists()
    with pytest.raises(CheckpointError, match=r"pass vae_checkpoint= to name another"):
        cfg = phigenesis.train.stage1.Stage1TrainConfig.load(config, steps=1)
        phigenesis.train.stage1.train_stage1(tmp_path / "cache", tmp_path / "run", cfg, progress=False)
    assert not (tmp_path / "run").exists()


def test_a_file_error_names_the_file_and_the_reason_without_errno(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def missing(*args: object, **kwargs: object) -> None:
        raise FileNotFoundError(2, "No such file or directory", "/data/run/model.safetensors")

    monkeypatch.setattr(phigenesis.export.stage1, "export_ply", missing)
    argv = ["ply", "--ckpt", "m", "--shards", str(tmp_path), "--frame", "0", "--out", str(tmp_path / "x")]
    assert export_cli.main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [
        "phigenesis-export: error: /data/run/model.safetensors: No such file or directory"
    ]


def test_an_unexpected_error_is_one_line_that_points_to_verbose_which_shows_the_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def bug(*args: object, **kwargs: object) -> None:
        raise RuntimeError("tensor sizes differ: 3 and 4")

    monkeypatch.setattr(phigenesis.prep, "synthetic", bug)
    assert prep_cli.main(["synthetic", "--out", str(tmp_path / "c")]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "phigenesis-prep: error: RuntimeError: tensor sizes differ: 3 and 4 "
        "(unexpected: a bug in phigenesis? rerun with -v for the traceback)"
    ]
    with pytest.raises(RuntimeError, match="tensor sizes differ"):
        prep_cli.main(["-v", "synthetic", "--out", str(tmp_path / "c")])


def test_preview_of_a_frame_outside_the_cache_is_a_user_error(
    tiny_cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert prep_cli.main(["preview", str(tiny_cache), "--frame", "6", "--out", str(tmp_path / "p.png")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"phigenesis-prep: error: --frame 6 is out of range: {tiny_cache} holds 6 frames"
    ]


# --------------------------------------------------------------------------------------------
# Help


def _parsers(parser: argparse.ArgumentParser, name: str) -> list[tuple[str, argparse.ArgumentParser]]:
    """The parser and every subcommand parser below it, with their command lines."""
    found = [(name, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                found += _parsers(sub, f"{name} {sub_name}")
    return found


ALL_PARSERS = [
    entry
    for module, name in (
        (prep_cli, "phigenesis-prep"),
        (synth_cli, "phigenesis-synth"),
        (train_cli, "phigenesis-train"),
        (eval_cli, "phigenesis-eval"),
        (export_cli, "phigenesis-export"),
    )
    for entry in _parsers(module.build_parser(), name)
]


@pytest.mark.parametrize(("name", "parser"), ALL_PARSERS, ids=[name for name, _ in ALL_PARSERS])
def test_help_of_every_command_and_subcommand_shows_no_sphinx_markup(
    name: str, parser: argparse.ArgumentParser
) -> None:
    text = parser.format_help()
    assert not MARKUP.search(text), f"{name} --help:\n{text}"


def test_the_train_help_names_the_functions_its_docstring_refers_to() -> None:
    text = " ".join(train_cli.build_parser().format_help().split())
    assert "segmenter (phigenesis.train.segmenter.train_segmenter)" in text


def test_help_as_the_command_prints_it_has_no_markup() -> None:
    proc = subprocess.run([*command("train"), "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "phigenesis.train.vae.train_vae" in proc.stdout
    assert not MARKUP.search(proc.stdout)


def test_plain_text_keeps_what_sphinx_shows_of_each_role() -> None:
    assert plain_text("``x = 1`` and :func:`a.b` and :class:`~pkg.mod.Name`") == "x = 1 and a.b and Name"
    assert plain_text(":meth:`the loader <pkg.Loader.load>` (:py:mod:`pkg`)") == "the loader (pkg)"


# --------------------------------------------------------------------------------------------
# The README's and the guide's promises about the checkout


def _readme_made_paths() -> set[str]:
    """What the README's and the guide's commands create in the working directory: their --out,
    --picture and phigenesis-synth output paths (absolute paths are outside the checkout)."""
    blocks = re.findall(r"```bash\n(.*?)```", DOCS, re.S) + re.findall(r"`(\.venv/bin/[^`]+)`", DOCS)
    made = set()
    for block in blocks:
        made |= set(re.findall(r"--(?:out|picture) (\S+)", block))
    return {m for m in made if not m.startswith(("DIR", "runs/NAME", "x.", "/"))}


def test_the_readme_commands_make_only_paths_git_ignores() -> None:
    made = _readme_made_paths()
    assert {
        "cache/",
        "heldout-cache/",
        "waymo/",
        "waymo-cache/",
        "nusc/",
        "nusc-cache/",
        "frame10.png",
    } <= made
    for path in sorted(made):
        ignored = subprocess.run(["git", "check-ignore", "-q", "--no-index", path], cwd=ROOT, check=False)
        assert ignored.returncode == 0, f"{path} (made by a README or guide command) is not in .gitignore"


def test_the_readme_says_how_to_make_the_held_out_cache_as_the_benchmark_does() -> None:
    (line,) = [m for m in re.findall(r"(\S*phigenesis-prep synthetic [^\n`]*)", README) if "heldout" in m]
    bench = (ROOT / "benchmarks" / "stage1.py").read_text()
    assert "_cache(eval_cache, args.eval_scenes, 100, 40)" in bench
    assert "frames=frames, seed=seed, height=96, width=144" in bench
    for flag in ("--seed 100", "--height 96", "--width 144", "--out heldout-cache/"):
        assert flag in line, line


def test_the_real_sample_skip_message_and_the_readme_name_every_place_the_tests_look() -> None:
    import tests.test_waymo_real as real

    reason = real.pytestmark.kwargs["reason"]
    places = [
        "$PHIGENESIS_WAYMO_SAMPLES",
        str(ROOT.parent / "shared" / "data" / "waymo"),
        "/work/shared/data/waymo",
    ]
    for place in places:
        assert place in reason, reason
    flat = " ".join((ROOT / "docs" / "guide" / "contributing.md").read_text().split())
    for place in ("$PHIGENESIS_WAYMO_SAMPLES", "../shared/data/waymo/", "/work/shared/data/waymo/"):
        assert place in flat


def test_a_resumed_run_that_had_finished_says_so_instead_of_an_empty_last_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    finished = phigenesis.train.stage1.Stage1Run(tmp_path, tmp_path / "model.safetensors", 40, {}, 0.1)
    monkeypatch.setattr(phigenesis.train.stage1, "train_stage1", lambda *a, **k: finished)
    config = Path(__file__).resolve().parents[1] / "configs/stage1/tiny.yaml"
    argv = [
        "stage1",
        "--shards",
        "c",
        "--out",
        str(tmp_path),
        "--config",
        str(config),
        "--vae",
        "v",
        "--resume",
    ]
    assert train_cli.main(argv) == 0
    out = capsys.readouterr().out
    assert "the run had already finished its 40 steps; nothing to do" in out and "last step" not in out


def test_render_names_the_ply_files_it_wrote(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import phigenesis.infer.rig_render as rig_render
    from phigenesis.cli import render as render_cli

    plys = tmp_path / "edited"
    plys.mkdir()
    (plys / "scene-a.ply").write_bytes(b"ply")
    result = rig_render.RenderResult(tmp_path / "out", ["scene-a"], [], 3, 1.0, {})
    monkeypatch.setattr(rig_render, "render", lambda *a, **k: result)
    argv = ["--shards", "c", "--rig", "nuscenes6", "--out", str(tmp_path / "out"), "--geometry", "cache"]
    assert render_cli.main([*argv, "--export-ply", str(plys)]) == 0
    out = capsys.readouterr().out
    assert f"edited Gaussians: {plys / 'scene-a.ply'}" in out and "<scene id>" not in out


def test_the_stage2_table_shows_the_vae_ceiling_beside_the_generated_frames() -> None:
    metrics = {"images": 4, "psnr_db": 18.5, "ssim": 0.61, "abs_rel": 0.12, "fid": 80.0, "kid": 0.05}
    ceiling = {"images": 4, "psnr_db": 27.25, "ssim": 0.875, "fid": 12.5}
    report = {
        "sections": {
            "rollout@5": {
                "generated": metrics,
                "render_only": {"psnr_db": 15.0},
                "vae_reconstruction": ceiling,
            }
        },
        "clips": 2,
        "seconds_per_frame": 1.5,
    }
    lines = eval_cli.format_stage2_table(report).splitlines()
    assert "VAE ceiling" in lines[0] and lines[2].split()[0] == "rollout@5"
    assert lines[2].split()[-3:] == ["27.25", "0.875", "12.50"]
    del report["sections"]["rollout@5"]["vae_reconstruction"]
    assert "VAE ceiling" not in eval_cli.format_stage2_table(report)
