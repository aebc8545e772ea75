"""Stage 2 benchmark: the tiny denoiser trained on 2 CPU cores per conditioning variant and seed,
rolled out on held-out synthetic scenes and scored against the exact truth (the ablation table).

Usage (from the repository root, on a quiet machine)::

    python benchmarks/stage2.py [--work /tmp/stage2-bench] [--seeds 0 1 2] [--stage2-steps 800]

1. Caches (reused when present): ``--train-scenes`` synthetic scenes (seed 1000) of
   ``--train-frames`` frames and ``--eval-scenes`` held-out scenes (seed 100) of ``--eval-frames``
   frames, at 96 x 144, bundled synthetic pipeline.
2. ``phigenesis-train vae`` (vae_tiny, 1000 steps) and ``phigenesis-train stage1``
   (``configs/stage1/tiny.yaml``, ``--stage1-steps`` steps, torchrun 2 x 1 thread): the frozen VAE and
   the Stage 1 model every row shares (reused when present).
3. The Stage 2 latent caches (:func:`phigenesis.train.stage2_data.precompute_stage2`), once per
   geometry (``stage1``: Stage 1's Gaussians of the history, the paper; ``truth``: the synthetic
   truth lifted, the ceiling), shared by every row and seed of that geometry.
4. Per row and seed, ``phigenesis-train stage2`` (``configs/stage2/tiny.yaml``, ``--stage2-steps``
   steps, 1 thread, two runs side by side on the 2 cores) with the row's ``uncertainty`` and
   ``geometry``; then ``phigenesis-eval stage2`` on the held-out cache (+5 / +10 frames, 1 / 2 / 4 m
   shifted trajectories, rollout frames ``--rollout-frames``; FID/KID with ``--fid-model``).
   Rows: ``no geometry`` (uncertainty ``none``: the condition is always zero), ``coverage`` (the
   render trusted wherever it covers: the "no SF" row), ``SF random``, ``SF entropy``, ``SF
   localization potential`` (``lp_trust: stable``, the config's), the same with ``u localised``
   (the reading before 2026-12-05) and ``truth geometry`` (localization potential on the truth's
   render). Each (geometry, ``lp_trust``) has its own latent cache, made only when a run still to
   be trained needs it.
   ``render only`` is the history's Stage 1 render scored at the same cameras (no diffusion).
   Sampling uses render anchoring and pasting (``--anchor``, ``--anchor-until``, ``--paste``; the
   defaults are ``GenerateOptions``'); ``--no-anchor-rows`` also scores every geometry row with
   neither (the network alone), ``--no-paste-rows`` anchored but not pasted.
5. An omega sweep of the localization-potential model of the first seed.

``--update`` writes the ``stage2`` section of BENCHMARKS.md (mean +- std over the seeds) and a picture
per row. No timing is asserted anywhere; runs side by side share the machine, so their step times are not
a quiet machine's.
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
from phigenesis.rollout.runner import GenerateOptions
from phigenesis.train.runner import read_metrics

BIN = Path(sys.executable).parent
#: (row name, uncertainty, geometry) of the trained rows; ``kind@trust`` names the localization
#: potential's mapping when it is not ``configs/stage2/tiny.yaml``'s (``stable``).
ROWS = (
    ("no geometry", "none", "stage1"),
    ("coverage (no SF)", "coverage", "stage1"),
    ("SF random", "random", "stage1"),
    ("SF entropy", "entropy", "stage1"),
    ("SF localization potential", "localization_potential", "stage1"),
    ("SF localization potential, u localised", "localization_potential@localised", "stage1"),
    ("truth geometry (LP)", "localization_potential", "truth"),
)
SECTIONS_SHOWN = ("+5", "+10", "shift_1m", "shift_2m", "shift_4m")
CEILING = "VAE reconstruction of the truth (ceiling)"
RENDER_ONLY = "render only (Stage 1, no diffusion)"
#: A run's other evaluations: (flag, file, row-name suffix, options): without render anchoring or
#: pasting (``--no-anchor-rows``), anchored but not pasted (``--no-paste-rows``).
VARIANTS = (
    ("no_anchor_rows", "eval-anchor0.json", "no anchoring", {"anchor": 0.0, "paste": 0.0}),
    ("no_paste_rows", "eval-paste0.json", "anchored, not pasted", {"paste": 0.0}),
)


def _cmd(cmd: list[str], env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    print("+", " ".join(cmd), flush=True)
    return subprocess.Popen(cmd, env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})


def _wait(procs: list[tuple[subprocess.Popen[bytes], list[str]]]) -> list[tuple[float, float]]:
    """Waits for every process; (its wall seconds since now, peak RSS GiB) each; raises on failure."""
    out = []
    t0 = time.perf_counter()
    for proc, cmd in procs:
        _, status, usage = os.wait4(proc.pid, 0)
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            raise subprocess.CalledProcessError(code, cmd)
        out.append((time.perf_counter() - t0, usage.ru_maxrss / 2**20))
    return out


def _run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    t0 = time.perf_counter()
    (wall_rss,) = _wait([(_cmd(cmd, env), cmd)])
    return time.perf_counter() - t0, wall_rss[1]


def _in_pairs(jobs: list[list[str]]) -> list[tuple[float, float]]:
    """Runs the commands two at a time (one per core), starting the next as soon as one ends;
    (wall s, peak RSS GiB) of each, in the order given."""
    results: dict[int, tuple[float, float]] = {}
    # pid -> (index, start, cmd, the Popen: kept so that subprocess never reaps it behind os.wait4)
    running: dict[int, tuple[int, float, list[str], subprocess.Popen[bytes]]] = {}
    queue = list(enumerate(jobs))
    while queue or running:
        while queue and len(running) < 2:
            i, cmd = queue.pop(0)
            proc = _cmd(cmd)
            running[proc.pid] = (i, time.perf_counter(), cmd, proc)
        pid, status, usage = os.wait4(-1, 0)
        if pid not in running:
            continue
        i, t0, cmd, proc = running.pop(pid)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            raise subprocess.CalledProcessError(proc.returncode, cmd)
        results[i] = (time.perf_counter() - t0, usage.ru_maxrss / 2**20)
    return [results[i] for i in range(len(jobs))]


def _kind(kind: str, base: dict[str, object]) -> tuple[str, str]:
    """(uncertainty, lp_trust) of a row's kind (``kind`` or ``kind@trust``)."""
    uncertainty, _, trust = kind.partition("@")
    return uncertainty, trust or str(base.get("lp_trust", "stable"))


