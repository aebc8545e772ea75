"""Depth completion benchmark: coverage and error of the ``complete_depth`` stage on synthetic
scenes whose dense depth and classes are exact.

Usage (from the repository root)::

    python -m benchmarks.completion [--scenes N] [--frames F] [--eval-frames K] [--quick]

Each synthetic scene (``waymo5`` rig, 160 x 240 images, 64-beam LiDAR) runs through the synthetic
pipeline's stages up to ``pseudo_semantics`` with its parameters (aggregation, projection,
densification, pseudo labels). On ``K`` frames spread over the scene, every image's dense depth is
scored before (densifier only) and after ``complete_depth`` against the exact z-depth, on the
pixels that show a surface other than the sky (the ego body excluded): coverage, AbsRel, MAE,
RMSE, by origin (``records.DENSE_ORIGINS``) and by truth class. The stage is timed per frame as
the pipeline runs it (lazily, per-camera tables cached), and once on an image upscaled 8x
(1280 x 1920, the coarse-grid path). A few ablations rerun the stage with one part switched off.

``--update`` writes the ``completion`` section of BENCHMARKS.md and a figure of one image before and after to
docs/images/depth_completion.png. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, output_path

from phigenesis import taxonomy as tx
from phigenesis.data.pipeline import load_pipeline
from phigenesis.data.records import DENSE_ORIGINS, CameraDepth, Frame, LazyFrames, Scene
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.complete import CompletionParams, segment_image
from phigenesis.data.stages.densify import camera_focal_px
from phigenesis.models.metrics import depth_errors

FIGURE = "docs/images/depth_completion.png"
STAGES = [stage for stage in load_pipeline("synthetic").stages if stage.name != "range_view"]
BEFORE = [stage for stage in STAGES if stage.name != "complete_depth"]
PARAMS = next((dict(s.params) for s in STAGES if s.name == "complete_depth"), {})
CODES = {name: i for i, name in enumerate(DENSE_ORIGINS)}
COMPLETED = (CODES["plane"], CODES["vertical"])
#: Reruns of the stage with one part switched off (parameter overrides).
ABLATIONS = {
    "no segment merging": {"merge_color_tol": 0.0},
    "no ground planes": {"ground_planes": False},
    "no ground beyond the data": {"propagate_ground": False},
    "no second plane per segment": {"min_plane_share": 0.7},
    "no thin vertical structures": {"max_thin_width_ref_px": 1e-3},
    "no planes for thin segments step 6 left (thin_planes)": {"thin_planes": False},
    "no facades climbing (propagate_up)": {"propagate_up": False},
    "no planes from sparse depth": {"sparse_planes": False},
    "no planes through a line of points (line_planes)": {"line_planes": False},
    "no tree crowns (crowns)": {"crowns": False},
    "no crowns of many segments (canopies)": {"canopies": False},
    "no vehicles of one depth (vehicle_max_spread 0)": {"vehicle_max_spread": 0.0},
    "no climbing columns of two apart facades (climb_columns)": {"climb_columns": False},
    "no walls climbing from each column's top (wall_columns)": {"wall_columns": False},
    "min_height_m only (min_height_rel 1)": {"min_height_rel": 1.0},
    "min_incidence_deg 8": {"min_incidence_deg": 8.0},
}


@dataclass
class Image:
    """One camera image of an evaluation frame: truth and the depth before and after completion."""

    rgb: np.ndarray
    focal_px: float
    truth_m: np.ndarray
    semantic: np.ndarray
    valid: np.ndarray  # a surface, not sky, not the ego body
    pseudo_sky: np.ndarray  # labelled sky by pseudo_semantics (never filled)
    before: CameraDepth
    after: CameraDepth


def run_pipeline(cfg: SyntheticConfig, index: int, eval_frames: int) -> tuple[Scene, list[Frame]]:
    """The scene through the stages before ``complete_depth``, and its evaluation frames."""
    synthetic = SyntheticScene(cfg, index)
    scene = synthetic.scene()
    for stage in BEFORE:
        scene = get_stage(stage.name)(scene, dict(stage.params))
    picks = np.linspace(1, cfg.frames - 2, eval_frames).round().astype(int)
    return scene, [scene.frames[int(i)] for i in picks]


def complete(scene: Scene, frames: list[Frame], params: dict) -> tuple[list[Frame], list[float]]:
    """The frames through ``complete_depth`` as the pipeline runs it (lazily), and the seconds
    each frame took (the first includes the per-camera tables)."""
    lazy = Scene(
        scene.scene_id, scene.source, scene.calibrations, LazyFrames(len(frames), frames.__getitem__)
    )
    out = get_stage("complete_depth")(lazy, params)
    done, seconds = [], []
    for k in range(len(frames)):
        t0 = time.perf_counter()
        done.append(out.frames[k])
        seconds.append(time.perf_counter() - t0)
    return done, seconds


def images_of(before: list[Frame], after: list[Frame]) -> list[Image]:
    out = []
    for fb, fa in zip(before, after, strict=True):
        for cb, ca in zip(fb.cameras, fa.cameras, strict=True):
            t = cb.truth
            valid = (t.depth_m > 0) & (t.semantic != tx.IGNORE_ID) & (t.semantic != tx.SKY)
            rgb, focal = cb.decode_image(), camera_focal_px(cb)
            sky = cb.pseudo.semantic == tx.SKY if cb.pseudo is not None else np.zeros_like(valid)
            out.append(Image(rgb, focal, t.depth_m, t.semantic, valid, sky, cb.depth, ca.depth))
    return out


def flat(values: Sequence[np.ndarray]) -> np.ndarray:
    return np.concatenate([v.ravel() for v in values])


def error_cells(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, total: int) -> list[str]:
    """Share of ``total`` pixels, AbsRel, MAE and RMSE of ``pred`` on ``mask``."""
    e = depth_errors(pred, truth, mask)
    if e.covered == 0:
        return ["0.0", "—", "—", "—"]
    return [f"{100 * e.covered / total:.1f}", f"{e.abs_rel:.4f}", f"{e.mae_m:.3f}", f"{e.rmse_m:.3f}"]


def summary(images: list[Image], report: Report) -> dict[str, float]:
    truth = flat([i.truth_m for i in images])
    valid = flat([i.valid for i in images])
    sem = flat([i.semantic for i in images])
    before = flat([i.before.dense_m for i in images])
    after = flat([i.after.dense_m for i in images])
    origin = flat([i.after.dense_origin for i in images])
    conf = flat([i.after.dense_confidence for i in images])
    n = int(valid.sum())
    completed = np.isin(origin, COMPLETED)
    sky = (sem == tx.SKY) & (after > 0)
    e_before, e_after = depth_errors(before, truth, valid), depth_errors(after, truth, valid)
    e_new = depth_errors(after, truth, valid & completed)
    rows = [
        ["densifier only", *error_cells(before, truth, valid, n)],
        ["densifier + completion", *error_cells(after, truth, valid, n)],
        ["  of which completed (plane, vertical)", *error_cells(after, truth, valid & completed, n)],
    ]
    report.table(
        "Coverage and errors, before and after completion",
        ["depth", "coverage % of non-sky", "AbsRel", "MAE m", "RMSE m"],
        rows,
        f"{len(images)} images, {n} pixels showing a surface other than the sky (ego body excluded). "
        f"Sky pixels (truth) given a depth after completion: {int(sky.sum())} "
        f"({100 * sky.sum() / max((sem == tx.SKY).sum(), 1):.3f} % of the sky); before: "
        f"{int(((sem == tx.SKY) & (before > 0)).sum())}.",
    )
    rows = []
    for name in DENSE_ORIGINS[1:]:
        mine = valid & (origin == CODES[name])
        c = conf[mine]
        rows.append([name, *error_cells(after, truth, mine, n), f"{c.mean():.3f}" if c.size else "—"])
    report.table(
        "By origin (after completion)",
        ["origin", "share % of non-sky", "AbsRel", "MAE m", "RMSE m", "mean confidence"],
        rows,
    )
    rows = []
    for cls in np.unique(sem[valid]):
        mine = valid & (sem == cls)
        b = depth_errors(before, truth, mine)
        new = depth_errors(after, truth, mine & completed)
        rows.append(
            [
                tx.class_name(int(cls)),
                f"{100 * mine.sum() / n:.1f}",
                f"{100 * b.coverage:.1f}",
                f"{100 * depth_errors(after, truth, mine).coverage:.1f}",
                f"{b.abs_rel:.4f}" if b.covered else "—",
                f"{new.abs_rel:.4f}" if new.covered else "—",
                f"{new.mae_m:.3f}" if new.covered else "—",
            ]
        )
    rows.sort(key=lambda r: -float(r[1]))
    report.table(
        "By truth class",
        [
            "class",
            "share % of non-sky",
            "coverage % before",
            "coverage % after",
            "AbsRel before",
            "AbsRel completed",
            "MAE m completed",
        ],
        rows,
        "AbsRel before: the densifier's pixels of the class; completed: the pixels completion added.",
    )
    edges = [0.0, 0.05, 0.1, 0.2, 0.3, 0.46]
    rows = []
    for lo, hi in itertools.pairwise(edges):
        mine = valid & completed & (conf >= lo) & (conf < hi)
        e = depth_errors(after, truth, mine)
        rows.append([f"[{lo:.2f}, {hi:.2f})", e.covered, f"{e.abs_rel:.4f}" if e.covered else "—"])
    report.table(
        "Confidence of completed pixels against their error",
        ["confidence", "pixels", "AbsRel"],
        rows,
        "Training can weigh by confidence: the lower it is, the larger the error should be.",
    )
    return {
        "coverage_before": e_before.coverage,
        "coverage_after": e_after.coverage,
        "abs_rel_completed": e_new.abs_rel,
        "sky_share": float(sky.sum() / max((sem == tx.SKY).sum(), 1)),
    }


def left_empty(images: list[Image], report: Report) -> None:
    """Why the non-sky pixels without depth after completion have none, by their image segment
    (recomputed: :func:`segment_image` is deterministic)."""
    p = CompletionParams(**PARAMS)
    n = sum(int(i.valid.sum()) for i in images)
    rows: dict[str, list[int]] = {}
    veg = tx.CLASS_IDS["vegetation"]
    for image in images:
        empty = image.valid & (image.after.dense_m <= 0)
        seg = segment_image(image.rgb, image.focal_px, p).ravel()
        count = int(seg.max()) + 1
        evidence = (image.before.dense_m > 0) | (image.before.sparse_m > 0)
        seen = np.bincount(seg, evidence.ravel(), count) >= p.min_inliers
        e, sky = empty.ravel(), image.pseudo_sky.ravel()
        far = image.truth_m.ravel() > 75.0  # the synthetic LiDAR's range
        green = image.semantic.ravel() == veg
        cases = {
            "labelled sky by pseudo_semantics (never filled)": e & sky,
            "segment the LiDAR did not see, beyond its 75 m range": e & ~sky & ~seen[seg] & far,
            "segment the LiDAR did not see, nearer (tops, far facades)": e & ~sky & ~seen[seg] & ~far,
            "segment with LiDAR depth, no plane explains it: vegetation": e & ~sky & seen[seg] & green,
            "segment with LiDAR depth, no plane explains it: other": e & ~sky & seen[seg] & ~green,
        }
        for name, mask in cases.items():
            rows.setdefault(name, [0])[0] += int(mask.sum())
    report.table(
        "What stays empty",
        ["non-sky pixels without depth after completion", "share % of non-sky"],
        [[name, f"{100 * v[0] / n:.1f}"] for name, v in rows.items()],
        "By the image segment they lie in (LiDAR depth: dense or sparse, at least min_inliers "
        "pixels). Only the geometry of the scene anchors a completion: what the LiDAR did not see "
        "is completed only from a facade below it (step 7), and vegetation only where its known "
        "depths are those of one crown (step 6b).",
    )


def timing(report: Report, seconds: list[list[float]], images: list[Image], cams: int) -> None:
    """``seconds``: per scene, each evaluation frame's time (the first builds the tables)."""
    steady = [t for scene in seconds for t in (scene[1:] or scene)]
    per_image = 1e3 * float(np.median(steady)) / cams
    p = CompletionParams(**PARAMS)
    seg = []
    for image in images[: 3 * cams]:
        t0 = time.perf_counter()
        segment_image(image.rgb, image.focal_px, p)
        seg.append(time.perf_counter() - t0)
    big, big_ms = upscaled_timing(images[0])
    report.table(
        "Time",
        ["what", "ms"],
        [
            [
                "complete_depth per 160 x 240 image (median over frames, as the pipeline runs it)",
                f"{per_image:.1f}",
            ],
            ["  of which image segmentation (graph segmentation + merging)", f"{1e3 * np.median(seg):.1f}"],
            [
                f"one {big} image (upscaled 8x: the coarse-grid path, max_side_px {p.max_side_px})",
                f"{big_ms:.0f}",
            ],
        ],
        "Wall time on the machine above (shared, see its load average); the stage's time includes "
        "decoding the JPEG and building its inputs.",
    )


