"""Ground and facades beyond the LiDAR's data (steps 5, 6d and 7 of
:mod:`phigenesis.data.stages.complete`): a ground plane carried to the segments beside it, each
column of a wall climbing from its topmost known pixel, and vertical planes climbing into the
segments above them.

:class:`_FacadeFills` is mixed into :class:`~phigenesis.data.stages.completion.completer._Completer`
and works on its state (segment tables, outputs updated in place, ``_fill``, ``intersect``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.completion.params import (
    F32,
    F64,
    ORIGIN,
    Mask,
)
from phigenesis.data.stages.completion.planes import PlaneFits
from phigenesis.data.stages.completion.segments import (
    _adjacent_pixels,
)
from phigenesis.data.stages.densification.registry import REFERENCE_FOCAL_PX


class _FacadeFills:
    """Steps 5, 6d and 7 of the completion, as methods of
    :class:`~phigenesis.data.stages.completion.completer._Completer` (its state and its ``_fill``)."""

    def propagate(self, segs: NDArray[np.intp], fits: PlaneFits, source: Mask) -> None:
        """Fills each segment of ``segs`` (without depth) with the plane of the ``source`` segment
        it shares the longest boundary with, of at least ``min_boundary_ref_px``, if their mean
        colours are within ``propagate_color_tol`` (step 5)."""
        if len(segs) == 0 or not source.any():
            return
        i, j = self.boundary_pairs()
        a, b = self.flat[i].astype(np.int64), self.flat[j].astype(np.int64)
        keys, length = np.unique(np.concatenate([a * self.count + b, b * self.count + a]), return_counts=True)
        seg, nb = np.divmod(keys, self.count)
        want = np.zeros(self.count, bool)
        want[segs] = True
        mean = self.segment_colours()
        ok = want[seg] & source[nb] & (length >= self.p.min_boundary_ref_px * self.scale)
        ok &= np.linalg.norm(mean[seg] - mean[nb], axis=1) < self.p.propagate_color_tol
        seg, nb, length = seg[ok], nb[ok], length[ok]
        order = np.lexsort((-length, seg))  # by segment, longest boundary first
        seg, nb = seg[order], nb[order]
        first = np.concatenate([[True], seg[1:] != seg[:-1]]) if len(seg) else np.zeros(0, bool)
        w = self.shape[1]
        for s, src in zip(seg[first].tolist(), nb[first].tolist(), strict=True):
            idx = self.pixels(s)
            empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
            dist = np.abs(empty // w - (self.r0[src] + self.r1[src]) / 2).astype(np.float32)
            self._fill(empty, fits, src, dist, self.p.propagate_confidence, ORIGIN["plane"])

    def boundary_pairs(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Flat indices of every pair of horizontally or vertically adjacent pixels of different
        segments (first, second; computed once per completion)."""
        if self._boundary_pairs is None:
            i, j = _adjacent_pixels(self.shape)
            cut = self.flat[i] != self.flat[j]
            self._boundary_pairs = (i[cut], j[cut])
        return self._boundary_pairs

    def segment_colours(self) -> F64:
        """(S, 3) mean colour of each segment (computed once: the image and its segments do not
        change during a completion; a read-only array)."""
        if self._segment_colours is None:
            colour = self.image.reshape(-1, 3).astype(np.float64)
            sums = np.stack([np.bincount(self.flat, colour[:, c], self.count) for c in range(3)], axis=1)
            self._segment_colours = sums / np.maximum(self.sizes, 1)[:, None]
            self._segment_colours.setflags(write=False)
        return self._segment_colours

    def unseen_facade_parts(self, todo: Mask) -> Mask:
        """The segments of ``todo`` a facade may climb into (step 7): fewer than ``min_inliers``
        pixels of depth (dense or sparse: the LiDAR did not see them), at most
        ``upward_max_thing_share`` of their pixels labelled things, neither green nor blue."""
        p = self.p
        mean = self.segment_colours()
        green, blue = mean @ np.array([-1.0, 2.0, -1.0]), mean @ np.array([-1.0, -1.0, 2.0])
        evidence = np.bincount(self.flat, self.thin_depth > 0, self.count)
        todo = todo & ~self.thing_touched & (self.n_known < p.min_inliers) & (evidence < p.min_inliers)
        # Excess green (2 g - r - b), a vegetation index: a tree's crown above a roof is not the
        # facade; nor is the sky above it that the labels missed, blue (2 b - r - g).
        return todo & (green <= p.upward_max_green) & (blue <= p.upward_max_blue)

    def propagate_up(self, todo: Mask) -> None:
        """Vertical planes climb into the segments above them (step 7): the upper part of a
        facade, beyond the LiDAR's top beam, is often a segment of its own (cut off by a ledge, a
        row of windows), without depth.

        A candidate is a segment of ``todo`` with at most ``upward_max_thing_share`` of its pixels
        labelled things, neither green nor blue
        (``upward_max_green``, ``upward_max_blue``),
        with fewer than ``min_inliers`` pixels of depth (dense or sparse: the LiDAR did not see it)
        and none completed. It takes the vertical plane whose region (:attr:`facade_of`: one plane
        and the segments it climbed into) runs along its lower boundary for at least
        ``upward_min_boundary_ref_px`` and ``upward_boundary_share`` of that whole boundary; or the
        plane whose region holds all but a tenth of its whole boundary (the windows
        between two of those segments). Then it is that plane's region too, for the segments above
        it: ``upward_steps`` rounds. Its pixels' distance to the data: the rows up from that
        boundary, plus the boundary's own. Sky pixels are left out of every boundary.
        """
        p = self.p
        h, w = self.shape
        if h < 2 or not self.facades:
            return
        todo = self.unseen_facade_parts(todo)
        i, j = self.boundary_pairs()
        # Every boundary pair both ways: (pixel of the candidate, its neighbour, neighbour below).
        a, b = np.concatenate([i, j]), np.concatenate([j, i])
        below = b - a == w
        if self.sky is not None:
            keep = ~self.sky[b]
            a, b, below = a[keep], b[keep], below[keep]
        seg_a = self.flat[a].astype(np.int64)
        least = max(p.upward_min_boundary_ref_px * self.scale, 1.0)
        done = np.zeros(self.count, bool)
        for _ in range(p.upward_steps):
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            cand = todo & ~done & (completed == 0)
            on = cand[seg_a]
            if not on.any():
                return
            sa, bb, down = seg_a[on], b[on], below[on]
            fid = self.facade_of[bb]
            family = np.array([f[3] for f in self.facades] + [-1], np.int64)[fid]  # -1: none
            n_f = len(self.facades) + 1
            # Below: support of each (segment, family), and the whole boundary below.
            lower = np.bincount(sa[down], minlength=self.count)
            keys, support = np.unique(
                sa[down & (fid >= 0)] * n_f + family[down & (fid >= 0)], return_counts=True
            )
            seg, fam = np.divmod(keys, n_f)
            ok = (support >= least) & (support >= p.upward_boundary_share * lower[seg])
            # All around: enclosed by one plane's region.
            total = np.bincount(sa, minlength=self.count)
            keys2, around = np.unique(sa[fid >= 0] * n_f + family[fid >= 0], return_counts=True)
            seg2, fam2 = np.divmod(keys2, n_f)
            enclosed = around >= 0.9 * total[seg2]
            seg = np.concatenate([seg[ok], seg2[enclosed]])
            fam = np.concatenate([fam[ok], fam2[enclosed]])
            length = np.concatenate([support[ok], around[enclosed]])
            if len(seg) == 0:
                return
            order = np.lexsort((-length, seg))  # by segment, longest boundary first
            seg, fam = seg[order], fam[order]
            first = np.concatenate([[True], seg[1:] != seg[:-1]])
            for s, q in zip(seg[first].tolist(), fam[first].tolist(), strict=True):
                done[s] = True
                mine = (sa == s) & (family == q)
                ref = bb[mine & down] if np.any(mine & down) else bb[mine]
                k = int(np.bincount(fid[mine]).argmax())  # the region's part it touches most
                fits, t, factor, _ = self.facades[k]
                idx = self.pixels(s)
                empty = idx[self.fillable[idx] & (self.depth[idx] == 0)]
                empty = empty[~self.sky_like[empty]]  # a roofline's segment takes in some sky
                rows = np.maximum(float(np.mean(ref // w)) - empty // w, 0)
                dist = (rows + float(np.mean(self.fill_dist[ref]))).astype(np.float32)
                factor *= p.upward_confidence
                self._fill(empty, fits, t, dist, factor, ORIGIN["plane"])
                filled = empty[self.depth[empty] > 0]
                if len(filled):
                    self.facade_of[filled] = len(self.facades)
                    self.facades.append((fits, t, factor, q))

    def climb_walls(self, s: int) -> None:
        """Each column of segment ``s`` climbs from its topmost known pixel (step 6d): its empty
        pixels above that one and above the horizon take the vertical plane facing the camera
        through that pixel's point (each column its own plane), at ``wall_confidence`` at most,
        the distance to the data being the rows up from that pixel."""
        p = self.p
        h, w = self.shape
        idx = self.pixels(s)
        rows, cols = np.divmod(idx, w)
        ref_ok = self.known[idx] & ~self.things[idx]
        top = np.full(w, h, np.intp)
        np.minimum.at(top, cols[ref_ok], rows[ref_ok])
        top[~self._column_is_vertical(s, top)] = h
        above = (top[cols] < h) & (rows < top[cols]) & ((self.rays[idx] @ self.up) > 0)
        empty = above & self.fillable[idx] & (self.depth[idx] == 0) & ~self.things[idx] & ~self.sky_like[idx]
        if not empty.any():
            return
        px, col = idx[empty], cols[empty]
        ref = top[col] * w + col
        point = self.rays[ref] * self.depth[ref, None]
        normal = self.horizontal(point)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
        offset = -np.einsum("ij,ij->i", normal, point)
        z, ok = self.intersect(self.rays[px], normal, offset, self.ray_norm[px])
        px, ref, z, normal, offset = px[ok], ref[ok], z[ok], normal[ok], offset[ok]
        dist = (ref // w - px // w).astype(np.float32)
        conf = np.minimum(p.wall_confidence, self.conf[ref]) * np.exp(
            -dist / (p.conf_distance_ref_px * self.scale)
        )
        self.depth[px], self.conf[px], self.origin[px] = z, conf, ORIGIN["vertical"]
        self.plane_normal[px], self.plane_offset[px], self.fill_dist[px] = normal, offset, dist

    def climb_through(self, walled: Mask, todo: Mask) -> None:
        """The columns step 6d climbed go on up (after step 7): from each pixel of ``walled``, the
        empty pixels straight above it take its plane while they belong to segments step 7 could
        climb into (of ``todo``, not seen by the LiDAR, without things, neither green nor blue, not
        ground or vegetation), lie above the horizon and are not sky; the first pixel that is not
        ends the column's climb. Confidence: the walled pixel's times ``upward_confidence``, and
        ``exp(-d / d0)`` of the rows climbed beyond it."""
        p = self.p
        h, w = self.shape
        assert self.sky is not None  # the wall step runs only with sky labels
        unseen = self.unseen_facade_parts(todo) & ~(self.ground | self.vegetation)
        open_px = (
            unseen[self.flat] & self.fillable & (self.depth == 0) & ~self.sky & ~self.things & ~self.sky_like
        )
        open_px = (open_px & ((self.rays @ self.up) > 0)).reshape(h, w)
        walled = walled.reshape(h, w)
        # Row by row upward, each column carrying the plane, distance and confidence it climbs with.
        per_row = np.float32(np.exp(-1.0 / (p.conf_distance_ref_px * self.scale)))
        active = np.zeros(w, bool)
        normal, offset = np.zeros((w, 3), np.float32), np.zeros(w, np.float32)
        dist, conf = np.zeros(w, np.float32), np.zeros(w, np.float32)
        taken: list[tuple[NDArray[np.intp], NDArray[np.float32], NDArray[np.float32], F32, F32]] = []
        for r in range(h - 1, -1, -1):
            here = np.arange(r * w, (r + 1) * w)
            start = walled[r]
            normal[start], offset[start] = self.plane_normal[here[start]], self.plane_offset[here[start]]
            dist[start], conf[start] = (
                self.fill_dist[here[start]],
                self.conf[here[start]] * p.upward_confidence,
            )
            go_on = active & ~start & open_px[r]
            if go_on.any():
                cols = np.flatnonzero(go_on)
                dist[cols] += 1
                conf[cols] *= per_row
                taken.append(
                    (
                        r * w + cols,
                        normal[cols].copy(),
                        offset[cols].copy(),
                        dist[cols].copy(),
                        conf[cols].copy(),
                    )
                )
            active = start | go_on
        if not taken:
            return
        px, n, o, d, c = (np.concatenate(parts) for parts in zip(*taken, strict=True))
        z, ok = self.intersect(self.rays[px], n.astype(np.float64), o.astype(np.float64), self.ray_norm[px])
        px, z, n, o, d, c = px[ok], z[ok], n[ok], o[ok], d[ok], c[ok]
        self.depth[px], self.conf[px], self.origin[px] = z, c, ORIGIN["vertical"]
        self.plane_normal[px], self.plane_offset[px], self.fill_dist[px] = n, o, d

    def _column_is_vertical(self, s: int, top: NDArray[np.intp]) -> Mask:
        """(W,) whether the known pixels of segment ``s`` in each column stand upright below its
        topmost one ``top`` (``h``: none): the known pixel ``wall_min_height_m`` lower (the first
        at or below the row that height takes at its depth) lies at the same horizontal distance
        within ``inlier_tol_m + inlier_tol_rel * z`` (a rounded body is upright at its widest
        only). A column whose known pixels span less height stands if most of the segment's
        columns that could be checked do."""
        p = self.p
        h, w = self.shape
        out = np.zeros(w, bool)
        cols = np.flatnonzero(top < h)
        if len(cols) == 0:
            return out
        # The first known pixel at or below each probe row: a search over (column, row) keys.
        idx = self.pixels(s)
        idx = idx[self.known[idx] & ~self.things[idx]]
        keys = np.sort((idx % w) * h + idx // w)
        ref = top[cols] * w + cols
        z_ref = self.depth[ref]
        step = np.ceil(p.wall_min_height_m * self.scale * REFERENCE_FOCAL_PX / z_ref).astype(np.intp)
        at = np.searchsorted(keys, cols * h + top[cols] + np.maximum(step, 1))
        found = keys[np.minimum(at, len(keys) - 1)]
        has = (at < len(keys)) & (found // h == cols)
        probe_px = (found % h) * w + cols

        def distance(px: NDArray[np.intp]) -> F64:
            return np.linalg.norm(self.horizontal(self.rays[px] * self.depth[px, None]), axis=1)

        tol = p.inlier_tol_m + p.inlier_tol_rel * z_ref
        upright = np.abs(distance(ref) - distance(probe_px)) <= tol
        # A column too short to check stands if most of the segment's checked columns do.
        wall = bool(has.any()) and float(upright[has].mean()) >= 0.5
        out[cols] = np.where(has, upright, wall)
        return out
