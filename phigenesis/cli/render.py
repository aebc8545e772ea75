"""``phigenesis-render``: a cache as another rig's cameras would have seen it, written as a new cache (a
thin front end over :func:`phigenesis.infer.rig_render.render`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from phigenesis.cli.common import Parser, positive, positive_float, run, size_hw

if TYPE_CHECKING:
    from phigenesis.infer.insert import InsertSpec


def build_parser() -> argparse.ArgumentParser:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
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
    parser.add_argument(
        "--insert",
        metavar="ASSET",
        help="insert this asset into every frame: a mesh (OBJ, GLB/GLTF, PLY, STL, OFF; uncompressed) made "
        "into surface Gaussians, or a 3DGS PLY; its box joins the frames' boxes (needs --insert-pose or "
        "--insert-path, and --insert-class)",
    )
    parser.add_argument(
        "--insert-pose",
        action="append",
        metavar="POSE",
        help="x,y,z[,yaw_deg][@t_s]: the asset's position (metres) and heading (degrees about +z) at t_s "
        "seconds after the scene's first frame; repeat for a path (each with @t_s; linear in position, "
        "slerped in heading; held before the first and after the last)",
    )
    parser.add_argument(
        "--insert-path",
        metavar="PATH",
        help="a JSON or YAML file of keyframes instead of --insert-pose: "
        "{keyframes: [{t_s, xyz, yaw_deg} or {t_s, world_from_asset}, ...]}",
    )
    parser.add_argument(
        "--insert-frame",
        choices=("world", "ego"),
        default="world",
        help="poses in the cache's world frame (default) or in the ego frame of each scene's first frame",
    )
    parser.add_argument("--insert-class", metavar="NAME", help="the asset's class (car, person, truck, ...)")
    parser.add_argument(
        "--insert-scale", type=positive_float, default=1.0, help="the asset file's unit in metres (default 1)"
    )
    parser.add_argument(
        "--insert-spacing",
        type=positive_float,
        metavar="METRES",
        help="spacing of a mesh's surface Gaussians (default: its bounding-box diagonal / 100)",
    )
    parser.add_argument(
        "--insert-up",
        choices=("z", "y"),
        default="z",
        help="the asset file's up axis: z (x forward, y left; default) or y (glTF: +Z forward)",
    )
    parser.add_argument(
        "--export-ply",
        metavar="DIR",
        help="also write each scene's first rendered frame's (edited) Gaussians to DIR/<scene id>.ply",
    )
    parser.add_argument("--threads", type=positive, help="torch threads")
    parser.add_argument("--out", required=True, help="new folder for the rendered cache (or a run to resume)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(command="render")
    return parser


def _insert_specs(args: argparse.Namespace) -> list[InsertSpec]:
    """The --insert options as InsertSpecs (AssetError naming the option that is wrong)."""
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.infer.insert import AssetError, InsertSpec, load_path_file, parse_keyframe

    given = [name for name in ("insert_pose", "insert_path", "insert_class") if getattr(args, name)]
    if args.insert is None:
        if given:
            raise AssetError(f"--{given[0].replace('_', '-')} needs --insert ASSET")
        return []
    if (args.insert_pose is None) == (args.insert_path is None):
        raise AssetError("--insert needs its pose: --insert-pose (repeatable) or --insert-path, not both")
    if args.insert_class is None:
        raise AssetError("--insert needs --insert-class NAME (the class of the asset's box)")
    if args.insert_path is not None:
        keyframes = load_path_file(args.insert_path)
    else:
        keyframes = [parse_keyframe(text) for text in args.insert_pose]
    spec = InsertSpec(
        Path(args.insert),
        tuple(keyframes),
        args.insert_class,
        frame=args.insert_frame,
        scale=args.insert_scale,
        spacing_m=args.insert_spacing,
        up=args.insert_up,
    )
    return [spec]


def _render(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.infer.rig_render import render

    height, width = args.size if args.size else (None, None)
    inserts = _insert_specs(args)
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
        insert=inserts,
        export_ply=args.export_ply,
    )
    per_frame = result.seconds / max(result.frames, 1)
    print(
        f"rendered {result.frames} frames of {len(result.scenes)} scenes in {result.seconds:.1f} s "
        f"({per_frame:.2f} s/frame)"
    )
    if result.skipped:
        print(f"already rendered, skipped: {', '.join(result.skipped)}")
    print(f"cache: {result.out} (phigenesis-prep verify {result.out})")
    if args.export_ply:
        written = [Path(args.export_ply) / f"{scene}.ply" for scene in result.scenes]
        shown = ", ".join(str(p) for p in written if p.is_file()) or "none (every scene was already rendered)"
        print(f"edited Gaussians: {shown}")
    return 0


def interrupted(args: argparse.Namespace) -> str:
    return f"interrupted; rerun the same command to resume {args.out} after its last finished scene"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-render", build_parser, argv, {"render": _render}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