def upscaled_timing(image: Image, factor: int = 8) -> tuple[str, float]:
    """Seconds of one completion of an image upscaled ``factor`` times (nearest neighbour)."""
    from phigenesis.data.stages.complete import complete_depth_map

    h, w = image.truth_m.shape
    big = (h * factor, w * factor)

    def up(a: np.ndarray) -> np.ndarray:
        return cv2.resize(a, big[::-1], interpolation=cv2.INTER_NEAREST)

    f = image.focal_px * factor
    u, v = np.meshgrid((np.arange(big[1]) - (big[1] - 1) / 2) / f, (np.arange(big[0]) - (big[0] - 1) / 2) / f)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3)
    before = image.before
    t0 = time.perf_counter()
    complete_depth_map(
        up(before.dense_m),
        up(before.dense_confidence),
        up(image.rgb),
        rays_cam=rays,
        up_cam=np.array([0.0, -1.0, 0.0]),
        focal_px=f,
        params=CompletionParams(**PARAMS),
    )
    return f"{big[0]} x {big[1]}", 1e3 * (time.perf_counter() - t0)


def ablations(report: Report, runs: list[tuple[Scene, list[Frame]]], default: dict[str, float]) -> None:
    rows = [
        [
            "default",
            f"{100 * default['coverage_after']:.1f}",
            f"{default['abs_rel_completed']:.4f}",
        ]
    ]
    for name, overrides in ABLATIONS.items():
        images = []
        for scene, frames in runs:
            after, _ = complete(scene, frames, {**PARAMS, **overrides})
            images += images_of(frames, after)
        truth = flat([i.truth_m for i in images])
        valid = flat([i.valid for i in images])
        after_m = flat([i.after.dense_m for i in images])
        origin = flat([i.after.dense_origin for i in images])
        cover = depth_errors(after_m, truth, valid).coverage
        new = depth_errors(after_m, truth, valid & np.isin(origin, COMPLETED))
        rows.append([name, f"{100 * cover:.1f}", f"{new.abs_rel:.4f}" if new.covered else "—"])
    report.table(
        "Ablations: the stage with one part switched off",
        ["variant", "coverage % of non-sky", "AbsRel of completed pixels"],
        rows,
    )


