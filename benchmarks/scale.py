"""Prep at the size users have: real-size Waymo segments and nuScenes scenes through the bundled
pipelines, per stage, against the floor, projected to whole datasets.

::

    .venv/bin/python -m benchmarks.scale --work /tmp/scale            # prints the tables
    .venv/bin/python -m benchmarks.scale --work /tmp/scale --update   # and writes BENCHMARKS.md

What it measures, each in a fresh process (one worker, so CPU seconds are one core's):

- **Per stage**: CPU seconds per frame of the read, of each stage and of the write, and each
  stage's per-scene work (setup, the LiDAR aggregation) spread over the frames, from the
  pipeline's own accounting (``PrepSummary.timings``); the process's total CPU seconds and wall
  time per frame and its peak RSS.
- **The floor**: the same segment with no stage: read and check the frame, decode every image once
  (what any stage that looks at pixels pays), encode and write its row.
- **Projected cost** of Waymo (~230k frames) and nuScenes trainval at 12 Hz (~204k frames):
  core-hours, hours on one 64-core machine and on 2,000 cores.
- **Error** against the synthetic truth on real-size frames (the synthetic source with the same
  rig, LiDARs and stages), so speed never buys error silently; ``--baseline DIR`` runs the same
  measurement with an older checkout's package for the "before" column.

Datasets are written once under ``--work`` and reused (full-size rendering is slow). Long
segments are rendered with ``--render-scale`` (images ray cast at a fraction of the size and
resized: the pixels' content matters little to the cost; the LiDAR is always full density).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag

#: Frames of whole datasets at their native camera rate (WOD paper, arXiv:1912.04838: 1150 segments
#: of 20 s at 10 Hz; nuScenes paper, arXiv:1903.11027, and its devkit: 850 trainval scenes of 20 s):
#: Waymo Perception 1150 segments x ~198.5 frames; nuScenes trainval 850 scenes x ~240 frames.
WAYMO_FRAMES = 228_300
NUSCENES_TRAINVAL_FRAMES = 204_000
#: The issue's goals.
GOAL_WAYMO_CPU_S = 3.0
GOAL_NUSCENES_CPU_S = 2.0
GOAL_FLOOR_RATIO = 3.0
GOAL_RSS_GIB = 4.0
GOAL_LONG_RATIO = 1.25
GOAL_REAL_FRAME_CPU_S = 3.0
#: The real Waymo frame without LiDAR (non-commercial licence, never in the repository).
REAL_FRAME_NAME = "one_frame_five_cameras_panoptic.tfrecord"
#: Maps the floor run leaves out (they are what the stages make).
STAGE_OUTPUTS = ("depth", "pseudo_semantics", "range_view", "lidar_range_image")


# --------------------------------------------------------------------------------------------
# Child processes: one measurement each


def _decode_images_stage() -> None:
    """Registers ``decode_images``: every image decoded once at full size (the floor's stand-in
    for the stages' pixel work), in this process only."""
    from phigenesis.data.records import LazyFrames
    from phigenesis.data.stages import STAGES, register_stage

    if "decode_images" in STAGES:
        return

    def decode(frame: Any) -> Any:
        for cam in frame.cameras:
            if cam.image_bytes is not None:
                cam.decode_image()
        return frame

    @register_stage("decode_images")
    def decode_images(scene: Any, params: Any) -> Any:
        if isinstance(scene.frames, LazyFrames):
            scene.frames = scene.frames.map(decode)
        else:
            scene.frames = [decode(f) for f in scene.frames]
        return scene


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Runs one prep (``job``: source, overrides, pipeline name, ``floor``, out) in this process
    and returns its figures."""
    from phigenesis.data.pipeline import PipelineSpec, load_pipeline, prepare

    spec = load_pipeline(job["pipeline"])
    d = spec.to_dict()
    if job.get("floor"):
        _decode_images_stage()
        d["stages"] = [{"name": "decode_images", "params": {}}]
        for key in STAGE_OUTPUTS:
            if key in d["output"]:
                d["output"][key] = False
    if job.get("source_params"):
        d["source"]["params"] = {**d["source"]["params"], **job["source_params"]}
    spec = PipelineSpec.from_dict(d, "scale benchmark")
    start_cpu, start = time.process_time(), time.perf_counter()
    summary = prepare(
        job["out"], job["source"], job.get("overrides") or {}, spec, workers=1, overwrite=True, progress=False
    )
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "frames": summary.frames_written,
        "cpu_s": time.process_time() - start_cpu,
        "wall_s": time.perf_counter() - start,
        "peak_rss_gib": usage.ru_maxrss / 2**20,
        "bytes": summary.bytes_written,
        "timings": getattr(summary, "timings", {}),
    }


def run_child(job: dict[str, Any], pythonpath: str | None = None, reuse: bool = False) -> dict[str, Any]:
    """``job`` in a fresh interpreter (``pythonpath`` first on its path: another checkout); its
    figures are kept in ``job["out"] + ".json"``, which ``reuse`` returns instead of running again
    (a rerun that only failed later in the script)."""
    saved = Path(job["out"] + ".json")
    if reuse and saved.exists():
        return json.loads(saved.read_text())
    result = _run_child(job, pythonpath)
    saved.write_text(json.dumps(result))
    return result


def _run_child(job: dict[str, Any], pythonpath: str | None) -> dict[str, Any]:
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = os.pathsep.join([pythonpath, str(Path(__file__).resolve().parents[1])])
    code = (
        "import json, sys; from benchmarks.scale import child; "
        "print('RESULT ' + json.dumps(child(json.loads(sys.argv[1]))))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, json.dumps(job)],
        env=env,
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise RuntimeError(f"scale child failed ({proc.returncode}):\n{proc.stderr[-4000:]}")


# --------------------------------------------------------------------------------------------
# Datasets


def synth_dataset(
    work: Path, fmt: str, preset: str, frames: int, render_scale: int, keyframes: int = 0
) -> Path:
    """The dataset written by ``phigenesis-synth`` under ``work`` (reused when complete)."""
    name = f"{fmt}-{preset}-f{frames or keyframes}-r{render_scale}"
    out = work / "data" / name
    done = out / ".complete"
    if done.exists():
        return out
    shutil.rmtree(out, ignore_errors=True)
    cmd = [
        sys.executable, "-m", "phigenesis.cli.synth", "--format", fmt, "--preset", preset,
        "--render-scale", str(render_scale), "--out", str(out),
    ]  # fmt: skip
    cmd += ["--keyframes", str(keyframes)] if fmt == "nuscenes" else ["--frames", str(frames)]
    start = time.perf_counter()
    subprocess.run(cmd, check=True)
    print(f"synthesised {name} in {time.perf_counter() - start:.0f} s", flush=True)
    done.write_text("")
    return out


# --------------------------------------------------------------------------------------------
# Error against the synthetic truth


def truth_errors(cache: Path) -> dict[str, float]:
    """Depth and label errors of a cache made by the synthetic source (camera truth stored)."""
    from phigenesis import taxonomy as tx
    from phigenesis.data.schema import row_to_frame
    from phigenesis.data.shards import CacheReader

    reader = CacheReader(cache)
    sparse_rel, dense_rel, dense_sq = [], [], []
    surface = dense_px = pseudo_px = pseudo_ok = labelled_truth = 0
    for i in range(len(reader)):
        frame = row_to_frame(reader.read(i))
        for cam in frame.cameras:
            truth, depth = cam.truth, cam.depth
            if truth is None or depth is None:
                continue
            has = (truth.depth_m > 0) & (truth.semantic != tx.IGNORE_ID)
            surface += int(has.sum())
            s = has & (depth.sparse_m > 0)
            sparse_rel.append(np.abs(depth.sparse_m[s] - truth.depth_m[s]) / truth.depth_m[s])
            if depth.dense_m is not None:
                d = has & (depth.dense_m > 0)
                dense_px += int(d.sum())
                err = depth.dense_m[d] - truth.depth_m[d]
                dense_rel.append(np.abs(err) / truth.depth_m[d])
                dense_sq.append(err.astype(np.float64) ** 2)
            if cam.pseudo is not None:
                t = truth.semantic != tx.IGNORE_ID
                lab = t & (cam.pseudo.semantic != tx.IGNORE_ID)
                labelled_truth += int(t.sum())
                pseudo_px += int(lab.sum())
                pseudo_ok += int((cam.pseudo.semantic[lab] == truth.semantic[lab]).sum())

    def mean(parts: list[np.ndarray]) -> float:
        values = np.concatenate(parts) if parts else np.zeros(0)
        return float(values.mean()) if values.size else float("nan")

    return {
        "sparse_absrel": mean(sparse_rel),
        "dense_coverage": dense_px / max(surface, 1),
        "dense_absrel": mean(dense_rel),
        "dense_rmse_m": float(np.sqrt(mean(dense_sq))),
        "pseudo_coverage": pseudo_px / max(labelled_truth, 1),
        "pseudo_accuracy": pseudo_ok / max(pseudo_px, 1),
    }


# --------------------------------------------------------------------------------------------
# Tables


def stage_rows(result: dict[str, Any]) -> dict[str, float]:
    """CPU-s per frame by part: per-frame parts as measured, per-scene parts spread over frames."""
    out: dict[str, float] = {}
    frames = max(result["frames"], 1)
    for timing in result["timings"].values():
        for name, seconds in timing.get("frame_s", {}).items():
            out[name] = out.get(name, 0.0) + seconds / frames
        for name, seconds in timing.get("scene_s", {}).items():
            key = f"{name} (per scene)"
            out[key] = out.get(key, 0.0) + seconds / frames
    return out


def fmt(x: float, digits: int = 2) -> str:
    return "—" if x != x else f"{x:.{digits}f}"


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", required=True, help="datasets and caches (datasets are reused)")
    parser.add_argument("--waymo-frames", type=int, nargs="+", default=[20, 50, 200])
    parser.add_argument(
        "--nuscenes-keyframes", type=int, default=9, help="2 Hz keyframes (12 Hz frames follow)"
    )
    parser.add_argument("--render-scale", type=int, default=4, help="image render scale of the datasets")
    parser.add_argument("--error-frames", type=int, default=3, help="real-size frames scored against truth")
    parser.add_argument("--baseline", help="an older checkout: its package gives the 'before' error column")
    add_update_flag(parser)
    parser.add_argument("--data-only", action="store_true", help="only write the datasets, then stop")
    parser.add_argument("--reuse", action="store_true", help="reuse the figures of runs already measured")
    parser.add_argument(
        "--real-frame",
        help=f"the real Waymo frame without LiDAR ({REAL_FRAME_NAME}; default: looked for where the tests "
        "look for it, skipped if absent)",
    )
    args = parser.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.data_only:
        for frames in args.waymo_frames:
            synth_dataset(work, "waymo-v1", "waymo", frames, args.render_scale)
        synth_dataset(work, "nuscenes", "nuscenes", 0, args.render_scale, args.nuscenes_keyframes)
        return

    report = Report(
        "scale",
        "Prep at real size (benchmarks/scale.py)",
        "Synthetic datasets at the real rigs' sizes (`phigenesis-synth --preset waymo|nuscenes`: Waymo five "
        "cameras, 3 x 1920 x 1280 and 2 x 1920 x 886, five LiDARs with two returns at 64 x 2650 and 4 x 200 "
        "x 600; nuScenes six 1600 x 900 cameras at 12 Hz and a 32-beam LiDAR at 20 Hz), read by the real "
        "readers (Waymo v1 TFRecord, nuScenes tables) and converted by the bundled pipelines "
        f"(`pipelines/waymo.yaml`, `pipelines/nuscenes.yaml`) with one worker. Images are rendered at 1/"
        f"{args.render_scale} and resized (the LiDAR at full density). CPU seconds are the process's "
        "(all its threads), per frame; each run is a fresh process.",
    )

    runs: list[tuple[str, dict[str, Any], dict[str, Any]]] = []
    for frames in args.waymo_frames:
        data = synth_dataset(work, "waymo-v1", "waymo", frames, args.render_scale)
        job = {"source": "waymo", "overrides": {"input": str(data)}, "pipeline": "waymo"}
        result = run_child({**job, "out": str(work / f"cache-waymo-{frames}")}, reuse=args.reuse)
        floor = run_child(
            {**job, "out": str(work / f"floor-waymo-{frames}"), "floor": True}, reuse=args.reuse
        )
        runs.append((f"Waymo, {frames} frames", result, floor))
        print(f"waymo {frames}: {result['cpu_s'] / result['frames']:.2f} CPU-s/frame", flush=True)
    data = synth_dataset(work, "nuscenes", "nuscenes", 0, args.render_scale, args.nuscenes_keyframes)
    job = {
        "source": "nuscenes",
        "overrides": {"dataroot": str(data), "version": "v1.0-mini"},
        "pipeline": "nuscenes",
    }
    result = run_child({**job, "out": str(work / "cache-nuscenes")}, reuse=args.reuse)
    floor = run_child({**job, "out": str(work / "floor-nuscenes"), "floor": True}, reuse=args.reuse)
    runs.append((f"nuScenes 12 Hz, {result['frames']} frames", result, floor))

    parts: list[str] = []
    per_run = [stage_rows(r) for _, r, _ in runs]
    for rows in per_run:
        parts += [k for k in rows if k not in parts]
    table = [[part, *(fmt(rows.get(part, 0.0)) for rows in per_run)] for part in parts]
    table.append(["**total CPU-s per frame**", *(fmt(r["cpu_s"] / r["frames"]) for _, r, _ in runs)])
    table.append(["wall s per frame", *(fmt(r["wall_s"] / r["frames"]) for _, r, _ in runs)])
    table.append(["floor: CPU-s per frame", *(fmt(f["cpu_s"] / f["frames"]) for _, _, f in runs)])
    table.append(["ratio to the floor", *(fmt(r["cpu_s"] / f["cpu_s"], 1) for _, r, f in runs)])
    table.append(["peak RSS GiB", *(fmt(r["peak_rss_gib"]) for _, r, _ in runs)])
    table.append(["floor peak RSS GiB", *(fmt(f["peak_rss_gib"]) for _, _, f in runs)])
    table.append(["cache MB per frame", *(fmt(r["bytes"] / r["frames"] / 1e6, 1) for _, r, _ in runs)])
    report.table(
        "CPU seconds per frame, by part",
        ["part", *(name for name, _, _ in runs)],
        table,
        "Per-frame parts are timed between the lazy frame layers as each row is written; a part marked "
        "(per scene) runs once per scene (setup, the LiDAR aggregation's pass over every frame) and is "
        "shown spread over the frames. Totals are the process's CPU time over the run (imports and the "
        "manifest included), so they exceed the sum of the parts a little.",
    )

    real = _real_frame_run(work, args)
    if real is not None:
        scene_timings = next(iter(real["timings"].values()), {})
        per_scene = sum(scene_timings.get("scene_s", {}).values())
        report.text(
            f"The real Waymo frame without LiDAR (`{REAL_FRAME_NAME}`, five cameras at 1920 x 1280 / 886, "
            f"the bundled Waymo pipeline): {fmt(real['cpu_s'] / real['frames'])} CPU-s for its one frame, "
            f"of which {fmt(per_scene)} per-scene work (camera tables, range-view layout); peak RSS "
            f"{fmt(real['peak_rss_gib'])} GiB."
        )

    waymo_runs = [r for name, r, _ in runs if name.startswith("Waymo")]
    waymo_short = min(waymo_runs, key=lambda r: r["frames"])
    waymo = max(waymo_runs, key=lambda r: r["frames"])
    waymo_long = waymo if waymo["frames"] > waymo_short["frames"] else None
    nusc = runs[-1][1]
    cost_rows = []
    for name, frames, r in (
        ("Waymo Perception (1150 segments)", WAYMO_FRAMES, waymo),
        ("nuScenes trainval at 12 Hz (850 scenes)", NUSCENES_TRAINVAL_FRAMES, nusc),
    ):
        per_frame = r["cpu_s"] / r["frames"]
        core_hours = per_frame * frames / 3600
        cost_rows.append(
            [
                name,
                f"{frames:,}",
                fmt(per_frame),
                f"{core_hours:,.0f}",
                fmt(core_hours / 64, 1),
                fmt(core_hours / 2000, 2),
            ]
        )
    report.table(
        "What a whole dataset costs",
        [
            "dataset",
            "frames",
            "CPU-s per frame",
            "core-hours",
            "hours, one 64-core machine",
            "hours, 2,000 cores",
        ],
        cost_rows,
        "CPU-s per frame from the longest Waymo segment and the nuScenes scene above; the hours assume "
        "scenes "
        "spread evenly over the cores (one worker per core, each within the peak RSS above), at this "
        "machine's per-core speed.",
    )

    error_job = {"source": "synthetic", "pipeline": "synthetic"}
    errors: dict[str, dict[str, float]] = {}
    if args.baseline:
        job = {**error_job, "source_params": _source_params(args.error_frames, preset=False)}
        run_child({**job, "out": str(work / "truth-before")}, pythonpath=args.baseline, reuse=args.reuse)
        errors["before: TOP only"] = truth_errors(work / "truth-before")
    job = {**error_job, "source_params": _source_params(args.error_frames, preset=False)}
    run_child({**job, "out": str(work / "truth-common")}, reuse=args.reuse)
    errors["now: TOP only"] = truth_errors(work / "truth-common")
    job = {**error_job, "source_params": _source_params(args.error_frames, preset=True)}
    run_child({**job, "out": str(work / "truth-preset")}, reuse=args.reuse)
    errors["now: five LiDARs, two returns"] = truth_errors(work / "truth-preset")
    labels = {
        "sparse_absrel": "sparse depth AbsRel",
        "dense_coverage": "dense depth coverage of surface pixels",
        "dense_absrel": "dense depth AbsRel",
        "dense_rmse_m": "dense depth RMSE m",
        "pseudo_coverage": "pseudo labels: share of labelled-truth pixels",
        "pseudo_accuracy": "pseudo labels: accuracy where given",
    }
    rows = [[label, *(fmt(e[k], 4) for e in errors.values())] for k, label in labels.items()]
    report.table(
        f"Error against the synthetic truth, {args.error_frames} real-size Waymo frames",
        ["figure", *errors],
        rows,
        "The synthetic source at the Waymo preset's image sizes, rendered exactly (no render scale), through "
        "the synthetic pipeline's stages; every camera pixel with a truth surface counts (the ego body "
        "excluded). TOP only: the 64 x 2650 TOP LiDAR with one return, which an older checkout also reads"
        + (f" (before: the package of `{args.baseline}`)" if args.baseline else "")
        + "; five LiDARs: the whole preset.",
    )

    goals = []
    w_per_frame = waymo["cpu_s"] / waymo["frames"]
    w_floor = next(f for name, r, f in runs if r is waymo)
    goals.append(
        [
            "Waymo CPU-s per real-size frame",
            f"<= {GOAL_WAYMO_CPU_S}",
            fmt(w_per_frame),
            w_per_frame <= GOAL_WAYMO_CPU_S,
        ]
    )
    ratio = waymo["cpu_s"] / w_floor["cpu_s"]
    goals.append(
        ["Waymo, ratio to its floor", f"<= {GOAL_FLOOR_RATIO}", fmt(ratio, 1), ratio <= GOAL_FLOOR_RATIO]
    )
    n_per_frame = nusc["cpu_s"] / nusc["frames"]
    goals.append(
        [
            "nuScenes 12 Hz CPU-s per frame",
            f"<= {GOAL_NUSCENES_CPU_S}",
            fmt(n_per_frame),
            n_per_frame <= GOAL_NUSCENES_CPU_S,
        ]
    )
    rss = waymo["peak_rss_gib"]
    goals.append(
        [f"peak RSS, Waymo {waymo['frames']} frames", f"<= {GOAL_RSS_GIB} GiB", fmt(rss), rss <= GOAL_RSS_GIB]
    )
    if waymo_long is not None:
        long_ratio = (waymo_long["cpu_s"] / waymo_long["frames"]) / (
            waymo_short["cpu_s"] / waymo_short["frames"]
        )
        goals.append(
            [
                f"per-frame cost at {waymo_long['frames']} / at {waymo_short['frames']} frames",
                f"<= {GOAL_LONG_RATIO}",
                fmt(long_ratio),
                long_ratio <= GOAL_LONG_RATIO,
            ]
        )
    if real is not None:
        real_s = real["cpu_s"] / real["frames"]
        goals.append(
            [
                "real LiDAR-less Waymo frame, CPU-s",
                f"<= {GOAL_REAL_FRAME_CPU_S}",
                fmt(real_s),
                real_s <= GOAL_REAL_FRAME_CPU_S,
            ]
        )
    report.table(
        "Goals", ["goal", "target", "measured", "met"], [[*g[:3], "yes" if g[3] else "**no**"] for g in goals]
    )
    report.write(update=args.update)


def _real_frame(given: str | None) -> Path | None:
    """The real LiDAR-less Waymo frame: ``given``, else where the tests look for it
    (``$PHIGENESIS_WAYMO_SAMPLES``, ``../shared/data/waymo`` beside the checkout,
    ``/work/shared/data/waymo``); None when absent."""
    if given:
        return Path(given)
    root = Path(__file__).resolve().parents[1]
    places = [
        os.environ.get("PHIGENESIS_WAYMO_SAMPLES"),
        root.parent / "shared/data/waymo",
        "/work/shared/data/waymo",
    ]
    for place in places:
        if place and (Path(place) / REAL_FRAME_NAME).is_file():
            return Path(place) / REAL_FRAME_NAME
    return None


def _real_frame_run(work: Path, args: argparse.Namespace) -> dict[str, Any] | None:
    """Prep of the real LiDAR-less frame with the bundled Waymo pipeline in a fresh process (None,
    with a line saying so, when the file is absent)."""
    path = _real_frame(args.real_frame)
    if path is None:
        print(f"real frame: {REAL_FRAME_NAME} not found; its row is left out", flush=True)
        return None
    job = {"source": "waymo", "overrides": {"input": str(path)}, "pipeline": "waymo"}
    return run_child({**job, "out": str(work / "cache-real-frame")}, reuse=args.reuse)


#: The synthetic source at real size that an older checkout also reads: the Waymo preset's cameras
#: and TOP LiDAR (64 x 2650) with one return, no short-range LiDARs (older checkouts have none).
COMMON_SOURCE = {
    "rig": "waymo5",
    "height": 1280,
    "width": 1920,
    "uniform_image_size": False,
    "lidar": {
        "beams": 64,
        "columns": 2650,
        "inclination_top_deg": 2.4,
        "inclination_bottom_deg": -17.6,
        "max_range_m": 75.0,
    },
}


def _source_params(frames: int, preset: bool) -> dict[str, Any]:
    """Synthetic source values: the whole Waymo preset (five LiDARs, two returns) or
    :data:`COMMON_SOURCE`, one scene of ``frames`` frames."""
    if not preset:
        return {**COMMON_SOURCE, "scenes": 1, "frames": frames}
    from phigenesis.data.sources.synthetic import SyntheticConfig

    values = SyntheticConfig.from_preset("waymo", scenes=1, frames=frames).to_dict()
    return json.loads(json.dumps(values))  # tuples as lists, as a spec file holds them


if __name__ == "__main__":
    main()
