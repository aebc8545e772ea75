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


def keep_freed_memory() -> bool:
    """Sets glibc's trim and mmap thresholds for this process and, through the environment, for
    processes it starts; True if this process's allocator took them."""
    if os.environ.get("PHIGENESIS_MALLOC") == "0" or platform.libc_ver()[0] != "glibc":
        return False
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(TRIM_THRESHOLD_BYTES))
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MMAP_THRESHOLD_BYTES))
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        taken = libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
        taken &= libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    except (OSError, AttributeError) as error:
        logger.debug("malloc thresholds left as they were: %s", error)
        return False
    return bool(taken)


__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "keep_freed_memory"]
