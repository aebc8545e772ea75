"""Tests for the cache layer: the Arrow schema, shard files, the manifest, the reader and verify."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from numpy.testing import assert_array_equal

from phigenesis import prep
from phigenesis.data import codec, shards
from phigenesis.data.cache import reader as cache_reader
from phigenesis.data.codec import DEPTH_MAX_M, DEPTH_SCALE
from phigenesis.data.loader import FIELD_GROUPS, FrameDataset
from phigenesis.data.pipeline import load_pipeline
from phigenesis.data.records import Frame
from phigenesis.data.schema import TRUTH_MAPS, CacheContents, frame_schema, frame_to_batch, row_to_frame
from phigenesis.data.shards import (
    MANIFEST_NAME,
    SHARDS_DIR,
    TMP_MARKER,
    CacheError,
    CacheReader,
    Manifest,
    SceneEntry,
    ShardReader,
    ShardWriter,
    column_ranges,
    verify_cache,
)
from phigenesis.data.sources.synthetic import synthetic_scene
from tests.conftest import TINY_PREP_ARGS, tiny_config

QUANTUM = 1 / 512  # half a step of the 1/256 depth and flow encodings


# --------------------------------------------------------------------------------------------
# Helpers and fixtures


def prep_command() -> list[str]:
    exe = Path(sys.executable).with_name("phigenesis-prep")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "phigenesis.cli.prep"]


def run_prep(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prep_command(), *args], capture_output=True, text=True, timeout=120)


def copy_cache(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def shard_infos(cache_dir: Path) -> list[shards.ShardInfo]:
    return Manifest.load(cache_dir).complete_shards()


def ipc_round_trip(batch: pa.RecordBatch) -> pa.RecordBatch:
    """The batch after writing it to an Arrow IPC file in memory and reading it back."""
    sink = pa.BufferOutputStream()
    with pa.ipc.new_file(sink, batch.schema) as writer:
        writer.write_batch(batch)
    return pa.ipc.open_file(sink.getvalue()).get_batch(0)


def tiny_batches(cache_dir: Path) -> list[pa.RecordBatch]:
    return list(CacheReader(cache_dir))


@pytest.fixture(scope="module")
def frame() -> Frame:
    """One rendered synthetic frame (with truth maps and a LiDAR sweep with truth)."""
    return synthetic_scene(tiny_config(scenes=1, frames=1), 0).frames[0]


@pytest.fixture(scope="module")
def round_tripped(frame: Frame) -> Frame:
    batch = frame_to_batch(frame, "synthetic", frame_schema(CacheContents()))
    return row_to_frame(ipc_round_trip(batch), 0)


@pytest.fixture(scope="module")
def corrupt_cache(tiny_cache: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    """A copy of the tiny cache with one byte flipped in the middle of row 1 of its first shard.

    Returns the cache directory, the damaged shard's path and the damaged row."""
    out = copy_cache(tiny_cache, tmp_path_factory.mktemp("corrupt") / "cache")
    info = shard_infos(out)[0]
    row = 1
    pos = (info.row_start(row) + info.row_index[row][0]) // 2
    path = out / info.path
    data = bytearray(path.read_bytes())
    data[pos] ^= 0xFF
    path.write_bytes(bytes(data))
    return out, path, row


# --------------------------------------------------------------------------------------------
# Readable without phigenesis

