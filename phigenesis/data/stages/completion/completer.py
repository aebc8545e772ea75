"""The completion state of one image (:class:`_Completer`): its segment tables, the plane fits of
its segments and their fill (steps 2-4 of :mod:`phigenesis.data.stages.complete`), holes, and the
confidence of every filled pixel. Steps 5, 6d and 7 are :class:`~.facades._FacadeFills`'s, steps 6-6c
:class:`~.thin._ThinFills`'s.

Arrays are flat (H * W,) per pixel unless named otherwise; depths in metres along the camera's z
axis, rays (H * W, 3) in camera axes with z = 1.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import taxonomy as tx
from phigenesis.data.stages.completion.facades import _FacadeFills
from phigenesis.data.stages.completion.params import (
    _SIN_GOOD_INCIDENCE,
    F32,
    F64,
    KIND_GROUND,
    KIND_NONE,
    KIND_VERTICAL,
    ORIGIN,
    STANDING_CLASSES,
    VEHICLE_CLASSES,
    CompletionParams,
    Mask,
)
from phigenesis.data.stages.completion.planes import PlaneFits, fit_planes
from phigenesis.data.stages.completion.segments import (
    _majority_in,
    _majority_never_filled,
    _nearest_pixel,
)
from phigenesis.data.stages.completion.thin import _ThinFills
from phigenesis.data.stages.densification.registry import REFERENCE_FOCAL_PX


@dataclass
class _Inputs:
    """The arrays of one completion, all (H, W) (``rays`` (H * W, 3)); ``depth``, ``conf`` and
    ``origin`` are the outputs, updated in place."""

    depth: F32
    conf: F32
    origin: NDArray[np.uint8]
    known: Mask
    fillable: Mask
    rgb: NDArray[np.uint8]
    rays: F64
    sky: Mask | None
    classes: NDArray[np.uint8] | None
    sparse: tuple[F32, F32] | None
    #: What is known of ``rays`` across calls (:func:`~.depth_map._ray_info`): its lengths, its coarse grids.
    ray_info: dict[Any, Any] | None = None


class _Completer(_FacadeFills, _ThinFills):
    """Completion state of one image; :meth:`run` updates the outputs of ``inputs`` in place."""

    def __init__(
        self,
        inputs: _Inputs,
        segments: NDArray[np.int32],
        up: F64,
        focal_px: float,
        p: CompletionParams,
        ray_norm: F64 | None = None,
    ):
        self.shape = inputs.depth.shape
        self.depth, self.conf = inputs.depth.reshape(-1), inputs.conf.reshape(-1)
        self.origin = inputs.origin.reshape(-1)
        self.known, self.fillable = inputs.known.reshape(-1), inputs.fillable.reshape(-1)
        self.image, self.rays, self.up, self.p = inputs.rgb, inputs.rays, up, p
        self.segments = segments
        self._segment_colours: F64 | None = None
        self._boundary_pairs: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None
        self.scale = focal_px / REFERENCE_FOCAL_PX
        self.rng = np.random.default_rng(p.seed)
        self.ray_norm = np.linalg.norm(self.rays, axis=1) if ray_norm is None else ray_norm
        # The plane each completed pixel took (to complete a finer grid from this one).
        self.plane_normal = np.zeros((self.depth.size, 3), np.float32)
        self.plane_offset = np.zeros(self.depth.size, np.float32)
        # Each completed pixel's distance to the data its plane was fitted to (pixels).
        self.fill_dist = np.zeros(self.depth.size, np.float32)
        # The vertical plane each pixel lies on (its segment's inliers and completed pixels), an
        # index into ``facades`` ((fits, segment of fits, confidence factor, family)); -1 none. Planes
        # climb from these into the segments above (step 7).
        self.facade_of = np.full(self.depth.size, -1, np.int32)
        self.facades: list[tuple[PlaneFits, int, float, int]] = []  # (..., family: the first's index)
        self.sky = None if inputs.sky is None else inputs.sky.reshape(-1)
        # Thin structures' evidence: the dense depth, and the sparse depth where it has none.
        self.thin_depth, self.thin_conf = self.depth.copy(), self.conf.copy()
        if inputs.sparse is not None:
            sparse, sparse_conf = (a.reshape(-1) for a in inputs.sparse)
            extra = (self.thin_depth == 0) & (sparse > 0) & (sparse_conf > 0)
            self.thin_depth[extra], self.thin_conf[extra] = sparse[extra], sparse_conf[extra]
        # Segment tables: pixels sorted by segment, sizes, bounding boxes, counts.
        w = self.shape[1]
        flat = self.flat = segments.reshape(-1)
        n = self.count = int(flat.max()) + 1
        self.order = np.argsort(flat, kind="stable")
        self.sizes = np.bincount(flat, minlength=n)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)])
        rows, cols = np.divmod(self.order, w)
        first = self.starts[:-1][self.sizes > 0]
        self.r0, self.r1, self.c0, self.c1 = (np.zeros(n, np.intp) for _ in range(4))
        full = self.sizes > 0
        self.r0[full], self.r1[full] = np.minimum.reduceat(rows, first), np.maximum.reduceat(rows, first) + 1
        self.c0[full], self.c1[full] = np.minimum.reduceat(cols, first), np.maximum.reduceat(cols, first) + 1
        self.n_dense = np.bincount(flat, weights=self.known, minlength=n)
        # Anchors, the pixels planes are fitted to: the dense depth, and in segments with fewer than
        # ``min_inliers`` of it, the sparse depth (the densifier leaves out the scan lines on a far
        # lawn) if it has that many.
        self.anchor, self.anchor_depth, self.anchor_conf = self.known, self.depth, self.conf
        self.seg_factor = np.ones(n)
        self.sparse_seg = np.zeros(n, bool)
        if p.sparse_planes and inputs.sparse is not None:
            extra = (self.n_dense < p.min_inliers)[flat] & (self.thin_depth > 0) & ~self.known
            n_sparse = np.bincount(flat, weights=extra, minlength=n)
            sparse_seg = (n_sparse >= p.min_inliers) & (n_sparse >= p.sparse_min_share * self.sizes)
            extra &= sparse_seg[flat]
            if extra.any():
                self.anchor = self.known | extra
                self.anchor_depth = np.where(extra, self.thin_depth, self.depth)
                self.anchor_conf = np.where(extra, self.thin_conf, self.conf)
                self.seg_factor[sparse_seg] = p.sparse_plane_confidence
                self.sparse_seg = sparse_seg
        self.n_known = np.bincount(flat, weights=self.anchor, minlength=n)
        self.n_fill = np.bincount(flat, weights=self.fillable, minlength=n)
        self.skip = np.zeros(n, bool)
        if inputs.sky is not None:
            self.skip |= (
                np.bincount(flat, weights=inputs.sky.reshape(-1), minlength=n) > p.max_sky_share * self.sizes
            )
        if inputs.classes is not None:
            self.skip |= _majority_never_filled(flat, inputs.classes.reshape(-1), n)
        # Segments with more than a few pixels labelled things (vehicles, people;
        # ``upward_max_thing_share``): things end where their box does, so no plane climbs from or
        # into them; a car's side merged with the facade behind it would carry the car's depth up
        # the facade.
        self.thing_touched = np.zeros(n, bool)
        # What a segment's label says of its plane, for a line of known points (``line_planes``).
        self.lies = self.stands = None
        if inputs.classes is not None and p.line_planes:
            labels = inputs.classes.reshape(-1)
            self.lies = _majority_in(flat, labels, n, tx.GROUND_IDS)
            self.stands = _majority_in(flat, labels, n, STANDING_CLASSES)
        # Pixels of excess blue (2 b - r - g) above ``upward_max_blue``: sky the labels missed; with
        # their 8 neighbours, the rim where a crown blends into it (blended pixels are sky).
        blue = inputs.rgb.reshape(-1, 3).astype(np.float64) @ np.array([-1.0, -1.0, 2.0])
        self.sky_like = blue > p.upward_max_blue
        rim = cv2.dilate(self.sky_like.reshape(self.shape).view(np.uint8), np.ones((3, 3), np.uint8))
        self.sky_rim = rim.astype(bool).reshape(-1)
        self.vegetation = np.zeros(n, bool)
        self.vehicle = np.zeros(n, bool)
        self.ground = np.zeros(n, bool)
        self.things = np.zeros(self.depth.size, bool)
        if inputs.classes is not None:
            labels = inputs.classes.reshape(-1)
            self.vegetation = _majority_in(flat, labels, n, frozenset({tx.VEGETATION}))
            self.vehicle = _majority_in(flat, labels, n, VEHICLE_CLASSES)
            self.ground = _majority_in(flat, labels, n, tx.GROUND_IDS)
            self.things = np.isin(labels, list(tx.THING_IDS))
            share = np.bincount(flat, weights=self.things, minlength=n) / np.maximum(self.sizes, 1)
            self.thing_touched = share > p.upward_max_thing_share

    def horizontal(self, points: F64) -> F64:
        """The part of (..., 3) camera-frame points across ``up``: the horizontal direction to them."""
        return points - (points @ self.up)[..., None] * self.up

    def pixels(self, s: int) -> NDArray[np.intp]:
        """Flat indices of the pixels of segment ``s``."""
        return self.order[self.starts[s] : self.starts[s + 1]]

    def crop(self, s: int) -> tuple[slice, slice]:
        """The bounding box of segment ``s``."""
        return slice(self.r0[s], self.r1[s]), slice(self.c0[s], self.c1[s])

    def run(self) -> None:
        p = self.p
        height = self.r1 - self.r0
        mean_width = self.sizes / np.maximum(height, 1)
        thin = (
            (mean_width <= p.max_thin_width_ref_px * self.scale)
            & (height >= p.min_thin_aspect * mean_width)
            & (height >= p.min_thin_height_ref_px * self.scale)
        )
        todo = (self.n_fill > 0) & ~self.skip
        planar = np.flatnonzero(todo & ~thin & (self.n_known >= p.min_inliers))
        planes, plane_px = self.fit_segments(planar)
        # A hole needs a few pixels of the segment's box that are not the segment's.
        room = (self.r1 - self.r0) * (self.c1 - self.c0) - self.sizes >= 4
        for s in planar[planes[0].kind[planar] != KIND_NONE].tolist():
            filled = self.fill_segment(s, planes, plane_px)
            if filled is not None and room[s]:
                self.fill_holes(s, planes, *filled)
        if p.crowns:
            green = self.segment_colours() @ np.array([-1.0, 2.0, -1.0]) > p.upward_max_green
            green |= self.vegetation
            blobs = planar[
                (planes[0].kind[planar] == KIND_NONE) & green[planar] & ~self.thing_touched[planar]
            ]
            for s in blobs.tolist():
                self.fill_crown(s)
            if p.vehicle_max_spread > 0:
                for s in planar[(planes[0].kind[planar] == KIND_NONE) & self.vehicle[planar]].tolist():
                    self.fill_crown(s, p.vehicle_max_spread)
            if p.canopies:
                self.fill_canopies(~self.skip & green & ~self.thing_touched)
        if p.propagate_ground:
            below = np.bincount(self.flat, weights=(self.rays @ self.up) > 0, minlength=self.count) == 0
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            empty = todo & ~thin & (self.n_dense < p.min_inliers) & (completed == 0) & below
            self.propagate(np.flatnonzero(empty), planes[0], planes[0].kind == KIND_GROUND)
        evidence = np.bincount(self.flat, weights=self.thin_depth > 0, minlength=self.count)
        enough = evidence >= np.maximum(p.min_thin_known, p.min_thin_evidence * self.sizes)
        for s in np.flatnonzero(todo & thin & enough & (self.n_dense >= p.min_thin_trusted)).tolist():
            self.fill_thin(s)
        if p.thin_planes:
            # A thin segment the step above did not fill (a strip of wall between two columns of
            # windows, a kerb, seen too little to show a pole's rise) is fitted like any other.
            completed = np.bincount(self.flat, (self.depth > 0) & ~self.known, self.count)
            rest = np.flatnonzero(todo & thin & (completed == 0) & (self.n_known >= p.min_inliers))
            if len(rest):
                thin_fits, thin_px = self.fit_segments(rest)
                for s in rest[thin_fits[0].kind[rest] != KIND_NONE].tolist():
                    self.fill_segment(s, thin_fits, thin_px)
        # Only with sky labels: nothing else tells the sky above a roofline from a wall.
        walled: Mask | None = None
        if p.wall_columns and self.sky is not None:
            walls = todo & (self.n_dense >= p.min_inliers) & ~(self.ground | self.vegetation | self.vehicle)
            open_above = self.fillable & (self.depth == 0) & ((self.rays @ self.up) > 0)
            walls &= np.bincount(self.flat, open_above & ~self.things & ~self.sky_like, self.count) > 0
            before = self.depth > 0
            for s in np.flatnonzero(walls).tolist():
                self.climb_walls(s)
            walled = (self.depth > 0) & ~before
        # Thin ones too (the wall between two columns of windows).
        if p.propagate_up and self.sky is not None:
            self.propagate_up(todo)
        if walled is not None:
            self.climb_through(walled, todo)  # after step 7, which climbs whole segments first

    # -- planes ------------------------------------------------------------------------------

    def fit_segments(self, segs: NDArray[np.intp]) -> tuple[list[PlaneFits], NDArray[np.int8]]:
        """Up to two planes per segment of ``segs`` (complete.py's docstring, step 2), and per pixel the
        plane (1, 2) it is an inlier of (0: none)."""
        p = self.p
        each = dataclasses.replace(p, min_inlier_share=p.min_plane_share)
        chosen = np.zeros(self.count, bool)
        chosen[segs] = True
        kn = self.order[self.anchor[self.order] & chosen[self.flat[self.order]]]  # sorted by segment
        groups = self.flat[kn]
        first = self._fit(kn, segs, each)
        if p.line_planes:
            self._fit_lines_by_height(kn, segs, first, each)
        on_first = self._on_plane(kn, first)
        n_first = np.bincount(groups, on_first, self.count)
        share = n_first / np.maximum(self.n_known, 1)
        split = segs[(first.kind[segs] != KIND_NONE) & (share[segs] < p.min_inlier_share)]
        second = PlaneFits.empty(self.count)
        on_second = np.zeros(len(kn), bool)
        if len(split):
            is_split = np.zeros(self.count, bool)
            is_split[split] = True
            rest = ~on_first & is_split[groups]
            second = self._fit(kn[rest], split, each)
            second.kind[~is_split] = KIND_NONE
            on_second[rest] = self._on_plane(kn[rest], second)
            n_second = np.bincount(groups, on_second, self.count)
            share = (n_first + n_second) / np.maximum(self.n_known, 1)
            bad = is_split & ((share < p.min_inlier_share) | (n_second < p.min_plane_share * self.n_known))
            first.kind[bad] = second.kind[bad] = KIND_NONE
        first.share = second.share = share
        plane_px = np.zeros(self.flat.shape, np.int8)
        plane_px[kn[on_first & (first.kind[groups] != KIND_NONE)]] = 1
        plane_px[kn[on_second & (second.kind[groups] != KIND_NONE)]] = 2
        return [first, second], plane_px

    def _fit_lines_by_height(
        self, kn: NDArray[np.intp], segs: NDArray[np.intp], fits: PlaneFits, p: CompletionParams
    ) -> None:
        """Where the labels do not say, a line of points at the ground's height (the image's own
        ground planes: their median distance below the camera) lies: refits the segments of
        ``segs`` without a plane and without a ground or standing label, in place."""
        ground = segs[fits.kind[segs] == KIND_GROUND]
        failed = segs[fits.kind[segs] == KIND_NONE]
        if self.lies is not None and self.stands is not None:
            failed = failed[~(self.lies[failed] | self.stands[failed])]
        if len(ground) == 0 or len(failed) == 0:
            return
        camera_height_m = float(np.median(fits.offset[ground]))
        groups = self.flat[kn]
        points = self.rays[kn] * self.anchor_depth[kn, None]
        count = np.maximum(np.bincount(groups, minlength=self.count), 1)
        height = np.bincount(groups, points @ self.up, self.count) / count + camera_height_m
        depth = np.bincount(groups, points[:, 2], self.count) / count
        # Only lying lines: a line of points above the ground is as often a car's flank or a
        # kerb-top row as a wall's foot (measured: standing lines by height alone were wrong).
        lies = np.abs(height) <= p.inlier_tol_m + 2 * p.inlier_tol_rel * depth
        chosen = np.zeros(self.count, bool)
        chosen[failed] = True
        refit = self._fit(kn[chosen[groups]], failed, p, labels=(lies, None))
        won = failed[refit.kind[failed] != KIND_NONE]
        for f in dataclasses.fields(PlaneFits):
            getattr(fits, f.name)[won] = getattr(refit, f.name)[won]

    def _fit(
        self,
        kn: NDArray[np.intp],
        segs: NDArray[np.intp],
        p: CompletionParams,
        labels: tuple[Mask | None, Mask | None] | None = None,
    ) -> PlaneFits:
        """Planes of ``segs`` from about ``fit_points`` random pixels per segment of the known
        pixels ``kn`` (sorted by segment); ``labels``: the (S,) lies / stands flags of the segments
        (default: what their labels say)."""
        groups = self.flat[kn]
        count = np.bincount(groups, minlength=self.count)
        sub = kn[self.rng.random(len(kn)) < (p.fit_points / np.maximum(count, 1))[groups]]
        compact = np.full(self.count, -1, np.intp)
        compact[segs] = np.arange(len(segs))
        points = self.rays[sub] * self.anchor_depth[sub, None]
        conf = self.anchor_conf[sub].astype(np.float64)
        lies, stands = (None if a is None else a[segs] for a in (labels or (self.lies, self.stands)))
        fits, _ = fit_planes(
            compact[self.flat[sub]], points, conf, len(segs), self.up, p, self.rng, lies, stands
        )
        return fits.scattered(segs, self.count)

    def _on_plane(self, kn: NDArray[np.intp], fits: PlaneFits) -> Mask:
        """Whether each known pixel of ``kn`` lies on its segment's plane of ``fits``."""
        g = self.flat[kn]
        res = np.einsum("ij,ij->i", self.rays[kn], fits.normal[g]) * self.anchor_depth[kn] + fits.offset[g]
        tol = self.p.inlier_tol_m + self.p.inlier_tol_rel * self.anchor_depth[kn]
        return (fits.kind[g] != KIND_NONE) & (np.abs(res) <= tol)

    def fill_segment(
        self, s: int, planes: list[PlaneFits], plane_px: NDArray[np.int8]
    ) -> tuple[NDArray[np.int8], F32] | None:
        """Fills the segment's empty pixels from the plane of its nearest known pixel (step 3).
        Returns, for every pixel of its crop, that plane (1, 2; 0 none) and the distance to that
        pixel; None where the two planes do not meet (:meth:`planes_meet`: then no holes are
        filled either)."""
        rs, cs = self.crop(s)
        w = self.shape[1]
        seg = self.segments[rs, cs] == s
        dist, nearest = _nearest_pixel(seg & self.anchor.reshape(self.shape)[rs, cs])
        nr, nc = np.divmod(nearest, cs.stop - cs.start)
        which = plane_px[(nr + rs.start) * w + (nc + cs.start)]
        apart = planes[1].kind[s] != KIND_NONE and not self.planes_meet(s, planes, which, seg, rs, cs)
        reach = self.p.split_extrapolation_ref_px if apart else self.p.max_extrapolation_ref_px
        which[dist > reach * self.scale] = 0
        climbed = (
            apart
            and self.p.climb_columns
            and self.climb_columns(s, planes, plane_px, seg, rs, cs, which, dist)
        )
        empty = self.fillable.reshape(self.shape)[rs, cs] & (self.depth.reshape(self.shape)[rs, cs] == 0)
        for k, fits in enumerate(planes, start=1):
            tr, tc = np.nonzero(seg & empty & (which == k))
            self._fill(
                (tr + rs.start) * w + (tc + cs.start),
                fits,
                s,
                dist[tr, tc],
                self.seg_factor[s] * (self.p.line_confidence if fits.from_line[s] else 1.0),
                ORIGIN["plane"],
            )
            # Planes of the sparse depth alone do not climb: it leaks at silhouettes, most of all
            # into the sky beside a roofline.
            if fits.kind[s] == KIND_VERTICAL and not self.thing_touched[s] and not self.sparse_seg[s]:
                # The plane's region: its inliers and the pixels it completed.
                idx = self.pixels(s)
                mine = plane_px[idx] == k
                tr, tc = np.nonzero(seg & empty & (which == k))
                done = (tr + rs.start) * w + (tc + cs.start)
                done = done[self.depth[done] > 0]
                self.facade_of[idx[mine]] = self.facade_of[done] = len(self.facades)
                self.facades.append((fits, s, float(self.seg_factor[s]), len(self.facades)))
        return None if apart and not climbed else (which, dist)

    def climb_columns(
        self,
        s: int,
        planes: list[PlaneFits],
        plane_px: NDArray[np.int8],
        seg: Mask,
        rs: slice,
        cs: slice,
        which: NDArray[np.int8],
        dist: F32,
    ) -> bool:
        """A segment with two vertical planes that do not meet (two facades of one colour) fills
        its pixels above each column's topmost inlier with that inlier's plane: a facade's upper
        part lies above its lower part, however far it is from the data. The climb runs through
        the segment and its holes (windows) and stops at anything else. Updates ``which`` and
        ``dist`` (rows up from that inlier) of the crop in place; whether it climbed."""
        if self.thing_touched[s] or not (
            planes[0].kind[s] == KIND_VERTICAL and planes[1].kind[s] == KIND_VERTICAL
        ):
            return False
        h = seg.shape[0]
        inlier = seg & (plane_px.reshape(self.shape)[rs, cs] > 0) & self.anchor.reshape(self.shape)[rs, cs]
        rows = np.arange(h)[:, None]
        top = np.where(inlier, rows, h).min(axis=0)
        _, comp = cv2.connectedComponents((~seg).view(np.uint8), connectivity=4)
        edge = np.unique(np.concatenate([comp[0], comp[-1], comp[:, 0], comp[:, -1]]))
        passable = seg | ~np.isin(comp, edge[edge > 0])
        blocked = np.where(~passable & (rows < top), rows, -1).max(axis=0)
        climb = seg & (rows < top) & (rows > blocked) & (which == 0) & (top < h)
        cr, cc = np.nonzero(climb)
        which[cr, cc] = plane_px.reshape(self.shape)[rs, cs][top[cc], cc]
        dist[cr, cc] = (top[cc] - cr).astype(np.float32)
        return True

    def planes_meet(
        self, s: int, planes: list[PlaneFits], which: NDArray[np.int8], seg: Mask, rs: slice, cs: slice
    ) -> bool:
        """Whether a segment's two planes give the same depth (within the inlier tolerance) along
        the seam where their parts of the segment touch: a building's corner, not a bus standing
        in front of a facade, where a pixel far from both could belong to either."""
        inside = seg & (which > 0)
        seam = np.zeros(seg.shape, bool)
        seam[:, 1:] |= inside[:, 1:] & inside[:, :-1] & (which[:, 1:] != which[:, :-1])
        seam[1:, :] |= inside[1:, :] & inside[:-1, :] & (which[1:, :] != which[:-1, :])
        sr, sc = np.nonzero(seam)
        if len(sr) < 3:
            return False
        rays = self.rays[(sr + rs.start) * self.shape[1] + (sc + cs.start)]
        with np.errstate(divide="ignore", invalid="ignore"):
            z1 = -planes[0].offset[s] / (rays @ planes[0].normal[s])
            z2 = -planes[1].offset[s] / (rays @ planes[1].normal[s])
        gap = np.abs(z1 - z2) - (self.p.inlier_tol_m + self.p.inlier_tol_rel * np.abs(z1))
        return bool(np.all(np.isfinite(gap)) and np.median(gap) <= 0)

    def fill_holes(self, s: int, planes: list[PlaneFits], which: NDArray[np.int8], data_dist: F32) -> None:
        """Fills the holes of the segment's region with depth (step 4).

        A hole is a component of the rest of the region's bounding box that does not reach the
        box's border; one that reaches it only where that border is the image's (a window cut by
        the image's top edge) counts if it looks like an enclosed one (mean colours within
        ``merge_color_tol``, at most 1.5 times its area): facades repeat their windows, and a
        patch of sky beside a facade does not look like them. A hole takes the plane of the
        region pixel nearest to it (``which``: per pixel of the crop, :meth:`fill_segment`),
        unless its own known pixels lie off that plane; ``data_dist``: each crop pixel's
        distance to the segment's known pixels.
        """
        rs, cs = self.crop(s)
        h, w = self.shape
        region = (self.segments[rs, cs] == s) & (self.depth.reshape(self.shape)[rs, cs] > 0)
        if region.sum() < 4:
            return
        count, comp, stats, _ = cv2.connectedComponentsWithStats((~region).view(np.uint8), connectivity=4)
        if count <= 1:
            return
        inner, outer = np.zeros(count, bool), np.zeros(count, bool)
        for line, image_edge in (
            (comp[0], rs.start == 0),
            (comp[-1], rs.stop == h),
            (comp[:, 0], cs.start == 0),
            (comp[:, -1], cs.stop == w),
        ):
            (outer if image_edge else inner)[line] = True
        inner[0] = True  # the region itself
        hole = ~inner & ~outer
        cut = np.flatnonzero(~inner & outer)
        if len(cut) and hole.any():
            colour = self.image[rs, cs].reshape(-1, 3).astype(np.float64)
            area = np.maximum(stats[:, cv2.CC_STAT_AREA], 1)
            sums = np.stack([np.bincount(comp.reshape(-1), colour[:, c], count) for c in range(3)], axis=1)
            mean = sums / area[:, None]
            ref = np.flatnonzero(hole)
            for k in cut.tolist():
                alike = np.linalg.norm(mean[ref] - mean[k], axis=1) < self.p.merge_color_tol
                hole[k] = bool(np.any(alike & (area[k] <= 1.5 * area[ref])))
        if not hole.any():
            return
        _, nearest = _nearest_pixel(region)
        k_of = which.reshape(-1)[nearest]
        hr, hc = np.nonzero(hole[comp])
        pixels = (hr + rs.start) * w + (hc + cs.start)
        k_of = k_of[hr, hc]
        known = self.known[pixels]
        if known.any():  # a hole whose known pixels lie off its plane is something else
            kp, kk = pixels[known], np.maximum(k_of[known], 1) - 1
            normal = np.stack([f.normal[s] for f in planes])[kk]
            offset = np.array([f.offset[s] for f in planes])[kk]
            res = np.abs(np.einsum("ij,ij->i", self.rays[kp], normal) * self.depth[kp] + offset)
            off = (res > self.p.inlier_tol_m + self.p.inlier_tol_rel * self.depth[kp]) | (k_of[known] == 0)
            bad = np.bincount(comp[hr[known], hc[known]], off, count) > 0
            keep = ~bad[comp[hr, hc]]
            pixels, hr, hc, k_of = pixels[keep], hr[keep], hc[keep], k_of[keep]
        empty = self.fillable[pixels] & (self.depth[pixels] == 0)
        for k, fits in enumerate(planes, start=1):
            sel = empty & (k_of == k)
            dist = data_dist[hr[sel], hc[sel]]
            self._fill(
                pixels[sel], fits, s, dist, self.p.hole_confidence * self.seg_factor[s], ORIGIN["plane"]
            )

    # -- shared ------------------------------------------------------------------------------

    def intersect(self, rays: F64, normal: F64, offset: F64, ray_norm: F64 | None = None) -> tuple[F64, Mask]:
        """Depths where (P, 3) rays (z = 1) meet planes (P, 3) / (P,) or one plane (3,) / (), and
        whether each is valid: finite, in ``(min_depth_m, max_depth_m]`` and at an incidence of at
        least ``min_incidence_deg``. ``ray_norm``: the rays' (P,) lengths, if known."""
        denom = rays @ normal if normal.ndim == 1 else np.einsum("ij,ij->i", rays, normal)
        if ray_norm is None:
            ray_norm = np.linalg.norm(rays, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = -offset / denom
            sin_incidence = np.abs(denom) / ray_norm
        ok = np.isfinite(z) & (z > self.p.min_depth_m) & (z <= self.p.max_depth_m)
        ok &= sin_incidence >= np.sin(np.radians(self.p.min_incidence_deg))
        return z, ok

    def _fill(
        self,
        pixels: NDArray[np.intp],
        fits: PlaneFits,
        s: int,
        dist: F32,
        factor: float,
        code: int,
        cap: float | None = None,
    ) -> None:
        """Fills ``pixels`` with plane ``s`` of ``fits`` (where valid), with the confidence of the
        complete.py's docstring (``dist``: each pixel's distance to the data)."""
        if len(pixels) == 0:
            return
        normal, offset = fits.normal[s], float(fits.offset[s])
        z, ok = self.intersect(self.rays[pixels], normal, offset, self.ray_norm[pixels])
        if not ok.any():
            return
        pixels, z, dist = pixels[ok], z[ok], dist[ok]
        sin_incidence = np.abs(self.rays[pixels] @ normal) / self.ray_norm[pixels]
        rel = fits.rms_m[s] / (max(fits.depth_m[s], 1e-6) * self.p.conf_relative_residual)
        cap = self.p.max_confidence if cap is None else cap
        conf = (
            min(cap, fits.confidence[s])
            * factor
            * fits.share[s]
            * np.exp(-(rel**2))
            * np.exp(-dist / (self.p.conf_distance_ref_px * self.scale))
            * np.minimum(1.0, sin_incidence / _SIN_GOOD_INCIDENCE)
        )
        self.depth[pixels] = z
        self.conf[pixels] = conf
        self.origin[pixels] = code
        self.plane_normal[pixels] = normal
        self.plane_offset[pixels] = offset
        self.fill_dist[pixels] = dist
