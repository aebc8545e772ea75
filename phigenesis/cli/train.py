"""``phigenesis-train``: train models on caches (a thin front end over phigenesis.train).

Subcommands: ``segmenter`` (:func:`phigenesis.train.segmenter.train_segmenter`).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys

from phigenesis.data.shards import CacheError
from phigenesis.models import list_models
from phigenesis.train.checkpoint import CheckpointError
from phigenesis.train.segmenter import train_segmenter


def _positive(value: str) -> int:
    n = int(value)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def _size(value: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW (e.g. 128x192), got {value!r}") from None
    return h, w


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="phigenesis-train", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    s = sub.add_parser("segmenter", help="train a semantic segmenter on a cache's labelled images")
    s.add_argument("--shards", required=True, help="cache directory to train on")
    s.add_argument("--out", required=True, help="run directory for checkpoints and metrics")
    s.add_argument(
        "--config", default="segformer_tiny", choices=list_models("segformer"), help="model variant"
    )
    s.add_argument("--steps", type=_positive, help="optimiser steps (default: --epochs passes)")
    s.add_argument("--epochs", type=float, help="passes over the training images (default 10)")
    s.add_argument("--batch-size", type=_positive, default=8, help="images per step (default 8)")
    s.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (default 2e-3)")
    s.add_argument("--val-fraction", type=float, default=0.2, help="share of scenes held out (default 0.2)")
    s.add_argument(
        "--labels", choices=("auto", "truth", "labels"), default="auto", help="human labels, synthetic truth"
    )
    s.add_argument("--image-height", type=_positive, help="resize images to this height (aspect kept)")
    s.add_argument("--crop", type=_size, help="random training crops HxW (needed for mixed image sizes)")
    s.add_argument("--eval-every", type=_positive, default=250, help="steps between validations")
    s.add_argument("--seed", type=int, default=0, help="seed of the split, init and sampling")
    s.add_argument("--threads", type=_positive, help="torch CPU threads")
    s.add_argument("--device", default="cpu", help="torch device (default cpu)")
    s.add_argument("--init", help="start from this checkpoint (same --config)")
    s.add_argument("--pretrained", help="start from a local Hugging Face SegFormer pytorch_model.bin")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        if args.command == "segmenter":
            run = train_segmenter(
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
            scores = run.scores
            if scores:
                held_out = ", ".join(run.val_scenes)
                print(f"validation mIoU {scores['miou']:.3f} on {scores['images']} images ({held_out})")
                for name, iou in sorted(scores["iou"].items(), key=lambda kv: -kv[1]):
                    print(f"  {name:14s} {iou:.3f}" if not math.isnan(iou) else f"  {name:14s} -")
            print(f"best checkpoint: {run.best}")
            return 0
    except (ValueError, CacheError, CheckpointError, OSError) as e:
        print(f"phigenesis-train: error: {e}", file=sys.stderr)
        return 2
    return 2


if __name__ == "__main__":
    sys.exit(main())
