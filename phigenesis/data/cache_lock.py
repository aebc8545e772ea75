"""One writer per cache directory: an advisory lock file that a run holds while it writes the cache.

Every command that writes a cache takes it: prep, ``phigenesis-render``, ``phigenesis-generate`` and
Stage 2's latent cache (:mod:`phigenesis.data.cache_run`). The lock is ``DIR/.phigenesis.lock``, held
with ``fcntl.flock`` by the coordinating process of a run (its worker processes write shards under
it) and holding that process's PID, host, start time and command as text. The flock is the
authority: the kernel releases it when its holder exits, however it exits, so a lock file left by a
killed run is free and is taken over (and logged). On a file system without flock the recorded PID
decides: a holder that no longer runs on this host has left a stale lock. Readers never lock. The
file is removed when its holder releases it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import socket
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from phigenesis.errors import PrepError
from phigenesis.native_cache import NO_FLOCK

LOCK_NAME = ".phigenesis.lock"
log = logging.getLogger("phigenesis.prep")

#: How long to wait for a holder that has taken the flock to finish writing its PID, in seconds.
_HOLDER_WRITE_WAIT_S = 1.0
#: How often to re-open a lock file that its releasing holder removed while we locked it.
_REOPEN_ATTEMPTS = 100


@dataclass(frozen=True)
class LockHolder:
    """The process a lock file names."""

    pid: int
    host: str
    started: str  # ISO 8601, UTC
    command: str = ""  # what the run writes: "prep", "render", ...; "" in lock files that name none

    def to_text(self) -> str:
        text = f"pid: {self.pid}\nhost: {self.host}\nstarted: {self.started}\n"
        return text + (f"command: {self.command}\n" if self.command else "")

    @classmethod
    def from_text(cls, text: str) -> LockHolder | None:
        """The holder a lock file's text names; None for an empty or garbled file."""
        fields = dict(line.split(": ", 1) for line in text.splitlines() if ": " in line)
        try:
            return cls(int(fields["pid"]), fields["host"], fields["started"], fields.get("command", ""))
        except (KeyError, ValueError):
            return None

    @classmethod
    def this_process(cls, command: str = "") -> LockHolder:
        started = datetime.now(timezone.utc).isoformat(timespec="seconds")
        return cls(os.getpid(), socket.gethostname(), started, command)

    def run_name(self) -> str:
        """The run as messages name it: "prep run", "render run"; "run" when the file names none."""
        return f"{self.command} run" if self.command else "run"

    def describe(self) -> str:
        return f"PID {self.pid} on {self.host}, started {self.started}"

    def is_running(self) -> bool | None:
        """Whether the holder still runs; None where that cannot be known (another host)."""
        if self.host != socket.gethostname():
            return None
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # it exists, under another user
            return True
        return True


class CacheLock:
    """The exclusive lock on a cache directory for one run that writes it. Use as a context manager.

    ``command`` names what the run writes ("prep", "render", "generate", "stage2-latents"); it is
    recorded in the lock file so that a refused run is told what holds the cache.
    :meth:`acquire` raises :class:`~phigenesis.errors.PrepError` naming the holder's PID when
    another run holds the lock; a lock left by a run that was killed is taken over with a log line.
    """

    def __init__(self, cache_dir: str | os.PathLike[str], command: str = "prep"):
        self.path = Path(cache_dir) / LOCK_NAME
        self.command = command
        self._fd: int | None = None

    def __enter__(self) -> CacheLock:
        self.acquire()
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.release()

    def acquire(self) -> None:
        """Takes the lock, or raises PrepError naming the run that holds it."""
        for _attempt in range(_REOPEN_ATTEMPTS):
            fd = self._open()
            try:
                previous = self._lock(fd)
            except BaseException:
                os.close(fd)
                raise
            if self._still_named(fd):
                break
            os.close(fd)  # the holder removed the file as we opened it: lock the new one
        else:
            raise PrepError(f"{self.path}: the lock file keeps being replaced; cannot lock the cache")
        if previous is not None:
            log.warning(
                "%s: taking over the lock left by a %s that no longer holds it (%s)",
                self.path,
                previous.run_name(),
                previous.describe(),
            )
        self._write_holder(fd)
        self._fd = fd

    def release(self) -> None:
        """Removes the lock file and releases the lock (a no-op if not held)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if self._still_named(fd):
                with contextlib.suppress(OSError):
                    self.path.unlink()
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def _open(self) -> int:
        """Opens (or creates) the lock file; never through a symbolic link, which could point
        anywhere, since the holder truncates and writes the file."""
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise PrepError(f"{self.path}: the cache's lock file is a symbolic link; remove it") from e
            raise PrepError(f"{self.path}: cannot create the cache's lock file ({e.strerror or e})") from e

    def _lock(self, fd: int) -> LockHolder | None:
        """Takes the flock on ``fd``; returns the stale holder it replaces (None if the file named
        none). Raises PrepError if a live run holds it."""
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise self._held_error(self._wait_for_holder(fd)) from None
        except OSError as e:
            if e.errno not in NO_FLOCK:
                raise PrepError(f"{self.path}: cannot lock ({e.strerror or e})") from e
            holder = _read_holder(fd)
            if holder is not None and holder.is_running() is not False:
                raise self._held_error(holder) from None
            return holder
        return _read_holder(fd)

    def _wait_for_holder(self, fd: int) -> LockHolder | None:
        """The holder of a taken flock, waiting briefly while it writes its PID."""
        deadline = time.monotonic() + _HOLDER_WRITE_WAIT_S
        while (holder := _read_holder(fd)) is None and time.monotonic() < deadline:
            time.sleep(0.02)
        return holder

    def _held_error(self, holder: LockHolder | None) -> PrepError:
        who = holder.describe() if holder is not None else "a process that has not written its PID yet"
        if holder is not None and holder.is_running() is False:
            who += ", which no longer runs, though a process it started still holds the lock"
        run = holder.run_name() if holder is not None else "run"
        return PrepError(
            f"{self.path.parent}: another {run} is writing this cache ({who}; lock file {self.path}); "
            "wait for it to finish or stop it, or choose another --out"
        )

    def _still_named(self, fd: int) -> bool:
        """Whether ``self.path`` is still the file open as ``fd`` (a releasing holder removes it)."""
        try:
            return os.lstat(self.path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            return False

    def _write_holder(self, fd: int) -> None:
        """Names this process in the lock file; the lock holds even if that write fails (a full
        disk): the flock, not the text, is what excludes other runs."""
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, LockHolder.this_process(self.command).to_text().encode(), 0)
            os.fsync(fd)


def _read_holder(fd: int) -> LockHolder | None:
    try:
        return LockHolder.from_text(os.pread(fd, 4096, 0).decode(errors="replace"))
    except OSError:
        return None
