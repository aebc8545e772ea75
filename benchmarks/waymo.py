"""Waymo benchmark: frames/s of reading v1 and v2 frames and writing them to the cache, on one core.

Usage (from the repository root)::

    python benchmarks/waymo.py [--frames N] [--rounds R] [--quick]

There are no real Waymo frames with LiDAR here, so one frame of realistic size is built from the
synthetic exporter: the five cameras upscaled to Waymo's image sizes (1920x1280, 1920x886 for the
side cameras) with mild sensor noise and stored as JPEG quality 95, the TOP LiDAR at Waymo's
64 x 2650 with per-column pixel poses and second returns, and the four short-range LiDARs
(200 x 600, sparse ground returns). The frame is repeated with advancing timestamps into a v1
TFRecord file and a v2 Parquet root. Then, pinned to one CPU and taking turns within each round:

1. v1 floor: the records read with plain file reads, ``Frame.ParseFromString``, ``zlib.decompress``
   of every range image and pixel pose, ``MatrixFloat.ParseFromString`` of each decompressed blob.
2. v1 full: what ``phigenesis-prep waymo`` does per frame: :class:`WaymoSource` over the file (CRCs
   checked), conversion to the scene model, ``frame_to_batch`` and a :class:`ShardWriter`.
3. v2 streamed floor: every component file decoded with ``ParquetFile.iter_batches`` one
   frame's rows at a time, restricted to the columns the reader uses (the v2 goal is measured
   against it), and, for comparison, every row group read whole with ``read_row_group``.
4. v2 full: as 2, over the v2 root.

and the same full paths instrumented per stage. Then, each in a fresh process, the peak resident
memory of the full readers and the two v2 floors. Prints the tables and replaces the ``waymo``
section of BENCHMARKS.md. No timing is asserted.
"""

# ruff: noqa: E402  (the thread limits below must be set before numpy and pyarrow are imported)
from __future__ import annotations

import os

for _var in (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "BLIS_NUM_THREADS",
):
    os.environ[_var] = "1"

import argparse
import contextlib
import dataclasses
import functools
import gc
import json
import shutil
import subprocess
import sys
import tempfile
import time
import zlib
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _report beside it, as a script or with -m
from _report import Report, add_update_flag, round_ratio

from phigenesis import geometry
from phigenesis.data.pipeline import PipelineSpec, load_pipeline
from phigenesis.data.schema import frame_schema, frame_to_batch
from phigenesis.data.shards import SHARDS_DIR, ShardWriter
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.data.sources.synthetic.waymo_export import GLOBAL_OFFSET_M, raw_frame
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource, convert, protos, tfrecord, v1, v2
from phigenesis.data.sources.waymo.raw import (
    LASER_NAMES,
    TOP_LASER,
    RawFrame,
    RawLaser,
    RawLaserCalibration,
)
from phigenesis.malloc_tuning import avoid_huge_page_faults, huge_pages_disabled, keep_freed_memory

#: Goal: the full reader takes at most this multiple of the floor's time per frame.
FLOOR_RATIO_GOAL = 1.5
KIB = 1024
MIB = 1024 * 1024
#: Waymo's image sizes (width, height): the front cameras, and the shorter side cameras.
FRONT_SIZE, SIDE_SIZE = (1920, 1280), (1920, 886)
SIDE_CAMERAS = (4, 5)  # SIDE_LEFT, SIDE_RIGHT
#: Standard deviation (grey levels) of the noise added to the upscaled images, so their JPEGs have
#: realistic sizes (300-500 KiB for the front cameras); without it the flat-shaded renders compress
#: to a fraction of that.
SENSOR_NOISE = 1.5
JPEG_QUALITY = 95
TOP_LIDAR = LidarSpec(beams=64, columns=2650)
#: Short-range LiDARs: (x, y, z) mount in the vehicle frame and yaw facing outwards.
SHORT_RANGE_MOUNTS: dict[int, tuple[tuple[float, float, float], float]] = {
    2: ((4.05, 0.0, 0.65), 0.0),  # FRONT
    3: ((3.20, 1.02, 0.95), np.pi / 2),  # SIDE_LEFT
    4: ((3.20, -1.02, 0.95), -np.pi / 2),  # SIDE_RIGHT
    5: ((-1.05, 0.0, 0.95), np.pi),  # REAR
}
SHORT_RANGE_SHAPE = (200, 600)
SHORT_RANGE_INCLINATION = (-np.pi / 2, np.pi / 6)
SHORT_RANGE_RETURNS = 3000
#: Fraction of first returns that also have a second return.
SECOND_RETURN_FRACTION = {"TOP": 0.08, "short-range": 0.05}
FRAME_PERIOD_MICROS = 100_000


def ms(seconds: float) -> str:
    return f"{1e3 * seconds:.1f}"


# --------------------------------------------------------------------------------------------
# The benchmark frame


