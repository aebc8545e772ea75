"""Stage 1 benchmark: the tiny config trained on 2 CPU cores within 30 minutes, evaluated on held-out
synthetic scenes beside an oracle, with its training speed and memory.

Usage (from the repository root, on a quiet machine)::

    python benchmarks/stage1.py [--work /tmp/stage1-bench] [--vae-steps 1000] [--budget-min 30] [--reuse]
    python benchmarks/stage1.py --stage1-steps 560   # a fixed step count instead of the budget

1. Caches (reused when present): ``--train-scenes`` synthetic scenes (seed 1000) of ``--train-frames``
   frames and ``--eval-scenes`` held-out scenes (seed 100) of 40 frames, at 96 x 144, bundled
   synthetic pipeline.
2. ``phigenesis-train vae`` (vae_tiny, 5-frame clips at 48 x 72, 2 threads).
3. Step time before/after the native rasterizer and projection: ``--speed-steps`` (15) steps of the
   same Stage 1 run (same config, VAE and ``torchrun`` setup as step 4), once with
   ``PHIGENESIS_RASTERIZER=torch`` (tiled PyTorch), once with ``PHIGENESIS_RASTERIZER=cpu`` and
   ``PHIGENESIS_PROJECTION=torch`` (the native kernel, the projection in PyTorch) and once with the
   native kernel and projection; not counted in the budget.
4. ``phigenesis-train stage1`` with ``configs/stage1/tiny.yaml`` under ``torchrun`` with 2 CPU
   processes of 1 thread each (gloo), each drawing one clip per step (batch 2), with the native
   rasterizer where it builds. Its steps fill the budget: the trainer has no wall-clock limit (its
   cosine schedule needs the step count up front), so ``steps = floor((budget - VAE wall - start-up)
   x (1 - margin) / s_per_step)``, with the native speed run's mean step time (after the first step)
   and the start-up (wall time less the steps) of the speed runs in step 3; ``--stage1-steps`` fixes
   it instead.
   The run also gets the remaining budget as a wall-clock limit (``--time-limit-min``): if the
   estimate was too long, it ends at the budget with its weights written (the table says so).
5. ``phigenesis-eval stage1`` on the held-out cache: input views, +5/+10 frames, 1/2/4 m lateral
   shifts (truth rendered exactly), beside the oracle (one Gaussian per pixel at the true depth with
   the true colour), and the picture ``docs/images/stage1_eval.png``; ``--baseline CKPT`` scores an
   earlier Stage 1 checkpoint on the same held-out cache beside them (the "old" rows).
6. The input views again on ``--wide-eval-scenes`` (8) more held-out scenes (seed 300, 12 frames, 3
   clips each: 120 images against step 5's 30), new model and baseline: two held-out scenes are few
   enough that which scenes they are moves δ<1.25 by more than a change of model does.

Peak RSS is the largest resident set of any one process of a step (``wait4`` of that step's command:
torchrun and its workers included); step times are the medians of the ``seconds`` column of the
runs' ``metrics.csv``. Writes the
``stage1`` section of BENCHMARKS.md. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import REPO_ROOT, Report, add_update_flag, output_path

from phigenesis import prep
from phigenesis.models.checkpoint import read_safetensors_metadata
from phigenesis.models.rasterizer import native_available
from phigenesis.train.runner import read_metrics

BIN = Path(sys.executable).parent
#: The wider held-out set of input views (step 6): scenes of another seed than the training (1000) and
#: the main held-out (100) caches, short, since only their input views are scored.
WIDE_EVAL_SEED = 300
WIDE_EVAL_FRAMES = 12
#: PHIGENESIS_RASTERIZER values of the two full-run choices, and their names in the tables.
SPEED_BACKENDS = {"torch": "tiled PyTorch", "cpu": "native C++"}
#: The speed runs: key -> (name, environment). The second is the first native version (its projection,
#: forward and backward, still in PyTorch); the last is what the full run uses where the kernel builds.
SPEED_RUNS = {
    "torch": ("tiled PyTorch rasterizer", {"PHIGENESIS_RASTERIZER": "torch"}),
    "cpu-torch-projection": (
        "native C++ rasterizer, PyTorch projection",
        {"PHIGENESIS_RASTERIZER": "cpu", "PHIGENESIS_PROJECTION": "torch"},
    ),
    "cpu": ("native C++ rasterizer and projection", {"PHIGENESIS_RASTERIZER": "cpu"}),
}


def _run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Runs a command (its paths hold no spaces), streaming its output; returns (wall seconds,
    peak RSS in GiB of its largest process: the command itself or any child it waited for)."""
    print("+", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env={**os.environ, **(env or {})})
    _, status, usage = os.wait4(proc.pid, 0)  # this command's own rusage, its descendants included
    proc.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return seconds, usage.ru_maxrss / 2**20  # Linux: KiB


