"""The shard writer's hashes are computed from the bytes as it writes them: they must equal a
re-hash of the finished files (``shards.shard_info``, which reads a file back from disk)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from phigenesis.data import shards
from phigenesis.data.shards import ShardInfo, ShardReader, ShardWriter

SCHEMA = pa.schema(
    [
        ("frame_index", pa.int64()),
        ("image", pa.binary()),
        ("note", pa.string()),  # null in some rows
        ("points", pa.list_(pa.float32())),
        (
            "cameras",
            pa.list_(pa.struct([("name", pa.string()), ("pose", pa.list_(pa.float64(), 16))])),
        ),
    ]
)


def rows(count: int, image_bytes: int = 10_000, seed: int = 0) -> pa.Table:
    """``count`` rows of :data:`SCHEMA` with random contents, ``image_bytes`` per image."""
    rng = np.random.default_rng(seed)
    return pa.table(
        {
            "frame_index": list(range(count)),
            "image": [rng.bytes(image_bytes) for _ in range(count)],
            "note": [None if i % 2 else f"row {i}" for i in range(count)],
            "points": [rng.random(3 * (50 + i), dtype=np.float32) for i in range(count)],
            "cameras": [
                [{"name": f"cam{k}", "pose": rng.random(16).tolist()} for k in range(1 + i % 3)]
                for i in range(count)
            ],
        },
        schema=SCHEMA,
    )


def write(cache: Path, batches: list[pa.RecordBatch], max_bytes: int) -> list[ShardInfo]:
    with ShardWriter(cache, "scene-a", SCHEMA, max_bytes) as writer:
        for batch in batches:
            writer.write(batch)
    return writer.shards


def reread(cache: Path, info: ShardInfo) -> ShardInfo:
    """The manifest entry of ``info``'s file, computed by reading the file back from disk."""
    again = shards.shard_info(cache / info.path, info.scene_id, [row[0] for row in info.row_index])
    again.path = info.path
    return again


def test_written_hashes_equal_a_rehash_of_each_shard_file_on_disk(tmp_path: Path) -> None:
    batches = rows(7).to_batches(max_chunksize=1)  # slices of one table: the IPC writer rebases them
    infos = write(tmp_path, batches, max_bytes=30_000)  # rolls over every few rows
    assert len(infos) > 1 and sum(i.rows for i in infos) == 7
    for info in infos:
        assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
        assert info.bytes == (tmp_path / info.path).stat().st_size
        assert info.file_crc32c == shards.crc32c_file(tmp_path / info.path) and info.sha256 is None


def test_rows_larger_than_the_writers_buffer_hash_as_the_file_on_disk(tmp_path: Path) -> None:
    batches = rows(3, image_bytes=3 << 20).to_batches(max_chunksize=1)  # 3 MiB rows: the buffer grows
    (info,) = write(tmp_path, batches, max_bytes=1 << 30)
    assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
    reader = ShardReader(tmp_path, info)  # checks the footer and each row's CRCs as it reads
    assert [reader.read(r).column("image")[0].as_py() for r in range(3)] == [
        b.column("image")[0].as_py() for b in batches
    ]


def test_the_writer_never_reads_a_shard_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the writer read a shard back")

    monkeypatch.setattr(shards, "shard_info", refuse)
    monkeypatch.setattr(shards, "crc32c_file", refuse)
    monkeypatch.setattr(Path, "read_bytes", refuse)
    monkeypatch.setattr(shards.pa, "memory_map", refuse)
    infos = write(tmp_path, rows(4).to_batches(max_chunksize=1), max_bytes=30_000)
    monkeypatch.undo()
    for info in infos:
        assert dataclasses.asdict(info) == dataclasses.asdict(reread(tmp_path, info))
