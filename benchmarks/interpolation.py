"""12 Hz box interpolation benchmark: boxes at every camera sweep from 2 Hz keyframes, against exact truth.

Usage (from the repository root)::

    .venv/bin/python benchmarks/interpolation.py [--scenes 4] [--seconds 20] [--tracks 8] [--seed 0]

Each scene holds ``--tracks`` analytic tracks (:mod:`phigenesis.data.sources.synthetic.motion`, so
the truth is exact at any time) of each type: straight (constant speed), turning (20-30 deg/s yaw
rate), stop-and-go (+-3 m/s^2 between rest and 8-12 m/s), pedestrians (0.6-1.6 m/s on wandering
arcs), parked (stationary) and entering/leaving (cars that exist only for a 3-10 s window not
aligned with the keyframes). Keyframes come every 0.5 s (+-3 ms jitter) and annotate every track
alive then. The six cameras of the ``nuscenes6`` rig run at 12 Hz with nuScenes' timing: each
fires as the LiDAR revolution passes it, 7-49 ms after the revolution starts, so a keyframe's own
images (which carry ``KeyframeBoxes.camera_timestamps_micros``) are 1-43 ms before the keyframe
(the LiDAR timestamp ends the revolution); 2 ms jitter on the other sweeps (0.5 ms on the
keyframe images) and 1 % of the non-keyframe sweeps dropped. Every sweep from 50 ms before the
first keyframe to 50 ms after the last is scored against the truth at its own timestamp.

Methods: ``asap`` (ASAP's ``interp``, what MagicDrive uses: each camera's own keyframe image gets
the annotations, the next five sweeps the uniform k/6 subdivision times, objects in both keyframes
only), ``linear`` (linear centre + slerp at the real timestamp, with the same track-end and
stationary handling as the others), ``hermite`` (cubic Hermite through the annotations) and
``ctra`` (the default: motion models fitted over windows of annotations). Runs once with exact
annotations and once with annotation noise (centre 5 cm, height 2 cm, yaw 1 deg; 5 deg for
pedestrians). Metrics per track type: centre error mean and p95 (m), yaw error mean and p95 (deg),
recall (share of the truth boxes that get a box) and spurious boxes (boxes where the object does
not exist); then boxes per second of each method and the drift of parked objects.

``--update`` writes the ``interpolation`` section of BENCHMARKS.md. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np
from _report import Report, add_update_flag

from phigenesis import geometry
from phigenesis.data import taxonomy as tx
from phigenesis.data.records import Boxes, KeyframeBoxes
from phigenesis.data.sources.synthetic.motion import Path, Segment, SpeedProfile, Trajectory
from phigenesis.data.sources.synthetic.nuscenes_export import LIDAR_MICROS, camera_trigger_micros
from phigenesis.data.sources.synthetic.rigs import NUSCENES6
from phigenesis.data.stages.interpolate import InterpolateParams, asap_boxes, interpolate_boxes_at

TYPES = ("straight", "turning", "stop-and-go", "pedestrian", "parked", "enter/leave")
METHODS = ("asap", "linear", "hermite", "ctra")
#: Each camera's trigger after the start of the LiDAR revolution that ends at a keyframe,
#: microseconds (the synthetic export's nuScenes timing: 7, 15, 22, 30, 40, 49 ms).
CAMERA_OFFSETS_MICROS = {spec.name: camera_trigger_micros(spec.yaw_deg) for spec in NUSCENES6}
SWEEP_MICROS = 1e6 / 12
KEYFRAME_MICROS = 500_000
SWEEPS_PER_KEYFRAME = 6


@dataclass
class Track:
    """One analytic object: its motion, class, size and the time window (s) it exists in."""

    name: str
    kind: str
    trajectory: Trajectory
    class_id: int
    size_lwh: tuple[float, float, float]
    alive_s: tuple[float, float] = (-np.inf, np.inf)


@dataclass
class Tally:
    """Errors and counts of one method on one track type."""

    centre_m: list[float] = field(default_factory=list)
    yaw_deg: list[float] = field(default_factory=list)
    truth: int = 0
    spurious: int = 0


def _path(rng: np.random.Generator, pieces: list[tuple[float, float]]) -> Path:
    start = rng.uniform(-40, 40, 2)
    return Path(start, rng.uniform(-np.pi, np.pi), [Segment(length, kappa) for length, kappa in pieces])


def make_track(kind: str, index: int, seconds: float, rng: np.random.Generator) -> Track:
    """A random track of type ``kind`` lasting at least ``seconds``."""
    name = f"{kind}-{index}"
    car = (tx.CAR, (4.5, 1.9, 1.6))
    if kind == "straight" or kind == "enter/leave":
        speed = rng.uniform(6, 14)
        pieces = [(speed * (seconds + 2), 0.0)]
        if kind == "enter/leave" and rng.random() < 0.5:  # half of them turn while they are seen
            rate = np.radians(rng.uniform(20, 30)) * rng.choice([-1, 1])
            pieces = [(speed * 2, 0.0), (speed * 3, rate / speed), (speed * (seconds + 2), 0.0)]
        trajectory = Trajectory(_path(rng, pieces), SpeedProfile(0.0, 0.0, speed, []), 0.8)
        track = Track(name, kind, trajectory, *car)
        if kind == "enter/leave":
            t_in = rng.uniform(0.3, seconds / 3)
            track.alive_s = (t_in, min(seconds - 0.3, t_in + rng.uniform(3, 10)))
        return track
    if kind == "turning":
        speed = rng.uniform(6, 10)
        pieces = []
        while sum(length for length, _ in pieces) < speed * (seconds + 2):
            rate = np.radians(rng.uniform(20, 30)) * rng.choice([-1, 1])
            pieces += [(speed * rng.uniform(2, 4), rate / speed), (speed * rng.uniform(0.3, 1), 0.0)]
        return Track(name, kind, Trajectory(_path(rng, pieces), SpeedProfile(0.0, 0.0, speed, []), 0.8), *car)
    if kind == "stop-and-go":
        plan: list[tuple[str, float, float]] = []
        while len(plan) < 4 * seconds:
            top = rng.uniform(8, 12)
            plan += [("ramp", top, 3.0), ("hold", rng.uniform(0.5, 2), 0), ("ramp", 0.0, 3.0)]
            plan += [("hold", rng.uniform(0.5, 2), 0)]
        speed = SpeedProfile.build(0.0, 0.0, 0.0, plan)
        return Track(name, kind, Trajectory(_path(rng, [(400.0, 0.0)]), speed, 0.8), *car)
    if kind == "pedestrian":
        pieces = [(rng.uniform(1.5, 4), rng.choice([-1, 1]) / rng.uniform(3, 8)) for _ in range(int(seconds))]
        plan = []
        for _ in range(int(seconds)):
            plan += [("ramp", rng.uniform(0.6, 1.6), 0.5), ("hold", rng.uniform(0.5, 2), 0)]
        speed = SpeedProfile.build(0.0, 0.0, 1.0, plan)
        return Track(name, kind, Trajectory(_path(rng, pieces), speed, 0.9), tx.PERSON, (0.6, 0.7, 1.75))
    if kind == "parked":
        return Track(
            name, kind, Trajectory(_path(rng, [(1.0, 0.0)]), SpeedProfile(0.0, 0.0, 0.0, []), 0.8), *car
        )
    raise ValueError(f"unknown track type {kind!r}")


def truth_boxes(tracks: list[Track], t_s: float) -> dict[str, tuple[np.ndarray, float]]:
    """Exact centre and yaw of every track alive at ``t_s``."""
    out = {}
    for track in tracks:
        if track.alive_s[0] <= t_s <= track.alive_s[1]:
            pos, yaw, _, _ = track.trajectory.state(t_s)
            out[track.name] = (pos, float(yaw))
    return out


def keyframes_of(
    tracks: list[Track],
    times_micros: np.ndarray,
    noise: bool,
    rng: np.random.Generator,
    camera_times: list[dict[str, int]],
) -> list[KeyframeBoxes]:
    """Annotations of the tracks alive at each keyframe (with annotation noise if ``noise``);
    ``camera_times``: each keyframe's own camera images (name -> timestamp)."""
    out = []
    for t, cameras in zip(times_micros, camera_times, strict=True):
        alive = [tr for tr in tracks if tr.alive_s[0] <= t * 1e-6 <= tr.alive_s[1]]
        m = len(alive)
        centres = np.zeros((m, 3))
        yaws = np.zeros(m)
        for k, tr in enumerate(alive):
            pos, yaw, _, _ = tr.trajectory.state(t * 1e-6)
            centres[k], yaws[k] = pos, yaw
            if noise:
                centres[k] += rng.normal(0, [0.05, 0.05, 0.02])
                yaws[k] += np.radians(rng.normal(0, 5.0 if tr.kind == "pedestrian" else 1.0))
        boxes = Boxes(
            track_id=[tr.name for tr in alive],
            class_id=np.array([tr.class_id for tr in alive], np.uint8),
            center_world=centres,
            size_lwh=np.array([tr.size_lwh for tr in alive]).reshape(m, 3),
            yaw_world=yaws,
            velocity_world=np.full((m, 3), np.nan),
            status=np.zeros(m, np.uint8),
            instance_id=np.arange(1, m + 1, dtype=np.uint16),
            num_lidar_points=np.full(m, -1, np.int32),
        )
        out.append(KeyframeBoxes(int(t), boxes, camera_timestamps_micros=cameras))
    return out