def _train_stage1(
    train_cache: Path,
    vae_run: Path,
    out: Path,
    steps: int,
    env: dict[str, str],
    time_limit_s: float | None = None,
) -> tuple[float, float]:
    """Stage 1 of ``configs/stage1/tiny.yaml`` for ``steps`` steps under torchrun (2 x 1 thread) with
    ``env`` (the rasterizer's choice); (wall seconds, peak RSS GiB)."""
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load((REPO_ROOT / "configs/stage1/tiny.yaml").read_text())
    cfg |= {"vae_checkpoint": str(vae_run / "model.safetensors"), "steps": steps}
    cfg |= {"batch_size": 2, "threads": 1}
    cfg_path = out.with_name(f"{out.name}.yaml")
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return _run(
        f"{sys.executable} -m torch.distributed.run --nproc_per_node 2 -m phigenesis.cli.train stage1 "
        f"--shards {train_cache} --config {cfg_path} --out {out} --no-progress".split()
        + ([] if time_limit_s is None else ["--time-limit-min", f"{time_limit_s / 60:.3f}"]),
        env={"OMP_NUM_THREADS": "1", **env},
    )


def _step_seconds(run: Path) -> list[float]:
    """The logged ``seconds`` of every step of a run, in step order."""
    rows = sorted(read_metrics(run), key=lambda r: r["step"])
    return [r["seconds"] for r in rows if "seconds" in r]


def _per_step(seconds: list[float]) -> float:
    """Mean step time after the first step (which also warms up)."""
    return statistics.mean(seconds[1:] if len(seconds) > 1 else seconds)


def budget_steps(
    budget_s: float,
    vae_wall_s: float,
    speed: dict[str, tuple[list[float], float, float]],
    backend: str,
    margin: float,
) -> tuple[int, float, float]:
    """Stage 1 steps with ``backend`` that fit ``budget_s`` after the VAE, from the short speed runs
    ``speed`` (backend: (step seconds, wall s, RSS)); (steps, s_per_step, start-up s).

    Start-up: a run's wall time less its steps at the mean step time, the smallest over the speed runs
    (a run that had to build the native kernel first would otherwise overstate it)."""
    per_step = _per_step(speed[backend][0])
    startup = min(max(wall - _per_step(sec) * len(sec), 0.0) for sec, wall, _ in speed.values())
    steps = math.floor((budget_s - vae_wall_s - startup) * (1.0 - margin) / per_step)
    return steps, per_step, startup


def _cache(path: Path, scenes: int, seed: int, frames: int) -> None:
    if (path / "manifest.json").exists():
        return
    prep.synthetic(path, scenes=scenes, frames=frames, seed=seed, height=96, width=144, workers=2)


