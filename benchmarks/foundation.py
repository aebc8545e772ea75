"""Foundation benchmark: synthetic rendering time, cache bytes per frame and loader throughput.

Usage (from the repository root)::

    python benchmarks/foundation.py [--frames N] [--scenes S] [--quick]

Measures, in one run:

1. Render time of the synthetic source per camera image, per frame's cameras and per LiDAR sweep,
   for the waymo5 and nuscenes6 rigs at the default image size and LiDAR; world building,
   renderer setup and the first (warm-up) frame are reported separately.
2. Bytes per frame of a cache built with :func:`phigenesis.prep.synthetic` (default pipeline),
   broken down by column group from the Arrow buffers of the shards.
3. Frames/s of :class:`~phigenesis.data.loader.FrameDataset` through a torch DataLoader, against
   the "decode floor": decoding the same stored images (and truth PNGs) from memory with
   ``cv2.imdecode`` in one process; for the training fields on that cache, then for images alone
   at the paper's R1 (160x240, that cache) and R2 (576x1024, a small cache built for it) sizes,
   with where an image-only frame's time goes beyond decoding.

Prints the tables and replaces the ``foundation`` section of BENCHMARKS.md. No timing is asserted.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, round_ratio
from torch.utils.data import DataLoader

from phigenesis import prep
from phigenesis._open3d import open3d
from phigenesis.data.loader import FrameDataset, auto_decode_threads, collate_frames
from phigenesis.data.schema import TRUTH_MAPS, cameras_of
from phigenesis.data.shards import CacheReader
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene

RIGS = ("waymo5", "nuscenes6")
#: The loader's field groups for a training step, and for images alone.
TRAINING_FIELDS = ("images", "cameras", "truth", "boxes")
IMAGE_FIELDS = ("images",)
#: Goal: the loader with 0 workers takes at most this multiple of the decode floor's time.
FLOOR_RATIO_GOAL = 1.5
KIB = 1024


def median_ms(seconds: Sequence[float]) -> str:
    """The median of ``seconds``, formatted in milliseconds."""
    return f"{1e3 * float(np.median(seconds)):.1f}"


def p90_ms(seconds: Sequence[float]) -> str:
    """The 90th percentile of ``seconds``, formatted in milliseconds."""
    return f"{1e3 * float(np.percentile(seconds, 90)):.1f}"


# --------------------------------------------------------------------------------------------
# 1. Rendering


@dataclass
class RenderTimes:
    """Render timings of one rig (seconds) and the LiDAR points per sweep."""

    rig: str
    cameras: int
    image_size: str
    lidar_size: str
    world_s: float
    renderer_s: float
    first_frame_s: float
    per_camera: list[float] = field(default_factory=list)
    cameras_per_frame: list[float] = field(default_factory=list)
    lidar: list[float] = field(default_factory=list)
    whole_frame: list[float] = field(default_factory=list)
    lidar_points: list[int] = field(default_factory=list)


def time_rendering(rig: str, frames: int) -> RenderTimes:
    """Times ``frames`` frames of scene 0 of a default-config ``rig`` run, after one warm-up frame.

    Each frame's cameras and LiDAR are rendered exactly as ``SyntheticScene.render_frame`` does
    (same capture times, poses and random stream) and timed separately; the frame is then rendered
    again whole with ``render_frame`` (which adds JPEG encoding and the boxes).
    """
    scene = SyntheticScene(SyntheticConfig(rig=rig, scenes=1, frames=frames + 1), 0)
    cfg = scene.config
    t0 = time.perf_counter()
    _ = scene.world
    t1 = time.perf_counter()
    renderer = scene.renderer
    t2 = time.perf_counter()
    scene.render_frame(0)
    t3 = time.perf_counter()
    result = RenderTimes(
        rig=rig,
        cameras=len(scene.calibrations),
        image_size=f"{cfg.height}x{cfg.width}",
        lidar_size=f"{cfg.lidar.beams}x{cfg.lidar.columns}",
        world_s=t1 - t0,
        renderer_s=t2 - t1,
        first_frame_s=t3 - t2,
    )
    for k in range(1, frames + 1):
        t_micros = scene.frame_micros[k]
        frame_cameras = 0.0
        for i, calibration in enumerate(scene.calibrations):
            cam_micros = scene.camera_time_micros(t_micros, i)
            pose = scene.world_from_ego(cam_micros)
            t0 = time.perf_counter()
            renderer.render_camera(calibration, pose, scene.seconds(cam_micros))
            elapsed = time.perf_counter() - t0
            result.per_camera.append(elapsed)
            frame_cameras += elapsed
        result.cameras_per_frame.append(frame_cameras)
        rng = np.random.default_rng([*scene.seed_sequence, k])
        world_from_ego = scene.world_from_ego(t_micros)
        t0 = time.perf_counter()
        raw = renderer.render_lidar(cfg.lidar, t_micros, cfg.start_micros, scene.spin_period_s, rng)
        sweep = scene._lidar(raw, t_micros, world_from_ego)
        result.lidar.append(time.perf_counter() - t0)
        result.lidar_points.append(len(sweep.points_ego))
        t0 = time.perf_counter()
        scene.render_frame(k)
        result.whole_frame.append(time.perf_counter() - t0)
    return result


def report_rendering(report: Report, frames: int) -> None:
    """Section 1: render times of both rigs, then their one-time costs and LiDAR points."""
    t0 = time.perf_counter()
    open3d()
    import_s = time.perf_counter() - t0
    results = [time_rendering(rig, frames) for rig in RIGS]
    rows = []
    for r in results:
        rows += [
            [r.rig, "one camera image", median_ms(r.per_camera), p90_ms(r.per_camera), len(r.per_camera)],
            [
                r.rig,
                f"all {r.cameras} cameras of a frame",
                median_ms(r.cameras_per_frame),
                p90_ms(r.cameras_per_frame),
                len(r.cameras_per_frame),
            ],
            [r.rig, "LiDAR sweep", median_ms(r.lidar), p90_ms(r.lidar), len(r.lidar)],
            [
                r.rig,
                "whole frame (render_frame: + JPEG, boxes)",
                median_ms(r.whole_frame),
                p90_ms(r.whole_frame),
                len(r.whole_frame),
            ],
        ]
    report.table(
        "Render time",
        ["rig", "what", "median ms", "p90 ms", "samples"],
        rows,
        f"{frames} frames of scene 0 per rig after one warm-up frame; images "
        f"{results[0].image_size} (HxW), LiDAR {results[0].lidar_size} (beams x columns).",
    )
    report.table(
        "Render setup (once per scene) and LiDAR points",
        ["rig", "world build s", "renderer setup ms", "first frame s", "LiDAR points/sweep (median)"],
        [
            [
                r.rig,
                f"{r.world_s:.2f}",
                f"{1e3 * r.renderer_s:.1f}",
                f"{r.first_frame_s:.2f}",
                f"{int(np.median(r.lidar_points)):,}",
            ]
            for r in results
        ],
        f"The Open3D import ({import_s:.2f} s, once per process) is excluded. The first frame includes "
        "Open3D's lazy build of the static scene's ray-casting structure.",
    )


# --------------------------------------------------------------------------------------------
# 2. Cache bytes


def buffer_bytes(array: pa.Array, path: str) -> Iterator[tuple[str, int]]:
    """(field path, bytes) of the Arrow buffers of ``array`` and of its nested children.

    A list's or struct's own buffers (validity, offsets) count under its own path. Arrays read
    from IPC files are unsliced, so each buffer's size is what the field stores.
    """
    own = array.buffers()[: array.type.num_buffers]
    yield path, sum(b.size for b in own if b is not None)
    t = array.type
    if pa.types.is_struct(t):
        for i in range(t.num_fields):
            yield from buffer_bytes(array.field(i), f"{path}.{t.field(i).name}")
    elif pa.types.is_list(t) or pa.types.is_fixed_size_list(t):
        yield from buffer_bytes(array.values, path)


def column_group(path: str) -> str:
    """The reported group of a field path: images, each truth map, LiDAR fields, boxes, metadata."""
    top, _, rest = path.partition(".")
    child = rest.split(".", 1)[0]
    if top == "cameras":
        if child == "image":
            return "images (JPEG)"
        if child.startswith("truth_"):
            return f"truth {child.removeprefix('truth_').removesuffix('_png')} (PNG)"
        return "camera metadata"
    if top == "lidar":
        return f"LiDAR: {child or 'struct validity'}"
    if top == "boxes":
        return "boxes"
    return "frame metadata"


def report_cache_bytes(report: Report, cache_dir: Path, build_s: float) -> None:
    """Section 2: bytes per frame of the cache at ``cache_dir`` (built in ``build_s``), by group."""
    reader = CacheReader(cache_dir)
    frames = len(reader)
    by_group: dict[str, int] = defaultdict(int)
    cameras = 0
    for batch in reader:
        cameras += len(cameras_of(batch)["camera_name"])
        for name, column in zip(batch.schema.names, batch.columns, strict=True):
            for path, size in buffer_bytes(column, name):
                by_group[column_group(path)] += size
    arrow_total = sum(by_group.values())
    file_total = sum(sh.bytes for sh in reader.shards)
    lidar_total = sum(v for k, v in by_group.items() if k.startswith("LiDAR"))
    images = by_group["images (JPEG)"]

    def row(name: str, size: int) -> list[str]:
        return [name, f"{size / frames / KIB:,.1f}", f"{100 * size / file_total:.1f}%"]

    order = ["images (JPEG)", *(f"truth {m} (PNG)" for m in TRUTH_MAPS), "camera metadata"]
    rows = [row(g, by_group[g]) for g in order if g in by_group]
    rows.append(row("LiDAR (all fields)", lidar_total))
    lidar_fields = sorted(((v, g) for g, v in by_group.items() if g.startswith("LiDAR") and v), reverse=True)
    rows += [row(f"  {g}", v) for v, g in lidar_fields]
    rows += [row("boxes", by_group["boxes"]), row("frame metadata", by_group["frame metadata"])]
    rows += [row("Arrow buffers, total", arrow_total), row("shard files", file_total)]
    args = reader.manifest.arguments
    report.table(
        "Cache bytes per frame",
        ["column group", "KiB/frame", "share of file bytes"],
        rows,
        f"Cache built by `phigenesis.prep.synthetic` (default pipeline: rig {args['rig']}, "
        f"{args['height']}x{args['width']} images, JPEG quality {args['jpeg_quality']}): "
        f"{len(reader.scene_ids())} scenes x {args['frames']} frames = {frames} frames in "
        f"{len(reader.shards)} shards, built in {build_s:.1f} s "
        f"({build_s / frames:.2f} s/frame in one process). "
        f"One JPEG image is {images / cameras / KIB:.1f} KiB on average. Shard files add the IPC framing "
        "and footer to the Arrow buffers.",
    )


# --------------------------------------------------------------------------------------------
# 3. Loader throughput


def stored_bytes(cache_dir: Path, with_truth: bool) -> list[list[tuple[np.ndarray, int]]]:
    """Per frame, the stored (encoded bytes, cv2 imread flag) of every image and truth PNG."""
    columns = [("image", cv2.IMREAD_COLOR)]
    if with_truth:
        columns += [(f"truth_{m}_png", cv2.IMREAD_UNCHANGED) for m in TRUTH_MAPS]
    out = []
    for batch in CacheReader(cache_dir):
        cf = cameras_of(batch)
        out.append(
            [
                (np.frombuffer(data, np.uint8), flag)
                for name, flag in columns
                if name in cf
                for data in cf[name].to_pylist()
                if data is not None
            ]
        )
    return out


def interleaved_times(runs: dict[str, Callable[[], None]], passes: int) -> dict[str, list[float]]:
    """Wall times of each run in each of ``passes`` rounds, after one untimed warm-up round.

    The runs take turns within each round, so drift in the machine's speed (a shared VM) affects
    all of them alike and their ratios stay meaningful.
    """
    for run in runs.values():
        run()
    times: dict[str, list[float]] = defaultdict(list)
    for _ in range(passes):
        for name, run in runs.items():
            t0 = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - t0)
    return dict(times)


def interleaved_medians(runs: dict[str, Callable[[], None]], passes: int) -> dict[str, float]:
    """Median wall time of each run over ``passes`` interleaved rounds (:func:`interleaved_times`)."""
    return {name: float(np.median(t)) for name, t in interleaved_times(runs, passes).items()}


def decode_pass(encoded: list[list[tuple[np.ndarray, int]]]) -> Callable[[], None]:
    """One pass that ``cv2.imdecode``s every stored buffer of every frame, in this process."""

    def run_pass() -> None:
        for frame in encoded:
            for data, flag in frame:
                cv2.imdecode(data, flag)

    return run_pass


def loader_pass(
    cache_dir: Path,
    fields: Sequence[str],
    workers: int,
    batch_size: int,
    repeat: int = 1,
    decode_threads: int | None = None,
) -> Callable[[], None]:
    """One full pass of a DataLoader over the cache's frames, ``repeat`` times each (persistent workers)."""
    dataset = FrameDataset(cache_dir, fields=fields, decode_threads=decode_threads)
    loader = DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=list(range(len(dataset))) * repeat,
        collate_fn=collate_frames,
        num_workers=workers,
        persistent_workers=workers > 0,
    )

    def run_pass() -> None:
        collections.deque(loader, maxlen=0)  # iterate, keeping nothing

    return run_pass