PLAIN_READER = r"""
import json, struct, sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.ipc

cache = Path(sys.argv[1])
manifest = json.loads((cache / "manifest.json").read_text())
result = {"shards": []}
for sh in manifest["shards"]:
    path = cache / sh["path"]
    with pa.memory_map(str(path)) as source:
        reader = pa.ipc.open_file(source)
        table = reader.read_all()
        meta = {k.decode(): v.decode() for k, v in (reader.schema.metadata or {}).items()}
        batches = reader.num_record_batches
    df = pd.read_feather(path)
    camera = df["cameras"].iloc[0][0]
    rgb = cv2.imdecode(np.frombuffer(camera["image"], np.uint8), cv2.IMREAD_COLOR)
    # A map blob (phigenesis/data/codec.py): 20-byte header, one zstd frame, 16-bit values as byte planes,
    # rows delta-coded if filter bit 2 is set.
    blob = camera["truth_depth_png"]
    magic, version, itemsize, channels, filt, h, w, n = struct.unpack_from("<4sBBBBIII", blob)
    raw = np.frombuffer(pa.decompress(blob[20:], h * w * channels * itemsize, codec="zstd"), np.uint8)
    depth = raw.reshape(2, -1).T.copy().view("<u2").reshape(h, w) if filt & 1 else raw.reshape(h, w)
    depth = np.cumsum(depth, axis=0, dtype=depth.dtype) if filt & 2 else depth
    result["shards"].append({
        "path": sh["path"],
        "arrow_rows": table.num_rows,
        "arrow_batches": batches,
        "arrow_columns": table.column_names,
        "schema_version": meta.get("phigenesis.schema_version"),
        "pandas_rows": len(df),
        "pandas_columns": list(df.columns),
        "scene_ids": sorted(set(df["scene_id"])),
        "frame_indices": [int(i) for i in df["frame_index"]],
        "image_format": camera["image_format"],
        "image_shape": list(rgb.shape),
        "image_size": [camera["height"], camera["width"]],
        "depth_dtype": str(depth.dtype),
        "depth_shape": list(depth.shape),
        "depth_sum": int(depth.sum(dtype=np.int64)),
        "depth_magic": magic.hex(),
    })
result["phigenesis_imported"] = sorted(m for m in sys.modules if m.split(".")[0] == "phigenesis")
print(json.dumps(result))
"""


def test_cache_opens_with_plain_pyarrow_and_pandas_without_importing_phigenesis(
    tiny_cache: Path, tmp_path: Path
) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", PLAIN_READER, str(tiny_cache)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    manifest = Manifest.load(tiny_cache)
    columns = frame_schema(load_pipeline("synthetic").contents).names  # what the tiny cache's spec asks for

    assert result["phigenesis_imported"] == []
    assert [s["path"] for s in result["shards"]] == [s.path for s in manifest.shards]
    for got, info in zip(result["shards"], manifest.shards, strict=True):
        assert got["arrow_rows"] == got["arrow_batches"] == got["pandas_rows"] == info.rows
        assert got["arrow_columns"] == got["pandas_columns"] == columns
        assert got["schema_version"] == str(manifest.schema_version)
        assert got["scene_ids"] == [info.scene_id]
        assert got["frame_indices"] == list(range(info.rows))
        assert got["image_format"] == "jpeg"
        assert (
            got["image_shape"]
            == [*got["image_size"], 3]
            == [TINY_PREP_ARGS["height"], TINY_PREP_ARGS["width"], 3]
        )
        assert got["depth_dtype"] == "uint16"
        assert got["depth_shape"] == got["image_size"]
        assert got["depth_magic"] == codec.MAGIC.hex()
        with pa.memory_map(str(tiny_cache / info.path)) as source:
            blob = pa.ipc.open_file(source).get_batch(0).column("cameras")[0][0]["truth_depth_png"].as_py()
        assert got["depth_sum"] == int(codec.decode_array(blob, np.uint16).sum(dtype=np.int64)) > 0


# --------------------------------------------------------------------------------------------
# Schema: frame <-> row


def test_frame_round_trips_with_equal_poses_and_timestamps(frame: Frame, round_tripped: Frame) -> None:
    back = round_tripped
    assert (back.scene_id, back.frame_index, back.timestamp_micros) == (
        frame.scene_id,
        frame.frame_index,
        frame.timestamp_micros,
    )
    assert_array_equal(back.world_from_ego, frame.world_from_ego)
    assert [c.timestamp_micros for c in back.cameras] == [c.timestamp_micros for c in frame.cameras]
    for got, want in zip(back.cameras, frame.cameras, strict=True):
        assert_array_equal(got.world_from_ego, want.world_from_ego)


