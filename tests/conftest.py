"""Shared fixtures: tiny synthetic configurations and a small cache built once per session."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from phigenesis.data.sources.synthetic import SyntheticConfig
from phigenesis.data.sources.synthetic.rigs import LidarSpec

# A suite started in the background of a non-interactive shell inherits SIGINT ignored, which Python
# then leaves ignored (no KeyboardInterrupt) in itself and in every command it starts: the Ctrl-C
# tests would fail for the launcher's sake. Restore Python's handler (children then get the default).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

#: A LiDAR small enough for fast tests (16 beams x 256 columns).
TINY_LIDAR = LidarSpec(beams=16, columns=256, sectors=8)


def tiny_config(**overrides: object) -> SyntheticConfig:
    """A synthetic config that renders a frame in well under a second (60 x 90 images)."""
    values: dict[str, object] = {
        "scenes": 2,
        "frames": 3,
        "seed": 7,
        "height": 60,
        "width": 90,
        "lidar": TINY_LIDAR,
    }
    values.update(overrides)
    return SyntheticConfig(**values)  # type: ignore[arg-type]


#: The arguments of the session cache, as passed to phigenesis.prep.synthetic.
TINY_PREP_ARGS: dict[str, object] = {
    "scenes": 2,
    "frames": 3,
    "seed": 7,
    "height": 60,
    "width": 90,
    "lidar": {"beams": 16, "columns": 256, "sectors": 8},
}


@pytest.fixture(scope="session")
def tiny_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache of 2 scenes x 3 frames built with the default pipeline (read-only for tests)."""
    from phigenesis import prep

    out = tmp_path_factory.mktemp("tiny_cache")
    prep.synthetic(out, progress=False, **TINY_PREP_ARGS)  # type: ignore[arg-type]
    return out


#: The synthetic nuScenes export shared by the nuScenes tests: one scene of 3 keyframes (13 camera
#: steps at 12 Hz, 21 LiDAR sweeps at 20 Hz), 96 x 160 images, with CAM_BACK's step-3 sweep dropped.
NUSCENES_CONFIG = tiny_config(scenes=1, height=96, width=160)
NUSCENES_KEYFRAMES = 3
NUSCENES_DROPPED = ("CAM_BACK", 3)


@pytest.fixture(scope="session")
def nuscenes_dataroot(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The dataroot of the shared nuScenes export (read-only for tests)."""
    from phigenesis.data.sources.synthetic.nuscenes_export import export_nuscenes

    root = tmp_path_factory.mktemp("nuscenes")
    export_nuscenes(NUSCENES_CONFIG, root, keyframes=NUSCENES_KEYFRAMES, dropped=[NUSCENES_DROPPED])
    return root


def one_scene_cache(
    tmp_path_factory: pytest.TempPathFactory, name: str, frames: int, size_hw: tuple[int, int]
) -> Path:
    """A one-scene cache of the tiny synthetic scene (seed 7) at ``size_hw``, one thread."""
    import torch

    from phigenesis import prep

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp(name)
    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": frames, "height": size_hw[0], "width": size_hw[1]}
    prep.synthetic(out, progress=False, **args)  # type: ignore[arg-type]
    return out


def two_step_stage1(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The checkpoint of a 2-step Stage 1 run on ``cache`` (an untrained but real model)."""
    from phigenesis.train.stage1 import Stage1TrainConfig, train_stage1

    run = train_stage1(
        cache,
        tmp_path_factory.mktemp("s1"),
        Stage1TrainConfig(steps=2, warmup_steps=1, threads=1),
        progress=False,
    )
    assert run.checkpoint is not None
    return run.checkpoint


def stage2_latents(cache: Path, stage1: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The Stage 2 latent cache of ``cache`` (windows every 3 frames) under the Stage 1 checkpoint
    ``stage1``."""
    from phigenesis.models.loading import load_stage1
    from phigenesis.rollout.config import Stage2DataConfig
    from phigenesis.train.stage2_data import precompute_stage2

    out = tmp_path_factory.mktemp("lat") / "latents"
    model = load_stage1(stage1)
    return precompute_stage2(cache, out, model, Stage2DataConfig(stride=3), stage1_checkpoint=str(stage1))
