"""Pseudo-semantic labels benchmark: the geometric fallback, the segmenter and segmenter + geometry,
scored against exact synthetic truth and against the real Waymo frame's panoptic labels.

Usage (from the repository root)::

    python benchmarks/semantics.py [--train-scenes 10] [--train-frames 12] [--minutes 8 | --steps N]
                                   [--eval-scenes 2] [--eval-frames 4] [--work DIR] [--reuse]

1. Renders ``--train-scenes`` synthetic scenes (``waymo5`` rig, 160 x 240, frames 0.5 s apart so a
   scene shows several streets) into a cache with images and exact semantics only, and trains
   ``segformer_tiny`` on it with ``phigenesis.train.segmenter.train_segmenter`` on the CPU (2
   threads; 10 % of the training scenes validate the checkpoint choice) for ``--steps`` steps, or
   as many as fit in ``--minutes`` (measured on a few steps first). ``--reuse`` keeps a trained
   checkpoint in ``--work``.
2. Renders ``--eval-scenes`` other synthetic scenes (another seed: streets the segmenter never
   saw), runs the depth stages as the bundled pipeline does, and labels every image three ways:
   geometry alone (no checkpoint), the segmenter alone (no rules) and both. Each is scored against
   the exact truth (ignore excluded): mIoU over the classes in the truth, per-class IoU, the share
   of pixels labelled and the accuracy of the labels given; ms/frame (5 cameras, depth stages not
   included) with torch and numpy on 2 cores.
3. Reads the real Waymo frame (``one_frame_five_cameras_panoptic.tfrecord``, 5 cameras with
   panoptic labels in the unified taxonomy), runs the depth stages, and scores the same three
   ways against its labels (the segmenter sees the images resized to 160 px high).

``--update`` writes the ``semantics`` section of BENCHMARKS.md. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag

from phigenesis import prep
from phigenesis import taxonomy as tx
from phigenesis.data.pipeline import PipelineSpec
from phigenesis.data.records import Frame, Scene
from phigenesis.data.schema import CacheContents
from phigenesis.data.segmenter import Segmenter
from phigenesis.data.sources.synthetic import SyntheticConfig, synthetic_scene
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.semantics import PseudoSemanticsParams, RayCache, label_frame
from phigenesis.models.checkpoint import load_checkpoint
from phigenesis.models.metrics import confusion_matrix, segmentation_scores
from phigenesis.train.checkpoint import save_checkpoint
from phigenesis.train.segmenter import train_segmenter

DEPTH_STAGES = ("aggregate_lidar", "project_depth", "densify_depth")
WAYMO_SAMPLE = Path(
    os.environ.get(
        "PHIGENESIS_WAYMO_SAMPLES", Path(__file__).resolve().parents[2] / "shared" / "data" / "waymo"
    )
)
WAYMO_FILE = "one_frame_five_cameras_panoptic.tfrecord"


@dataclass
class Method:
    """One way of labelling: its name, parameters and segmenter, with accumulated scores."""

    name: str
    params: PseudoSemanticsParams
    segmenter: Segmenter | None
    confusion: np.ndarray = field(
        default_factory=lambda: np.zeros((tx.NUM_CLASSES, tx.NUM_CLASSES + 1), np.int64)
    )
    seconds: list[float] = field(default_factory=list)

    def run(self, frame: Frame, truth: Callable, cache: RayCache) -> None:
        t0 = time.perf_counter()
        out = label_frame(frame, self.params, self.segmenter, cache)
        self.seconds.append(time.perf_counter() - t0)
        for cam in out.cameras:
            target = truth(cam)
            if target is not None and cam.pseudo is not None:
                self.confusion += confusion_matrix(cam.pseudo.semantic, target, tx.NUM_CLASSES)


def methods(checkpoint: Path, input_height: int | None) -> list[Method]:
    seg = Segmenter.load(str(checkpoint), input_height=input_height)
    return [
        Method("geometry only (no checkpoint)", PseudoSemanticsParams(), None),
        Method("segmenter only", PseudoSemanticsParams(checkpoint=str(checkpoint), rules=()), seg),
        Method("segmenter + geometry", PseudoSemanticsParams(checkpoint=str(checkpoint)), seg),
    ]


def train(args: argparse.Namespace, work: Path) -> tuple[Path, dict, float, int]:
    """Renders the training cache and trains; returns (checkpoint, scores, seconds, images)."""
    ckpt = work / "run" / "best.pt"
    if args.reuse and ckpt.exists():
        meta = load_checkpoint(ckpt).meta
        args.steps = meta["training"]["steps"]
        return (
            ckpt,
            meta.get("scores", {}),
            float(meta.get("seconds", float("nan"))),
            int(meta.get("images", 0)),
        )
    spec = PipelineSpec(
        name="segmenter-training",
        source="synthetic",
        source_params={"rig": "waymo5", "height": 160, "width": 240},
        contents=CacheContents(
            camera_truth=("semantic",), lidar=False, lidar_truth=False, camera_labels=False
        ),
    )
    t0 = time.perf_counter()
    prep.synthetic(
        work / "train-cache",
        scenes=args.train_scenes,
        frames=args.train_frames,
        seed=args.seed,
        frame_rate_hz=2.0,
        pipeline=spec,
        overwrite=True,
        progress=False,
    )
    print(f"rendered the training cache in {time.perf_counter() - t0:.0f} s", flush=True)
    if args.steps is None:
        args.steps = max(10, int(args.minutes * 60 / seconds_per_step() * 0.9))
        print(f"training for {args.steps} steps", flush=True)
    t0 = time.perf_counter()
    run = train_segmenter(
        work / "train-cache",
        work / "run",
        config="segformer_tiny",
        steps=args.steps,
        batch_size=8,
        crop=(128, 192),
        val_fraction=0.1,
        eval_every=max(1, args.steps // 5),
        threads=2,
        seed=args.seed,
        progress=lambda r: print(
            r["step"], r["seconds"], round(r["train_loss"], 3), r.get("val", {}).get("miou")
        ),
    )
    seconds = time.perf_counter() - t0
    images = args.train_scenes * args.train_frames * 5
    # Record the training time in the checkpoint for --reuse.
    best = load_checkpoint(run.best)
    save_checkpoint(run.best, best.model, {**best.meta, "seconds": seconds, "images": images})
    return run.best, run.scores, seconds, images


def seconds_per_step(steps: int = 6) -> float:
    """Median seconds of one training step of segformer_tiny (batch 8, 128 x 192) on random data."""
    import torch.nn.functional as F

    from phigenesis.models import create_model

    model = create_model("segformer_tiny")
    optimizer = torch.optim.AdamW(model.parameters(), 1e-4)
    x, y = torch.rand(8, 3, 128, 192), torch.randint(0, tx.NUM_CLASSES, (8, 128, 192))
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        loss = F.cross_entropy(F.interpolate(model(x), size=(128, 192), mode="bilinear"), y)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - t0)
    return float(np.median(times[1:])) + 0.01  # + loading and decoding a batch


def scene_frames(scene: Scene) -> list[Frame]:
    """The scene's frames after the depth stages, each loaded once."""
    for name in DEPTH_STAGES:
        scene = get_stage(name)(scene, {})
    return [scene.frames[i] for i in range(len(scene.frames))]


