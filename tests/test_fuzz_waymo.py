"""Fuzzing the Waymo v1 reader: mutated records either convert to a cache of finite values or fail
with an input error that names the file; never another exception, a hang or a huge allocation.

The records are a tiny synthetic segment written as Waymo v1 (``waymo_export.raw_frame``), decoded
with the reader's own protobuf messages, mutated field by field (NaN, Inf, huge and negative
numbers, truncated, zeroed or foreign bytes, wrong lengths, repeated or missing messages,
mutated range images and zlib bombs), re-encoded and written with correct TFRecord CRCs, so the
parser sees every mutation (a flipped byte alone is caught by the CRC). The cases run in one
child process whose address space is limited to its baseline + 2 GiB (``RLIMIT_AS``), each under
a time limit, through ``pipeline.process_scene`` (what ``prepare`` runs per scene) into a small
cache with no stages; the parent checks the child's report.

Run the child by hand to see every case: ``python -m tests.test_fuzz_waymo OUT_DIR [SEED] [CASES]``.
"""

from __future__ import annotations

import copy
import json
import os
import resource
import signal
import subprocess
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

SEED = 20260214
RANDOM_CASES = 120
#: Seconds one case may take (a tiny segment converts in well under one).
CASE_SECONDS = 20
#: Extra address space each case may allocate beyond the child's baseline, bytes.
ALLOCATION_LIMIT = 2 << 30
REPO = Path(__file__).resolve().parents[1]

Mutation = Callable[[Any, np.random.Generator, list[Any]], str]

# --------------------------------------------------------------------------------------------
# Values and helpers


#: Hostile values for floating-point fields (huge, negative, not finite).
BAD_FLOATS = (float("nan"), float("inf"), float("-inf"), 1e300, -1e300, 1e18, -1e18, 0.0, -1.0, 3.4e38)
#: Hostile values for integer fields.
BAD_INTS = (0, -1, 1, 2**31 - 1, -(2**31), 65535, 65536, 99)
BAD_INT64 = (0, -1, -(2**63), 2**63 - 1, 2**62, 10**18)


def _pick(rng: np.random.Generator, values: Any) -> Any:
    return values[int(rng.integers(len(values)))]


def _set(msg: Any, field: str, values: Any, rng: np.random.Generator) -> str:
    """Sets a scalar field to a hostile value (one the field's type can hold)."""
    value = _pick(rng, values)
    try:
        setattr(msg, field, value)
    except (ValueError, TypeError, OverflowError):
        setattr(msg, field, type(getattr(msg, field))(0))
        value = 0
    return f"{field}={value!r}"


def _bad_bytes(data: bytes, rng: np.random.Generator, others: list[bytes]) -> tuple[bytes, str]:
    """A hostile version of a bytes field: cut, zeroed, emptied, random, another field's bytes."""
    kind = _pick(rng, ("truncate", "zero", "empty", "random", "other", "flip_header"))
    if kind == "truncate":
        cut = int(rng.integers(0, max(len(data), 1)))
        return data[:cut], f"truncated to {cut} of {len(data)} bytes"
    if kind == "zero":
        return bytes(len(data)), f"{len(data)} zero bytes"
    if kind == "empty":
        return b"", "emptied"
    if kind == "random":
        n = int(rng.integers(1, 64))
        return rng.bytes(n), f"{n} random bytes"
    if kind == "other" and others:
        return _pick(rng, others), "another field's bytes"
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        if out:
            out[int(rng.integers(0, min(len(out), 64)))] ^= 1 << int(rng.integers(8))
    return bytes(out), "header bytes flipped"


def zlib_bomb(mib: int) -> bytes:
    """A valid zlib stream of ``mib`` MiB of zero bytes, about 1 KB per MiB: one compressed 1 MiB
    block (full flush: it refers to nothing before it) repeated, a final empty block, and the
    Adler-32 of n zero bytes, which is ((n mod 65521) << 16) | 1."""
    compressor = zlib.compressobj(9)
    chunk = compressor.compress(bytes(1 << 20)) + compressor.flush(zlib.Z_FULL_FLUSH)
    header, block = chunk[:2], chunk[2:]
    n = mib << 20
    adler = ((n % 65521) << 16) | 1
    return header + block * mib + b"\x03\x00" + adler.to_bytes(4, "big")


