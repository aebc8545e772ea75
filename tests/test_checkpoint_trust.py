"""Checkpoints are trusted only as far as they are checked: a run that diverges stops at the first
non-finite loss, gradient or weight and never writes non-finite weights; every loader refuses
non-finite weights, a checkpoint of the wrong kind and a damaged (checksum) file by name; a header's
config is range-checked and its sizes compared with the file's tensors before anything is
allocated; a full disk while writing a checkpoint names the file and keeps the previous one."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from phigenesis.cli.train import main as train_main
from phigenesis.errors import CheckpointError, PhiGenesisError
from phigenesis.models import create_model, list_models
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.loading import load_stage1, load_stage2
from phigenesis.rollout.config import Stage2TrainConfig
from phigenesis.train import runner, segmenter, stage1, stage2, vae
from phigenesis.train.checkpoint import read_trainer_state, save_checkpoint
from phigenesis.train.runner import latest_checkpoint
from phigenesis.train.stage1 import Stage1TrainConfig, train_stage1
from phigenesis.train.vae import train_vae
from tests.conftest import one_scene_cache, stage2_latents, two_step_stage1

#: A VAE run of single frames at 32 x 48, checkpointed every 2 steps (about 0.1 s a step).
VAE = {"frames": 1, "size": (32, 48), "batch_size": 1, "val_fraction": 0.0, "threads": 1}
#: Stage 1 and 2 at the size of tests/test_stage2.py, on one 12-frame scene.
SIZE, FRAMES = (48, 72), 12
#: Peak resident memory allowed for loading a crafted small checkpoint (the issue's goal).
PEAK_BYTES = 500 * 2**20


def _one_line(error: pytest.ExceptionInfo[BaseException]) -> str:
    text = str(error.value)
    assert "\n" not in text, text
    return text


def _rewrite(
    src: Path,
    dst: Path,
    config: dict | None = None,
    tensors: Callable[[dict[str, torch.Tensor]], None] | None = None,
    drop: tuple[str, ...] = (),
) -> Path:
    """A copy of the safetensors checkpoint ``src`` at ``dst`` with its header's config fields
    replaced by ``config``, its tensors changed in place by ``tensors`` and the header fields
    ``drop`` left out (a file as an older phigenesis, or someone else, would write it)."""
    with safe_open(src, framework="pt") as f:
        metadata = dict(f.metadata())
    weights = load_file(src)
    if config:
        metadata["config"] = json.dumps(json.loads(metadata["config"]) | config)
    if tensors is not None:
        tensors(weights)
    save_file(weights, dst, metadata={k: v for k, v in metadata.items() if k not in drop})
    return dst


def _poison(name: str, count: int = 3) -> Callable[[dict[str, torch.Tensor]], None]:
    """Sets the first ``count`` values of tensor ``name`` to NaN (what a diverged run wrote)."""

    def poison(weights: dict[str, torch.Tensor]) -> None:
        weights[name].view(-1)[:count] = float("nan")

    return poison


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One synthetic scene of 12 frames at 48 x 72 (every trainer here runs on it)."""
    return one_scene_cache(tmp_path_factory, "trust_cache", FRAMES, SIZE)


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A freshly initialised checkpoint of each tiny variant, by family."""
    root = tmp_path_factory.mktemp("saved")
    torch.manual_seed(0)
    names = {"vae": "vae_tiny", "stage1": "stage1_tiny", "dit": "stage2_tiny", "segformer": "segformer_tiny"}
    meta = {"dit": {"train": Stage2TrainConfig().to_dict()}}  # generate reads the training config
    return {
        family: save_checkpoint(root / f"{name}.safetensors", create_model(name), meta.get(family))
        for family, name in names.items()
    }


# --------------------------------------------------------------------------------------------
# Non-finite weights


def test_save_checkpoint_refuses_nan_weights_naming_the_file_and_the_tensor(tmp_path: Path) -> None:
    model = create_model("stage2_tiny")
    with torch.no_grad():
        model.x_embed.weight[0, :4] = float("nan")
    path = tmp_path / "model.safetensors"
    with pytest.raises(CheckpointError) as error:
        save_checkpoint(path, model)
    assert str(path) in _one_line(error) and "'x_embed.weight'" in str(error.value)
    assert "4 non-finite values" in str(error.value)
    assert not path.exists() and not list(tmp_path.iterdir())


def _load_stage1(path: Path) -> object:
    return load_stage1(path)


def _load_stage2(path: Path) -> object:
    return load_stage2(path)


def _stage2_for_generate(path: Path) -> object:
    from phigenesis.rollout.runner import trained_uncertainty

    return trained_uncertainty(path)


def _stage1_vae(path: Path) -> object:
    return stage1.build_model(Stage1TrainConfig(vae_checkpoint=str(path)))


def _vae_init(path: Path) -> object:
    return load_checkpoint(path, "vae_tiny")


#: Every way a checkpoint is loaded, with the family it needs (export, render and eval load Stage 1
#: through load_stage1; generate and eval stage2 load Stage 2 as trained_uncertainty does).
LOADERS = {
    "load_stage1": (_load_stage1, "stage1"),
    "load_stage2": (_load_stage2, "dit"),
    "generate": (_stage2_for_generate, "dit"),
    "train stage1 --vae": (_stage1_vae, "vae"),
    "--init": (_vae_init, "vae"),
}


@pytest.mark.parametrize("loader", sorted(LOADERS))
def test_every_loader_refuses_nan_weights_naming_the_file_the_tensor_and_the_count(
    loader: str, saved: dict[str, Path], tmp_path: Path
) -> None:
    load, family = LOADERS[loader]
    src = saved[family]
    first = sorted(load_file(src))[0]
    # As a diverged run wrote them before checksums (a checksum of NaN weights is refused alike).
    bad = _rewrite(src, tmp_path / "nan.safetensors", tensors=_poison(first), drop=("checksum",))
    with pytest.raises(CheckpointError) as error:
        load(bad)
    text = _one_line(error)
    assert text.startswith(f"{bad}: ") and repr(first) in text and "3 non-finite values" in text


def test_export_ply_refuses_nan_weights_with_a_clear_error_and_writes_nothing(
    saved: dict[str, Path], cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from phigenesis.cli.export import main as export_main

    name = sorted(k for k in load_file(saved["stage1"]) if k.startswith("adapter."))[-1]
    bad = _rewrite(
        saved["stage1"], tmp_path / "nan.safetensors", tensors=_poison(name, 5), drop=("checksum",)
    )
    out = tmp_path / "scene.ply"
    assert (
        export_main(["ply", "--ckpt", str(bad), "--shards", str(cache), "--frame", "0", "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err
    assert f"phigenesis-export: error: {bad}: " in err and "5 non-finite values" in err
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# The wrong kind of checkpoint


@pytest.mark.parametrize(
    ("loader", "given", "said"),
    [
        ("train stage1 --vae", "dit", "a stage2_tiny checkpoint (Stage 2 denoiser), not a VAE"),
        ("load_stage1", "vae", "a vae_tiny checkpoint (VAE), not a Stage 1 model"),
        ("load_stage2", "stage1", "a stage1_tiny checkpoint (Stage 1 model), not a Stage 2 denoiser"),
        ("generate", "segformer", "a segformer_tiny checkpoint (segmenter), not a Stage 2 denoiser"),
        ("--init", "dit", "a stage2_tiny checkpoint (Stage 2 denoiser), not a VAE"),
    ],
)
def test_a_checkpoint_of_the_wrong_kind_is_refused_by_name(
    loader: str, given: str, said: str, saved: dict[str, Path]
) -> None:
    load, _ = LOADERS[loader]
    with pytest.raises(CheckpointError) as error:
        load(saved[given])
    assert _one_line(error) == f"{saved[given]}: {said}"


# --------------------------------------------------------------------------------------------
# Bounded before building


def _peak_of_loading(paths: list[Path]) -> tuple[list[str], int]:
    """(the one-line outcome of ``load_checkpoint`` of each path, peak resident bytes) in a
    process limited to 3 GiB of address space (an unbounded build fails there, not the machine)."""
    code = textwrap.dedent(
        f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
        import torch
        torch.set_num_threads(1)
        from phigenesis.errors import PhiGenesisError
        from phigenesis.models.checkpoint import load_checkpoint
        for path in {[str(p) for p in paths]!r}:
            try:
                load_checkpoint(path)
                print("loaded")
            except PhiGenesisError as e:
                print("refused: " + str(e))
            except BaseException as e:
                print("crashed: " + type(e).__name__ + ": " + " ".join(str(e).split())[:300])
        # VmHWM: this program's peak (ru_maxrss would include the forking test process's).
        status = open("/proc/self/status").read()
        print(int(status.split("VmHWM:")[1].split()[0]) * 1024)
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    lines = done.stdout.strip().splitlines()
    assert len(lines) == len(paths) + 1, done.stdout + done.stderr[-2000:]
    return lines[:-1], int(lines[-1])


def test_a_header_claiming_a_huge_model_is_refused_before_anything_is_allocated(
    saved: dict[str, Path], tmp_path: Path
) -> None:
    # Out of its declared range; then in range, 64 blocks 8192 wide (50 billion parameters, 200 GB)
    # claimed by a file of 2 MB.
    deep = _rewrite(saved["dit"], tmp_path / "deep.safetensors", config={"depth": 1_000_000})
    wide = _rewrite(
        saved["dit"], tmp_path / "wide.safetensors", config={"depth": 64, "hidden": 8192, "heads": 64}
    )
    (deep_said, wide_said), peak = _peak_of_loading([deep, wide])
    assert deep_said == (
        f"refused: {deep}: cannot rebuild model 'stage2_tiny' from its config (DiTConfig: depth = 1000000: "
        "must be an integer in [1, 256])"
    )
    assert wide_said.startswith(f"refused: {wide}: weights do not fit model 'stage2_tiny' of its config"), (
        wide_said
    )
    assert peak < PEAK_BYTES, peak


@pytest.mark.parametrize("name", list_models())
def test_every_registered_variant_rebuilds_from_its_stored_config(name: str) -> None:
    with torch.device("meta"):
        model = create_model(name)
        again = create_model(name, **model.config.to_dict())
    assert again.config == model.config


@pytest.mark.parametrize(
    ("name", "override", "said"),
    [
        ("stage2_tiny", {"hidden": 10**6}, "hidden = 1000000: must be an integer in [4, 8192]"),
        ("stage2_tiny", {"heads": True}, "heads = True: must be an integer"),
        ("stage2_tiny", {"latent_std": [1.0, 0.0, 1.0, 1.0]}, "latent_std[1] = 0.0"),
        ("vae_tiny", {"channels": [16, 32, 10**5]}, "channels[2] = 100000"),
        ("vae_tiny", {"logvar_max": float("nan")}, "logvar_max = nan"),
        ("stage1_tiny", {"image_size": [48, -72]}, "image_size = "),
        (
            "stage1_tiny",
            {"adapter": {"width": "wide"}},
            "Stage1Config.adapter: AdapterConfig: width = 'wide'",
        ),
        ("stage1_tiny", {"vae": {"depth": 3}}, "Stage1Config.vae: unknown keys ['depth']"),
        ("segformer_tiny", {"depths": [1, 1, 300, 1]}, "depths[2] = 300"),
    ],
)
def test_a_model_config_value_outside_its_range_is_refused_naming_the_field(
    name: str, override: dict, said: str
) -> None:
    with pytest.raises(PhiGenesisError) as error, torch.device("meta"):
        create_model(name, **override)
    assert said in _one_line(error)


# --------------------------------------------------------------------------------------------
# Checksums


def test_one_flipped_bit_in_a_checkpoints_tensors_is_a_checksum_mismatch(
    saved: dict[str, Path], tmp_path: Path
) -> None:
    data = bytearray(saved["dit"].read_bytes())
    data[-1000] ^= 0x01  # a low mantissa bit of a weight: the values stay finite and plausible
    flipped = tmp_path / "flipped.safetensors"
    flipped.write_bytes(bytes(data))
    with pytest.raises(CheckpointError) as error:
        load_stage2(flipped)
    assert _one_line(error).startswith(f"{flipped}: checksum mismatch")


def test_a_checkpoint_written_before_checksums_loads_with_one_warning(
    saved: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    old = _rewrite(saved["vae"], tmp_path / "old.safetensors", drop=("checksum",))
    with caplog.at_level(logging.WARNING):
        model = load_checkpoint(old, kind="vae").model
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and str(old) in warnings[0].getMessage()
    assert "checksum" in warnings[0].getMessage()
    expected = load_file(saved["vae"])
    assert all(torch.equal(v, expected[k]) for k, v in model.state_dict().items())


def test_the_checksum_is_in_the_header_and_a_pt_checkpoint_carries_one_too(
    saved: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with safe_open(saved["vae"], framework="pt") as f:
        assert json.loads(f.metadata()["checksum"]).startswith("sha256:")
    pt = save_checkpoint(tmp_path / "seg.pt", create_model("segformer_tiny"))
    with caplog.at_level(logging.WARNING):
        load_checkpoint(pt, "segformer_tiny")
    assert not caplog.records
    payload = torch.load(pt, weights_only=True)
    payload["state_dict"]["decoder.classify.bias"][0] += 1.0
    torch.save(payload, tmp_path / "changed.pt")
    with pytest.raises(CheckpointError, match="checksum mismatch"):
        load_checkpoint(tmp_path / "changed.pt", "segformer_tiny")


# --------------------------------------------------------------------------------------------
# Divergence (VAE, Stage 1, Stage 2, segmenter)


def _nan_from_call(real: Callable, at: int, term: str) -> Callable:
    """``real`` (a loss function returning a dict of terms or a tensor) with ``term`` NaN from
    its ``at``-th call on (1-based)."""
    calls = [0]

    def poisoned(*args: object, **kwargs: object) -> object:
        calls[0] += 1
        out = real(*args, **kwargs)
        if calls[0] < at:
            return out
        if isinstance(out, tuple):
            terms, rest = out[0], out[1:]
            return (
                terms * float("nan") if term == "loss" else {**terms, term: terms[term] * float("nan")},
                *rest,
            )
        return {**out, term: out[term] * float("nan")}

    return poisoned


def _finite(path: Path) -> bool:
    return all(torch.isfinite(v).all() for v in load_file(path).values() if v.is_floating_point())


def test_a_vae_run_stops_at_a_nan_loss_keeps_its_last_good_checkpoint_and_resumes(
    cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "vae"
    monkeypatch.setattr(vae, "vae_loss", _nan_from_call(vae.vae_loss, 3, "reconstruction"))
    with pytest.raises(PhiGenesisError) as error:
        train_vae(cache, out, steps=4, checkpoint_every=2, lr=1e-3, **VAE)
    text = _one_line(error)
    assert text.startswith(f"{out}: training diverged at step 3: the loss term 'reconstruction' is nan")
    assert "most likely at fault: lr = 0.001 (lower it)" in text
    assert "the checkpoint of step 2 is kept" in text
    kept = latest_checkpoint(out)
    assert kept is not None and kept.name == "step-0000002" and _finite(kept / "model.safetensors")
    assert not (out / "model.safetensors").exists()
    monkeypatch.undo()
    run = train_vae(cache, out, steps=4, checkpoint_every=2, lr=1e-3, resume=True, **VAE)
    assert run.finished and _finite(run.checkpoint)


def test_a_stage1_run_stops_at_a_nan_term_naming_the_step_the_term_and_the_lr(
    cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = Stage1TrainConfig(steps=3, warmup_steps=1, checkpoint_every=1, threads=1, lr=0.01)
    monkeypatch.setattr(stage1, "stage1_losses", _nan_from_call(stage1.stage1_losses, 2, "depth"))
    out = tmp_path / "s1"
    with pytest.raises(PhiGenesisError) as error:
        train_stage1(cache, out, cfg, progress=False)
    text = _one_line(error)
    assert text.startswith(f"{out}: training diverged at step 2: the loss term 'depth' is nan")
    assert "most likely at fault: lr = 0.01 (lower it)" in text and "step 1 is kept" in text
    assert [p.name for p in (out / "checkpoints").glob("step-*")] == ["step-0000001"]
    assert not (out / "model.safetensors").exists()


def test_an_update_that_leaves_weights_non_finite_stops_training_and_names_the_weight_decay() -> None:
    model = torch.nn.Linear(2, 2)
    check = runner.DivergenceCheck(Path("runs/x"), lr=0.5, weight_decay=4.0)
    with torch.no_grad():
        model.bias[1] = float("inf")
    with pytest.raises(PhiGenesisError) as error:
        check.weights_after(7, model.named_parameters())
    assert _one_line(error).startswith("runs/x: training diverged at step 7: the update left 'bias'")
    assert "weight_decay = 4 (AdamW scales each weight by 1 - lr x weight_decay = -1" in str(error.value)


def test_a_non_finite_gradient_names_the_first_parameter_that_holds_one() -> None:
    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.Linear(2, 1))
    model(torch.ones(1, 2)).sum().backward()
    model[1].weight.grad[0, 1] = float("nan")
    check = runner.DivergenceCheck(Path("runs/x"), lr=1e-3, kept=lambda: "nothing kept")
    with pytest.raises(PhiGenesisError) as error:
        check.clip_gradients(4, model.named_parameters(), 1.0)
    assert _one_line(error) == (
        "runs/x: training diverged at step 4: the gradient of '1.weight' is not finite; most likely at "
        "fault: lr = 0.001 (lower it); nothing kept"
    )


def test_a_total_that_overflows_from_finite_terms_names_the_heaviest_weight() -> None:
    check = runner.DivergenceCheck(
        Path("r"), lr=1e-3, weights={"rgb": ("weights.rgb", 1.0), "depth": ("weights.depth", 1e3)}
    )
    with pytest.raises(
        PhiGenesisError, match=r"the total loss is inf; most likely at fault: weights.depth = 1000"
    ):
        check.losses(5, {"loss": float("inf"), "rgb": 1.0, "depth": 3e38})


def test_a_segmenter_step_with_a_nan_loss_stops_before_the_update(tmp_path: Path) -> None:
    model = create_model("segformer_tiny")
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    cfg = segmenter.SegmenterTrainConfig(steps=1)
    images = torch.zeros(1, 3, 32, 32, dtype=torch.uint8)
    target = torch.zeros(1, 32, 32, dtype=torch.int64)
    with torch.no_grad():
        model.stages[0].embed.proj.weight[0, 0, 0, 0] = float("nan")  # the forward pass is NaN
    before = {k: v.clone() for k, v in model.named_parameters()}
    check = runner.DivergenceCheck(tmp_path, cfg.lr, cfg.weight_decay, kept=lambda: "last.pt is kept")
    with pytest.raises(PhiGenesisError, match="training diverged at step 1: the loss is nan"):
        segmenter._train_step(model, optimizer, images, target, cfg, check, 1)
    after = dict(model.named_parameters())
    assert all(torch.allclose(v, after[k], rtol=0, atol=0, equal_nan=True) for k, v in before.items())
    assert not optimizer.state  # no update was taken


# --------------------------------------------------------------------------------------------
# Stage 2: divergence through the CLI, the training config a checkpoint records


def test_a_nan_stage2_loss_is_a_clear_error_not_a_bug_and_keeps_the_last_checkpoint(
    cache: Path,
    tmp_path: Path,
    tmp_path_factory: pytest.TempPathFactory,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    stage1_ckpt = two_step_stage1(cache, tmp_path_factory)
    latents = stage2_latents(cache, stage1_ckpt, tmp_path_factory)
    config = tmp_path / "tiny.yaml"
    config.write_text(
        "steps: 3\nbatch_size: 1\nstride: 3\nwarmup_steps: 1\ncheckpoint_every: 1\nthreads: 1\n"
    )
    out = tmp_path / "run"
    argv = ["stage2", "--shards", str(cache), "--config", str(config), "--stage1", str(stage1_ckpt)]
    argv += ["--latents", str(latents), "--out", str(out), "--no-progress"]
    monkeypatch.setattr(stage2, "stage2_loss", _nan_from_call(stage2.stage2_loss, 2, "loss"))
    assert train_main(argv) == 2
    err = capsys.readouterr().err
    assert f"phigenesis-train: error: {out}: training diverged at step 2: the loss is nan" in err
    assert "lr = 0.001" in err and "unexpected" not in err
    kept = latest_checkpoint(out)
    assert kept is not None and kept.name == "step-0000001"
    load_stage2(kept / "model.safetensors")


def test_a_stage2_checkpoint_whose_training_config_says_window_frames_0_is_refused(
    saved: dict[str, Path], tmp_path: Path
) -> None:
    from phigenesis.rollout.runner import trained_uncertainty

    train = Stage2TrainConfig().to_dict() | {"window_frames": 0}
    bad = save_checkpoint(tmp_path / "w0.safetensors", load_stage2(saved["dit"]), {"train": train})
    with pytest.raises(CheckpointError) as error:
        trained_uncertainty(bad)
    assert _one_line(error).startswith(f"{bad}: its training config: ") and "window_frames" in str(
        error.value
    )


# --------------------------------------------------------------------------------------------
# A full disk


def _write_with_a_size_limit(code: str, limit: int = 64 * 1024) -> list[str]:
    """The lines ``code`` prints, run in a process whose files may not grow past ``limit`` bytes
    (a write past it fails with EFBIG, as on a full disk)."""
    prelude = textwrap.dedent(
        f"""
        import resource, signal
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        import torch
        torch.set_num_threads(1)
        from phigenesis.errors import PhiGenesisError
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True, timeout=120
    )
    lines = done.stdout.strip().splitlines()
    assert lines, done.stderr[-2000:]
    return lines


