"""Densification methods compared on synthetic frames: every registered method of
``phigenesis.data.stages.densify`` on the same inputs, speed against error.

Usage (from the repository root)::

    .venv/bin/python benchmarks/densify_methods.py [--repeats 5] [--frames 0 5] [--upscale 8]

Inputs per image of the waymo5 rig (240x160, 10-frame synthetic scene 0): "sweep", the frame's
own LiDAR sweep; "agg30" and "agg60", 30 % / 60 % of the exact depth with 2 cm noise and
background leaking through foreground edges. Prints a text table (the figures as they stood are
in docs/experiments.md, "Densification methods"); writes nothing.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.densify import (
    DENSIFIERS,
    F32,
    DenseResult,
    camera_focal_px,
    densify,
    sweep_sparse_depth,
)


def _sampled_depth(truth: F32, fraction: float, rng: np.random.Generator) -> F32:
    """``fraction`` of the truth's pixels with 2 cm noise; 30 % of the sampled foreground pixels
    within 2 px of a surface 20 % deeper take that deeper depth (background leaking through)."""
    picked = (rng.random(truth.shape) < fraction) & (truth > 0)
    sparse = np.where(picked, truth + rng.normal(0, 0.02, truth.shape), 0)
    deeper = cv2.dilate(truth, np.ones((5, 5), np.uint8))
    leak = picked & (deeper > 1.2 * truth) & (rng.random(truth.shape) < 0.3)
    sparse[leak] = deeper[leak]
    return np.maximum(sparse, 0).astype(np.float32)


def benchmark(frames: tuple[int, ...] = (0, 5), repeats: int = 5, upscale: int = 8) -> str:
    """Scores every registered method on synthetic frames; returns a text table.

    Inputs per image of the waymo5 rig (240x160, 10-frame scene 0): "sweep", the frame's own
    LiDAR sweep; "agg30" and "agg60", 30 % / 60 % of the exact depth (:func:`_sampled_depth`).
    Errors in metres on pixels where truth and output are both > 0 (the last column: RMSE on
    the pixels where every method gives a depth), coverage over pixels with truth; ms = median
    over images and ``repeats`` runs, the methods interleaved; the ``xN`` rows time one agg30
    image upscaled ``upscale`` times (nearest neighbour, points at the centres of the pixel
    blocks, focal length times ``upscale``).
    """
    from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene

    scene = SyntheticScene(SyntheticConfig(scenes=1, frames=10, rig="waymo5"), 0)
    rng = np.random.default_rng(0)
    images = []
    for index in frames:
        frame = scene.render_frame(index)
        for cam in frame.cameras:
            truth = cam.truth.depth_m
            inputs = {
                "sweep": sweep_sparse_depth(frame, cam),
                "agg30": _sampled_depth(truth, 0.3, rng),
                "agg60": _sampled_depth(truth, 0.6, rng),
            }
            images.append((truth, cam.decode_image(), camera_focal_px(cam), inputs))

    def timed(method: str, sparse: F32, rgb: NDArray[np.uint8], focal: float) -> tuple[DenseResult, float]:
        start = time.perf_counter()
        out = densify(sparse, (sparse > 0).astype(np.float32), rgb, focal_px=focal, method=method)
        return out, time.perf_counter() - start

    methods = sorted(DENSIFIERS)
    rows = []
    for kind in ("sweep", "agg30", "agg60"):
        times: dict[str, list[float]] = {m: [] for m in methods}
        # Squared, absolute, relative error, pixels, coverage; squared error and pixels where all
        # methods give a depth.
        sums = {m: np.zeros(7) for m in methods}
        for truth, rgb, focal, inputs in images:
            outs = {}
            for _ in range(repeats):
                for method in methods:
                    outs[method], seconds = timed(method, inputs[kind], rgb, focal)
                    times[method].append(seconds)
            common = np.logical_and.reduce([truth > 0, *(o.depth_m > 0 for o in outs.values())])
            for method, out in outs.items():
                both = (out.depth_m > 0) & (truth > 0)
                err = np.abs(out.depth_m[both] - truth[both])
                cover = both.sum() / max((truth > 0).sum(), 1)
                common_se = np.sum((out.depth_m[common] - truth[common]) ** 2)
                sums[method] += [
                    *(np.sum(err**2), err.sum(), np.sum(err / truth[both]), both.sum(), cover),
                    *(common_se, common.sum()),
                ]
        for method in methods:
            se, ae, rel, hits, cover, common_se, common_hits = sums[method]
            rows.append(
                f"{method:14s} {kind:6s} {1e3 * np.median(times[method]):6.1f} {np.sqrt(se / hits):6.3f} "
                f"{ae / hits:6.3f} {rel / hits:7.4f} {cover / len(images):6.3f} "
                f"{np.sqrt(common_se / common_hits):6.3f}"
            )
    truth, rgb, focal, inputs = images[0]
    big = np.zeros((truth.shape[0] * upscale, truth.shape[1] * upscale), np.float32)
    big[upscale // 2 :: upscale, upscale // 2 :: upscale] = inputs["agg30"]
    big_rgb = cv2.resize(rgb, big.shape[::-1], interpolation=cv2.INTER_NEAREST)
    big_times: dict[str, list[float]] = {m: [] for m in methods}
    for _ in range(max(1, repeats // 2)):
        for method in methods:
            big_times[method].append(timed(method, big, big_rgb, focal * upscale)[1])
    for method in methods:
        rows.append(f"{method:14s} x{upscale:<5d} {1e3 * np.median(big_times[method]):6.0f}")
    header = (
        f"{'method':14s} {'input':6s} {'ms':>6s} {'RMSE':>6s} {'MAE':>6s} {'AbsRel':>7s} {'cover':>6s} "
        f"{'common RMSE':>6s}"
    )
    return "\n".join([header, *sorted(rows, key=lambda r: r.split()[0])])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--frames", type=int, nargs="+", default=[0, 5], help="frames of the scene (default 0 5)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per image and method (default 5)")
    parser.add_argument(
        "--upscale", type=int, default=8, help="upscale factor of the large image (default 8)"
    )
    args = parser.parse_args(argv)
    print(benchmark(tuple(args.frames), args.repeats, args.upscale))


if __name__ == "__main__":
    main()