def test_frame_round_trips_with_equal_calibrations_and_image_bytes(
    frame: Frame, round_tripped: Frame
) -> None:
    assert [c.name for c in round_tripped.cameras] == [c.name for c in frame.cameras]
    for got, want in zip(round_tripped.cameras, frame.cameras, strict=True):
        assert (got.calibration.width, got.calibration.height) == (
            want.calibration.width,
            want.calibration.height,
        )
        assert_array_equal(got.calibration.intrinsics, want.calibration.intrinsics)
        assert_array_equal(got.calibration.distortion, want.calibration.distortion)
        assert_array_equal(got.calibration.ego_from_camera, want.calibration.ego_from_camera)
        assert got.image_format == want.image_format
        assert got.image_bytes == want.image_bytes


def test_frame_round_trips_with_equal_lidar_arrays(frame: Frame, round_tripped: Frame) -> None:
    got, want = round_tripped.lidar, frame.lidar
    assert got is not None and want is not None and len(want) > 0
    assert got.timestamp_micros == want.timestamp_micros
    assert_array_equal(got.world_from_ego, want.world_from_ego)
    for name in (
        "points_ego",
        "intensity",
        "beam_index",
        "origins_ego",
        "time_offset_micros",
        "lidar_id",
        "semantic",
        "instance",
    ):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype, name
        assert_array_equal(a, b, err_msg=name)


def test_frame_round_trips_with_equal_boxes(frame: Frame, round_tripped: Frame) -> None:
    got, want = round_tripped.boxes, frame.boxes
    assert len(want) > 0
    assert got.track_id == want.track_id
    for f in dataclasses.fields(want):
        if f.name != "track_id":
            assert_array_equal(getattr(got, f.name), getattr(want, f.name), err_msg=f.name)
            assert getattr(got, f.name).dtype == getattr(want, f.name).dtype, f.name


def test_truth_semantics_and_instances_round_trip_exactly(frame: Frame, round_tripped: Frame) -> None:
    for got, want in zip(round_tripped.cameras, frame.cameras, strict=True):
        assert got.truth is not None and want.truth is not None
        assert got.truth.semantic.dtype == np.uint8 and got.truth.instance.dtype == np.uint16
        assert_array_equal(got.truth.semantic, want.truth.semantic)
        assert_array_equal(got.truth.instance, want.truth.instance)


def test_truth_depth_round_trips_within_half_a_step(frame: Frame, round_tripped: Frame) -> None:
    for got, want in zip(round_tripped.cameras, frame.cameras, strict=True):
        d = want.truth.depth_m.astype(np.float64)
        encodable = (d > 0) & (np.round(d * DEPTH_SCALE) <= 65535)
        assert encodable.any()
        err = np.abs(got.truth.depth_m.astype(np.float64) - d)
        assert err[encodable].max() <= QUANTUM + 1e-6
        # sky and depths beyond the encodable range come back as 0 = unknown
        assert_array_equal(got.truth.depth_m[~encodable], 0)
        assert np.all(d[~encodable & (d > 0)] > DEPTH_MAX_M)


def test_truth_flow_round_trips_within_half_a_step(frame: Frame, round_tripped: Frame) -> None:
    moving = 0
    for got, want in zip(round_tripped.cameras, frame.cameras, strict=True):
        f = want.truth.flow_world_mps.astype(np.float64)
        assert np.abs(f).max() < 128
        assert got.truth.flow_world_mps.shape == f.shape
        assert np.abs(got.truth.flow_world_mps - f).max() <= QUANTUM + 1e-6
        moving += int(np.count_nonzero(f))
    assert moving > 0, "the frame should show moving surfaces"