def camera_sweeps(
    seconds: float, key_times: np.ndarray, rng: np.random.Generator
) -> tuple[dict[str, np.ndarray], list[dict[str, int]]]:
    """Each camera's 12 Hz sweep times (microseconds) and each keyframe's own images.

    Camera sweep n fires ``CAMERA_OFFSETS_MICROS`` after the start of a revolution that ends at
    n / 12 s (2 ms jitter); every 6th sweep is keyframe k's image, triggered in the revolution
    ending at keyframe k's own time (0.5 ms jitter) and never dropped; 1 % of the others are.
    """
    count = int(seconds * 12) + 1
    steps = np.arange(count)
    key_step = steps % SWEEPS_PER_KEYFRAME == 0
    images: list[dict[str, int]] = [{} for _ in key_times]
    out = {}
    for spec in NUSCENES6:
        offset = CAMERA_OFFSETS_MICROS[spec.name] - LIDAR_MICROS
        t = offset + steps * SWEEP_MICROS + rng.normal(0, 2000, count)
        key = steps[key_step] // SWEEPS_PER_KEYFRAME
        t[key_step] = key_times[key] + offset + rng.normal(0, 500, len(key))
        t = np.round(t).astype(np.int64)
        for k, stamp in zip(key, t[key_step], strict=True):
            images[k][spec.name] = int(stamp)
        keep = key_step | (rng.random(count) >= 0.01)
        out[spec.name] = t[keep]
    return out, images


