"""The cache's files: its layout's names, atomic writes, whole-file digests, scene ids as file names.

A cache directory holds ``manifest.json`` (:data:`MANIFEST_NAME`), ``shards/`` (:data:`SHARDS_DIR`)
and, during an overwrite, ``.phigenesis-staging/`` (:data:`STAGING_DIR`). Every file is written
under a temporary name (:data:`TMP_MARKER`), flushed with fsync and renamed
(:func:`atomic_write_bytes`); a write that fails raises :class:`CacheWriteError` naming the file.
Scene ids name their shard files, so they are bounded (:func:`scene_id_problem`).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

import google_crc32c

from phigenesis.errors import PrepError
from phigenesis.native_cache import write_replacing

MANIFEST_NAME = "manifest.json"
SHARDS_DIR = "shards"
CACHE_FORMAT = "phigenesis-cache"
DEFAULT_SHARD_MAX_BYTES = 256 * 1024 * 1024
TMP_MARKER = ".tmp-"
#: Where an ``overwrite`` run builds the new version of a cache, inside the cache directory.
STAGING_DIR = ".phigenesis-staging"
#: Written into the staging folder once the new version is complete, before the old one is
#: touched: a run that finds it finishes the swap.
SWAP_MARKER = "swapping"


class CacheWriteError(PrepError, OSError):
    """A cache file could not be written (a full disk, ...): the message names the file and the
    system's reason. Its temporary file is removed; complete files stay."""


def os_reason(error: OSError) -> str:
    """The system's reason for ``error`` in words ("No space left on device")."""
    if error.strerror:
        return error.strerror
    code = error.args[0] if len(error.args) == 1 else None
    if isinstance(code, int):
        return os.strerror(code)
    return str(error) or type(error).__name__


# --------------------------------------------------------------------------------------------
# Atomic file writes


def fsync_dir(path: Path) -> None:
    """Flushes a directory entry (a rename) to disk, where the platform allows it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):  # some file systems cannot fsync a directory
            os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Writes ``data`` to ``path`` via a temporary file, fsync and rename.

    On failure the temporary file is removed and ``path`` is left as it was; an OSError becomes a
    :class:`CacheWriteError` naming ``path``."""
    path = Path(path)
    try:
        write_replacing(path, data, TMP_MARKER)
    except OSError as e:
        raise CacheWriteError(f"{path}: cannot write ({os_reason(e)})") from e
    fsync_dir(path.parent)


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def crc32c_file(path: Path, chunk: int = 1 << 22) -> int:
    """CRC-32C of a whole file (what a shard's ``file_crc32c`` records)."""
    crc = 0
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            crc = google_crc32c.extend(crc, block)
    return crc


def safe_name(scene_id: str) -> str:
    """A file-name-safe form of a scene id."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in scene_id)


#: The longest scene id a cache holds, in characters: its shard files are named after it.
MAX_SCENE_ID_CHARS = 200
#: The longest file name most file systems take (Linux's NAME_MAX), in bytes of UTF-8.
MAX_FILE_NAME_BYTES = 255


def scene_id_problem(scene_id: object) -> str | None:
    """Why ``scene_id`` cannot be a cache's scene id (None if it can): it names the scene's shard
    files (:func:`safe_name` plus ``-00000.arrow``), so it is a non-empty string of at most
    :data:`MAX_SCENE_ID_CHARS` characters without control characters, whose file-name form fits in
    200 bytes."""
    if not isinstance(scene_id, str):
        return "is not a string"
    if not scene_id:
        return "is empty"
    if len(scene_id) > MAX_SCENE_ID_CHARS:
        return (
            f"has {len(scene_id)} characters; a scene id has at most {MAX_SCENE_ID_CHARS} "
            "(it names the scene's shard files)"
        )
    if any(ord(c) < 32 or ord(c) == 127 for c in scene_id):
        return "holds a control character"
    if len(safe_name(scene_id).encode()) > MAX_SCENE_ID_CHARS:
        return f"takes {len(safe_name(scene_id).encode())} bytes as a file name; at most {MAX_SCENE_ID_CHARS}"
    return None
