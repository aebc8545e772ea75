"""Keep freed memory in the process instead of handing it back to the kernel after every frame.

Converting a Waymo frame allocates tens of MB (the inflated range images, the points, the Arrow
row) and frees them before the next frame. With glibc's defaults the free space at the top of the
heap is returned to the kernel as soon as it passes twice the largest block seen, so the next
frame takes every page again as a page fault on zeroed memory: on the Waymo benchmark that was a
sixth of the v1 reader's time (``benchmarks/waymo.py``). :func:`keep_freed_memory` raises the two
thresholds involved, process-wide, as ``MALLOC_TRIM_THRESHOLD_`` and ``MALLOC_MMAP_THRESHOLD_``
would at start-up; ``phigenesis-prep`` calls it, and the worker processes it spawns inherit the
same settings through those variables. The cost is that a process keeps up to
:data:`TRIM_THRESHOLD_BYTES` of freed memory after a frame, as its peak resident size already
counted it. Nothing happens on a C library other than glibc; ``PHIGENESIS_MALLOC=0`` turns it off.

:func:`avoid_huge_page_faults` turns transparent huge pages off for the process (and the processes
it starts). NumPy advises the kernel to back every array of 4 MiB or more with 2 MiB pages, so one
page fault zeroes 2 MiB, and on a virtual machine whose host takes free memory back (free page
reporting) each such fault also waits for the host, which can make a frame's time bimodal
(``benchmarks/waymo.py``; docs/design/waymo.md, "Huge pages off"). A converter's arrays live for
one frame, so huge pages buy it nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform

logger = logging.getLogger(__name__)

#: Blocks up to this size come from the heap (and are reused) rather than from a fresh mapping.
MMAP_THRESHOLD_BYTES = 32 << 20
#: Free memory at the top of the heap is returned to the kernel only beyond this.
TRIM_THRESHOLD_BYTES = 256 << 20

# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def keep_freed_memory() -> bool:
    """Sets glibc's trim and mmap thresholds for this process and, through the environment, for
    processes it starts; True if this process's allocator took them."""
    if os.environ.get("PHIGENESIS_MALLOC") == "0" or platform.libc_ver()[0] != "glibc":
        return False
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(TRIM_THRESHOLD_BYTES))
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MMAP_THRESHOLD_BYTES))
    try:
        libc = _libc()
        taken = libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
        taken &= libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    except (OSError, AttributeError) as error:
        logger.debug("malloc thresholds left as they were: %s", error)
        return False
    return bool(taken)


# prctl options (linux/prctl.h).
_PR_SET_THP_DISABLE = 41
_PR_GET_THP_DISABLE = 42


def _prctl(option: int, value: int = 0) -> int:
    return int(_libc().prctl(option, value, 0, 0, 0))


def avoid_huge_page_faults() -> bool:
    """Turns transparent huge pages off for this process and its children (Linux's
    ``PR_SET_THP_DISABLE``, inherited across fork and exec); True if the kernel took it."""
    if os.environ.get("PHIGENESIS_MALLOC") == "0" or platform.system() != "Linux":
        return False
    try:
        return _prctl(_PR_SET_THP_DISABLE, 1) == 0
    except (OSError, AttributeError) as error:
        logger.debug("transparent huge pages left as they were: %s", error)
        return False


def huge_pages_disabled() -> bool:
    """Whether transparent huge pages are off for this process (False off Linux)."""
    if platform.system() != "Linux":
        return False
    try:
        return _prctl(_PR_GET_THP_DISABLE) == 1
    except (OSError, AttributeError):
        return False


__all__ = [
    "MMAP_THRESHOLD_BYTES",
    "TRIM_THRESHOLD_BYTES",
    "avoid_huge_page_faults",
    "huge_pages_disabled",
    "keep_freed_memory",
]