def _tag(kind: str, geometry: str, seed: int) -> str:
    """The run folder's name of a row's kind, geometry and seed."""
    return f"{kind.replace('@', '-')}-{geometry}-s{seed}"


def _latents(work: Path, geometry: str, trust: str) -> Path:
    """The latent cache of a geometry and localization-potential mapping."""
    return work / (f"latents-{geometry}" if trust == "stable" else f"latents-{geometry}-{trust}")


def _cache(path: Path, scenes: int, seed: int, frames: int) -> None:
    if (path / "manifest.json").exists():
        return
    prep.synthetic(path, scenes=scenes, frames=frames, seed=seed, height=96, width=144, workers=2)


def _mean_std(values: list[float], digits: int = 2) -> str:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return "—"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/stage2-bench"))
    ap.add_argument("--train-scenes", type=int, default=16)
    ap.add_argument("--train-frames", type=int, default=24)
    ap.add_argument("--eval-scenes", type=int, default=2)
    ap.add_argument("--eval-frames", type=int, default=60)
    ap.add_argument("--vae-steps", type=int, default=1000)
    ap.add_argument("--stage1-steps", type=int, default=1500)
    ap.add_argument("--stage2-steps", type=int, default=800)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rollout-frames", type=int, nargs="*", default=[50])
    ap.add_argument("--omegas", type=float, nargs="*", default=[0.0, 1.0, 2.0, 3.0])
    ap.add_argument(
        "--long-rollout-frames",
        type=int,
        nargs="*",
        default=[],
        help="further rollout frames scored only for --long-rollout-seeds (a long rollout costs minutes)",
    )
    ap.add_argument("--long-rollout-seeds", type=int, nargs="*", default=[0])
    ap.add_argument(
        "--sweep-rollout-frames",
        type=int,
        nargs="*",
        default=[50],
        help="rollout frames of the omega sweep (shorter than the ablation's, to save time)",
    )
    ap.add_argument("--sample-steps", type=int, default=10)
    ap.add_argument("--fid-model", type=Path, help="local TorchScript Inception (default_1.pt) for FID/KID")
    ap.add_argument(
        "--fid-frames",
        type=int,
        help="generated frames ending at each rollout frame that its FID/KID pools (default: one window's)",
    )
    ap.add_argument("--rows", nargs="*", help="only these rows (by uncertainty name), for a partial run")
    defaults = GenerateOptions()
    ap.add_argument("--anchor", type=float, default=defaults.anchor, help="render anchoring's strength")
    ap.add_argument(
        "--anchor-until", type=float, default=defaults.anchor_until, help="flow time the anchor stops at"
    )
    ap.add_argument(
        "--no-anchor-rows",
        action="store_true",
        help="also evaluate every geometry row without render anchoring and pasting (rollouts to "
        "--rollout-frames)",
    )
    ap.add_argument("--paste", type=float, default=defaults.paste, help="render pasting's strength")
    ap.add_argument(
        "--no-paste-rows",
        action="store_true",
        help="also evaluate every geometry row anchored but not pasted (rollouts to --rollout-frames)",
    )
    add_update_flag(ap)
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    report = Report("stage2", "Stage 2 (tiny config, 2 CPU cores)", intro=_intro(args))
    t_all = time.perf_counter()

    train_cache, eval_cache = work / "train", work / "eval"
    _cache(train_cache, args.train_scenes, 1000, args.train_frames)
    _cache(eval_cache, args.eval_scenes, 100, args.eval_frames)
    vae = work / "vae"
    if not (vae / "model.safetensors").exists():
        shutil.rmtree(vae, ignore_errors=True)
        _run(
            [
                str(BIN / "phigenesis-train"),
                "vae",
                "--shards",
                str(train_cache),
                "--out",
                str(vae),
                "--steps",
                str(args.vae_steps),
                "--batch-size",
                "4",
                "--threads",
                "2",
            ],
            {"OMP_NUM_THREADS": "2"},
        )
    stage1 = work / "stage1"
    if not (stage1 / "model.safetensors").exists():
        shutil.rmtree(stage1, ignore_errors=True)
        cfg = yaml.safe_load((REPO_ROOT / "configs/stage1/tiny.yaml").read_text())
        cfg |= {"vae_checkpoint": str(vae / "model.safetensors"), "steps": args.stage1_steps, "batch_size": 2}
        cfg |= {"threads": 1}
        cfg_path = work / "stage1.yaml"
        cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        _run(
            f"{sys.executable} -m torch.distributed.run --nproc_per_node 2 -m phigenesis.cli.train stage1 "
            f"--shards {train_cache} --config {cfg_path} --out {stage1} --no-progress".split()
        )

    base = yaml.safe_load((REPO_ROOT / "configs/stage2/tiny.yaml").read_text())
    base |= {"stage1_checkpoint": str(stage1 / "model.safetensors"), "steps": args.stage2_steps, "threads": 1}
    rows = [r for r in ROWS if not args.rows or r[1] in args.rows or r[0] in args.rows]
    # The latent caches, one per geometry, before any training run reads them.
    from phigenesis.models.loading import load_stage1
    from phigenesis.rollout.config import Stage2TrainConfig
    from phigenesis.train.stage2_data import precompute_stage2

    model = load_stage1(stage1 / "model.safetensors")
    precompute_s: dict[str, float] = {}
    # Only the caches a run still to be trained reads (a reused run's cache may be gone).
    needed = {
        (g, _kind(k, base)[1])
        for _, k, g in rows
        for seed in args.seeds
        if not (work / "runs" / _tag(k, g, seed) / "model.safetensors").exists()
    }
    for geometry, trust in sorted(needed):
        cfg = Stage2TrainConfig(**{**base, "geometry": geometry, "lp_trust": trust})
        t0 = time.perf_counter()
        precompute_stage2(
            train_cache,
            _latents(work, geometry, trust),
            model,
            cfg.data_config(),
            stage1_checkpoint=cfg.stage1_checkpoint,
        )
        precompute_s[geometry if trust == "stable" else f"{geometry}, {trust}"] = time.perf_counter() - t0
    del model

    runs: dict[tuple[str, int], Path] = {}
    train_jobs, eval_jobs = [], []
    for name, kind, geometry in rows:
        uncertainty, trust = _kind(kind, base)
        for seed in args.seeds:
            tag = _tag(kind, geometry, seed)
            out = work / "runs" / tag
            runs[(name, seed)] = out
            cfg_path = work / "runs" / f"{tag}.yaml"
            cfg_path.parent.mkdir(parents=True, exist_ok=True)
            cfg_path.write_text(
                yaml.safe_dump(
                    {
                        **base,
                        "uncertainty": uncertainty,
                        "lp_trust": trust,
                        "geometry": geometry,
                        "seed": seed,
                    }
                )
            )
            if not (out / "model.safetensors").exists():
                shutil.rmtree(out, ignore_errors=True)
                train_jobs.append(
                    [
                        str(BIN / "phigenesis-train"),
                        "stage2",
                        "--shards",
                        str(train_cache),
                        "--config",
                        str(cfg_path),
                        "--latents",
                        str(_latents(work, geometry, trust)),
                        "--out",
                        str(out),
                        "--no-progress",
                    ]
                )
            result = out / "eval.json"
            if not result.exists():
                frames = args.rollout_frames + (
                    args.long_rollout_frames if seed in args.long_rollout_seeds else []
                )
                eval_jobs.append(_eval_cmd(out, eval_cache, result, args, 1.0, rollout_frames=frames))
            for flag, file, _, options in VARIANTS:
                if getattr(args, flag) and kind != "none" and not (out / file).exists():
                    eval_jobs.append(_eval_cmd(out, eval_cache, out / file, args, 1.0, **options))
    train_wall = _in_pairs(train_jobs)
    eval_wall = _in_pairs(eval_jobs)
    precompute_s, train_wall, eval_wall = _remembered(work, precompute_s, train_wall, eval_wall)
    lp_name = "SF localization potential"
    sweep: dict[float, Path] = {}
    if (lp_name, args.seeds[0]) in runs:
        jobs = []
        for omega in args.omegas:
            path = runs[(lp_name, args.seeds[0])] / f"eval-omega{omega:g}.json"
            if omega == 1.0:  # the row's own evaluation
                path = runs[(lp_name, args.seeds[0])] / "eval.json"
            sweep[omega] = path
            if not path.exists():
                jobs.append(
                    _eval_cmd(
                        runs[(lp_name, args.seeds[0])],
                        eval_cache,
                        path,
                        args,
                        omega,
                        rollout_frames=args.sweep_rollout_frames,
                    )
                )
        _in_pairs(jobs)

    results = {key: json.loads((out / "eval.json").read_text()) for key, out in runs.items()}
    variant_rows = []
    for flag, file, suffix, _ in VARIANTS:
        for name, kind, geometry in rows:
            paths = {seed: runs[(name, seed)] / file for seed in args.seeds}
            if kind != "none" and getattr(args, flag) and all(p.exists() for p in paths.values()):
                label = f"{name}, {suffix}"
                variant_rows.append((label, kind, geometry))
                results |= {(label, seed): json.loads(p.read_text()) for seed, p in paths.items()}
    _report_tables(
        report, args, rows, variant_rows, runs, results, sweep, precompute_s, train_wall, eval_wall
    )
    picture = _rows_picture(
        [(name, runs[(name, args.seeds[0])] / "eval.png") for name, _, _ in rows], args.update
    )
    if picture is not None:
        report.text(
            f"![history, condition render, u, generated frame and truth at +10, one block per row, seed "
            f"{args.seeds[0]}]({picture.relative_to(REPO_ROOT)})"
        )
    # A re-invocation that reuses the work folder adds its own time to the first one's.
    timing = work / "wall_minutes.json"
    spent = json.loads(timing.read_text()) if timing.exists() else []
    spent.append(round((time.perf_counter() - t_all) / 60, 1))
    timing.write_text(json.dumps(spent))
    parts = (
        f" ({' + '.join(f'{m:.1f}' for m in spent)} min over {len(spent)} invocations)"
        if len(spent) > 1
        else ""
    )
    report.text(f"The whole run took {sum(spent):.1f} min{parts}.")
    report.write(update=args.update)