#: (workers, batch size, decode threads) of the DataLoader variants measured; None: the default
#: (``auto_decode_threads``: the cores in the main process, the cores per worker in a worker).
LOADER_VARIANTS = ((0, 1, 1), (0, 1, None), (2, 1, None), (2, 4, None))


def goal_cell(ratio: float) -> str:
    return f"≤ {FLOOR_RATIO_GOAL}: " + ("met" if ratio <= FLOOR_RATIO_GOAL else "missed")


def _loader_label(workers: int, batch: int, threads: int | None) -> str:
    label = f"DataLoader, {workers} workers, batch {batch}"
    if threads is not None:
        return label + f", {threads} decode thread" + ("s" if threads != 1 else "")
    threads = auto_decode_threads(workers)
    return label + f" (default: {threads} decode thread" + ("s" if threads != 1 else "") + ")"


def loader_rows(
    label: str, cache_dir: Path, fields: Sequence[str], floor_label: str, passes: int, repeat: int = 1
) -> list[list[str]]:
    """Rows of the decode floor and of each LOADER_VARIANTS DataLoader over the same frames,
    measured in one interleaved run."""
    encoded = stored_bytes(cache_dir, with_truth=fields != IMAGE_FIELDS) * repeat
    runs = {"floor": decode_pass(encoded)}
    for workers, batch, threads in LOADER_VARIANTS:
        runs[f"{workers}/{batch}/{threads}"] = loader_pass(cache_dir, fields, workers, batch, repeat, threads)
    times = interleaved_times(runs, passes)
    floor = times.pop("floor")
    loads = len(encoded)
    rows = [[label, f"decode floor ({floor_label})", f"{loads / float(np.median(floor)):.1f}", "1.00", "—"]]
    for variant, t in zip(LOADER_VARIANTS, times.values(), strict=True):
        ratio = round_ratio(t, floor)
        rows.append(
            [
                label,
                _loader_label(*variant),
                f"{loads / float(np.median(t)):.1f}",
                f"{ratio:.2f}",
                goal_cell(ratio),
            ]
        )
    return rows