def _step_stats(run: Path, wall_s: float) -> tuple[float, int]:
    """(median seconds per step, steps) of a run: its logged step times, else wall time / steps (a
    reused run folder that kept only its weights: the steps its checkpoint's header records)."""
    if not (run / "metrics.csv").is_file():
        meta = json.loads(read_safetensors_metadata(run / "model.safetensors").get("meta", "{}"))
        steps = int(meta["steps"])
        return wall_s / steps, steps
    rows = read_metrics(run)
    steps = int(max(r["step"] for r in rows))
    if all("seconds" in r for r in rows):
        return statistics.median(r["seconds"] for r in rows), steps
    return wall_s / steps, steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/stage1-bench"))
    # Many short scenes: at equal steps, 32 scenes of 12 frames held out far better than 8 of 40
    # (frames of one scene are near copies of each other; scenes are what varies).
    ap.add_argument("--train-scenes", type=int, default=32)
    ap.add_argument("--train-frames", type=int, default=12)
    ap.add_argument("--eval-scenes", type=int, default=2)
    ap.add_argument("--vae-steps", type=int, default=1000)
    ap.add_argument(
        "--budget-min", type=float, default=30.0, help="VAE + Stage 1 wall time to fill, minutes (default 30)"
    )
    ap.add_argument(
        "--budget-margin", type=float, default=0.05, help="share of the budget kept free (default 0.05)"
    )
    ap.add_argument("--stage1-steps", type=int, help="fixed Stage 1 steps (default: fill --budget-min)")
    ap.add_argument("--speed-steps", type=int, default=15, help="steps of each before/after speed run")
    ap.add_argument("--clips-per-scene", type=int, default=3)
    ap.add_argument(
        "--wide-eval-scenes", type=int, default=8, help="more held-out scenes for the input views (0: none)"
    )
    ap.add_argument("--baseline", type=Path, help="an earlier Stage 1 checkpoint to score beside the new one")
    ap.add_argument("--baseline-name", default="old", help="its name in the held-out table (default old)")
    ap.add_argument("--baseline-note", default="", help="what the baseline is, said under the held-out table")
    ap.add_argument(
        "--picture", type=Path, help="default docs/images/stage1_eval.png with --update, else benchmarks/out/"
    )
    ap.add_argument(
        "--reuse", action="store_true", help="keep trained runs in --work (and their timings, timings.json)"
    )
    add_update_flag(ap)
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    train_cache, eval_cache = work / "train", work / "eval"
    _cache(train_cache, args.train_scenes, 1000, args.train_frames)
    _cache(eval_cache, args.eval_scenes, 100, 40)
    native = native_available()
    if not native:
        print(
            "WARNING: the native rasterizer is not built; Stage 1 trains with the tiled PyTorch one",
            flush=True,
        )
    full_backend = "cpu" if native else "torch"

    report = Report(
        "stage1",
        "Stage 1 (tiny config, 2 CPU cores)",
        f"Written by `benchmarks/stage1.py`. Training: {args.train_scenes} synthetic scenes (seed 1000) x "
        f"{args.train_frames} frames, 5 views at 96 x 144 in the cache, 48 x 72 in the model; evaluation: "
        f"{args.eval_scenes} held-out scenes (seed 100) x 40 frames; the bundled synthetic pipeline (depth "
        "completion included). The VAE trains first (`phigenesis-train vae`, frozen afterwards), then "
        "the range-view adapter (`phigenesis-train stage1 --config configs/stage1/tiny.yaml` under "
        "`torchrun --nproc_per_node 2`, gloo, 1 thread per process, one clip per process per step; semantic "
        "labels: the synthetic truth, which `semantic_target: auto` takes where a cache has it), with the "
        f"{SPEED_BACKENDS[full_backend]} rasterizer (`PHIGENESIS_RASTERIZER={full_backend}`).",
    )

    vae_run, s1_run = work / "vae", work / "stage1"
    timings_path = work / "timings.json"  # wall time and peak RSS of each phase, kept for --reuse
    timings = json.loads(timings_path.read_text()) if args.reuse and timings_path.exists() else {}
    if not (args.reuse and (vae_run / "model.safetensors").exists() and "vae" in timings):
        shutil.rmtree(vae_run, ignore_errors=True)
        timings["vae"] = _run(
            f"{BIN}/phigenesis-train vae --shards {train_cache} --out {vae_run} --steps {args.vae_steps} "
            "--threads 2 --size 48x72 --frames 5 --batch-size 4".split()
        )
        timings_path.write_text(json.dumps(timings))

    # Before/after: a few steps of the same run with each rasterizer (not counted in the budget).
    speed: dict[str, tuple[list[float], float, float]] = {}  # backend: (step seconds, wall s, RSS GiB)
    for backend in SPEED_RUNS if native else ("torch",):
        run = work / f"speed-{backend}"
        key = f"speed_{backend}"
        reused = args.reuse and key in timings and (run / "model.safetensors").exists()
        if not reused:
            timings[key] = _train_stage1(train_cache, vae_run, run, args.speed_steps, SPEED_RUNS[backend][1])
            timings_path.write_text(json.dumps(timings))
        speed[backend] = (_step_seconds(run), *timings[key])

    vae_wall = timings["vae"][0]
    budget_s = 60.0 * args.budget_min
    if args.stage1_steps is not None:
        plan = (
            f"Stage 1 steps planned at {args.stage1_steps} (`--stage1-steps`), the run ending at the budget "
            "if it gets there first."
        )
        s1_steps = args.stage1_steps
    else:
        s1_steps, per_step, startup = budget_steps(
            budget_s, vae_wall, speed, full_backend, args.budget_margin
        )
        if s1_steps < 1:
            raise SystemExit(
                f"the VAE took {vae_wall / 60:.1f} min of the {args.budget_min:g}-minute budget: no time left"
            )
        plan = (
            f"Stage 1 steps: {s1_steps} = floor(({args.budget_min:g} min budget "
            f"- {vae_wall / 60:.1f} min VAE - {startup:.0f} s start-up) x {1 - args.budget_margin:.2f} "
            f"/ {per_step:.2f} s per step), "
            f"from the speed runs (the {SPEED_BACKENDS[full_backend]} one's mean step time after its first "
            "step; start-up: the smallest wall time less steps)."
        )
    if not (args.reuse and (s1_run / "model.safetensors").exists() and "stage1" in timings):
        print(plan, flush=True)
        limit = budget_s - vae_wall  # the budget holds with fixed steps too
        timings["stage1"] = _train_stage1(
            train_cache, vae_run, s1_run, s1_steps, SPEED_RUNS[full_backend][1], limit
        )
        timings["stage1_plan"] = plan
        timings_path.write_text(json.dumps(timings))
    plan = timings.get("stage1_plan", "")  # how the reused run's steps were chosen
    result = work / "eval.json"
    picture = args.picture or output_path("docs/images/stage1_eval.png", args.update)
    timings["eval"] = _run(
        f"{BIN}/phigenesis-eval stage1 --ckpt {s1_run / 'model.safetensors'} --shards {eval_cache} "
        f"--out {result} --picture {picture} --clips-per-scene {args.clips_per_scene} --threads 2".split()
    )
    timings_path.write_text(json.dumps(timings))
    # The same model on its own training scenes (input views only): does it fit what it was trained on?
    fit_json = work / "eval-train.json"
    _run(
        f"{BIN}/phigenesis-eval stage1 --ckpt {s1_run / 'model.safetensors'} --shards {train_cache} "
        f"--out {fit_json} --offsets 1 --shifts --clips-per-scene 1 --no-oracle --threads 2".split()
    )
    baseline = None
    if args.baseline is not None:
        baseline_json = work / "eval-baseline.json"
        _run(
            f"{BIN}/phigenesis-eval stage1 --ckpt {args.baseline} --shards {eval_cache} "
            f"--out {baseline_json} --clips-per-scene {args.clips_per_scene} --threads 2".split()
        )
        baseline = json.loads(baseline_json.read_text())
    wide: dict[str, dict] = {}  # renderer name -> the input views on the wider held-out set
    if args.wide_eval_scenes > 0:
        wide_cache = work / "eval-wide"
        _cache(wide_cache, args.wide_eval_scenes, WIDE_EVAL_SEED, WIDE_EVAL_FRAMES)
        checkpoints = {"new": s1_run / "model.safetensors"}
        if args.baseline is not None:
            checkpoints[args.baseline_name] = args.baseline
        for i, (name, ckpt) in enumerate(checkpoints.items()):
            out = work / f"eval-wide-{i}.json"
            _run(
                f"{BIN}/phigenesis-eval stage1 --ckpt {ckpt} --shards {wide_cache} --out {out} --offsets 1 "
                f"--shifts --clips-per-scene {args.clips_per_scene} --no-oracle --threads 2".split()
            )
            wide[name] = json.loads(out.read_text())

    rows = []
    s1_name = f"stage1 (stage1_tiny, {SPEED_BACKENDS[full_backend]})"
    for key, name, run, batch in (("vae", "vae (vae_tiny)", vae_run, None), ("stage1", s1_name, s1_run, 2)):
        wall, rss = timings.get(key, (float("nan"), float("nan")))
        step_s, steps = _step_stats(run, wall)
        rows.append(
            [name, steps, f"{wall / 60:.1f}", f"{step_s:.2f}", f"{1 / step_s:.2f}", batch or "", f"{rss:.2f}"]
        )
    total_min = (timings["vae"][0] + timings["stage1"][0]) / 60
    report.table(
        "Training speed and memory",
        ["run", "steps", "wall min", "median s/step", "steps/s", "clips/step", "peak RSS GiB"],
        rows,
        f"Wall time includes start-up and validation; the {args.budget_min:g}-minute budget covers both runs "
        f"together: {total_min:.1f} min here. {plan} Peak RSS: the largest process (each torchrun worker "
        "holds the model and its clips).",
    )
    report.table(*_speed_table(speed, args.speed_steps, native))
    summary = json.loads((s1_run / "summary.json").read_text())
    if summary.get("stopped_by_time"):
        report.text(
            f"The time limit ended the Stage 1 run at step {summary['steps']} of the "
            f"{summary['planned_steps']} planned (its learning rate had not decayed all the way)."
        )
    metrics = json.loads(result.read_text())
    report.table(*_eval_table(metrics, baseline, args.baseline_name, args.baseline, args.baseline_note))
    report.table(*_class_table(metrics, json.loads(fit_json.read_text())))
    if wide:
        report.table(*_wide_table(wide))
    report.table(*_goals_table(metrics, wide.get("new")))
    report.text("![input, render, depth and semantics of a held-out clip](docs/images/stage1_eval.png)")
    report.write(update=args.update)


