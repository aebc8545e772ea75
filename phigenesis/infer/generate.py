"""``phigenesis-generate``: Stage 2 rollouts along a trajectory, written as a cache.

A rollout (:class:`phigenesis.rollout.runner.Stage2Runner`, which describes its steps and the
trajectories it takes) generates ``frames`` frames of a scene from frame ``start`` on.

The output folder holds a cache in the project's schema (one scene, the generated frames numbered
from 0, with the recorded frame they start at in the scene's metadata: images, calibrations at the
model's size, poses, the generated Gaussians' rendered depth (dense origin ``rendered``) and class
labels (pseudo source ``rendered``)), so ``phigenesis-prep verify``, ``preview`` and the loader work
on it; ``strip.png`` (generated frames, views side by side); ``gaussians/window-KKK.ply`` (the
Gaussians each window added to the buffer); ``generate.json`` (what made it, timings).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from phigenesis.data import records
from phigenesis.data.cache_run import writing_cache
from phigenesis.data.colormap import FONT, PANEL_RGB, TEXT_RGB
from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraDepth,
    CameraImage,
    CameraSemantics,
    Frame,
    encode_rgb,
)
from phigenesis.data.schema import CacheContents, frame_schema, frame_to_batch
from phigenesis.data.shards import MANIFEST_NAME, SceneEntry, ShardInfo, ShardWriter, atomic_write_bytes
from phigenesis.export.ply import write_ply
from phigenesis.rollout.runner import HOLE_ALPHA, GenerateOptions, Rollout, Stage2Runner
from phigenesis.version import __version__

log = logging.getLogger(__name__)

#: The generated scene's id in its cache: the recorded scene's with this suffix.
GENERATED_SUFFIX = "-generated"


# --------------------------------------------------------------------------------------------
# Writing the generated scene


def generated_frames(result: Rollout, scene_id: str, calibrations: list[CameraCalibration]) -> list[Frame]:
    """The generated frames as scene-model records (the images JPEG-encoded, the rendered depth as
    the dense depth and the rendered classes as pseudo labels, no LiDAR, no boxes). The generated
    scene is a scene of its own: its frames are numbered from 0 (``frame_index``, as in every
    cache); the scene's metadata records the recorded frame it starts at (``start``)."""
    frames = []
    n, v = result.images.shape[:2]
    for i in range(n):
        traj = result.trajectory[i]
        cameras = []
        for j in range(v):
            cal = calibrations[j]
            rgb = (result.images[i, j].numpy() * 255).round().clip(0, 255).astype(np.uint8)
            depth = result.depth[i, j].numpy().astype(np.float32)
            covered = result.alpha[i, j].numpy() >= HOLE_ALPHA
            depth = np.where(covered & (depth > 0), depth, 0).astype(np.float32)
            conf = np.where(depth > 0, result.alpha[i, j].numpy().clip(0, 1), 0).astype(np.float32)
            origin = np.where(depth > 0, records.DENSE_ORIGINS.index("rendered"), 0).astype(np.uint8)
            sem = result.semantic[i, j].numpy().astype(np.uint8)
            labelled = covered
            empty = CameraDepth.empty(cal.height, cal.width)
            cameras.append(
                CameraImage(
                    calibration=cal,
                    timestamp_micros=int(traj.camera_timestamp_micros[j]),
                    world_from_ego=traj.camera_world_from_ego[j],
                    image_bytes=encode_rgb(rgb),
                    depth=CameraDepth(
                        empty.sparse_m, empty.sparse_confidence, empty.sparse_origin, depth, conf, origin
                    ),
                    pseudo=CameraSemantics(
                        np.where(labelled, sem, 255).astype(np.uint8),
                        labelled.astype(np.float32),
                        np.where(labelled, records.PSEUDO_SOURCES.index("rendered"), 0).astype(np.uint8),
                    ),
                )
            )
        frames.append(
            Frame(
                scene_id,
                i,
                traj.timestamp_micros,
                traj.world_from_ego,
                cameras,
                None,
                Boxes.empty(),
            )
        )
    return frames


#: The manifest ``pipeline`` of a generated cache: what its rows hold.
GENERATED_PIPELINE: dict[str, Any] = {
    "name": "generated",
    "output": {"camera_truth": [], "lidar": False, "depth": True, "pseudo_semantics": True},
}


