"""Stage 1: the range-view adapter's geometry and rules, the trainer (losses, checkpoints, exact resume,
torchrun), its clear errors, and the PLY export of a trained model."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from phigenesis import geometry, prep
from phigenesis.data.clips import Stage1Clips, clip_inputs
from phigenesis.data.pipeline import PipelineSpec
from phigenesis.data.schema import SCHEMA_VERSION
from phigenesis.data.shards import Manifest
from phigenesis.export.ply import scene_from_ply
from phigenesis.export.stage1 import export_ply, predict_frame
from phigenesis.models import create_model, list_models
from phigenesis.models.adapter import GROUND_MIN_DOWN, AdapterConfig, column_base, ground_log_depth
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.loading import load_stage1
from phigenesis.models.losses import edge_aware_smoothness
from phigenesis.models.stage1 import (
    Stage1Model,
    pixel_rays,
    quaternion_multiply,
    range_view_order,
)
from phigenesis.taxonomy import SKY
from phigenesis.train.checkpoint import CheckpointError, save_checkpoint
from phigenesis.train.runner import ProcessGroup, latest_checkpoint, read_metrics
from phigenesis.train.stage1 import (
    Stage1TrainConfig,
    VaeFeatureCache,
    _draw_clips,
    stage1_losses,
    train_stage1,
)
from tests.conftest import TINY_PREP_ARGS

SIZE = (24, 36)  # divisible by vae_tiny's 4x compression; resized from the cache's 60 x 90


def tiny_train_config(**overrides: object) -> Stage1TrainConfig:
    values: dict[str, object] = {
        "model_overrides": {"image_size": list(SIZE), "adapter": {"width": 16}},
        "steps": 4,
        "warmup_steps": 1,
        "checkpoint_every": 2,
        "target_offset": 1,
        "seed": 3,
        "threads": 1,
    }
    values.update(overrides)
    return Stage1TrainConfig(**values)  # type: ignore[arg-type]


def _rig_poses() -> torch.Tensor:
    """(5, 4, 4) camera poses of a Waymo-like rig at the origin: yaws 0, +45, -45, +90, -90 degrees
    (left positive), OpenCV camera axes, ego x forward / y left / z up."""
    ego_from_opencv = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)
    poses = []
    for yaw_deg in (0, 45, -45, 90, -90):
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = torch.from_numpy(geometry.rotation_z(math.radians(yaw_deg))) @ ego_from_opencv
        pose[:3, 3] = torch.tensor([1.5, 0.0, 2.0])
        poses.append(pose)
    return torch.stack(poses)


def _inputs(model: Stage1Model, frames: int = 1, seed: int = 0):
    h, w = model.config.image_size
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(1, frames, 5, 3, h, w, generator=g)
    k = torch.tensor([[w * 0.8, 0, (w - 1) / 2], [0, w * 0.8, (h - 1) / 2], [0, 0, 1]]).expand(1, 5, 3, 3)
    poses = _rig_poses().expand(1, frames, 5, 4, 4).clone()
    times = torch.arange(frames, dtype=torch.float32)[None, :, None].expand(1, frames, 5) * 0.1
    return images, k.clone(), poses, times


# --------------------------------------------------------------------------------------------
# Model


def test_registry_lists_stage1_variants():
    assert list_models("stage1") == ["stage1_base", "stage1_tiny"]


def test_range_view_order_is_left_to_right():
    order = range_view_order(_rig_poses())
    assert order.tolist() == [3, 1, 0, 2, 4]  # +90, +45, 0, -45, -90 degrees


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=8, max_size=8))
def test_quaternion_multiply_matches_rotation_product(values):
    a = torch.tensor(values[:4], dtype=torch.float64)
    b = torch.tensor(values[4:], dtype=torch.float64)
    if a.norm() < 1e-3 or b.norm() < 1e-3:
        return
    got = geometry.quaternion_to_matrix(quaternion_multiply(a, b).numpy())
    want = geometry.quaternion_to_matrix(a.numpy()) @ geometry.quaternion_to_matrix(b.numpy())
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_zero_initialised_head_gives_pixel_gaussians_on_the_rays():
    torch.manual_seed(0)
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    images, k, poses, times = _inputs(model)
    with torch.no_grad():
        pred = model(images, k, poses, times)
    c = model.config.adapter_config
    # Depth starts at the geometric middle of [near, far]; colours are the input pixels.
    np.testing.assert_allclose(pred.pixels.depth.numpy(), math.sqrt(c.near_m * c.far_m), rtol=1e-5)
    rgb = images.permute(0, 1, 2, 4, 5, 3).clamp(0.01, 0.99)
    np.testing.assert_allclose(pred.pixels.colour.numpy(), rgb.numpy(), atol=1e-5)
    # A pixel's centre sits on its ray: camera pose times K^-1 (u, v, 1) * z.
    v, u, cam = 5, 30, 3
    ray = torch.linalg.solve(k[0, cam].double(), torch.tensor([u, v, 1.0], dtype=torch.float64))
    want = (
        poses[0, 0, cam, :3, :3] @ (ray * pred.pixels.depth[0, 0, cam, v, u].double())
        + poses[0, 0, cam, :3, 3]
    )
    np.testing.assert_allclose(pred.means[0, 0, cam, v, u].double().numpy(), want.numpy(), atol=1e-4)
    # Identity rotation in the camera frame = the camera's rotation in the world.
    q = pred.quats[0, 0, cam, v, u].double().numpy()
    np.testing.assert_allclose(geometry.quaternion_to_matrix(q), poses[0, 0, cam, :3, :3].numpy(), atol=1e-6)
    # Scales: 0.6 pixel footprints; nothing moves.
    focal = 0.5 * (k[0, cam, 0, 0] + k[0, cam, 1, 1])
    np.testing.assert_allclose(
        pred.pixels.scale[0, 0, cam, v, u].numpy(), 0.6 * math.sqrt(c.near_m * c.far_m) / focal, rtol=1e-5
    )
    assert float(pred.velocity.abs().max()) == 0.0


def test_pixel_rays_invert_the_intrinsics():
    k = torch.tensor([[50.0, 0.5, 20.3], [0, 48.0, 11.7], [0, 0, 1]], dtype=torch.float64)
    rays = pixel_rays(k, 24, 36)  # (3, H, W)
    uv = k @ rays.reshape(3, -1)
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(36.0), indexing="ij")
    np.testing.assert_allclose(uv[0].numpy(), u.reshape(-1).double().numpy(), atol=1e-9)
    np.testing.assert_allclose(uv[1].numpy(), v.reshape(-1).double().numpy(), atol=1e-9)


def test_scene_rules_sky_spawns_nothing_and_only_dynamic_gaussians_move():
    torch.manual_seed(1)
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    with torch.no_grad():  # a random head: classes, opacities and motion vary from pixel to pixel
        model.adapter.head[-1].weight.normal_(0.0, 0.5)
        model.adapter.head[-1].bias.normal_(0.0, 0.5)
    with torch.no_grad():
        pred = model(*_inputs(model))
    logits = pred.pixels.semantic_logits[0]
    scene = pred.scene(0)
    expected = ((logits.argmax(-1) != SKY) & (pred.pixels.opacity[0] >= 1 / 255)).sum()
    assert 0 < len(scene) == int(expected) < logits[..., 0].numel()
    static = ~scene.dynamic
    assert 0 < int(static.sum()) < len(scene)
    assert float(scene.velocity[static].abs().max()) == 0.0
    assert float(scene.velocity[scene.dynamic].norm(dim=1).min()) > 0.0
    moving = pred.dynamic_prob[0] > 0.5
    assert int(scene.dynamic.sum()) == int(
        (moving & (logits.argmax(-1) != SKY) & (pred.pixels.opacity[0] >= 1 / 255)).sum()
    )
    # The soft (training) scene keeps every pixel asked for and scales velocity by the probability.
    keep = torch.ones(1, 5, *SIZE, dtype=torch.bool)
    soft = pred.scene(0, keep=keep, hard=False)
    assert len(soft) == 5 * SIZE[0] * SIZE[1]
    np.testing.assert_allclose(
        soft.velocity.numpy(),
        (pred.velocity[0] * pred.dynamic_prob[0][..., None]).reshape(-1, 3).numpy(),
        atol=1e-6,
    )


def test_clip_features_are_causal_over_frames():
    torch.manual_seed(2)
    model = create_model("stage1_tiny", image_size=list(SIZE), frames=5, adapter={"width": 16})
    images = _inputs(model, frames=5)[0]
    feats = model.features(images)
    assert [f.shape[1] for f in feats] == [5, 5, 5]
    changed = images.clone()
    changed[:, 4] = torch.rand_like(changed[:, 4])
    feats2 = model.features(changed)
    for a, b in zip(feats, feats2, strict=True):
        assert torch.equal(a[:, 0], b[:, 0])  # frame 0 never sees later frames
    assert not torch.equal(feats[-1][:, 4], feats2[-1][:, 4])


def test_render_with_per_camera_times_equals_separate_renders():
    g = torch.Generator().manual_seed(4)
    n = 300
    means = torch.randn(n, 3, generator=g) * 2 + torch.tensor([0.0, 0.0, 8.0])
    scene = GaussianScene(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(),
        scales=torch.full((n, 3), 0.1),
        opacities=torch.full((n,), 0.8),
        colors=torch.rand(n, 3, generator=g),
        semantic_logits=torch.zeros(n, 0),
        velocity=torch.randn(n, 3, generator=g),
        dynamic=torch.ones(n, dtype=torch.bool),
        time_s=torch.zeros(n),
    )
    poses = torch.eye(4).expand(2, 4, 4).clone()
    poses[1, 0, 3] = 0.5
    k = torch.tensor([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]).expand(2, 3, 3)
    both = scene.render(poses, k, 32, 24, torch.tensor([0.0, 0.3]))
    for cam, t in enumerate((0.0, 0.3)):
        one = scene.render(poses[cam : cam + 1], k[cam : cam + 1], 32, 24, t)
        torch.testing.assert_close(both.rgb[cam], one.rgb[0])
        torch.testing.assert_close(both.depth[cam], one.depth[0])


# --------------------------------------------------------------------------------------------
# Data


def test_moving_pixels_agree_with_the_truth_flow(tiny_cache):
    data = Stage1Clips(tiny_cache, (60, 90), semantic="truth")
    clip = data.clip(data.windows()[0][0], 0, [])
    sample = data.dataset[data.scenes[clip.scene_id][0]]
    speed = torch.linalg.norm(sample["truth_flow"][:, :2], dim=1)  # [V, H, W] m/s
    known = clip.context.moving[0] >= 0
    truth_moving = speed > 0.5
    agree = (clip.context.moving[0] > 0) == truth_moving
    assert known.float().mean() > 0.05  # 16-beam LiDAR over 3 frames: sparse dense depth
    assert agree[known].float().mean() > 0.97
    assert truth_moving[known].any(), "the tiny scenes should show something moving"


def test_clip_times_are_relative_to_the_first_context_frame(tiny_cache):
    data = Stage1Clips(tiny_cache, SIZE)
    scene = data.windows()[0][0]
    clip = data.clip(scene, 1, [1, -1])
    assert clip.target_indices == [1, 2, 0]
    sample = data.dataset[data.scenes[scene][2]]
    want = (sample["camera_timestamp_micros"] - clip.time_origin_micros).double() * 1e-6
    np.testing.assert_allclose(clip.targets.time_s[1].numpy(), want.numpy())
    assert clip.context.images.shape == (1, 5, 3, *SIZE)


# --------------------------------------------------------------------------------------------
# Training


def test_losses_fall_on_one_clip(tiny_cache):
    torch.manual_seed(0)
    torch.set_num_threads(1)
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    data = Stage1Clips(tiny_cache, SIZE)
    clips = [data.clip(data.windows()[0][0], 0, [1])]
    opt = torch.optim.AdamW(model.trainable_parameters(), lr=5e-3)
    first = None
    for _ in range(25):
        terms, _n = stage1_losses(model, clips)
        loss = terms["rgb"] + terms["depth"] + terms["pixel_depth"] + 0.2 * terms["semantic"]
        first = first if first is not None else {k: float(v) for k, v in terms.items()}
        opt.zero_grad()
        loss.backward()
        opt.step()
    last = {k: float(v) for k, v in terms.items()}
    assert last["pixel_depth"] < 0.6 * first["pixel_depth"]
    assert last["semantic"] < 0.8 * first["semantic"]
    assert last["rgb"] < first["rgb"]


def test_vae_stays_frozen_and_adapter_trains(tiny_cache, tmp_path):
    vae = create_model("vae_tiny")
    vae_path = save_checkpoint(tmp_path / "vae.safetensors", vae)
    run = train_stage1(
        tiny_cache, tmp_path / "run", tiny_train_config(steps=2, vae_checkpoint=str(vae_path)), progress=False
    )
    trained = load_stage1(run.checkpoint)
    for name, p in vae.state_dict().items():
        assert torch.equal(trained.vae.state_dict()[name], p), name
    fresh = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    head = "adapter.head.1.weight"
    assert not torch.equal(trained.state_dict()[head], fresh.state_dict()[head])


def test_killed_run_resumes_to_the_same_loss_curve(tiny_cache, tmp_path):
    cfg = tiny_train_config(steps=4, checkpoint_every=2)
    full = train_stage1(tiny_cache, tmp_path / "full", cfg, progress=False)
    # "Killed" after step 3: the last checkpoint is step 2, step 3's row is in the CSV already.
    train_stage1(tiny_cache, tmp_path / "cut", cfg, stop_after=3, progress=False)
    assert latest_checkpoint(tmp_path / "cut").name == "step-0000002"
    assert len(read_metrics(tmp_path / "cut")) == 3
    with pytest.raises(ValueError, match="holds a run already"):
        train_stage1(tiny_cache, tmp_path / "cut", cfg, progress=False)
    # A run made before depth_confidence_floor existed resumes as the 0 it trained with.
    recorded = tmp_path / "cut" / "config.yaml"
    old_yaml = "".join(x for x in recorded.read_text().splitlines(True) if "depth_confidence_floor" not in x)
    assert old_yaml != recorded.read_text()
    recorded.write_text(old_yaml)
    floored = tiny_train_config(steps=4, checkpoint_every=2, depth_confidence_floor=0.5)
    with pytest.raises(ValueError, match=r"fields differ: \['depth_confidence_floor'\]"):
        train_stage1(tiny_cache, tmp_path / "cut", floored, resume=True, progress=False)
    resumed = train_stage1(tiny_cache, tmp_path / "cut", cfg, resume=True, progress=False)
    a, b = read_metrics(tmp_path / "full"), read_metrics(tmp_path / "cut")
    assert [r["step"] for r in b] == [1, 2, 3, 4]
    for ra, rb in zip(a, b, strict=True):
        for key in ("loss", "rgb", "depth", "semantic", "grad_norm"):
            assert ra[key] == pytest.approx(rb[key], rel=1e-6, abs=1e-9), (ra["step"], key)
    assert full.last["loss"] == pytest.approx(resumed.last["loss"], rel=1e-6)
    sd_a, sd_b = load_stage1(full.checkpoint).state_dict(), load_stage1(resumed.checkpoint).state_dict()
    for name in sd_a:
        torch.testing.assert_close(sd_a[name], sd_b[name], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="another config"):
        train_stage1(
            tiny_cache, tmp_path / "cut", tiny_train_config(steps=4, lr=1.0), resume=True, progress=False
        )


@pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="this torch build has no torch.distributed with gloo",
)
def test_torchrun_two_cpu_processes(tiny_cache, tmp_path):
    cfg_path = tmp_path / "tiny.yaml"
    import yaml

    cfg_path.write_text(yaml.safe_dump(tiny_train_config(steps=2, batch_size=2).to_dict()))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "--master_port",
        "29533",
        "-m",
        "phigenesis.cli.train",
        "stage1",
        "--shards",
        str(tiny_cache),
        "--config",
        str(cfg_path),
        "--out",
        str(tmp_path / "ddp"),
        "--no-progress",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = read_metrics(tmp_path / "ddp")
    assert [r["step"] for r in rows] == [1, 2]
    assert load_stage1(tmp_path / "ddp" / "model.safetensors").config.image_size == SIZE


# --------------------------------------------------------------------------------------------
# Errors


def test_checkpoint_of_another_model_or_config_is_refused(tmp_path, tiny_cache):
    vae_path = save_checkpoint(tmp_path / "vae.safetensors", create_model("vae_tiny"))
    with pytest.raises(CheckpointError, match="not a Stage 1 model"):
        load_stage1(vae_path)
    wide = save_checkpoint(tmp_path / "wide.safetensors", create_model("vae_tiny", latent_channels=8))
    with pytest.raises(CheckpointError, match="latent_channels"):
        train_stage1(
            tiny_cache, tmp_path / "run", tiny_train_config(vae_checkpoint=str(wide)), progress=False
        )
    (tmp_path / "junk.safetensors").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"junk\.safetensors"):
        load_stage1(tmp_path / "junk.safetensors")


def test_cache_without_depth_or_frames_is_refused(tmp_path):
    spec = PipelineSpec(name="bare", source="synthetic", source_params={})
    bare = tmp_path / "bare"
    prep.synthetic(bare, pipeline=spec, progress=False, **{**TINY_PREP_ARGS, "scenes": 1, "frames": 1})
    with pytest.raises(ValueError, match=r"bare: the cache has no dense depth"):
        Stage1Clips(bare, SIZE)
    empty = tmp_path / "empty"
    empty.mkdir()
    Manifest(SCHEMA_VERSION, "synthetic", {}, {}, "none").save(empty)
    with pytest.raises(ValueError, match="empty: the cache holds no frames"):
        Stage1Clips(empty, SIZE)


# --------------------------------------------------------------------------------------------
# Export


def test_export_ply_of_a_trained_model(tiny_cache, tmp_path):
    run = train_stage1(tiny_cache, tmp_path / "run", tiny_train_config(steps=1), progress=False)
    scene = predict_frame(run.checkpoint, tiny_cache, 1)
    path = export_ply(run.checkpoint, tiny_cache, tmp_path / "x.ply", 1, t_s=0.0)
    back = scene_from_ply(path)
    assert len(back) == len(scene) > 0
    np.testing.assert_allclose(back.means.numpy(), scene.means_at(0.0).numpy(), rtol=1e-6, atol=1e-5)
    with pytest.raises(ValueError, match="no frame 999"):
        predict_frame(run.checkpoint, tiny_cache, 999)


def test_edge_aware_smoothness_prefers_depth_edges_at_image_edges():
    depth = torch.full((2, 12, 16), 10.0)
    image = torch.full((2, 12, 16, 3), 0.5)
    assert float(edge_aware_smoothness(depth, image)) == 0.0
    step = depth.clone()
    step[:, :, 8:] = 20.0
    flat = float(edge_aware_smoothness(step, image))
    edged = image.clone()
    edged[:, :, 8:] = 0.9  # the image has an edge where the depth steps
    at_edge = float(edge_aware_smoothness(step, edged))
    assert flat > 0 and at_edge < 0.05 * flat  # exp(-10 * 0.4) = 0.018
    # Scale-free: the whole scene twice as far costs the same.
    assert float(edge_aware_smoothness(2 * step, image)) == pytest.approx(flat, rel=1e-6)


# --------------------------------------------------------------------------------------------
# Depth bins head, latents in, checkpoints made before the bins head


def _bins_model(bins: int = 16) -> Stage1Model:
    torch.manual_seed(0)
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16, "depth_bins": bins})
    # A head that is not zero, so the outputs depend on the features and the entropy varies.
    torch.nn.init.normal_(model.adapter.head[-1].weight, std=0.05)
    return model


def test_registered_configs_classify_depth():
    assert create_model("stage1_tiny").config.adapter_config.depth_bins == 64
    assert create_model("stage1_base").config.adapter_config.depth_bins == 200


def test_latents_in_equal_images_in():
    model = _bins_model()
    images, k, poses, times = _inputs(model)
    with torch.no_grad():
        from_images = model(images, k, poses, times)
        latents = model.encode(images)
        from_latents = model.forward_latents(latents, k, poses, times, images)
        decoded = model.forward_latents(latents, k, poses, times)  # colours: the VAE's decoding
    for name in ("means", "quats", "velocity", "dynamic_prob"):
        assert torch.equal(getattr(from_images, name), getattr(from_latents, name)), name
    assert torch.equal(from_images.pixels.depth_entropy, from_latents.pixels.depth_entropy)
    # Without images, the pixel colours the adapter sees and corrects are the VAE's decoding.
    with torch.no_grad():
        explicit = model.forward_latents(latents, k, poses, times, model.decode(latents))
    assert torch.equal(decoded.means, explicit.means)
    assert torch.equal(decoded.pixels.colour, explicit.pixels.colour)
    with pytest.raises(ValueError, match="do not match latents"):
        model.forward_latents(latents, k, poses, times, images[:, :, :3])


def test_bins_head_depth_and_entropy_render():
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16, "depth_bins": 16})
    images, k, poses, times = _inputs(model)
    with torch.no_grad():
        pred = model(images, k, poses, times)
    c = model.config.adapter_config
    # The zero-initialised head: uniform bins, the geometric middle of [near, far], entropy log K.
    np.testing.assert_allclose(pred.pixels.depth.numpy(), math.sqrt(c.near_m * c.far_m), rtol=1e-5)
    np.testing.assert_allclose(pred.pixels.depth_entropy.numpy(), math.log(16), rtol=1e-5)
    scene = pred.scene(0, keep=torch.ones(pred.pixels.depth.shape[1:], dtype=torch.bool))
    out = scene.render(poses[0, 0].float(), k[0], SIZE[1], SIZE[0], 0.0, entropy=True)
    covered = out.alpha > 0.5
    assert covered.float().mean() > 0.9
    np.testing.assert_allclose(out.depth_entropy[covered].numpy(), math.log(16), rtol=1e-4)
    with pytest.raises(ValueError, match="no depth_entropy"):
        dataclasses.replace(scene, depth_entropy=None).render(
            poses[0, 0].float(), k[0], 8, 8, 0.0, entropy=True
        )


def _checkpoint_with_adapter(path: Path, out: Path, change: Callable[[dict], object]) -> Path:
    """A copy of the checkpoint at ``path`` written to ``out``, its weights as they were and its stored
    adapter config edited in place by ``change``: what an older, or a crafted, checkpoint holds."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), "pt") as f:
        header, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118
    config = json.loads(header["config"])
    change(config["adapter"])
    save_file(tensors, str(out), metadata=header | {"config": json.dumps(config)})
    return out