def test_a_full_disk_while_writing_a_checkpoint_names_the_file_and_keeps_the_previous_one(
    tmp_path: Path,
) -> None:
    paths = [tmp_path / "model.safetensors", tmp_path / "model.pt"]  # the trainers' and the segmenter's
    kept = [save_checkpoint(path, create_model("vae_tiny")).read_bytes() for path in paths]
    said = _write_with_a_size_limit(
        f"""
        from phigenesis.models import create_model
        from phigenesis.train.checkpoint import save_checkpoint
        for path in {[str(p) for p in paths]!r}:
            try:
                save_checkpoint(path, create_model("vae_tiny"))
                print("written")
            except PhiGenesisError as e:
                print("refused: " + str(e))
        """
    )
    assert said == [
        f"refused: {p}: cannot be written (File too large); a file already there is unchanged" for p in paths
    ]
    assert [p.read_bytes() for p in paths] == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)
    for path in paths:
        load_checkpoint(path, "vae_tiny")


def test_a_full_disk_at_a_training_checkpoint_keeps_the_previous_checkpoint_and_resumes(
    cache: Path, tmp_path: Path
) -> None:
    out = tmp_path / "vae"
    train_vae(cache, out, steps=4, checkpoint_every=2, stop_after=2, **VAE)
    said = _write_with_a_size_limit(
        f"""
        from phigenesis.train.vae import train_vae
        try:
            train_vae({str(cache)!r}, {str(out)!r}, steps=4, checkpoint_every=2, resume=True, **{VAE!r})
            print("finished")
        except PhiGenesisError as e:
            print("refused: " + str(e))
        """,
        limit=512 * 1024,  # metrics.csv and config.yaml fit, a checkpoint (4.8 MB) does not
    )
    final = out / "checkpoints" / "step-0000004" / "model.safetensors"
    assert said == [
        f"refused: {final}: the checkpoint of step 4 cannot be written (File too large); the checkpoint of "
        "step 2 is kept (nothing of this step was written)"
    ]
    assert [p.name for p in (out / "checkpoints").iterdir() if p.name.startswith(("step-", "."))] == [
        "step-0000002"
    ]
    read_trainer_state(out / "checkpoints" / "step-0000002" / "trainer.safetensors")
    run = train_vae(cache, out, steps=4, checkpoint_every=2, resume=True, **VAE)
    assert run.finished
