"""Run folders and checkpoints are untrusted input: nothing in them is unpickled, a damaged file is a
one-line error naming it, a damaged ``checkpoints/latest`` never restarts a run from step 0 over its
log, no path read from a run folder leads outside it, and an interrupt leaves nothing half-written."""

from __future__ import annotations

import ast
import builtins
import csv
import logging
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

import phigenesis
from phigenesis.errors import CheckpointError
from phigenesis.models import create_model
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.train import checkpoint, runner, vae
from phigenesis.train.checkpoint import save_checkpoint
from phigenesis.train.runner import latest_checkpoint, load_training_state, read_metrics
from phigenesis.train.stage1 import Stage1TrainConfig, train_stage1
from phigenesis.train.vae import VAETrainConfig, make_optimizer, train_vae

#: A VAE run of 6 steps on single frames at 32 x 48, checkpointed every 2 steps (about 0.1 s a step).
VAE = {
    "steps": 6,
    "checkpoint_every": 2,
    "frames": 1,
    "size": (32, 48),
    "batch_size": 1,
    "val_fraction": 0.0,
    "threads": 1,
}
#: The loss written into metrics.csv's first row before a resume: a run restarted from step 0 overwrites it.
SENTINEL = "123"


class _WritesAFile:
    """Unpickling this runs ``open(path, "w").write(...)``: the harmless stand-in for any code."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return builtins.exec, (f"open({str(self.path)!r}, 'w').write('pwned')",)


class _TouchesAFile(_WritesAFile):
    """Unpickling this runs a shell command (``os.system``), whose module torch blocks outright:
    its refusal message has another form than an unlisted global's."""

    def __reduce__(self):
        return os.system, (f"touch {str(self.path)!r}",)