def evaluate(frames: list[Frame], ms: list[Method], truth: Callable) -> None:
    cache = RayCache()
    for m in ms:  # warm up: ray cache, torch's first calls
        label_frame(frames[0], m.params, m.segmenter, cache)
    for frame in frames:
        for m in ms:
            m.run(frame, truth, cache)


def rows(ms: list[Method]) -> list[list[str]]:
    out = []
    for m in ms:
        s = segmentation_scores(m.confusion)
        out.append(
            [
                m.name,
                f"{100 * s.miou:.1f}",
                f"{100 * s.pixel_accuracy:.1f}",
                f"{100 * s.labelled:.1f}",
                f"{100 * s.labelled_accuracy:.1f}",
                f"{1e3 * np.median(m.seconds):.0f}",
            ]
        )
    return out


def class_rows(ms: list[Method]) -> list[list[str]]:
    scores = [segmentation_scores(m.confusion) for m in ms]
    pixels = ms[0].confusion.sum(axis=1)
    out = []
    for k, name in enumerate(tx.CLASS_NAMES):
        if pixels[k] == 0:
            continue
        out.append(
            [name, f"{100 * pixels[k] / pixels.sum():.1f}", *(f"{100 * s.iou[k]:.1f}" for s in scores)]
        )
    return out