def _intro(args: argparse.Namespace) -> str:
    """What the section measured, from the run's arguments and the shipped config."""
    cfg = yaml.safe_load((REPO_ROOT / "configs" / "stage2" / "tiny.yaml").read_text())
    latents = "latents standardised per channel (`latent_norm`)" if cfg.get("latent_norm") else "raw latents"
    longest = max([*args.rollout_frames, *args.long_rollout_frames], default=0)
    fid_frames = args.fid_frames or int(cfg["window_frames"])  # the evaluator's default: one window
    fid_images = fid_frames * 5 * args.eval_scenes
    return (
        f"Written by `benchmarks/stage2.py`. Data: {args.train_scenes} synthetic training scenes "
        f"(seed 1000) x {args.train_frames} frames and {args.eval_scenes} held-out scenes (seed 100) x "
        f"{args.eval_frames} frames, 96 x 144 in the caches, 48 x 72 in the models. Shared by every row: "
        f"`vae_tiny` ({args.vae_steps} steps) and `stage1_tiny` (`configs/stage1/tiny.yaml`, "
        f"{args.stage1_steps} steps, torchrun 2 x 1 thread). Each row and seed: `stage2_tiny` trained "
        f"{args.stage2_steps} steps (`configs/stage2/tiny.yaml`: 1 history frame + 5 generated frames a "
        f"window, the flow on {latents}), two runs at a time on the 2 cores. Evaluation "
        f"(`phigenesis-eval stage2`, {args.sample_steps} Euler steps, omega 1, render anchoring "
        f"{args.anchor:g} until flow time {args.anchor_until:g}, render pasting {args.paste:g}): one clip "
        "per held-out scene from frame 1 (history frame 0); +5 and +10 along the recorded "
        "trajectory; the first window of trajectories shifted 1, 2 and 4 m left against the ray-cast "
        "truth (a frame whose shifted rig comes within 0.5 m of a labelled road user is not scored); "
        "one rollout per scene through the Gaussian buffer (each generated window's newest frame "
        "joins it, as many frames as the history: `--lift-frames`' default) "
        f"to frame {max(args.rollout_frames, default=0)} for every seed and to frame {longest} for "
        f"seed(s) {', '.join(map(str, args.long_rollout_seeds)) or 'none'} (the columns past "
        f"{max(args.rollout_frames, default=0)} are those seeds'). FID/KID at rollout frame k over the "
        f"{fid_frames} frames ending there (Inception `default_1.pt`, {fid_images} generated against as "
        "many true images, 5 views per scene: the FID is dominated by its small-sample bias and does not "
        "compare with the paper's; KID is the better-behaved of the two here). `VAE reconstruction of the "
        "truth`: the true windows encoded and decoded by the frozen VAE, the ceiling of any generated row; "
        "`render only`: the history's Stage 1 render at the same cameras, no diffusion."
    )