def _loads_without(old: Stage1Model, path: Path, tmp_path: Path, *fields: str) -> Stage1Model:
    """Loads ``old``'s checkpoint at ``path`` rewritten without the adapter config's ``fields`` (what a
    checkpoint written before them holds) and checks it predicts the same Gaussian centres."""

    def drop(adapter: dict) -> None:
        for field in fields:
            adapter.pop(field, None)

    loaded = load_stage1(_checkpoint_with_adapter(path, tmp_path / "old.safetensors", drop))
    images, k, poses, times = _inputs(loaded)
    with torch.no_grad():
        assert torch.equal(loaded(images, k, poses, times).means, old.eval()(images, k, poses, times).means)
    return loaded


def test_checkpoint_made_before_the_bins_head_still_loads(tmp_path):
    torch.manual_seed(0)
    old = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    path = save_checkpoint(tmp_path / "new.safetensors", old)
    # What a checkpoint written before the bins head holds: no depth_bins.
    loaded = _loads_without(old, path, tmp_path, "depth_bins")
    assert loaded.config.adapter_config.depth_bins == 0
    # A config that says bins with weights of the regression head: the error names the head.
    mixed = _checkpoint_with_adapter(path, tmp_path / "mixed.safetensors", lambda a: a.update(depth_bins=16))
    with pytest.raises(CheckpointError, match=r"mixed\.safetensors: weights do not fit .*adapter\.head"):
        load_stage1(mixed)