def _metrics_rows(out: Path) -> list[dict[str, str]]:
    with (out / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _mark_first_row(out: Path) -> None:
    """Writes :data:`SENTINEL` as the loss of metrics.csv's first row."""
    rows = _metrics_rows(out)
    rows[0]["loss"] = SENTINEL
    with (out / "metrics.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _trainer_file(folder: Path) -> Path:
    """The trainer state of a checkpoint folder, whatever its format."""
    (path,) = folder.glob("trainer.*")
    return path


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _resume(cache: Path, out: Path, stop_after: int = 5) -> list[int]:
    """Resumes the VAE run ``out`` until ``stop_after``; returns the steps it trained."""
    trained: list[int] = []
    train_vae(
        cache,
        out,
        resume=True,
        stop_after=stop_after,
        progress=lambda v: trained.append(int(v["step"])),
        **VAE,
    )
    return trained


def _one_line(error: pytest.ExceptionInfo[BaseException]) -> str:
    message = str(error.value)
    assert "\n" not in message, message
    return message


@pytest.fixture(scope="module")
def killed_run(tiny_cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A VAE run killed after step 4 of 6: ``checkpoints/step-0000002`` and ``step-0000004``,
    metrics.csv rows 1 to 4 (read-only: tests damage copies)."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("killed") / "run"
    train_vae(tiny_cache, out, stop_after=4, **VAE)
    return out


@pytest.fixture
def run(killed_run: Path, tmp_path: Path) -> Path:
    """A copy of :func:`killed_run` to damage, with :data:`SENTINEL` as its first row's loss."""
    out = tmp_path / "run"
    shutil.copytree(killed_run, out, symlinks=True)
    _mark_first_row(out)
    return out


def _outside_copy(run: Path, step: int) -> Path:
    """A complete copy of the run's checkpoint of ``step``, outside the run folder."""
    outside = run.parent / "x"
    shutil.copytree(run / "checkpoints" / f"step-{step:07d}", outside)
    return outside


def _say(text: str) -> Callable[[Path], None]:
    """A damage that writes ``text`` into the run's ``checkpoints/latest``."""

    def damage(run: Path) -> None:
        (run / "checkpoints" / "latest").write_text(text)

    return damage


def _garbage(run: Path) -> None:
    (run / "checkpoints" / "latest").write_bytes(b"\xff\xfe\x00garbage")


def _missing(run: Path) -> None:
    (run / "checkpoints" / "latest").unlink()


def _incomplete(run: Path) -> None:
    _truncate(_trainer_file(run / "checkpoints" / "step-0000004"))


def _parent_path(run: Path) -> None:
    _outside_copy(run, 2)
    (run / "checkpoints" / "latest").write_text("../../x\n")


def _absolute_path(run: Path) -> None:
    (run / "checkpoints" / "latest").write_text(f"{_outside_copy(run, 2)}\n")


def _linked_folder(run: Path) -> None:
    (run / "checkpoints" / "step-0000008").symlink_to(_outside_copy(run, 2), target_is_directory=True)
    (run / "checkpoints" / "latest").write_text("step-0000008\n")


#: Each damage of ``checkpoints/latest``: (damage, what the warning quotes, the step resumed from).
DAMAGED_POINTERS = {
    "empty": (_say(""), "is empty", 4),
    "garbage": (_garbage, "not a checkpoint folder name", 4),
    "missing": (_missing, "is missing", 4),
    "naming a missing folder": (_say("step-0000099\n"), "'step-0000099', which does not exist", 4),
    "naming an incomplete folder": (_incomplete, "'step-0000004', which cannot be used", 2),
    "naming an older folder": (_say("step-0000002\n"), "but step-0000004 is newer", 4),
    "naming a parent path": (_parent_path, "'../../x', a path outside", 4),
    "naming an absolute path": (_absolute_path, "a path outside", 4),
    "naming a folder linked outside": (_linked_folder, "resolves outside the run folder", 4),
}


# --------------------------------------------------------------------------------------------
# Nothing is unpickled


@pytest.mark.parametrize("payload", [_WritesAFile, _TouchesAFile])
def test_a_crafted_trainer_pt_is_refused_without_running_its_code(
    payload: type[_WritesAFile], tmp_path: Path
) -> None:
    marker = tmp_path / "pwned.txt"
    folder = tmp_path / "step-0000002"
    folder.mkdir()
    torch.save({"step": 2, "optimizer": payload(marker), "extra": {}}, folder / "trainer.pt")
    with pytest.raises(CheckpointError) as error:
        load_training_state(folder)
    assert not marker.exists()
    message = _one_line(error)
    assert str(folder / "trainer.pt") in message and "refused" in message and "weights_only" not in message


def test_resuming_a_run_whose_checkpoint_holds_a_crafted_trainer_pt_runs_no_code(
    tiny_cache: Path, run: Path
) -> None:
    marker = run.parent / "pwned.txt"
    folder = run / "checkpoints" / "step-0000004"
    _trainer_file(folder).unlink()
    torch.save({"step": 4, "optimizer": _WritesAFile(marker), "extra": {}}, folder / "trainer.pt")
    with pytest.raises(CheckpointError, match=r"step-0000004/trainer\.pt: refused"):
        _resume(tiny_cache, run)
    assert not marker.exists()
    assert _metrics_rows(run)[0]["loss"] == SENTINEL


def test_no_module_of_the_package_unpickles_arbitrary_objects() -> None:
    """Every torch.load passes weights_only=True; nothing calls pickle, marshal, yaml.load, eval or exec."""
    unsafe = []
    for path in Path(phigenesis.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Call):
                continue
            name = ast.unparse(node.func)
            safe_kw = any(
                k.arg == "weights_only" and isinstance(k.value, ast.Constant) and k.value.value is True
                for k in node.keywords
            )
            if name.endswith("torch.load") and not safe_kw:
                unsafe.append(f"{path}:{node.lineno}: {name} without weights_only=True")
            if name in ("eval", "exec", "yaml.load", "yaml.unsafe_load", "yaml.full_load") or name.startswith(
                ("pickle.", "marshal.", "dill.", "cloudpickle.")
            ):
                unsafe.append(f"{path}:{node.lineno}: {name}")
    assert not unsafe, unsafe


# --------------------------------------------------------------------------------------------
# Clear errors


def test_a_truncated_trainer_state_is_a_one_line_error_naming_the_file(run: Path) -> None:
    folder = run / "checkpoints" / "step-0000004"
    trainer = _trainer_file(folder)
    _truncate(trainer)
    with pytest.raises(CheckpointError) as error:
        load_training_state(folder)
    message = _one_line(error)
    assert str(trainer) in message and "truncated" in message


def test_a_truncated_trainer_pt_of_an_older_run_is_a_one_line_error_naming_the_file(tmp_path: Path) -> None:
    folder = tmp_path / "step-0000001"
    folder.mkdir()
    model = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(model.parameters())
    model(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    torch.save({"step": 1, "optimizer": optimizer.state_dict(), "extra": {}}, folder / "trainer.pt")
    _truncate(folder / "trainer.pt")
    with pytest.raises(CheckpointError) as error:
        load_training_state(folder)
    message = _one_line(error)
    assert str(folder / "trainer.pt") in message and "truncated" in message


def _garbage_pt(tmp_path: Path) -> Path:
    path = tmp_path / "garbage.pt"
    path.write_bytes(b"not a checkpoint")
    return path


def _truncated_pt(tmp_path: Path) -> Path:
    path = save_checkpoint(tmp_path / "truncated.pt", create_model("vae_tiny"))
    _truncate(path)
    return path


def _crafted_pt(tmp_path: Path) -> Path:
    path = tmp_path / "crafted.pt"
    torch.save({"format": "phigenesis.checkpoint", "model": _WritesAFile(tmp_path / "pwned.txt")}, path)
    return path


def _truncated_safetensors(tmp_path: Path) -> Path:
    path = save_checkpoint(tmp_path / "truncated.safetensors", create_model("vae_tiny"))
    _truncate(path)
    return path


def _garbage_safetensors(tmp_path: Path) -> Path:
    path = tmp_path / "garbage.safetensors"
    path.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}      ")
    return path


def _safetensors_without_a_model(tmp_path: Path) -> Path:
    path = tmp_path / "nameless.safetensors"
    save_file({"w": torch.zeros(2)}, path, metadata={"format": '"phigenesis.checkpoint"', "version": "1"})
    return path


def _weights_of_another_model(tmp_path: Path) -> Path:
    real = save_checkpoint(tmp_path / "real.safetensors", create_model("vae_tiny"))
    path = tmp_path / "other.safetensors"
    with safe_open(real, framework="pt") as f:
        save_file({"w": torch.zeros(2)}, path, metadata=f.metadata())
    return path


@pytest.mark.parametrize(
    "make",
    [
        _garbage_pt,
        _truncated_pt,
        _crafted_pt,
        _truncated_safetensors,
        _garbage_safetensors,
        _safetensors_without_a_model,
        _weights_of_another_model,
    ],
)
def test_a_damaged_model_checkpoint_is_a_one_line_error_without_torch_advice(
    make: Callable[[Path], Path], tmp_path: Path
) -> None:
    path = make(tmp_path)
    with pytest.raises(CheckpointError) as error:
        load_checkpoint(path)
    message = _one_line(error)
    assert message.startswith(f"{path}: ") and "weights_only" not in message and "Please" not in message
    assert "phigenesis.train" not in message and not (tmp_path / "pwned.txt").exists()


def _wrong_shape(state: dict) -> None:
    first = next(iter(state["state"].values()))
    first["exp_avg"] = torch.zeros(3, 3, 3)


def _missing_moment(state: dict) -> None:
    del next(iter(state["state"].values()))["exp_avg_sq"]


def _extra_group(state: dict) -> None:
    state["param_groups"].append({**state["param_groups"][0], "params": [10_000]})


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (_wrong_shape, r"exp_avg of parameter \d+ has shape \(3, 3, 3\)"),
        (_missing_moment, "lacks exp_avg_sq"),
        (_extra_group, "parameter groups"),
    ],
)
def test_optimiser_state_that_does_not_fit_the_model_is_a_clear_error(
    run: Path, damage: Callable[[dict], None], expected: str
) -> None:
    state = load_training_state(run / "checkpoints" / "step-0000004")
    damage(state.optimizer)
    optimizer = make_optimizer(create_model("vae_tiny"), VAETrainConfig(**VAE))
    with pytest.raises(CheckpointError, match=f"does not fit the model.*{expected}"):
        runner.restore_optimizer(optimizer, state)


def test_a_resume_whose_optimiser_state_has_other_shapes_is_refused_naming_the_file(
    tiny_cache: Path, run: Path
) -> None:
    folder = run / "checkpoints" / "step-0000004"
    state = load_training_state(folder)
    _wrong_shape(state.optimizer)
    _trainer_file(folder).unlink()
    checkpoint.write_trainer_state(folder / "trainer.safetensors", 4, state.optimizer, state.extra)
    with pytest.raises(
        CheckpointError, match=r"step-0000004/trainer\.safetensors: the optimiser state does not"
    ):
        _resume(tiny_cache, run)
    assert _metrics_rows(run)[0]["loss"] == SENTINEL


def test_the_optimiser_state_round_trips_exactly_through_safetensors_and_json(tmp_path: Path) -> None:
    model = torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.Linear(3, 1))
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-4, betas=(0.8, 0.95), amsgrad=True)
    for _ in range(3):
        model(torch.randn(5, 4)).square().mean().backward()
        optimizer.step()
    path = checkpoint.write_trainer_state(
        tmp_path / "trainer.safetensors", 3, optimizer.state_dict(), {"a": [1]}
    )
    state = checkpoint.read_trainer_state(path)
    fresh = torch.optim.AdamW(model.parameters(), lr=1.0)
    checkpoint.restore_optimizer(fresh, state)
    before, after = optimizer.state_dict(), fresh.state_dict()
    assert state.step == 3 and state.extra == {"a": [1]} and after["param_groups"] == before["param_groups"]
    for index, entries in before["state"].items():
        for name, value in entries.items():
            assert torch.equal(after["state"][index][name], value), (index, name)


