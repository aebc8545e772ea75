"""Stage 1 benchmark: the tiny config trained on 2 CPU cores within 30 minutes, evaluated on held-out
synthetic scenes beside an oracle, with its training speed and memory.

Usage (from the repository root, on a quiet machine)::

    python benchmarks/stage1.py [--work /tmp/stage1-bench] [--vae-steps 1000] [--stage1-steps 560] [--reuse]

1. Caches (reused when present): ``--train-scenes`` synthetic scenes (seed 0) and ``--eval-scenes``
   held-out scenes (seed 100), 40 frames at 96 x 144, bundled synthetic pipeline.
2. ``phigenesis-train vae`` (vae_tiny, 5-frame clips at 48 x 72, 2 threads).
3. ``phigenesis-train stage1`` with ``configs/stage1/tiny.yaml`` under ``torchrun`` with 2 CPU
   processes of 1 thread each (gloo), each drawing one clip per step (batch 2).
4. ``phigenesis-eval stage1`` on the held-out cache: input views, +5/+10 frames, 1/2/4 m lateral
   shifts (truth rendered exactly), beside the oracle (one Gaussian per pixel at the true depth with
   the true colour), and the picture ``docs/images/stage1_eval.png``.

Peak RSS is the largest resident set of any one process of a step (``getrusage`` of the children);
step times are the medians of the ``seconds`` column of the runs' ``metrics.csv``. Writes the
``stage1`` section of BENCHMARKS.md. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import yaml
from _report import REPO_ROOT, Report

from phigenesis import prep
from phigenesis.train.runner import read_metrics

BIN = Path(sys.executable).parent


def _run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Runs a command (its paths hold no spaces), streaming its output; returns (wall seconds,
    peak RSS of its largest process so far in GiB)."""
    print("+", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env={**os.environ, **(env or {})})
    seconds = time.perf_counter() - t0
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return seconds, peak_kib / 2**20


def _cache(path: Path, scenes: int, seed: int) -> None:
    if (path / "manifest.json").exists():
        return
    prep.synthetic(path, scenes=scenes, frames=40, seed=seed, height=96, width=144, workers=2)


