"""Scene-flow benchmark: the ``scene_flow`` stage's per-pixel flow against the synthetic truth flow,
and its cost per frame at Waymo's image size.

Usage (from the repository root)::

    .venv/bin/python benchmarks/scene_flow.py [--scenes 2] [--frames 8] [--cost-frames 3] [--seed 0]
        [--update]   # replace the section of BENCHMARKS.md (else benchmarks/out/scene_flow.md)

Accuracy: synthetic scenes (the bundled ``synthetic`` pipeline's source parameters: five cameras
of 240 x 160, a 64-beam LiDAR) run through the bundled pipeline's stages up to ``scene_flow``, so
the flow is made from the dense depth the pipeline builds from LiDAR (``complete_depth``'s). Each
image's flow is scored against its exact truth flow (``CameraTruth.flow_world_mps``, world frame,
m/s) with STORM's definitions (:mod:`phigenesis.eval.scene_flow`): EPE3D, Acc5, Acc10, outliers,
angle; pixels scored as STORM scores them (truth depth > 0, not ground). The same frames are also
run with the truth depth in place of the pipeline's, which separates the rigid-box model's error
from the depth's. Breakdowns: by the truth speed of the pixel's surface and, on moving pixels, by
its truth class; the dynamic mask's precision and recall against the truth's moving pixels. The
LiDAR points' flow is scored against the exact velocity of each point's surface at its own
measurement time (from the agents' trajectories), by speed and class.

Cost: frames of the ``waymo`` preset (five cameras 1920 x 1280 / 1920 x 886, five LiDARs with two
returns; images cast at 1/8 and resized, which leaves the maps' size unchanged) given their truth
depth as dense depth; CPU seconds per frame of the stage (all cameras and the sweep's points) and
of encoding its three maps per camera for the cache. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag

from phigenesis import taxonomy as tx
from phigenesis.data import codec
from phigenesis.data.pipeline import load_pipeline
from phigenesis.data.records import CameraDepth, Frame
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene, synthetic_scene
from phigenesis.data.stages import run_stage
from phigenesis.data.stages.flow import TRACKS_PRODUCT, SceneFlowParams, flow_frame
from phigenesis.eval.scene_flow import FlowAccumulator, flow_pixels, numpy_flow_errors

#: Truth speed bins of the scored pixels, m/s (upper bounds; the last is open).
SPEED_BINS = ((0.0, 0.5, "static (<= 0.5)"), (0.5, 2.0, "0.5-2"), (2.0, 5.0, "2-5"), (5.0, 10.0, "5-10"))
FAST = (10.0, np.inf, "> 10")
MOVING_MPS = SceneFlowParams().moving_mps
HEADERS = ["pixels", "EPE3D m/s", "Acc5 %", "Acc10 %", "outlier %", "angle deg"]


@dataclasses.dataclass
class Pool:
    """Per-pixel predictions and truths of one depth variant, pooled over every scored pixel."""

    pred: list[np.ndarray] = dataclasses.field(default_factory=list)
    truth: list[np.ndarray] = dataclasses.field(default_factory=list)
    semantic: list[np.ndarray] = dataclasses.field(default_factory=list)
    dynamic: list[np.ndarray] = dataclasses.field(default_factory=list)
    confidence: list[np.ndarray] = dataclasses.field(default_factory=list)
    storm: FlowAccumulator = dataclasses.field(default_factory=FlowAccumulator)

    def add(
        self,
        pred: np.ndarray,
        truth: np.ndarray,
        depth: np.ndarray,
        sem: np.ndarray,
        dyn: np.ndarray,
        conf: np.ndarray,
    ) -> None:
        valid = flow_pixels(torch.from_numpy(depth), torch.from_numpy(sem)).numpy()
        self.storm.add(torch.from_numpy(pred), torch.from_numpy(truth), torch.from_numpy(valid))
        self.pred.append(pred[valid])
        self.truth.append(truth[valid])
        self.semantic.append(sem[valid])
        self.dynamic.append(dyn[valid])
        self.confidence.append(conf[valid])

    def arrays(self, known_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pred, truth, class, dynamic) of the scored pixels; ``known_only``: only those where the
        stage had a depth (confidence > 0: the pixels Stage 1 trains on)."""
        parts = [np.concatenate(x) for x in (self.pred, self.truth, self.semantic, self.dynamic)]
        if known_only:
            keep = np.concatenate(self.confidence) > 0
            parts = [x[keep] for x in parts]
        return tuple(parts)  # type: ignore[return-value]