def test_frame_without_lidar_round_trips_to_a_frame_without_lidar(frame: Frame) -> None:
    no_lidar = dataclasses.replace(frame, lidar=None)
    back = row_to_frame(ipc_round_trip(frame_to_batch(no_lidar, "synthetic", frame_schema())))
    assert back.lidar is None
    assert back.boxes.track_id == frame.boxes.track_id


def _all_fields(schema: pa.Schema) -> list[tuple[str, pa.Field]]:
    out = []

    def walk(prefix: str, f: pa.Field) -> None:
        out.append((prefix + f.name, f))
        t = f.type
        if pa.types.is_list(t) and pa.types.is_struct(t.value_type):
            t = t.value_type
        if pa.types.is_struct(t):
            for child in t:
                walk(f"{prefix}{f.name}.", child)

    for f in schema:
        walk("", f)
    return out


def test_every_column_carries_a_doc_and_units_and_frames_where_they_apply() -> None:
    fields = dict(_all_fields(frame_schema()))
    assert all(f.metadata and f.metadata.get(b"doc") for f in fields.values()), [
        name for name, f in fields.items() if not (f.metadata and f.metadata.get(b"doc"))
    ]

    def meta(name: str) -> dict[str, str]:
        return {k.decode(): v.decode() for k, v in fields[name].metadata.items()}

    assert meta("world_from_ego")["unit"] == "m"
    assert meta("world_from_ego")["frame"] == "world<-ego"
    assert meta("frame_timestamp_micros")["unit"] == "microseconds"
    assert meta("cameras.ego_from_camera")["frame"] == "ego<-camera"
    assert meta("cameras.truth_depth_png")["unit"] == "m/256"
    assert meta("cameras.truth_depth_png")["frame"] == "camera"
    assert meta("cameras.truth_flow_png")["frame"] == "world"
    assert meta("lidar.points_ego")["frame"] == "ego"
    assert meta("boxes.velocity_world")["unit"] == "m/s"
    assert "unit" not in meta("scene_id")


def test_contents_without_truth_maps_or_lidar_give_a_schema_without_those_columns(frame: Frame) -> None:
    schema = frame_schema(CacheContents(camera_truth=(), lidar=False))
    camera_columns = [f.name for f in schema.field("cameras").type.value_type]
    assert "lidar" not in schema.names
    assert not [c for c in camera_columns if c.startswith("truth_")]
    batch = frame_to_batch(frame, "synthetic", schema)
    assert batch.schema.equals(schema)
    back = row_to_frame(ipc_round_trip(batch))
    assert back.lidar is None
    assert all(c.truth is None for c in back.cameras)


def test_contents_select_single_truth_maps_and_lidar_truth() -> None:
    schema = frame_schema(CacheContents(camera_truth=("depth", "flow"), lidar=True, lidar_truth=False))
    camera_columns = {f.name for f in schema.field("cameras").type.value_type}
    lidar_columns = {f.name for f in schema.field("lidar").type}
    assert {f"truth_{m}_png" for m in TRUTH_MAPS} & camera_columns == {"truth_depth_png", "truth_flow_png"}
    assert "points_ego" in lidar_columns
    assert not {"truth_semantic", "truth_instance"} & lidar_columns


def test_a_cache_holds_only_the_columns_its_pipeline_spec_asks_for(tmp_path: Path) -> None:
    spec = dataclasses.replace(
        load_pipeline("synthetic"), contents=CacheContents(camera_truth=("depth",), lidar=False)
    )
    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": 1}
    prep.synthetic(tmp_path, pipeline=spec, progress=False, **args)  # type: ignore[arg-type]
    info = Manifest.load(tmp_path).shards[0]
    schema = pa.ipc.open_file(str(tmp_path / info.path)).schema
    camera_columns = {f.name for f in schema.field("cameras").type.value_type}
    assert "lidar" not in schema.names
    assert {c for c in camera_columns if c.startswith("truth_")} == {"truth_depth_png"}


