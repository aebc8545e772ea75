"""A least-recently-used cache bounded by the bytes of its values: :class:`BoundedCache`.

Training draws the same clips again and again from a cache of a few hundred frames; what a clip
costs to prepare and does not depend on the weights (its frames decoded and resized, the frozen
VAE's features) is kept here instead of being computed again each time it is drawn. The bound is
the caller's (a config value): when a new value would pass it, the least recently used ones go.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable
from typing import Generic, TypeVar

import numpy as np
import torch

V = TypeVar("V")


def tensor_bytes(values: Iterable[object]) -> int:
    """Bytes held by the tensors and arrays among ``values`` (others count 0)."""
    total = 0
    for v in values:
        if isinstance(v, torch.Tensor):
            total += v.numel() * v.element_size()
        elif isinstance(v, np.ndarray):
            total += v.nbytes
    return total


class BoundedCache(Generic[V]):
    """Values by key, at most ``max_bytes`` of them (as ``size_of`` counts them); least recently
    used out first. ``max_bytes`` 0 keeps nothing. ``hits`` and ``misses`` count lookups."""

    def __init__(self, max_bytes: int, size_of: Callable[[V], int]):
        if max_bytes < 0:
            raise ValueError(f"BoundedCache: max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.size_of = size_of
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self._values: OrderedDict[Hashable, tuple[V, int]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._values)

    def get_or_make(self, key: Hashable, make: Callable[[], V]) -> V:
        """The value of ``key``, made by ``make()`` (and kept if it fits) when absent."""
        found = self._values.get(key)
        if found is not None:
            self._values.move_to_end(key)
            self.hits += 1
            return found[0]
        self.misses += 1
        value = make()
        size = self.size_of(value)
        if size <= self.max_bytes:
            while self.bytes + size > self.max_bytes:
                _, (_, dropped) = self._values.popitem(last=False)
                self.bytes -= dropped
            self._values[key] = (value, size)
            self.bytes += size
        return value