def test_an_older_runs_trainer_pt_still_resumes_as_the_new_format_does(
    tiny_cache: Path, run: Path, killed_run: Path, tmp_path: Path
) -> None:
    folder = run / "checkpoints" / "step-0000004"
    state = load_training_state(folder)
    _trainer_file(folder).unlink()
    torch.save({"step": 4, "optimizer": state.optimizer, "extra": state.extra}, folder / "trainer.pt")
    new = tmp_path / "new"
    shutil.copytree(killed_run, new)
    assert _resume(tiny_cache, run) == _resume(tiny_cache, new) == [5]
    assert read_metrics(run)[4] == read_metrics(new)[4]


# --------------------------------------------------------------------------------------------
# A damaged pointer never restarts a run


@pytest.mark.parametrize("case", list(DAMAGED_POINTERS))
def test_a_damaged_latest_pointer_resumes_from_the_newest_complete_checkpoint(
    case: str, tiny_cache: Path, run: Path, caplog: pytest.LogCaptureFixture
) -> None:
    damage, said, resumed_at = DAMAGED_POINTERS[case]
    before = _metrics_rows(run)
    damage(run)
    with caplog.at_level(logging.WARNING, logger="phigenesis.train.runner"):
        trained = _resume(tiny_cache, run)
    assert trained == list(range(resumed_at + 1, 6))
    rows = _metrics_rows(run)
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5]
    assert rows[:resumed_at] == before[:resumed_at] and rows[0]["loss"] == SENTINEL
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    pointer = run / "checkpoints" / "latest"
    assert any(str(pointer) in w and said in w and f"using step-{resumed_at:07d}" in w for w in warnings), (
        warnings
    )
    outside = run.parent / "x"
    assert not outside.exists() or sorted(p.name for p in outside.iterdir()) == [
        "model.safetensors",
        "trainer.safetensors",
    ]