def _upscale_cameras(raw: RawFrame, rng: np.random.Generator) -> None:
    """Replaces each image by its upscale to Waymo's size (+ sensor noise) and scales the calibration.

    Waymo's pixel 0 spans [0, 1), so the intrinsics scale exactly with the image. The panoptic
    labels are dropped: most real frames have none.
    """
    scale: dict[int, tuple[float, float, tuple[int, int]]] = {}
    for cal in raw.camera_calibrations:
        size = SIDE_SIZE if cal.name in SIDE_CAMERAS else FRONT_SIZE
        sx, sy = size[0] / cal.width, size[1] / cal.height
        cal.intrinsic = cal.intrinsic * np.array([sx, sy, sx, sy, 1, 1, 1, 1, 1])
        cal.width, cal.height = size
        scale[cal.name] = (sx, sy, size)
    for im in raw.images:
        assert im.jpeg is not None
        rgb = cv2.imdecode(np.frombuffer(im.jpeg, np.uint8), cv2.IMREAD_COLOR)
        up = cv2.resize(rgb, scale[im.name][2], interpolation=cv2.INTER_CUBIC).astype(np.float32)
        up += rng.normal(0.0, SENSOR_NOISE, up.shape).astype(np.float32)
        ok, jpeg = cv2.imencode(
            ".jpg", np.clip(up, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
        )
        assert ok
        im.jpeg = jpeg.tobytes()
        im.panoptic_label, im.panoptic_label_divisor, im.instance_to_global = None, 0, {}


def _second_returns(first: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """A second-return image: a random ``fraction`` of the first returns, a little further away."""
    second = np.zeros_like(first)
    rows, cols = np.nonzero(first[..., 0] > 0)
    pick = rng.random(len(rows)) < fraction
    rows, cols = rows[pick], cols[pick]
    second[rows, cols, 0] = first[rows, cols, 0] + rng.uniform(0.3, 4.0, len(rows))
    second[rows, cols, 1] = first[rows, cols, 1] * rng.uniform(0.1, 0.6, len(rows))
    second[rows, cols, 2] = rng.exponential(0.1, len(rows))
    return second


def _top_realistic(raw: RawFrame, scene: SyntheticScene, rng: np.random.Generator) -> None:
    """Gives the TOP range image per-column pixel poses (as real ones, not per sector), an
    elongation channel and second returns."""
    (top,) = [la for la in raw.lasers if la.name == TOP_LASER]
    assert top.return1 is not None
    h, w, _ = top.return1.shape
    valid = top.return1[..., 0] > 0
    top.return1[..., 2] = np.where(valid, rng.exponential(0.05, (h, w)), 0.0)
    top.return2 = _second_returns(top.return1, SECOND_RETURN_FRACTION["TOP"], rng)
    column_micros = raw.timestamp_micros + np.round((np.arange(w) + 0.5) / w * FRAME_PERIOD_MICROS)
    poses = scene.world_from_ego_many(column_micros.astype(np.int64))
    roll, pitch, yaw = geometry.matrix_to_euler_zyx(poses[:, :3, :3])
    per_column = np.stack([roll, pitch, yaw, *(poses[:, :3, 3] + GLOBAL_OFFSET_M).T], axis=1)
    top.pixel_pose = np.ascontiguousarray(np.broadcast_to(per_column, (h, w, 6)), dtype=np.float32)


def _short_range_laser(
    name: int, rng: np.random.Generator
) -> tuple[RawLaserCalibration, RawLaser, dict[str, int]]:
    """A short-range LiDAR looking outwards from the car's side: ground returns in a wedge in
    front of it (the ``SHORT_RANGE_RETURNS`` pixels nearest its axis that hit the ground within
    1-20 m), the rest of the 200 x 600 image empty."""
    (x, y, z), yaw = SHORT_RANGE_MOUNTS[name]
    extrinsic = geometry.make_transform(geometry.rotation_z(yaw), (x, y, z))
    cal = RawLaserCalibration(name, extrinsic, None, *SHORT_RANGE_INCLINATION)
    h, w = SHORT_RANGE_SHAPE
    incl = convert.beam_inclinations(cal, h)[:, None]
    az = convert.column_azimuths(extrinsic, w)[None, :]
    dz = np.broadcast_to(np.sin(incl), (h, w))  # the laser is mounted level: z is the vehicle's
    with np.errstate(divide="ignore"):
        ground = np.where(dz < 0, -z / dz, np.inf)
    azimuth = np.abs(np.angle(np.exp(1j * np.broadcast_to(az, (h, w)))))
    candidates = np.flatnonzero(((ground > 1.0) & (ground < 20.0)).ravel())
    keep = candidates[np.argsort(azimuth.ravel()[candidates], kind="stable")[:SHORT_RANGE_RETURNS]]
    first = np.zeros((h, w, 4), np.float32)
    flat = first.reshape(-1, 4)
    n = len(keep)
    flat[keep, 0] = ground.ravel()[keep] * (1 + rng.normal(0, 0.005, n)) + rng.normal(0, 0.02, n)
    flat[keep, 1] = rng.gamma(2.0, 0.05, n)
    flat[keep, 2] = rng.exponential(0.05, n)
    second = _second_returns(first, SECOND_RETURN_FRACTION["short-range"], rng)
    return cal, RawLaser(name, first, second), {"r1": n, "r2": int((second[..., 0] > 0).sum())}


@dataclass
class BenchFrame:
    """The benchmark frame and what it holds."""

    raw: RawFrame
    render_s: float
    returns: dict[str, dict[str, int]] = field(default_factory=dict)

    @property
    def points(self) -> int:
        return sum(r["r1"] + r["r2"] for r in self.returns.values())


def build_frame(height: int, width: int, seed: int = 0) -> BenchFrame:
    """Renders one synthetic frame at ``height`` x ``width`` and makes it Waymo-size (see module doc)."""
    config = SyntheticConfig(
        scenes=1, frames=1, seed=seed, height=height, width=width, uniform_image_size=False, lidar=TOP_LIDAR
    )
    scene = SyntheticScene(config, 0)
    t0 = time.perf_counter()
    raw = raw_frame(scene, 0)
    render_s = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    _upscale_cameras(raw, rng)
    _top_realistic(raw, scene, rng)
    (top,) = raw.lasers
    assert top.return1 is not None and top.return2 is not None
    frame = BenchFrame(raw, render_s)
    frame.returns["TOP"] = {
        "r1": int((top.return1[..., 0] > 0).sum()),
        "r2": int((top.return2[..., 0] > 0).sum()),
    }
    for name in sorted(SHORT_RANGE_MOUNTS):
        cal, laser, counts = _short_range_laser(name, rng)
        raw.laser_calibrations.append(cal)
        raw.lasers.append(laser)
        frame.returns[LASER_NAMES[name]] = counts
    return frame


def frame_sequence(raw: RawFrame, count: int) -> list[RawFrame]:
    """``count`` copies of ``raw`` 100 ms apart (timestamps and camera times advanced; arrays shared)."""
    out = []
    for k in range(count):
        dt_s = k * FRAME_PERIOD_MICROS * 1e-6
        images = [
            dataclasses.replace(
                im,
                pose_timestamp=im.pose_timestamp + dt_s,
                trigger_time=im.trigger_time + dt_s,
                readout_done_time=im.readout_done_time + dt_s,
            )
            for im in raw.images
        ]
        out.append(
            dataclasses.replace(
                raw, timestamp_micros=raw.timestamp_micros + k * FRAME_PERIOD_MICROS, images=images
            )
        )
    return out


def v1_records(frames: Sequence[RawFrame]) -> Iterator[bytes]:
    """The serialized v1 ``Frame`` of each frame; the first is compressed and serialized by
    :func:`v1.serialize_frame`, the rest differ only in their times (set on the parsed message)."""
    message = protos.Frame()
    message.ParseFromString(v1.serialize_frame(frames[0]))
    for f in frames:
        message.timestamp_micros = f.timestamp_micros
        for m, im in zip(message.images, f.images, strict=True):
            m.pose_timestamp = im.pose_timestamp
            m.camera_trigger_time = im.trigger_time
            m.camera_readout_done_time = im.readout_done_time
        yield message.SerializeToString()


@dataclass
class Inputs:
    """The files under test."""

    v1_path: Path
    v2_root: Path
    segment: str
    frames: int
    record_bytes: list[int]
    jpeg_bytes: list[int]
    range_image_bytes: int
    lidar_row_group_bytes: int


def write_inputs(frame: BenchFrame, count: int, workdir: Path) -> Inputs:
    frames = frame_sequence(frame.raw, count)
    segment = frame.raw.segment
    v1_path = workdir / "v1" / f"segment-{segment}_with_camera_labels.tfrecord"
    v1_path.parent.mkdir(parents=True)
    records = list(v1_records(frames))
    tfrecord.write_records(v1_path, records)
    v2_root = workdir / "v2"
    v2.write_v2(v2_root, frames)
    message = protos.Frame()
    message.ParseFromString(records[0])
    range_bytes = sum(
        len(getattr(getattr(laser, ret), part))
        for laser in message.lasers
        for ret in ("ri_return1", "ri_return2")
        for part in ("range_image_compressed", "range_image_pose_compressed")
    )
    lidar_group = sum(
        pq.ParquetFile(v2_root / tag / f"{segment}.parquet").read_row_group(0, columns=cols).nbytes
        for tag in ("lidar", "lidar_pose")
        for cols in [[c for cs in v2._read_columns(tag) for c in cs]]
    )
    return Inputs(
        v1_path,
        v2_root,
        segment,
        count,
        [len(r) for r in records],
        [len(im.jpeg or b"") for im in frame.raw.images],
        range_bytes,
        lidar_group,
    )


def check_inputs(inputs: Inputs, frame: BenchFrame) -> None:
    """Reads frame 1 back through both formats: same points and images as built, or it raises."""
    for path in (inputs.v1_path, inputs.v2_root):
        scene = WaymoSource(WaymoConfig(input=str(path))).load(inputs.segment)
        converted = scene.frames[1]
        assert converted.lidar is not None
        got = len(converted.lidar.points_ego)
        if got != frame.points:
            raise RuntimeError(f"{path}: frame 1 has {got} LiDAR points, the benchmark frame {frame.points}")
        images = [c.image_bytes for c in converted.cameras]
        if images != [im.jpeg for im in frame.raw.images]:
            raise RuntimeError(f"{path}: frame 1's images differ from the benchmark frame's")


# --------------------------------------------------------------------------------------------
# One core


def pin_to_one_cpu(cpu: int | None) -> str:
    """Limits Arrow and OpenCV to one thread and pins every thread of this process to one CPU
    (the last one allowed unless ``cpu`` is given); returns a description."""
    pa.set_cpu_count(1)
    pa.set_io_thread_count(1)
    cv2.setNumThreads(1)
    if not hasattr(os, "sched_setaffinity"):
        return "one thread per library; not pinned (no sched_setaffinity on this platform)"
    allowed = sorted(os.sched_getaffinity(0))
    cpu = allowed[-1] if cpu is None else cpu
    with contextlib.suppress(OSError):
        for tid in os.listdir("/proc/self/task"):  # every existing thread, not only this one
            with contextlib.suppress(OSError):
                os.sched_setaffinity(int(tid), {cpu})
    os.sched_setaffinity(0, {cpu})
    return f"pinned to CPU {cpu} (of {len(allowed)} allowed), one thread per library"


# --------------------------------------------------------------------------------------------
# The measured variants: each runs over every frame and returns (seconds, per-stage seconds).


class Stopwatch:
    """Accumulates wall time per stage name; stages may nest (the outer one includes the inner)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0

    @contextlib.contextmanager
    def patched(self, owner: Any, attr: str, name: str) -> Iterator[None]:
        """Times every call of ``owner.attr`` (a module function or a class's method) as ``name``."""
        original = getattr(owner, attr)

        @functools.wraps(original)
        def timed(*args: Any, **kwargs: Any) -> Any:
            with self(name):
                return original(*args, **kwargs)

        setattr(owner, attr, timed)
        try:
            yield
        finally:
            setattr(owner, attr, original)


Variant = Callable[[], tuple[float, dict[str, float]]]


def _empty_cache(cache_dir: Path) -> None:
    shutil.rmtree(cache_dir / SHARDS_DIR, ignore_errors=True)


def write_scene(source: WaymoSource, cache_dir: Path, spec: PipelineSpec) -> None:
    """What :func:`phigenesis.data.pipeline.process_scene` does for a scene (the waymo pipeline
    has no stages), without the manifest and progress reporting."""
    (scene_id,) = source.scene_ids()
    scene = source.load(scene_id)
    schema = frame_schema(
        spec.contents,
        {"phigenesis.source": scene.source, "phigenesis.scene_metadata": json.dumps(scene.metadata)},
    )
    with ShardWriter(cache_dir, scene.scene_id, schema, spec.shard_max_bytes) as writer:
        for frame in scene.frames:
            writer.write(frame_to_batch(frame, scene.source, schema))


def full_variant(path: Path, cache_dir: Path, spec: PipelineSpec) -> Variant:
    def run() -> tuple[float, dict[str, float]]:
        t0 = time.perf_counter()
        write_scene(WaymoSource(WaymoConfig(input=str(path))), cache_dir, spec)
        elapsed = time.perf_counter() - t0
        _empty_cache(cache_dir)
        return elapsed, {}

    return run


def _zlib_inflate(blob: bytes) -> bytes:
    return zlib.decompress(blob)


def _raw_inflate(blob: bytes) -> bytes:
    """The deflate data inside the zlib framing, without the Adler-32 of the output."""
    return zlib.decompressobj(-zlib.MAX_WBITS).decompress(memoryview(blob)[2:])


def v1_floor_variant(path: Path, adler32: bool = True) -> Variant:
    spans = tfrecord.index_records(path)
    inflate, inflate_step = (_zlib_inflate, "zlib.decompress") if adler32 else (_raw_inflate, "raw inflate")

    def run() -> tuple[float, dict[str, float]]:
        watch = Stopwatch()
        t0 = time.perf_counter()
        with open(path, "rb") as f:
            for span in spans:
                with watch("file read"):
                    f.seek(span.data_offset)
                    data = f.read(span.length)
                with watch("protobuf Frame parse"):
                    frame = protos.Frame()
                    frame.ParseFromString(data)
                for laser in frame.lasers:
                    for blob in (
                        laser.ri_return1.range_image_compressed,
                        laser.ri_return1.range_image_pose_compressed,
                        laser.ri_return2.range_image_compressed,
                    ):
                        if blob:
                            with watch(inflate_step):
                                matrix = inflate(blob)
                            with watch("MatrixFloat parse"):
                                protos.MatrixFloat().ParseFromString(matrix)
        return time.perf_counter() - t0, dict(watch.seconds)

    return run


def _v2_files(root: Path, segment: str, frames: int) -> list[tuple[str, Path, list[str], int]]:
    """(component tag, file, the columns the reader uses, rows per frame) of a segment's files;
    the calibrations count all their rows as one frame's."""
    files = []
    for path in sorted(root.glob(f"*/{segment}.parquet")):
        tag = path.parent.name
        required, optional = v2._read_columns(tag)
        names = set(pq.read_schema(path).names)
        rows = pq.ParquetFile(path).metadata.num_rows
        per_frame = rows if tag in ("camera_calibration", "lidar_calibration") else -(-rows // frames)
        files.append((tag, path, [c for c in required + optional if c in names], max(per_frame, 1)))
    return files


def v2_floor_variant(root: Path, segment: str, frames: int) -> Variant:
    files = _v2_files(root, segment, frames)

    def run() -> tuple[float, dict[str, float]]:
        watch = Stopwatch()
        t0 = time.perf_counter()
        for tag, path, columns, _ in files:
            with watch(tag):
                file = pq.ParquetFile(path)
                for group in range(file.metadata.num_row_groups):
                    file.read_row_group(group, columns=columns)
        return time.perf_counter() - t0, dict(watch.seconds)

    return run


def v2_streamed_floor_variant(root: Path, segment: str, frames: int) -> Variant:
    files = _v2_files(root, segment, frames)

    def run() -> tuple[float, dict[str, float]]:
        watch = Stopwatch()
        t0 = time.perf_counter()
        for tag, path, columns, per_frame in files:
            with watch(tag):
                for _batch in pq.ParquetFile(path).iter_batches(batch_size=per_frame, columns=columns):
                    pass
        return time.perf_counter() - t0, dict(watch.seconds)

    return run


def _convert_and_write(
    watch: Stopwatch, raws: Iterator[RawFrame], segment: str, cache_dir: Path, spec: PipelineSpec
) -> None:
    """The scene setup, conversion, Arrow batch and shard write of each raw frame, timed per stage
    (as :class:`WaymoSource` and :func:`write_scene` do them)."""
    writer: ShardWriter | None = None
    origin = np.zeros(3)
    schema: pa.Schema | None = None
    with watch.patched(convert, "lidar_sweep", "range images -> points"):
        for i, raw in enumerate(raws):
            if writer is None:
                with watch("scene setup"):
                    origin = raw.global_from_vehicle[:3, 3].copy()
                    convert.rig_calibrations(raw)
                    schema = frame_schema(spec.contents, {"phigenesis.source": "waymo"})
                    writer = ShardWriter(cache_dir, segment, schema, spec.shard_max_bytes)
            with watch("convert"):
                frame = convert.frame(raw, i, origin)
                frame.scene_id = segment
            with watch("Arrow batch"):
                batch = frame_to_batch(frame, "waymo", schema)
            with watch("shard write"):
                writer.write(batch)
    assert writer is not None
    with watch("shard finish"):
        writer.close()


def _staged_variant(
    raws: Callable[[Stopwatch], Iterator[RawFrame]], segment: str, cache_dir: Path, spec: PipelineSpec
) -> Variant:
    """A full-path variant timed per stage; ``raws(watch)`` yields the raw frames, timing its own
    reading stages on ``watch``."""

    def run() -> tuple[float, dict[str, float]]:
        watch = Stopwatch()
        t0 = time.perf_counter()
        _convert_and_write(watch, raws(watch), segment, cache_dir, spec)
        elapsed = time.perf_counter() - t0
        _empty_cache(cache_dir)
        return elapsed, dict(watch.seconds)

    return run


def v1_stages_variant(path: Path, segment: str, cache_dir: Path, spec: PipelineSpec) -> Variant:
    def raws(watch: Stopwatch) -> Iterator[RawFrame]:
        with watch("scene setup"):
            file = v1.V1File(path)
        with watch.patched(v1, "_matrix", "range images: zlib + decode"):
            for i in range(len(file)):
                with watch("read + CRC"):
                    data = file.record(i)
                with watch("parse"):
                    raw = v1.parse_frame(data, file.where(i))
                yield raw

    return _staged_variant(raws, segment, cache_dir, spec)


def v2_stages_variant(root: Path, segment: str, cache_dir: Path, spec: PipelineSpec) -> Variant:
    def raws(watch: Stopwatch) -> Iterator[RawFrame]:
        with watch("scene setup"):
            seg = v2.V2Segment(root, segment)
        with watch.patched(v2._RowStream, "take", "Parquet batches"):
            for i in range(len(seg)):
                with watch("read"):
                    raw = seg.frame(i)
                yield raw

    return _staged_variant(raws, segment, cache_dir, spec)


#: The timed variants, in the order they take turns.
VARIANTS = (
    "v1 floor",
    "v1 floor, no Adler-32",
    "v1 full",
    "v1 full, tmpfs",
    "v2 floor",
    "v2 streamed floor",
    "v2 full",
    "v2 full, tmpfs",
    "v1 stages",
    "v2 stages",
)
#: The variants whose peak memory is measured, each in a fresh process.
MEMORY_PROBES = ("v2 full", "v2 streamed floor", "v2 floor", "v1 full")


def make_variant(
    name: str, inputs: Inputs, caches: Path, spec: PipelineSpec, memory_caches: Path | None = None
) -> Variant:
    """The variant called ``name`` (one of :data:`VARIANTS`) over ``inputs``, writing under ``caches``
    (the ``tmpfs`` ones under ``memory_caches``: the same work without the disk)."""
    memory_caches = memory_caches or caches
    frames, segment = inputs.frames, inputs.segment
    makers: dict[str, Callable[[], Variant]] = {
        "v1 floor": lambda: v1_floor_variant(inputs.v1_path),
        "v1 floor, no Adler-32": lambda: v1_floor_variant(inputs.v1_path, adler32=False),
        "v1 full": lambda: full_variant(inputs.v1_path, caches / "v1-full", spec),
        "v2 floor": lambda: v2_floor_variant(inputs.v2_root, segment, frames),
        "v2 streamed floor": lambda: v2_streamed_floor_variant(inputs.v2_root, segment, frames),
        "v2 full": lambda: full_variant(inputs.v2_root, caches / "v2-full", spec),
        "v1 full, tmpfs": lambda: full_variant(inputs.v1_path, memory_caches / "v1-full", spec),
        "v2 full, tmpfs": lambda: full_variant(inputs.v2_root, memory_caches / "v2-full", spec),
        "v1 stages": lambda: v1_stages_variant(inputs.v1_path, segment, caches / "v1-stages", spec),
        "v2 stages": lambda: v2_stages_variant(inputs.v2_root, segment, caches / "v2-stages", spec),
    }
    return makers[name]()


@dataclass
class Memory:
    """Resident memory of one variant's pass over the segment, in a fresh process (bytes)."""

    before: int  # resident when the pass starts (interpreter, libraries, inputs indexed)
    peak: int  # the process's peak resident memory (VmHWM), the pass included

    @property
    def pass_peak(self) -> int:
        """How far the pass raised the resident memory above where it started."""
        return max(self.peak - self.before, 0)


def _status_bytes(field: str) -> int:
    """A memory figure of this process from /proc/self/status (``VmRSS``: resident now; ``VmHWM``:
    the peak since exec, which unlike ``ru_maxrss`` does not include the parent's at the fork)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * KIB
    raise RuntimeError(f"/proc/self/status has no {field}")


def pinned_cpu(pinned: str) -> int | None:
    """The CPU that :func:`pin_to_one_cpu`'s description names, or None if it did not pin."""
    words = pinned.split()
    return int(words[3]) if words[:3] == ["pinned", "to", "CPU"] else None


def peak_memory(name: str, inputs: Inputs, caches: Path, cpu: int | None) -> Memory:
    """Peak resident memory of one pass of variant ``name``, run in a fresh process (this script
    with ``--memory-probe``), pinned as the timed runs are, so nothing this process allocated
    counts."""
    probe = {"variant": name, "cpu": cpu, "caches": str(caches), "inputs": dataclasses.asdict(inputs)}
    probe["inputs"] = {k: str(v) if isinstance(v, Path) else v for k, v in probe["inputs"].items()}
    out = subprocess.run(
        [sys.executable, __file__, "--memory-probe", json.dumps(probe)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    result = json.loads(out.strip().splitlines()[-1])
    shutil.rmtree(caches, ignore_errors=True)
    return Memory(result["before"], result["peak"])


def memory_probe(probe_json: str) -> None:
    """The child of :func:`peak_memory`: runs the variant once and prints its memory as JSON."""
    probe = json.loads(probe_json)
    fields = probe["inputs"]
    inputs = Inputs(**{**fields, "v1_path": Path(fields["v1_path"]), "v2_root": Path(fields["v2_root"])})
    pin_to_one_cpu(probe["cpu"])
    run = make_variant(probe["variant"], inputs, Path(probe["caches"]), load_pipeline("waymo"))
    gc.collect()
    before = _status_bytes("VmRSS")
    run()
    print(json.dumps({"before": before, "peak": _status_bytes("VmHWM")}))


@dataclass
class Timings:
    """Per-frame seconds of each round: the whole run and each stage."""

    total: list[float] = field(default_factory=list)
    stages: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))

    def median(self, stage: str | None = None) -> float:
        values = self.total if stage is None else self.stages.get(stage, [0.0])
        return float(np.median(values))

    def spread(self) -> str:
        """The fastest and slowest round's per-frame time, in milliseconds."""
        return f"{ms(min(self.total))}–{ms(max(self.total))}"


def run_rounds(variants: dict[str, Variant], rounds: int, frames: int) -> dict[str, Timings]:
    """Per-frame times of each variant over ``rounds`` rounds after one untimed warm-up round.

    The variants take turns within each round, so drift in the machine's speed affects all alike,
    and their order rotates from round to round, so none always follows the same one (the memory
    a variant leaves behind changes the next one's allocation costs).
    """
    for run in variants.values():
        run()
    names = list(variants)
    out = {name: Timings() for name in variants}
    for r in range(rounds):
        t0 = time.perf_counter()
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            gc.collect()
            seconds, stages = variants[name]()
            out[name].total.append(seconds / frames)
            for stage, s in stages.items():
                out[name].stages[stage].append(s / frames)
        print(f"round {r + 1}/{rounds}: {time.perf_counter() - t0:.1f} s", flush=True)
    return out


# --------------------------------------------------------------------------------------------
# Reporting


def report_frame(report: Report, frame: BenchFrame, inputs: Inputs, cache_bytes: int, render: str) -> None:
    raw = frame.raw
    jpeg = inputs.jpeg_bytes
    sizes = sorted({f"{c.width}x{c.height}" for c in raw.camera_calibrations}, reverse=True)
    rows = [
        [
            "camera images",
            f"{len(jpeg)} JPEGs ({', '.join(sizes)}), {sum(jpeg) / KIB:,.0f} KiB "
            f"({min(jpeg) / KIB:.0f}-{max(jpeg) / KIB:.0f} KiB each)",
        ],
    ]
    for name, counts in frame.returns.items():
        shape = "64x2650" if name == "TOP" else "x".join(map(str, SHORT_RANGE_SHAPE))
        rows.append([f"LiDAR {name} ({shape})", f"{counts['r1']:,} + {counts['r2']:,} returns (1st + 2nd)"])
    rows += [
        ["LiDAR points per frame", f"{frame.points:,}"],
        ["laser labels (boxes)", f"{len(raw.labels)}"],
        [
            "v1 record",
            f"{np.median(inputs.record_bytes) / MIB:.2f} MiB, of which JPEG {sum(jpeg) / MIB:.2f} MiB, "
            f"compressed range images and pixel poses {inputs.range_image_bytes / MIB:.2f} MiB",
        ],
        [
            "v2 Parquet per frame",
            f"{sum(p.stat().st_size for p in inputs.v2_root.rglob('*.parquet')) / inputs.frames / MIB:.2f} "
            f"MiB (all components; {v2.FRAMES_PER_ROW_GROUP} frames per row group, Snappy)",
        ],
        [
            "v2 LiDAR row group in memory",
            f"{inputs.lidar_row_group_bytes / MIB:,.0f} MiB (lidar + lidar_pose row group 0, "
            f"{min(v2.FRAMES_PER_ROW_GROUP, inputs.frames)} frames, decoded into Arrow)",
        ],
        ["cache (Arrow shard) per frame", f"{cache_bytes / inputs.frames / MIB:.2f} MiB"],
    ]
    report.table(
        "Benchmark frame",
        ["what", "value (per frame unless said)"],
        rows,
        f"One synthetic frame (seed 0) rendered at {render} (HxW), {frame.render_s:.1f} s, then made "
        f"Waymo-size: each image upscaled (bicubic) to its camera's Waymo size with Gaussian noise "
        f"(sigma {SENSOR_NOISE} grey levels) and stored as JPEG quality {JPEG_QUALITY}, intrinsics "
        "scaled to match; the rendered TOP range image (64 x 2650, explicit beam inclinations) given "
        f"per-column pixel poses, an elongation channel and second returns for "
        f"{SECOND_RETURN_FRACTION['TOP']:.0%} of its pixels; four short-range LiDARs (200 x 600, "
        "uniform inclinations -90° to +30°, mounted on the car's front, sides and rear with a yawed "
        f"extrinsic) with {SHORT_RANGE_RETURNS:,} ground returns each, "
        f"{SECOND_RETURN_FRACTION['short-range']:.0%} of them with a second return. No panoptic "
        "labels and no camera projections (real v1 records also carry camera-projection range images, "
        "which the reader skips, so real records are larger). The frame is repeated "
        f"{inputs.frames} times, 100 ms apart, into one v1 file (written with `v1.serialize_frame`, "
        "zlib level 6) and one v2 root (`v2.write_v2`).",
    )


def report_throughput(report: Report, t: dict[str, Timings], frames: int, rounds: int) -> None:
    def row(fmt: str, name: str, what: str, floor: str, goal: bool) -> list[str]:
        median = t[name].median()
        ratio = round_ratio(t[name].total, t[floor].total)
        verdict = f"≤ {FLOOR_RATIO_GOAL}: " + ("met" if ratio <= FLOOR_RATIO_GOAL else "missed")
        return [
            fmt,
            what,
            ms(median),
            t[name].spread(),
            f"{1 / median:.1f}",
            f"{ratio:.2f}",
            verdict if goal else "—",
        ]

    full_what = "full: WaymoSource -> convert -> Arrow batch -> shard write"
    tmpfs_what = "full, the cache on tmpfs (no disk)"
    v1_floor, v2_floor = "v1 floor", "v2 streamed floor"
    v1_what = "floor: file read + protobuf parse + zlib + MatrixFloat parse"
    v2_what = "floor: Parquet iter_batches, one frame's rows per batch"
    groups_what = "for comparison: Parquet read_row_group (10 frames at a time)"
    raw_floor = "v1 floor, no Adler-32"
    rows = [
        row("v1", "v1 floor", v1_what, v1_floor, False),
        row("v1", "v1 full", full_what, v1_floor, True),
        row("v1", "v1 full, tmpfs", tmpfs_what, v1_floor, True),
        row("v1", raw_floor, "floor without Adler-32 (raw inflate, as the reader inflates)", v1_floor, False),
        row("v1", "v1 full", "full, its time over the floor without Adler-32", raw_floor, False),
        row("v2", "v2 streamed floor", v2_what, v2_floor, False),
        row("v2", "v2 floor", groups_what, v2_floor, False),
        row("v2", "v2 full", full_what, v2_floor, True),
        row("v2", "v2 full, tmpfs", tmpfs_what, v2_floor, True),
    ]
    report.table(
        "Throughput on one core",
        ["format", "reader", "ms/frame", "min–max ms", "frames/s", "time / floor", "goal"],
        rows,
        f"Per-frame time of a pass over all {frames} frames of the segment, median (and range) of "
        f"{rounds} rounds after one warm-up round; the variants (these eight and the two instrumented "
        "runs below) take turns within each round, in an order rotated from round to round; time / floor "
        "is the median over rounds of each round's time over the floor's in the same round (this VM's "
        "speed drifts by tens of percent within minutes, and this cancels it). Input files are in the page "
        "cache. **v1 floor**: for each record (offsets from the headers, indexed beforehand), a plain "
        "`seek` + `read` of its payload (no CRC), `Frame.ParseFromString`, and for each laser "
        "`zlib.decompress` of its compressed return 1, return 2 and pixel-pose range images, each "
        "decompressed blob parsed with `MatrixFloat.ParseFromString` (the library reads the packed "
        "floats with `np.frombuffer` instead, which is cheaper). **v1 floor without Adler-32**: the same "
        "with the deflate data inflated raw (`decompressobj(-15)` after the 2-byte zlib header), as the "
        "reader inflates the range images of a record whose CRC-32C it checked: that CRC covers the "
        "compressed bytes, so recomputing zlib's Adler-32 of the output (a tenth of the reader's time "
        "with the system zlib) checks nothing more. The goal is judged against the floor as the issue "
        "defines it (`zlib.decompress`); the time over this one is the reader's own cost beyond "
        "the inflating it does. "
        "**v2 floor**: for each component file of the segment, `pq.ParquetFile` opened and its rows "
        "decoded with `iter_batches` in batches of one frame's rows (the calibrations in one batch), "
        "restricted to the columns the reader uses, into Arrow (nothing converted to numpy): the "
        "decoding the reader cannot avoid, with memory bounded to about a frame; the v2 goal is "
        "measured against it. For comparison, the same files and columns read a whole row group "
        "at a time (`read_row_group`), which allocates 10 frames of range images at once (see the "
        "LiDAR row group above and the memory table below). "
        "**full**: a new `WaymoSource(WaymoConfig(input=...))` (v1: both CRCs of every record "
        "checked), `load` of the segment and, per frame, `convert.frame`, `frame_to_batch` with the "
        "waymo pipeline's contents (`pipelines/waymo.yaml`: LiDAR, camera labels, no truth maps) and "
        "`ShardWriter.write` (which checksums the row as it writes it: CRC-32C of the whole file, of "
        "the row's metadata and of each column), then the shard's close (footer, fsync, rename), amortized "
        "over the frames; as `process_scene` does, without manifest and progress bar; the cache on "
        "the work folder's disk. Every variant runs with glibc's trim and mmap thresholds raised as "
        "`phigenesis-prep` raises them (`phigenesis/malloc_tuning.py`: freed memory is kept for the "
        "next frame instead of being taken again page by page) and transparent huge pages off for the "
        "process, as `phigenesis-prep` turns them off (a fresh 2 MiB page cost milliseconds on this VM). "
        "**full, the cache on tmpfs**: the "
        "same, the cache written to "
        "`/dev/shm` (memory): the reader's own work without the disk's write and fsync, which "
        "depend on the machine's storage (here a virtual disk, where fsync waits for the host).",
    )


def report_floor(report: Report, t: dict[str, Timings]) -> None:
    rows = []
    for fmt, stages in (
        ("v1", ("file read", "protobuf Frame parse", "zlib.decompress", "MatrixFloat parse")),
        ("v2", tuple(sorted(t["v2 streamed floor"].stages))),
    ):
        floor = t["v1 floor" if fmt == "v1" else "v2 streamed floor"]
        total = floor.median()
        for stage in stages:
            s = floor.median(stage)
            rows.append([fmt, stage, ms(s), f"{100 * s / total:.0f}%"])
        rows.append([fmt, "whole floor", ms(total), "100%"])
    report.table(
        "Floor, by step",
        ["format", "step (v2: component file)", "ms/frame", "share"],
        rows,
        "Medians of the per-round step times of the floor runs above (v2: the streamed floor, per "
        "component file, the calibrations amortized over the frames).",
    )


#: (label, v1 stage, v2 stage, inner stages to subtract) of the breakdown table.
_BREAKDOWN = (
    ("scene setup (index, calibrations, writer), amortized", "scene setup", "scene setup", ()),
    ("v1: read record + CRC check", "read + CRC", None, ()),
    ("v1: protobuf parse, fields -> raw records", "parse", None, ("range images: zlib + decode",)),
    ("v1: range images zlib + decode", "range images: zlib + decode", None, ()),
    ("v2: Parquet decode, a frame's rows at a time", None, "Parquet batches", ()),
    ("v2: Arrow -> raw records", None, "read", ("Parquet batches",)),
    ("range images -> points", "range images -> points", "range images -> points", ()),
    ("convert rest (cameras, boxes)", "convert", "convert", ("range images -> points",)),
    ("Arrow batch (frame_to_batch)", "Arrow batch", "Arrow batch", ()),
    ("shard write (IPC, CRC-32Cs of the file and the row)", "shard write", "shard write", ()),
    ("shard finish (footer, fsync, rename), amortized", "shard finish", "shard finish", ()),
)


def report_breakdown(report: Report, t: dict[str, Timings]) -> None:
    v1_t, v2_t = t["v1 stages"], t["v2 stages"]
    sums = {"v1": 0.0, "v2": 0.0}
    rows = []
    for label, s1, s2, inner in _BREAKDOWN:
        row = [label]
        for fmt, timings, stage in (("v1", v1_t, s1), ("v2", v2_t, s2)):
            if stage is None:
                row += ["—", "—"]
                continue
            per_round = np.array(timings.stages[stage]) - sum(np.array(timings.stages[i]) for i in inner)
            s = float(np.median(per_round))
            sums[fmt] += s
            row += [ms(s), f"{100 * s / timings.median():.0f}%"]
        rows.append(row)
    rows.append(
        ["sum of the stages", ms(sums["v1"]), "", ms(sums["v2"]), ""],
    )
    rows.append(
        [
            "instrumented run, whole",
            ms(v1_t.median()),
            "100%",
            ms(v2_t.median()),
            "100%",
        ]
    )
    rows.append(
        ["full run (uninstrumented, above)", ms(t["v1 full"].median()), "", ms(t["v2 full"].median()), ""]
    )
    report.table(
        "Where the time goes (full readers, by stage)",
        ["stage", "v1 ms/frame", "v1 share", "v2 ms/frame", "v2 share"],
        rows,
        "The full path run stage by stage (the library's own functions, called as `WaymoSource` and "
        "`process_scene` call them; nested stages are timed by wrapping `v1._matrix`, "
        "`convert.lidar_sweep` and `v2._RowStream.take` for the run, and subtracted from "
        "the stage that contains them). Medians per stage over the rounds, so the sum need not equal "
        "the whole. Shares are of the instrumented run's whole time.",
    )


# --------------------------------------------------------------------------------------------


def report_memory(report: Report, memory: dict[str, Memory]) -> None:
    what = {
        "v2 full": "v2 full reader (WaymoSource -> ... -> shard write)",
        "v2 streamed floor": "v2 streamed floor (iter_batches, a frame's rows per batch)",
        "v2 floor": "v2 read_row_group (10 frames at a time)",
        "v1 full": "v1 full reader (for comparison)",
    }
    rows = [
        [what[name], f"{m.peak / MIB:,.0f}", f"{m.pass_peak / MIB:,.0f}", f"{m.before / MIB:,.0f}"]
        for name, m in memory.items()
    ]
    report.table(
        "Peak memory (each in a fresh process)",
        ["variant", "peak RSS MiB", "pass above start MiB", "RSS at start MiB"],
        rows,
        "Each variant's pass over the segment (as timed above) run once in a fresh Python process "
        "(this script with `--memory-probe`, pinned to the same CPU): the process's peak resident "
        "memory (`VmHWM`), and how far the pass raised it above the resident memory it started "
        "with (the interpreter, numpy, pyarrow, OpenCV and the benchmark's imports, the inputs "
        "indexed). It includes what pyarrow's allocator keeps for reuse.",
    )


def _tmpfs() -> str | None:
    """A memory-backed folder for the ``tmpfs`` variants (``/dev/shm`` where it exists; else the
    system's temporary folder, which may be a disk: then those rows measure the disk too)."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def _malloc_setting() -> str:
    pages = (
        "transparent huge pages off"
        if huge_pages_disabled()
        else "transparent huge pages as the system sets them"
    )
    if os.environ.get("MALLOC_TRIM_THRESHOLD_") is None:
        return f"the C library's defaults; {pages}"
    return (
        f"glibc trim threshold {int(os.environ['MALLOC_TRIM_THRESHOLD_']) >> 20} MiB, mmap threshold "
        f"{int(os.environ['MALLOC_MMAP_THRESHOLD_']) >> 20} MiB; {pages} (as phigenesis-prep sets them)"
    )


def _size(text: str) -> tuple[int, int]:
    h, _, w = text.lower().partition("x")
    return int(h), int(w)


def main(argv: Sequence[str] | None = None) -> None:
    """Builds the inputs, measures the variants on one core, prints the tables, updates BENCHMARKS.md."""
    t_start = time.perf_counter()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, help="frames of the benchmark segment (default 20)")
    parser.add_argument("--rounds", type=int, help="timed rounds after the warm-up round (default 7)")
    parser.add_argument(
        "--render-size",
        type=_size,
        help="HxW the synthetic frame is rendered at before upscaling (default 640x960)",
    )
    parser.add_argument("--cpu", type=int, help="the CPU to pin to (default: the last one allowed)")
    parser.add_argument(
        "--workdir", type=Path, help="where the inputs and caches go (default: a temporary dir)"
    )
    parser.add_argument("--quick", action="store_true", help="small numbers, for a smoke test (< 1 min)")
    parser.add_argument("--memory-probe", help=argparse.SUPPRESS)  # internal: see peak_memory
    add_update_flag(parser)
    args = parser.parse_args(argv)
    keep_freed_memory()  # as phigenesis-prep does, for every variant alike
    avoid_huge_page_faults()
    if args.memory_probe:
        memory_probe(args.memory_probe)
        return
    frames = args.frames if args.frames is not None else (3 if args.quick else 20)
    rounds = args.rounds if args.rounds is not None else (2 if args.quick else 7)
    render_h, render_w = args.render_size or ((320, 480) if args.quick else (640, 960))
    if frames < 2 or rounds < 1:
        parser.error("need --frames >= 2 and --rounds >= 1")

    report = Report(
        "waymo",
        "Waymo: reading v1 and v2 frames into the cache",
        "Written by `benchmarks/waymo.py`."
        + (" **Smoke test (`--quick`): numbers are not representative.**" if args.quick else ""),
    )
    spec = load_pipeline("waymo")
    with contextlib.ExitStack() as stack:
        if args.workdir is None:
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="phigenesis-bench-waymo-")))
        else:
            workdir = args.workdir
            workdir.mkdir(parents=True, exist_ok=True)
            for sub in ("v1", "v2", "caches"):
                shutil.rmtree(workdir / sub, ignore_errors=True)
        print(f"rendering the benchmark frame at {render_h}x{render_w} ...", flush=True)
        frame = build_frame(render_h, render_w)
        inputs = write_inputs(frame, frames, workdir)
        check_inputs(inputs, frame)
        setup_s = time.perf_counter() - t_start
        pinned = pin_to_one_cpu(args.cpu)
        print(f"inputs ready in {setup_s:.1f} s; {pinned}", flush=True)

        caches = workdir / "caches"
        probe = caches / "probe"
        write_scene(WaymoSource(WaymoConfig(input=str(inputs.v1_path))), probe, spec)
        cache_bytes = sum(p.stat().st_size for p in (probe / SHARDS_DIR).glob("*.arrow"))
        shutil.rmtree(probe)

        memory_caches = Path(stack.enter_context(tempfile.TemporaryDirectory(dir=_tmpfs())))
        variants = {name: make_variant(name, inputs, caches, spec, memory_caches) for name in VARIANTS}
        timings = run_rounds(variants, rounds, frames)
        cpu = pinned_cpu(pinned)
        memory = {name: peak_memory(name, inputs, caches / "memory", cpu) for name in MEMORY_PROBES}

        report.table(
            "Setup",
            ["what", "value"],
            [
                ["one core", pinned],
                ["frames per segment", f"{frames}"],
                ["timed rounds", f"{rounds}"],
                ["malloc", _malloc_setting()],
            ],
        )
        report_frame(report, frame, inputs, cache_bytes, f"{render_h}x{render_w}")
        report_throughput(report, timings, frames, rounds)
        report_floor(report, timings)
        report_breakdown(report, timings)
        report_memory(report, memory)
    total_s = time.perf_counter() - t_start
    report.parts.append(
        f"The run took {total_s:.0f} s ({setup_s:.0f} s of it rendering the frame and writing the inputs)."
    )
    print(report.parts[-1])
    report.write(update=args.update)


if __name__ == "__main__":
    main()