# --------------------------------------------------------------------------------------------
# Shard writer


def test_writer_rolls_over_to_a_new_shard_by_size_and_rows_read_back_in_order(
    tiny_cache: Path, tmp_path: Path
) -> None:
    batches = tiny_batches(tiny_cache)
    max_bytes = int(2.5 * sum(b.nbytes for b in batches) / len(batches))
    with ShardWriter(tmp_path, "scene-a", batches[0].schema, max_bytes) as writer:
        for b in batches:
            writer.write(b)
    infos = writer.shards

    assert len(infos) >= 2
    assert [i.path for i in infos] == [f"{SHARDS_DIR}/scene-a-{k:05d}.arrow" for k in range(len(infos))]
    assert sum(i.rows for i in infos) == len(batches)
    for info in infos[:-1]:  # a shard closes with the first row that reaches the limit, not before
        assert info.row_index[-1][0] >= max_bytes
        assert info.rows == 1 or info.row_index[-2][0] < max_bytes
    back = [ShardReader(tmp_path, info).read(r) for info in infos for r in range(info.rows)]
    assert all(a.equals(b) for a, b in zip(back, batches, strict=True))


def test_writer_aborted_by_an_exception_keeps_complete_shards_and_drops_the_unfinished_one(
    tiny_cache: Path, tmp_path: Path
) -> None:
    batches = tiny_batches(tiny_cache)
    max_bytes = int(1.5 * max(b.nbytes for b in batches))  # one row alone never fills a shard
    shard_dir = tmp_path / SHARDS_DIR
    with (
        pytest.raises(RuntimeError, match="interrupted"),
        ShardWriter(tmp_path, "scene-a", batches[0].schema, max_bytes) as writer,
    ):
        rows = iter(batches)
        while not writer.shards:
            writer.write(next(rows))
        writer.write(next(rows))  # opens the second shard
        assert [p for p in shard_dir.iterdir() if TMP_MARKER in p.name], "a temporary shard should be open"
        raise RuntimeError("interrupted")

    assert sorted(p.name for p in shard_dir.iterdir()) == ["scene-a-00000.arrow"]
    info = writer.shards[0]
    assert shards.crc32c_file(tmp_path / info.path) == info.file_crc32c
    assert all(ShardReader(tmp_path, info).read(r).equals(batches[r]) for r in range(info.rows))


def test_writer_aborted_before_any_shard_is_complete_leaves_no_files(
    tiny_cache: Path, tmp_path: Path
) -> None:
    batches = tiny_batches(tiny_cache)
    with pytest.raises(RuntimeError), ShardWriter(tmp_path, "scene-a", batches[0].schema) as writer:
        writer.write(batches[0])
        writer.write(batches[1])
        raise RuntimeError("interrupted")
    assert writer.shards == []
    assert list((tmp_path / SHARDS_DIR).iterdir()) == []


def test_writer_refuses_a_batch_of_another_schema(tiny_cache: Path, tmp_path: Path) -> None:
    batch = tiny_batches(tiny_cache)[0]
    other = frame_schema(CacheContents(lidar=False))
    with pytest.raises(ValueError, match="scene-a"), ShardWriter(tmp_path, "scene-a", other) as writer:
        writer.write(batch)


# --------------------------------------------------------------------------------------------
# Manifest


def _manifest(fingerprint: str) -> Manifest:
    m = Manifest(
        schema_version=1, source="synthetic", arguments={"frames": 3}, pipeline={}, fingerprint=fingerprint
    )
    m.record_scene(SceneEntry("s0", "synthetic", 0, "complete"), [])
    return m


