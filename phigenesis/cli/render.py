"""``phigenesis-render``: a cache as another rig's cameras would have seen it, written as a new cache (a
thin front end over :func:`phigenesis.infer.rig_render.render`)."""

from __future__ import annotations

import argparse
import sys

from phigenesis.cli.common import Parser, positive, run, size_hw


def build_parser() -> argparse.ArgumentParser:
    from phigenesis.infer.rig_render import GEOMETRIES
    from phigenesis.infer.rigs import NAMED_RIGS

    parser = Parser(prog="phigenesis-render", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument(
        "--ckpt", help="Stage 1 checkpoint (a run's model.safetensors); not needed with --geometry cache"
    )
    parser.add_argument("--shards", required=True, help="the source cache")
    parser.add_argument(
        "--rig",
        required=True,
        help=f"{' | '.join(NAMED_RIGS)} | a YAML rig file | random (a rig per scene around the source's own)",
    )
    parser.add_argument(
        "--geometry",
        choices=GEOMETRIES,
        default="stage1",
        help="stage1: the model's Gaussians; cache: the cache's dense depth lifted (e.g. a generated cache); "
        "truth: a synthetic cache's exact depth lifted",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random rigs (default 0)")
    parser.add_argument("--size", type=size_hw, help="HxW of a named rig's images (default: the source's)")
    parser.add_argument("--scene", action="append", help="only this scene id (repeatable)")
    parser.add_argument("--max-frames", type=positive, help="at most this many frames per scene")
    parser.add_argument(
        "--history-frames",
        type=positive,
        default=1,
        help="join the Gaussians of this many frames up to each frame (default 1: the frame's own)",
    )
    parser.add_argument("--threads", type=positive, help="torch threads")
    parser.add_argument("--out", required=True, help="new folder for the rendered cache (or a run to resume)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(command="render")
    return parser


def _render(args: argparse.Namespace) -> int:
    from phigenesis.infer.rig_render import render

    height, width = args.size if args.size else (None, None)
    result = render(
        args.ckpt,
        args.shards,
        args.rig,
        args.out,
        geometry=args.geometry,
        seed=args.seed,
        height=height,
        width=width,
        scenes=args.scene,
        max_frames=args.max_frames,
        history_frames=args.history_frames,
        progress=not args.no_progress,
        threads=args.threads,
    )
    per_frame = result.seconds / max(result.frames, 1)
    print(
        f"rendered {result.frames} frames of {len(result.scenes)} scenes in {result.seconds:.1f} s "
        f"({per_frame:.2f} s/frame)"
    )
    if result.skipped:
        print(f"already rendered, skipped: {', '.join(result.skipped)}")
    print(f"cache: {result.out} (phigenesis-prep verify {result.out})")
    return 0


def interrupted(args: argparse.Namespace) -> str:
    return f"interrupted; rerun the same command to resume {args.out} after its last finished scene"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-render", build_parser, argv, {"render": _render}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