def goals(report: Report, s: dict[str, float]) -> None:
    report.table(
        "Goals",
        ["goal", "measured", "met"],
        [
            [
                ">= 90 % of non-sky pixels with depth",
                f"{100 * s['coverage_before']:.1f} → {100 * s['coverage_after']:.1f} %",
                "yes" if s["coverage_after"] >= 0.9 else "no",
            ],
            [
                "AbsRel <= 0.05 on the completed pixels",
                f"{s['abs_rel_completed']:.4f}",
                "yes" if s["abs_rel_completed"] <= 0.05 else "no",
            ],
            [
                "the sky stays empty (<= 0.1 % of its pixels given a depth)",
                f"{100 * s['sky_share']:.3f} %",
                "yes" if s["sky_share"] <= 0.001 else "no",
            ],
        ],
    )


def figure(image: Image, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    colours = ["black", "tab:blue", "tab:green", "tab:orange", "tab:red", "tab:purple"][: len(DENSE_ORIGINS)]
    far = float(np.percentile(image.truth_m[image.truth_m > 0], 95))
    panels = [
        ("image", image.rgb, {}),
        ("densified (before)", image.before.dense_m, {"cmap": "turbo", "vmin": 0, "vmax": far}),
        ("completed (after)", image.after.dense_m, {"cmap": "turbo", "vmin": 0, "vmax": far}),
        (
            "origin",
            image.after.dense_origin,
            {"cmap": ListedColormap(colours), "vmin": 0, "vmax": len(colours) - 1},
        ),
        ("truth", image.truth_m, {"cmap": "turbo", "vmin": 0, "vmax": far}),
    ]
    fig, axes = plt.subplots(1, 5, figsize=(20, 3.4))
    for ax, (title, data, kw) in zip(axes, panels, strict=True):
        depth_panel = kw.get("cmap") == "turbo"
        ax.imshow(np.where(data > 0, data, np.nan) if depth_panel else data, interpolation="nearest", **kw)
        ax.set_title(title)
        ax.axis("off")
    axes[3].legend(
        handles=[Patch(color=c, label=n) for c, n in zip(colours, DENSE_ORIGINS, strict=True)],
        loc="lower left",
        fontsize=7,
    )
    fig.suptitle(f"Depth completion (depth 0-{far:.0f} m; white: no depth)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--eval-frames", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="1 scene of 8 frames, 2 evaluated, no ablations")
    add_update_flag(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.frames, args.eval_frames = 1, 8, 2
    cfg = SyntheticConfig(
        scenes=args.scenes, frames=args.frames, seed=args.seed, rig="waymo5", height=160, width=240
    )
    report = Report(
        "completion",
        "Depth completion (benchmarks/completion.py)",
        f"Synthetic scenes (waymo5, 160 x 240 images, 64 x 1024 LiDAR), {args.scenes} scene(s) of "
        f"{args.frames} frames, {args.eval_frames} frames each scored against the exact z-depth; the "
        f"synthetic pipeline's stages and parameters (complete_depth: {PARAMS or 'defaults'}). Figure: "
        "`docs/images/depth_completion.png`.",
    )
    runs, images, seconds = [], [], []
    for index in range(args.scenes):
        scene, frames = run_pipeline(cfg, index, args.eval_frames)
        after, took = complete(scene, frames, PARAMS)
        runs.append((scene, frames))
        images += images_of(frames, after)
        seconds.append(took)
        print(f"scene {scene.scene_id} done", flush=True)
    cams = len(runs[0][1][0].cameras)
    s = summary(images, report)
    left_empty(images, report)
    timing(report, seconds, images, cams)
    if not args.quick:
        ablations(report, runs, s)
    goals(report, s)
    gain = [int(np.isin(i.after.dense_origin, COMPLETED).sum()) for i in images[: cams * args.eval_frames]]
    figure(images[int(np.argmax(gain))], output_path(FIGURE, args.update))
    report.write(update=args.update)


if __name__ == "__main__":
    main()