def write_generated_scene(
    target: Path, frames: list[Frame], scene_id: str, metadata: dict[str, Any]
) -> tuple[SceneEntry, list[ShardInfo]]:
    """Writes ``frames`` as the shards of the generated scene ``scene_id`` in the cache folder
    ``target``: (its manifest entry, its complete shards), which the caller commits
    (:meth:`~phigenesis.data.cache_run.CacheRun.commit`)."""
    contents = CacheContents(
        camera_truth=(),
        lidar=False,
        lidar_truth=False,
        camera_labels=False,
        depth=True,
        pseudo_semantics=True,
    )
    schema = frame_schema(
        contents, {"phigenesis.source": "generated", "phigenesis.scene_metadata": json.dumps(metadata)}
    )
    with ShardWriter(target, scene_id, schema) as writer:
        for frame in frames:
            writer.write(frame_to_batch(frame, "generated", schema))
        shards = writer.close()
    return SceneEntry(scene_id, "generated", len(frames), "complete", [s.path for s in shards]), shards


def save_strip(
    result: Rollout, path: Path, camera_names: Sequence[str] = (), start: int = 0, max_rows: int = 8
) -> Path:
    """A PNG of generated frames (at most ``max_rows`` spread over the rollout, each named in a
    left margin by its frame index in the generated cache and its frame in the source scene,
    ``start`` + index), the views side by side under their camera names, each generated row
    followed by the condition render it was generated from."""
    n, views = result.images.shape[:2]
    rows = sorted(set(np.linspace(0, n - 1, min(n, max_rows)).round().astype(int).tolist()))
    h, w = result.images.shape[2:4]
    names = list(camera_names) or [f"view {j}" for j in range(views)]
    margin, scale = 150, 0.4
    lines = [_strip_header(names, w, margin, scale, f"{len(rows)} of {n} frames")]
    for i in rows:
        for kind, image in (("generated", result.images[i]), ("condition", result.condition_rgb[i])):
            body = (torch.cat(list(image), dim=1).numpy() * 255).round().clip(0, 255).astype(np.uint8)
            label = np.full((h, margin, 3), PANEL_RGB, np.uint8)
            for k, text in enumerate((f"frame {i}", f"(scene {start + i})", kind)):
                cv2.putText(label, text, (4, 14 + 16 * k), FONT, scale, TEXT_RGB, 1, cv2.LINE_AA)
            lines.append(np.concatenate([label, body], axis=1))
    picture = np.concatenate(lines, axis=0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{path}: cannot encode the strip")
    atomic_write_bytes(path, png.tobytes())
    return path


def _strip_header(names: list[str], view_width: int, margin: int, scale: float, note: str) -> np.ndarray:
    """(20, margin + V * view_width, 3) uint8: ``note`` over the margin, each camera's name over
    its column (cut to the column's width)."""
    header = np.full((20, margin + view_width * len(names), 3), PANEL_RGB, np.uint8)
    cv2.putText(header, note, (4, 14), FONT, scale, TEXT_RGB, 1, cv2.LINE_AA)
    for j, name in enumerate(names):
        while name and cv2.getTextSize(name, FONT, scale, 1)[0][0] > view_width - 6:
            name = name[:-1]
        cv2.putText(header, name, (margin + j * view_width + 3, 14), FONT, scale, TEXT_RGB, 1, cv2.LINE_AA)
    return header


# --------------------------------------------------------------------------------------------
# The entry function


@dataclass
class GenerateResult:
    """What :func:`generate` wrote, with the rollout itself (None when ``out`` already held the
    finished rollout of the same command, and nothing was generated)."""

    out: Path
    cache: Path
    strip: Path
    plys: list[Path]
    rollout: Rollout | None
    seconds: float


def generate(
    ckpt: str | os.PathLike[str],
    shards: str | os.PathLike[str],
    scene: str,
    start: int,
    frames: int,
    out: str | os.PathLike[str],
    *,
    trajectory: str = "recorded",
    stage1: str | os.PathLike[str] | None = None,
    options: GenerateOptions | None = None,
    progress: bool = True,
) -> GenerateResult:
    """Rolls out ``frames`` frames of ``scene`` from frame ``start`` on (its history: the frames just
    before) with the Stage 2 checkpoint ``ckpt`` along ``trajectory`` and writes them to ``out``
    (see the module docstring). ``stage1``: the Stage 1 checkpoint (default: the one the Stage 2
    model was trained with). Raises ValueError naming what is wrong for a scene not in the cache,
    a start without enough history, ``--frames`` past the cache's end with a recorded (or shifted)
    trajectory, or a bad trajectory file; CheckpointError for a checkpoint that is not Stage 2's;
    all before ``out`` is touched. ``out`` is written as every cache is
    (:mod:`phigenesis.data.cache_run`): under its lock (PrepError while another run writes it, or
    when it holds anything but a run of this command), the scene committed last, after its shards,
    ``strip.png``, the PLYs and ``generate.json``; a run stopped before that (killed, a full disk:
    CacheWriteError naming the file) is redone by a rerun of the same command, and a rerun of a
    finished one returns at once (``rollout`` None).

    Example::

        generate("runs/stage2/model.safetensors", "cache/", "synthetic-s7-0000", 1, 40, "gen/",
                 trajectory="shift:2m", options=GenerateOptions(omega=2.0))
    """
    t0 = time.perf_counter()
    out = Path(out)
    runner = Stage2Runner(ckpt, shards, stage1)
    options = runner.resolve(options)
    clip, traj = runner.inputs(scene, start, frames, trajectory)
    generated_id = scene + GENERATED_SUFFIX
    arguments = {
        "stage2_checkpoint": str(ckpt),
        "stage1_checkpoint": str(runner.stage1_path),
        "frame_cache": str(Path(shards).resolve()),
        "scene": scene,
        "start": start,
        "frames": frames,
        "trajectory": trajectory,
        **options.__dict__,
    }
    with writing_cache(out, "generated", arguments, GENERATED_PIPELINE, [generated_id], "generate") as run:
        if run.is_complete(generated_id):
            log.info("%s already holds this rollout (%s); nothing to do", out, generated_id)
            plys = sorted((out / "gaussians").glob("window-*.ply"))
            return GenerateResult(out, out / MANIFEST_NAME, out / "strip.png", plys, None, 0.0)
        result = runner.roll_out(clip, traj, start, options, progress)
        entry, written = write_generated_scene(
            run.target,
            generated_frames(result, generated_id, _generated_calibrations(runner, clip, start)),
            generated_id,
            {"generated_from": scene, "start": start},
        )
        strip, plys = _write_extras(out, result, list(clip.camera_names), start)
        seconds = time.perf_counter() - t0
        report = {
            **{k: v for k, v in arguments.items() if k not in options.__dict__},
            # The sampler's options apart, so its time shift is not read as the trajectory's shift.
            "sampling": {("time_shift" if k == "shift" else k): v for k, v in options.__dict__.items()},
            "windows": len(result.windows),
            "window_frames": runner.window,
            "seconds": seconds,
            "seconds_per_window": result.seconds_per_window,
            "seconds_per_frame": sum(result.seconds_per_window) / max(frames, 1),
            "buffer_sizes": result.buffer_sizes,
            "phigenesis_version": __version__,
        }
        atomic_write_bytes(out / "generate.json", json.dumps(report, indent=1, default=str).encode())
        run.commit(entry, written)  # last: a finished cache has its strip, PLYs and report
    log.info("generated %d frames of %s in %.1f s into %s", frames, scene, seconds, out)
    return GenerateResult(out, out / MANIFEST_NAME, strip, plys, result, seconds)


def _generated_calibrations(runner: Stage2Runner, clip: Any, start: int) -> list[CameraCalibration]:
    """The cameras of the generated frames: the history's rig (its last frame's extrinsics, the
    clip's intrinsics) at the Stage 1 model's image size, pinhole."""
    ego_from_camera = clip.frames[start - 1]["ego_from_camera"]
    h, w = runner.stage1.config.image_size
    names = list(clip.camera_names)
    return [
        CameraCalibration(
            names[j],
            w,
            h,
            clip.intrinsics[j].double().numpy(),
            np.zeros(5),
            ego_from_camera[j].double().numpy(),
        )
        for j in range(len(names))
    ]


def _write_extras(out: Path, result: Rollout, camera_names: list[str], start: int) -> tuple[Path, list[Path]]:
    """Writes the rollout's ``strip.png`` and ``gaussians/window-KKK.ply`` (each window's Gaussians
    added to the buffer) into ``out``; returns their paths."""
    strip = save_strip(result, out / "strip.png", camera_names, start)
    (out / "gaussians").mkdir(exist_ok=True)
    plys = [
        write_ply(g, out / "gaussians" / f"window-{i:03d}.ply")
        for i, g in enumerate(result.windows)
        if len(g)
    ]
    return strip, plys