def test_losses_with_the_bins_head_and_several_targets(tiny_cache):
    cfg = tiny_train_config(
        model_overrides={"image_size": list(SIZE), "adapter": {"width": 16, "depth_bins": 16}},
        targets_per_clip=2,
    )
    model = create_model(cfg.model, **cfg.model_overrides)
    data = Stage1Clips(tiny_cache, SIZE, 1)
    clips = _draw_clips(data, cfg, 0, ProcessGroup(0, 1))
    assert len(clips[0].target_indices) == 1 + 2
    assert len(set(clips[0].target_indices)) == 3 or data.scene_length(clips[0].scene_id) < 4
    terms, _ = stage1_losses(model, clips)
    # Uniform bins at the start: the cross-entropy is log K wherever the cache has depth.
    np.testing.assert_allclose(float(terms["depth_ce"]), math.log(16), rtol=1e-4)
    assert 0 < float(terms["target_semantic"]) < 20
    with pytest.raises(ValueError, match="targets_per_clip"):
        tiny_train_config(targets_per_clip=3)  # target_offset 1: only 2 distinct frames


def test_the_depth_confidence_floor_weighs_every_depth_term(tiny_cache):
    """Floor 1 weighs every dense-depth target alike: the three depth terms equal those of the same
    clips with every confidence set to 1, and differ from the cache's weighting (floor 0); the
    other terms do not change. Values outside [0, 1] are refused."""
    from phigenesis.train.stage1 import depth_target_weight

    cfg = tiny_train_config(
        model_overrides={"image_size": list(SIZE), "adapter": {"width": 16, "depth_bins": 16}},
        targets_per_clip=2,
    )
    torch.manual_seed(0)
    model = create_model(cfg.model, **cfg.model_overrides)
    torch.nn.init.normal_(model.adapter.head[-1].weight, std=0.05)  # depths that vary per pixel
    clips = _draw_clips(Stage1Clips(tiny_cache, SIZE, 1), cfg, 0, ProcessGroup(0, 1))

    def sure(views):
        return dataclasses.replace(views, depth_confidence=torch.ones_like(views.depth_confidence))

    confidence = clips[0].context.depth_confidence[clips[0].context.depth > 0]
    assert float(confidence.min()) < 0.5 < float(confidence.max())  # the cache's weights vary
    uniform = [dataclasses.replace(c, context=sure(c.context), targets=sure(c.targets)) for c in clips]
    with torch.no_grad():
        as_is, floored, ones = (
            stage1_losses(model, c, None, f)[0] for c, f in ((clips, 0.0), (clips, 1.0), (uniform, 0.0))
        )
    for name in ("depth", "pixel_depth", "depth_ce"):
        assert float(floored[name]) == pytest.approx(float(ones[name]), rel=1e-6), name
        assert float(floored[name]) != pytest.approx(float(as_is[name]), rel=1e-3), name
    for name in ("rgb", "semantic", "target_semantic"):
        assert float(floored[name]) == float(as_is[name]), name
    weight = depth_target_weight(torch.tensor([0.0, 0.2, 1.0]), 0.5)
    torch.testing.assert_close(weight, torch.tensor([0.5, 0.6, 1.0]))
    for bad in (-0.1, 1.5, float("nan"), True, "0.5"):
        with pytest.raises(ValueError, match=r"depth_confidence_floor = \S+: must be a number in \[0, 1\]"):
            tiny_train_config(depth_confidence_floor=bad)