HEADERS = ["method", "mIoU %", "pixel acc %", "labelled %", "acc. of labelled %", "ms/frame"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--train-scenes", type=int, default=10)
    parser.add_argument("--train-frames", type=int, default=12)
    parser.add_argument("--steps", type=int, help="training steps (default: what fits in --minutes)")
    parser.add_argument("--minutes", type=float, default=8.0, help="training time budget")
    parser.add_argument("--eval-scenes", type=int, default=2)
    parser.add_argument("--eval-frames", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", default="/tmp/phigenesis-semantics-benchmark")
    parser.add_argument("--reuse", action="store_true", help="reuse a checkpoint trained before in --work")
    parser.add_argument("--no-waymo", action="store_true")
    add_update_flag(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    report = Report(
        "semantics",
        "Pseudo-semantic labels: geometry, segmenter, both",
        "Script: `benchmarks/semantics.py`. mIoU is over the classes present in the truth; pixels a "
        "method leaves unlabelled (255) count as misses. *Labelled*: share of truth pixels given a "
        "class; *acc. of labelled*: share of those that are right. ms/frame: labelling the 5 "
        "cameras of one frame (depth stages and image rendering not included), torch and numpy on "
        "2 threads.",
    )
    ckpt, val_scores, seconds, images = train(args, work)
    report.table(
        "Segmenter training (CPU)",
        ["model", "training images", "steps x batch", "CPU minutes (2 threads)", "val mIoU %"],
        [
            [
                "segformer_tiny (0.53 M params)",
                str(images),
                f"{args.steps} x 8",
                f"{seconds / 60:.1f}",
                f"{100 * val_scores.get('miou', float('nan')):.1f}",
            ]
        ],
        note=f"{args.train_scenes} synthetic scenes x {args.train_frames} frames (2 Hz) x 5 cameras at "
        "160 x 240, exact semantics as labels; random 128 x 192 crops and flips, AdamW, warm-up + "
        "cosine. Validation: 10 % of these scenes (checkpoint choice only).",
    )

    ms = methods(ckpt, None)
    for k in range(args.eval_scenes):
        config = SyntheticConfig(scenes=args.eval_scenes, frames=args.eval_frames, seed=args.seed + 1000)
        frames = scene_frames(synthetic_scene(config, k))
        evaluate(frames, ms, lambda cam: cam.truth.semantic)
    n_eval = args.eval_scenes * args.eval_frames
    report.table(
        f"Held-out synthetic scenes ({n_eval} frames, 160 x 240)",
        HEADERS,
        rows(ms),
        note="Other seed than the training scenes. Geometry alone labels only road, sky and boxed "
        "things, hence its low mIoU; its labels are what the accuracy column shows.",
    )
    report.table(
        "Per-class IoU %, held-out synthetic scenes",
        ["class", "share of pixels %", *(m.name for m in ms)],
        class_rows(ms),
    )

    path = WAYMO_SAMPLE / WAYMO_FILE
    if not args.no_waymo and path.exists():
        from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource

        source = WaymoSource(WaymoConfig(input=str(path)))
        (scene_id,) = source.scene_ids()
        t0 = time.perf_counter()
        frames = scene_frames(source.load(scene_id))
        depth_s = time.perf_counter() - t0
        wm = methods(ckpt, 160)
        evaluate(frames, wm, lambda cam: None if cam.labels is None else cam.labels.semantic)
        report.table(
            "Real Waymo frame (5 cameras, 1920 x 1280 / 886, panoptic labels)",
            HEADERS,
            rows(wm),
            note=f"One frame; the depth stages took {depth_s:.0f} s (not included); its LiDAR: "
            f"{sum(len(f.lidar) if f.lidar is not None else 0 for f in frames)} points (this sample "
            "file carries none, so the geometric rules have nothing to work with). The segmenter was "
            "trained on synthetic images only (no real labels): these rows measure the domain gap, "
            "not what a segmenter fine-tuned on real labelled frames (as in the paper) would reach.",
        )
        report.table(
            "Per-class IoU %, real Waymo frame",
            ["class", "share of pixels %", *(m.name for m in wm)],
            class_rows(wm),
        )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
