"""Evaluation of a trained Stage 2 model on held-out synthetic scenes: ``phigenesis-eval stage2``.

On synthetic scenes the truth of every future frame and of every shifted camera exists, so the
rollouts are scored against it (peers can only report FID). Per clip (frame ``T`` of a scene as
the history, the rollout from ``T + 1`` on), sections:

- ``+5``, ``+10`` (``offsets``): the generated frames ``T + k`` of a rollout along the recorded
  trajectory against the cache's images of those frames (the paper's cross-temporal table);
- ``shift_1m``, ``shift_2m``, ``shift_4m`` (``shifts_m``): the first window of a rollout along the
  recorded trajectory moved d metres to the ego's left, against the synthetic renderer's exact
  images of those cameras (the NVS table). Frames where the shifted rig would collide with a
  labelled road user (:func:`~phigenesis.eval.stage1.shift_collision`) are not scored
  (``skipped_frames``): their truth is the inside of that road user;
- ``rollout_50`` .. ``rollout_200`` (``rollout_frames``): one long rollout per scene from its first
  frame with a history; the generated frame ``start + k - 1`` against the true one (PSNR, SSIM),
  and, over all scenes, FID and KID between the generated frames ending there (``fid_frames`` of
  them, default one window's) and the true frames of the same times (with ``fid_model``, a local
  TorchScript Inception: :mod:`phigenesis.eval.fid`); the VAE ceiling's over the same frames.
  Scenes shorter than ``k`` frames after their start skip ``k``.

Every section scores three renderers: ``generated`` (the rollout: the VAE's decoding of the
generated latents; depth from the Gaussians Stage 1 builds of them), ``render_only`` (the
history's Stage 1 Gaussians rendered at the same cameras, Stage 1's sky behind: the ablation row
"render only, no diffusion") and ``vae_reconstruction`` (the true frames of the same window
encoded and decoded by the frozen VAE, as a generated window is decoded: the ceiling of anything
generated in the VAE's latent space; no depth). Depth is scored under the standard protocol
(:mod:`phigenesis.eval.depth_protocol`) against the synthetic truth depth.

Units: PSNR in dB on RGB in [0, 1] at the Stage 1 model's size; depth in metres.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from phigenesis.data.frame_truth import frame_truth
from phigenesis.data.views import resize_images
from phigenesis.eval.depth_protocol import DepthAccumulator
from phigenesis.eval.fid import fid, image_features, kid, load_feature_extractor
from phigenesis.eval.stage1 import SyntheticTruth, shift_collision, shifted_views
from phigenesis.models.losses import psnr, ssim
from phigenesis.rollout.conditions import TargetCameras, history_scene, render_condition, with_sky
from phigenesis.rollout.runner import GenerateOptions, Rollout, Stage2Runner

log = logging.getLogger(__name__)

RENDERERS = ("generated", "render_only", "vae_reconstruction")


@dataclass
class _Scores:
    """Running scores of one section for one renderer."""

    psnr_db: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    depth: DepthAccumulator = field(default_factory=lambda: DepthAccumulator(()))
    skipped_frames: int = 0  # shifted frames not scored: the shifted rig would collide

    def add(self, rgb: Tensor, truth_rgb: Tensor, depth: Tensor | None, truth_depth: Tensor | None) -> None:
        """``rgb``, ``truth_rgb`` [N, H, W, 3] in [0, 1]; depths [N, H, W] metres (0 = none)."""
        self.psnr_db += psnr(rgb.clamp(0, 1).float(), truth_rgb.float()).tolist()
        self.ssim += ssim(rgb.clamp(0, 1).float(), truth_rgb.float()).mean(dim=(-2, -1)).tolist()
        if depth is not None and truth_depth is not None:
            self.depth.add(depth.numpy(), truth_depth.numpy())

    def summary(self) -> dict[str, float]:
        out = {"psnr_db": float(np.mean(self.psnr_db)) if self.psnr_db else math.nan}
        out["ssim"] = float(np.mean(self.ssim)) if self.ssim else math.nan
        out["images"] = float(len(self.psnr_db))
        out["skipped_frames"] = float(self.skipped_frames)
        if self.depth.images():
            d = self.depth.image_mean()["all"]
            out |= {"abs_rel": d.abs_rel, "rmse_m": d.rmse_m, "delta_1_25": d.delta_1_25}
        return out


def _section_name(kind: str, value: float) -> str:
    if kind == "offset":
        return f"{int(value):+d}"
    if kind == "shift":
        return f"shift_{value:g}m"
    return f"rollout_{int(value)}"


def _truth_frame(runner: Stage2Runner, scene: str, index: int) -> tuple[Tensor, Tensor]:
    """(images [V, H, W, 3], truth depth [V, H, W]) of a cache frame at the model's size."""
    sample = runner.data._frame(scene, index)
    size = tuple(runner.stage1.config.image_size)
    images = resize_images(sample["images"], size).permute(0, 2, 3, 1)
    return images, frame_truth(sample, size).depth  # type: ignore[arg-type]


