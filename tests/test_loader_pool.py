"""Tests for phigenesis.data.batch_pool: pooled shared-memory segments for worker batches, and the
lifetime rule that a segment is reused only once every tensor of its batch is freed."""

from __future__ import annotations

import copy
import gc
import pickle
from multiprocessing.reduction import ForkingPickler
from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader

from phigenesis.data import batch_pool
from phigenesis.data.loader import FrameBatch, FrameDataset, collate_frames
from tests.test_loader import assert_same


@pytest.fixture
def pool(monkeypatch: pytest.MonkeyPatch) -> batch_pool.WorkerPool:
    """A pool that this process uses as if it were a DataLoader worker of itself."""
    pool = batch_pool.WorkerPool(slots=2)
    monkeypatch.setattr(batch_pool, "worker_pool", lambda: pool)
    yield pool
    batch_pool._attached.pop(pool.key, None)


def send(batch: FrameBatch) -> FrameBatch:
    """``batch`` sent through the pickler DataLoader queues use (shared memory by file descriptor)."""
    return ForkingPickler.loads(ForkingPickler.dumps(batch))


def make_batch(value: int, pixels: int = 1000) -> FrameBatch:
    return FrameBatch(
        {
            "images": torch.full((1, 2, 3, pixels), value, dtype=torch.uint8),
            "frame_index": torch.tensor([value]),
            "scene_id": ["s"],
            "lidar_points_ego": [torch.full((value + 1, 3), float(value))],
        }
    )


def storage_address(batch: FrameBatch) -> int:
    return batch["images"].untyped_storage().data_ptr()


def test_a_batch_sent_through_a_pooled_segment_arrives_unchanged(pool: batch_pool.WorkerPool) -> None:
    batch = make_batch(3)
    received = send(batch)
    assert_same(dict(received), dict(batch))
    assert isinstance(received, FrameBatch)
    assert (pool.sent_pooled, pool.sent_fresh) == (1, 0)


def test_a_freed_batch_gives_its_segment_back_for_the_next_one(pool: batch_pool.WorkerPool) -> None:
    first = send(make_batch(1))
    address = storage_address(first)
    del first
    gc.collect()
    second = send(make_batch(2))
    assert storage_address(second) == address
    assert pool.created == 1
    assert_same(dict(second), dict(make_batch(2)))


def test_held_batches_are_never_overwritten_and_extra_ones_travel_in_fresh_segments(
    pool: batch_pool.WorkerPool,
) -> None:
    held = [send(make_batch(v)) for v in range(4)]  # 2 pooled slots, then 2 fresh segments
    assert (pool.sent_pooled, pool.sent_fresh) == (2, 2)
    for v in range(4, 8):
        send(make_batch(v))  # dropped at once: fresh segments, the pool being held
    for v, batch in enumerate(held):
        assert_same(dict(batch), dict(make_batch(v)))
    assert pool.created == 2


def test_one_tensor_kept_from_a_batch_keeps_its_whole_segment_out_of_the_pool(
    pool: batch_pool.WorkerPool,
) -> None:
    first = send(make_batch(5))
    frame_index = first["frame_index"]
    image_row = first["images"][0, 1].numpy()  # a numpy view made from a tensor view
    del first
    gc.collect()
    address_held = frame_index.untyped_storage().data_ptr()
    others = [send(make_batch(v)) for v in (6, 7)]
    assert address_held not in {storage_address(b) for b in others}
    assert frame_index.tolist() == [5] and (image_row == 5).all()
    del frame_index, image_row
    gc.collect()
    assert storage_address(send(make_batch(8))) == address_held


def test_a_larger_batch_replaces_a_free_segment_that_is_too_small(pool: batch_pool.WorkerPool) -> None:
    send(make_batch(1, pixels=10))
    gc.collect()
    large = send(make_batch(2, pixels=200_000))
    assert_same(dict(large), dict(make_batch(2, pixels=200_000)))
    assert pool.created == 2 and pool.sent_fresh == 0


def samples(count: int) -> list[dict]:
    return [
        {
            "images": torch.full((2, 3, 4, 5), i, dtype=torch.uint8),
            "frame_index": i,
            "lidar_points_ego": torch.full((i + 1, 3), float(i)),
            "boxes_track_id": [f"t{i}"],
        }
        for i in range(count)
    ]


