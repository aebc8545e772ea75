"""Stage 2 denoiser variants against the ablation's localization-potential row, on the same data.

Usage (after ``benchmarks/stage2.py`` has filled its work folder)::

    python benchmarks/stage2_variants.py [--work /tmp/stage2-bench] [--seeds 0] [--rollout-frames 50 100]

Reuses the work folder of ``benchmarks/stage2.py`` (its caches, VAE, Stage 1 model and Stage 1 latent
cache) and trains, per variant and seed, ``stage2_tiny`` with the ablation's config
(``configs/stage2/tiny.yaml``, SF localization potential, Stage 1 geometry, the same steps) and one
change:

- ``latent_norm``: the flow on per-channel standardised latents;
- ``x0_skip``: the denoiser predicts a correction to its Stereo-Forcing condition as the clean latent;
- both together.

Each is evaluated as the ablation's rows are (``phigenesis-eval stage2``, 10 Euler steps, omega 1) and
set beside the ablation's own ``SF localization potential`` run of the same seed (the velocity
prediction on raw latents), the history's render alone and the VAE reconstruction of the truth. Writes the
``stage2-variants`` section of BENCHMARKS.md. Finished runs and evaluations are reused.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import REPO_ROOT, Report, add_update_flag
from stage2 import BIN, CEILING, RENDER_ONLY, _eval_cmd, _fixed_row, _in_pairs, _metric

#: (name, config changes) of the variants; the first row is the ablation's own run.
VARIANTS = (
    ("latent_norm", {"latent_norm": True}),
    ("x0_skip", {"model_overrides": {"prediction": "x0_skip"}}),
    ("latent_norm + x0_skip", {"latent_norm": True, "model_overrides": {"prediction": "x0_skip"}}),
)
BASELINE = "velocity, raw latents (the ablation's SF localization potential)"
SECTIONS = ("+5", "+10", "shift_1m", "shift_2m", "shift_4m")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/stage2-bench"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--stage2-steps", type=int, default=800)
    ap.add_argument("--rollout-frames", type=int, nargs="*", default=[50, 100])
    ap.add_argument("--sample-steps", type=int, default=10)
    ap.add_argument("--only", nargs="*", help="train and evaluate only these variants (the table shows all)")
    ap.add_argument("--fid-model", type=Path, help="local TorchScript Inception (default_1.pt) for FID/KID")
    add_update_flag(ap)
    args = ap.parse_args()
    work = args.work
    for need in ("train/manifest.json", "eval/manifest.json", "stage1/model.safetensors", "latents-stage1"):
        if not (work / need).exists():
            sys.exit(f"{work / need} is missing: run benchmarks/stage2.py --work {work} first")
    report = Report("stage2-variants", "Stage 2 denoiser variants (tiny config, 2 CPU cores)")
    t_all = time.perf_counter()
    base = yaml.safe_load((REPO_ROOT / "configs/stage2/tiny.yaml").read_text())
    base |= {
        "stage1_checkpoint": str(work / "stage1" / "model.safetensors"),
        "steps": args.stage2_steps,
        "threads": 1,
        "uncertainty": "localization_potential",
        "geometry": "stage1",
    }
    runs: dict[tuple[str, int], Path] = {}
    train_jobs, eval_jobs = [], []
    for seed in args.seeds:
        runs[(BASELINE, seed)] = work / "runs" / f"localization_potential-stage1-s{seed}"
        for name, change in VARIANTS:
            tag = name.replace(" + ", "-").replace("_", "-") + f"-s{seed}"
            out = work / "variants" / tag
            if (args.only and name not in args.only) and not (out / "eval.json").exists():
                continue
            runs[(name, seed)] = out
            cfg_path = work / "variants" / f"{tag}.yaml"
            cfg_path.parent.mkdir(parents=True, exist_ok=True)
            cfg_path.write_text(yaml.safe_dump({**base, **change, "seed": seed}))
            if not (out / "model.safetensors").exists():
                shutil.rmtree(out, ignore_errors=True)
                train_jobs.append(
                    [
                        *(str(BIN / "phigenesis-train"), "stage2", "--shards", str(work / "train")),
                        *("--config", str(cfg_path), "--latents", str(work / "latents-stage1")),
                        *("--out", str(out), "--no-progress"),
                    ]
                )
            if not (out / "eval.json").exists():
                eval_jobs.append(_eval_cmd(out, work / "eval", out / "eval.json", args, 1.0))
    for (name, _seed), out in runs.items():
        if name == BASELINE and not (out / "eval.json").exists():
            sys.exit(f"{out / 'eval.json'} is missing: run benchmarks/stage2.py --work {work} first")
    _in_pairs(train_jobs)
    _in_pairs(eval_jobs)

    results = {key: json.loads((out / "eval.json").read_text()) for key, out in runs.items()}
    sections = [*SECTIONS, *(f"rollout_{k}" for k in args.rollout_frames)]
    first = results[(BASELINE, args.seeds[0])]["sections"]
    names = [BASELINE, *(n for n, _ in VARIANTS)]
    have = {name: [seed for seed in args.seeds if (name, seed) in results] for name in names}
    for key, label, digits in (
        ("psnr_db", "PSNR (dB)", 2),
        ("ssim", "SSIM", 3),
        ("abs_rel", "depth AbsRel", 3),
    ):
        table = []
        if key != "abs_rel":
            table.append([RENDER_ONLY, *_fixed_row(first, "render_only", sections, key, digits)])
            table.append([CEILING, *_fixed_row(first, "vae_reconstruction", sections, key, digits)])
        for name in names:
            cells = [_metric(results, name, have[name], s, key, digits) for s in sections]
            table.append([f"{name} (seeds {', '.join(map(str, have[name]))})", *cells])
        report.table(f"Held-out {label}, mean ± std over the seeds", ["row", *sections], table)
    if args.fid_model is not None:
        cols = [(f"rollout_{k}", m) for k in args.rollout_frames for m in ("fid", "kid")]
        fid_rows = []
        for name in names:
            fid_rows.append([name, *[_metric(results, name, have[name], s, m, 3) for s, m in cols]])
        report.table("Rollout FID / KID", ["row", *[f"{s} {m.upper()}" for s, m in cols]], fid_rows)
    report.text(f"The whole run took {(time.perf_counter() - t_all) / 60:.1f} min.")
    report.write(update=args.update)


if __name__ == "__main__":
    main()