def _vae_reconstruction(runner: Stage2Runner, truth_rgb: list[Tensor]) -> Tensor:
    """[F, V, H, W, 3] of the true frames ``truth_rgb`` (F <= one window, each [V, H, W, 3] in
    [0, 1]) encoded as one window and decoded by the frozen VAE; a short window is padded with its
    last frame, as a rollout pads its last window."""
    frames = list(truth_rgb) + [truth_rgb[-1]] * (runner.window - len(truth_rgb))
    video = torch.stack(frames).permute(0, 1, 4, 2, 3)[None]  # [1, F, V, 3, H, W]
    with torch.no_grad():
        out = runner.stage1.decode(runner.stage1.encode(video))[0]
    return out[: len(truth_rgb)].permute(0, 1, 3, 4, 2).clamp(0, 1)


def _render_only(runner: Stage2Runner, clip: Any, cams: TargetCameras) -> tuple[Tensor, Tensor]:
    """(rgb [F, V, H, W, 3] with Stage 1's sky behind, depth [F, V, H, W]) of the history's Stage 1
    Gaussians at ``cams``."""
    scene = history_scene("stage1", clip, runner.stage1)
    out = render_condition(scene, cams)
    return with_sky(out, runner.stage1, cams), out.depth


def clip_starts(length: int, history: int, needed: int, count: int) -> list[int]:
    """Up to ``count`` rollout starts spread over a scene of ``length`` frames, each with ``history``
    frames before it and ``needed`` frames from it on."""
    last = length - needed
    if last < history:
        return []
    return sorted(set(np.linspace(history, last, count).round().astype(int).tolist()))