def test_time_limit_ends_the_run_with_its_weights(tiny_cache, tmp_path):
    run = train_stage1(
        tiny_cache, tmp_path / "run", tiny_train_config(steps=50), progress=False, time_limit_s=0.0
    )
    assert run.stopped_by_time and run.steps_done == 1
    assert run.checkpoint is not None and run.checkpoint.is_file()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] == 1 and summary["planned_steps"] == 50 and summary["stopped_by_time"]
    assert load_stage1(run.checkpoint).config.image_size == SIZE


@settings(max_examples=25, deadline=None)
@given(
    st.floats(-0.3, 0.3),  # pitch, radians (down positive)
    st.floats(-0.2, 0.2),  # roll
    st.floats(-3.1, 3.1),  # yaw
    st.floats(0.5, 3.0),  # camera height above the ground, metres
)
def test_ground_prior_plus_log_height_is_the_grounds_log_depth(pitch, roll, yaw, height):
    """A camera ``height`` above a level ground (world z = 0), pitched, rolled and yawed: where a ray
    meets the ground (found by intersecting it in the world frame), its camera z-depth's log equals
    the prior + log(height); rays that never meet it get the cap."""
    h, w = 12, 18
    k = torch.tensor([[14.0, 0.0, 8.5], [0.0, 14.0, 5.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    ego_from_opencv = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)
    rot = (
        torch.from_numpy(geometry.rotation_z(yaw)) @ _rotation_y(pitch) @ _rotation_x(roll) @ ego_from_opencv
    )
    rays = pixel_rays(k, h, w)  # (3, H, W), camera z = 1
    prior = ground_log_depth(rays, rot[2])[0]  # world up in the camera frame: row 2
    dirs = torch.einsum("ij,jhw->ihw", rot, rays)  # world-frame directions, camera z = 1
    hits = dirs[2] < -GROUND_MIN_DOWN
    z_at_ground = height / -dirs[2][hits]  # the ray parameter at the ground = camera z (z = 1 rays)
    np.testing.assert_allclose(
        prior[hits].numpy(), (torch.log(z_at_ground) - math.log(height)).numpy(), atol=1e-9
    )
    np.testing.assert_allclose(prior[~hits].numpy(), -math.log(GROUND_MIN_DOWN), rtol=1e-12)


def test_ground_feature_model_runs_and_old_configs_lack_it(tmp_path):
    torch.manual_seed(0)
    plain = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    assert not plain.config.adapter_config.ground_feature
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16, "ground_feature": True})
    images, k, poses, times = _inputs(model)
    with torch.no_grad():
        torch.nn.init.normal_(model.adapter.head[-1].weight, std=0.05)
        pred = model(images, k, poses, times)
        latents = model.encode(images)
        assert torch.equal(model.forward_latents(latents, k, poses, times, images).means, pred.means)
    assert torch.isfinite(pred.means).all()
    # The prior reaches the head: tilting the rig (same images and rays) changes the depth.
    tilted = poses.clone()
    tilted[..., :3, :3] = _rotation_y(0.2) @ poses[..., :3, :3]
    with torch.no_grad():
        assert not torch.allclose(model(images, k, tilted, times).pixels.depth, pred.pixels.depth)
        assert torch.allclose(
            plain(images, k, tilted, times).pixels.depth, plain(images, k, poses, times).pixels.depth
        )
    feats = [f[:, 0] for f in model.features(images)]  # [B, V, C, h, w] per level
    with pytest.raises(ValueError, match="up_camera"):
        model.adapter(feats, images[:, 0], pixel_rays(k[0], *SIZE), k[0, :, 0, 0])