def _step_stats(run: Path, wall_s: float) -> tuple[float, int]:
    """(median seconds per step, steps) of a run: its logged step times, else wall time / steps."""
    rows = read_metrics(run)
    steps = int(max(r["step"] for r in rows))
    if all("seconds" in r for r in rows):
        return statistics.median(r["seconds"] for r in rows), steps
    return wall_s / steps, steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/stage1-bench"))
    ap.add_argument("--train-scenes", type=int, default=8)
    ap.add_argument("--eval-scenes", type=int, default=2)
    ap.add_argument("--vae-steps", type=int, default=1000)
    ap.add_argument("--stage1-steps", type=int, default=560)
    ap.add_argument("--clips-per-scene", type=int, default=3)
    ap.add_argument(
        "--reuse", action="store_true", help="keep trained runs in --work (and their timings, timings.json)"
    )
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    train_cache, eval_cache = work / "train", work / "eval"
    _cache(train_cache, args.train_scenes, 0)
    _cache(eval_cache, args.eval_scenes, 100)

    report = Report(
        "stage1",
        "Stage 1 (tiny config, 2 CPU cores)",
        f"Written by `benchmarks/stage1.py`. Training: {args.train_scenes} synthetic scenes (seed 0) x 40 "
        f"frames, 5 views at 96 x 144 in the cache, 48 x 72 in the model; evaluation: {args.eval_scenes} "
        "held-out scenes (seed 100). The VAE trains first (`phigenesis-train vae`, frozen afterwards), then "
        "the range-view adapter (`phigenesis-train stage1 --config configs/stage1/tiny.yaml` under "
        "`torchrun --nproc_per_node 2`, gloo, 1 thread per process, one clip per process per step; semantic "
        "labels: the synthetic truth, which `semantic_target: auto` takes where a cache has it).",
    )

    vae_run, s1_run = work / "vae", work / "stage1"
    timings_path = work / "timings.json"  # wall time and peak RSS of each phase, kept for --reuse
    timings = json.loads(timings_path.read_text()) if args.reuse and timings_path.exists() else {}
    if not (args.reuse and (vae_run / "model.safetensors").exists()):
        shutil.rmtree(vae_run, ignore_errors=True)
        timings["vae"] = _run(
            f"{BIN}/phigenesis-train vae --shards {train_cache} --out {vae_run} --steps {args.vae_steps} "
            "--threads 2 --size 48x72 --frames 5 --batch-size 4".split()
        )
    if not (args.reuse and (s1_run / "model.safetensors").exists()):
        shutil.rmtree(s1_run, ignore_errors=True)
        cfg = yaml.safe_load((REPO_ROOT / "configs/stage1/tiny.yaml").read_text())
        cfg |= {"vae_checkpoint": str(vae_run / "model.safetensors"), "steps": args.stage1_steps}
        cfg |= {"batch_size": 2, "threads": 1}
        cfg_path = work / "tiny.yaml"
        cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        timings["stage1"] = _run(
            f"{sys.executable} -m torch.distributed.run --nproc_per_node 2 -m phigenesis.cli.train stage1 "
            f"--shards {train_cache} --config {cfg_path} --out {s1_run} --no-progress".split(),
            env={"OMP_NUM_THREADS": "1"},
        )
    timings_path.write_text(json.dumps(timings))
    result = work / "eval.json"
    picture = REPO_ROOT / "docs/images/stage1_eval.png"
    timings["eval"] = _run(
        f"{BIN}/phigenesis-eval stage1 --ckpt {s1_run / 'model.safetensors'} --shards {eval_cache} "
        f"--out {result} --picture {picture} --clips-per-scene {args.clips_per_scene} --threads 2".split()
    )

    rows = []
    for name, run, batch in (("vae (vae_tiny)", vae_run, None), ("stage1 (stage1_tiny)", s1_run, 2)):
        wall, rss = timings.get(name.split()[0], (float("nan"), float("nan")))
        step_s, steps = _step_stats(run, wall)
        rows.append(
            [name, steps, f"{wall / 60:.1f}", f"{step_s:.2f}", f"{1 / step_s:.2f}", batch or "", f"{rss:.2f}"]
        )
    report.table(
        "Training speed and memory",
        ["run", "steps", "wall min", "median s/step", "steps/s", "clips/step", "peak RSS GiB"],
        rows,
        "Wall time includes start-up and validation; the 30-minute budget covers both runs together. "
        "Peak RSS: the largest process (each torchrun worker holds the model and its clips).",
    )
    metrics = json.loads(result.read_text())
    report.table(*_eval_table(metrics))
    report.text("![input, render, depth and semantics of a held-out clip](docs/images/stage1_eval.png)")
    report.write()


def _eval_table(metrics: dict) -> tuple[str, list[str], list[list[object]], str]:
    """The model-versus-oracle table from the evaluation JSON."""
    names = {"psnr_db": "PSNR dB", "ssim": "SSIM", "rmse_m": "depth RMSE m", "abs_rel": "AbsRel"}
    names |= {"delta_1_25": "δ<1.25", "miou": "mIoU"}
    headers = ["views", "images"] + [
        f"{label} {who}" for label in names.values() for who in ("model", "oracle")
    ]
    rows = []
    for section, entry in metrics["sections"].items():
        row: list[object] = [section, entry["images"]]
        for key in names:
            for who in ("model", "oracle"):
                value = entry.get(who, {}).get(key)
                row.append("—" if value is None else f"{value:.3f}")
        rows.append(row)
    note = (
        f"{metrics['clips']} clips ({metrics['seconds_per_clip']:.1f} s per clip to evaluate). Depth errors "
        "against the exact synthetic depth where the render covers a pixel; mIoU of the rendered semantics "
        "against the truth. Oracle: one Gaussian per input pixel at the true depth with the true colour and "
        "class, 0.3 pixel footprints wide, moving at the true flow, rendered by the same rasterizer."
    )
    return ("Held-out scenes: model against the oracle", headers, rows, note)


if __name__ == "__main__":
    main()