def run_method(
    method: str, keyframes: list[KeyframeBoxes], sweeps: dict[str, np.ndarray]
) -> tuple[dict[str, list[Boxes]], float]:
    """Boxes at every camera sweep and the seconds it took."""
    t0 = time.perf_counter()
    if method == "asap":
        out = {name: asap_boxes(keyframes, times, channel=name) for name, times in sweeps.items()}
    else:
        # All cameras in one call: the tracks are built once per scene, as the stage does.
        every = np.concatenate(list(sweeps.values()))
        boxes = interpolate_boxes_at(keyframes, every, InterpolateParams(method=method))  # type: ignore[arg-type]
        out, start = {}, 0
        for name, times in sweeps.items():
            out[name] = boxes[start : start + len(times)]
            start += len(times)
    return out, time.perf_counter() - t0


def score(
    tracks: list[Track],
    sweeps: dict[str, np.ndarray],
    boxes: dict[str, list[Boxes]],
    window_micros: tuple[int, int],
    tallies: dict[str, Tally],
    parked_centres: dict[str, list[np.ndarray]],
) -> None:
    kind_of = {tr.name: tr.kind for tr in tracks}
    for name, times in sweeps.items():
        for t, got in zip(times, boxes[name], strict=True):
            if not window_micros[0] <= t <= window_micros[1]:
                continue
            truth = truth_boxes(tracks, t * 1e-6)
            for track_name in truth:
                tallies[kind_of[track_name]].truth += 1
            for k, track_name in enumerate(got.track_id):
                tally = tallies[kind_of[track_name]]
                if track_name not in truth:
                    tally.spurious += 1
                    continue
                centre, yaw = truth[track_name]
                tally.centre_m.append(float(np.linalg.norm(got.center_world[k] - centre)))
                tally.yaw_deg.append(float(np.degrees(abs(geometry.angle_difference(got.yaw_world[k], yaw)))))
                if kind_of[track_name] == "parked":
                    parked_centres.setdefault(f"{name}/{track_name}", []).append(got.center_world[k])


