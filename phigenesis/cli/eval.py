"""``phigenesis-eval``: evaluate trained models on caches (a thin front end over phigenesis.train).

Subcommand ``stage1`` (:func:`phigenesis.eval.stage1.evaluate_stage1`): renders a Stage 1
model's Gaussians at the context views, at future frames and at laterally shifted novel views and
prints PSNR, SSIM, depth errors and mIoU beside those of a ground-truth-depth oracle.
Subcommand ``stage2`` (:func:`phigenesis.eval.stage2.evaluate_stage2`): rolls a Stage 2 model out on
held-out synthetic scenes and scores future frames, shifted trajectories and long rollouts against
the exact truth, beside the history's Stage 1 render alone.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from phigenesis.cli.common import Parser, add_anchor_options, positive, run

#: Table columns: (metric key, header, format).
COLUMNS = (
    ("psnr_db", "PSNR", "{:6.2f}"),
    ("ssim", "SSIM", "{:6.3f}"),
    ("rmse_m", "RMSE", "{:6.2f}"),
    ("abs_rel", "AbsRel", "{:6.3f}"),
    ("delta_1_25", "δ<1.25", "{:6.3f}"),
    ("miou", "mIoU", "{:6.3f}"),
    ("psnr_dynamic_db", "dynPSNR", "{:6.2f}"),
    ("epe3d_mps", "EPE3D", "{:6.3f}"),
    ("acc5", "Acc5", "{:6.3f}"),
)


def _shift(value: str) -> float:
    d = float(value)
    if not math.isfinite(d):
        raise argparse.ArgumentTypeError(f"must be a finite distance in metres, got {value!r}")
    return d


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="phigenesis-eval", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("stage1", help="evaluate a Stage 1 model (a run's model.safetensors) on a cache")
    s.add_argument("--ckpt", required=True, help="Stage 1 checkpoint (file or run folder)")
    s.add_argument("--shards", required=True, help="cache directory to evaluate on (held-out scenes)")
    s.add_argument("--out", help="write the results as JSON here")
    s.add_argument(
        "--offsets", type=positive, nargs="+", default=[5, 10], help="future frames (default 5 10)"
    )
    s.add_argument(
        "--shifts", type=_shift, nargs="*", default=[1.0, 2.0, 4.0], help="lateral shifts, m (default 1 2 4)"
    )
    s.add_argument("--clips-per-scene", type=positive, default=3, help="clips per scene (default 3)")
    s.add_argument("--no-oracle", action="store_true", help="skip the ground-truth-depth oracle")
    s.add_argument("--picture", help="write a PNG of the first clip here")
    s.add_argument("--threads", type=positive, help="torch CPU threads")

    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.rollout.conditions import UNCERTAINTY_KINDS

    d = sub.add_parser("stage2", help="evaluate a Stage 2 model on held-out synthetic scenes")
    d.add_argument("--ckpt", required=True, help="Stage 2 checkpoint (file or run folder)")
    d.add_argument("--shards", required=True, help="held-out cache (synthetic for the shifted views)")
    d.add_argument("--stage1", help="Stage 1 checkpoint (default: the one the model was trained with)")
    d.add_argument("--out", help="write the results as JSON here")
    d.add_argument(
        "--offsets", type=positive, nargs="*", default=[5, 10], help="future frames (default 5 10)"
    )
    d.add_argument("--shifts", type=_shift, nargs="*", default=[1.0, 2.0, 4.0], help="lateral shifts, m")
    d.add_argument(
        "--rollout-frames", type=positive, nargs="*", default=[50, 100, 150, 200], help="long-rollout frames"
    )
    d.add_argument("--clips-per-scene", type=positive, default=1, help="clips per scene (default 1)")
    d.add_argument("--uncertainty", choices=(*UNCERTAINTY_KINDS, "none"), help="default: the trained one")
    d.add_argument("--omega", type=float, default=1.0, help="guidance scale (default 1)")
    d.add_argument("--steps", type=positive, default=10, help="Euler steps per window (default 10)")
    d.add_argument("--seed", type=int, default=0, help="seed of the noise")
    add_anchor_options(d)
    d.add_argument("--fid-model", help="local TorchScript Inception (default_1.pt) for FID/KID")
    d.add_argument(
        "--fid-frames",
        type=positive,
        help="generated frames ending at each rollout frame that its FID/KID pools (default: one window's)",
    )
    d.add_argument("--picture", help="write a PNG of the first clip here")
    d.add_argument("--threads", type=positive, help="torch CPU threads")
    return parser


def format_stage2_table(report: dict[str, Any]) -> str:
    """The Stage 2 report as a text table: one row per section, the generated frames beside the
    render alone (no diffusion) and the VAE's reconstruction of the truth (the ceiling of any
    generated frame, when the report has it)."""
    ceiling = any("vae_reconstruction" in e for e in report["sections"].values())
    top = f"{'':12s} {'':6s}  {'generated':^34s}  | {'render only':^13s}"
    head = f"{'section':12s} {'images':>6s}  {'PSNR':>6s} {'SSIM':>6s} {'AbsRel':>6s} {'FID':>7s} {'KID':>7s}"
    head += f"  | {'PSNR':>6s} {'SSIM':>6s}"
    if ceiling:
        top += f"  | {'VAE ceiling':^20s}"
        head += f"  | {'PSNR':>6s} {'SSIM':>6s} {'FID':>6s}"
    lines = [top, head]
    for name, entry in report["sections"].items():
        g, r = entry["generated"], entry["render_only"]
        row = (
            f"{name:12s} {int(g['images']):6d}  {_cell(g, 'psnr_db', '{:6.2f}')} "
            f"{_cell(g, 'ssim', '{:6.3f}')} {_cell(g, 'abs_rel', '{:6.3f}')} "
            f"{_cell(g, 'fid', '{:7.2f}')} {_cell(g, 'kid', '{:7.4f}')}"
            f"  | {_cell(r, 'psnr_db', '{:6.2f}')} {_cell(r, 'ssim', '{:6.3f}')}"
        )
        if ceiling:
            v = entry.get("vae_reconstruction")
            row += f"  | {_cell(v, 'psnr_db', '{:6.2f}')} {_cell(v, 'ssim', '{:6.3f}')} "
            row += _cell(v, "fid", "{:6.2f}")
        lines.append(row)
    lines.append(f"{report['clips']} clips, {report['seconds_per_frame']:.2f} s per generated frame")
    return "\n".join(lines)


def _stage2(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.eval.stage2 import evaluate_stage2
    from phigenesis.rollout.runner import GenerateOptions, trained_uncertainty

    options = GenerateOptions(
        uncertainty=args.uncertainty or trained_uncertainty(args.ckpt),
        omega=args.omega,
        steps=args.steps,
        anchor=args.anchor,
        anchor_until=args.anchor_until,
        paste=args.paste,
        generated_trust=args.generated_trust,
        spawn_max_u=args.spawn_max_u,
        lift_frames=args.lift_frames,
        lp_trust=args.lp_trust,
        geometry=args.geometry,
        seed=args.seed,
    )
    report = evaluate_stage2(
        args.ckpt,
        args.shards,
        stage1=args.stage1,
        options=options,
        offsets=tuple(args.offsets),
        shifts_m=tuple(args.shifts),
        rollout_frames=tuple(args.rollout_frames),
        clips_per_scene=args.clips_per_scene,
        fid_model=args.fid_model,
        out_json=args.out,
        picture=args.picture,
        threads=args.threads,
        fid_frames=args.fid_frames,
    )
    print(format_stage2_table(report))
    if args.out:
        print(f"results: {args.out}")
    if args.picture:
        print(f"picture: {args.picture}")
    return 0


def _cell(values: dict[str, Any] | None, key: str, fmt: str) -> str:
    value = None if values is None else values.get(key)
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return f"{'-':>6s}"
    return fmt.format(value)


def format_table(report: dict[str, Any]) -> str:
    """The report's sections as a text table: one row per section, the model's metrics and (when
    scored) the oracle's."""
    has_oracle = any("oracle" in e for e in report["sections"].values())
    header = " ".join(f"{h:>6s}" for _, h, _ in COLUMNS)
    width = len(header)
    top = f"{'':10s} {'images':>6s}  {'model':^{width}s}"
    head = f"{'section':10s} {'':6s}  {header}"
    if has_oracle:
        top += f"  | {'oracle':^{width}s}"
        head += f"  | {header}"
    lines = [top, head]
    for name, entry in report["sections"].items():
        row = f"{name:10s} {entry['images']:6d}  " + " ".join(
            _cell(entry["model"], k, f) for k, _, f in COLUMNS
        )
        if has_oracle:
            row += "  | " + " ".join(_cell(entry.get("oracle"), k, f) for k, _, f in COLUMNS)
        lines.append(row)
    clips, seconds = report["clips"], report["seconds_per_clip"]
    lines.append(f"{clips} clips, {seconds:.1f} s per clip; checkpoint {report['checkpoint']}")
    return "\n".join(lines)


def _stage1(args: argparse.Namespace) -> int:
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.eval.stage1 import evaluate_stage1

    report = evaluate_stage1(
        args.ckpt,
        args.shards,
        offsets=tuple(args.offsets),
        shifts_m=tuple(args.shifts),
        clips_per_scene=args.clips_per_scene,
        oracle=not args.no_oracle,
        picture=args.picture,
        threads=args.threads,
        out_json=args.out,
    )
    print(format_table(report))
    if args.out:
        print(f"results: {args.out}")
    if args.picture:
        print(f"picture: {args.picture}")
    return 0


def interrupted(args: argparse.Namespace) -> str:
    """Ctrl-C: the JSON and the picture are written only when every clip is scored."""
    return "interrupted before every clip was scored; no results were written (rerun the same command)"


def main(argv: list[str] | None = None) -> int:
    return run("phigenesis-eval", build_parser, argv, {"stage1": _stage1, "stage2": _stage2}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
