"""The byte-bounded LRU cache training keeps prepared clips and VAE features in."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from phigenesis.data.memory_cache import BoundedCache, tensor_bytes


def test_tensor_bytes_counts_tensors_and_arrays_only() -> None:
    values = [torch.zeros(3, 4), torch.zeros(5, dtype=torch.uint8), np.zeros(2, np.float64), "x", 7]
    assert tensor_bytes(values) == 48 + 5 + 16


def test_least_recently_used_values_go_first_and_the_bound_holds() -> None:
    cache: BoundedCache[bytes] = BoundedCache(10, len)
    made: list[str] = []

    def make(key: str, size: int):
        return lambda: made.append(key) or bytes(size)

    cache.get_or_make("a", make("a", 4))
    cache.get_or_make("b", make("b", 4))
    cache.get_or_make("a", make("a", 4))  # a found, and now the most recent
    cache.get_or_make("c", make("c", 4))  # 12 bytes would pass 10: b, the least recent, goes
    assert made == ["a", "b", "c"] and cache.bytes == 8 and len(cache) == 2
    cache.get_or_make("a", make("a", 4))
    cache.get_or_make("b", make("b", 4))  # made again
    assert made == ["a", "b", "c", "b"] and cache.hits == 2 and cache.misses == 4
    big = cache.get_or_make("big", make("big", 11))  # larger than the bound: returned, not kept
    assert len(big) == 11 and "big" not in cache._values and cache.bytes <= 10
    nothing: BoundedCache[bytes] = BoundedCache(0, len)
    nothing.get_or_make("a", make("a", 1))
    nothing.get_or_make("a", make("a", 1))
    assert len(nothing) == 0 and nothing.misses == 2
    with pytest.raises(ValueError, match="max_bytes"):
        BoundedCache(-1, len)
