"""Depth ground truth benchmark: speed against error of projection and densification, on
synthetic scenes whose dense depth is exact.

Usage (from the repository root)::

    python benchmarks/depth.py [--scenes N] [--frames F] [--eval-frames K] [--full-frames 200] [--quick]
    python benchmarks/depth.py --stage-only --height 480 --width 720   # only the whole-stage timing

For each synthetic scene (``waymo5`` rig, 160 x 240 images, 64-beam LiDAR) the LiDAR is
aggregated with each voxel size; then, on ``K`` frames spread over the scene, every camera's
sparse depth is projected single-sweep and aggregated (the default, and ablations of its
visibility test, plane fits and depth-edge confidence), and every densifier runs on the default
sparse input. Each variant is scored against the exact z-depth on
the pixels that show a surface (the ego body excluded): coverage, RMSE, MAE, AbsRel and
delta < 1.25, split into static and dynamic pixels (surfaces of moving objects) and near (< 20 m)
and far. The see-through share (projected depths more than 5 % + 0.1 m behind the visible
surface) is counted before and after the visibility test. Source reading (rendering) is never
timed: the geometry frames are rendered once beforehand.

Then (``--full-frames``) one scene of that many frames runs the whole depth stage as the pipeline
does, timing aggregation, projection and densification per frame (the frames rendered first),
and reports the peak RSS.

``--update`` writes the ``depth`` section of BENCHMARKS.md and a figure (Pareto front and depth maps) to
docs/images/depth_benchmark.png, and the ``depth-stage`` section. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import resource
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, output_path

from phigenesis.data.pipeline import load_pipeline
from phigenesis.data.records import TRUSTED_DEPTH_CONFIDENCE, Frame, LazyFrames, Scene
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.stages import get_stage
from phigenesis.data.stages.aggregate import AggregateParams, LidarMap, aggregate_scene
from phigenesis.data.stages.densify import DEFAULT_DENSIFIER, DENSIFIERS, densify, needs_rgb
from phigenesis.data.stages.project import ProjectParams, _Projector
from phigenesis.models.metrics import depth_errors, see_through_share

FIGURE = "docs/images/depth_benchmark.png"
VOXELS_M = (0.02, 0.05, 0.1)
#: The depth stages' parameters as the synthetic pipeline runs them.
PIPELINE_PARAMS = {stage.name: dict(stage.params) for stage in load_pipeline("synthetic").stages}
AGGREGATE = AggregateParams.from_dict(PIPELINE_PARAMS["aggregate_lidar"])
DEFAULT_VOXEL_M = AGGREGATE.voxel_m
NEAR_M = 20.0
#: Projection variants on the default map: the default, and ablations that show what each part of
#: it (visibility test, plane fits, depth-edge confidence) contributes.
ZBUFFER = {"visibility": "none", "estimator": "nearest_centre", "edge_band_px": 0}
AGG_DEFAULT = "aggregated (default)"
SINGLE_DEFAULT = "single sweep (default)"
ABLATIONS = {
    "aggregated, z-buffer only": ZBUFFER,
    "aggregated, local_min": {"visibility": "local_min"},
    "aggregated, splat, nearest point, no edge band": {"estimator": "nearest_centre", "edge_band_px": 0},
    "aggregated, splat, plane fits, no edge band": {"edge_band_px": 0},
    AGG_DEFAULT: {},
}


@dataclass
class Sample:
    """One camera image of an evaluation frame: its truth and masks."""

    truth_m: np.ndarray
    valid: np.ndarray  # truth > 0 and not the ego body
    dynamic: np.ndarray  # on a moving object
    rgb: np.ndarray
    focal_px: float


@dataclass
class Variant:
    """A way of producing a depth map, with its outputs per sample and its timings (s/frame)."""

    name: str
    kind: str  # "sparse" or "dense"
    maps: list[np.ndarray] = field(default_factory=list)
    seconds_per_frame: list[float] = field(default_factory=list)
    seen_through: int = 0
    projected: int = 0
    agg_seconds_per_frame: float = 0.0


def geometry_cached_scene(synthetic: SyntheticScene) -> tuple[Scene, float]:
    """The scene with its geometry frames rendered once (so aggregation is timed alone), and the
    time that rendering took."""
    t0 = time.perf_counter()
    cache = [synthetic.render_geometry(i) for i in range(synthetic.config.frames)]
    seconds = time.perf_counter() - t0
    scene = synthetic.scene()
    scene.frames = LazyFrames(len(cache), synthetic.render_frame, cache.__getitem__)
    return scene, seconds


def moving_instances(synthetic: SyntheticScene) -> np.ndarray:
    return np.array([a.instance_id for a in synthetic.world.agents if not a.is_static], np.int64)


def samples_of(frame: Frame, moving: np.ndarray) -> list[Sample]:
    out = []
    for cam in frame.cameras:
        t = cam.truth
        out.append(
            Sample(
                truth_m=t.depth_m,
                valid=(t.depth_m > 0) & (t.semantic != 255),
                dynamic=np.isin(t.instance, moving),
                rgb=cam.decode_image(),
                focal_px=float(cam.calibration.intrinsics[0, 0]),
            )
        )
    return out


def project_variant(
    variant: Variant, scene: Scene, frames: list[Frame], params: ProjectParams, samples: list[Sample]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Projects every evaluation frame; returns each camera's (sparse, confidence). The variant
    keeps the trusted depths (confidence >= ``TRUSTED_DEPTH_CONFIDENCE``)."""
    projector = _Projector(scene, params)
    projector(frames[0])  # warm the per-camera caches (rays, ego body)
    out = []
    for frame in frames:
        t0 = time.perf_counter()
        projector(frame)
        variant.seconds_per_frame.append(time.perf_counter() - t0)
        for cam in frame.cameras:
            out.append((cam.depth.sparse_m.copy(), cam.depth.sparse_confidence.copy()))
    for (sparse, conf), s in zip(out, samples, strict=True):
        # Scored as users train on it: the depths at or above the trusted confidence.
        trusted = np.where(conf >= TRUSTED_DEPTH_CONFIDENCE, sparse, 0)
        variant.maps.append(trusted)
        behind, projected = see_through_share(np.where(s.valid, trusted, 0), s.truth_m)
        variant.seen_through += behind
        variant.projected += projected
    return out