def _speed_table(
    speed: dict[str, tuple[list[float], float, float]], steps: int, native: bool
) -> tuple[str, list[str], list[list[object]], str]:
    """Stage 1 step time with the tiled PyTorch rasterizer, the native kernel with the PyTorch
    projection, and the native kernel and projection."""
    medians = {b: statistics.median(sec) for b, (sec, _, _) in speed.items()}
    rows: list[list[object]] = []
    for key, (label, env) in SPEED_RUNS.items():
        setting = ", ".join(f"`{k}={v}`" for k, v in env.items())
        if key not in speed:
            rows.append([label, setting, "—", "—", "—", "—", "—", "—"])
            continue
        seconds, wall, rss = speed[key]
        previous = medians.get("cpu-torch-projection")
        rows.append(
            [
                label,
                setting,
                len(seconds),
                f"{medians[key]:.2f}",
                f"{wall:.0f}",
                f"{rss:.2f}",
                f"{medians['torch'] / medians[key]:.1f}x",
                "—" if previous is None else f"{previous / medians[key]:.2f}x",
            ]
        )
    note = (
        f"{steps} steps of the Stage 1 run above (same config, VAE, data and torchrun layout; the first "
        "steps of its warm-up), once per setting, one after the other. The projection (EWA, shared by the "
        "CPU rasterizers) is native unless `PHIGENESIS_PROJECTION=torch`. Median s/step "
        "of the logged step times (the first step included in the median); wall: the whole command, "
        "start-up and the final checkpoint included. Speed-ups: the tiled run's median, and the native "
        "run's with the PyTorch projection (the previous state), over this one's."
    )
    if not native:
        note += " The native kernel is not built here (`native_available()` is False): no native row."
    return (
        "Stage 1 step time: tiled PyTorch vs native rasterizer vs native projection",
        [
            "rasterizer",
            "environment",
            "steps",
            "median s/step",
            "wall s",
            "peak RSS GiB",
            "speed-up over tiled",
            "speed-up over PyTorch projection",
        ],
        rows,
        note,
    )