def _rotation_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)


def _rotation_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def test_column_base_carries_the_ground_prior_up_to_what_stands_on_it():
    """A column (bottom to top): ground, ground, facade x 3, sky; a hard gate gives the facade its
    base's prior (the top ground pixel), the ground its own; a column with no ground gets the far
    cap; a soft gate mixes linearly."""
    prior = torch.tensor([[4.6], [1.0], [1.2], [1.4], [0.5], [0.2]])  # (H=6, W=1), top row first
    gate = torch.tensor([[0.0], [0.0], [0.0], [0.0], [1.0], [1.0]])  # the two bottom rows are ground
    base = column_base(prior, gate)
    assert base[:, 0].tolist() == pytest.approx([0.5, 0.5, 0.5, 0.5, 0.5, 0.2])
    no_ground = column_base(prior, torch.zeros_like(gate))
    np.testing.assert_allclose(no_ground.numpy(), -math.log(GROUND_MIN_DOWN))
    half = column_base(prior, torch.full_like(gate, 0.5))
    far = -math.log(GROUND_MIN_DOWN)
    want = far
    expected = []
    for g_prior in prior[:, 0].flip(0).tolist():  # bottom-up recurrence by hand
        want = 0.5 * g_prior + 0.5 * want
        expected.append(want)
    np.testing.assert_allclose(half[:, 0].numpy(), expected[::-1], rtol=1e-6)


