"""Gaussian rasterizer on a GPU: gsplat's CUDA kernels (``backend="gsplat"``) against the native CPU
kernel on the same scenes, agreement and speed.

The GPU is on another machine than the one that keeps BENCHMARKS.md, so this runs in two steps::

    python benchmarks/rasterizer_gpu.py --measure gpu.json [--commit REV]   # CUDA, gsplat 1.5.3
    python benchmarks/rasterizer_gpu.py --report gpu.json                   # writes the section

The scenes, cameras and sizes are ``benchmarks/rasterizer.py``'s (5 views; 10k / 100k / 1M Gaussians;
80 x 120, 160 x 240, 576 x 1024; RGB; float32). On the GPU machine it times, each as wall time of one
synchronised call, median over repeats after warm-up calls:

- ``gsplat``: ``rasterize(..., backend="gsplat")`` on CUDA tensors, forward (no grad) and forward+backward
  (the sum of colours, depth and alpha back-propagated to all five inputs), with peak CUDA memory;
- ``tiled``: ``rasterize(..., backend="torch")`` on CUDA tensors (what ``"auto"`` falls back to on a GPU
  without gsplat), on the configurations where the CPU benchmark runs it;
- ``native``: ``rasterize(..., backend="cpu")`` on that machine's CPU, all its cores.

Agreement compares gsplat's forward outputs and gradients with the native kernel's on every
configuration. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, cpu_model, ram_gib
from rasterizer import CAMERAS, COUNTS, SIZES, TILED_ROWS, _loss, _visible, make_cameras, make_scene

from phigenesis.models.rasterizer import RenderOutput, gsplat_available, native_available, rasterize

#: Repeats of a timed call (after warm-up); calls over LONG_CALL_S are timed fewer times.
GPU_REPEATS, CPU_REPEATS, LONG_CALL_S = 20, 3, 5.0  # calls over 0.5 s on the GPU: CPU_REPEATS
INPUTS = ("means", "quats", "scales", "opacities", "features")


def _timed(fn: Callable[[], None], repeats: int, sync: bool) -> dict:
    """Median wall ms of ``fn`` over ``repeats`` calls after one timed warm-up call (two more untimed
    on the GPU); a warm-up over LONG_CALL_S is the only timed call."""

    def once() -> float:
        if sync:
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if sync:
            torch.cuda.synchronize()
        return 1000 * (time.perf_counter() - start)

    first = once()
    if first > 1000 * LONG_CALL_S:
        return {"ms": first, "runs": 1}
    if sync:
        once(), once()
    if first > 500:  # a slow path on the GPU (tiled at 576 x 1024): a few calls say enough
        repeats = min(repeats, CPU_REPEATS)
    times = [once() for _ in range(repeats)]
    return {"ms": statistics.median(times), "runs": repeats, "min_ms": min(times)}


def _modes(render: Callable[..., RenderOutput], scene: dict, cams, k, width: int, height: int) -> dict:
    """The two timed callables of one backend: forward without grad, forward+backward."""
    leaves = {name: t.detach().clone().requires_grad_() for name, t in scene.items()}

    def forward() -> None:
        with torch.no_grad():
            render(*scene.values(), cams, k, width, height)

    def forward_backward() -> None:
        _loss(render(*leaves.values(), cams, k, width, height)).backward()
        for t in leaves.values():
            t.grad = None

    return {"fwd": forward, "fwdbwd": forward_backward}


def _outputs_and_grads(backend: str, scene: dict, cams, k, width: int, height: int):
    leaves = [t.detach().clone().requires_grad_() for t in scene.values()]
    out = rasterize(*leaves, cams, k, width, height, backend=backend)
    grads = torch.autograd.grad(_loss(out), leaves)
    cpu = RenderOutput(*(t.detach().cpu() for t in (out.features, out.depth, out.alpha, out.radii)))
    return cpu, [g.cpu() for g in grads]


def agreement(scene: dict, cams, k, width: int, height: int) -> dict:
    """gsplat (CUDA) against the native kernel (CPU): max output differences, radii and culling
    mismatches, and each input's largest gradient difference relative to its largest native gradient."""
    cuda = {name: t.cuda() for name, t in scene.items()}
    gs, gs_grads = _outputs_and_grads("gsplat", cuda, cams.cuda(), k.cuda(), width, height)
    nat, nat_grads = _outputs_and_grads("cpu", scene, cams, k, width, height)
    both = (gs.alpha > 0.5) & (nat.alpha > 0.5)
    kept = (gs.radii > 0) & (nat.radii > 0)
    return {
        "features": (gs.features - nat.features).abs().max().item(),
        "alpha": (gs.alpha - nat.alpha).abs().max().item(),
        "depth": (gs.depth - nat.depth)[both].abs().max().item() if both.any() else 0.0,
        "pixels_over_1e-3": (gs.features - nat.features).abs().amax(-1).gt(1e-3).float().mean().item(),
        "radii_differing": int(((gs.radii != nat.radii) & kept).sum()),
        "culling_differing": int(((gs.radii > 0) != (nat.radii > 0)).sum()),
        "grad_rel": {
            name: ((a - b).abs().max() / b.abs().max().clamp(min=1e-30)).item()
            for name, a, b in zip(INPUTS, gs_grads, nat_grads, strict=True)
        },
    }