def benchmark(args: argparse.Namespace, noise: bool) -> tuple[dict, dict, dict]:
    tallies = {m: {kind: Tally() for kind in TYPES} for m in METHODS}
    seconds = {m: 0.0 for m in METHODS}
    counts = {m: 0 for m in METHODS}
    drift: dict[str, list[float]] = {m: [] for m in METHODS}
    for scene in range(args.scenes):
        rng = np.random.default_rng([args.seed, scene, int(noise)])
        tracks = [make_track(kind, i, args.seconds, rng) for kind in TYPES for i in range(args.tracks)]
        n_keys = int(args.seconds * 2) + 1
        key_times = np.arange(n_keys) * KEYFRAME_MICROS + np.round(rng.normal(0, 3000, n_keys)).astype(
            np.int64
        )
        key_times[0] = 0
        sweeps, images = camera_sweeps(args.seconds, key_times, rng)
        keyframes = keyframes_of(tracks, key_times, noise, rng, images)
        window = (int(key_times[0]) - 50_000, int(key_times[-1]) + 50_000)
        for method in METHODS:
            boxes, took = run_method(method, keyframes, sweeps)
            seconds[method] += took
            counts[method] += sum(len(b) for per_camera in boxes.values() for b in per_camera)
            parked: dict[str, list[np.ndarray]] = {}
            score(tracks, sweeps, boxes, window, tallies[method], parked)
            drift[method] += [float(np.ptp(np.array(c), axis=0)[:2].max()) for c in parked.values()]
    speed = {m: counts[m] / seconds[m] if seconds[m] else 0.0 for m in METHODS}
    return tallies, speed, drift


def rows_of(tallies: dict[str, dict[str, Tally]]) -> list[list[object]]:
    rows = []
    for kind in TYPES:
        for method in METHODS:
            t = tallies[method][kind]
            c, y = np.array(t.centre_m), np.array(t.yaw_deg)
            rows.append(
                [
                    kind,
                    method,
                    f"{c.mean():.3f}" if len(c) else "—",
                    f"{np.percentile(c, 95):.3f}" if len(c) else "—",
                    f"{y.mean():.2f}" if len(y) else "—",
                    f"{np.percentile(y, 95):.2f}" if len(y) else "—",
                    f"{100 * len(c) / max(t.truth, 1):.2f}",
                    t.spurious,
                ]
            )
    return rows


def p95(tallies: dict[str, dict[str, Tally]], method: str, kind: str) -> float:
    return float(np.percentile(tallies[method][kind].centre_m, 95))


