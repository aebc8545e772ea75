"""Benchmark of ``phigenesis-render``: a waymo5 cache re-rendered for its own rig and for nuscenes6,
scored against the synthetic renderer's exact truth of those very cameras.

    python benchmarks/render.py [--work /tmp/render-bench] [--scenes 2] [--frames 6]
                                [--ckpt runs/stage1-tiny/model.safetensors]

1. A held-out synthetic waymo5 cache (seed 100, ``--scenes`` x ``--frames`` at 96 x 144).
2. For each geometry (``truth``: the exact depth lifted, the oracle; ``cache``: the cache's LiDAR-derived
   dense depth lifted; ``stage1``: the model of ``--ckpt``, when given) and each rig (``waymo5`` at the
   cache's size, pinhole; ``nuscenes6`` at the same size), ``phigenesis.infer.rig_render.render``.
3. Every rendered camera against ``SyntheticTruth.render`` of the same calibration, pose and time:
   PSNR over all pixels, depth under the standard protocol (pixels the render leaves empty count as
   1e-3 m; AbsRel per image, averaged), the share of truth pixels with a rendered depth, and mIoU of the
   rendered classes (pixels without a class count as wrong).

Written to BENCHMARKS.md (section ``render``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, output_path

from phigenesis import prep
from phigenesis.data.shards import CacheReader
from phigenesis.eval.depth_protocol import DepthAccumulator
from phigenesis.eval.stage1 import SyntheticTruth
from phigenesis.infer.rig_render import render
from phigenesis.models.losses import psnr
from phigenesis.models.metrics import confusion_matrix, segmentation_scores
from phigenesis.taxonomy import NUM_CLASSES

RIGS = ("waymo5", "nuscenes6")


def score(source: Path, rendered: Path) -> dict[str, float]:
    """PSNR, depth AbsRel / RMSE / delta, coverage and mIoU of every camera of ``rendered`` against
    the exact truth of the source cache's synthetic scenes."""
    manifest = CacheReader(source).manifest
    truth = SyntheticTruth(manifest.arguments, manifest.source)
    reader = CacheReader(rendered)
    depth = DepthAccumulator(())
    psnrs, covered, truth_pixels = [], 0, 0
    confusion = np.zeros((NUM_CLASSES, NUM_CLASSES + 1), np.int64)
    for i in range(len(reader)):
        frame = reader.frame(i)
        for cam in frame.cameras:
            rgb, tr = truth.render(frame.scene_id, cam.calibration, cam.world_from_ego, cam.timestamp_micros)
            image = cam.decode_image()
            psnrs.append(
                float(
                    psnr(
                        torch.from_numpy(image / 255.0)[None].float(),
                        torch.from_numpy(rgb / 255.0)[None].float(),
                    )
                )
            )
            assert cam.depth is not None and cam.depth.dense_m is not None and cam.pseudo is not None
            depth.add(cam.depth.dense_m[None], tr.depth_m[None])
            has = tr.depth_m > 0
            truth_pixels += int(has.sum())
            covered += int((has & (cam.depth.dense_m > 0)).sum())
            confusion += confusion_matrix(cam.pseudo.semantic, tr.semantic, NUM_CLASSES)
    d = depth.image_mean()["all"]
    return {
        "images": len(psnrs),
        "psnr_db": float(np.mean(psnrs)),
        "abs_rel": d.abs_rel,
        "rmse_m": d.rmse_m,
        "delta_1_25": d.delta_1_25,
        "coverage": covered / max(truth_pixels, 1),
        "miou": segmentation_scores(confusion).miou,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/render-bench"))
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--ckpt", type=Path, help="a Stage 1 checkpoint for the stage1 rows")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--history", type=int, default=5, help="history frames of the second row per geometry")
    add_update_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    source = work / "source"
    if not (source / "manifest.json").exists():
        prep.synthetic(
            source, scenes=args.scenes, frames=args.frames, seed=100, height=96, width=144, workers=2
        )
    report = Report(
        "render",
        "Rendering a cache for another rig (benchmarks/render.py)",
        f"A held-out synthetic waymo5 cache ({args.scenes} scenes x {args.frames} frames, seed 100, "
        "96 x 144) "
        "rendered by `phigenesis-render` for its own rig (`waymo5`, pinhole, at the cache's size) and for "
        "`nuscenes6` (six 70-110 degree cameras, other mounting heights, a rear camera no waymo5 camera "
        "covers) at the same size, every camera scored against the synthetic renderer's exact image, "
        "depth and classes for that camera at its pose and time.",
    )
    geometries = ["truth", "cache"] + (["stage1"] if args.ckpt else [])
    rows = []
    for geometry, history in [(g, h) for g in geometries for h in (1, args.history)]:
        for rig in RIGS:
            out = work / f"{geometry}-{history}-{rig}"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            result = render(
                args.ckpt, source, rig, out, geometry=geometry, history_frames=history, progress=False
            )
            seconds = (time.perf_counter() - t0) / max(result.frames, 1)
            s = score(source, out)
            depth = f"{s['abs_rel']:.3f}", f"{s['rmse_m']:.2f}", f"{100 * s['delta_1_25']:.1f}"
            rest = f"{100 * s['coverage']:.1f}", f"{s['miou']:.3f}", f"{seconds:.2f}"
            rows.append([geometry, history, rig, s["images"], f"{s['psnr_db']:.2f}", *depth, *rest])
    report.table(
        "Rendered caches against the exact truth of the new cameras",
        [
            "geometry",
            "history frames",
            "rig",
            "images",
            "PSNR dB",
            "AbsRel",
            "RMSE m",
            "δ<1.25 %",
            "depth coverage %",
            "mIoU",
            "s/frame",
        ],
        rows,
        note=(
            "`truth`: one Gaussian per pixel at the exact depth of the source images (the oracle's "
            "geometry); `cache`: the same from the cache's LiDAR-derived dense depth; `stage1`: the Stage 1 "
            "model. History frames: the Gaussians of that many frames up to each frame, joined (moving ones "
            "moved at their velocities). PSNR over every pixel (holes show the sky colour); depth under the "
            "standard protocol "
            "(empty pixels count as 1e-3 m); depth coverage: share of truth pixels with a rendered depth; "
            "mIoU of the rendered classes, pixels without one counting as wrong. s/frame: the whole "
            "command per frame (Gaussians, every camera, LiDAR re-projection, encoding, writing)."
            + ("" if args.ckpt else " No Stage 1 checkpoint was given to this run, so it has no stage1 rows.")
        ),
    )
    picture = _random_rigs_picture(source, work, output_path(PICTURE, args.update))
    report.text(
        f"![one frame for three random rigs]({PICTURE})\n\n"
        "One frame of the first scene rendered (truth geometry) for three random rigs (`--rig random`, "
        "seeds 0, 1, 2: field of view, image size, mounting height, pitch, yaw and lateral offset drawn "
        f"around the waymo5 rig), one row per rig, its cameras left to right: `{picture.name}`."
    )
    report.write(update=args.update)