def _row(label: Sequence[str], pred: np.ndarray, truth: np.ndarray) -> list[object]:
    if len(pred) == 0:
        return [*label, 0, "—", "—", "—", "—", "—"]
    m = numpy_flow_errors(pred.astype(np.float64), truth.astype(np.float64))
    angle = "—" if np.isnan(m["angle_rad"]) else f"{np.degrees(m['angle_rad']):.2f}"
    return [
        *label,
        f"{len(pred):,}",
        f"{m['epe3d_mps']:.3f}",
        f"{100 * m['acc5']:.1f}",
        f"{100 * m['acc10']:.1f}",
        f"{100 * m['outlier']:.1f}",
        angle,
    ]


def _truth_depth(frame: Frame) -> Frame:
    """``frame`` with every camera's dense depth replaced by its truth depth."""
    cams = []
    for cam in frame.cameras:
        d = cam.truth.depth_m
        known = (d > 0).astype(np.float32)
        cams.append(
            dataclasses.replace(cam, depth=CameraDepth(d, known, np.zeros(d.shape, np.uint8), d, known))
        )
    return dataclasses.replace(frame, cameras=cams)


@dataclasses.dataclass
class PointPool:
    """Per-point predicted and truth flows (m/s, world) of the LiDAR points, with their classes."""

    pred: list[np.ndarray] = dataclasses.field(default_factory=list)
    truth: list[np.ndarray] = dataclasses.field(default_factory=list)
    classes: list[np.ndarray] = dataclasses.field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(np.concatenate(x) for x in (self.pred, self.truth, self.classes))  # type: ignore[return-value]


def point_truth(frame: Frame, source: SyntheticScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keep (N,) bool, truth flow (K, 3) m/s world, class (K,)) of the frame's sweep: the exact
    velocity of each point's surface at its own measurement time (agents: v + omega x (p - c) of
    their trajectory; static world: 0); points on something that is no agent (the ego body) are
    left out."""
    sweep = frame.lidar
    p = sweep.points_world()
    t_s = np.array([source.seconds(sweep.timestamp_micros)]) + sweep.time_offset_micros * 1e-6
    truth = np.zeros((len(p), 3))
    classes = np.full(len(p), tx.IGNORE_ID, np.uint8)
    keep = sweep.instance == 0
    for agent in source.world.agents:
        mine = sweep.instance == agent.instance_id
        if not mine.any():
            continue
        keep |= mine
        classes[mine] = agent.class_id
        if agent.is_static:
            continue
        pos, _, vel, rate = agent.trajectory.state(t_s[mine])
        r = p[mine] - pos
        truth[mine] = vel + np.stack([-rate * r[:, 1], rate * r[:, 0], np.zeros(len(r))], axis=1)
    return keep, truth[keep], classes[keep]


def accuracy(scenes: int, frames: int, seed: int) -> tuple[dict[str, Pool], PointPool]:
    """The pipeline-depth and truth-depth pools over ``scenes`` x ``frames`` synthetic frames, and
    the LiDAR points' pool."""
    spec = load_pipeline("synthetic")
    params = dict(spec.source_params)
    config = SyntheticConfig.from_dict({**params, "scenes": scenes, "frames": frames, "seed": seed})
    pools = {"pipeline depth": Pool(), "truth depth": Pool()}
    points = PointPool()
    flow_params = SceneFlowParams()
    for index in range(scenes):
        scene = synthetic_scene(config, index)
        source = SyntheticScene(config, index)
        for st in spec.stages:
            scene = run_stage(st.name, scene, st.params)
            if st.name == "scene_flow":
                break
        table = scene.products[TRACKS_PRODUCT]
        keyframes = np.zeros(0, np.int64)
        for frame in scene.frames:
            exact = flow_frame(_truth_depth(frame), table, keyframes, flow_params)
            for variant, f in (("pipeline depth", frame), ("truth depth", exact)):
                for cam in f.cameras:
                    t = cam.truth
                    fl = cam.flow
                    pools[variant].add(
                        fl.flow_world_mps, t.flow_world_mps, t.depth_m, t.semantic, fl.dynamic, fl.confidence
                    )
            keep, truth, classes = point_truth(frame, source)
            points.pred.append(frame.lidar.flow_world_mps[keep])
            points.truth.append(truth)
            points.classes.append(classes)
            print(f"scene {index} frame {frame.frame_index}", flush=True)
    return pools, points


