"""Thin vertical structures, tree crowns and vehicles' sides (steps 6-6c of
:mod:`phigenesis.data.stages.complete`): the vertical plane facing the camera through a pole's
base or through the median of a crown's or a vehicle's known points.

:class:`_ThinFills` is mixed into :class:`~phigenesis.data.stages.completion.completer._Completer`
and works on its state (segment tables, outputs updated in place, ``_fill``, ``horizontal``).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.completion.params import (
    ORIGIN,
    Mask,
)
from phigenesis.data.stages.completion.planes import PlaneFits
from phigenesis.data.stages.completion.segments import (
    _nearest_pixel,
)


class _ThinFills:
    """Steps 6-6c of the completion (thin structures, crowns, vehicles), as methods of
    :class:`~phigenesis.data.stages.completion.completer._Completer` (its state and its ``_fill``)."""

    def fill_thin(self, s: int) -> None:
        """A thin vertical segment: the vertical plane facing the camera through its base (step 6),
        if its evidence shows an upright structure (depths that agree and rise ``min_height_m``; a
        strip of ground does neither)."""
        p = self.p
        idx = self.pixels(s)
        kn = idx[self.thin_depth[idx] > 0]
        empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
        if len(empty) == 0:
            return
        w = self.shape[1]
        z = self.thin_depth[kn]
        tol = p.inlier_tol_m + p.inlier_tol_rel * float(np.median(z))
        if float(np.median(np.abs(z - np.median(z)))) > tol:
            return
        height = np.sort((self.rays[kn] * z[:, None]) @ self.up)
        if height[-1 - len(height) // 20] - height[len(height) // 20] < p.min_height_m:  # 95th - 5th
            return
        rows = kn // w
        base = kn[rows >= rows.max() - p.base_band_ref_px * self.scale]
        z_base = float(np.median(self.thin_depth[base]))
        spread = float(np.median(np.abs(self.thin_depth[base] - z_base)))
        point = self.rays[base].mean(axis=0) * z_base
        facing = self.horizontal(point)  # horizontal direction to the base
        norm = float(np.linalg.norm(facing))
        on = np.abs(z - z_base) <= tol
        # The low-confidence sparse depths alone, where foreground and background leak, do not do.
        if norm < 1e-6 or spread > tol or np.count_nonzero(on & self.known[kn]) < p.min_thin_trusted:
            return
        n = facing / norm
        fits = PlaneFits(
            *(n[None], np.array([-float(n @ point)]), np.ones(1, np.int8), np.array([spread])),
            *(np.ones(1), np.array([z_base]), np.array([float(np.mean(self.thin_conf[base]))])),
            np.zeros(1, bool),
        )
        # Only the columns that hold the structure: those of its evidence (+-1 pixel).
        allowed = np.zeros(w + 2, bool)
        cols = kn[on] % w + 1
        allowed[cols - 1] = allowed[cols] = allowed[cols + 1] = True
        empty = empty[allowed[empty % w + 1]]
        dist = np.maximum(rows[on].min() - empty // w, 0).astype(np.float32)  # rows above the evidence
        self._fill(empty, fits, 0, dist, 1.0, ORIGIN["vertical"], cap=p.vertical_confidence)

    def fill_crown(self, s: int, max_spread: float | None = None) -> None:
        """A green segment no plane explains (a tree's crown) with enough dense depth of about one
        depth (``crown_max_spread``: the spread of its known depths relative to their median)
        takes the vertical plane facing the camera through its known points' median, at
        ``crown_confidence`` at most (origin ``vertical``); with ``max_spread``, a vehicle's
        segment (6c)."""
        rs, cs = self.crop(s)
        self.fill_facing(self.pixels(s), rs, cs, self.segments[rs, cs] == s, max_spread)

    def fill_canopies(self, segs: Mask) -> None:
        """A tree's crown is many small green segments, most above the LiDAR's top beam: each
        connected region of the pixels above the horizon (and not blue) of the segments ``segs``
        (green, without things) is filled as one crown (:meth:`fill_facing`) from the depths its
        lower part holds."""
        # Not the sky a segment took in at the crown's rim: no pixel of excess blue, nor its
        # neighbours.
        mask = segs[self.flat] & ((self.rays @ self.up) > 0) & ~self.sky_rim
        count, comp = cv2.connectedComponents(mask.reshape(self.shape).view(np.uint8), connectivity=4)
        if count <= 1:
            return
        flat = comp.reshape(-1)
        order = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order], np.arange(count + 1))
        w = self.shape[1]
        for c in range(1, count):
            px = order[starts[c] : starts[c + 1]]
            if not np.any(self.fillable[px] & (self.depth[px] == 0)):
                continue
            r, q = np.divmod(px, w)
            rs, cs = slice(int(r.min()), int(r.max()) + 1), slice(int(q.min()), int(q.max()) + 1)
            # A few known pixels in a large region are as often a facade's a segment took in, or
            # depth seen through the leaves, as the crown's.
            if np.count_nonzero(self.known[px]) >= self.p.canopy_min_known_share * len(px):
                self.fill_facing(px, rs, cs, comp[rs, cs] == c)

    def fill_facing(
        self, px: NDArray[np.intp], rs: slice, cs: slice, member: Mask, max_spread: float | None = None
    ) -> None:
        """Fills the empty pixels ``px`` (flat indices; ``member``: the same within the crop
        ``rs, cs``) with the vertical plane facing the camera through the median of their known
        points, if they are enough (``min_inliers``) and of about one depth (``max_spread``, by
        default ``crown_max_spread``), at ``crown_confidence`` at most (origin ``vertical``)."""
        p = self.p
        kn = px[self.known[px]]
        if len(kn) < p.min_inliers:
            return
        z = self.depth[kn]
        z_mid = float(np.median(z))
        q25, q75 = np.percentile(z, [25, 75])
        if (q75 - q25) > (p.crown_max_spread if max_spread is None else max_spread) * z_mid:
            return
        point = np.median(self.rays[kn] * z[:, None], axis=0)
        facing = self.horizontal(point)
        norm = float(np.linalg.norm(facing))
        if norm < 1e-6:
            return
        n = facing / norm
        spread = float(q75 - q25)
        fits = PlaneFits(
            *(n[None], np.array([-float(n @ point)]), np.ones(1, np.int8), np.array([spread])),
            *(np.ones(1), np.array([z_mid]), np.array([float(np.mean(self.conf[kn]))])),
            np.zeros(1, bool),
        )
        empty = px[self.fillable[px] & (self.depth[px] == 0) & ~self.sky_rim[px]]
        w = self.shape[1]
        dist_map, _ = _nearest_pixel(self.known.reshape(self.shape)[rs, cs] & member)
        er, ec = np.divmod(empty, w)
        dist = dist_map[er - rs.start, ec - cs.start]
        keep = dist <= p.max_extrapolation_ref_px * self.scale
        self._fill(empty[keep], fits, 0, dist[keep], 1.0, ORIGIN["vertical"], cap=p.crown_confidence)
