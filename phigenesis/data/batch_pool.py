"""Pooled shared-memory buffers for batches that DataLoader workers send to the main process.

A batch travels as one flat uint8 buffer holding all its tensors, rebuilt as views of it. In a
DataLoader worker that buffer is one of a few shared-memory segments the worker reuses batch
after batch (:class:`WorkerPool`): a fresh segment costs its creation, a file descriptor passed
to the main process and, in both processes, a page fault (and the kernel zeroing a page) for
every 4 KiB of it, which on 2 cores cost more than decoding a frame of 160x240 images. A pooled
segment is sent once; afterwards a batch names its slot, and the main process views the mapping
it already holds. :func:`~phigenesis.data.loader.collate_frames` builds the batch straight in a
segment (:func:`allocate`), so that :func:`pack` sends it without copying; a batch built
elsewhere is copied into a free segment.

Lifetime rule: **a pooled segment is reused only after the main process has freed every tensor
of the batch it carries.** The rebuilt batch's tensors share one storage; when the last of them
(or of their views, or of the numpy arrays made from them) is freed, the slot is marked free in
a small shared control array, and only then may its worker write the slot again. Holding a batch,
or any tensor from it, is therefore always safe: it only keeps that segment out of the pool. A
worker whose segments are all held sends its batch in a fresh segment, as without a pool, and
never waits. In the worker, a batch belongs to the main process once it has been sent (the
DataLoader never touches it again); one collated but never sent frees its segment when dropped.

Each worker keeps at most :data:`SLOTS_PER_WORKER` segments, each as large as the largest batch
it carried (plus 1/8 for variable-size LiDAR), created only when that many are in use at once
(the DataLoader's prefetched batches plus the ones the training loop holds). The main process
keeps a pool's segments mapped while its worker lives: they are dropped when a new pool
registers and the worker's process is gone, and in every process forked from it.
"""

from __future__ import annotations

import math
import os
import secrets
import threading
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

#: Most segments one worker keeps; when all are held it sends batches in fresh segments.
SLOTS_PER_WORKER = 4
#: Byte alignment of each tensor inside a buffer.
ALIGN = 64
#: Segment sizes are rounded up to this many bytes.
SEGMENT_GRANULE = 1 << 16
_FREE, _BUSY = 0, 1
#: Control array rows: one per slot ``[state, generation the main process has mapped]``, then one
#: ``[1 once the main process has registered the pool, 0]``.
_STATE, _MAPPED = 0, 1

#: Where each packed tensor lies in its buffer: (byte offset, dtype, shape).
Spec = tuple[int, torch.dtype, tuple[int, ...]]


def layout(shapes: list[tuple[tuple[int, ...], torch.dtype]]) -> tuple[list[Spec], int]:
    """The specs of tensors of these (shape, dtype) packed back to back (each at a multiple of
    ALIGN) and the total bytes."""
    specs, total = [], 0
    for shape, dtype in shapes:
        specs.append((total, dtype, tuple(shape)))
        total += (math.prod(shape) * dtype.itemsize + ALIGN - 1) // ALIGN * ALIGN
    return specs, total


def _fill(buffer: torch.Tensor, specs: list[Spec], tensors: list[torch.Tensor]) -> None:
    for (offset, dtype, shape), t in zip(specs, tensors, strict=True):
        buffer[offset : offset + t.numel() * t.element_size()].view(dtype).view(shape).copy_(t)


def views(buffer: torch.Tensor, specs: list[Spec]) -> list[torch.Tensor]:
    """The tensors described by ``specs``, as views of ``buffer``."""
    return [
        buffer[o : o + math.prod(shape) * dtype.itemsize].view(dtype).view(shape) for o, dtype, shape in specs
    ]


def _new_shared(nbytes: int) -> torch.Tensor:
    """A uint8 tensor of ``nbytes`` in a new shared-memory segment (torch's sharing strategy)."""
    return torch.empty(0, dtype=torch.uint8).set_(torch.UntypedStorage._new_shared(nbytes))


# --------------------------------------------------------------------------------------------
# Worker side


@dataclass
class _Segment:
    tensor: torch.Tensor  # uint8 [capacity], shared memory
    generation: int