def cost(frames: int, seed: int, index: int) -> dict[str, float]:
    """CPU seconds per frame of the stage and of encoding its maps, at the waymo preset's size, on
    scene ``index`` of ``seed``."""
    config = SyntheticConfig.from_preset("waymo", scenes=index + 1, frames=frames, seed=seed, render_scale=8)
    scene = synthetic_scene(config, index)
    scene = run_stage("box_tracks", scene, {})
    table = scene.products[TRACKS_PRODUCT]
    params = SceneFlowParams()
    stage_s, encode_s, points, pixels, dynamic, moving_boxes = 0.0, 0.0, 0, 0, 0, 0
    for i in range(len(scene.frames)):  # every frame's boxes, as the aggregation's pass records them
        table.at(i)
    flow_frame(_truth_depth(scene.frames[0]), table, np.zeros(0, np.int64), params)  # per-calibration tables
    for frame in scene.frames:
        frame = _truth_depth(frame)
        t0 = time.process_time()
        out = flow_frame(frame, table, np.zeros(0, np.int64), params)
        stage_s += time.process_time() - t0
        t0 = time.process_time()
        for cam in out.cameras:
            codec.encode_flow(cam.flow.flow_world_mps)
            codec.encode_semantic(cam.flow.dynamic.astype(np.uint8))
            codec.encode_confidence(cam.flow.confidence)
        encode_s += time.process_time() - t0
        points += len(out.lidar)
        pixels += sum(c.flow.dynamic.size for c in out.cameras)
        dynamic += sum(int(c.flow.dynamic.sum()) for c in out.cameras)
        moving_boxes += int(
            (np.linalg.norm(frame.boxes.velocity_world[:, :2], axis=1) > params.moving_mps).sum()
        )
    n = len(scene.frames)
    return {
        "stage_s": stage_s / n,
        "encode_s": encode_s / n,
        "points": points / n,
        "pixels": pixels / n,
        "dynamic_share": dynamic / max(pixels, 1),
        "moving_boxes": moving_boxes / n,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--frames", type=int, default=8, help="frames per scene (accuracy)")
    parser.add_argument("--cost-scenes", type=int, default=2, help="scenes of the waymo preset (cost)")
    parser.add_argument("--cost-frames", type=int, default=3, help="frames per cost scene")
    parser.add_argument("--seed", type=int, default=0)
    add_update_flag(parser)
    args = parser.parse_args(argv)
    report = Report(
        "scene_flow",
        "Scene flow from boxes against the synthetic truth",
        f"Written by `benchmarks/scene_flow.py`. Accuracy: {args.scenes} synthetic scenes x {args.frames} "
        "frames (seed "
        f"{args.seed}; the bundled synthetic pipeline's cameras and LiDAR) through the bundled pipeline up "
        "to `scene_flow`, every image scored against its exact truth flow (world frame, m/s) on STORM's "
        "pixels (truth depth > 0, not ground). 'pipeline depth': the flow made from the completed dense "
        "depth the pipeline builds from LiDAR; 'truth depth': the same boxes and yaw rates with the "
        "exact depth, so only the rigid-box model's error is left (and the pixels of objects the frame has "
        "no box for: agents beyond the source's box range, and the bottom `clearance_m` of a box, which "
        "keep flow 0). EPE3D, Acc5, Acc10, outliers and "
        "angle as STORM defines them (m/s; Acc thresholds 0.05 and 0.1 m/s or 5 and 10 % of the truth "
        "speed).",
    )
    pools, points = accuracy(args.scenes, args.frames, args.seed)
    rows = []
    for variant, pool in pools.items():
        s = pool.storm.summary()
        rows.append(
            [
                variant,
                f"{int(s['flow_pixels']):,}",
                f"{s['epe3d_mps']:.3f}",
                f"{100 * s['acc5']:.1f}",
                f"{100 * s['acc10']:.1f}",
                f"{100 * s['outlier']:.1f}",
                f"{np.degrees(s['angle_rad']):.2f}",
            ]
        )
    report.table(
        "All scored pixels (STORM's protocol)",
        ["depth", *HEADERS],
        rows,
        "Pooled over every scored pixel of every image with something moving faster than 1 m/s "
        "(FlowAccumulator); most pixels are static, so EPE3D here is small whatever the moving pixels' "
        "error: the tables below split it.",
    )
    speed_rows, class_rows, mask_rows, moving_rows = [], [], [], []
    variants = [
        ("pipeline depth", pools["pipeline depth"], False),
        ("pipeline depth, where known", pools["pipeline depth"], True),
        ("truth depth", pools["truth depth"], False),
    ]
    for variant, pool, known_only in variants:
        pred, truth, sem, dyn = pool.arrays(known_only)
        speed = np.linalg.norm(truth, axis=1)
        moving_rows.append(_row([variant], pred[speed > MOVING_MPS], truth[speed > MOVING_MPS]))
        for lo, hi, name in (*SPEED_BINS, FAST):
            sel = (speed > lo) & (speed <= hi) if lo > 0 else speed <= hi
            speed_rows.append(_row([variant, name], pred[sel], truth[sel]))
        moving = speed > MOVING_MPS
        for k in np.unique(sem[moving]).tolist():
            sel = moving & (sem == k)
            if sel.sum() >= 50:
                class_rows.append(_row([variant, tx.class_name(int(k))], pred[sel], truth[sel]))
        both = int((dyn & moving).sum())
        mask_rows.append(
            [
                variant,
                f"{int(moving.sum()):,}",
                f"{int(dyn.sum()):,}",
                f"{100 * both / max(int(dyn.sum()), 1):.1f}",
                f"{100 * both / max(int(moving.sum()), 1):.1f}",
            ]
        )
    report.table(
        f"Moving pixels (truth speed > {MOVING_MPS:g} m/s)",
        ["depth", *HEADERS],
        moving_rows,
        "'where known': only the pixels where the stage had a depth (flow confidence > 0), the pixels "
        "Stage 1 trains on; a moving pixel without a depth has flow 0 and counts its whole speed as error "
        "in the plain 'pipeline depth' row.",
    )
    report.table("By truth speed (m/s)", ["depth", "speed", *HEADERS], speed_rows)
    report.table(
        f"By truth class, moving pixels (truth speed > {MOVING_MPS:g} m/s; classes with >= 50 pixels)",
        ["depth", "class", *HEADERS],
        class_rows,
    )
    report.table(
        "Dynamic mask against the truth's moving pixels",
        ["depth", "truth moving px", "dynamic px", "precision %", "recall %"],
        mask_rows,
        f"Truth moving: truth speed > {MOVING_MPS:g} m/s (the stage's moving threshold), on the scored "
        "pixels.",
    )
    pred, truth, classes = points.arrays()
    speed = np.linalg.norm(truth, axis=1)
    point_rows = [
        _row(["all points (static world and agents)", "all"], pred, truth),
        _row(["static (<= 0.5)", "all"], pred[speed <= MOVING_MPS], truth[speed <= MOVING_MPS]),
        _row([f"moving (> {MOVING_MPS:g})", "all"], pred[speed > MOVING_MPS], truth[speed > MOVING_MPS]),
    ]
    for k in np.unique(classes[speed > MOVING_MPS]).tolist():
        sel = (speed > MOVING_MPS) & (classes == k)
        if sel.sum() >= 20:
            point_rows.append(
                _row([f"moving (> {MOVING_MPS:g})", tx.class_name(int(k))], pred[sel], truth[sel])
            )
    report.table(
        "LiDAR points against the exact flow at each point's time",
        ["points (truth speed, m/s)", "class", "points", *HEADERS[1:]],
        point_rows,
        "Every point of every sweep of the accuracy scenes (the ego body's left out), against the exact "
        "velocity of its surface at its own measurement time from the agents' trajectories; EmerNeRF "
        "scores flow on LiDAR points (there in displacement per 0.1 s, here m/s).",
    )
    cost_rows = []
    for index in range(args.cost_scenes):
        c = cost(args.cost_frames, args.seed, index)
        cost_rows.append(
            [
                index,
                args.cost_frames,
                f"{c['pixels']:,.0f}",
                f"{c['points']:,.0f}",
                f"{c['moving_boxes']:.1f}",
                f"{100 * c['dynamic_share']:.2f}",
                f"{c['stage_s']:.3f}",
                f"{c['encode_s']:.3f}",
            ]
        )
    report.table(
        "Cost per frame at Waymo's size (CPU s)",
        [
            "scene",
            "frames",
            "pixels",
            "LiDAR points",
            "moving boxes",
            "dynamic px %",
            "stage CPU s",
            "encode CPU s",
        ],
        cost_rows,
        "Waymo preset (five cameras, 1920 x 1280 and 1920 x 886; five LiDARs with two returns), truth "
        "depth as the dense depth; per frame: the stage (yaw rates, every camera's maps, every point's "
        "flow) and encoding its three maps per camera for the cache. The per-calibration ray tables are "
        "built and every frame's boxes recorded before timing (the pipeline shares the tables with the "
        "depth stages, and its LiDAR aggregation loads every frame through box_tracks).",
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