def densify_variant(
    variant: Variant,
    method: str,
    inputs: list[tuple[np.ndarray, np.ndarray]],
    samples: list[Sample],
    cams: int,
) -> None:
    per_frame = 0.0
    for k, ((sparse, conf), s) in enumerate(zip(inputs, samples, strict=True)):
        rgb = s.rgb if needs_rgb(method) else None
        seeds = np.where(conf >= TRUSTED_DEPTH_CONFIDENCE, conf, 0.0)  # as the densify_depth stage
        t0 = time.perf_counter()
        result = densify(sparse, seeds, rgb, focal_px=s.focal_px, method=method)
        per_frame += time.perf_counter() - t0
        variant.maps.append(result.depth_m)
        if (k + 1) % cams == 0:
            variant.seconds_per_frame.append(per_frame)
            per_frame = 0.0


def flat(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """Per-camera maps (or masks) of all samples as one flat array."""
    return np.concatenate([a.ravel() for a in arrays])


def errors_row(variant: Variant, samples: list[Sample], extra_ms: float = 0.0) -> list[object]:
    pred = flat(variant.maps)
    truth = flat([s.truth_m for s in samples])
    valid = flat([s.valid for s in samples])
    dynamic = flat([s.dynamic for s in samples])
    near = truth < NEAR_M
    e = depth_errors(pred, truth, valid)
    parts = [depth_errors(pred, truth, valid & m) for m in (~dynamic, dynamic, near, ~near)]
    ms = 1e3 * float(np.median(variant.seconds_per_frame)) + extra_ms
    return [
        variant.name,
        f"{ms:.0f}",
        f"{100 * e.coverage:.1f}",
        f"{e.rmse_m:.3f}",
        f"{e.mae_m:.3f}",
        f"{e.abs_rel:.4f}",
        f"{100 * e.delta_1_25:.2f}",
        *(f"{p.mae_m:.3f} ({100 * p.coverage:.0f}%)" for p in parts),
    ]


ERROR_HEADERS = (
    "variant",
    "ms/frame",
    "coverage %",
    "RMSE m",
    "MAE m",
    "AbsRel",
    "δ<1.25 %",
    "static MAE (cov)",
    "dynamic MAE (cov)",
    "near MAE (cov)",
    "far MAE (cov)",
)


def common_mae(a: Variant, b: Variant, samples: list[Sample]) -> tuple[float, float, int]:
    """MAE of two variants on the pixels both cover."""
    pa = flat(a.maps)
    pb = flat(b.maps)
    truth = flat([s.truth_m for s in samples])
    valid = flat([s.valid for s in samples]) & (pa > 0) & (pb > 0)
    return depth_errors(pa, truth, valid).mae_m, depth_errors(pb, truth, valid).mae_m, int(valid.sum())


def run_scenes(args: argparse.Namespace, report: Report) -> dict[str, Variant]:
    variants: dict[str, Variant] = {}

    def get(name: str, kind: str) -> Variant:
        return variants.setdefault(name, Variant(name, kind))

    all_samples: list[Sample] = []
    examples: list[tuple[str, np.ndarray]] = []
    agg_stats: list[list[object]] = []
    render_s = 0.0
    for index in range(args.scenes):
        cfg = SyntheticConfig(
            scenes=args.scenes,
            frames=args.frames,
            seed=args.seed,
            rig=args.rig,
            height=args.height,
            width=args.width,
        )
        synthetic = SyntheticScene(cfg, index)
        scene, seconds = geometry_cached_scene(synthetic)
        render_s += seconds
        eval_idx = np.linspace(2, args.frames - 3, args.eval_frames).round().astype(int)
        frames = [synthetic.render_frame(int(i)) for i in eval_idx]
        samples = [s for f in frames for s in samples_of(f, moving_instances(synthetic))]
        all_samples += samples
        cams = len(frames[0].cameras)
        maps: dict[float, LidarMap] = {}
        for voxel in VOXELS_M:
            gc.collect()
            t0 = time.perf_counter()
            maps[voxel] = aggregate_scene(scene, dataclasses.replace(AGGREGATE, voxel_m=voxel))
            agg_s = time.perf_counter() - t0
            st = maps[voxel].stats
            agg_stats.append(
                [
                    scene.scene_id,
                    voxel,
                    f"{1e3 * agg_s / args.frames:.0f}",
                    st["points"],
                    st["static_points"],
                    st["outliers_removed"],
                    st["moving_tracks"],
                    st["object_models"],
                    st["object_points"],
                ]
            )
            runs = ABLATIONS if voxel == DEFAULT_VOXEL_M else {f"aggregated, voxel {voxel} m": {}}
            for name, overrides in runs.items():
                v = get(name, "sparse")
                v.agg_seconds_per_frame += agg_s / args.frames / args.scenes
                scene.products["lidar_map"] = maps[voxel]
                out = project_variant(v, scene, frames, ProjectParams(**overrides), samples)
                if name == AGG_DEFAULT:
                    default_inputs = out
        scene.products["lidar_map"] = maps[DEFAULT_VOXEL_M]
        single_inputs = None
        for name, overrides in (("single sweep, z-buffer only", ZBUFFER), (SINGLE_DEFAULT, {})):
            params = ProjectParams(use_map=False, **overrides)
            out = project_variant(get(name, "sparse"), scene, frames, params, samples)
            if name == SINGLE_DEFAULT:
                single_inputs = out
        for method in DENSIFIERS:
            densify_variant(get(f"aggregated + {method}", "dense"), method, default_inputs, samples, cams)
        for method in ("ipbasic", DEFAULT_DENSIFIER):
            densify_variant(get(f"single sweep + {method}", "dense"), method, single_inputs, samples, cams)
        if index == 0:
            k = cams * (len(frames) // 2)  # the first camera of the middle frame
            s = samples[k]
            examples = [
                ("image", s.rgb),
                ("truth", s.truth_m),
                ("single sweep", variants[SINGLE_DEFAULT].maps[k]),
                ("aggregated", variants[AGG_DEFAULT].maps[k]),
                ("aggregated + ipbasic", variants["aggregated + ipbasic"].maps[k]),
                (f"aggregated + {DEFAULT_DENSIFIER}", variants[f"aggregated + {DEFAULT_DENSIFIER}"].maps[k]),
            ]
            examples_truth = s
        print(f"scene {scene.scene_id} done", flush=True)
    report.table(
        "LiDAR aggregation",
        [
            "scene",
            "voxel m",
            "ms/frame",
            "raw points",
            "static map points",
            "outliers removed",
            "moving tracks",
            "rigid models",
            "model points",
        ],
        agg_stats,
        "Aggregation time per frame of the scene (the scene's sweeps gathered, moving objects split off, "
        "voxel down-sampling, and outlier removal where the pipeline asks for it: not for synthetic scenes); "
        "rendering the geometry frames took "
        f"{1e3 * render_s / (args.scenes * args.frames):.0f} ms/frame and is not included.",
    )
    sparse_rows = [
        errors_row(v, all_samples, 1e3 * v.agg_seconds_per_frame)
        for v in variants.values()
        if v.kind == "sparse"
    ]
    report.table(
        "Sparse depth: projection",
        ERROR_HEADERS,
        sparse_rows,
        "ms/frame: projecting into the 5 cameras of one frame plus, for aggregated rows, the aggregation "
        "time per frame. Errors over the pixels each variant gives with confidence >= "
        f"{TRUSTED_DEPTH_CONFIDENCE} (what densification seeds from; pixels at depth edges fall below); "
        "coverage is of the truth pixels (surfaces, ego body excluded). Dynamic: pixels on moving "
        f"objects. Default: splat visibility, plane fits over {ProjectParams().fit_window_px * 2 + 1}x"
        f"{ProjectParams().fit_window_px * 2 + 1}-pixel windows, depth-edge band of "
        f"{ProjectParams().edge_band_px} px at low confidence, voxel {DEFAULT_VOXEL_M} m.",
    )
    report.table(
        "See-through points",
        ["variant", "see-through / projected pixels", "share %"],
        [
            [v.name, f"{v.seen_through} / {v.projected}", f"{100 * v.seen_through / max(v.projected, 1):.2f}"]
            for v in variants.values()
            if v.kind == "sparse"
        ],
        "A projected depth is see-through if it lies more than 5 % + 0.1 m behind the visible surface "
        "(a background point seen through a gap in the foreground); over the trusted pixels.",
    )
    dense_rows = [errors_row(v, all_samples) for v in variants.values() if v.kind == "dense"]
    report.table(
        "Dense depth: densifiers",
        ERROR_HEADERS,
        dense_rows,
        "ms/frame: densifying the 5 cameras of one frame (the projection is not included).",
    )
    variants["_examples"] = examples  # type: ignore[assignment]
    variants["_examples_truth"] = examples_truth  # type: ignore[assignment]
    variants["_samples"] = all_samples  # type: ignore[assignment]
    return variants


def _change(before: float, after: float, unit: str) -> str:
    """``before → after unit (signed relative change)``: a cut of 58 % reads -58 %."""
    return f"{before:.3f} → {after:.3f} {unit} ({100 * (after / before - 1):+.0f} %)"


def goals(report: Report, variants: dict[str, Variant]) -> None:
    samples = variants["_samples"]
    agg = variants[AGG_DEFAULT]
    single = variants[SINGLE_DEFAULT]
    agg_dense = variants[f"aggregated + {DEFAULT_DENSIFIER}"]
    single_dense = variants[f"single sweep + {DEFAULT_DENSIFIER}"]
    ip = variants["aggregated + ipbasic"]

    def err(v: Variant) -> object:
        pred = flat(v.maps)
        truth = flat([s.truth_m for s in samples])
        valid = flat([s.valid for s in samples])
        return depth_errors(pred, truth, valid)

    a_common, s_common, n_common = common_mae(agg, single, samples)
    ad_common, sd_common, nd_common = common_mae(agg_dense, single_dense, samples)
    e_ip, e_def = err(ip), err(agg_dense)
    t_ip = float(np.median(ip.seconds_per_frame))
    t_def = float(np.median(agg_dense.seconds_per_frame))
    see = agg.seen_through / max(agg.projected, 1)
    rows = [
        [
            "aggregation cuts MAE vs single sweep by >= 30 % (sparse, each on its own trusted pixels)",
            _change(err(single).mae_m, err(agg).mae_m, "m"),
        ],
        [
            f"  same, sparse, on the {n_common} pixels both cover",
            _change(s_common, a_common, "m"),
        ],
        [
            f"  same, dense ({DEFAULT_DENSIFIER}), on the {nd_common} pixels both cover",
            _change(sd_common, ad_common, "m"),
        ],
        [
            f"  same, dense ({DEFAULT_DENSIFIER}), coverage",
            f"{100 * err(single_dense).coverage:.1f} → {100 * err(agg_dense).coverage:.1f} %",
        ],
        [
            f"default densifier ({DEFAULT_DENSIFIER}) RMSE >= 10 % below ipbasic",
            _change(e_ip.rmse_m, e_def.rmse_m, "m"),
        ],
        ["  at <= 2x ipbasic's time", f"{1e3 * t_ip:.1f} → {1e3 * t_def:.1f} ms/frame ({t_def / t_ip:.2f}x)"],
        ["see-through after the visibility test < 1 %", f"{100 * see:.2f} %"],
    ]
    report.table("Goals", ["goal", "measured"], rows)


def full_scene(report: Report, args: argparse.Namespace) -> None:
    """The whole depth stage over one long scene, as the pipeline runs it."""
    cfg = SyntheticConfig(
        scenes=1,
        frames=args.full_frames,
        seed=args.seed + 100,
        rig=args.rig,
        height=args.height,
        width=args.width,
    )
    synthetic = SyntheticScene(cfg, 0)
    render = {"s": 0.0}

    def timed_geometry(i: int) -> Frame:
        t0 = time.perf_counter()
        frame = synthetic.render_geometry(i)
        render["s"] += time.perf_counter() - t0
        return frame

    scene = synthetic.scene()
    scene.frames = LazyFrames(cfg.frames, synthetic.render_frame, timed_geometry)
    t0 = time.perf_counter()
    scene = get_stage("aggregate_lidar")(scene, PIPELINE_PARAMS["aggregate_lidar"])
    agg_s = time.perf_counter() - t0 - render["s"]
    # Real-data pipelines also remove outliers (Open3D); timed once more for reference, on the same
    # geometry frames (rendered again, not counted).
    with_outliers = dataclasses.replace(AGGREGATE, outlier_neighbors=AggregateParams().outlier_neighbors)
    render["s"] = 0.0
    t0 = time.perf_counter()
    aggregate_scene(scene, with_outliers)
    agg_outliers_s = time.perf_counter() - t0 - render["s"]
    projector = _Projector(scene, ProjectParams.from_dict(PIPELINE_PARAMS["project_depth"]))
    densifier = get_stage("densify_depth")
    project_s, densify_s = [], []
    step = max(1, cfg.frames // args.full_eval)
    # Rendered before any timing (the renderer's threads would otherwise still compete).
    frames = [synthetic.render_frame(i) for i in range(0, cfg.frames, step)]
    t0 = time.perf_counter()
    for camera in frames[0].cameras:  # per-camera ray tables and ego body: once per scene
        projector.rays_and_ego_depth(camera)
    setup_s = time.perf_counter() - t0
    for frame in frames:
        t0 = time.perf_counter()
        projector(frame)
        t1 = time.perf_counter()
        densifier(
            Scene(scene.scene_id, "synthetic", scene.calibrations, [frame]), PIPELINE_PARAMS["densify_depth"]
        )
        t2 = time.perf_counter()
        project_s.append(t1 - t0)
        densify_s.append(t2 - t1)
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    lidar_map = scene.products["lidar_map"]
    per_frame = (agg_s + setup_s) / cfg.frames + np.median(project_s) + np.median(densify_s)
    report.table(
        f"Whole depth stage on one scene of {cfg.frames} frames x {len(synthetic.calibrations)} cameras",
        ["part", "value"],
        [
            ["aggregation (whole scene)", f"{agg_s:.1f} s = {1e3 * agg_s / cfg.frames:.0f} ms/frame"],
            [
                "  with Open3D outlier removal (real-data pipelines; not in the total)",
                f"{agg_outliers_s:.1f} s = {1e3 * agg_outliers_s / cfg.frames:.0f} ms/frame",
            ],
            ["projection: per-camera ray tables (once per scene)", f"{setup_s:.2f} s"],
            ["projection, median per frame", f"{1e3 * np.median(project_s):.0f} ms"],
            ["densification, median per frame", f"{1e3 * np.median(densify_s):.0f} ms"],
            ["total per frame (goal < 2 s)", f"{per_frame:.2f} s"],
            [
                "static map",
                f"{len(lidar_map.points_world)} points ({lidar_map.points_world.nbytes / 2**20:.0f} MiB)",
            ],
            ["peak RSS of the process (renderer included)", f"{peak_gib:.2f} GiB"],
            ["rendering the geometry frames (not counted)", f"{1e3 * render['s'] / cfg.frames:.0f} ms/frame"],
        ],
        f"Projection and densification timed on {len(project_s)} frames spread over the scene.",
    )


def figure(variants: dict[str, Variant], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = variants["_samples"]
    examples = variants["_examples"]
    truth = flat([s.truth_m for s in samples])
    valid = flat([s.valid for s in samples])
    fig = plt.figure(figsize=(15, 8.5))
    grid = fig.add_gridspec(3, 4)
    ax = fig.add_subplot(grid[:, :2])
    points = []
    for v in variants.values():
        if not isinstance(v, Variant):
            continue
        e = depth_errors(flat(v.maps), truth, valid)
        ms = 1e3 * (float(np.median(v.seconds_per_frame)) + v.agg_seconds_per_frame)
        points.append((ms, e.mae_m, e.coverage, v.name, v.kind))
    for ms, mae, cov, name, kind in points:
        ax.scatter(ms, mae, s=30 + 200 * cov, marker="o" if kind == "dense" else "s", alpha=0.7)
        ax.annotate(
            f"{name} ({100 * cov:.0f}%)", (ms, mae), fontsize=7, xytext=(4, 2), textcoords="offset points"
        )
    front = sorted(points)
    best = np.inf
    pareto = []
    for p in front:
        if p[1] < best:
            pareto.append(p)
            best = p[1]
    ax.plot([p[0] for p in pareto], [p[1] for p in pareto], "k--", lw=1, label="Pareto front (time, MAE)")
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (5 cameras; aggregated rows include aggregation per frame)")
    ax.set_ylabel("MAE over covered truth pixels (m)")
    ax.set_title("Error against time (marker area ~ coverage; squares sparse, circles dense)")
    ax.legend(loc="upper right", fontsize=8)
    vmax = float(np.percentile(examples[1][1][examples[1][1] > 0], 98))
    for k, (title, img) in enumerate(examples):
        a = fig.add_subplot(grid[k // 2, 2 + k % 2])
        if img.ndim == 3:
            a.imshow(img)
        else:
            a.imshow(np.ma.masked_equal(img, 0), cmap="turbo", vmin=0, vmax=vmax, interpolation="nearest")
        a.set_title(title, fontsize=9)
        a.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    print(f"wrote {path}")


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--eval-frames", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rig", default="waymo5")
    parser.add_argument("--height", type=int, default=160)
    parser.add_argument("--width", type=int, default=240)
    parser.add_argument("--full-frames", type=int, default=200, help="0 skips the whole-scene run")
    parser.add_argument("--full-eval", type=int, default=10, help="frames of the whole scene timed")
    parser.add_argument(
        "--quick", action="store_true", help="1 scene of 16 frames, 3 evaluated, no whole scene"
    )
    parser.add_argument(
        "--stage-only",
        action="store_true",
        help="only the whole-stage timing (its own section, so it can be re-timed on a quiet machine)",
    )
    add_update_flag(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.frames, args.eval_frames, args.full_frames = 1, 16, 3, 0
    if not args.stage_only:
        report = Report(
            "depth",
            "Dense depth ground truth (benchmarks/depth.py)",
            f"Synthetic scenes ({args.rig}, {args.height} x {args.width} images, 64 x 1024 LiDAR), "
            f"{args.scenes} scene(s) of {args.frames} frames, {args.eval_frames} frames each scored "
            "against the exact z-depth. Figure: `docs/images/depth_benchmark.png`.",
        )
        variants = run_scenes(args, report)
        goals(report, variants)
        figure(variants, output_path(FIGURE, args.update))
        report.write(update=args.update)
    if args.full_frames:
        stage = Report(
            "depth-stage",
            "Dense depth ground truth: the whole stage on a long scene (benchmarks/depth.py)",
            f"One synthetic scene ({args.rig}, {args.height} x {args.width} images) of {args.full_frames} "
            "frames through aggregate_lidar, project_depth and densify_depth with the synthetic "
            "pipeline's parameters, as `phigenesis-prep synthetic` runs them.",
        )
        full_scene(stage, args)
        stage.write(update=args.update)


if __name__ == "__main__":
    main()