def test_column_base_from_the_bottom_row_bounds_what_runs_off_the_image():
    """With ``floor="bottom_row"`` a pixel with no ground below it takes the bottom row's prior (the
    nearest ground the column shows), where ``"far"`` gave it the farthest; above the first ground
    pixel both agree, and an unknown floor is refused."""
    # Column 0: a car from the bottom row up to row 2, ground above it (rows 1), sky; column 1: all
    # ground; column 2: nothing is ground.
    prior = torch.tensor([[4.6, 0.9, 4.6], [1.5, 1.0, 1.5], [0.6, 0.6, 0.6], [0.4, 0.4, 0.4]])
    gate = torch.tensor([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    bottom = column_base(prior, gate, "bottom_row")
    far = column_base(prior, gate, "far")
    cap = -math.log(GROUND_MIN_DOWN)
    assert bottom[:, 0].tolist() == pytest.approx([1.5, 1.5, 0.4, 0.4])  # the car: its bottom row's prior
    assert far[:, 0].tolist() == pytest.approx([1.5, 1.5, cap, cap])
    assert torch.equal(bottom[:, 1], prior[:, 1]) and torch.equal(far[:, 1], prior[:, 1])
    assert bottom[:, 2].tolist() == pytest.approx([0.4] * 4)
    with pytest.raises(ValueError, match="floor must be one of"):
        column_base(prior, gate, "top")
    with pytest.raises(ValueError, match="column_floor = 'top': must be one of 'far', 'bottom_row'"):
        AdapterConfig(ground_feature=True, column_base=True, column_floor="top")


def test_column_base_model_outputs_the_gate_and_trains_it(tiny_cache):
    adapter = {"width": 16, "depth_bins": 16, "ground_feature": True, "column_base": True}
    cfg = tiny_train_config(
        model_overrides={"image_size": list(SIZE), "adapter": adapter}, weights={"ground": 1.0}
    )
    model = create_model(cfg.model, **cfg.model_overrides)
    data = Stage1Clips(tiny_cache, SIZE, 1)
    clips = _draw_clips(data, cfg, 0, ProcessGroup(0, 1))
    terms, _ = stage1_losses(model, clips)
    # An untrained gate says 0.5 everywhere: the cross-entropy is log 2.
    assert 0.3 < float(terms["ground"]) < 1.2
    terms["ground"].backward()
    assert model.adapter.ground_gate[-1].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="column_base needs ground_feature"):
        create_model("stage1_tiny", adapter={"column_base": True})


def test_prior_gain_pulls_the_bins_to_the_ground_priors_depth():
    """With the bin logits flat and a gain of 1, the bins are a Gaussian one bin wide around the depth
    the prior gives (base + log height): the expected log depth lands on it; over flat logits even the
    untrained gain puts it there."""
    from phigenesis.models.adapter import PRIOR_GAIN_OFFSET, RangeViewAdapter

    cfg = AdapterConfig(width=16, depth_bins=64, ground_feature=True, column_base=True)
    adapter = RangeViewAdapter(cfg)
    base = torch.tensor([[[[0.4, 1.7, 3.1]]]])  # (N=1, V=1, H=1, W=3): ground at 3-44 m for h = 2 m
    raw = torch.zeros(1, 1, 1, 3, cfg.out_channels)
    rgb = torch.full((1, 1, 1, 3, 3), 0.5)
    flat = adapter._activate(raw, rgb, torch.tensor([50.0]), base)
    # Untrained (gain 0.31 over flat logits): the bins already sit at the prior's depth.
    want = torch.exp(base + math.log(2.0))
    np.testing.assert_allclose(flat.depth.detach().numpy(), want.numpy(), rtol=1e-2)
    raw[..., -1] = PRIOR_GAIN_OFFSET + math.log(math.e - 1)  # softplus -> gain 1
    pulled = adapter._activate(raw, rgb, torch.tensor([50.0]), base)
    np.testing.assert_allclose(pulled.depth.detach().numpy(), want.numpy(), rtol=1e-3)


def test_checkpoint_made_before_the_ground_prior_loads_as_it_was(tmp_path):
    """A stage1_tiny checkpoint written before the ground prior has no ``ground_feature`` /
    ``column_base`` in its adapter config: it rebuilds without them; one whose config claims them
    over weights without them fails naming the tensors that do not fit."""
    torch.manual_seed(0)
    old = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16, "depth_bins": 16})
    path = save_checkpoint(tmp_path / "new.safetensors", old)
    loaded = _loads_without(old, path, tmp_path, "ground_feature", "column_base", "column_floor")
    assert not loaded.config.adapter_config.ground_feature
    claims = _checkpoint_with_adapter(
        path, tmp_path / "claims.safetensors", lambda a: a.update(ground_feature=True, column_base=True)
    )
    with pytest.raises(CheckpointError, match=r"claims\.safetensors: weights do not fit .*adapter\."):
        load_stage1(claims)


