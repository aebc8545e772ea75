"""``phigenesis-train``: train models on caches (a thin front end over phigenesis.train).

Subcommands: ``segmenter`` (:func:`phigenesis.train.segmenter.train_segmenter`), ``vae``
(:func:`phigenesis.train.vae.train_vae`), ``stage1`` (:func:`phigenesis.train.stage1.train_stage1`)
and ``stage2`` (:func:`phigenesis.train.stage2.train_stage2`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from phigenesis.cli.common import Command, Parser, positive, positive_float, run, size_hw


def build_parser() -> argparse.ArgumentParser:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.models import list_models

    parser = Parser(prog="phigenesis-train", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    s = sub.add_parser("segmenter", help="train a semantic segmenter on a cache's labelled images")
    s.add_argument("--shards", required=True, help="cache directory to train on")
    s.add_argument("--out", required=True, help="run directory for checkpoints and metrics")
    s.add_argument(
        "--config", default="segformer_tiny", choices=list_models("segformer"), help="model variant"
    )
    s.add_argument("--steps", type=positive, help="optimiser steps (default: --epochs passes)")
    s.add_argument("--epochs", type=float, help="passes over the training images (default 10)")
    s.add_argument("--batch-size", type=positive, default=8, help="images per step (default 8)")
    s.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (default 2e-3)")
    s.add_argument("--val-fraction", type=float, default=0.2, help="share of scenes held out (default 0.2)")
    s.add_argument(
        "--labels", choices=("auto", "truth", "labels"), default="auto", help="human labels, synthetic truth"
    )
    s.add_argument("--image-height", type=positive, help="resize images to this height (aspect kept)")
    s.add_argument("--crop", type=size_hw, help="random training crops HxW (needed for mixed image sizes)")
    s.add_argument("--eval-every", type=positive, default=250, help="steps between validations")
    s.add_argument("--seed", type=int, default=0, help="seed of the split, init and sampling")
    s.add_argument("--threads", type=positive, help="torch CPU threads")
    s.add_argument("--device", default="cpu", help="torch device (default cpu)")
    s.add_argument("--init", help="start from this checkpoint (same --config)")
    s.add_argument("--pretrained", help="start from a local Hugging Face SegFormer pytorch_model.bin")

    v = sub.add_parser("vae", help="train the causal video VAE on a cache's camera clips")
    v.add_argument("--shards", required=True, help="cache directory to train on")
    v.add_argument("--out", required=True, help="run directory (runs/NAME) for checkpoints and metrics")
    v.add_argument("--config", default="vae_tiny", choices=list_models("vae"), help="VAE variant")
    v.add_argument("--steps", type=positive, default=2000, help="optimiser steps (default 2000)")
    v.add_argument("--batch-size", type=positive, default=8, help="clips per step, all ranks (default 8)")
    v.add_argument("--frames", type=positive, default=5, help="frames per clip; frames - 1 must divide by 4")
    v.add_argument("--size", type=size_hw, default=(48, 72), help="clip size HxW in pixels (default 48x72)")
    v.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (default 1e-3)")
    v.add_argument("--kl-weight", type=float, default=1e-6, help="per-element KL weight (default 1e-6)")
    v.add_argument("--val-fraction", type=float, default=0.2, help="share of scenes held out (default 0.2)")
    v.add_argument("--checkpoint-every", type=positive, default=500, help="steps between checkpoints")
    v.add_argument("--seed", type=int, default=0, help="seed of the split, init and sampling")
    v.add_argument("--threads", type=positive, help="torch CPU threads")
    v.add_argument("--device", default="cpu", help="torch device (default cpu)")
    v.add_argument("--init", help="start from this checkpoint's weights (same --config)")
    v.add_argument("--resume", action="store_true", help="continue --out from its newest checkpoint")
    v.add_argument("--stop-after", type=positive, help="leave after this many steps (then --resume)")

    g = sub.add_parser("stage1", help="train the Stage 1 range-view adapter (frozen VAE) on a cache")
    g.add_argument("--shards", required=True, help="cache directory to train on (needs dense depth)")
    g.add_argument("--config", required=True, help="training config YAML (configs/stage1/tiny.yaml)")
    g.add_argument("--out", required=True, help="run directory (runs/NAME) for checkpoints and logs")
    g.add_argument("--vae", help="trained VAE checkpoint (overrides the config's vae_checkpoint)")
    g.add_argument("--steps", type=positive, help="optimiser steps (overrides the config)")
    g.add_argument("--threads", type=positive, help="torch CPU threads per process (overrides the config)")
    g.add_argument("--resume", action="store_true", help="continue --out from its newest checkpoint")
    g.add_argument("--stop-after", type=positive, help="leave after this many steps (then --resume)")
    g.add_argument(
        "--time-limit-min",
        type=positive_float,
        help="wall-clock budget in minutes: end (and write the final weights) after the step that passes it",
    )
    g.add_argument("--no-progress", action="store_true", help="no progress bar")

    d = sub.add_parser("stage2", help="train the Stage 2 multi-view video diffusion model on a cache")
    d.add_argument(
        "--shards", required=True, help="frame cache to train on (the windows' images and cameras)"
    )
    d.add_argument("--config", required=True, help="training config YAML (configs/stage2/tiny.yaml)")
    d.add_argument("--out", required=True, help="run directory (runs/NAME) for checkpoints and logs")
    d.add_argument("--stage1", help="trained Stage 1 checkpoint (overrides the config's stage1_checkpoint)")
    d.add_argument(
        "--latents", help="the Stage 2 latent cache (default OUT/latents; computed there if missing)"
    )
    d.add_argument("--steps", type=positive, help="optimiser steps (overrides the config)")
    d.add_argument("--threads", type=positive, help="torch CPU threads per process (overrides the config)")
    d.add_argument("--resume", action="store_true", help="continue --out from its newest checkpoint")
    d.add_argument("--stop-after", type=positive, help="leave after this many steps (then --resume)")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def _train_stage2(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.rollout.config import Stage2TrainConfig
    from phigenesis.train.stage2 import train_stage2

    config = Stage2TrainConfig.load(args.config, steps=args.steps, threads=args.threads)
    result = train_stage2(
        args.shards,
        args.out,
        config,
        stage1=args.stage1,
        latents=args.latents,
        resume=args.resume,
        stop_after=args.stop_after,
        progress=not args.no_progress,
    )
    if os.environ.get("RANK", "0") != "0":  # torchrun: rank 0 reports
        return 0
    if result.checkpoint is None:
        print(f"stopped at step {result.steps_done}; continue with --resume")
        return 0
    if "loss" in result.last:
        minutes = result.seconds / 60
        print(f"{result.steps_done} steps in {minutes:.1f} min; last loss {result.last['loss']:.4f}")
    else:  # a resumed run that had already finished: no step ran in this call
        print(f"the run had already finished its {result.steps_done} steps; nothing to do")
    print(f"latent cache: {result.latents}")
    print(f"final checkpoint: {result.checkpoint}")
    return 0


def _train_stage1(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.train.stage1 import Stage1TrainConfig, train_stage1

    config = Stage1TrainConfig.load(
        args.config, vae_checkpoint=args.vae, steps=args.steps, threads=args.threads
    )
    result = train_stage1(
        args.shards,
        args.out,
        config,
        resume=args.resume,
        stop_after=args.stop_after,
        progress=not args.no_progress,
        time_limit_s=None if args.time_limit_min is None else 60.0 * args.time_limit_min,
    )
    if os.environ.get("RANK", "0") != "0":  # torchrun: rank 0 reports
        return 0
    if result.checkpoint is None:
        print(f"stopped at step {result.steps_done}; continue with --resume")
        return 0
    losses = ", ".join(
        f"{k} {result.last[k]:.4f}" for k in ("loss", "rgb", "depth", "semantic") if k in result.last
    )
    limit = " (the time limit ended it before the planned steps)" if result.stopped_by_time else ""
    if losses:
        print(f"{result.steps_done} steps in {result.seconds / 60:.1f} min{limit}; last step: {losses}")
    else:  # a resumed run that had already finished: no step ran in this call
        print(f"the run had already finished its {result.steps_done} steps; nothing to do")
    print(f"final checkpoint: {result.checkpoint}")
    return 0


def _train_vae(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.train.vae import train_vae

    result = train_vae(
        args.shards,
        args.out,
        config=args.config,
        resume=args.resume,
        stop_after=args.stop_after,
        steps=args.steps,
        batch_size=args.batch_size,
        frames=args.frames,
        size=args.size,
        lr=args.lr,
        kl_weight=args.kl_weight,
        val_fraction=args.val_fraction,
        checkpoint_every=args.checkpoint_every,
        seed=args.seed,
        threads=args.threads,
        device=args.device,
        init=args.init,
    )
    if os.environ.get("RANK", "0") != "0":  # torchrun: rank 0 reports
        return 0
    if not result.finished:
        print(f"stopped at step {result.step}; resume with --resume; checkpoint: {result.checkpoint}")
        return 0
    if result.val:
        held_out = ", ".join(result.val_scenes)
        print(f"validation PSNR {result.val['psnr_db']:.2f} dB on {result.val['clips']} clips ({held_out})")
    else:
        print("no validation clips (--val-fraction 0 or too few frames)")
    print(f"final checkpoint: {result.checkpoint}")
    return 0


def _train_segmenter(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.train.segmenter import train_segmenter

    result = train_segmenter(
        args.shards,
        args.out,
        config=args.config,
        steps=args.steps,
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr=args.lr,
        val_fraction=args.val_fraction,
        labels=args.labels,
        image_height=args.image_height,
        crop=args.crop,
        eval_every=args.eval_every,
        seed=args.seed,
        threads=args.threads,
        device=args.device,
        init=args.init,
        pretrained=args.pretrained,
    )
    scores = result.scores
    if scores:
        held_out = ", ".join(result.val_scenes)
        print(f"validation mIoU {scores['miou']:.3f} on {scores['images']} images ({held_out})")
        for name, iou in sorted(scores["iou"].items(), key=lambda kv: -kv[1]):
            print(f"  {name:14s} {iou:.3f}" if not math.isnan(iou) else f"  {name:14s} -")
    print(f"best checkpoint: {result.best}")
    return 0


COMMANDS: dict[str, Command] = {
    "segmenter": _train_segmenter,
    "vae": _train_vae,
    "stage1": _train_stage1,
    "stage2": _train_stage2,
}


def _steps_logged(out: Path) -> int | None:
    """The last step in the run's ``metrics.csv`` (one row per step done), None if there is none."""
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.train.runner import read_metrics

    try:
        steps = [int(row["step"]) for row in read_metrics(out)]
    except (OSError, ValueError, KeyError):
        return None
    return steps[-1] if steps else None


