"""Stage 2 data and training: conditions from history, the latent cache, the trainer and its CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import pyarrow as pa
import pyarrow.ipc as ipc
import pytest
import torch

from phigenesis.cli.train import main as train_main
from phigenesis.data.clips import Stage1Clips
from phigenesis.data.frame_truth import frame_truth
from phigenesis.data.shards import CacheError, verify_cache
from phigenesis.errors import PrepError
from phigenesis.models.loading import load_stage1, load_stage2
from phigenesis.rollout.conditions import context_cameras, future_cameras, history_scene, render_condition
from phigenesis.rollout.config import Stage2DataConfig, Stage2TrainConfig
from phigenesis.train.checkpoint import CheckpointError
from phigenesis.train.runner import read_metrics
from phigenesis.train.stage2 import make_batch, restarted_cosine_lr, train_stage2
from phigenesis.train.stage2_data import (
    Stage2Latents,
    precompute_stage2,
    window_clip,
    window_sample,
    window_starts,
)
from tests.conftest import one_scene_cache, stage2_latents, two_step_stage1

SIZE = (48, 72)
FRAMES = 12


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return one_scene_cache(tmp_path_factory, "stage2_cache", FRAMES, SIZE)


@pytest.fixture(scope="module")
def stage1_checkpoint(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return two_step_stage1(cache, tmp_path_factory)


@pytest.fixture(scope="module")
def latents(cache: Path, stage1_checkpoint: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return stage2_latents(cache, stage1_checkpoint, tmp_path_factory)


def _config(**overrides: object) -> Stage2TrainConfig:
    base = {"steps": 6, "batch_size": 2, "stride": 3, "warmup_steps": 2, "checkpoint_every": 3, "threads": 1}
    return Stage2TrainConfig(**{**base, **overrides})  # type: ignore[arg-type]


def test_windows_lie_inside_the_scene_and_step_by_the_stride() -> None:
    cfg = Stage2DataConfig(history_frames=1, window_frames=5, stride=3)
    assert window_starts(12, cfg) == [0, 3, 6]
    assert window_starts(6, cfg) == [0]
    assert window_starts(5, cfg) == []


def test_a_windows_condition_uses_no_frame_at_or_after_its_start(
    cache: Path, stage1_checkpoint: Path
) -> None:
    """The history is before the targets, and the render and its maps do not change when every
    target image is replaced: nothing of the frames to generate leaks into their condition."""
    model = load_stage1(stage1_checkpoint)
    data = Stage1Clips(cache, SIZE, 1, "auto")
    cfg = Stage2DataConfig(stride=3)
    sample = window_sample(model, data, data.reader.scene_ids()[0], 3, cfg)
    assert max(sample.history_indices) < min(sample.target_indices)
    assert sample.target_indices == [4, 5, 6, 7, 8]

    real_clip = data.clip

    def clip_with_blank_targets(scene_id: str, start: int, offsets: list[int], keep_frames: bool = False):  # type: ignore[no-untyped-def]
        clip = real_clip(scene_id, start, offsets, keep_frames)
        t = len(clip.frame_indices)
        images = clip.targets.images.clone()
        images[t:] = 0.5
        targets = dataclasses.replace(clip.targets, images=images)
        return dataclasses.replace(clip, targets=targets)

    data.clip = clip_with_blank_targets  # type: ignore[method-assign]
    blanked = window_sample(model, data, data.reader.scene_ids()[0], 3, cfg)
    assert torch.equal(blanked.z_render, sample.z_render)
    assert torch.equal(blanked.z_history, sample.z_history)
    for kind in sample.u:
        assert torch.equal(blanked.u[kind], sample.u[kind]), kind
    assert not torch.equal(blanked.z_target, sample.z_target)


def test_truth_geometry_renders_the_history_at_its_own_cameras_and_covers_more_than_the_cache(
    cache: Path,
) -> None:
    data = Stage1Clips(cache, SIZE, 1, "auto")
    scene_id = data.reader.scene_ids()[0]
    clip = window_clip(data, scene_id, 0, Stage2DataConfig(geometry="truth"))
    assert clip.frames is not None
    truths = [frame_truth(clip.frames[i], SIZE) for i in clip.frame_indices]
    truth = {
        "truth_depth_m": torch.stack([t.depth for t in truths]),
        "truth_semantic": torch.stack([t.semantic for t in truths]),
        "truth_flow_mps": torch.stack([t.flow for t in truths]),  # type: ignore[misc]
    }
    scene = history_scene("truth", clip, **truth)
    own = render_condition(scene, context_cameras(clip))
    covered = own.alpha > 0.9
    assert covered.float().mean() > 0.6  # every non-sky pixel spawned a Gaussian
    images = clip.context.images.permute(0, 1, 3, 4, 2)
    err = (own.rgb / own.alpha.clamp(min=1e-6)[..., None] - images).abs()[covered]
    assert float(err.mean()) < 0.05
    future = render_condition(scene, future_cameras(clip))
    cached = render_condition(history_scene("cache", clip), future_cameras(clip))
    assert future.rgb.shape == (5, 5, *SIZE, 3)
    assert float(future.alpha.mean()) > float(cached.alpha.mean())  # the LiDAR's dense depth has holes
    with pytest.raises(ValueError, match="needs a Stage 1 model"):
        history_scene("stage1", clip)
    with pytest.raises(ValueError, match="truth depth"):
        history_scene("truth", clip)


def test_the_latent_cache_passes_verify_and_opens_with_plain_pyarrow(latents: Path) -> None:
    report = verify_cache(latents)
    assert not report.errors, report.errors
    assert report.frames == 3
    manifest = json.loads((latents / "manifest.json").read_text())
    assert manifest["source"] == "stage2-latents" and manifest["arguments"]["geometry"] == "stage1"
    shard = latents / manifest["shards"][0]["path"]
    with pa.memory_map(str(shard)) as f:
        table = ipc.open_file(f).read_all()
    assert table.num_rows == 3
    shape = table.column("z_target_shape")[0].as_py()
    assert shape == [5, 4, 2, 12, 18]
    assert len(table.column("z_target")[0].as_py()) == 5 * 4 * 2 * 12 * 18
    u = torch.tensor(table.column("u_localization_potential")[0].as_py())
    assert float(u.min()) >= 0 and float(u.max()) <= 1
    sample = Stage2Latents(latents)[0]
    assert set(sample.u) == {"coverage", "random", "entropy", "localization_potential"}
    assert sample.z_history.shape == (5, 4, 1, 12, 18)


def test_a_rerun_of_the_precompute_skips_finished_scenes_and_other_inputs_are_refused(
    cache: Path, stage1_checkpoint: Path, latents: Path
) -> None:
    model = load_stage1(stage1_checkpoint)
    before = (latents / "manifest.json").read_text()
    precompute_stage2(
        cache, latents, model, Stage2DataConfig(stride=3), stage1_checkpoint=str(stage1_checkpoint)
    )
    assert (latents / "manifest.json").read_text() == before
    with pytest.raises(PrepError, match=r"other arguments \(stride 3 -> 2\)"):
        precompute_stage2(
            cache, latents, model, Stage2DataConfig(stride=2), stage1_checkpoint=str(stage1_checkpoint)
        )


def test_the_latent_caches_localization_potential_follows_lp_trust_and_is_part_of_its_fingerprint(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path: Path
) -> None:
    model = load_stage1(stage1_checkpoint)
    other = tmp_path / "localised"
    cfg = Stage2DataConfig(stride=3, lp_trust="localised")
    precompute_stage2(cache, other, model, cfg, stage1_checkpoint=str(stage1_checkpoint))
    assert json.loads((latents / "manifest.json").read_text())["arguments"]["lp_trust"] == "stable"
    assert json.loads((other / "manifest.json").read_text())["arguments"]["lp_trust"] == "localised"
    stable, localised = Stage2Latents(latents), Stage2Latents(other)
    assert len(stable) == len(localised) == 3
    for i in range(3):
        a, b = stable[i], localised[i]
        for kind in ("coverage", "random", "entropy"):
            assert torch.equal(a.u[kind], b.u[kind]), kind
        # Per covered pixel the two readings are complements, and pooling to the latent grid averages.
        torch.testing.assert_close(
            a.u["localization_potential"] + b.u["localization_potential"], a.u["coverage"], rtol=0, atol=1e-5
        )
        assert not torch.equal(a.u["localization_potential"], b.u["localization_potential"])
    with pytest.raises(PrepError, match=r"other arguments \(lp_trust 'localised' -> 'stable'\)"):
        precompute_stage2(
            cache, other, model, Stage2DataConfig(stride=3), stage1_checkpoint=str(stage1_checkpoint)
        )
    with pytest.raises(ValueError, match="lp_trust"):
        Stage2DataConfig(lp_trust="sure")  # type: ignore[arg-type]


def test_generation_uses_the_lp_trust_its_checkpoint_was_trained_with(
    stage2_checkpoint: Path, cache: Path
) -> None:
    from phigenesis.errors import CheckpointError
    from phigenesis.rollout.runner import GenerateOptions, Stage2Runner, trained_lp_trust

    runner = Stage2Runner(stage2_checkpoint, cache)
    assert runner.lp_trust == "stable"
    assert runner.resolve(None).lp_trust == "stable"
    assert runner.resolve(GenerateOptions(lp_trust="localised")).lp_trust == "localised"
    # Checkpoints trained before the choice existed used the localised reading.
    assert trained_lp_trust({"window_frames": 5}, "old.safetensors") == "localised"
    with pytest.raises(CheckpointError, match=r"old\.safetensors.*lp_trust"):
        trained_lp_trust({"lp_trust": "sure"}, "old.safetensors")
    with pytest.raises(ValueError, match="lp_trust"):
        GenerateOptions(lp_trust="sure")


def test_generation_samples_on_the_geometry_its_checkpoint_was_trained_on(
    stage2_checkpoint: Path, cache: Path, tmp_path: Path
) -> None:
    """A model trained on the truth's renders (the benchmark's ceiling row) is sampled on them unless
    told otherwise; until 2026-12-06 every evaluation sampled on Stage 1's."""
    from safetensors.torch import load_file, save_file

    from phigenesis.errors import CheckpointError
    from phigenesis.models.checkpoint import read_safetensors_metadata
    from phigenesis.rollout.runner import GenerateOptions, Stage2Runner, trained_geometry

    runner = Stage2Runner(stage2_checkpoint, cache)
    assert runner.geometry == "stage1" and runner.resolve(None).geometry == "stage1"
    # The same weights with a training config that says truth.
    src = stage2_checkpoint / "model.safetensors" if stage2_checkpoint.is_dir() else stage2_checkpoint
    meta = read_safetensors_metadata(src)
    extra = json.loads(meta["meta"])
    meta["meta"] = json.dumps({**extra, "train": {**extra["train"], "geometry": "truth"}})
    truth_ckpt = tmp_path / "truth.safetensors"
    save_file(load_file(str(src)), str(truth_ckpt), metadata=meta)
    truth_runner = Stage2Runner(truth_ckpt, cache)
    assert truth_runner.resolve(None).geometry == "truth"
    assert truth_runner.resolve(GenerateOptions(geometry="stage1")).geometry == "stage1"
    result, _ = truth_runner.run(sorted(truth_runner.data.scenes)[0], 1, 2, "recorded", None)
    assert torch.isfinite(result.images).all()
    # A config that predates the field was trained on Stage 1's renders; a crafted value is refused.
    assert trained_geometry({"window_frames": 5}, "old.safetensors") == "stage1"
    with pytest.raises(CheckpointError, match=r"old\.safetensors.*geometry.*'lidar'"):
        trained_geometry({"geometry": "lidar"}, "old.safetensors")
    with pytest.raises(ValueError, match="geometry"):
        GenerateOptions(geometry="lidar")