def test_checkpoint_made_before_the_column_floor_loads_as_it_was(tmp_path):
    """A checkpoint whose adapter has ``column_base`` but no ``column_floor`` (written before the
    choice) rebuilds with the floor it was trained with, "far", and renders as it did; the
    registered configs start from the bottom row; an unknown floor fails naming the file and field."""
    assert create_model("stage1_tiny").config.adapter_config.column_floor == "bottom_row"
    torch.manual_seed(0)
    adapter = {
        "width": 16,
        "depth_bins": 16,
        "ground_feature": True,
        "column_base": True,
        "column_floor": "far",
    }
    old = create_model("stage1_tiny", image_size=list(SIZE), adapter=adapter)
    torch.nn.init.normal_(old.adapter.head[-1].weight, std=0.05)  # the floor must matter to the output
    path = save_checkpoint(tmp_path / "new.safetensors", old)
    loaded = _loads_without(old, path, tmp_path, "column_floor")
    assert loaded.config.adapter_config.column_floor == "far"
    images, k, poses, times = _inputs(loaded)
    with torch.no_grad():
        want = old.eval()(images, k, poses, times).means
        bottom = create_model(
            "stage1_tiny", image_size=list(SIZE), adapter=adapter | {"column_floor": "bottom_row"}
        )
        bottom.load_state_dict(old.state_dict())
        assert not torch.equal(bottom.eval()(images, k, poses, times).means, want)
    bad = _checkpoint_with_adapter(
        path, tmp_path / "bad.safetensors", lambda a: a.update(column_floor="sideways")
    )
    said = r"bad\.safetensors: .*column_floor = 'sideways': must be one of"
    with pytest.raises(CheckpointError, match=said):
        load_stage1(bad)


def _drop_group_norms(module: torch.nn.Module) -> None:
    """Replaces every GroupNorm under ``module`` by the identity, in place."""
    for name, child in module.named_children():
        if isinstance(child, torch.nn.GroupNorm):
            setattr(module, name, torch.nn.Identity())
        else:
            _drop_group_norms(child)


def test_context_blocks_start_as_the_identity_and_widen_what_a_pixel_sees():
    """Zero-initialised, the context blocks change nothing; trained (random weights), a pixel of the
    fused map depends on coarse cells 25 columns away, which without them it cannot see (a 1x1
    lateral and one 3x3 block per level reach about two coarse cells; the convolutions' reach is
    measured with the GroupNorms taken out, whose statistics span the whole map)."""
    from phigenesis.models.adapter import RangeViewAdapter

    torch.manual_seed(0)
    cfg = AdapterConfig(width=16, context_blocks=4)
    adapter = RangeViewAdapter(cfg)
    plain = RangeViewAdapter(dataclasses.replace(cfg, context_blocks=0))
    plain.load_state_dict({k: v for k, v in adapter.state_dict().items() if not k.startswith("context.")})
    feats = [torch.randn(1, c, 6 * 2**i, 40 * 2**i) for i, c in enumerate(cfg.feature_channels)]
    with torch.no_grad():
        assert torch.equal(adapter.fuse(feats), plain.fuse(feats))
        for block in adapter.context:
            torch.nn.init.normal_(block.body[-1].weight, std=0.1)

    def reach(model: RangeViewAdapter) -> Tensor:
        """|d (fused map's left column) / d coarse input| summed over channels and rows, per column."""
        coarse = feats[0].clone().requires_grad_(True)
        model.fuse([coarse, *feats[1:]])[..., 0].sum().backward()
        return coarse.grad.abs().sum(dim=(0, 1, 2))

    for model in (adapter, plain):  # GroupNorm's statistics tie every pixel to every other one
        _drop_group_norms(model)
    wide, narrow = reach(adapter), reach(plain)
    assert float(wide[25]) > 0 and float(narrow[25]) == 0
    assert float(narrow[:2].sum()) > 0 and float(narrow[3:].sum()) == 0
    with pytest.raises(ValueError, match=r"context_blocks = -1: must be an integer in \[0, 64\]"):
        AdapterConfig(context_blocks=-1)


def test_checkpoint_made_before_the_context_blocks_loads_as_it_was(tmp_path):
    """An adapter config without ``context_blocks`` (written before them) rebuilds without them and
    predicts as it did; one whose config claims them over weights without them fails naming the
    tensors."""
    assert create_model("stage1_tiny").config.adapter_config.context_blocks == 4
    torch.manual_seed(0)
    old = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16, "depth_bins": 16})
    torch.nn.init.normal_(old.adapter.head[-1].weight, std=0.05)
    path = save_checkpoint(tmp_path / "new.safetensors", old)
    loaded = _loads_without(old, path, tmp_path, "context_blocks")
    assert loaded.config.adapter_config.context_blocks == 0
    claims = _checkpoint_with_adapter(
        path, tmp_path / "claims.safetensors", lambda a: a.update(context_blocks=2)
    )
    with pytest.raises(CheckpointError, match=r"claims\.safetensors: weights do not fit .*adapter\.context"):
        load_stage1(claims)


def test_checkpoint_made_before_the_head_kernel_loads_as_it_was(tmp_path):
    """An adapter config without ``head_kernel`` (written when the head's last layer was always 3x3)
    rebuilds with a 3x3 layer and predicts as it did; a config that claims a 1x1 layer over 3x3
    weights fails naming the head; an even or zero kernel is refused."""
    assert create_model("stage1_tiny").config.adapter_config.head_kernel == 3
    torch.manual_seed(0)
    adapter = {"width": 16, "depth_bins": 16, "head_kernel": 3}
    old = create_model("stage1_tiny", image_size=list(SIZE), adapter=adapter)
    torch.nn.init.normal_(old.adapter.head[-1].weight, std=0.05)
    path = save_checkpoint(tmp_path / "new.safetensors", old)
    loaded = _loads_without(old, path, tmp_path, "head_kernel")
    assert loaded.adapter.head[-1].kernel_size == (3, 3)
    claims = _checkpoint_with_adapter(
        path, tmp_path / "claims.safetensors", lambda a: a.update(head_kernel=1)
    )
    with pytest.raises(CheckpointError, match=r"claims\.safetensors: weights do not fit .*adapter\.head"):
        load_stage1(claims)
    for bad, said in (
        (0, r"head_kernel = 0: must be an integer in \[1, 31\]"),
        (2, "head_kernel must be odd"),
    ):
        with pytest.raises(ValueError, match=said):
            AdapterConfig(head_kernel=bad)


