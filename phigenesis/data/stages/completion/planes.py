"""Robust plane fits of many groups of camera-frame points at once (step 2 of
:mod:`phigenesis.data.stages.complete`): RANSAC over two-point hypotheses that hold the up
direction (vertical planes) or three points (ground planes), least-squares refinement, and the
acceptance tests. Planes are ``normal . p + offset = 0`` in camera axes (OpenCV), metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.stages.completion.params import (
    _MODE_GROUND_LINE,
    F64,
    KIND_GROUND,
    KIND_VERTICAL,
    CompletionParams,
    Mask,
)


@dataclass
class PlaneFits:
    """Planes ``normal . p + offset = 0`` (camera axes, unit ``normal``) of G groups of points.

    Attributes:
        normal: (G, 3) float64.
        offset: (G,) float64, metres.
        kind: (G,) int8: 0 no plane passed the tests, 1 vertical, 2 ground.
        rms_m: (G,) RMS distance of the inliers to the plane.
        share: (G,) share of the group's points the plane (or the group's planes) explain.
        depth_m: (G,) mean z of the inliers.
        confidence: (G,) mean confidence of the inliers.
        from_line: (G,) bool, the plane was fixed by a line of points and the group's label
            (``line_planes``).
    """

    normal: F64
    offset: F64
    kind: NDArray[np.int8]
    rms_m: F64
    share: F64
    depth_m: F64
    confidence: F64
    from_line: Mask

    @classmethod
    def empty(cls, n: int) -> PlaneFits:
        """G = n groups without a plane."""
        return cls(
            np.zeros((n, 3)),
            np.zeros(n),
            np.zeros(n, np.int8),
            *(np.zeros(n) for _ in range(4)),
            np.zeros(n, bool),
        )

    def scattered(self, groups: NDArray[np.intp], n: int) -> PlaneFits:
        """These fits (of groups 0..len(groups)-1) placed at ``groups`` among n."""
        out = PlaneFits.empty(n)
        for f in dataclasses.fields(PlaneFits):
            getattr(out, f.name)[groups] = getattr(self, f.name)
        return out


@dataclass(frozen=True)
class _Groups:
    """Points sorted by group: group g holds points ``start[g] : start[g] + count[g]``."""

    index: NDArray[np.intp]  # (N,) group of each point, non-decreasing
    count: NDArray[np.intp]  # (G,)
    start: NDArray[np.intp]  # (G,)

    @classmethod
    def of(cls, index: NDArray[np.intp], n: int) -> _Groups:
        count = np.bincount(index, minlength=n)
        return cls(index, count, np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.intp))

    def sums(self, values: F64) -> F64:
        """(G, k) sums of the (N, k) ``values`` over each group (0 for empty groups)."""
        out = np.zeros((len(self.count), values.shape[1]))
        full = self.count > 0
        if full.any():
            out[full] = np.add.reduceat(values, self.start[full], axis=0)
        return out

    def moments(self, weight: F64, points: F64) -> tuple[F64, F64, F64]:
        """Total weight (G,), weighted mean (G, 3) and covariance (G, 3, 3) of each group."""
        x, y, z = points.T
        cols = np.stack([np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], axis=1)
        s = self.sums(cols * weight[:, None])
        total = s[:, 0]
        inv = 1.0 / np.maximum(total, 1e-12)
        mean = s[:, 1:4] * inv[:, None]
        second = np.empty((len(total), 3, 3))
        for (i, j), k in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(4, 10), strict=True):
            second[:, i, j] = second[:, j, i] = s[:, k] * inv
        return total, mean, second - mean[:, :, None] * mean[:, None, :]


def _horizontal_basis(up: F64) -> F64:
    """(2, 3) orthonormal basis of the plane perpendicular to the unit vector ``up``."""
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(up, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)])


def fit_planes(
    groups: NDArray[np.intp],
    points: F64,
    confidence: F64,
    n_groups: int,
    up: F64,
    p: CompletionParams,
    rng: np.random.Generator,
    lies: Mask | None = None,
    stands: Mask | None = None,
) -> tuple[PlaneFits, Mask]:
    """A robust plane for each group of camera-frame points (the tests of the complete.py's docstring),
    all groups at once.

    Args:
        groups: (N,) group of each point in 0..G-1, non-decreasing (points sorted by group).
        points: (N, 3) camera-frame points, metres.
        confidence: (N,) their confidences.
        n_groups: G.
        up: (3,) unit up vector in camera axes.
        p: the tests' parameters (``min_inlier_share`` is the share each plane needs).
        rng: draws the RANSAC samples.
        lies, stands: (G,) bool or None, groups labelled ground / a standing structure: with
            ``line_planes``, a line of their points fixes their plane (complete.py's docstring, step 2).

    Returns:
        The planes (``share``: each plane's own inlier share) and each point's inlier flag.
        Vertical planes first (RANSAC over two-point hypotheses that contain ``up``, least squares
        with the normal kept horizontal); where none passes and ``ground_planes``, near-horizontal
        ones (three-point hypotheses, free least squares); then, for groups that ``lies`` marks,
        ground planes through a line of points.
    """
    assert points.shape == (len(groups), 3), (points.shape, len(groups))
    assert np.all(np.diff(groups) >= 0), "points must be sorted by group"
    g = _Groups.of(groups, n_groups)
    fits = PlaneFits.empty(n_groups)
    inlier = np.zeros(len(points), bool)
    tol = p.inlier_tol_m + p.inlier_tol_rel * points[:, 2]
    todo = np.flatnonzero(g.count >= p.min_inliers)
    lines = p.line_planes and lies is not None
    stands = stands if p.line_planes and stands is not None else np.zeros(n_groups, bool)
    for mode in (KIND_VERTICAL, KIND_GROUND, _MODE_GROUND_LINE):
        if mode == KIND_GROUND and not p.ground_planes:
            continue
        if mode == _MODE_GROUND_LINE and lines:
            todo = todo[lies[todo]]  # type: ignore[index]
        if len(todo) == 0 or (mode == _MODE_GROUND_LINE and not lines):
            break
        normal, offset = _ransac(mode, g, points, tol, todo, up, p, rng)
        on, ok, line = _refine_and_accept(mode, g, points, tol, todo, normal, offset, up, p, stands)
        won = todo[ok[todo]]
        kind = KIND_GROUND if mode == _MODE_GROUND_LINE else mode
        fits.normal[won], fits.offset[won], fits.kind[won] = normal[won], offset[won], kind
        fits.from_line[won] = line[won]
        take = ok[groups]
        inlier[take] = on[take]
        todo = todo[~ok[todo]]
    w = inlier.astype(np.float64)
    res = np.einsum("ij,ij->i", points, fits.normal[groups]) + fits.offset[groups]
    s = g.sums(np.stack([w, w * res * res, w * points[:, 2], w * confidence], axis=1))
    inv = 1.0 / np.maximum(s[:, 0], 1.0)
    fits.share = s[:, 0] / np.maximum(g.count, 1)
    fits.rms_m = np.sqrt(s[:, 1] * inv)
    fits.depth_m = s[:, 2] * inv
    fits.confidence = s[:, 3] * inv
    return fits, inlier


def _ransac(
    kind: int,
    g: _Groups,
    points: F64,
    tol: F64,
    todo: NDArray[np.intp],
    up: F64,
    p: CompletionParams,
    rng: np.random.Generator,
) -> tuple[F64, F64]:
    """The best hypothesis (most inliers among ``ransac_points`` points) of every group in
    ``todo``: (G, 3) normals and (G,) offsets (zeros elsewhere). ``kind``: ``KIND_VERTICAL``,
    ``KIND_GROUND`` or ``_MODE_GROUND_LINE``."""
    a, r, m = len(todo), p.ransac_points, p.ransac_iterations
    pick = g.start[todo, None] + (rng.random((a, r)) * g.count[todo, None]).astype(np.intp)  # [A, R]
    pts, tol_s = points[pick], tol[pick]  # [A, R, 3], [A, R]
    h = rng.integers(0, r, (3, a, m))
    rows = np.arange(a)[:, None]
    p0 = pts[rows, h[0]]  # [A, M, 3]
    d1 = pts[rows, h[1]] - p0
    # A vertical plane holds the up direction; a ground plane a third point; a ground plane
    # through a line the horizontal direction across it (the plane through it closest to level).
    if kind == KIND_VERTICAL:
        d2 = np.broadcast_to(up, d1.shape)
    elif kind == _MODE_GROUND_LINE:
        d2 = np.cross(np.broadcast_to(up, d1.shape), d1)
    else:
        d2 = pts[rows, h[2]] - p0
    cand = np.stack(
        [
            d1[..., 1] * d2[..., 2] - d1[..., 2] * d2[..., 1],
            d1[..., 2] * d2[..., 0] - d1[..., 0] * d2[..., 2],
            d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0],
        ],
        axis=-1,
    )
    length = np.sqrt(np.sum(cand * cand, axis=-1))
    cand = cand / np.maximum(length, 1e-12)[..., None]
    off = -np.sum(cand * p0, axis=-1)
    dist = np.abs(np.matmul(cand, pts.transpose(0, 2, 1)) + off[..., None])  # [A, M, R]
    score = np.count_nonzero(dist <= tol_s[:, None, :], axis=2)
    bad = length <= 1e-9
    if kind != KIND_VERTICAL:
        bad |= np.abs(cand @ up) < np.cos(np.radians(p.max_tilt_deg))
    score[bad] = -1
    best = np.argmax(score, axis=1)
    normal, offset = np.zeros((len(g.count), 3)), np.zeros(len(g.count))
    normal[todo], offset[todo] = cand[np.arange(a), best], off[np.arange(a), best]
    return normal, offset


def _refine_and_accept(
    kind: int,
    g: _Groups,
    points: F64,
    tol: F64,
    todo: NDArray[np.intp],
    normal: F64,
    offset: F64,
    up: F64,
    p: CompletionParams,
    stands: Mask,
    rounds: int = 2,
) -> tuple[Mask, Mask, Mask]:
    """Refines the planes of ``todo`` in place by least squares on their inliers (``rounds`` times:
    inliers, then the fit to them); returns each point's final inlier flag, whether each
    group's plane passes the tests of the complete.py's docstring, and whether it passes only as a plane
    through a line (``_MODE_GROUND_LINE``, or a vertical plane of a group ``stands`` marks
    without the height test)."""
    member = np.zeros(len(g.count), bool)
    member[todo] = True
    basis = _horizontal_basis(up)
    for step in range(rounds + 1):
        res = np.einsum("ij,ij->i", points, normal[g.index]) + offset[g.index]
        inlier = member[g.index] & (np.abs(res) <= tol)
        w = inlier.astype(np.float64)
        total, mean, cov = g.moments(w, points)
        if step == rounds:
            break
        if kind == KIND_VERTICAL:  # the smaller axis of the horizontal coordinates' spread
            new_normal = np.linalg.eigh(basis @ cov @ basis.T)[1][:, :, 0] @ basis
        elif kind == _MODE_GROUND_LINE:  # up, less its part along the inliers' main axis
            along = np.linalg.eigh(cov)[1][:, :, 2]
            new_normal = up - (along @ up)[:, None] * along
            new_normal /= np.maximum(np.linalg.norm(new_normal, axis=1), 1e-12)[:, None]
        else:
            new_normal = np.linalg.eigh(cov)[1][:, :, 0]
        new_normal *= np.where(new_normal @ up < 0, -1.0, 1.0)[:, None]
        enough = total >= 3
        normal[enough] = new_normal[enough]
        offset[enough] = -np.einsum("ij,ij->i", new_normal, mean)[enough]
    rms = np.sqrt(g.sums((w * res * res)[:, None])[:, 0] / np.maximum(total, 1))
    ok = member & (total >= p.min_inliers) & (total >= p.min_inlier_share * g.count)
    ok &= rms <= p.max_residual_rel * mean[:, 2]
    val, vec = np.linalg.eigh(cov)  # ascending
    free = vec[:, :, 0]
    surface = val[:, 1] > 0.01 * np.maximum(val[:, 2], 1e-12)  # spread over an area, not a line
    line = np.zeros_like(ok)
    if kind == KIND_VERTICAL:
        height_var = np.einsum("i,gij,j->g", up, cov, up)
        least = np.minimum(p.min_height_m, p.min_height_rel * mean[:, 2])
        tall = np.sqrt(12.0 * np.maximum(height_var, 0.0)) >= least  # extent, if uniform
        ok &= ~(surface & (np.abs(free @ up) > np.sin(np.radians(p.max_tilt_deg))))
        line = ok & ~tall & stands
        ok &= tall | stands
    elif kind == _MODE_GROUND_LINE:
        length = np.sqrt(12.0 * np.maximum(val[:, 2], 0.0))
        ok &= (length >= p.min_line_m) & (normal @ up >= np.cos(np.radians(p.max_tilt_deg)))
        line = ok
    else:
        ok &= surface & (np.abs(free @ up) >= np.cos(np.radians(p.max_tilt_deg)))
    return inlier, ok, line