def run_interrupted(out: str | os.PathLike[str]) -> str:
    """What Ctrl-C leaves of a resumable run (vae, stage1, stage2): the step it reached and the newest
    complete checkpoint, which ``--resume`` continues from."""
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.train.runner import kept_step

    out = Path(out)
    kept = kept_step(out)
    logged = _steps_logged(out)
    reached = max((s for s in (logged, kept) if s is not None), default=None)
    at = f"interrupted after step {reached}" if reached else "interrupted before the first step"
    if kept is None:
        return (
            f"{at}, before the first checkpoint; nothing to resume in {out} "
            "(rerun without --resume to start again)"
        )
    return f"{at}; the checkpoint of step {kept} is kept in {out} (rerun with --resume to continue)"


def segmenter_interrupted(out: str | os.PathLike[str]) -> str:
    """What Ctrl-C leaves of a segmenter run: ``last.pt`` and ``best.pt`` of its last evaluation,
    from which a new run can start (the segmenter does not resume)."""
    out = Path(out)
    last = out / "last.pt"
    if not last.is_file():
        return f"interrupted before the first evaluation; nothing is kept in {out}"
    try:
        step = json.loads((out / "metrics.json").read_text())["history"][-1]["step"]
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        step = None
    at = f" (step {step})" if step is not None else ""
    return (
        f"interrupted; {last}{at} and best.pt are kept (the segmenter does not resume: rerun to train "
        f"again, with --init {last} to start from its weights)"
    )


def interrupted(args: argparse.Namespace) -> str | None:
    """The Ctrl-C line of each subcommand; None in torchrun processes other than rank 0, so a job
    prints it once."""
    if os.environ.get("RANK", "0") != "0":
        return None
    if args.command == "segmenter":
        return segmenter_interrupted(args.out)
    return run_interrupted(args.out)


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-train", build_parser, argv, COMMANDS, interrupted)


if __name__ == "__main__":
    sys.exit(main())
