"""``phigenesis-eval``: evaluate trained models on caches (a thin front end over phigenesis.train).

Subcommand ``stage1`` (:func:`phigenesis.train.evaluate_stage1.evaluate_stage1`): renders a Stage 1
model's Gaussians at the context views, at future frames and at laterally shifted novel views and
prints PSNR, SSIM, depth errors and mIoU beside those of a ground-truth-depth oracle.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from phigenesis.cli.common import Parser, positive, run

#: Table columns: (metric key, header, format).
COLUMNS = (
    ("psnr_db", "PSNR", "{:6.2f}"),
    ("ssim", "SSIM", "{:6.3f}"),
    ("rmse_m", "RMSE", "{:6.2f}"),
    ("abs_rel", "AbsRel", "{:6.3f}"),
    ("delta_1_25", "δ<1.25", "{:6.3f}"),
    ("miou", "mIoU", "{:6.3f}"),
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
    return parser


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
    from phigenesis.train.evaluate_stage1 import evaluate_stage1

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
    return run("phigenesis-eval", build_parser, argv, {"stage1": _stage1}, interrupted)


if __name__ == "__main__":
    sys.exit(main())