def _rows_picture(pictures: list[tuple[str, Path]], update: bool) -> Path | None:
    """Stacks the evaluations' pictures (history, condition, u, generated, truth), each under a bar
    naming its row, into docs/images/stage2_rows.png (``update``; else benchmarks/out/); None when
    none exists."""
    import cv2
    import numpy as np

    blocks = []
    for name, path in pictures:
        image = cv2.imread(str(path)) if path.exists() else None
        if image is None:
            continue
        bar = np.zeros((16, image.shape[1], 3), np.uint8)
        cv2.putText(bar, name, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        blocks += [bar, image]
    if not blocks:
        return None
    out = output_path("docs/images/stage2_rows.png", update)
    cv2.imwrite(str(out), np.concatenate(blocks), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return out


def _remembered(
    work: Path,
    precompute_s: dict[str, float],
    train_wall: list[tuple[float, float]],
    eval_wall: list[tuple[float, float]],
) -> tuple[dict[str, float], list[tuple[float, float]], list[tuple[float, float]]]:
    """The precompute times and the (wall s, peak RSS GiB) of the training and evaluation runs, kept in
    ``work/measured.json``: a re-invocation that reuses the work folder's caches and runs reports what
    the invocation that made them measured, and anything it measures itself replaces that."""
    path = work / "measured.json"
    kept = json.loads(path.read_text()) if path.exists() else {}
    if any(s > 1.0 for s in precompute_s.values()):  # a reused cache costs a fraction of a second
        kept["precompute_s"] = precompute_s
    if train_wall:
        kept["train_wall"] = train_wall
    if eval_wall:
        kept["eval_wall"] = eval_wall
    path.write_text(json.dumps(kept))
    pairs = [tuple(x) for x in kept.get("train_wall", [])], [tuple(x) for x in kept.get("eval_wall", [])]
    return kept.get("precompute_s", precompute_s), *pairs  # type: ignore[return-value]


def _eval_cmd(
    run: Path,
    eval_cache: Path,
    out: Path,
    args: argparse.Namespace,
    omega: float,
    rollout_frames: list[int] | None = None,
    anchor: float | None = None,
    paste: float | None = None,
) -> list[str]:
    cmd = [
        str(BIN / "phigenesis-eval"),
        "stage2",
        "--ckpt",
        str(run),
        "--shards",
        str(eval_cache),
        "--out",
        str(out),
        "--steps",
        str(args.sample_steps),
        "--omega",
        f"{omega:g}",
        "--threads",
        "1",
        "--rollout-frames",
        *[str(k) for k in (args.rollout_frames if rollout_frames is None else rollout_frames)],
        "--anchor",
        f"{args.anchor if anchor is None else anchor:g}",
        "--anchor-until",
        f"{args.anchor_until:g}",
        "--paste",
        f"{args.paste if paste is None else paste:g}",
    ]
    if omega == 1.0 and out.name == "eval.json":
        cmd += ["--picture", str(run / "eval.png")]
    if args.fid_model is not None:
        cmd += ["--fid-model", str(args.fid_model)]
    if args.fid_frames is not None:
        cmd += ["--fid-frames", str(args.fid_frames)]
    return cmd


def _metric(results: dict, name: str, seeds: list[int], section: str, key: str, digits: int = 2) -> str:
    """Mean +- std over the seeds of one generated-frame metric of a row's section."""
    values = [results[(name, s)]["sections"].get(section, {}).get("generated", {}).get(key) for s in seeds]
    return _mean_std([math.nan if v is None else v for v in values], digits)


def _fixed_row(secs: dict, renderer: str, sections: list[str], key: str, digits: int) -> list[str]:
    """One renderer's metric per section of one evaluation's ``sections`` ("—" where it has none):
    the rows that do not depend on the Stage 2 model (render only, the VAE ceiling)."""
    cells = []
    for s in sections:
        value = secs.get(s, {}).get(renderer, {}).get(key)
        cells.append("—" if value is None else f"{value:.{digits}f}")
    return cells


def _report_tables(
    report, args, rows, variant_rows, runs, results, sweep, precompute_s, train_wall, eval_wall
) -> None:  # type: ignore[no-untyped-def]
    seeds = args.seeds
    rollout_sections = [f"rollout_{k}" for k in sorted({*args.rollout_frames, *args.long_rollout_frames})]
    sections = [*SECTIONS_SHOWN, *rollout_sections]
    first = results[(rows[0][0], seeds[0])]["sections"]
    # The same for every row (no Stage 2 model in it); older evaluations did not score it.
    with_ceiling = [
        r["sections"] for r in results.values() if "vae_reconstruction" in r["sections"].get("+5", {})
    ]

    for key, label, digits in (
        ("psnr_db", "PSNR (dB)", 2),
        ("ssim", "SSIM", 3),
        ("abs_rel", "depth AbsRel", 3),
    ):
        table = []
        if key != "abs_rel":
            table.append([RENDER_ONLY, *_fixed_row(first, "render_only", sections, key, digits)])
            if with_ceiling:
                row = _fixed_row(with_ceiling[0], "vae_reconstruction", sections, key, digits)
                table.append([CEILING, *row])
        table += [
            [name, *[_metric(results, name, seeds, s, key, digits) for s in sections]]
            for name, _, _ in [*rows, *variant_rows]
        ]
        report.table(f"Held-out {label}, mean ± std over {len(seeds)} seeds", ["row", *sections], table)
    if args.fid_model is not None:
        cols = [(s, k) for s in rollout_sections for k in ("fid", "kid")]
        fid_rows = [
            [name, *[_metric(results, name, seeds, s, k, 3) for s, k in cols]]
            for name, _, _ in [*rows, *variant_rows]
        ]
        if with_ceiling:
            cells = [with_ceiling[0].get(s, {}).get("vae_reconstruction", {}).get(k) for s, k in cols]
            fid_rows.append([CEILING, *["—" if c is None else f"{c:.3f}" for c in cells]])
        report.table(
            "Rollout FID / KID against the true frames",
            ["row", *[f"{s} {k.upper()}" for s, k in cols]],
            fid_rows,
        )
    if sweep:
        sweep_rows = []
        sweep_sections = [*SECTIONS_SHOWN, *(f"rollout_{k}" for k in args.sweep_rollout_frames)]
        for omega, path in sweep.items():
            sec = json.loads(path.read_text())["sections"]
            cells = [f"{sec[s]['generated']['psnr_db']:.2f}" if s in sec else "—" for s in sweep_sections]
            sweep_rows.append([f"{omega:g}", *cells])
        report.table(
            "Guidance scale omega (SF localization potential, first seed): PSNR dB",
            ["omega", *sweep_sections],
            sweep_rows,
        )
    speed = []
    for (name, seed), out in runs.items():
        logged = read_metrics(out)
        per_step = statistics.median(r["seconds"] for r in logged) if logged else math.nan
        steps = int(max(r["step"] for r in logged)) if logged else 0
        per_frame = results[(name, seed)]["seconds_per_frame"]
        speed.append([name, str(seed), str(steps), f"{per_step:.3f}", f"{per_frame:.2f}"])
    report.table(
        "Speed (two runs side by side on 2 cores, 1 thread each)",
        ["row", "seed", "steps", "median s/step", "s per generated frame"],
        speed,
    )
    report.text(
        "Latent precompute: " + ", ".join(f"{g} {s / 60:.1f} min" for g, s in precompute_s.items()) + "."
    )
    if train_wall:
        rss_eval = max((r for _, r in eval_wall), default=math.nan)
        report.text(
            f"Peak RSS of a training run: {max(r for _, r in train_wall):.2f} GiB; of an evaluation: "
            f"{rss_eval:.2f} GiB."
        )


if __name__ == "__main__":
    main()
