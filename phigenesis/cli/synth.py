"""``phigenesis-synth``: write synthetic scenes in a dataset's own format (over phigenesis.synth)."""

from __future__ import annotations

import os

# numpy's BLAS single-threaded unless the user says otherwise (set before numpy loads): the
# renderer's matrix products are (N, 3) x (3, 3), where threads gain nothing and, on a busy
# machine, spinning BLAS threads slow every transform down.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys

from phigenesis.cli.common import Parser, positive, run
from phigenesis.data.sources.synthetic_names import PRESET_NAMES
from phigenesis.synth import SYNTH_FORMATS, synth


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="phigenesis-synth", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--format", required=True, choices=SYNTH_FORMATS, help="the dataset format to write")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--scenes", type=positive, default=1, help="number of scenes (default 1)")
    p.add_argument("--frames", type=positive, default=10, help="frames per scene (default 10)")
    p.add_argument("--seed", type=int, default=0, help="base random seed (default 0)")
    p.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        help="the real dataset's sensor sizes: waymo (5 cameras 1920x1280/886, 5 LiDARs x 2 returns; "
        "waymo-v1/v2) or nuscenes (6 cameras 1600x900 at 12 Hz, HDL-32E LiDAR; nuscenes)",
    )
    p.add_argument(
        "--height", type=positive, default=None, help="image height, pixels (default: the preset's, else 160)"
    )
    p.add_argument(
        "--width", type=positive, default=None, help="image width, pixels (default: the preset's, else 240)"
    )
    p.add_argument(
        "--render-scale",
        type=positive,
        default=1,
        help="cast images at 1/N of their size in each axis and resize them (cost benchmarks; "
        "truth inexact at edges; the LiDAR stays at full density; default 1)",
    )
    p.add_argument(
        "--keyframes", type=positive, default=3, help="nuscenes: 2 Hz keyframes per scene (default 3)"
    )
    p.add_argument("--version", default="v1.0-mini", help="nuscenes: the tables' folder (default v1.0-mini)")
    p.add_argument(
        "--drop",
        action="append",
        default=[],
        type=_camera_step,
        metavar="CAMERA:STEP",
        help="nuscenes: leave out this camera's sweep at this 12 Hz step (a non-keyframe); repeatable",
    )
    p.set_defaults(command="synth")  # one command: dispatch runs it
    return p


def _camera_step(value: str) -> tuple[str, int]:
    camera, _, step = value.rpartition(":")
    if not camera or not step.isdigit():
        raise argparse.ArgumentTypeError(f"expected CAMERA:STEP (e.g. CAM_BACK:3), got {value!r}")
    return camera, int(step)


def _synth(args: argparse.Namespace) -> int:
    paths = synth(
        args.format,
        args.out,
        scenes=args.scenes,
        frames=args.frames,
        seed=args.seed,
        height=args.height,
        width=args.width,
        preset=args.preset,
        render_scale=args.render_scale,
        **(
            {"keyframes": args.keyframes, "version": args.version, "dropped": args.drop}
            if args.format == "nuscenes"
            else {}
        ),
    )
    files = sorted({p.parent if args.format in ("waymo-v2", "nuscenes") else p for p in paths})
    print(
        f"wrote {len(paths)} files ({args.format}) under {args.out}: " + ", ".join(str(f) for f in files[:6])
    )
    return 0


def interrupted(args: argparse.Namespace) -> str:
    """Ctrl-C: the dataset under ``--out`` is incomplete; a rerun writes every file again."""
    return f"interrupted; the files under {args.out} are incomplete (rerun the same command to write them)"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-synth", build_parser, argv, {"synth": _synth}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