def machine() -> dict:
    """What the section header says about the GPU machine."""
    props = torch.cuda.get_device_properties(0)
    versions = {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda}
    for name in ("gsplat", "numpy"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return {
        "gpu": f"{props.name}, {props.total_memory / 2**30:.0f} GiB, {props.multi_processor_count} SMs",
        "cpu": f"{cpu_model()}, {os.cpu_count()} cores, {ram_gib() or 0:.0f} GiB RAM",
        "versions": versions,
        "date": f"{datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}",
    }


def measure(path: Path, commit: str, quick: bool) -> None:
    """Runs every measurement on this (CUDA) machine and writes them to ``path`` as JSON."""
    if not gsplat_available():
        sys.exit(
            "--measure needs CUDA and gsplat (pip install gsplat==1.5.3; its kernels compile on first use)"
        )
    if not native_available():
        sys.exit("--measure needs the native CPU kernel (g++ with OpenMP, ninja)")
    threads = os.cpu_count() or 1
    torch.set_num_threads(threads)
    result = {
        "machine": machine(),
        "commit": commit,
        "command": " ".join(sys.argv),
        "threads": threads,
        "rows": [],
    }
    counts, sizes = (COUNTS[:1], SIZES[:1]) if quick else (COUNTS, SIZES)
    for n in counts:
        for height, width in sizes:
            scene = make_scene(n)
            cams, k = make_cameras(width, height)
            cuda = {name: t.cuda() for name, t in scene.items()}
            cams_c, k_c = cams.cuda(), k.cuda()
            row: dict = {"n": n, "size": [height, width]}
            with torch.no_grad():
                row["visible"] = _visible(
                    rasterize(*cuda.values(), cams_c, k_c, width, height, backend="gsplat"), n
                )
            runs = {
                "gsplat": (
                    _modes(lambda *a: rasterize(*a, backend="gsplat"), cuda, cams_c, k_c, width, height),
                    True,
                ),
                "native": (
                    _modes(lambda *a: rasterize(*a, backend="cpu"), scene, cams, k, width, height),
                    False,
                ),
            }
            if (n, (height, width)) in TILED_ROWS:
                tiled = _modes(lambda *a: rasterize(*a, backend="torch"), cuda, cams_c, k_c, width, height)
                runs["tiled"] = (tiled, True)
            for backend, (modes, sync) in runs.items():
                for mode, fn in modes.items():
                    if sync:
                        torch.cuda.reset_peak_memory_stats()
                        base = torch.cuda.memory_allocated()
                    r = _timed(fn, GPU_REPEATS if sync else CPU_REPEATS, sync)
                    if sync:
                        r["peak_gib"] = torch.cuda.max_memory_allocated() / 2**30
                        r["peak_over_scene_gib"] = (torch.cuda.max_memory_allocated() - base) / 2**30
                    row[f"{backend} {mode}"] = r
                    print(f"{n:>9,} {height} x {width} {backend:>6} {mode:>6}: {r}", flush=True)
            row["agreement"] = agreement(scene, cams, k, width, height)
            print(f"{n:>9,} {height} x {width} agreement: {row['agreement']}", flush=True)
            result["rows"].append(row)
            path.write_text(json.dumps(result, indent=1))  # after every row: a cut-off run keeps its rows
            del cuda, runs
            torch.cuda.empty_cache()
    print(f"wrote {path}")


def _ms(r: dict | None) -> str:
    if r is None:
        return "—"
    return f"{r['ms']:,.0f}" if r["ms"] >= 100 else f"{r['ms']:.2f}" if r["ms"] < 10 else f"{r['ms']:.1f}"


def _ratio(slow: dict | None, fast: dict | None) -> str:
    if not (slow and fast):
        return "—"
    ratio = slow["ms"] / fast["ms"]
    return f"{ratio:,.0f}x" if ratio >= 10 else f"{ratio:.1f}x"


def report(path: Path, update: bool) -> None:
    """Writes the ``rasterizer_gpu`` section of BENCHMARKS.md from a ``--measure`` file."""
    data = json.loads(path.read_text())
    m, v = data["machine"], data["machine"]["versions"]
    header = "\n".join(
        [
            f"- Machine: {m['gpu']}; CPU {m['cpu']} (a GPU machine lent by the device tool)",
            f"- Command: `python3 {data['command']}` there, then "
            f"`python benchmarks/rasterizer_gpu.py --report {path}` here (the measurements: that file)",
            f"- Date: {m['date']}; commit {data['commit']}",
            "- Versions: " + ", ".join(f"{name} {version}" for name, version in v.items()),
        ]
    )
    rep = Report(
        "rasterizer_gpu",
        "Gaussian rasterizer (GPU): gsplat against the native CPU kernel",
        "Written by `benchmarks/rasterizer_gpu.py`. The scenes, cameras and sizes of the CPU section above "
        f'({CAMERAS} views, float32, RGB). `gsplat` is `rasterize(..., backend="gsplat")` on CUDA tensors '
        "(gsplat 1.5.3's kernels, one call for the five views); `tiled` is the pure-PyTorch path on the same "
        'GPU (what `"auto"` uses on a GPU without gsplat), where the CPU section runs it; `native` is the '
        f"C++ kernel on the same machine's CPU with {data['threads']} threads (the 2-core figures are in the "
        "CPU section). Times: wall time of one synchronised call (projection, binning, compositing and, for "
        f"fwd+bwd, the backward of the summed colours, depth and alpha), median of {GPU_REPEATS} calls on "
        f"the GPU after three warm-up calls, of {CPU_REPEATS} on the CPU after one (a call over "
        f"{LONG_CALL_S:.0f} s: that one call).",
        header=header,
    )
    rows, mem_rows, agree_rows = [], [], []
    for row in data["rows"]:
        h, w = row["size"]
        cfg = [f"{row['n']:,}", f"{h} x {w}"]
        rows.append(
            [
                *cfg,
                f"{row['visible']:,.0f}",
                _ms(row.get("gsplat fwd")),
                _ms(row.get("gsplat fwdbwd")),
                _ms(row.get("tiled fwd")),
                _ms(row.get("tiled fwdbwd")),
                _ms(row.get("native fwd")),
                _ms(row.get("native fwdbwd")),
                _ratio(row.get("native fwd"), row.get("gsplat fwd")),
                _ratio(row.get("native fwdbwd"), row.get("gsplat fwdbwd")),
                _ratio(row.get("tiled fwdbwd"), row.get("gsplat fwdbwd")),
            ]
        )
        mem_rows.append(
            [
                *cfg,
                *(
                    f"{row[key]['peak_gib']:.3f}" if key in row else "—"
                    for key in ("gsplat fwd", "gsplat fwdbwd", "tiled fwd", "tiled fwdbwd")
                ),
            ]
        )
        a = row["agreement"]
        worst = max(a["grad_rel"], key=a["grad_rel"].get)
        agree_rows.append(
            [
                *cfg,
                f"{a['features']:.1e}",
                f"{a['depth']:.1e}",
                f"{a['alpha']:.1e}",
                f"{100 * a['pixels_over_1e-3']:.3f}",
                a["radii_differing"],
                a["culling_differing"],
                *(f"{a['grad_rel'][name]:.1e}" for name in INPUTS),
                worst,
            ]
        )
    rep.table(
        f"Time for {CAMERAS} views (ms)",
        [
            "Gaussians",
            "H x W",
            "visible / view",
            "gsplat fwd",
            "gsplat fwd+bwd",
            "tiled GPU fwd",
            "tiled GPU fwd+bwd",
            f"native {data['threads']} threads fwd",
            f"native {data['threads']} threads fwd+bwd",
            "native / gsplat fwd",
            "native / gsplat fwd+bwd",
            "tiled GPU / gsplat fwd+bwd",
        ],
        rows,
        "Visible: Gaussians gsplat does not cull, mean over views. — where a path is not run (tiled: as in "
        "the CPU section).",
    )
    rep.table(
        "Peak CUDA memory (GiB, torch's allocator, scene included)",
        ["Gaussians", "H x W", "gsplat fwd", "gsplat fwd+bwd", "tiled GPU fwd", "tiled GPU fwd+bwd"],
        mem_rows,
    )
    rep.table(
        "Agreement: gsplat (CUDA) against the native kernel (CPU), float32",
        [
            "Gaussians",
            "H x W",
            "colour",
            "depth m",
            "alpha",
            "% pixels colour > 1e-3",
            "radii differing",
            "culling differing",
            *(f"grad {name}" for name in INPUTS),
            "worst grad",
        ],
        agree_rows,
        "Colour, depth, alpha: max abs difference of the forward outputs (depth where both alphas exceed "
        "0.5). Radii differing: (view, Gaussian) entries both keep with different box sizes; culling "
        "differing: entries one keeps and the other culls. gsplat keeps boxes that end within half a "
        "pixel outside the outermost pixel centres (its centres sit at j + 0.5), which touch no pixel: "
        "recomputing both rules from the PyTorch projection on the CPU gave exactly these counts on every "
        "row of the 2026-12-04 run, and no entry the other way. Grad: largest |gsplat - native| gradient of "
        "the summed colours, depth and alpha, relative to the largest native gradient of that input.",
    )
    rep.text(_summary(data))
    rep.write(update=update)


def _summary(data: dict) -> str:
    """One paragraph: the speed-up range and the worst agreement, from the measurements."""
    rows = data["rows"]

    def span(mode: str) -> str:
        ratios = [r[f"native {mode}"]["ms"] / r[f"gsplat {mode}"]["ms"] for r in rows]
        return f"{min(ratios):,.0f}-{max(ratios):,.0f}x"

    worst = max(rows, key=lambda r: r["agreement"]["features"])
    grad = max(max(r["agreement"]["grad_rel"].values()) for r in rows)
    alpha = max(r["agreement"]["alpha"] for r in rows)
    share = max(r["agreement"]["pixels_over_1e-3"] for r in rows)
    return (
        f"**Summary.** gsplat on the GPU is {span('fwd')} faster than the native kernel on "
        f"{data['threads']} CPU threads forward and {span('fwdbwd')} forward+backward. They agree to "
        f"{worst['agreement']['features']:.1e} in colour and {alpha:.1e} in alpha at worst, on at most "
        f"{100 * share:.4f} % of the pixels (all others within 1e-3); the gradients to {grad:.1e} of the "
        "largest gradient. The largest alpha differences stay below 1/255 = 3.9e-3, consistent with one "
        "Gaussian whose alpha sits at the 1/255 cut-off landing on different sides of it in the two kernels "
        "(gsplat's `__expf` against the CPU's `expf`)."
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--measure", type=Path, help="measure here (CUDA, gsplat) into this JSON file")
    action.add_argument("--report", type=Path, help="write the BENCHMARKS.md section from this JSON file")
    parser.add_argument("--commit", default="unknown", help="the commit measured (the GPU copy has no git)")
    parser.add_argument("--quick", action="store_true", help="10k Gaussians at 80 x 120 only")
    add_update_flag(parser)
    args = parser.parse_args(argv)
    if args.measure:
        measure(args.measure, args.commit, args.quick)
    else:
        report(args.report, args.update)


if __name__ == "__main__":
    main()