def evaluate_stage2(
    checkpoint: str | os.PathLike[str],
    shards: str | os.PathLike[str],
    *,
    stage1: str | os.PathLike[str] | None = None,
    options: GenerateOptions | None = None,
    offsets: tuple[int, ...] = (5, 10),
    shifts_m: tuple[float, ...] = (1.0, 2.0, 4.0),
    rollout_frames: tuple[int, ...] = (50, 100, 150, 200),
    clips_per_scene: int = 1,
    fid_model: str | os.PathLike[str] | None = None,
    out_json: str | os.PathLike[str] | None = None,
    picture: str | os.PathLike[str] | None = None,
    threads: int | None = None,
    fid_frames: int | None = None,
) -> dict[str, Any]:
    """Scores the Stage 2 checkpoint on the held-out cache ``shards`` (see the module docstring).
    ``fid_frames``: the generated frames ending at a rollout frame that its FID/KID pools (default:
    one window's; 50 images from 2 scenes of 5 views at the tiny config, whose FID is mostly bias).

    Returns ``{"checkpoint", "shards", "options", "clips", "seconds", "seconds_per_frame",
    "sections": {name: {renderer: {...}}}}`` (the renderers of :data:`RENDERERS`); FID/KID (and
    their sample counts) in the rollout sections when ``fid_model`` is given. Writes it as JSON to
    ``out_json``. Raises ValueError when no scene is long enough for any section, CheckpointError for a
    checkpoint that is not Stage 2's."""
    if threads:
        torch.set_num_threads(int(threads))
    if fid_frames is not None and fid_frames < 1:
        raise ValueError(f"fid_frames must be at least 1, got {fid_frames}")
    t0 = time.perf_counter()
    options = options or GenerateOptions()
    runner = Stage2Runner(checkpoint, shards, stage1)
    options = runner.resolve(options)
    t_h, window = runner.history_frames, runner.window
    fid_span = window if fid_frames is None else int(fid_frames)
    manifest = runner.data.reader.manifest
    truth = None
    if shifts_m:
        try:
            truth = SyntheticTruth(manifest.arguments, manifest.source)
        except (ValueError, TypeError) as e:
            log.warning("%s: skipping the shifted views (%s)", shards, e)
    scores: dict[str, dict[str, _Scores]] = {}
    long_frames: dict[int, dict[str, list[Tensor]]] = {}

    def section(name: str) -> dict[str, _Scores]:
        return scores.setdefault(name, {r: _Scores() for r in RENDERERS})

    generated_frames, generation_seconds, clips = 0, 0.0, 0
    first_picture: dict[str, Tensor] | None = None
    for scene in sorted(runner.data.scenes):
        length = runner.data.scene_length(scene)
        # Each true frame is read and decoded once per scene: the sections, the VAE ceiling's
        # windows and the FID windows share frames.
        truth_at = functools.lru_cache(maxsize=None)(functools.partial(_truth_frame, runner, scene))

        # Whole windows: the VAE reconstruction encodes the true frames of a scored frame's window.
        need = max([*(math.ceil(k / window) * window for k in offsets), window if shifts_m else 0, 1])
        for start in clip_starts(length, t_h, need, clips_per_scene):
            clips += 1
            # Future frames along the recorded trajectory.
            if offsets:
                result, clip = runner.run(scene, start, max(offsets), "recorded", options)
                generated_frames += max(offsets)
                generation_seconds += sum(result.seconds_per_window)
                cams = _rollout_cameras(result, clip)
                ro_rgb, ro_depth = _render_only(runner, clip, cams)
                for k in offsets:
                    images, depth = truth_at(start + k - 1)
                    s = section(_section_name("offset", k))
                    s["generated"].add(result.images[k - 1], images, result.depth[k - 1], depth)
                    s["render_only"].add(ro_rgb[k - 1], images, ro_depth[k - 1], depth)
                    w0 = (k - 1) // window * window  # the first frame of the window holding k
                    true_window = [truth_at(start + j)[0] for j in range(w0, w0 + window)]
                    recon = _vae_reconstruction(runner, true_window)[k - 1 - w0]
                    s["vae_reconstruction"].add(recon, images, None, None)
                if first_picture is None:
                    k = max(offsets)
                    first_picture = {
                        "history": clip.context.images[-1].permute(0, 2, 3, 1),
                        "condition": result.condition_rgb[k - 1],
                        "u": result.u[k - 1][..., None].expand(*result.u.shape[1:], 3),
                        "generated": result.images[k - 1],
                        "truth": truth_at(start + k - 1)[0],
                    }
            # Novel trajectories: the recorded one moved sideways.
            if truth is not None:
                for d in shifts_m:
                    result, clip = runner.run(scene, start, window, f"shift:{d:g}m", options)
                    generated_frames += window
                    generation_seconds += sum(result.seconds_per_window)
                    cams = _rollout_cameras(result, clip)
                    ro_rgb, ro_depth = _render_only(runner, clip, cams)
                    s = section(_section_name("shift", d))
                    size = tuple(runner.stage1.config.image_size)
                    samples = [runner.data._frame(scene, start + j) for j in range(window)]
                    views = [shifted_views(truth, clip, f, d, size) for f in samples]  # type: ignore[arg-type]
                    recon = _vae_reconstruction(runner, [v.images for v in views])
                    for j, (sample, view) in enumerate(zip(samples, views, strict=True)):
                        why = shift_collision(sample, d)
                        if why is not None:
                            log.info("%s frame %d: not scoring the %g m shift: %s", scene, start + j, d, why)
                            for r in RENDERERS:
                                s[r].skipped_frames += 1
                            continue
                        s["generated"].add(result.images[j], view.images, result.depth[j], view.depth)
                        s["render_only"].add(ro_rgb[j], view.images, ro_depth[j], view.depth)
                        s["vae_reconstruction"].add(recon[j], view.images, None, None)
        # One long rollout per scene.
        reach = [k for k in rollout_frames if t_h + k <= length]
        if reach:
            start = t_h
            result, clip = runner.run(scene, start, max(reach), "recorded", options)
            generated_frames += max(reach)
            generation_seconds += sum(result.seconds_per_window)
            cams = _rollout_cameras(result, clip)
            ro_rgb, ro_depth = _render_only(runner, clip, cams)
            for k in reach:
                images, depth = truth_at(start + k - 1)
                s = section(_section_name("rollout", k))
                s["generated"].add(result.images[k - 1], images, result.depth[k - 1], depth)
                s["render_only"].add(ro_rgb[k - 1], images, ro_depth[k - 1], depth)
                w0 = (k - 1) // window * window
                true_window = [truth_at(start + j)[0] for j in range(w0, min(w0 + window, length - start))]
                recon = _vae_reconstruction(runner, true_window)
                s["vae_reconstruction"].add(recon[k - 1 - w0], images, None, None)
                bucket = long_frames.setdefault(k, {"generated": [], "truth": [], "vae_reconstruction": []})
                first = max(k - fid_span, 0)
                for j in range(first, k):
                    bucket["generated"].append(result.images[j])
                    bucket["truth"].append(truth_at(start + j)[0])
                # The ceiling over the same frames, each window reconstructed as one.
                for w_start in range(first // window * window, k, window):
                    if w_start == w0:
                        rec = recon
                    else:
                        rec = _vae_reconstruction(
                            runner, [truth_at(start + j)[0] for j in range(w_start, w_start + window)]
                        )
                    for j in range(max(w_start, first), min(w_start + window, k)):
                        bucket["vae_reconstruction"].append(rec[j - w_start])
    if not scores:
        raise ValueError(
            f"{shards}: no scene is long enough for any section (history {t_h}, window {window})"
        )
    sections = {name: {r: sc.summary() for r, sc in by.items()} for name, by in scores.items()}
    if fid_model is not None and long_frames:
        extractor = load_feature_extractor(fid_model)
        for k, bucket in long_frames.items():
            tru = torch.cat(bucket["truth"]).permute(0, 3, 1, 2)
            fb = image_features(extractor, tru)
            for renderer in ("generated", "vae_reconstruction"):
                if not bucket[renderer]:
                    continue
                fa = image_features(extractor, torch.cat(bucket[renderer]).permute(0, 3, 1, 2))
                entry = sections[_section_name("rollout", k)][renderer]
                entry["fid"] = float(fid(fa, fb))
                score = kid(fa, fb)
                entry |= {"kid": float(score.mean), "kid_std": float(score.std), "fid_images": float(len(fa))}
    report = {
        "checkpoint": str(checkpoint),
        "shards": str(shards),
        "options": options.__dict__,
        "clips": clips,
        "seconds": time.perf_counter() - t0,
        "seconds_per_frame": generation_seconds / max(generated_frames, 1),
        "sections": sections,
    }
    if out_json is not None:
        Path(out_json).write_text(json.dumps(report, indent=1, default=_jsonable))
    if picture is not None and first_picture is not None:
        _save_picture(first_picture, Path(picture))
    return report


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)


def _rollout_cameras(result: Rollout, clip: Any) -> TargetCameras:
    """The cameras a rollout generated its frames at."""
    return TargetCameras(
        result.world_from_camera, clip.intrinsics, result.time_s, tuple(clip.context.images.shape[-2:])
    )


def _save_picture(picture: dict[str, Tensor], path: Path) -> Path:
    """One row per panel (the last history frame, the condition render at the scored frame, its u, the
    generated frame, the truth), the views side by side, each row labelled."""
    rows = []
    for name, views in picture.items():
        row = (torch.cat(list(views), dim=1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        row = np.ascontiguousarray(row)
        cv2.putText(row, name, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(rows), cv2.COLOR_RGB2BGR))
    if ok:
        path.write_bytes(png.tobytes())
    return path