def test_a_batch_collated_in_a_worker_is_built_in_a_segment_and_sent_without_a_copy(
    pool: batch_pool.WorkerPool,
) -> None:
    batch = collate_frames(samples(3))
    segment = pool.segments[0]
    assert segment is not None and storage_address(batch) == segment.tensor.data_ptr()
    received = send(batch)
    assert_same(dict(received), dict(batch))
    assert storage_address(received) == segment.tensor.data_ptr()
    assert (pool.created, pool.sent_pooled, pool.sent_fresh) == (1, 1, 0)


def test_a_collated_batch_that_is_never_sent_gives_its_segment_back(pool: batch_pool.WorkerPool) -> None:
    address = storage_address(collate_frames(samples(2)))  # dropped at once
    gc.collect()
    assert storage_address(collate_frames(samples(2))) == address
    assert pool.created == 1


def test_a_collated_batch_given_a_foreign_tensor_is_copied_whole_into_another_segment(
    pool: batch_pool.WorkerPool,
) -> None:
    batch = collate_frames(samples(2))
    batch["extra"] = torch.arange(4)
    received = send(batch)
    assert_same(dict(received), dict(batch))
    assert storage_address(received) != storage_address(batch)
    del batch
    gc.collect()
    assert pool.created == 2
    send(make_batch(1))  # the slot reserved for the first batch is free again
    assert (pool.created, pool.sent_fresh) == (2, 0)


def test_outside_a_worker_a_batch_pickles_into_ordinary_memory(tiny_cache: Path) -> None:
    batch = collate_frames([FrameDataset(tiny_cache, fields=("images",))[0]])
    received = pickle.loads(pickle.dumps(batch))
    assert_same(dict(received), dict(batch))
    assert batch_pool.worker_pool() is None and not received["images"].is_shared()


def test_copying_a_batch_for_pin_memory_keeps_its_tensors() -> None:
    batch = make_batch(4)
    clone = copy.copy(batch)
    assert isinstance(clone, FrameBatch) and clone["images"] is batch["images"]


@pytest.mark.slow
def test_batches_held_across_epochs_of_a_worker_stay_intact_and_freed_ones_are_reused(
    tiny_cache: Path,
) -> None:
    dataset = FrameDataset(tiny_cache, fields=("images", "cameras", "lidar"))
    reference = list(DataLoader(dataset, batch_size=1, collate_fn=collate_frames))
    loader = DataLoader(
        dataset, batch_size=1, collate_fn=collate_frames, num_workers=1, persistent_workers=True
    )
    held = list(loader)  # more batches than the worker has slots: the rest come in fresh segments
    for _ in range(2):
        for i, batch in enumerate(loader):
            assert_same(dict(batch), dict(reference[i]), f"batch {i}")
    assert_same([dict(b) for b in held], [dict(b) for b in reference])
    del held, batch
    gc.collect()
    addresses = [storage_address(batch) for batch in loader]
    pooled = {
        mapped.ctypes.data for pool in batch_pool._attached.values() for _, mapped in pool.segments.values()
    }
    assert set(addresses) <= pooled and len(pooled) <= batch_pool.SLOTS_PER_WORKER


@pytest.mark.slow
def test_the_main_process_drops_the_segments_of_workers_that_have_exited(tiny_cache: Path) -> None:
    dataset = FrameDataset(tiny_cache, fields=("images",))
    loader = DataLoader(dataset, batch_size=2, collate_fn=collate_frames, num_workers=1)
    for _ in range(3):  # a new worker, and a new pool, each epoch
        for _batch in loader:
            pass
    assert batch_pool.attached_pools() == 1


def test_a_batch_without_tensors_never_takes_the_segment_reserved_for_another(
    pool: batch_pool.WorkerPool,
) -> None:
    being_built = collate_frames(samples(2))
    received = send(FrameBatch({"scene_id": ["s"]}))
    assert received == {"scene_id": ["s"]}
    assert_same(dict(send(being_built)), dict(being_built))
    assert pool.sent_pooled == 1  # the collated batch, from the segment it was built in