def report_loader(report: Report, cache_dir: Path, passes: int) -> None:
    """Section 3a: DataLoader frames/s for the training fields and worker counts, against the decode floor."""
    frames = len(CacheReader(cache_dir))
    rows = loader_rows(
        "images+cameras+truth+boxes", cache_dir, TRAINING_FIELDS, "images + 4 truth PNGs", passes
    )
    report.table(
        "Loader throughput",
        ["fields", "reader", "frames/s", "time / floor", "goal"],
        rows,
        f"{frames} frames per pass with `collate_frames` and FrameDataset defaults (the CRCs of every "
        f"column read are checked); {passes} rounds after one warm-up round, the floor and the loaders "
        "taking turns within each round (workers are persistent, so their start-up is not timed). "
        "frames/s: from the median pass time; time / floor: the median over rounds of the pass time "
        "over the floor's in the same round. The decode floor decodes the same stored buffers, already "
        "in memory, with `cv2.imdecode` in one process, on one thread. `decode threads`: the threads "
        "FrameDataset decodes a frame's cameras on (OpenCV releases the GIL); the 1-thread row is the "
        "loader's own cost. Images alone: the next table.",
    )


#: The paper's image sizes (H, W): R1 is the default synthetic size, R2 gets a cache of its own.
PAPER_SIZES = {"R1": (160, 240), "R2": (576, 1024)}
#: Each pass over an image-size cache loads at least this many frames (small caches repeat theirs).
MIN_LOADS_PER_PASS = 32


