"""``phigenesis-generate``: roll a scene out along a trajectory with a trained Stage 2 model and write the
generated frames as a cache (a thin front end over :func:`phigenesis.infer.generate.generate`)."""

from __future__ import annotations

import argparse
import sys

from phigenesis.cli.common import Parser, add_anchor_options, positive, run


def build_parser() -> argparse.ArgumentParser:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.rollout.conditions import UNCERTAINTY_KINDS

    parser = Parser(prog="phigenesis-generate", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument(
        "--ckpt", required=True, help="Stage 2 checkpoint (a run's model.safetensors or run folder)"
    )
    parser.add_argument(
        "--shards", required=True, help="frame cache holding the scene (its history and poses)"
    )
    parser.add_argument("--scene", required=True, help="scene id in the cache")
    parser.add_argument(
        "--start", type=int, required=True, help="first generated frame (the history is before it)"
    )
    parser.add_argument("--frames", type=positive, required=True, help="frames to generate")
    parser.add_argument(
        "--trajectory",
        default="recorded",
        help="recorded (the cache's poses), shift:Xm (moved X m left; negative: right) or a JSON file",
    )
    parser.add_argument(
        "--uncertainty",
        choices=(*UNCERTAINTY_KINDS, "none"),
        help="Stereo Forcing's map (default: the one the model was trained with)",
    )
    parser.add_argument(
        "--omega", type=float, default=1.0, help="guidance scale (default 1: the conditional model)"
    )
    parser.add_argument("--steps", type=positive, default=10, help="Euler steps per window (default 10)")
    parser.add_argument(
        "--history-level", type=float, default=0.02, help="noise level generated history is held at"
    )
    add_anchor_options(parser)
    parser.add_argument("--max-gaussians", type=positive, default=200_000, help="the Gaussian buffer's bound")
    parser.add_argument(
        "--stage1", help="Stage 1 checkpoint (default: the one the Stage 2 model was trained with)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise")
    parser.add_argument(
        "--out",
        required=True,
        help="new folder for the generated cache, strip.png and PLYs (or a stopped run of the same "
        "command: rerunning it generates the rollout again)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(command="generate")
    return parser


def _generate(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.infer.generate import generate
    from phigenesis.rollout.runner import GenerateOptions, trained_uncertainty

    kind = args.uncertainty or trained_uncertainty(args.ckpt)
    options = GenerateOptions(
        uncertainty=kind,
        omega=args.omega,
        steps=args.steps,
        history_level=args.history_level,
        anchor=args.anchor,
        anchor_until=args.anchor_until,
        paste=args.paste,
        generated_trust=args.generated_trust,
        spawn_max_u=args.spawn_max_u,
        lift_frames=args.lift_frames,
        lp_trust=args.lp_trust,
        geometry=args.geometry,
        max_gaussians=args.max_gaussians,
        seed=args.seed,
    )
    result = generate(
        args.ckpt,
        args.shards,
        args.scene,
        args.start,
        args.frames,
        args.out,
        trajectory=args.trajectory,
        stage1=args.stage1,
        options=options,
        progress=not args.no_progress,
    )
    if result.rollout is None:
        print(f"{result.out} already holds this rollout (the same command finished it); nothing to do")
    else:
        per_frame = sum(result.rollout.seconds_per_window) / args.frames
        print(f"generated {args.frames} frames in {result.seconds:.1f} s ({per_frame:.2f} s/frame)")
    print(f"cache: {result.out} (phigenesis-prep verify {result.out}); strip: {result.strip}")
    return 0


def interrupted(args: argparse.Namespace) -> str:
    return f"interrupted; {args.out} holds no finished rollout (rerun the same command to generate it)"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-generate", build_parser, argv, {"generate": _generate}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
