"""Random access to a cache's rows: one shard (:class:`ShardReader`) or every frame of a cache in
manifest order (:class:`CacheReader`), checking the manifest's CRCs of what they return.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa

from phigenesis.data.cache.checksums import ShardInfo, _crc_name, _crc_range, column_range
from phigenesis.data.cache.files import MANIFEST_NAME
from phigenesis.data.cache.manifest import Manifest, resolve_shard_path
from phigenesis.errors import CacheError


class ShardReader:
    """Random access to the rows of one shard, checking the manifest's CRCs of what it returns.

    Each row's metadata and each column of a row is checked the first time this reader returns it
    (its memory map stays the one it checked): a DataLoader that reads every frame once per epoch
    pays for the CRCs in its first epoch only. A file damaged on disk is still refused on its first
    read in every process; ``verify`` re-hashes everything.
    """

    def __init__(self, cache_dir: Path, info: ShardInfo, check_crc: bool = True):
        self.info = info
        resolve_shard_path(cache_dir, info.path)  # never read a file outside the cache's shards/
        self.path = Path(cache_dir) / info.path
        self.check_crc = check_crc
        if not self.path.is_file():
            raise CacheError(f"{self.path}: shard listed in the manifest is missing")
        size = self.path.stat().st_size
        if size != info.bytes:
            raise CacheError(
                f"{self.path}: shard is {size} bytes, the manifest says {info.bytes} (truncated or replaced)"
            )
        self._mmap = pa.memory_map(str(self.path), "r")
        self._buffer = self._mmap.read_buffer()
        if check_crc:
            self._check(info.footer_start, info.bytes, info.footer_crc32, "the footer")
        try:
            self._reader = pa.ipc.open_file(self._buffer)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: not a readable Arrow IPC file ({e})") from e
        if self._reader.num_record_batches != info.rows:
            raise CacheError(
                f"{self.path}: holds {self._reader.num_record_batches} rows, the manifest says {info.rows}"
            )
        self._column_index = {name: i for i, name in enumerate(info.columns)}
        self._checked: set[tuple[int, int]] = set()  # (row, column index; -1: metadata) seen intact

    def _check(self, start: int, end: int, expected: int, what: str) -> None:
        if _crc_range(self.info.checksum, self._buffer, start, end) != expected:
            raise CacheError(
                f"{self.path}: {what} is corrupt ({_crc_name(self.info)} mismatch in bytes {start}..{end})"
            )

    def __len__(self) -> int:
        return self.info.rows

    def read(self, row: int, columns: Sequence[str] | None = None) -> pa.RecordBatch:
        """The one-row batch of ``row`` (only ``columns``, if given), after checking the CRCs of its
        metadata and of the columns returned."""
        if not 0 <= row < self.info.rows:
            raise IndexError(f"{self.path}: row {row} out of range ({self.info.rows} rows)")
        names = list(self.info.columns if columns is None else columns)
        unknown = [c for c in names if c not in self._column_index]
        if unknown:
            raise KeyError(f"{self.path}: no columns {unknown}; it has {self.info.columns}")
        entry = self.info.row_index[row]
        checked = self._checked
        if self.check_crc and (row, -1) not in checked:
            self._check(self.info.row_start(row), entry[1], entry[2], f"row {row} (metadata)")
            checked.add((row, -1))
        try:
            batch = self._reader.get_batch(row)
        except (pa.ArrowInvalid, OSError) as e:
            raise CacheError(f"{self.path}: row {row} does not decode ({e})") from e
        if self.check_crc:
            for name in names:
                k = self._column_index[name]
                if (row, k) in checked:
                    continue
                lo, hi = column_range(batch.column(k), self._buffer.address)
                self._check(lo, hi, entry[3 + k], f"row {row}, column {name!r}")
                checked.add((row, k))
        return batch if columns is None else batch.select(names)

    @property
    def schema(self) -> pa.Schema:
        return self._reader.schema


#: Columns every row of a frame cache has (:mod:`phigenesis.data.schema`), which a frame needs.
FRAME_KEY_COLUMNS = ("scene_id", "frame_index", "frame_timestamp_micros", "world_from_ego", "cameras")


class CacheReader:
    """Random access to every frame of a cache, in manifest order (scene by scene).

    Shards are memory-mapped on first use; the reader can be pickled (open files are reopened in
    the new process), so it works inside DataLoader workers.
    """

    def __init__(self, cache_dir: str | os.PathLike[str], check_crc: bool = True):
        self.cache_dir = Path(cache_dir)
        self.check_crc = check_crc
        self.manifest = Manifest.load(self.cache_dir)
        self.shards = self.manifest.complete_shards()
        self._index: list[tuple[int, int]] = [
            (i, r) for i, sh in enumerate(self.shards) for r in range(sh.rows)
        ]
        self._open: dict[int, ShardReader] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_open"] = {}
        return state

    def __len__(self) -> int:
        return len(self._index)

    def shard(self, index: int) -> ShardReader:
        if index not in self._open:
            self._open[index] = ShardReader(self.cache_dir, self.shards[index], self.check_crc)
        return self._open[index]

    def read(self, frame: int, columns: Sequence[str] | None = None) -> pa.RecordBatch:
        """The one-row batch of global frame index ``frame`` (only ``columns``, if given)."""
        if not -len(self) <= frame < len(self):
            raise IndexError(f"frame {frame} out of range for a cache of {len(self)} frames")
        shard, row = self._index[frame]
        return self.shard(shard).read(row, columns)

    def columns_of(self, frame: int) -> list[str]:
        """The top-level columns of the shard holding global frame index ``frame``."""
        return self.shards[self._index[frame][0]].columns

    def locate(self, frame: int) -> tuple[Path, int]:
        """The shard file and row holding global frame index ``frame``."""
        shard, row = self._index[frame]
        return self.cache_dir / self.shards[shard].path, row

    def __iter__(self) -> Iterator[pa.RecordBatch]:
        for i in range(len(self)):
            yield self.read(i)

    def scene_ids(self) -> list[str]:
        return [s.id for s in self.manifest.scenes if s.status == "complete"]

    def frames_of(self, scene_id: str) -> range:
        """Global frame indices of a scene's frames."""
        first = None
        count = 0
        for i, (shard, _row) in enumerate(self._index):
            if self.shards[shard].scene_id == scene_id:
                first = i if first is None else first
                count += 1
        if first is None:
            raise KeyError(f"{self.cache_dir}: no complete scene {scene_id!r}")
        return range(first, first + count)

    def _check_frames(self, frame: int) -> None:
        """CacheError naming the manifest if the shard holding ``frame`` does not hold frames (a
        Stage 2 latent cache holds one row per window)."""
        if not -len(self) <= frame < len(self):
            return  # read() says it is out of range
        missing = [c for c in FRAME_KEY_COLUMNS if c not in self.columns_of(frame)]
        if missing:
            raise CacheError(
                f"{self.cache_dir / MANIFEST_NAME}: a cache of source {self.manifest.source!r} whose rows "
                f"are not frames (no column {', '.join(missing)}); only frame caches (written by prep, "
                "render or generate) hold frames to read or preview"
            )

    def frame(self, frame: int, decode_truth: bool = True):  # -> records.Frame
        """The :class:`~phigenesis.data.records.Frame` record of a global frame index.

        The record validates what it is given, as it does for a source: a row holding an invalid
        value (a cache written before the scene model refused it, or a crafted one) raises a
        :class:`CacheError` naming the shard, the row and the field."""
        # the scene model and the schema (0.17 s more to import) load only when a frame is decoded
        from phigenesis.data.records import InvalidRecord
        from phigenesis.data.schema import row_to_frame

        self._check_frames(frame)
        batch = self.read(frame)
        try:
            return row_to_frame(batch, 0, decode_truth)
        except InvalidRecord as e:
            path, row = self.locate(frame)
            raise CacheError(f"{path}: row {row}: {e}") from None