#: Held-out table columns: report key -> header (depth under the standard protocol).
EVAL_COLUMNS = {
    "psnr_db": "PSNR dB",
    "ssim": "SSIM",
    "abs_rel": "AbsRel",
    "sq_rel": "SqRel",
    "rmse_m": "RMSE m",
    "rmse_log": "RMSE log",
    "delta_1_25": "δ<1.25",
    "delta_1_25_2": "δ<1.25²",
    "delta_1_25_3": "δ<1.25³",
    "abs_rel_lidar": "AbsRel LiDAR px",
    "abs_rel_no_lidar": "AbsRel no-LiDAR px",
    "miou": "mIoU",
}


def _cell(key: str, value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return f"{value:.2f}" if key in ("psnr_db", "rmse_m", "sq_rel") else f"{value:.3f}"


def _eval_table(
    metrics: dict,
    baseline: dict | None = None,
    baseline_name: str = "old",
    baseline_path: Path | None = None,
    baseline_note: str = "",
) -> tuple[str, list[str], list[list[object]], str]:
    """The held-out table from the evaluation JSON (keys of :mod:`phigenesis.eval.stage1`):
    per section a row for the new model, the baseline (when given) and the oracle."""
    headers = ["views", "images", "renderer", *EVAL_COLUMNS.values()]
    rows = []
    for section, entry in metrics["sections"].items():
        renderers = [("new", entry["model"])]
        if baseline is not None and section in baseline["sections"]:
            renderers.append((baseline_name, baseline["sections"][section]["model"]))
        if "oracle" in entry:
            renderers.append(("oracle", entry["oracle"]))
        for who, values in renderers:
            rows.append([section, entry["images"], who, *(_cell(k, values.get(k)) for k in EVAL_COLUMNS)])
    note = (
        f"{metrics['clips']} clips ({metrics['seconds_per_clip']:.1f} s per clip to evaluate). Depth under "
        "the standard protocol (SurroundDepth / DiST-4D / Omni-Scene): the rendered z-depth against the "
        "exact synthetic depth on every pixel with a truth, both clamped to [1e-3, 80] m (a pixel the "
        "render leaves empty counts as 1e-3 m), per image, averaged over the images; AbsRel also on the "
        "pixels the cache's LiDAR-derived dense depth covers and on the others (— for the shifted views, "
        "which have no cache depth). mIoU of the rendered semantics against the truth. Oracle: one "
        "Gaussian per input pixel at the true depth with the true colour and class, 0.3 pixel footprints "
        "wide, moving at the true flow, rendered by the same rasterizer."
    )
    if baseline is not None:
        note += (
            f" `{baseline_name}`: the checkpoint `{baseline_path}` ({baseline.get('model')}), scored on the "
            "same held-out cache and clips."
        ) + (f" {baseline_note.strip()}" if baseline_note.strip() else "")
    return ("Held-out scenes: model against the oracle", headers, rows, note)


def _class_table(metrics: dict, fit: dict) -> tuple[str, list[str], list[list[object]], str]:
    """Input-view depth by truth class: held-out (model and oracle) beside the training scenes."""
    held, train = metrics["sections"]["input"], fit["sections"]["input"]
    model, oracle, fitted = held["model_by_class"], held.get("oracle_by_class", {}), train["model_by_class"]
    rows = []
    for name, v in sorted(model.items(), key=lambda kv: -kv[1]["miss_share"]):
        t, o = fitted.get(name, {}), oracle.get(name, {})
        rows.append(
            [
                name,
                f"{100 * v['share']:.1f}",
                f"{v['abs_rel']:.3f}",
                f"{v['delta_1_25']:.3f}",
                f"{100 * v['miss_share']:.1f}",
                _cell("abs_rel", t.get("abs_rel")),
                _cell("delta_1_25", t.get("delta_1_25")),
                f"{100 * t['share']:.1f}" if t else "—",
                _cell("delta_1_25", o.get("delta_1_25")),
            ]
        )
    pooled = (held["model"]["delta_1_25_pooled"], train["model"]["delta_1_25_pooled"])
    rows.append(
        [
            "all (pooled)",
            "100.0",
            _cell("abs_rel", held["model"]["abs_rel_pooled"]),
            f"{pooled[0]:.3f}",
            "100.0",
            _cell("abs_rel", train["model"]["abs_rel_pooled"]),
            f"{pooled[1]:.3f}",
            "100.0",
            _cell("delta_1_25", held.get("oracle", {}).get("delta_1_25_pooled")),
        ]
    )
    headers = [
        "truth class",
        "held-out px %",
        "held-out AbsRel",
        "held-out δ<1.25",
        "% of held-out δ misses",
        "training AbsRel",
        "training δ<1.25",
        "training px %",
        "oracle δ<1.25",
    ]
    note = (
        f"The input views of the held-out table ({held['images']} images), depth pooled over the pixels of "
        "each truth class; misses: pixels outside δ<1.25, and the share of them each class holds. "
        f"Training: the same model on its own training cache ({train['images']} images, one clip per "
        "scene, input views). "
        "Where the training scenes score as low as the held-out ones, the model does not fit what it was "
        "trained on (capacity, resolution or steps), rather than failing to generalise."
    )
    return (
        "Where the depth error is: input views by truth class, held-out and training scenes",
        headers,
        rows,
        note,
    )


def _wide_table(wide: dict[str, dict]) -> tuple[str, list[str], list[list[object]], str]:
    """The input views of each renderer on the wider held-out set (:data:`WIDE_EVAL_SEED`)."""
    keys = ["psnr_db", "abs_rel", "rmse_m", "delta_1_25", "delta_1_25_2", "miou"]
    rows = []
    for name, report in wide.items():
        values = report["sections"]["input"]["model"]
        rows.append([name, report["images"]["input"], *(_cell(k, values.get(k)) for k in keys)])
    first = next(iter(wide.values()))
    scenes = len({scene for scene, _ in first["clip_list"]})
    note = (
        f"{scenes} more held-out scenes (`prep.synthetic`, seed {WIDE_EVAL_SEED}, {WIDE_EVAL_FRAMES} frames "
        f"each, {first['clips']} clips), input views only, the same protocol as above. Two held-out scenes "
        "hold few objects of each kind (a few trucks, one or two tree lines), so which scenes they are "
        "moves δ<1.25 by several hundredths; read model differences here."
    )
    headers = ["renderer", "images", *(EVAL_COLUMNS[k] for k in keys)]
    return (f"Input views on {scenes} more held-out scenes", headers, rows, note)


def _goals_table(metrics: dict, wide: dict | None = None) -> tuple[str, list[str], list[list[object]], str]:
    """The issue's goals for Stage 1's geometry, met or missed (``wide``: the new model on the wider
    held-out set, whose AbsRel and δ<1.25 are reported against the same goals)."""
    sections = metrics["sections"]
    rows: list[list[object]] = []

    def add(what: str, value: float, goal: str, met: bool) -> None:
        rows.append([what, f"{value:.3f}", goal, "met" if met else "missed"])

    model = sections["input"]["model"]
    add(
        "input views: AbsRel (all truth pixels)",
        model["abs_rel"],
        "≤ 0.16 (the paper's Waymo)",
        model["abs_rel"] <= 0.16,
    )
    add("input views: δ<1.25", model["delta_1_25"], "≥ 0.86", model["delta_1_25"] >= 0.86)
    if wide is not None:
        more = wide["sections"]["input"]["model"]
        add("input views, the wider held-out set: AbsRel", more["abs_rel"], "≤ 0.16", more["abs_rel"] <= 0.16)
        add(
            "input views, the wider held-out set: δ<1.25",
            more["delta_1_25"],
            "≥ 0.86",
            more["delta_1_25"] >= 0.86,
        )
    for name in ("shift_1m", "shift_2m"):
        if name in sections and "oracle" in sections[name]:
            gap = sections[name]["oracle"]["psnr_db"] - sections[name]["model"]["psnr_db"]
            add(f"{name}: PSNR below the oracle, dB", gap, "≤ 1 dB", gap <= 1.0)
    note = "From the held-out tables above (the new model)."
    return ("Goals", ["what", "value", "goal", ""], rows, note)


if __name__ == "__main__":
    main()