@dataclass
class SizedCache:
    name: str
    height: int
    width: int
    path: Path
    frames: int
    build_s: float | None  # None for the default benchmark cache, built for section 2

    @property
    def label(self) -> str:
        return f"{self.name} {self.height}x{self.width}"

    @property
    def repeat(self) -> int:
        return -(-MIN_LOADS_PER_PASS // self.frames)


def frame_costs(cache: SizedCache, passes: int) -> list[list[str]]:
    """Where an image-only frame's time goes in one process: reading its columns with and without
    their CRC checks, decoding its JPEGs, FrameDataset[i] and a DataLoader with 0 workers."""
    dataset = FrameDataset(cache.path, fields=IMAGE_FIELDS, decode_threads=1)
    unchecked = FrameDataset(cache.path, fields=IMAGE_FIELDS, check_crc=False, decode_threads=1)
    indices = list(range(len(dataset))) * cache.repeat
    columns = [dataset._columns(i) for i in range(len(dataset))]
    loader = loader_pass(cache.path, IMAGE_FIELDS, 0, 1, cache.repeat, decode_threads=1)

    def read(ds: FrameDataset) -> Callable[[], None]:
        return lambda: collections.deque((ds.reader.read(i, columns[i]) for i in indices), maxlen=0)

    runs = {
        "floor": decode_pass(stored_bytes(cache.path, with_truth=False) * cache.repeat),
        "read": read(dataset),
        "read_unchecked": read(unchecked),
        "item": lambda: collections.deque((dataset[i] for i in indices), maxlen=0),
        "loader": loader,
    }
    ms = {k: 1e3 * t / len(indices) for k, t in interleaved_medians(runs, passes).items()}
    total = ms["loader"]
    steps = [
        (f"read the frame's {len(columns[0])} columns, CRC-32Cs checked", ms["read"]),
        ("  of which the CRC-32C checks", ms["read"] - ms["read_unchecked"]),
        ("decode the JPEGs (the floor)", ms["floor"]),
        ("FrameDataset[i]: read + decode + de-interleave", ms["item"]),
        ("  beyond read and decode", ms["item"] - ms["read"] - ms["floor"]),
        ("DataLoader, 0 workers, batch 1", total),
        ("  beyond FrameDataset[i] (collate, batching)", total - ms["item"]),
    ]
    return [[cache.label, step, f"{t:.3f}", f"{100 * t / total:.0f}%"] for step, t in steps]


def report_image_sizes(report: Report, caches: list[SizedCache], passes: int) -> None:
    """Section 3b: image-only loading against the decode floor at R1 and R2, and its per-frame costs."""
    rows = []
    for cache in caches:
        rows += loader_rows(cache.label, cache.path, IMAGE_FIELDS, "images", passes, cache.repeat)

    def origin(c: SizedCache) -> str:
        if c.build_s is None:
            return f"{c.label}: the cache above ({c.frames} frames)"
        frames = f"{c.frames} frame" + ("s" if c.frames != 1 else "")
        return f"{c.label}: {frames} of 1 scene, default pipeline, built in {c.build_s:.0f} s"

    report.table(
        "Image-only loading at the paper's sizes",
        ["size", "reader", "frames/s", "time / floor", "goal"],
        rows,
        f"Field group `images` only (each frame's 5 JPEGs, decoded into `uint8 [C, 3, H, W]`); "
        f"{'; '.join(origin(c) for c in caches)}. A pass loads each frame "
        f"{' / '.join(str(c.repeat) for c in caches)} times (at least {MIN_LOADS_PER_PASS} loads); "
        f"{passes} rounds, the floor and the loaders taking turns within each round; frames/s and time / "
        "floor as above. The decode floor runs in one process on one thread; 2 workers, or 2 decode "
        "threads, can beat it on 2 cores. Worker batches travel in pooled shared-memory segments "
        "(`phigenesis.data.batch_pool`).",
    )
    cost_rows = []
    for cache in caches:
        cost_rows += frame_costs(cache, passes)
    report.table(
        "Image-only loading: where a frame's time goes (one process)",
        ["size", "step", "ms/frame", "share of DataLoader time"],
        cost_rows,
        "Medians of interleaved rounds as above, everything on one decode thread; the indented rows "
        "are differences of the others. "
        "Reading checks the CRC-32C of every column it returns: the `cameras` column holds every PNG "
        "of the frame's cameras, not only the JPEGs, so its check covers more bytes than are decoded.",
    )


def build_sized_caches(tmp: Path, default_cache: Path, frames_r2: int) -> list[SizedCache]:
    """R1 is the default benchmark cache (160x240); R2 is built here with ``frames_r2`` frames."""
    args = CacheReader(default_cache).manifest.arguments
    assert (args["height"], args["width"]) == PAPER_SIZES["R1"], args
    caches = [SizedCache("R1", *PAPER_SIZES["R1"], default_cache, len(CacheReader(default_cache)), None)]
    height, width = PAPER_SIZES["R2"]
    path = tmp / "cache_r2"
    t0 = time.perf_counter()
    prep.synthetic(path, scenes=1, frames=frames_r2, height=height, width=width, progress=False)
    caches.append(SizedCache("R2", height, width, path, frames_r2, time.perf_counter() - t0))
    return caches


# --------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> None:
    """Runs the three measurements, prints their tables and updates BENCHMARKS.md."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--frames", type=int, help="frames timed per rig, and frames per cache scene (default 20)"
    )
    parser.add_argument("--scenes", type=int, help="scenes of the benchmark cache (default 2)")
    parser.add_argument("--quick", action="store_true", help="small numbers, for a smoke test (< 1 min)")
    add_update_flag(parser)
    args = parser.parse_args(argv)
    frames = args.frames if args.frames is not None else (2 if args.quick else 20)
    scenes = args.scenes if args.scenes is not None else (1 if args.quick else 2)
    passes = 2 if args.quick else 11
    frames_r2 = 1 if args.quick else 4

    report = Report(
        "foundation",
        "Foundation: rendering, cache size, loader throughput",
        "Written by `benchmarks/foundation.py`."
        + (" **Smoke test (`--quick`): numbers are not representative.**" if args.quick else ""),
    )
    report_rendering(report, frames)
    with tempfile.TemporaryDirectory(prefix="phigenesis-bench-") as tmp:
        cache_dir = Path(tmp) / "cache"
        t0 = time.perf_counter()
        prep.synthetic(cache_dir, scenes=scenes, frames=frames, progress=False)
        report_cache_bytes(report, cache_dir, time.perf_counter() - t0)
        report_loader(report, cache_dir, passes)
        report_image_sizes(report, build_sized_caches(Path(tmp), cache_dir, frames_r2), passes)
    report.write(update=args.update)


if __name__ == "__main__":
    main()
