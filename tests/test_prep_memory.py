"""Memory of a prep run is bounded by one frame plus the scene's LiDAR map, not by its length.

Frames stream through the stages and the writer (:class:`~phigenesis.data.records.LazyFrames`):
nothing may keep every frame's images or maps. The peak of Python's allocations (tracemalloc:
numpy's buffers included) over a whole small scene of 12 frames must stay within 1.2x that of a
3-frame one, plus the map's own growth (:data:`MAP_BYTES_PER_POINT` per raw LiDAR point: the
map and the aggregation's chunks are at most that).
"""

from __future__ import annotations

import gc
import tracemalloc
from pathlib import Path

from phigenesis import prep
from tests.conftest import TINY_PREP_ARGS

#: Allowance per raw LiDAR point of the scene for the static map and its aggregation: 12 bytes
#: per kept float32 point plus the sort keys of a chunk being down-sampled.
MAP_BYTES_PER_POINT = 48
#: Raw LiDAR points per frame of the tiny config (16 beams x 256 columns).
POINTS_PER_FRAME = 16 * 256


def _peak_bytes(out: Path, frames: int) -> int:
    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": frames}
    gc.collect()
    tracemalloc.start()
    try:
        summary = prep.synthetic(out, progress=False, **args)  # type: ignore[arg-type]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert summary.frames_written == frames
    return peak


def test_peak_memory_does_not_grow_with_the_number_of_frames(tmp_path: Path) -> None:
    _peak_bytes(tmp_path / "warm", 1)  # imports and one-off tables outside the measurement
    short = _peak_bytes(tmp_path / "short", 3)
    long = _peak_bytes(tmp_path / "long", 12)
    allowance = MAP_BYTES_PER_POINT * POINTS_PER_FRAME * (12 - 3)
    assert long <= 1.2 * short + allowance, (short, long, allowance)
