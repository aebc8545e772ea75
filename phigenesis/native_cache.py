"""Where compiled parts of the package live, and what a build depends on beyond its source.

Native code (the CPU rasterizer, the data kernels) is compiled on first use into a cache
folder, once per machine: ``$PHIGENESIS_NATIVE_DIR`` if set, else
``$XDG_CACHE_HOME/phigenesis/native`` (``~/.cache/...``). Builds use ``-march=native``, so a build
folder's name hashes this CPU's instruction set too (:func:`cpu_flags`): a shared home never hands
one machine another's build. ``PHIGENESIS_NATIVE=0`` turns every native part off.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import platform
import uuid
from collections.abc import Iterator
from pathlib import Path

#: errno values of a file system that cannot flock (NFS without lockd, some FUSE mounts).
NO_FLOCK = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL})


def cache_root() -> Path:
    """The folder holding native builds (see the module docstring)."""
    if os.environ.get("PHIGENESIS_NATIVE_DIR"):
        return Path(os.environ["PHIGENESIS_NATIVE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "phigenesis" / "native"


def cpu_flags() -> str:
    """This CPU's instruction-set flags line (``/proc/cpuinfo``), else the processor's name."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def native_enabled() -> bool:
    """False when ``PHIGENESIS_NATIVE=0`` turns native code off."""
    return os.environ.get("PHIGENESIS_NATIVE", "1") != "0"


@contextlib.contextmanager
def build_lock(build_dir: Path) -> Iterator[bool]:
    """Holds an exclusive ``flock`` on ``build_dir/.build.lock`` for a build (or a load) of what the
    folder holds; yields whether the lock is held (False on a file system that cannot flock).

    The kernel releases a flock when its holder exits, however it exits, so this lock never
    outlives a killed build, unlike a lock *file* whose existence is the lock."""
    build_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(build_dir / ".build.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            held = True
        except OSError as error:
            if error.errno not in NO_FLOCK:
                raise
            held = False
        yield held
    finally:
        os.close(fd)  # closing the descriptor releases the flock


def write_replacing(path: Path, data: bytes, marker: str = ".tmp-") -> None:
    """Writes ``data`` to ``path`` under a unique temporary name (``path`` + ``marker`` + 8 hex
    digits), flushed, fsynced and renamed over ``path``, so a reader sees the old file or the whole
    new one; on failure the temporary file is removed and the error raised as it came."""
    tmp = path.with_name(f"{path.name}{marker}{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def write_source_copy(path: Path, data: bytes) -> None:
    """Writes ``data`` (a source file staged for a build) to ``path`` (:func:`write_replacing`),
    so a process staging the same sources sees the old file or the whole new one."""
    write_replacing(path, data)
