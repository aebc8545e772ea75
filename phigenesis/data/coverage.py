"""What a scene's cache rows hold, per camera: the share of pixels with a sparse depth, a dense
depth and a pseudo label, counted as the rows are written (after the last stage), so the log
says what the cache holds rather than what an intermediate stage made.

Entry point: :class:`SceneCoverage` (``add`` each written frame, then ``report``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from phigenesis import taxonomy as tx
from phigenesis.data.records import Frame

log = logging.getLogger("phigenesis.prep")


@dataclass
class CameraCounts:
    """Pixel counts of one camera over a scene's written frames (a map absent from a frame
    counts its pixels as not covered)."""

    pixels: int = 0
    with_depth: int = 0
    sparse: int = 0
    dense: int = 0
    with_pseudo: int = 0
    pseudo: int = 0

    def share(self, count: int, of: int) -> float:
        return count / of if of else 0.0


class SceneCoverage:
    """Per-camera coverage of a scene's written frames, logged once per scene."""

    def __init__(self, scene_id: str):
        self.scene_id = scene_id
        self.frames = 0
        self.cameras: dict[str, CameraCounts] = {}

    def add(self, frame: Frame) -> None:
        """Counts the pixels of ``frame``'s cameras with a sparse / dense depth and a pseudo label."""
        self.frames += 1
        for cam in frame.cameras:
            c = self.cameras.setdefault(cam.name, CameraCounts())
            pixels = cam.calibration.width * cam.calibration.height
            c.pixels += pixels
            if cam.depth is not None:
                c.with_depth += pixels
                c.sparse += int(np.count_nonzero(cam.depth.sparse_m > 0))
                if cam.depth.dense_m is not None:
                    c.dense += int(np.count_nonzero(cam.depth.dense_m > 0))
            if cam.pseudo is not None:
                c.with_pseudo += pixels
                c.pseudo += int(np.count_nonzero(cam.pseudo.semantic != tx.IGNORE_ID))

    def report(self) -> None:
        """Logs one INFO line of the shares per camera (the stages warn about thin maps:
        ``densify_depth`` about a thin sparse depth, ``pseudo_semantics`` about thin labels)."""
        depth = {n: c for n, c in self.cameras.items() if c.with_depth}
        pseudo = {n: c for n, c in self.cameras.items() if c.with_pseudo}
        if not depth and not pseudo:
            return
        parts = []
        for name, c in self.cameras.items():
            figures = []
            if c.with_depth:
                figures.append(
                    f"sparse {100 * c.share(c.sparse, c.with_depth):.1f} %, "
                    f"dense {100 * c.share(c.dense, c.with_depth):.1f} %"
                )
            if c.with_pseudo:
                figures.append(f"pseudo labels {100 * c.share(c.pseudo, c.with_pseudo):.1f} %")
            if figures:
                parts.append(f"{name} ({'; '.join(figures)})")
        log.info(
            "scene %s: what the cache holds over %d frames, share of pixels: %s",
            self.scene_id,
            self.frames,
            ", ".join(parts),
        )