PICTURE = "docs/images/render_random_rigs.png"


def _random_rigs_picture(source: Path, work: Path, path: Path) -> Path:
    """Frame 0 of the first scene for three random rigs, one row each, cameras side by side."""
    from PIL import Image, ImageDraw

    scene = CacheReader(source).scene_ids()[0]
    rows = []
    for seed in (0, 1, 2):
        out = work / f"random-{seed}"
        shutil.rmtree(out, ignore_errors=True)
        render(
            None,
            source,
            "random",
            out,
            geometry="truth",
            seed=seed,
            scenes=[scene],
            max_frames=1,
            progress=False,
        )
        frame = CacheReader(out).frame(0, decode_truth=False)
        tiles = []
        for cam in frame.cameras:
            tile = Image.fromarray(cam.decode_image())
            tile = tile.resize((round(tile.width * 120 / tile.height), 120))
            ImageDraw.Draw(tile).text(
                (3, 2), f"{cam.calibration.name} {cam.calibration.width}x{cam.calibration.height}"
            )
            tiles.append(np.asarray(tile))
        row = np.concatenate([np.pad(t, ((0, 0), (0, 4), (0, 0))) for t in tiles], axis=1)
        rows.append(row)
    width = max(r.shape[1] for r in rows)
    canvas = np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0))) for r in rows], axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(canvas).save(path)
    return path


if __name__ == "__main__":
    main()
