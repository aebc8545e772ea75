"""Sharded Arrow IPC caches: an atomic writer, the manifest, a random-access reader and a verifier.

Layout of a cache directory::

    manifest.json          what the cache holds (the commit point: rewritten atomically per scene)
    shards/<scene>-00000.arrow  Arrow IPC files, one row per frame, one record batch per row
    .phigenesis.lock       held by the one run writing the cache (see cache_lock.py, cache_run.py)
    .phigenesis-staging/   the new version an ``overwrite`` run builds before swapping it in

Integrity: the manifest records each shard's size and CRC-32C and, for every record batch (row),
where it ends, where its body starts, the CRC-32C of its metadata and of each top-level column's
bytes, plus the CRC-32C of the file footer (caches written before CRC-32C carry zlib CRC-32s and a
SHA-256 of the file instead, and are read and verified as such; see :data:`SHARD_CHECKSUM`). The
reader checks a shard's size and footer when it opens it, and a row's metadata and the columns it
returns when it reads the row: a flipped byte in anything a caller reads raises an error naming the
shard, row and column, and reading only the images of a frame never hashes its LiDAR.
:func:`verify_cache` re-hashes everything. The writer computes all of these from the bytes as it
writes them, never reading a shard back.

Trust: a manifest is untrusted input. :meth:`Manifest.load` checks it against the cache's schema
once (every field's type and range, the row index's shape, scenes and shards agreeing with each
other) and checks that every shard path resolves, symbolic links included, inside the cache's
``shards/`` folder; whatever reads or deletes a shard goes through :func:`resolve_shard_path`. A
manifest that is itself a symbolic link is refused; scene ids and shard file names are bounded
(:func:`scene_id_problem`, :data:`MAX_FILE_NAME_BYTES`), so no name reaches the file system that
it cannot take.

Atomicity: every file is written under a temporary name, flushed with fsync and renamed; the
manifest is rewritten the same way after each scene completes. A killed run leaves only complete
files under final names, and the manifest lists only scenes whose shards are all complete. A write
that fails (a full disk) removes its temporary file and raises :class:`CacheWriteError` naming the
file and the system's reason.

Each role is a module of :mod:`phigenesis.data.cache` (files, checksums, sink, writer, manifest,
reader, verify); this module re-exports their public names, the import path the rest of the
toolkit uses.
"""

from __future__ import annotations

from phigenesis.data.cache.checksums import (  # noqa: F401
    CHECKSUMS,
    SHARD_CHECKSUM,
    ShardInfo,
    column_range,
    column_ranges,
    crc_of,
    shard_info,
)
from phigenesis.data.cache.files import (  # noqa: F401
    CACHE_FORMAT,
    DEFAULT_SHARD_MAX_BYTES,
    MANIFEST_NAME,
    MAX_FILE_NAME_BYTES,
    MAX_SCENE_ID_CHARS,
    SHARDS_DIR,
    STAGING_DIR,
    SWAP_MARKER,
    TMP_MARKER,
    CacheWriteError,
    atomic_write_bytes,
    crc32c_file,
    fsync_dir,
    os_reason,
    safe_name,
    scene_id_problem,
    sha256_file,
)
from phigenesis.data.cache.manifest import (  # noqa: F401
    CRC32_MAX,
    SCENE_STATUSES,
    Manifest,
    SceneEntry,
    parse_manifest,
    resolve_shard_path,
)
from phigenesis.data.cache.reader import (  # noqa: F401
    FRAME_KEY_COLUMNS,
    CacheReader,
    ShardReader,
)
from phigenesis.data.cache.sink import (  # noqa: F401
    FLUSH_BYTES,
)
from phigenesis.data.cache.verify import (  # noqa: F401
    VerifyReport,
    verify_cache,
)
from phigenesis.data.cache.writer import (  # noqa: F401
    ShardWriter,
)
from phigenesis.errors import CacheError, PrepError  # noqa: F401