def goals(tallies: dict[str, dict[str, Tally]]) -> list[str]:
    """The goal lines printed under a table, each saying whether it is met."""
    ours = "ctra"
    lines = []
    linear, new = p95(tallies, "linear", "turning"), p95(tallies, ours, "turning")
    cut = 100 * (1 - new / linear)
    lines.append(
        f"turning: {ours} p95 centre error {new:.3f} m vs linear {linear:.3f} m ({cut:.0f}% lower; "
        f"goal at least 40%: {'met' if cut >= 40 else 'NOT met'})"
    )
    no_worse = [("straight", "linear"), ("pedestrian", "linear")]
    no_worse += [(kind, "hermite") for kind in ("stop-and-go", "parked", "enter/leave")]
    for kind, base in no_worse:
        a, b = p95(tallies, ours, kind), p95(tallies, base, kind)
        lines.append(
            f"{kind}: {ours} p95 {a:.3f} m vs {base} {b:.3f} m "
            f"(goal no worse than {base}: {'met' if a <= b else 'NOT met'})"
        )
    for kind in ("turning", "stop-and-go"):
        asap, new = p95(tallies, "asap", kind), p95(tallies, ours, kind)
        cut = 100 * (1 - new / asap)
        lines.append(
            f"{kind}: {ours} p95 {new:.3f} m vs asap {asap:.3f} m "
            f"({cut:.0f}% lower; goal 30%: {'met' if cut >= 30 else 'NOT met'})"
        )
    for method in ("asap", "hermite", ours):
        t = tallies[method]["enter/leave"]
        lines.append(
            f"enter/leave recall, {method}: {100 * len(t.centre_m) / t.truth:.2f}% (goal for {ours} >= 99%)"
        )
    return lines


HEADERS = [
    "track type",
    "method",
    "centre mean m",
    "centre p95 m",
    "yaw mean deg",
    "yaw p95 deg",
    "recall %",
    "spurious",
]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=20.0, help="scene length")
    parser.add_argument("--tracks", type=int, default=8, help="tracks of each type per scene")
    parser.add_argument("--seed", type=int, default=0)
    add_update_flag(parser)
    args = parser.parse_args(argv)
    report = Report(
        "interpolation",
        "12 Hz box interpolation from 2 Hz keyframes",
        f"Written by `benchmarks/interpolation.py`. {args.scenes} scenes of {args.seconds:g} s, "
        f"{args.tracks} tracks of each type per scene; keyframes every 0.5 s (+-3 ms), six cameras at "
        "12 Hz with nuScenes' timing (each fires as the LiDAR revolution passes it, 7-49 ms after the "
        "revolution starts, so a keyframe's own images are 1-43 ms before it; 2 ms jitter, 1 % of the "
        "non-keyframe sweeps dropped); every camera sweep from 50 ms before the first keyframe to 50 ms "
        "after the last is scored against the exact box at its own timestamp. `asap`: ASAP's interp "
        "(MagicDrive), each camera's own keyframe image getting the annotations; `linear`: linear + "
        "slerp at the real timestamp; `hermite`: cubic Hermite through the annotations; `ctra`, the "
        "default: CV/CA/CTRV/CTRA motion models fitted over windows of up to 7 annotations, chosen per "
        "window by BIC and a chi-square test against the noise it estimates from the scene; all but "
        "`asap` with the same track-end and stationary handling.",
    )
    speeds = {}
    for noise in (False, True):
        tallies, speed, drift = benchmark(args, noise)
        label = (
            "noisy annotations (centre 5 cm, height 2 cm, yaw 1 deg, pedestrians 5 deg)"
            if noise
            else "exact annotations"
        )
        speeds[label] = speed
        parked = ", ".join(f"{m} {1000 * np.mean(drift[m]):.0f} mm" for m in METHODS if drift[m])
        report.table(
            f"Errors at camera sweeps, {label}",
            HEADERS,
            rows_of(tallies),
            "Recall: share of the truth boxes at camera sweeps that got a box; spurious: boxes at "
            "sweeps where the object does not exist (extrapolated before an entering object appeared or "
            "after a leaving one vanished; in nuScenes such objects exist but are not annotated). Parked "
            f"objects' mean horizontal range of the box centre over a scene (jitter and drift): {parked}."
            "\n\n" + "\n".join(f"- {line}" for line in goals(tallies)),
        )
    report.table(
        "Speed",
        ["annotations", *(f"{m} boxes/s" for m in METHODS)],
        [[label, *(f"{s[m]:,.0f}" for m in METHODS)] for label, s in speeds.items()],
        "Boxes produced per second of interpolation, one process (ctra, hermite and linear include "
        "building the tracks, and ctra its window fits, once per scene, as the stage does).",
    )
    report.write(update=args.update)


if __name__ == "__main__":
    main()
