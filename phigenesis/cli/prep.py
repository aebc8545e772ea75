"""``phigenesis-prep``: build, verify and preview caches (a thin front end over phigenesis.prep)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from phigenesis import prep
from phigenesis.cli.common import Command, Parser, positive, run
from phigenesis.data.executors import EXECUTORS
from phigenesis.data.shards import CacheReader, Manifest
from phigenesis.data.sources.synthetic_names import PRESET_NAMES, RIG_NAMES
from phigenesis.malloc_tuning import avoid_huge_page_faults, keep_freed_memory


def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="cache directory (created if missing)")
    p.add_argument("--pipeline", help="pipeline spec: a bundled name or a YAML path")
    p.add_argument("--workers", type=positive, default=1, help="scenes processed in parallel (default 1)")
    p.add_argument("--executor", choices=EXECUTORS, default="local", help="local process pool or Ray")
    p.add_argument(
        "--ray-address", help="Ray cluster address for --executor ray (default: start a local Ray)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace a cache made with other arguments")
    p.add_argument(
        "--on-error", choices=("raise", "skip"), default="raise", help="stop at a failed scene, or skip it"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _run_arguments(args: argparse.Namespace, pipeline: str) -> dict[str, Any]:
    """The run options of a conversion command (see :func:`_run_options`) as keyword arguments."""
    return {
        "pipeline": args.pipeline or pipeline,
        "executor": args.executor,
        "workers": args.workers,
        "ray_address": args.ray_address,
        "overwrite": args.overwrite,
        "on_error": args.on_error,
        "progress": not args.no_progress,
    }


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="phigenesis-prep", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synthetic", help="render synthetic driving scenes with exact truth into a cache")
    s.add_argument("--scenes", type=positive, default=2, help="number of scenes (default 2)")
    s.add_argument("--frames", type=positive, default=40, help="frames per scene (default 40)")
    s.add_argument("--seed", type=int, default=0, help="base random seed (default 0)")
    s.add_argument("--rig", choices=RIG_NAMES, help="camera rig (default from the pipeline: waymo5)")
    s.add_argument("--height", type=positive, help="image height in pixels (default 160)")
    s.add_argument("--width", type=positive, help="image width in pixels (default 240)")
    s.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        help="the real rig's sensor sizes (waymo: 5 cameras at 1920 x 1280/886, five LiDARs, two returns; "
        "nuscenes: 6 cameras at 1600 x 900, a 32-beam LiDAR); --rig/--height/--width override it",
    )
    s.add_argument(
        "--render-scale",
        type=positive,
        help="ray cast the images at 1/N of their size and resize them (cost benchmarks; default 1)",
    )
    _run_options(s)

    w = sub.add_parser("waymo", help="convert Waymo Open Dataset segments (v1 TFRecord or v2 Parquet)")
    w.add_argument(
        "--input",
        required=True,
        help="a .tfrecord file, a folder of them, or a v2 root ({component}/{segment}.parquet)",
    )
    w.add_argument("--split", help="subfolder of --input to read (training, validation, testing)")
    w.add_argument(
        "--segment",
        action="append",
        default=[],
        dest="segments",
        help="keep this segment (name or shell pattern); repeat for more (default: all)",
    )
    w.add_argument(
        "--format", choices=("auto", "v1", "v2"), default="auto", help="input format (default: detect)"
    )
    w.add_argument("--no-crc", action="store_true", help="do not check the TFRecord CRCs (faster, unsafe)")
    _run_options(w)

    n = sub.add_parser("nuscenes", help="convert nuScenes scenes (JSON tables, images, LIDAR_TOP)")
    n.add_argument("--dataroot", required=True, help="folder holding <version>/, samples/, sweeps/, maps/")
    n.add_argument("--version", default="v1.0-mini", help="table folder: v1.0-mini (default), v1.0-trainval")
    n.add_argument(
        "--scenes",
        nargs="+",
        default=[],
        help="keep these scenes (names or shell patterns, e.g. scene-0061 'scene-01*'; default: all)",
    )
    _run_options(n)

    v = sub.add_parser(
        "verify",
        help="re-check every shard of a cache against its manifest, and whether its run finished",
        description="Re-checks a cache (from prep, render, generate or Stage 2's latents) against its\n"
        "manifest: every shard's size, checksums, rows and columns; then whether the run that wrote\n"
        "it finished every scene its arguments asked for.",
        epilog=VERIFY_EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    v.add_argument("cache", help="cache directory")

    pv = sub.add_parser("preview", help="draw one frame of a cache to a PNG")
    pv.add_argument("cache", help="cache directory")
    pv.add_argument("--frame", type=int, default=0, help="global frame index (default 0)")
    pv.add_argument("--out", required=True, help="PNG file to write")
    pv.add_argument("--scale", type=positive, default=2, help="image magnification (default 2)")
    return parser


def _synthetic(args: argparse.Namespace) -> int:
    summary = prep.synthetic(
        args.out,
        scenes=args.scenes,
        frames=args.frames,
        seed=args.seed,
        rig=args.rig,
        height=args.height,
        width=args.width,
        preset=args.preset,
        render_scale=args.render_scale,
        **_run_arguments(args, "synthetic"),
    )
    print(summary.describe())
    return 0


def _waymo(args: argparse.Namespace) -> int:
    summary = prep.waymo(
        args.out,
        input=args.input,
        split=args.split,
        segments=args.segments,
        format=args.format,
        check_crc=not args.no_crc,
        **_run_arguments(args, "waymo"),
    )
    print(summary.describe())
    return 0


def _nuscenes(args: argparse.Namespace) -> int:
    summary = prep.nuscenes(
        args.out,
        dataroot=args.dataroot,
        version=args.version,
        scenes=args.scenes,
        **_run_arguments(args, "nuscenes"),
    )
    print(summary.describe())
    return 0


#: ``phigenesis-prep verify``'s exit status for each :attr:`~phigenesis.data.shards.VerifyReport.status`.
VERIFY_EXIT = {"OK": 0, "DAMAGED": 1, "INCOMPLETE": 3}
VERIFY_EXIT_CODES = """exit status:
  0  OK: every shard matches its manifest and every scene the run asked for is finished
     (or, for a cache written before manifests recorded them, nothing more can be checked)
  1  DAMAGED: a shard or the manifest is missing, corrupt or inconsistent (each problem named)
  2  the command itself could not run (a bad argument)
  3  INCOMPLETE: intact, but the run that wrote it did not finish every scene it asked for (it was
     stopped: killed, a full disk, a failed scene); rerunning the same command resumes it"""


def _verify(args: argparse.Namespace) -> int:
    report = prep.verify(args.cache)
    for w in report.warnings:
        print(f"warning: {w}")
    for e in report.errors:
        print(f"BAD: {e}")
    if report.manifest_read:
        label = {None: "note", True: "complete", False: "incomplete"}[report.complete]
        print(f"{label}: {report.completeness()}")
    status = report.status + (f" ({len(report.errors)} problems)" if report.errors else "")
    print(f"{args.cache}: {report.shards} shards, {report.frames} frames verified: {status}")
    return VERIFY_EXIT[report.status]


def _preview(args: argparse.Namespace) -> int:
    frames = len(CacheReader(args.cache))
    if not -frames <= args.frame < frames:
        raise ValueError(f"--frame {args.frame} is out of range: {args.cache} holds {frames} frames")
    prep.preview(args.cache, frame=args.frame, out=args.out, scale=args.scale)
    print(f"wrote {args.out}")
    return 0


COMMANDS: dict[str, Command] = {
    "synthetic": _synthetic,
    "waymo": _waymo,
    "nuscenes": _nuscenes,
    "verify": _verify,
    "preview": _preview,
}


def complete_scenes(cache_dir: str | os.PathLike[str]) -> int:
    """How many scenes the manifest in ``cache_dir`` records as complete; 0 when a run was stopped
    before writing one (or left one that cannot be read)."""
    try:
        manifest = Manifest.load(Path(cache_dir))
    except Exception:  # no manifest yet, or one the run never finished writing: nothing is kept
        return 0
    return sum(s.status == "complete" for s in manifest.scenes)


def interrupted(args: argparse.Namespace) -> str:
    """What Ctrl-C leaves: a conversion keeps its complete scenes (counted from the manifest, which
    is rewritten after each scene) and resumes when rerun; verify and preview change nothing."""
    if args.command == "verify":
        return "interrupted; nothing was changed"
    if args.command == "preview":
        return f"interrupted; {args.out} was not written"
    done = complete_scenes(args.out)
    if args.command == "synthetic":
        kept = f"{done} of {args.scenes} scenes are complete"
    else:
        kept = f"{done} scene is complete" if done == 1 else f"{done} scenes are complete"
    return f"interrupted; {kept} in {args.out} (rerun the same command to resume)"


def main(argv: list[str] | None = None) -> int:
    keep_freed_memory()  # frame after frame of the same sizes: reuse the pages (see the module)
    avoid_huge_page_faults()  # a frame's arrays live for one frame: 4 KiB pages (see the module)
    return run("phigenesis-prep", build_parser, argv, COMMANDS, interrupted)


if __name__ == "__main__":
    sys.exit(main())