def test_manifest_save_replaces_the_file_by_rename_so_open_readers_see_a_whole_version(
    tmp_path: Path,
) -> None:
    _manifest("old").save(tmp_path)
    path = tmp_path / MANIFEST_NAME
    with open(path, "rb") as old_handle:
        _manifest("new").save(tmp_path)
        assert os.fstat(old_handle.fileno()).st_ino != path.stat().st_ino
        assert json.loads(old_handle.read())["fingerprint"] == "old"
    assert Manifest.load(tmp_path).fingerprint == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME]


def test_a_manifest_save_that_fails_before_the_rename_leaves_the_previous_manifest_intact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _manifest("old").save(tmp_path)
    before = (tmp_path / MANIFEST_NAME).read_bytes()

    def crash(*args: object) -> None:
        raise OSError("simulated crash before the rename")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="simulated"):
        _manifest("new").save(tmp_path)
    monkeypatch.undo()
    assert (tmp_path / MANIFEST_NAME).read_bytes() == before
    assert Manifest.load(tmp_path).fingerprint == "old"


def test_manifest_lists_the_scenes_of_a_cache_and_saves_back_identically(
    tiny_cache: Path, tmp_path: Path
) -> None:
    m = Manifest.load(tiny_cache)
    m.save(tmp_path)
    assert Manifest.load(tmp_path) == m
    assert [s.id for s in m.scenes] == ["synthetic-s7-0000", "synthetic-s7-0001"]
    assert all(s.status == "complete" and s.frames == TINY_PREP_ARGS["frames"] for s in m.scenes)


# --------------------------------------------------------------------------------------------
# Reader and verify on a sound cache


def test_verify_passes_a_fresh_cache_without_warnings(tiny_cache: Path) -> None:
    report = verify_cache(tiny_cache)
    assert report.ok, report.errors
    assert report.warnings == []
    assert report.frames == TINY_PREP_ARGS["scenes"] * TINY_PREP_ARGS["frames"]


def test_reader_lists_every_frame_scene_by_scene(tiny_cache: Path) -> None:
    reader = CacheReader(tiny_cache)
    keys = [(b.column("scene_id")[0].as_py(), b.column("frame_index")[0].as_py()) for b in reader]
    assert keys == [(s, k) for s in reader.scene_ids() for k in range(TINY_PREP_ARGS["frames"])]
    assert reader.frames_of("synthetic-s7-0001") == range(3, 6)
    assert reader.frame(-1).frame_index == TINY_PREP_ARGS["frames"] - 1
    with pytest.raises(IndexError):
        reader.read(len(reader))


# --------------------------------------------------------------------------------------------
# Corruption


def test_verify_command_fails_naming_the_shard_and_row_with_a_flipped_byte(
    corrupt_cache: tuple[Path, Path, int],
) -> None:
    cache, shard, row = corrupt_cache
    proc = run_prep("verify", str(cache))
    assert proc.returncode == 1, proc.stdout + proc.stderr
    bad = [line for line in proc.stdout.splitlines() if line.startswith("BAD")]
    assert len(bad) == 1, proc.stdout
    assert shard.name in bad[0]
    assert f"row {row}" in bad[0]


def test_reader_raises_cache_error_naming_the_shard_for_a_corrupt_row(
    corrupt_cache: tuple[Path, Path, int],
) -> None:
    cache, shard, row = corrupt_cache
    with pytest.raises(CacheError, match=f"{shard.name}.*row {row}"):
        CacheReader(cache).read(row)


def test_dataset_raises_cache_error_naming_the_shard_for_a_corrupt_row(
    corrupt_cache: tuple[Path, Path, int],
) -> None:
    cache, shard, row = corrupt_cache
    with pytest.raises(CacheError, match=shard.name):
        FrameDataset(cache, fields=FIELD_GROUPS)[row]