def test_a_split_head_reads_depth_from_a_pixels_own_features_and_keeps_the_output_order(tmp_path):
    """With ``depth_head_kernel`` 1 and ``head_kernel`` 3 the depth outputs (residual, bin logits,
    prior gain) come from a 1x1 layer of their own: the model predicts exactly what one 3x3 layer
    predicts whose depth rows hold those 1x1 weights at the centre tap and zeros around it, so the
    channels keep their order; zero-initialised, it starts where the unsplit head starts. A
    checkpoint made before the field rebuilds unsplit; one claiming a split over unsplit weights
    fails naming ``depth_out``."""
    assert create_model("stage1_tiny").config.adapter_config.depth_head_kernel is None
    torch.manual_seed(0)
    adapter = {"width": 16, "depth_bins": 16, "ground_feature": True, "column_base": True}
    split = create_model("stage1_tiny", image_size=list(SIZE), adapter={**adapter, "depth_head_kernel": 1})
    plain = create_model("stage1_tiny", image_size=list(SIZE), adapter={**adapter, "depth_head_kernel": None})
    c = split.config.adapter_config
    assert c.split_head and not plain.config.adapter_config.split_head
    assert split.adapter.depth_out.kernel_size == (1, 1) and split.adapter.head[-1].kernel_size == (3, 3)
    images, k, poses, times = _inputs(split)
    shared = {
        k: v
        for k, v in split.state_dict().items()
        if not k.startswith(("adapter.head.1.", "adapter.depth_out."))
    }
    assert not plain.load_state_dict(shared, strict=False).unexpected_keys  # all but the last layers
    with torch.no_grad():
        assert torch.equal(split(images, k, poses, times).means, plain(images, k, poses, times).means)
        torch.nn.init.normal_(split.adapter.head[-1].weight, std=0.05)
        torch.nn.init.normal_(split.adapter.head[-1].bias, std=0.05)
        torch.nn.init.normal_(split.adapter.depth_out.weight, std=0.05)
        torch.nn.init.normal_(split.adapter.depth_out.bias, std=0.05)
        last = plain.adapter.head[-1]
        rest, depth = split.adapter.head[-1], split.adapter.depth_out
        first_bin = c.out_channels - c.depth_channels + 1  # after the residual and the others
        rows = torch.cat([torch.arange(1), torch.arange(first_bin, c.out_channels)])
        others = torch.arange(1, first_bin)
        last.weight.zero_()
        last.weight[rows, :, 1, 1] = depth.weight[:, :, 0, 0]
        last.weight[others] = rest.weight
        last.bias[rows] = depth.bias
        last.bias[others] = rest.bias
        a, b = split(images, k, poses, times), plain(images, k, poses, times)
        for name in ("depth", "opacity", "scale", "colour", "semantic_logits", "depth_logits"):
            torch.testing.assert_close(getattr(a.pixels, name), getattr(b.pixels, name), rtol=1e-5, atol=1e-5)
    path = save_checkpoint(tmp_path / "plain.safetensors", plain)
    loaded = _loads_without(plain, path, tmp_path, "depth_head_kernel")
    assert not loaded.config.adapter_config.split_head
    claims = _checkpoint_with_adapter(
        path, tmp_path / "claims.safetensors", lambda a: a.update(depth_head_kernel=1)
    )
    fits = r"claims\.safetensors: weights do not fit .*adapter\.depth_out"
    with pytest.raises(CheckpointError, match=fits):
        load_stage1(claims)
    for bad, said in (
        (0, "depth_head_kernel = 0: must be an integer in"),
        (2, "depth_head_kernel must be odd"),
    ):
        with pytest.raises(ValueError, match=said):
            AdapterConfig(depth_head_kernel=bad)


def test_the_clip_and_vae_feature_caches_change_no_result(tiny_cache, tmp_path):
    runs = {}
    for name, mb in (("plain", 0.0), ("cached", 64.0)):
        runs[name] = train_stage1(
            tiny_cache, tmp_path / name, tiny_train_config(steps=6, cache_mb=mb), progress=False
        )
    a, b = read_metrics(tmp_path / "plain"), read_metrics(tmp_path / "cached")
    for ra, rb in zip(a, b, strict=True):
        for key in ("loss", "rgb", "depth", "pixel_depth", "semantic", "grad_norm"):
            assert ra[key] == rb[key], (ra["step"], key)
    sd_a, sd_b = (load_stage1(r.checkpoint).state_dict() for r in (runs["plain"], runs["cached"]))
    for name in sd_a:
        assert torch.equal(sd_a[name], sd_b[name]), name
    # A run may resume with another cache size: it changes how the run uses memory, not its results.
    train_stage1(
        tiny_cache, tmp_path / "cached", tiny_train_config(steps=6, cache_mb=0.0), resume=True, progress=False
    )
    with pytest.raises(ValueError, match=r"cache_mb = -1.0: must be a number in \[0, "):
        tiny_train_config(cache_mb=-1.0)


def test_kept_clips_and_vae_features_equal_fresh_ones(tiny_cache):
    model = create_model("stage1_tiny", image_size=list(SIZE), adapter={"width": 16})
    fresh, kept = Stage1Clips(tiny_cache, SIZE), Stage1Clips(tiny_cache, SIZE, cache_mb=16.0)
    scene = next(iter(fresh.scenes))
    for offsets in ([1], [1], [-1, 1]):
        a, b = fresh.clip(scene, 1, offsets), kept.clip(scene, 1, offsets)
        for part in ("context", "targets"):
            for f in dataclasses.fields(a.context):
                assert torch.equal(getattr(getattr(a, part), f.name), getattr(getattr(b, part), f.name)), (
                    part,
                    f.name,
                )
        assert torch.equal(a.intrinsics, b.intrinsics) and a.time_origin_micros == b.time_origin_micros
    # Frame 1 as context and frame 2 as a target: made once, then found twice; frame 0 as a target
    # is new in the third clip.
    assert kept.prepared.hits == 4 and kept.prepared.misses == 3
    assert 0 < kept.prepared.bytes <= 16 * 2**20
    cache = VaeFeatureCache(model, 2**30)
    clips = [kept.clip(scene, 0, [1]), kept.clip(scene, 1, [1]), kept.clip(scene, 0, [2])]
    images = clip_inputs(clips)[0]
    got = cache(clips, images)
    want = model.features(images)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-6)
    assert cache.kept.hits == 1 and cache.kept.misses == 2  # the third clip has the first's context
    pred_kept = model(*clip_inputs(clips), got)
    pred_fresh = model(*clip_inputs(clips))
    torch.testing.assert_close(pred_kept.means, pred_fresh.means, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="do not match images"):
        model(*clip_inputs(clips[:2]), got)