@pytest.mark.parametrize(
    ("damage", "said"),
    [("truncated trainer states", "no usable checkpoint"), ("no checkpoints folder", "nothing to resume")],
)
def test_a_resume_without_a_usable_checkpoint_is_refused_and_keeps_the_log(
    damage: str, said: str, tiny_cache: Path, run: Path
) -> None:
    if damage == "no checkpoints folder":
        shutil.rmtree(run / "checkpoints")
    else:
        for folder in (run / "checkpoints").glob("step-*"):
            _truncate(_trainer_file(folder))
    log = (run / "metrics.csv").read_bytes()
    expected = rf"{re.escape(str(run))}: {said}.*metrics\.csv holds 4 logged steps"
    with pytest.raises(CheckpointError, match=expected):
        _resume(tiny_cache, run)
    assert (run / "metrics.csv").read_bytes() == log


def test_latest_checkpoint_never_names_a_folder_outside_the_run(run: Path) -> None:
    (run / "checkpoints" / "step-0000008").symlink_to(_outside_copy(run, 4), target_is_directory=True)
    (run / "checkpoints" / "latest").write_text("step-0000008\n")
    assert latest_checkpoint(run) == run / "checkpoints" / "step-0000004"
    (run / "checkpoints" / "latest").write_text(f"{run.parent / 'x'}\n")
    assert latest_checkpoint(run) == run / "checkpoints" / "step-0000004"


