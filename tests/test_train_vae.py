"""Training the video VAE on a cache (phigenesis.train.vae, ``phigenesis-train vae``)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from phigenesis import prep
from phigenesis.cli.train import main as train_main
from phigenesis.data.pipeline import PipelineSpec, load_pipeline
from phigenesis.data.records import Frame, Scene
from phigenesis.data.shards import CacheReader
from phigenesis.data.stages import STAGES, register_stage
from phigenesis.models import create_model
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint
from phigenesis.train.runner import read_metrics, step_generator
from phigenesis.train.vae import ClipImages, VAETrainConfig, list_clips, split_clips, train_step, train_vae
from tests.conftest import TINY_PREP_ARGS

#: 2 scenes x 6 frames of the 5-camera rig at 32 x 48: 2 windows of 5 frames x 5 cameras per scene.
SIZE = (32, 48)
FAST = {"frames": 5, "size": SIZE, "batch_size": 2, "threads": 1, "val_clips": 4}


def _bare_cache(out: Path, **args: object) -> Path:
    """A cache of camera images only (no stages, truth or LiDAR columns): quick to build."""
    spec = load_pipeline("synthetic").to_dict()
    spec["stages"] = list(args.pop("stages", []))  # type: ignore[arg-type]
    spec["output"].update(
        camera_truth=[], lidar=False, lidar_truth=False, depth=False, pseudo_semantics=False, range_view=False
    )
    values = {**TINY_PREP_ARGS, "scenes": 2, "frames": 6, "height": SIZE[0], "width": SIZE[1], **args}
    prep.synthetic(out, pipeline=PipelineSpec.from_dict(spec), progress=False, **values)  # type: ignore[arg-type]
    return out


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.set_num_threads(1)
    return _bare_cache(tmp_path_factory.mktemp("vae_cache"))


def test_clips_cover_every_window_and_camera_and_validation_holds_out_whole_scenes(cache: Path) -> None:
    clips = list_clips(CacheReader(cache), frames=5)
    assert len(clips) == 2 * 2 * 5
    assert all(
        len(c.frames) == 5 and list(c.frames) == list(range(c.frames[0], c.frames[0] + 5)) for c in clips
    )
    train_scenes, val_scenes, train, val = split_clips(clips, 5, 0.5, seed=0)
    assert len(train_scenes) == len(val_scenes) == 1 and len(train) == len(val) == 10
    assert {c.scene for c in train}.isdisjoint({c.scene for c in val})
    # One scene of 6 frames cannot hold out 5 frames and keep 5: no validation.
    one = [c for c in clips if c.scene == train_scenes[0]]
    assert split_clips(one, 5, 0.2, seed=0)[3] == []


def test_loss_falls_on_a_fixed_batch(cache: Path) -> None:
    reader = CacheReader(cache)
    clips = list_clips(reader, frames=5)
    video = ClipImages(reader, SIZE).video([clips[0], clips[13]])  # [2, 3, 5, 32, 48]
    assert video.shape == (2, 3, 5, *SIZE) and -1.0 <= float(video.min()) < float(video.max()) <= 1.0
    torch.manual_seed(0)
    model = create_model("vae_tiny").train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.0)
    cfg = VAETrainConfig()
    losses = [
        float(train_step(model, optimizer, video, cfg, 1e-3, step_generator(0, step))["loss"])
        for step in range(30)
    ]
    # Measured: L1 0.69 at the start, 0.28 after 30 steps.
    assert losses[-1] < 0.5 * losses[0] and losses[-1] < min(losses[:10]), losses


def test_training_writes_a_final_checkpoint_that_loads_and_decodes(cache: Path, tmp_path: Path) -> None:
    run = train_vae(cache, tmp_path / "run", steps=8, checkpoint_every=4, **FAST)
    assert run.finished and run.step == 8 and run.checkpoint == tmp_path / "run" / "model.safetensors"
    assert len(run.train_scenes) == len(run.val_scenes) == 1
    assert 5.0 < run.val["psnr_db"] < 60.0 and run.val["clips"] == 4
    ckpt = load_checkpoint(run.checkpoint, "vae_tiny")
    assert ckpt.meta["steps"] == 8 and ckpt.meta["frames"] == 5 and ckpt.meta["size"] == list(SIZE)
    assert ckpt.meta["val_psnr_db"] == pytest.approx(run.val["psnr_db"])
    vae = ckpt.model.freeze()
    video = vae.decode(torch.zeros(1, 4, 2, 8, 12))
    assert video.shape == (1, 3, 5, *SIZE) and torch.isfinite(video).all()
    rows = read_metrics(run.out)
    assert [r["step"] for r in rows] == list(range(1, 9))
    assert all({"loss", "reconstruction", "kl", "lr", "grad_norm"} <= set(r) for r in rows)
    assert "val_psnr" in rows[3] and "val_psnr" in rows[7] and "val_psnr" not in rows[0]
    summary = json.loads((run.out / "metrics.json").read_text())
    assert summary["val"]["psnr_db"] == pytest.approx(run.val["psnr_db"]) and summary["train_clips"] == 10
    assert [h["step"] for h in summary["history"]] == [4, 8] and summary["final_train_loss"] > 0
    assert any((run.out / "tb").iterdir()) and (run.out / "config.yaml").is_file()


def test_a_resumed_run_reproduces_the_uninterrupted_loss_curve(cache: Path, tmp_path: Path) -> None:
    options = {**FAST, "steps": 6, "checkpoint_every": 100}
    whole = train_vae(cache, tmp_path / "whole", **options)
    first = train_vae(cache, tmp_path / "split", stop_after=3, **options)
    assert not first.finished and first.step == 3 and first.checkpoint.is_file()
    assert not (tmp_path / "split" / "model.safetensors").exists()
    resumed = train_vae(cache, tmp_path / "split", resume=True, **options)
    assert resumed.finished
    a, b = read_metrics(whole.out), read_metrics(resumed.out)
    assert [r["step"] for r in b] == list(range(1, 7))
    for column in ("loss", "reconstruction", "kl", "lr", "grad_norm"):
        assert [r[column] for r in b] == pytest.approx([r[column] for r in a], rel=1e-6, abs=1e-6), column
    assert resumed.val["psnr_db"] == pytest.approx(whole.val["psnr_db"], abs=1e-4)


def test_a_folder_with_a_run_is_refused_without_resume_and_with_other_options(
    cache: Path, tmp_path: Path
) -> None:
    train_vae(cache, tmp_path / "run", steps=2, **FAST)
    with pytest.raises(ValueError, match=r"already holds a run.*--resume"):
        train_vae(cache, tmp_path / "run", steps=2, **FAST)
    with pytest.raises(ValueError, match="differing: lr"):
        train_vae(cache, tmp_path / "run", steps=2, resume=True, lr=5e-4, **FAST)


def test_cli_trains_and_reports_psnr_and_errors_exit_2(cache: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "cli"
    common = ["vae", "--shards", str(cache), "--out", str(out), "--steps", "3", "--batch-size", "2"]
    common += ["--size", "32x48", "--frames", "5", "--threads", "1"]
    assert train_main([*common, "--stop-after", "2"]) == 0
    assert "stopped at step 2" in capsys.readouterr().out
    assert train_main([*common, "--resume"]) == 0
    printed = capsys.readouterr().out
    assert "validation PSNR" in printed and f"final checkpoint: {out / 'model.safetensors'}" in printed
    assert [r["step"] for r in read_metrics(out)] == [1, 2, 3]
    assert train_main([*common[:4], str(tmp_path / "bad"), *common[5:], "--size", "30x48"]) == 2
    assert "divide by 4" in capsys.readouterr().err


def test_clear_errors_for_shapes_and_caches(cache: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"30x48.*divide by 4"):
        train_vae(cache, tmp_path / "a", steps=1, **{**FAST, "size": (30, 48)})
    with pytest.raises(ValueError, match=r"frames=4.*divide by 4"):
        train_vae(cache, tmp_path / "a", steps=1, **{**FAST, "frames": 4})
    with pytest.raises(ValueError, match=f"{cache}.*no clip of 9 consecutive frames.*6 frames"):
        train_vae(cache, tmp_path / "a", steps=1, **{**FAST, "frames": 9})
    # An empty cache: every scene failed.
    empty = tmp_path / "empty"
    empty.mkdir()
    manifest = json.loads((cache / "manifest.json").read_text())
    manifest["scenes"] = [
        {**s, "status": "failed", "shards": [], "error": "test"} for s in manifest["scenes"]
    ]
    manifest["shards"] = []
    (empty / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=f"{empty}: the cache has no frames"):
        train_vae(empty, tmp_path / "a", steps=1, **FAST)


def test_a_cache_without_images_is_a_clear_error(tmp_path: Path) -> None:
    @register_stage("test_only_drop_images")
    def drop_images(scene: Scene, params: dict) -> Scene:
        def drop(frame: Frame) -> Frame:
            for camera in frame.cameras:
                camera.image_bytes = None
            return frame

        return Scene(scene.scene_id, scene.source, scene.calibrations, scene.frames.map(drop), scene.metadata)

    try:
        cache = _bare_cache(
            tmp_path / "no_images",
            scenes=1,
            frames=1,
            stages=[{"name": "test_only_drop_images", "params": {}}],
        )
    finally:
        STAGES.pop("test_only_drop_images", None)
    with pytest.raises(ValueError, match=f"{cache}: the cache has no camera images"):
        train_vae(cache, tmp_path / "a", steps=1, **FAST)


def test_init_from_a_checkpoint_of_another_config_names_the_fields(cache: Path, tmp_path: Path) -> None:
    other = save_checkpoint(tmp_path / "other.safetensors", create_model("vae_tiny", latent_channels=8))
    with pytest.raises(CheckpointError, match="latent_channels"):
        train_vae(cache, tmp_path / "a", steps=1, init=str(other), **FAST)
    same = save_checkpoint(tmp_path / "same.safetensors", create_model("vae_tiny"))
    assert train_vae(cache, tmp_path / "b", steps=1, init=str(same), **FAST).finished


@pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="torch.distributed with gloo is not available",
)
def test_torchrun_with_two_processes_trains_and_rank_0_writes(cache: Path, tmp_path: Path) -> None:
    out = tmp_path / "ddp"
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    command += ["-m", "phigenesis.cli.train", "vae", "--shards", str(cache), "--out", str(out)]
    command += ["--steps", "2", "--batch-size", "2", "--size", "32x48", "--frames", "5", "--threads", "1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert time.perf_counter() - start < 60
    assert done.stdout.count("validation PSNR") == 1
    assert [r["step"] for r in read_metrics(out)] == [1, 2]
    assert load_checkpoint(out / "model.safetensors", "vae_tiny").meta["steps"] == 2
    shutil.rmtree(out)