# --------------------------------------------------------------------------------------------
# Mutations: each changes one part of a decoded Frame and says what it did


def _transform_mutation(transform: Any, rng: np.random.Generator, what: str) -> str:
    values = list(transform.transform)
    kind = _pick(rng, ("entry", "scale", "length", "mirror"))
    if kind == "entry" and values:
        i = int(rng.integers(len(values)))
        values[i] = _pick(rng, BAD_FLOATS)
        desc = f"{what}[{i}]={values[i]!r}"
    elif kind == "scale" and len(values) == 16:
        for i in (0, 1, 2, 4, 5, 6, 8, 9, 10):
            values[i] *= 1e6
        desc = f"{what} rotation scaled by 1e6"
    elif kind == "mirror" and len(values) == 16:
        for i in (0, 4, 8):
            values[i] = -values[i]
        desc = f"{what} mirrored"
    else:
        values = values[: int(rng.integers(0, 16))] if rng.random() < 0.5 else [*values, 1.0]
        desc = f"{what} has {len(values)} values"
    del transform.transform[:]
    transform.transform.extend(values)
    return desc


def m_frame_pose(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    return _transform_mutation(f.pose, rng, "Frame.pose")


def m_frame_time(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    kind = _pick(rng, ("value", "copy_other", "before_other", "clear"))
    if kind == "value":
        return _set(f, "timestamp_micros", BAD_INT64, rng)
    if kind == "clear":
        f.ClearField("timestamp_micros")
        return "timestamp_micros removed"
    other = others[0].timestamp_micros
    f.timestamp_micros = other if kind == "copy_other" else other - 100_000
    return f"timestamp_micros {kind} ({f.timestamp_micros})"


def m_image_scalar(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    im = _pick(rng, f.images)
    field = _pick(rng, ("pose_timestamp", "shutter", "camera_trigger_time", "camera_readout_done_time"))
    return f"image {im.name} " + _set(im, field, BAD_FLOATS, rng)


def m_image_velocity(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    im = _pick(rng, f.images)
    field = _pick(rng, ("v_x", "v_y", "v_z", "w_x", "w_y", "w_z"))
    return f"image {im.name} velocity " + _set(im.velocity, field, BAD_FLOATS, rng)


def m_image_pose(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    im = _pick(rng, f.images)
    return _transform_mutation(im.pose, rng, f"image {im.name} pose")


def m_image_bytes(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    im = _pick(rng, f.images)
    data, desc = _bad_bytes(im.image, rng, [o.image for o in f.images if o.name != im.name])
    im.image = data
    return f"image {im.name} JPEG {desc}"


def m_panoptic(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    im = _pick(rng, f.images)
    seg = im.camera_segmentation_label
    kind = _pick(rng, ("bytes", "divisor", "local", "global", "repeat"))
    if kind == "bytes":
        data, desc = _bad_bytes(seg.panoptic_label, rng, [im.image])
        seg.panoptic_label = data
        return f"image {im.name} panoptic label {desc}"
    if kind == "divisor":
        return f"image {im.name} panoptic " + _set(seg, "panoptic_label_divisor", BAD_INTS, rng)
    mapping = seg.instance_id_to_global_id_mapping
    entry = mapping.add() if kind == "repeat" or not len(mapping) else _pick(rng, mapping)
    if kind == "repeat" and len(mapping) > 1:
        entry.CopyFrom(mapping[0])
        entry.global_instance_id += 1
        return f"image {im.name} panoptic mapping repeats local id {entry.local_instance_id}"
    field = "local_instance_id" if kind == "local" else "global_instance_id"
    return f"image {im.name} panoptic mapping " + _set(entry, field, BAD_INTS, rng)


def m_camera_calibration(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    c = _pick(rng, f.context.camera_calibrations)
    kind = _pick(rng, ("intrinsic", "intrinsic_length", "size", "extrinsic", "name", "shutter"))
    if kind == "intrinsic":
        i = int(rng.integers(len(c.intrinsic)))
        c.intrinsic[i] = _pick(rng, BAD_FLOATS)
        return f"camera {c.name} intrinsic[{i}]={c.intrinsic[i]!r}"
    if kind == "intrinsic_length":
        n = int(rng.integers(0, 12))
        values = (list(c.intrinsic) * 2)[:n]
        del c.intrinsic[:]
        c.intrinsic.extend(values)
        return f"camera {c.name} has {n} intrinsics"
    if kind == "size":
        return f"camera {c.name} " + _set(c, _pick(rng, ("width", "height")), BAD_INTS, rng)
    if kind == "extrinsic":
        return _transform_mutation(c.extrinsic, rng, f"camera {c.name} extrinsic")
    if kind == "name":
        return f"camera calibration {c.name} " + _set(c, "name", BAD_INTS, rng)
    return f"camera {c.name} " + _set(c, "rolling_shutter_direction", BAD_INTS, rng)


def m_laser_calibration(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    c = _pick(rng, f.context.laser_calibrations)
    kind = _pick(rng, ("inclination", "inclination_length", "min_max", "extrinsic", "name"))
    if kind == "inclination" and len(c.beam_inclinations):
        i = int(rng.integers(len(c.beam_inclinations)))
        c.beam_inclinations[i] = _pick(rng, BAD_FLOATS)
        return f"LiDAR {c.name} beam_inclinations[{i}]={c.beam_inclinations[i]!r}"
    if kind == "inclination_length":
        values = list(c.beam_inclinations)[: int(rng.integers(0, max(len(c.beam_inclinations), 1)))]
        del c.beam_inclinations[:]
        c.beam_inclinations.extend(values)
        return f"LiDAR {c.name} has {len(values)} beam inclinations"
    if kind == "extrinsic":
        return _transform_mutation(c.extrinsic, rng, f"LiDAR {c.name} extrinsic")
    if kind == "name":
        return f"LiDAR calibration {c.name} " + _set(c, "name", BAD_INTS, rng)
    del c.beam_inclinations[:]
    field = _pick(rng, ("beam_inclination_min", "beam_inclination_max"))
    return f"LiDAR {c.name} uniform inclinations, " + _set(c, field, BAD_FLOATS, rng)


def _decode(compressed: bytes) -> Any:
    from phigenesis.data.sources.waymo import protos

    matrix = protos.MatrixFloat()
    matrix.ParseFromString(zlib.decompress(compressed))
    return matrix


def m_range_values(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    laser = _pick(rng, f.lasers)
    image = laser.ri_return1
    field = _pick(rng, ("range_image_compressed", "range_image_pose_compressed"))
    compressed = getattr(image, field)
    if not compressed:
        return "nothing (laser without that range image)"
    matrix = _decode(compressed)
    values = np.array(matrix.data, np.float32)
    channels = int(matrix.shape.dims[-1])
    n = int(rng.integers(1, 200))
    pixels = rng.integers(0, len(values) // channels, n)
    channel = int(rng.integers(channels))
    value = _pick(rng, (np.nan, np.inf, -np.inf, 1e30, -5.0, 3.4e38))
    values[pixels * channels + channel] = value
    del matrix.data[:]
    matrix.data.extend(values.tolist())
    setattr(image, field, zlib.compress(matrix.SerializeToString()))
    return f"LiDAR {laser.name} {field} channel {channel} = {value} at {n} pixels"


def m_range_shape(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    laser = _pick(rng, f.lasers)
    image = _pick(rng, (laser.ri_return1, laser.ri_return2))
    if not image.range_image_compressed:
        return "nothing (laser without range image)"
    matrix = _decode(image.range_image_compressed)
    dims = list(matrix.shape.dims)
    kind = _pick(rng, ("swap", "grow", "negative", "drop", "extra", "huge"))
    if kind == "swap":
        dims = [dims[1], dims[0], dims[2]]
    elif kind == "grow":
        dims[0] *= 2
    elif kind == "negative":
        dims[0] = -dims[0]
    elif kind == "drop":
        dims = dims[:2]
    elif kind == "extra":
        dims = [*dims, 1]
    else:
        dims = [2**31 - 1, 2**31 - 1, 4]
    del matrix.shape.dims[:]
    matrix.shape.dims.extend(dims)
    image.range_image_compressed = zlib.compress(matrix.SerializeToString())
    return f"LiDAR {laser.name} range image shape {dims}"


def m_range_bytes(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    laser = _pick(rng, f.lasers)
    image = laser.ri_return1
    field = _pick(rng, ("range_image_compressed", "range_image_pose_compressed"))
    kind = _pick(rng, ("bytes", "bomb", "declared"))
    if kind == "bomb":
        setattr(image, field, zlib_bomb(int(rng.integers(64, 512))))
        return f"LiDAR {laser.name} {field} is a zlib bomb"
    if kind == "declared":  # a MatrixFloat whose data field declares 2 GiB, then ends
        setattr(image, field, zlib.compress(b"\x0a\x80\x80\x80\x80\x08" + bytes(64)))
        return f"LiDAR {laser.name} {field} declares 2 GiB of data"
    data, desc = _bad_bytes(getattr(image, field), rng, [image.range_image_compressed])
    setattr(image, field, data)
    return f"LiDAR {laser.name} {field} {desc}"


def m_label(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    if not len(f.laser_labels):
        return "nothing (no labels)"
    label = _pick(rng, f.laser_labels)
    kind = _pick(rng, ("box", "metadata", "type", "id", "points"))
    if kind == "box":
        field = _pick(rng, ("center_x", "center_y", "center_z", "width", "length", "height", "heading"))
        return f"label {label.id} box " + _set(label.box, field, BAD_FLOATS, rng)
    if kind == "metadata":
        field = _pick(rng, ("speed_x", "speed_y", "speed_z", "accel_x", "accel_y", "accel_z"))
        return f"label {label.id} " + _set(label.metadata, field, BAD_FLOATS, rng)
    if kind == "type":
        return f"label {label.id} " + _set(label, "type", BAD_INTS, rng)
    if kind == "id":
        label.id = _pick(rng, ("", f.laser_labels[0].id, "\u00e9" * 300))
        return f"label id set to {label.id[:12]!r}"
    return f"label {label.id} " + _set(label, "num_lidar_points_in_box", BAD_INTS, rng)


def m_messages(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    """Repeats or removes whole messages."""
    fields = ("images", "lasers", "laser_labels", "context.camera_calibrations", "context.laser_calibrations")
    path = _pick(rng, fields)
    owner = f.context if path.startswith("context.") else f
    repeated = getattr(owner, path.split(".")[-1])
    if not len(repeated):
        return f"nothing ({path} is empty)"
    kind = _pick(rng, ("repeat", "remove", "clear"))
    if kind == "repeat":
        repeated.add().CopyFrom(_pick(rng, repeated))
        return f"{path}: one repeated"
    if kind == "remove":
        del repeated[int(rng.integers(len(repeated)))]
        return f"{path}: one removed"
    del repeated[:]
    return f"{path}: all removed"


def m_top_level(f: Any, rng: np.random.Generator, others: list[Any]) -> str:
    field = _pick(rng, ("pose", "context", "timestamp_micros"))
    f.ClearField(field)
    return f"Frame.{field} removed"


MUTATIONS: tuple[Mutation, ...] = (
    m_frame_pose,
    m_frame_time,
    m_image_scalar,
    m_image_velocity,
    m_image_pose,
    m_image_bytes,
    m_panoptic,
    m_camera_calibration,
    m_laser_calibration,
    m_range_values,
    m_range_shape,
    m_range_bytes,
    m_label,
    m_messages,
    m_top_level,
)


def _serialized_mutation(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """Mutations of the serialized record itself (re-framed with correct CRCs)."""
    kind = _pick(rng, ("truncate", "garbage", "unknown_field"))
    if kind == "truncate":
        cut = int(rng.integers(0, len(data)))
        return data[:cut], f"record cut to {cut} of {len(data)} bytes"
    if kind == "garbage":
        return data + rng.bytes(int(rng.integers(1, 32))), "random bytes appended to the record"
    return data + b"\xfa\x3e\x05hello", "unknown length-delimited field appended"


# --------------------------------------------------------------------------------------------
# The child: build the base records, run every case, write the report


def _base_records() -> list[bytes]:
    """Two frames of a tiny synthetic segment as serialized v1 Frames."""
    from phigenesis.data.sources.synthetic import SyntheticScene
    from phigenesis.data.sources.synthetic.waymo_export import raw_frame
    from phigenesis.data.sources.waymo import v1
    from tests.conftest import tiny_config

    config = tiny_config(scenes=1, frames=2, height=24, width=36)
    scene = SyntheticScene(config, 0)
    return [v1.serialize_frame(raw_frame(scene, k)) for k in range(config.frames)]


def _named_cases() -> list[Callable[[list[Any]], str]]:
    """The cases the issue reports, each once, before the random ones."""

    def panoptic_huge_id(frames: list[Any]) -> str:
        entry = frames[1].images[0].camera_segmentation_label.instance_id_to_global_id_mapping.add()
        entry.local_instance_id, entry.global_instance_id = 2**31 - 1, 3
        return "panoptic local_instance_id 2^31-1 (a 16 GiB lookup table before the fix)"

    def bomb(frames: list[Any]) -> str:
        frames[1].lasers[0].ri_return1.range_image_compressed = zlib_bomb(3 << 10)
        return "range image zlib bomb: 3 GiB from 3 MB"

    def nan_pose(frames: list[Any]) -> str:
        frames[1].pose.transform[3] = float("nan")
        return "NaN frame pose"

    def scaled_pose(frames: list[Any]) -> str:
        for i in (0, 1, 2, 4, 5, 6, 8, 9, 10):
            frames[1].pose.transform[i] *= 1e6
        return "frame pose scaled by 1e6"

    def camera_time(frames: list[Any]) -> str:
        frames[1].images[2].pose_timestamp = 1e18
        return "camera pose_timestamp 1e18"

    def duplicate_time(frames: list[Any]) -> str:
        frames[1].timestamp_micros = frames[0].timestamp_micros
        return "duplicate frame time"

    def nan_size(frames: list[Any]) -> str:
        frames[1].laser_labels[0].box.width = float("nan")
        return "NaN box width"

    def other_jpeg(frames: list[Any]) -> str:
        import cv2

        frames[1].images[0].image = cv2.imencode(".jpg", np.zeros((30, 40, 3), np.uint8))[1].tobytes()
        return "a 40 x 30 JPEG for a camera calibrated at 36 x 24"

    return [panoptic_huge_id, bomb, nan_pose, scaled_pose, camera_time, duplicate_time, nan_size, other_jpeg]


def _case_file(base: list[bytes], case: int, seed: int, folder: Path) -> tuple[Path, str]:
    """Writes case ``case``'s TFRecord file; returns it and what was mutated."""
    from phigenesis.data.sources.waymo import protos, tfrecord

    frames = []
    for data in base:
        f = protos.Frame()
        f.ParseFromString(data)
        frames.append(f)
    named = _named_cases()
    rng = np.random.default_rng([seed, case])
    serialized_note = ""
    if case < len(named):
        what = named[case](frames)
        records = [f.SerializeToString() for f in frames]
    else:
        target = int(rng.integers(len(frames))) if rng.random() < 0.3 else len(frames) - 1
        others = [f for i, f in enumerate(frames) if i != target]
        mutations = [_pick(rng, MUTATIONS) for _ in range(1 + int(rng.random() < 0.25))]
        what = "; ".join(f"record {target}: {m(frames[target], rng, others)}" for m in mutations)
        records = [f.SerializeToString() for f in frames]
        if rng.random() < 0.08:
            records[target], serialized_note = _serialized_mutation(records[target], rng)
            what += f"; record {target}: {serialized_note}"
        elif rng.random() < 0.05:
            records.append(copy.copy(records[-1]))
            what += "; the last record repeated"
    path = folder / f"case{case:03d}" / f"segment-fuzz{case:03d}_with_camera_labels.tfrecord"
    path.parent.mkdir(parents=True, exist_ok=True)
    tfrecord.write_records(path, records)
    return path, what


class CaseTimeout(BaseException):
    """Raised by the alarm in a case that runs too long (a BaseException: nothing swallows it)."""


def _on_alarm(signum: int, frame: Any) -> None:
    raise CaseTimeout


def _spec() -> dict[str, Any]:
    """A pipeline with no stages that stores everything a Waymo frame has."""
    from phigenesis.data.pipeline import PipelineSpec
    from phigenesis.data.schema import CacheContents

    contents = CacheContents(camera_truth=(), lidar=True, lidar_truth=False, camera_labels=True)
    return PipelineSpec("fuzz", "waymo", {}, (), contents).to_dict()


def _run_case(path: Path, mode: str, spec: dict[str, Any]) -> dict[str, Any]:
    """Converts one file with ``process_scene``: the result, and the non-finite values of the
    shards it wrote."""
    import pyarrow as pa

    from phigenesis.data.pipeline import SceneTask, process_scene
    from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource
    from tests.cache_checks import non_finite_in_batch

    source = WaymoSource(WaymoConfig(input=str(path), on_error=mode))  # type: ignore[arg-type]
    (scene_id,) = source.scene_ids()
    cache = path.parent / f"cache-{mode}"
    result = process_scene(SceneTask(str(cache), "waymo", source.arguments(), spec, scene_id))
    problems = []
    for shard in result.shards:
        with pa.memory_map(str(cache / shard.path)) as mm:
            reader = pa.ipc.open_file(mm)
            for row in range(reader.num_record_batches):
                problems += [f"row {row} {p}" for p in non_finite_in_batch(reader.get_batch(row))]
    return {
        "error": result.error,
        "error_is_input": result.error_is_input,
        "frames": result.frames,
        "dropped": dict(getattr(result, "dropped", {}) or {}),
        "non_finite": problems,
    }


def _address_space_bytes() -> int:
    """This process's virtual memory size (VmSize), bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status")


def run_cases(out: Path, seed: int, random_cases: int) -> dict[str, Any]:
    """Runs the named and ``random_cases`` random cases; returns the report."""
    import cv2
    import pyarrow as pa

    cv2.setNumThreads(1)
    pa.set_cpu_count(1)
    pa.set_io_thread_count(1)
    base = _base_records()
    spec = _spec()
    # One clean conversion first, so every lazily started pool and cache exists before the limit.
    from phigenesis.data.sources.waymo import tfrecord

    clean = out / "warmup" / "segment-clean_with_camera_labels.tfrecord"
    clean.parent.mkdir(parents=True)
    tfrecord.write_records(clean, base)
    warm = _run_case(clean, "raise", spec)
    baseline = _address_space_bytes()
    limit = baseline + ALLOCATION_LIMIT + (256 << 20)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    signal.signal(signal.SIGALRM, _on_alarm)
    cases = []
    for case in range(len(_named_cases()) + random_cases):
        path, what = _case_file(base, case, seed, out)
        for mode in ("raise", "skip") if case < len(_named_cases()) else (("raise", "skip")[case % 2],):
            t0 = time.perf_counter()
            signal.alarm(CASE_SECONDS)
            try:
                outcome = _run_case(path, mode, spec)
            except CaseTimeout:
                outcome = {"timeout": True}
            except BaseException as e:  # an exception that escaped process_scene
                outcome = {"escaped": f"{type(e).__name__}: {e}"}
            finally:
                signal.alarm(0)
            cases.append(
                {"case": case, "mode": mode, "mutation": what, "path": str(path)}
                | outcome
                | {"seconds": round(time.perf_counter() - t0, 3)}
            )
    return {"warmup": warm, "baseline_bytes": baseline, "limit_bytes": limit, "cases": cases}


def main(argv: list[str]) -> int:
    out = Path(argv[0])
    seed = int(argv[1]) if len(argv) > 1 else SEED
    random_cases = int(argv[2]) if len(argv) > 2 else RANDOM_CASES
    report = run_cases(out, seed, random_cases)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return 0


# --------------------------------------------------------------------------------------------
# The test


def _verdict(case: dict[str, Any]) -> str | None:
    """What is wrong with one case's outcome, or None if it is acceptable."""
    if case.get("timeout"):
        return f"ran longer than {CASE_SECONDS} s"
    if "escaped" in case:
        return f"an exception escaped process_scene: {case['escaped']}"
    if case["error"] is None:
        return f"the cache holds non-finite values: {case['non_finite'][:3]}" if case["non_finite"] else None
    if not case["error_is_input"]:
        return f"failed with a toolkit error, not an input error: {case['error']}"
    if case["path"] not in case["error"]:
        return f"the error does not name the file: {case['error']}"
    return None


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("fuzz_waymo")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MALLOC_ARENA_MAX": "2"}
    budget = 60 + (len(_named_cases()) * 2 + RANDOM_CASES) * CASE_SECONDS // 10
    done = subprocess.run(
        [sys.executable, "-m", "tests.test_fuzz_waymo", str(out), str(SEED), str(RANDOM_CASES)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=budget,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return json.loads((out / "report.json").read_text())


def test_every_mutated_record_converts_to_finite_values_or_fails_naming_the_file(
    report: dict[str, Any],
) -> None:
    cases = report["cases"]
    assert len({c["case"] for c in cases}) >= 100
    bad = [f"case {c['case']} ({c['mode']}; {c['mutation']}): {v}" for c in cases if (v := _verdict(c))]
    assert not bad, "\n".join(bad)


def test_the_mutations_reach_the_parser_and_both_outcomes_occur(report: dict[str, Any]) -> None:
    assert report["warmup"]["error"] is None and report["warmup"]["frames"] == 2
    cases = report["cases"]
    failed = [c for c in cases if c.get("error")]
    converted = [c for c in cases if c.get("error") is None and "timeout" not in c and "escaped" not in c]
    assert len(failed) >= 20 and len(converted) >= 20, (len(failed), len(converted))
    # Under skip, some invalid parts were left out and counted rather than failing the scene.
    assert any(c["dropped"] for c in converted if c["mode"] == "skip")


#: Named case -> (frames converted under skip, what skip counts as left out); under raise each
#: fails as an input error, except the panoptic id, which maps no pixel and converts.
NAMED_UNDER_SKIP: dict[int, tuple[int, str | None]] = {
    0: (2, None),
    1: (2, "LiDAR range images left out as invalid"),
    2: (1, "frames left out as invalid records"),
    3: (1, "frames left out as invalid records"),
    4: (2, "camera images left out as invalid"),
    5: (1, "frames left out as invalid records"),
    6: (2, "boxes with invalid fields"),
    7: (2, "camera images left out as invalid"),
}


def test_the_issues_cases_fail_under_raise_and_lose_only_their_part_under_skip(
    report: dict[str, Any],
) -> None:
    by_case = {(c["case"], c["mode"]): c for c in report["cases"]}
    assert len(NAMED_UNDER_SKIP) == len(_named_cases())
    for case, (frames, kind) in NAMED_UNDER_SKIP.items():
        stop, skip = by_case[(case, "raise")], by_case[(case, "skip")]
        if kind is None:
            assert stop["error"] is None and stop["frames"] == 2, stop
        else:
            assert stop["error"] is not None and stop["error_is_input"], stop
            assert stop["path"] in stop["error"], stop
        assert skip["error"] is None and skip["frames"] == frames, skip
        assert (kind is None) == (not skip["dropped"]), skip
        if kind is not None:
            assert skip["dropped"].get(kind) == 1, skip


def test_the_zlib_bomb_is_three_gibibytes_from_three_megabytes() -> None:
    bomb = zlib_bomb(3 << 10)
    assert len(bomb) < 4 << 20
    inflater = zlib.decompressobj()
    assert inflater.decompress(bomb, 1 << 20) == bytes(1 << 20)  # a valid stream of zeros


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