def test_dataset_checks_only_the_columns_it_reads_and_names_a_damaged_one(
    tiny_cache: Path, tmp_path: Path
) -> None:
    out = copy_cache(tiny_cache, tmp_path / "cache")
    info = shard_infos(out)[0]
    path = out / info.path
    buffer = pa.py_buffer(path.read_bytes())
    ranges = column_ranges(pa.ipc.open_file(buffer).get_batch(2), buffer.address)
    lo, hi = ranges[info.columns.index("cameras")]
    data = bytearray(path.read_bytes())
    data[(lo + hi) // 2] ^= 0x55
    path.write_bytes(bytes(data))
    dataset = FrameDataset(out, fields=("cameras",))
    with pytest.raises(CacheError, match=rf"{path.name}: row 2, column 'cameras' is corrupt"):
        dataset[2]
    assert CacheReader(out).read(2, ["lidar", "boxes"]).num_columns == 2  # undamaged columns still read


def test_a_reader_checks_each_row_and_column_once(tiny_cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    reader = CacheReader(tiny_cache)
    reader.read(1, ["cameras"])  # opens the shard (footer) and checks row 1's metadata and cameras
    calls: list[int] = []
    real = cache_reader._crc_range
    monkeypatch.setattr(cache_reader, "_crc_range", lambda *a: calls.append(a[3] - a[2]) or real(*a))
    reader.read(1, ["cameras"])
    assert calls == []  # already checked by this reader
    reader.read(1, ["cameras", "lidar"])
    assert len(calls) == 1  # only the new column
    reader.read(2, ["cameras"])
    assert len(calls) == 3  # a new row: its metadata and its column


def test_rows_other_than_the_corrupt_one_still_read(
    corrupt_cache: tuple[Path, Path, int], tiny_cache: Path
) -> None:
    cache, _shard, row = corrupt_cache
    reader, clean = CacheReader(cache), CacheReader(tiny_cache)
    others = [i for i in range(len(reader)) if i != row]
    assert all(reader.read(i).equals(clean.read(i)) for i in others)
    dataset = FrameDataset(cache)
    assert [dataset[i]["frame_index"] for i in others] == [clean.frame(i).frame_index for i in others]


def test_truncated_shard_is_named_by_verify(tiny_cache: Path, tmp_path: Path) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    info = shard_infos(cache)[1]
    os.truncate(cache / info.path, info.bytes // 2)
    report = verify_cache(cache)
    assert not report.ok
    assert len(report.errors) == 1
    assert Path(info.path).name in report.errors[0]
    assert str(info.bytes // 2) in report.errors[0]


def test_reader_refuses_a_truncated_shard_naming_it_and_reads_the_others(
    tiny_cache: Path, tmp_path: Path
) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    info = shard_infos(cache)[1]
    os.truncate(cache / info.path, info.bytes - 10)
    reader = CacheReader(cache)
    first = reader.frames_of(info.scene_id)[0]
    with pytest.raises(CacheError, match=f"{Path(info.path).name}.*truncated"):
        reader.read(first)
    assert reader.frame(0).scene_id == shard_infos(cache)[0].scene_id


def test_truncated_manifest_is_named_by_verify(tiny_cache: Path, tmp_path: Path) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    path = cache / MANIFEST_NAME
    os.truncate(path, path.stat().st_size // 2)
    proc = run_prep("verify", str(cache))
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    assert f"{path}: manifest is truncated" in proc.stdout


def test_reader_and_dataset_refuse_a_truncated_manifest_naming_it(tiny_cache: Path, tmp_path: Path) -> None:
    cache = copy_cache(tiny_cache, tmp_path / "cache")
    path = cache / MANIFEST_NAME
    os.truncate(path, path.stat().st_size // 2)
    with pytest.raises(CacheError, match=f"{MANIFEST_NAME}: manifest is truncated"):
        CacheReader(cache)
    with pytest.raises(CacheError, match=MANIFEST_NAME):
        FrameDataset(cache)


def test_reader_refuses_a_directory_without_a_manifest(tmp_path: Path) -> None:
    with pytest.raises(CacheError, match="not a phigenesis cache"):
        CacheReader(tmp_path)
