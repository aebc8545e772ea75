"""``phigenesis-export``: write what a trained model predicts in standard formats (over phigenesis.export)."""

from __future__ import annotations

import argparse
import sys

from phigenesis.cli.common import Parser, run, time_after_frame_s


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="phigenesis-export", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("ply", help="a Stage 1 model's Gaussians of one frame as a 3DGS PLY")
    p.add_argument(
        "--ckpt", required=True, help="Stage 1 checkpoint (a run's model.safetensors or run folder)"
    )
    p.add_argument("--shards", required=True, help="cache holding the frame")
    p.add_argument("--frame", type=int, required=True, help="frame index (within --scene, else in the cache)")
    p.add_argument("--scene", help="scene id (default: --frame counts over the whole cache)")
    p.add_argument("--out", required=True, help="output .ply path")
    p.add_argument(
        "--t-s", type=time_after_frame_s, help="place moving Gaussians at this time (s after the frame)"
    )
    p.add_argument(
        "--sh-degree", type=int, default=3, choices=(0, 1, 2, 3), help="SH bands written (default 3)"
    )
    return parser


def _ply(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.export.stage1 import export_ply

    path = export_ply(
        args.ckpt,
        args.shards,
        args.out,
        args.frame,
        scene_id=args.scene,
        t_s=args.t_s,
        sh_degree=args.sh_degree,
    )
    print(f"wrote {path}")
    return 0


def interrupted(args: argparse.Namespace) -> str:
    """Ctrl-C: the PLY is written under a temporary name and renamed when complete."""
    return f"interrupted; nothing was written to {args.out} (rerun the same command)"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-export", build_parser, argv, {"ply": _ply}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