def test_a_checkpoints_folder_linked_outside_the_run_is_not_read(tiny_cache: Path, run: Path) -> None:
    outside = run.parent / "elsewhere"
    shutil.move(run / "checkpoints", outside)
    (run / "checkpoints").symlink_to(outside, target_is_directory=True)
    log = (run / "metrics.csv").read_bytes()
    with pytest.raises(CheckpointError, match=r"step-0000004: resolves outside the run folder"):
        _resume(tiny_cache, run)
    assert (run / "metrics.csv").read_bytes() == log


def test_a_run_never_writes_checkpoints_through_a_link_outside_it(tiny_cache: Path, tmp_path: Path) -> None:
    out, outside = tmp_path / "run", tmp_path / "elsewhere"
    out.mkdir()
    outside.mkdir()
    (out / "checkpoints").symlink_to(outside, target_is_directory=True)
    with pytest.raises(CheckpointError, match=r"checkpoints: resolves outside the run folder"):
        train_vae(tiny_cache, out, **VAE)
    assert not any(outside.iterdir())


# --------------------------------------------------------------------------------------------
# Interrupts


def test_an_interrupt_while_a_checkpoint_is_written_leaves_nothing_half_written(
    tiny_cache: Path, run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(path: Path, *args: object, **kwargs: object) -> Path:
        save_checkpoint(path, *args, **kwargs)  # type: ignore[arg-type]
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "save_checkpoint", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _resume(tiny_cache, run)
    monkeypatch.undo()
    entries = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert entries == ["latest", "step-0000002", "step-0000004"]
    assert (run / "checkpoints" / "latest").read_text() == "step-0000004\n"
    assert runner.kept_step(run) == 4
    assert _resume(tiny_cache, run) == [5]


def test_an_interrupt_while_metrics_csv_is_trimmed_keeps_its_rows(
    tiny_cache: Path, run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = (run / "metrics.csv").read_bytes()

    def interrupted(self: csv.DictWriter, rows: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(csv.DictWriter, "writerows", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _resume(tiny_cache, run)
    assert (run / "metrics.csv").read_bytes() == log
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]


def test_kept_step_says_what_an_interrupted_run_kept(tiny_cache: Path, tmp_path: Path) -> None:
    def interrupt_at_step_3(values: dict[str, float]) -> None:
        if values["step"] == 3:
            raise KeyboardInterrupt

    out = tmp_path / "run"
    assert runner.kept_step(out) is None
    with pytest.raises(KeyboardInterrupt):
        train_vae(tiny_cache, out, progress=interrupt_at_step_3, **VAE)
    assert runner.kept_step(out) == 2 and [r["step"] for r in read_metrics(out)] == [1, 2, 3]
    assert _resume(tiny_cache, out) == [3, 4, 5]


def test_an_interrupt_just_after_a_checkpoint_loses_no_row_of_the_log(
    tiny_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def save_then_interrupt(*args: object, **kwargs: object) -> Path:
        runner.save_training_state(*args, **kwargs)  # type: ignore[arg-type]
        raise KeyboardInterrupt

    out = tmp_path / "run"
    monkeypatch.setattr(vae, "save_training_state", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        train_vae(tiny_cache, out, **VAE)
    monkeypatch.undo()
    assert runner.kept_step(out) == 2
    assert _resume(tiny_cache, out) == [3, 4, 5]
    assert [r["step"] for r in read_metrics(out)] == [1, 2, 3, 4, 5]


def test_a_killed_runs_temporary_folders_are_removed_by_the_next_checkpoint(
    tiny_cache: Path, run: Path
) -> None:
    dead = 2**22 + 12_345  # above any pid_max: no process has it
    leftovers = [run / "checkpoints" / f".step-0000006.{dead}.tmp", run / f".metrics.csv.{dead}.tmp"]
    leftovers[0].mkdir()
    leftovers[1].write_text("half")
    _resume(tiny_cache, run)
    assert not any(p.exists() for p in leftovers)


# --------------------------------------------------------------------------------------------
# Stage 1 runs


def _stage1_config() -> Stage1TrainConfig:
    return Stage1TrainConfig(
        model_overrides={"image_size": [24, 36], "adapter": {"width": 16}},
        steps=3,
        warmup_steps=1,
        checkpoint_every=1,
        target_offset=1,
        seed=3,
        threads=1,
    )


@pytest.fixture(scope="module")
def stage1_killed(tiny_cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Stage 1 run killed after step 2 of 3: checkpoints step-0000001 and step-0000002."""
    out = tmp_path_factory.mktemp("stage1") / "run"
    train_stage1(tiny_cache, out, _stage1_config(), stop_after=2, progress=False)
    return out


@pytest.fixture
def stage1_run(stage1_killed: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(stage1_killed, out)
    _mark_first_row(out)
    return out


def test_a_stage1_run_with_a_garbage_pointer_resumes_from_its_newest_complete_checkpoint(
    tiny_cache: Path, stage1_run: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _garbage(stage1_run)
    with caplog.at_level(logging.WARNING, logger="phigenesis.train.runner"):
        train_stage1(tiny_cache, stage1_run, _stage1_config(), resume=True, progress=False)
    rows = _metrics_rows(stage1_run)
    assert [int(r["step"]) for r in rows] == [1, 2, 3] and rows[0]["loss"] == SENTINEL
    assert "using step-0000002" in caplog.text


def test_a_stage1_resume_without_a_usable_checkpoint_is_refused_and_keeps_the_log(
    tiny_cache: Path, stage1_run: Path
) -> None:
    for folder in (stage1_run / "checkpoints").glob("step-*"):
        _truncate(folder / "model.safetensors")
    log = (stage1_run / "metrics.csv").read_bytes()
    with pytest.raises(CheckpointError, match=r"no usable checkpoint.*model\.safetensors: truncated"):
        train_stage1(tiny_cache, stage1_run, _stage1_config(), resume=True, progress=False)
    with pytest.raises(ValueError, match="holds a run already"):
        train_stage1(tiny_cache, stage1_run, _stage1_config(), progress=False)
    assert (stage1_run / "metrics.csv").read_bytes() == log


def test_a_ctrl_c_while_a_log_row_is_written_arrives_after_the_row_is_complete(tmp_path: Path) -> None:
    import signal

    from phigenesis.train.runner import MetricsLog, interrupts_held, read_metrics

    metrics = MetricsLog(tmp_path, ["loss"], tensorboard=False)
    written = []
    with pytest.raises(KeyboardInterrupt), interrupts_held():
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the write
        metrics.log(1, {"loss": 0.5})
        written.append(True)
    assert written == [True]
    assert read_metrics(tmp_path) == [{"step": 1.0, "loss": 0.5}]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_run_from_step_0_leaves_one_event_file_and_a_resumed_run_keeps_the_earlier_steps(
    tmp_path: Path,
) -> None:
    """A restarted run's TensorBoard folder holds its own curve only, as its metrics.csv does."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from phigenesis.train.runner import MetricsLog

    def steps() -> list[int]:
        events = EventAccumulator(str(tmp_path / "tb"))
        events.Reload()
        return [e.step for e in events.Scalars("loss")]

    killed = MetricsLog(tmp_path, ["loss"])
    for step in (1, 2, 3):
        killed.log(step, {"loss": 9.0})
    killed.close()
    (tmp_path / "tb" / "notes.txt").write_text("kept")
    restarted = MetricsLog(tmp_path, ["loss"])
    restarted.log(1, {"loss": 1.0})
    restarted.close()
    assert len(list((tmp_path / "tb").glob("events.out.tfevents.*"))) == 1
    assert (tmp_path / "tb" / "notes.txt").read_text() == "kept"
    assert steps() == [1]
    resumed = MetricsLog(tmp_path, ["loss"], resume_step=1)
    resumed.log(2, {"loss": 0.5})
    resumed.close()
    assert steps() == [1, 2]