class WorkerPool:
    """The segments of one worker process, leased to one batch at a time (see the module docstring).

    Only the process that created the pool writes its segments; the main process only marks a
    slot free, in the shared ``control`` array, once the batch it carried has been freed.
    """

    def __init__(self, slots: int = SLOTS_PER_WORKER):
        self.key = (os.getpid(), secrets.token_hex(8))
        self.control = _new_shared((slots + 1) * 2 * 8).view(torch.int64).view(slots + 1, 2)
        self.control.zero_()
        self._control = self.control.numpy()
        self.segments: list[_Segment | None] = [None] * slots
        self._generations = 0
        self._leases = 0
        #: Slots reserved by :meth:`reserve` and not yet sent: slot -> (lease id, bytes).
        self._reserved: dict[int, tuple[int, int]] = {}
        self._lock = threading.RLock()
        #: Batches sent in pooled segments, in fresh segments, and segments created (for tests).
        self.sent_pooled = self.sent_fresh = self.created = 0

    def acquire(self, nbytes: int) -> int | None:
        """A free slot holding at least ``nbytes``, now marked busy; None if every slot is held.

        A free slot that is too small is given a larger segment (empty slots are filled first)."""
        with self._lock:
            free = [i for i in range(len(self.segments)) if self._control[i, _STATE] == _FREE]
            fits = [i for i in free if (s := self.segments[i]) is not None and s.tensor.numel() >= nbytes]
            if fits:
                slot = min(fits, key=lambda i: self.segments[i].tensor.numel())  # type: ignore[union-attr]
            elif free:
                empty = [i for i in free if self.segments[i] is None]
                slot = empty[0] if empty else free[0]
                capacity = -(-(nbytes + nbytes // 8) // SEGMENT_GRANULE) * SEGMENT_GRANULE
                self._generations += 1
                self.segments[slot] = _Segment(_new_shared(capacity), self._generations)
                self.created += 1
            else:
                return None
            self._control[slot, _STATE] = _BUSY
            return slot

    def reserve(self, nbytes: int) -> torch.Tensor | None:
        """A uint8 tensor of ``nbytes`` in a free slot, for a batch to be built in and sent without a
        copy (:meth:`claim`); None if every slot is held. Until the batch is sent the slot stays
        this process's: it is freed again when the tensor and all its views are."""
        with self._lock:
            slot = self.acquire(nbytes)
            if slot is None:
                return None
            self._leases += 1
            self._reserved[slot] = (self._leases, nbytes)
            segment = self.segments[slot]
            assert segment is not None
            lease = segment.tensor.numpy()[:nbytes]
            weakref.finalize(lease, self._unreserve, slot, self._leases).atexit = False
            return torch.from_numpy(lease)

    def _unreserve(self, slot: int, lease: int) -> None:
        if os.getpid() != self.key[0]:
            return  # a forked child dropping what it inherited: not its pool
        with self._lock:
            if self._reserved.get(slot, (None, 0))[0] == lease:  # never sent: the slot is free again
                del self._reserved[slot]
                self._control[slot, _STATE] = _FREE

    def claim(self, tensors: list[torch.Tensor]) -> tuple[int, list[Spec], int] | None:
        """(slot, specs, bytes) if ``tensors`` all lie contiguously in one reserved slot, which
        passes to the main process; None otherwise."""
        if not tensors:
            return None  # nothing to place: never take another batch's reservation
        with self._lock:
            for slot, (_lease, nbytes) in self._reserved.items():
                segment = self.segments[slot]
                assert segment is not None
                base = segment.tensor.data_ptr()
                specs = []
                for t in tensors:
                    offset = t.data_ptr() - base if t.numel() else 0
                    if not (t.is_contiguous() and 0 <= offset <= nbytes - t.numel() * t.element_size()):
                        break
                    specs.append((offset, t.dtype, tuple(t.shape)))
                else:
                    del self._reserved[slot]
                    return slot, specs, nbytes
            return None


_worker_pool: WorkerPool | None = None


def worker_pool() -> WorkerPool | None:
    """This process's pool if it is a DataLoader worker, else None."""
    global _worker_pool
    if torch.utils.data.get_worker_info() is None:
        return None
    if _worker_pool is None:
        _worker_pool = WorkerPool(SLOTS_PER_WORKER)
    return _worker_pool


# --------------------------------------------------------------------------------------------
# Main-process side


class _Attached:
    """A worker pool as the main process holds it: the control array and each slot's mapping."""

    def __init__(self, control: torch.Tensor):
        self.control = control.numpy()
        self.segments: dict[int, tuple[int, np.ndarray]] = {}


_attached: dict[tuple[int, str], _Attached] = {}
_attach_lock = threading.Lock()


def _forget_all() -> None:
    """In a forked child: drop the parent's mappings (they would keep its workers' pages alive)."""
    global _worker_pool
    _attached.clear()
    _worker_pool = None


os.register_at_fork(after_in_child=_forget_all)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _release(control: np.ndarray, slot: int, pid: int) -> None:
    if os.getpid() == pid:  # not in a forked child dropping a batch it inherited
        control[slot, _STATE] = _FREE


def attached_pools() -> int:
    """How many worker pools this process holds mappings of (for tests)."""
    return len(_attached)


def _rebuild_pooled(
    key: tuple[int, str],
    control: torch.Tensor | None,
    slot: int,
    generation: int,
    segment: torch.Tensor | None,
    nbytes: int,
    specs: list[Spec],
) -> list[torch.Tensor]:
    with _attach_lock:
        pool = _attached.get(key)
        if pool is None:
            if control is None:
                raise RuntimeError(f"a batch names the unknown shared-memory pool {key} of another process")
            for other in [k for k in _attached if not _process_alive(k[0])]:
                del _attached[other]
            pool = _attached[key] = _Attached(control)
            pool.control[-1, _STATE] = 1
        if segment is not None:
            pool.segments[slot] = (generation, segment.numpy())
            pool.control[slot, _MAPPED] = generation
    mapped_generation, mapped = pool.segments[slot]
    if mapped_generation != generation:
        raise RuntimeError(f"pool {key} slot {slot}: generation {generation} was never sent")
    lease = mapped[:nbytes]  # a new array per batch: its death frees the slot
    finalizer = weakref.finalize(lease, _release, pool.control, slot, os.getpid())
    finalizer.atexit = False
    return views(torch.from_numpy(lease), specs)


def _rebuild_plain(buffer: torch.Tensor, specs: list[Spec]) -> list[torch.Tensor]:
    return views(buffer, specs)


# --------------------------------------------------------------------------------------------


def _ticket(pool: WorkerPool, slot: int, nbytes: int, specs: list[Spec]) -> tuple[Any, tuple[Any, ...]]:
    """What the main process needs to view a batch sent in ``slot``: the segment (and the pool's
    control array) only the first time it sees them."""
    segment = pool.segments[slot]
    assert segment is not None
    control = pool._control
    pool.sent_pooled += 1
    return _rebuild_pooled, (
        pool.key,
        None if control[-1, _STATE] else pool.control,
        slot,
        segment.generation,
        None if control[slot, _MAPPED] == segment.generation else segment.tensor,
        nbytes,
        specs,
    )


def allocate(nbytes: int) -> torch.Tensor | None:
    """In a DataLoader worker, a uint8 tensor of ``nbytes`` in a pooled segment to build a batch in,
    so that :func:`pack` sends it without copying; None elsewhere or when no segment is free."""
    pool = worker_pool()
    return pool.reserve(nbytes) if pool is not None and nbytes else None


def pack(tensors: list[torch.Tensor]) -> tuple[Any, tuple[Any, ...]]:
    """``(rebuild, args)`` such that ``rebuild(*args)`` returns copies of ``tensors`` as views of one
    buffer, for a ``__reduce__``.

    In a DataLoader worker the buffer is the pooled segment the tensors were built in
    (:func:`allocate`), else a pooled segment they are copied into when one is free (see the module
    docstring), else a fresh one; elsewhere it is ordinary memory.
    """
    pool = worker_pool()
    if pool is not None and (claimed := pool.claim(tensors)) is not None:
        slot, specs, nbytes = claimed
        return _ticket(pool, slot, nbytes, specs)
    specs, total = layout([(tuple(t.shape), t.dtype) for t in tensors])
    slot = pool.acquire(total) if pool is not None and total else None
    if pool is None or slot is None:
        if pool is not None:
            pool.sent_fresh += 1
        buffer = _new_shared(total) if pool is not None else torch.empty(total, dtype=torch.uint8)
        _fill(buffer, specs, tensors)
        return _rebuild_plain, (buffer, specs)
    segment = pool.segments[slot]
    assert segment is not None
    _fill(segment.tensor, specs, tensors)
    return _ticket(pool, slot, total, specs)
