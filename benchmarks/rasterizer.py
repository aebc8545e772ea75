"""Gaussian rasterizer benchmark: forward and forward+backward time of the tile-based CPU rasterizer.

Usage (from the repository root)::

    python benchmarks/rasterizer.py [--repeats 3] [--threads 2] [--quick]

Random scenes of N Gaussians (10k and 100k) spread over a 90-degree wedge 2-40 m in front of five
cameras (yaws -40..40 degrees, like a front rig), rendered at 80 x 120 and 160 x 240 with RGB features,
in float32. Forward runs under ``torch.no_grad``; forward+backward renders with gradients and back-
propagates the sum of the colours, depth and alpha. The per-pixel reference (``rasterize_reference``)
runs only at the smallest size (10k Gaussians, 80 x 120). Writes the ``rasterizer`` section of
BENCHMARKS.md. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable

import torch
from _report import Report

from phigenesis.models.rasterizer import rasterize, rasterize_reference

CAMERAS = 5


def make_scene(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """N Gaussians in a wedge in front of the rig, log-uniform depth and scale (0.02-0.3 m)."""
    g = torch.Generator().manual_seed(seed)
    depth = torch.exp(torch.empty(n).uniform_(math.log(2.0), math.log(40.0), generator=g))
    yaw = torch.empty(n).uniform_(-math.pi / 4, math.pi / 4, generator=g)
    height = torch.empty(n).uniform_(-0.3, 0.3, generator=g) * depth
    means = torch.stack([depth * torch.sin(yaw), height, depth * torch.cos(yaw)], dim=-1)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.02), math.log(0.3), generator=g))
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": scales,
        "opacities": torch.rand(n, generator=g) * 0.9 + 0.05,
        "features": torch.rand(n, 3, generator=g),
    }


def make_cameras(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Five cameras at the origin, yaws -40..40 degrees, 60-degree horizontal field of view."""
    poses = []
    for yaw in torch.linspace(-math.radians(40), math.radians(40), CAMERAS).tolist():
        pose = torch.eye(4)
        pose[0, 0], pose[0, 2] = math.cos(yaw), math.sin(yaw)
        pose[2, 0], pose[2, 2] = -math.sin(yaw), math.cos(yaw)
        poses.append(pose)
    focal = 0.5 * width / math.tan(math.radians(30))
    k = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return torch.stack(poses), k[None].repeat(CAMERAS, 1, 1)


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_renderer(
    render: Callable, scene: dict, cams, k, width: int, height: int, repeats: int, backward: bool = True
) -> tuple[float, float | None, float, float]:
    def forward() -> None:
        with torch.no_grad():
            render(*scene.values(), cams, k, width, height)

    leaves = {name: t.clone().requires_grad_() for name, t in scene.items()}

    def forward_backward() -> None:
        out = render(*leaves.values(), cams, k, width, height)
        (out.features.sum() + out.depth.sum() + out.alpha.sum()).backward()
        for t in leaves.values():
            t.grad = None

    start = time.perf_counter()
    with torch.no_grad():
        out = render(*scene.values(), cams, k, width, height)
    first = time.perf_counter() - start
    coverage = 100.0 * out.alpha.gt(0.5).float().mean().item()
    visible = out.radii.gt(0).sum().item() / CAMERAS
    fwd_bwd = median_seconds(forward_backward, repeats) if backward else None
    fwd = first if repeats == 1 else median_seconds(forward, repeats)  # a single run: this one
    return fwd, fwd_bwd, coverage, visible


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    parser.add_argument("--quick", action="store_true", help="only 10k Gaussians at 80 x 120")
    parser.add_argument("--no-reference", action="store_true", help="skip the per-pixel reference")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    report = Report(
        "rasterizer",
        "Gaussian rasterizer (CPU)",
        f"Written by `benchmarks/rasterizer.py`. {CAMERAS} views, float32, RGB features, "
        f"{args.threads} torch threads, median of {args.repeats} runs (one warm-up render first). "
        "Scenes: Gaussians log-uniform 2-40 m deep in a 90-degree wedge, scales 0.02-0.3 m, "
        "opacity 0.05-0.95, seen by "
        "five 60-degree cameras (yaws -40..40 degrees). `tiled` is `rasterize` (16 px tiles); "
        "`reference` is `rasterize_reference` (every Gaussian at every pixel, no tiles), timed once per row; "
        "speed-up = reference forward / tiled forward, in the same run.",
    )
    sizes = [(80, 120)] if args.quick else [(80, 120), (160, 240)]
    counts = [10_000] if args.quick else [10_000, 100_000]
    cams, k = make_cameras(120, 80)
    time_renderer(rasterize, make_scene(2000), cams, k, 120, 80, 1)  # warm-up
    rows = []
    for n in counts:
        scene = make_scene(n)
        for height, width in sizes:
            cams, k = make_cameras(width, height)
            fwd, fwd_bwd, coverage, visible = time_renderer(
                rasterize, scene, cams, k, width, height, args.repeats, backward=True
            )
            # The reference's autograd graph (one step per Gaussian and view) would need ~10 GB, so
            # only its forward is timed, once (it takes minutes at 100k Gaussians).
            ref = None
            if not args.no_reference:
                ref = time_renderer(rasterize_reference, scene, cams, k, width, height, 1, backward=False)[0]
            rows.append(
                [
                    f"{n:,}",
                    f"{height} x {width}",
                    f"{visible:,.0f}",
                    f"{coverage:.0f}",
                    f"{fwd * 1000:,.0f}",
                    f"{fwd_bwd * 1000:,.0f}",
                    "—" if ref is None else f"{ref * 1000:,.0f}",
                    "—" if ref is None else f"{ref / fwd:.1f}x",
                ]
            )
            print(rows[-1], flush=True)
    report.table(
        "Time for 5 views",
        [
            "Gaussians",
            "H x W",
            "visible / view",
            "alpha > 0.5 %",
            "tiled forward ms",
            "tiled fwd+bwd ms",
            "reference forward ms",
            "speed-up",
        ],
        rows,
        "Visible: Gaussians not culled (in front of the near plane, support on screen), mean over views. "
        "The reference's forward+backward is not timed: its autograd graph (one step per Gaussian and "
        "view over the whole image) would need about 10 GB.",
    )
    report.write()


if __name__ == "__main__":
    main()