def test_a_crafted_latent_row_with_nan_is_refused_naming_the_shard_and_column(
    cache: Path, latents: Path, tmp_path: Path
) -> None:
    import shutil

    from phigenesis.data.shards import ShardWriter
    from phigenesis.train.stage2_data import latent_schema, sample_to_batch

    sample = Stage2Latents(latents)[0]
    with pytest.raises(ValueError, match="z_render holds NaN"):
        bad = dataclasses.replace(sample, z_render=sample.z_render.clone().fill_(float("nan")))
        sample_to_batch(bad, latent_schema({}))
    # A shard whose bytes are right for its manifest but whose values leave [0, 1]: the reader refuses.
    crafted = tmp_path / "crafted"
    shutil.copytree(latents, crafted)
    manifest = json.loads((crafted / "manifest.json").read_text())
    scene = manifest["scenes"][0]["id"]
    for p in (crafted / "shards").iterdir():
        p.unlink()
    u = dict(sample.u)
    u["coverage"] = u["coverage"] * 0 + 2.0
    with ShardWriter(crafted, scene, latent_schema({})) as writer:
        writer.write(sample_to_batch(dataclasses.replace(sample, u=u), latent_schema({})))
        shards = writer.close()
    manifest["shards"] = [dataclasses.asdict(s) for s in shards]
    manifest["scenes"][0]["frames"] = 1
    manifest["scenes"][0]["shards"] = [s.path for s in shards]
    (crafted / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(CacheError, match=r"row 0: u_coverage leaves \[0, 1\]"):
        Stage2Latents(crafted)[0]
    with pytest.raises(CacheError, match="not a Stage 2 latent cache"):
        Stage2Latents(cache)


def test_a_batch_holds_history_then_targets_with_the_condition_on_the_targets_only(latents: Path) -> None:
    data = Stage2Latents(latents)
    batch = make_batch([data[0], data[1]], "localization_potential", 4)
    assert batch.z0.shape == (2, 5, 4, 3, 12, 18)
    assert batch.target.tolist() == [False, True, True]
    assert torch.count_nonzero(batch.condition[:, :, :, 0]) == 0
    u = data[0].u["localization_potential"]
    assert torch.allclose(batch.condition[0, :, 4, 1:], u)  # the last channel is u itself
    assert torch.allclose(batch.condition[0, :, :4, 1:], u[:, None] * data[0].z_render)
    assert batch.plucker.shape == (2, 5, 6, 3, 12, 18)
    d = batch.plucker[:, :, :3]
    assert torch.allclose(d.norm(dim=2), torch.ones(()), atol=1e-5)
    none = make_batch([data[0]], "none", 4)
    assert torch.count_nonzero(none.condition) == 0


def test_latent_norm_standardises_every_latent_of_a_batch_by_the_caches_statistics(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path: Path
) -> None:
    from phigenesis.train.stage2 import build_denoiser, latent_statistics

    data = Stage2Latents(latents)
    mean, std = latent_statistics(data)
    every = torch.stack([data[i].z_target for i in range(len(data))]).double()  # [N, V, C, T, h, w]
    by_channel = every.transpose(0, 2).reshape(every.shape[2], -1)
    assert mean == pytest.approx(by_channel.mean(1).tolist(), abs=1e-9)
    assert std == pytest.approx(by_channel.std(1, unbiased=False).tolist(), rel=1e-9)
    model = build_denoiser(_config(latent_norm=True), 4, (mean, std))
    batch = make_batch([data[0], data[1]], "coverage", 4, model)
    plain = make_batch([data[0], data[1]], "coverage", 4)
    m = torch.tensor(mean).float()[None, None, :, None, None, None]
    s = torch.tensor(std).float()[None, None, :, None, None, None]
    torch.testing.assert_close(batch.z0, (plain.z0 - m) / s)
    u = data[0].u["coverage"]
    z_ren = (data[0].z_render - m[0]) / s[0]
    torch.testing.assert_close(batch.condition[0, :, :4, 1:], u[:, None] * z_ren)
    torch.testing.assert_close(model.denormalize_latents(batch.z0), plain.z0, rtol=1e-5, atol=1e-5)
    # A run trained with it carries the statistics in its checkpoint, and its rollouts stay finite.
    run = train_stage2(
        cache,
        tmp_path / "norm",
        _config(steps=2, latent_norm=True),
        stage1=stage1_checkpoint,
        latents=latents,
        progress=False,
    )
    assert run.checkpoint is not None
    loaded = load_stage2(run.checkpoint)
    assert loaded.config.latent_mean == pytest.approx(mean) and loaded.config.latent_std == pytest.approx(std)
    from phigenesis.rollout.runner import GenerateOptions, Stage2Runner

    result, _ = Stage2Runner(run.checkpoint, cache).run(
        "synthetic-s7-0000", 2, 5, "recorded", GenerateOptions(steps=2, uncertainty="coverage")
    )
    assert bool(torch.isfinite(result.images).all()) and result.images.shape[0] == 5


def test_the_learning_rate_warms_up_then_restarts_its_cosine() -> None:
    cfg = _config(steps=100, warmup_steps=10, restart_steps=30, lr=1e-3, final_lr_ratio=0.1)
    assert restarted_cosine_lr(0, cfg) == pytest.approx(1e-4)
    assert restarted_cosine_lr(10, cfg) == pytest.approx(1e-3)
    assert restarted_cosine_lr(39, cfg) < 2e-4
    assert restarted_cosine_lr(40, cfg) == pytest.approx(1e-3)


def test_a_killed_training_run_resumes_to_the_same_losses(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path: Path
) -> None:
    whole = train_stage2(
        cache, tmp_path / "whole", _config(), stage1=stage1_checkpoint, latents=latents, progress=False
    )
    assert whole.checkpoint is not None and whole.steps_done == 6
    part = train_stage2(
        cache,
        tmp_path / "part",
        _config(),
        stage1=stage1_checkpoint,
        latents=latents,
        stop_after=3,
        progress=False,
    )
    assert part.checkpoint is None and part.steps_done == 3
    again = train_stage2(
        cache,
        tmp_path / "part",
        _config(),
        stage1=stage1_checkpoint,
        latents=latents,
        resume=True,
        progress=False,
    )
    assert again.steps_done == 6
    a, b = read_metrics(tmp_path / "whole"), read_metrics(tmp_path / "part")
    assert [r["loss"] for r in a] == pytest.approx([r["loss"] for r in b], rel=1e-6)
    model = load_stage2(whole.checkpoint)
    assert model.name == "stage2_tiny"
    with pytest.raises(ValueError, match="holds a run already"):
        train_stage2(
            cache, tmp_path / "whole", _config(), stage1=stage1_checkpoint, latents=latents, progress=False
        )


def test_a_stage1_checkpoint_where_a_stage2_one_is_expected_is_refused(stage1_checkpoint: Path) -> None:
    with pytest.raises(CheckpointError, match="not a Stage 2 denoiser"):
        load_stage2(stage1_checkpoint)


def test_entropy_without_a_depth_entropy_is_refused_naming_the_map(latents: Path) -> None:
    sample = Stage2Latents(latents)[0]
    del sample.u["entropy"]
    with pytest.raises(ValueError, match="no 'entropy' map"):
        make_batch([sample], "entropy", 4)


def test_the_cli_trains_from_a_config_file_and_reports_bad_configs(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "tiny.yaml"
    config.write_text("steps: 2\nbatch_size: 1\nstride: 3\nwarmup_steps: 1\nthreads: 1\n")
    argv = ["stage2", "--shards", str(cache), "--config", str(config), "--stage1", str(stage1_checkpoint)]
    argv += ["--latents", str(latents), "--out", str(tmp_path / "run"), "--no-progress"]
    assert train_main(argv) == 0
    assert "final checkpoint" in capsys.readouterr().out
    bad = tmp_path / "bad.yaml"
    bad.write_text("uncertainty: depth\n")
    argv[argv.index(str(config))] = str(bad)
    assert train_main(argv) == 2
    assert "bad.yaml: Stage2TrainConfig: uncertainty = 'depth': must be one of" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Generation


@pytest.fixture(scope="module")
def stage2_checkpoint(
    cache: Path, stage1_checkpoint: Path, latents: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    run = train_stage2(
        cache,
        tmp_path_factory.mktemp("s2"),
        _config(steps=2),
        stage1=stage1_checkpoint,
        latents=latents,
        progress=False,
    )
    assert run.checkpoint is not None
    return run.checkpoint


def _straight_trajectory(cache: Path, frames: int, path: Path) -> Path:
    """A JSON trajectory driving on at the recorded scene's last velocity, ``frames`` frames long."""
    from phigenesis.data.loader import FrameDataset

    ds = FrameDataset(cache, fields=["cameras"])
    a, b = ds[0], ds[1]
    step = b["world_from_ego"][:3, 3] - a["world_from_ego"][:3, 3]
    dt = int(b["frame_timestamp_micros"]) - int(a["frame_timestamp_micros"])
    entries = []
    for i in range(frames):
        pose = b["world_from_ego"].clone()
        pose[:3, 3] += step * (i + 1)
        entries.append(
            {
                "timestamp_micros": int(b["frame_timestamp_micros"]) + dt * (i + 1),
                "world_from_ego": pose.tolist(),
            }
        )
    path.write_text(json.dumps({"frames": entries}))
    return path


def test_a_generated_cache_passes_verify_and_the_loader_reads_its_rendered_depth(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    from phigenesis.data import records
    from phigenesis.data.loader import FrameDataset
    from phigenesis.infer.generate import generate
    from phigenesis.rollout.runner import GenerateOptions

    out = tmp_path / "gen"
    result = generate(
        stage2_checkpoint,
        cache,
        "synthetic-s7-0000",
        2,
        7,
        out,
        trajectory="shift:2m",
        options=GenerateOptions(steps=2, omega=2.0),
        progress=False,
    )
    report = verify_cache(out)
    assert not report.errors and report.frames == 7
    assert (out / "strip.png").stat().st_size > 0 and len(result.plys) == 2
    # The strip: a header of camera names, then each shown frame's generated and condition rows,
    # labelled in a left margin.
    strip = cv2.imread(str(out / "strip.png"))
    n, views, h, w = result.rollout.images.shape[:4]
    assert strip.shape[:2] == (20 + 2 * min(n, 8) * h, 150 + views * w)
    margin = strip[20:, :150]
    assert all((margin[r * h : (r + 1) * h] > 100).any() for r in range(2 * min(n, 8)))  # every row named
    assert (strip[:20, 150:] > 100).any()  # camera names over the columns
    sample = FrameDataset(out, fields=["images", "cameras", "depth", "pseudo"])[0]
    assert sample["images"].shape == (5, 3, *SIZE) and sample["frame_index"] == 0
    rendered = records.DENSE_ORIGINS.index("rendered")
    dense = sample["depth_dense"]
    assert (dense > 0).any() and bool(((sample["depth_dense_origin"] == rendered) == (dense > 0)).all())
    # The shift moved every camera 2 m along the ego's +y.
    recorded = FrameDataset(cache, fields=["cameras"])[2]
    moved = sample["camera_world_from_ego"][:, :3, 3] - recorded["camera_world_from_ego"][:, :3, 3]
    left = recorded["world_from_ego"][:3, 1]
    assert torch.allclose(moved.double(), 2.0 * left.double().expand(5, 3), atol=1e-6)
    report = json.loads((out / "generate.json").read_text())
    assert report["windows"] == 2 and "shift" not in report
    assert report["sampling"]["time_shift"] == 1.0 and report["sampling"]["steps"] >= 1
    # The cache records the mapping the rollout used: the checkpoint's, as options left it open.
    assert json.loads((out / "manifest.json").read_text())["arguments"]["lp_trust"] == "stable"


def test_a_200_frame_rollout_keeps_its_buffer_bounded_and_finite(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    from phigenesis.infer.generate import generate
    from phigenesis.rollout.runner import GenerateOptions

    path = _straight_trajectory(cache, 200, tmp_path / "straight.json")
    options = GenerateOptions(steps=1, uncertainty="coverage", max_gaussians=20_000)
    result = generate(
        stage2_checkpoint,
        cache,
        "synthetic-s7-0000",
        2,
        200,
        tmp_path / "long",
        trajectory=str(path),
        options=options,
        progress=False,
    )
    r = result.rollout
    assert r.images.shape[0] == 200 and len(r.buffer_sizes) == 40
    assert max(r.buffer_sizes) <= 20_000
    assert torch.isfinite(r.images).all() and torch.isfinite(r.depth).all()
    assert verify_cache(tmp_path / "long").frames == 200


def test_render_anchoring_pulls_the_targets_to_the_render_over_the_sky_where_u_trusts_it(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from phigenesis.infer import generate as gen
    from phigenesis.rollout import runner

    seen: list = []
    renders: list = []
    real_sample, real_with_sky = runner.euler_sample, runner.with_sky

    def spy_sample(*args, anchor=None, **kwargs):  # type: ignore[no-untyped-def]
        z = real_sample(*args, anchor=anchor, **kwargs)
        seen.append((anchor, args[5], z))
        return z

    def spy_with_sky(render, stage1, cams):  # type: ignore[no-untyped-def]
        out = real_with_sky(render, stage1, cams)
        renders.append((out, stage1))
        return out

    monkeypatch.setattr(runner, "euler_sample", spy_sample)
    monkeypatch.setattr(runner, "with_sky", spy_with_sky)
    options = gen.GenerateOptions(steps=3, uncertainty="coverage", anchor=1.0, anchor_until=0.0)
    result = gen.generate(
        stage2_checkpoint, cache, "synthetic-s7-0000", 2, 5, tmp_path / "a", options=options, progress=False
    )
    assert len(seen) == 1 and len(renders) == 1
    anchor, condition, z = seen[0]
    c = anchor.z0.shape[2]
    u = condition[:, :, c:]  # the condition's trust channel
    assert torch.equal(anchor.weight, u) and anchor.until == 0.0
    t_h = 1  # one latent history frame
    assert float(anchor.weight[:, :, :, :t_h].abs().max()) == 0.0  # history is never anchored
    full, stage1 = renders[0]
    denoiser, _ = runner._stage2_checkpoint(stage2_checkpoint)
    z_full = denoiser.normalize_latents(stage1.encode(full.permute(0, 1, 4, 2, 3)[None]))
    assert torch.allclose(anchor.z0[:, :, :, t_h:], z_full, atol=1e-5)
    trusted = (u[:, :, :, t_h:] == 1).expand_as(z_full)
    assert bool(trusted.any()) and torch.equal(z[:, :, :, t_h:][trusted], anchor.z0[:, :, :, t_h:][trusted])
    assert torch.isfinite(result.rollout.images).all()
    with pytest.raises(ValueError, match=r"anchor = 1.5: must be a number in \[0, 1\]"):
        gen.GenerateOptions(anchor=1.5)
    with pytest.raises(ValueError, match="anchor_until"):
        gen.GenerateOptions(anchor_until=1.0)


def test_render_pasting_keeps_the_render_where_u_trusts_it_and_the_decoding_in_the_holes(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from phigenesis.infer import generate as gen
    from phigenesis.rollout import runner

    renders: list = []
    real_with_sky = runner.with_sky

    def spy_with_sky(render, stage1, cams):  # type: ignore[no-untyped-def]
        out = real_with_sky(render, stage1, cams)
        renders.append(out)
        return out

    monkeypatch.setattr(runner, "with_sky", spy_with_sky)
    results = {}
    for paste in (0.0, 1.0):
        options = gen.GenerateOptions(steps=2, uncertainty="coverage", paste=paste)
        results[paste] = gen.generate(
            stage2_checkpoint,
            cache,
            "synthetic-s7-0000",
            2,
            5,
            tmp_path / f"p{paste:g}",
            options=options,
            progress=False,
        ).rollout
    assert len(renders) == 2  # one window each
    decoded, pasted = results[0.0], results[1.0]
    u = pasted.u  # [N, V, H, W], the same map in both runs (the same history)
    assert torch.equal(u, decoded.u)
    trusted, holes = u == 1, u == 0
    assert bool(trusted.any()) and bool(holes.any())
    full = renders[1].clamp(0, 1)  # [N, V, H, W, 3] the render over Stage 1's sky
    assert torch.equal(pasted.images[trusted], full[trusted])
    assert torch.equal(pasted.images[holes], decoded.images[holes])
    between = (u > 0.1) & (u < 0.9)
    if bool(between.any()):  # a blend: between the two, never outside them
        lo = torch.minimum(full, decoded.images)[between] - 1e-6
        hi = torch.maximum(full, decoded.images)[between] + 1e-6
        assert bool(((pasted.images[between] >= lo) & (pasted.images[between] <= hi)).all())
    # The Gaussians are those of the frames as kept: the pasted run's differ from the decoded run's.
    assert not torch.equal(pasted.windows[0].means, decoded.windows[0].means)
    with pytest.raises(ValueError, match=r"paste = -0.1: must be a number in \[0, 1\]"):
        gen.GenerateOptions(paste=-0.1)


def test_a_rollout_can_trust_its_own_windows_less_and_keep_the_gaussians_trusted_pixels_showed(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    from phigenesis.infer import generate as gen

    def run(name: str, **options: float) -> gen.Rollout:
        opts = gen.GenerateOptions(steps=1, uncertainty="coverage", **options)  # type: ignore[arg-type]
        out = tmp_path / name
        return gen.generate(
            stage2_checkpoint, cache, "synthetic-s7-0000", 2, 10, out, options=opts, progress=False
        ).rollout

    base, halved, kept = run("base"), run("half", generated_trust=0.5), run("kept", spawn_max_u=0.0)
    # Window 0 sees only the recorded history's Gaussians: trust 1, the same u and frames.
    assert torch.equal(halved.u[:5], base.u[:5]) and torch.equal(halved.images[:5], base.images[:5])
    # Window 1 also sees window 0's generated Gaussians: u scaled by the blend of 1 and 0.5.
    later, scaled = base.u[5:], halved.u[5:]
    assert bool((scaled <= later + 1e-6).all()) and bool((scaled >= 0.5 * later - 1e-6).all())
    assert bool((scaled < later - 0.1).any())
    # Spawning only where u <= 0 (coverage: the holes) adds fewer Gaussians than spawning everywhere,
    # and the written depth, rendered from the whole buffer, still covers what the render covered.
    assert len(kept.windows[0]) < len(base.windows[0])
    covered = base.u[:5] == 1
    assert bool((kept.alpha[:5][covered] > 0.5).float().mean() > 0.95)
    assert torch.isfinite(kept.images).all() and torch.isfinite(kept.depth).all()
    for bad in ({"generated_trust": 1.5}, {"spawn_max_u": -0.1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            gen.GenerateOptions(**bad)  # type: ignore[arg-type]


def test_a_rollout_can_lift_only_the_newest_frame_of_each_window_into_its_buffer(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    from phigenesis.infer import generate as gen

    def run(name: str, lift_frames: int | None) -> gen.Rollout:  # None: the history's 1 frame
        opts = gen.GenerateOptions(steps=1, uncertainty="coverage", lift_frames=lift_frames)
        out = tmp_path / name
        return gen.generate(
            stage2_checkpoint, cache, "synthetic-s7-0000", 2, 10, out, options=opts, progress=False
        ).rollout

    every, newest = run("every", 5), run("newest", None)
    # Window 0 stands on the recorded history alone: the same frames either way.
    assert torch.equal(newest.images[:5], every.images[:5])
    for w in range(2):
        last = newest.time_s[5 * w + 4]  # [V] capture times of the window's newest frame, s
        times = newest.windows[w].time_s.double()  # the static ones keep the time they were seen at
        assert len(times) > 0
        assert float((times[:, None] - last[None]).abs().min(dim=1).values.max()) < 1e-4
    # Lifting every frame adds Gaussians seen at all five frames' times, five times as many or so.
    seen = every.windows[0].time_s.double()
    frame_of = (seen[:, None] - every.time_s[:5, 0][None]).abs().argmin(dim=1)
    assert len(frame_of.unique()) == 5
    assert len(every.windows[0]) > 3 * len(newest.windows[0])
    assert torch.isfinite(newest.images).all() and torch.isfinite(newest.depth).all()
    with pytest.raises(ValueError, match="lift_frames"):
        gen.GenerateOptions(lift_frames=0)


def test_generation_refuses_bad_inputs_naming_what_is_wrong(
    cache: Path,
    stage1_checkpoint: Path,
    stage2_checkpoint: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from phigenesis.cli.generate import main as generate_main

    def run(*extra: str, ckpt: Path = stage2_checkpoint, out: str = "g") -> str:
        argv = ["--ckpt", str(ckpt), "--shards", str(cache), "--scene", "synthetic-s7-0000", "--start", "2"]
        argv += ["--frames", "5", "--out", str(tmp_path / out), "--steps", "1", "--no-progress", *extra]
        assert generate_main(argv) == 2
        return capsys.readouterr().err

    assert "not a Stage 2 denoiser" in run(ckpt=stage1_checkpoint)
    with pytest.raises(SystemExit):
        run("--lp-trust", "sure")
    assert "--lp-trust: invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run("--geometry", "lidar")
    assert "--geometry: invalid choice" in capsys.readouterr().err
    assert "'nope' is not in" in run("--scene", "nope")
    assert "runs past the end of scene" in run("--frames", "40")
    nan = _straight_trajectory(cache, 5, tmp_path / "nan.json")
    doc = json.loads(nan.read_text())
    doc["frames"][3]["world_from_ego"][0][3] = float("nan")
    nan.write_text(json.dumps(doc))
    assert "frames[3].world_from_ego" in run("--trajectory", str(nan))
    short = _straight_trajectory(cache, 4, tmp_path / "short.json")
    assert "holds 4 frames, --frames asks for 5" in run("--trajectory", str(short))
    back = _straight_trajectory(cache, 5, tmp_path / "back.json")
    doc = json.loads(back.read_text())
    doc["frames"][2]["timestamp_micros"] = doc["frames"][1]["timestamp_micros"]
    back.write_text(json.dumps(doc))
    assert "frames[2].timestamp_micros" in run("--trajectory", str(back))


def test_the_stage2_evaluation_scores_rollouts_against_the_truth(
    cache: Path, stage2_checkpoint: Path, tmp_path: Path
) -> None:
    from phigenesis.data.views import resize_images
    from phigenesis.eval.stage2 import evaluate_stage2
    from phigenesis.models.losses import psnr
    from phigenesis.rollout.runner import GenerateOptions, Stage2Runner

    class Tiny(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.adaptive_avg_pool2d(x, 4).flatten(1)  # [N, 48]

    fid_model = tmp_path / "tiny.pt"
    torch.jit.script(Tiny()).save(str(fid_model))
    options = GenerateOptions(steps=1, uncertainty="coverage")
    report = evaluate_stage2(
        stage2_checkpoint,
        cache,
        options=options,
        offsets=(2,),
        shifts_m=(1.0,),
        rollout_frames=(6,),
        fid_model=fid_model,
        out_json=tmp_path / "eval.json",
    )
    assert set(report["sections"]) == {"+2", "shift_1m", "rollout_6"}
    gen = report["sections"]["+2"]["generated"]
    assert gen["images"] == 5 and 0 <= gen["ssim"] <= 1 and gen["abs_rel"] > 0
    assert report["sections"]["shift_1m"]["generated"]["images"] == 25  # one window of 5 frames x 5 views
    assert json.loads((tmp_path / "eval.json").read_text())["clips"] == 1
    # The same rollout scored by hand: frame start + 1 against the cache's image.
    runner = Stage2Runner(stage2_checkpoint, cache)
    start = 1  # one clip per scene: the first frame with a history (clip_starts)
    result, _ = runner.run("synthetic-s7-0000", start, 2, "recorded", options)
    sample = runner.data._frame("synthetic-s7-0000", start + 1)
    truth = resize_images(sample["images"], SIZE).permute(0, 2, 3, 1)
    assert gen["psnr_db"] == pytest.approx(float(psnr(result.images[1], truth).mean()), abs=1e-4)
    rollout = report["sections"]["rollout_6"]["generated"]
    assert rollout["fid"] >= 0 and rollout["fid_images"] == 25 and math.isfinite(rollout["kid"])
    # The VAE ceiling: the true window (frames start .. start + 4) encoded and decoded as one.
    window = [
        resize_images(runner.data._frame("synthetic-s7-0000", start + j)["images"], SIZE).permute(0, 2, 3, 1)
        for j in range(runner.window)
    ]
    video = torch.stack(window).permute(0, 1, 4, 2, 3)[None]
    recon = runner.stage1.decode(runner.stage1.encode(video))[0, 1].permute(0, 2, 3, 1).clamp(0, 1)
    ceiling = report["sections"]["+2"]["vae_reconstruction"]
    assert ceiling["psnr_db"] == pytest.approx(float(psnr(recon, truth).mean()), abs=1e-4)
    assert ceiling["images"] == 5 and "abs_rel" not in ceiling
    assert report["sections"]["shift_1m"]["vae_reconstruction"]["images"] == 25
    # Rollout frame 6 sits in its second window (generated frames 5 .. 9): one frame per view; its FID
    # pools the five frames ending at 6, as the generated one does (frames 1 .. 4 reconstructed as
    # the first window, 5 as the second), x 5 views.
    rollout_ceiling = report["sections"]["rollout_6"]["vae_reconstruction"]
    assert rollout_ceiling["images"] == 5 and rollout_ceiling["fid_images"] == 25
    # --fid-frames: the FID of rollout frame 6 over the two frames ending there, for both renderers.
    short = evaluate_stage2(
        stage2_checkpoint,
        cache,
        options=options,
        offsets=(),
        shifts_m=(),
        rollout_frames=(6,),
        fid_model=fid_model,
        fid_frames=2,
    )["sections"]["rollout_6"]
    assert short["generated"]["fid_images"] == 10 and short["vae_reconstruction"]["fid_images"] == 10
    assert short["generated"]["psnr_db"] == pytest.approx(rollout["psnr_db"], abs=1e-6)
    with pytest.raises(ValueError, match="fid_frames"):
        evaluate_stage2(stage2_checkpoint, cache, options=options, rollout_frames=(6,), fid_frames=0)
