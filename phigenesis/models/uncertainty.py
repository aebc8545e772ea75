"""Per-pixel uncertainty maps ``u`` in [0, 1] that Stereo Forcing weighs the rendered condition by.

Stereo Forcing conditions Stage 2 on ``SF(u, z_ren) = u * z_ren``: the condition rendered from the
history's 4D Gaussians at a target camera, scaled by a map ``u`` that is 1 where the render is to be
trusted and 0 where the diffusion model is to fill in (the PhiGenesis paper, "PhiGenesis with Stereo
Forcing"). This module makes ``u`` for every target view, at the render's resolution (another
module pools it to the latent grid), in one of four kinds, :data:`UncertaintyKind`:

- ``"coverage"`` (:func:`coverage_map`): 1 on every rendered pixel, 0 in holes: the "no Stereo
  Forcing" baseline, which trusts the render wherever it has something.
- ``"random"`` (:func:`random_map`): one uniform level in [0, 1] per square patch, diffusion
  forcing's per-token noise levels (the paper's "random noise").
- ``"entropy"`` (:func:`entropy_map`): ``1 - H / log K`` of the rendered entropy of Stage 1's depth
  distribution over K bins (:mod:`phigenesis.models.depth_bins`).
- ``"localization_potential"`` (:func:`localization_potential`, then
  :func:`localization_potential_to_u`): how far a pixel's point moves in the history images per
  metre of depth along its ray (Park et al. 2022, "Time Will Tell"), turned into ``u`` by the pixels
  it moves per depth bin: by default high where a depth error barely moves the render.

Every map is 0 in holes: pixels whose rendered alpha is below ``hole_alpha`` (default
:data:`HOLE_ALPHA`, 0.5, the alpha at which the rest of the toolkit counts a rendered pixel as
covered; NaN alpha is a hole). :func:`uncertainty_map` is the single entry point over them.

Conventions are the toolkit's: OpenCV cameras (x right, y down, z forward), depth in metres along
the camera z axis with 0 = unknown, 4x4 float64 poses named ``world_from_camera``, pinhole
intrinsics ``[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` at the image's resolution with pixel
centres at integer coordinates (:func:`phigenesis.models.stage1.pixel_rays`), so an image of width
W spans ``u`` in [-1/2, W - 1/2).

Localization potential (LP)
---------------------------
A target pixel with rendered z-depth ``d`` sees the point ``d r`` along its ray ``r = K^-1 (u, v,
1)`` (z = 1, target camera frame). In a history camera, with ``[R | t]`` the history camera from the
target camera, that point is ``X = d a + t = (x, y, z)``, ``a = R r``, and projects to
``(fx x/z + skew y/z + cx, fy y/z + cy)``. Its image motion per metre of depth along the target
ray is, differentiating in ``d``::

    d(x/z)/dd = (a_x z - x a_z) / z^2        d(y/z)/dd = (a_y z - y a_z) / z^2
    du/dd = fx d(x/z)/dd + skew d(y/z)/dd    dv/dd = fy d(y/z)/dd

and ``LP = |(du/dd, dv/dd)|`` in px/m (the derivative of the source-view projection in depth that
Park et al., "Time Will Tell", arXiv:2210.02443, call localization potential, with the skew term
added; theirs when skew = 0). LP is 0 for that history view where ``z`` is below
:data:`phigenesis.geometry.MIN_PROJECTION_DEPTH_M` (behind the history camera), where the projection
leaves the history image, and, given the history views' own depth maps, where the point is occluded
there; over several history views the largest counts. For a history camera displaced by a baseline
``b`` perpendicular to the optical axis, a point on the axis at depth ``d`` has ``LP = f b / d^2``;
a history camera at the target's position (any rotation) has LP = 0: a pixel's ray projects to one
point there, whatever its depth.

From LP to u (a choice: the paper does not say)
-----------------------------------------------
Stage 1 resolves depth in log-spaced bins (``DepthBins``), so a depth error of one bin at depth
``d`` spans ``delta_d = 2 d sinh(step / 2)`` metres (``step`` the bin's width in natural log
depth; :func:`depth_bin_width_m`). Between the target view and the history view that sees the
point best, such an error moves the point by ``m = LP * delta_d`` pixels. Pixels per bin measures
a relative depth error, as the log-spaced bins do, whatever the scene's scale in metres; for the
lateral pair ``m = f b step / d`` (up to ``sinh``): the stereo disparity times the bin's relative
width. Two readings of ``m`` turn it into trust, :data:`LpTrust`:

- ``"stable"`` (the default), ``u = exp(-m / scale_px)``: trust the render where a depth error
  barely moves it. A render made from the history's Gaussians is right at the target where the
  pixel it shows would not move much if its depth were off by a bin: far points, targets near the
  history camera. It falls to ``1/e`` where one bin shows as ``scale_px`` pixels (default 1 px).
  A covered pixel that no history view sees unoccluded (mostly the occlusion test at depth edges)
  has ``m = 0`` and u = 1.
- ``"localised"``, ``u = 1 - exp(-m / scale_px)``: trust the points the history's views localise
  well (Park et al.'s reading: a wide baseline pins the depth down), 0 where the history cannot
  see a depth error at all (no baseline, ``m = 0``). This was the only mapping before
  2026-12-05: a Stage 2 checkpoint whose training config names none was trained with it.

Why ``"stable"`` is the default: our Stage 1 predicts depth from each view alone (no stereo
across the history), so how well the history *could* localise a point says little about how
right its depth is, while how far a depth error moves the render says directly how wrong the
render can be. Scored on held-out scenes, untrained and trained, ``"stable"`` beats both
``coverage`` and ``"localised"`` (BENCHMARKS.md, "Stage 2"; docs/design/stage2.md, "Which way LP
becomes trust").
Holes, unknown depth (0, NaN, inf) give 0 either way.

Memory and speed: :func:`localization_potential` works in float64 one history camera at a time,
vectorised over target views and pixels, with about twenty float64 values per target pixel alive
at once: 5 target views x 10 history views at 160 x 240 (with occlusion) grow the peak memory by
about 50 MB and take about 0.15 s on one CPU thread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, assert_never, get_args

import torch
from torch import Tensor

from phigenesis.geometry import MIN_PROJECTION_DEPTH_M
from phigenesis.models.depth_bins import DepthBins
from phigenesis.models.stage1 import pixel_rays
from phigenesis.options import check_options, option

#: The kinds of uncertainty map :func:`uncertainty_map` makes.
UncertaintyKind = Literal["random", "entropy", "localization_potential", "coverage"]
#: How the localization potential becomes trust (module docstring): ``"stable"`` trusts pixels a
#: depth error barely moves, ``"localised"`` the points the history localises well.
LpTrust = Literal["stable", "localised"]
LP_TRUSTS: tuple[str, ...] = get_args(LpTrust)
#: The mapping Stage 2 uses unless told otherwise.
DEFAULT_LP_TRUST: LpTrust = "stable"
#: The mapping of Stage 2 checkpoints, configs and latent caches that name none (made before the
#: choice existed).
LEGACY_LP_TRUST: LpTrust = "localised"

#: Rendered pixels whose alpha is below this are holes (u = 0), as elsewhere in the toolkit.
HOLE_ALPHA = 0.5
#: Side of one random level's square patch, pixels: one latent token of an 8x spatial VAE.
DEFAULT_PATCH_PX = 8
#: The paper's Stage 1 depth bins (``stage1_base``: 200 bins between 0.5 m and 120 m).
PAPER_DEPTH_BINS = DepthBins(0.5, 120.0, 200)
#: One depth bin's width in natural log depth, for :func:`localization_potential_to_u`.
DEFAULT_LOG_DEPTH_STEP = PAPER_DEPTH_BINS.step
#: Pixels moved per depth bin at which the localization-potential u is ``1/e`` (``1 - 1/e`` localised).
DEFAULT_SCALE_PX = 1.0
#: A point is occluded in a history view when its z exceeds that view's depth by more than this
#: fraction of it (about two of the paper's depth bins).
OCCLUSION_TOLERANCE = 0.05
#: Largest deviation from a rigid transform (``R^T R - I``, bottom row) a pose may have.
RIGID_TOLERANCE = 1e-6


# --------------------------------------------------------------------------------------------
# Checks


def check_lp_trust(value: object, what: str) -> LpTrust:
    """``value`` as an :data:`LpTrust`, or ValueError naming ``what`` (e.g. the config field)."""
    if value not in LP_TRUSTS:
        raise ValueError(f"{what} must be one of {LP_TRUSTS}, got {value!r}")
    return value  # type: ignore[return-value]


def _covered(alpha: Tensor, hole_alpha: float) -> Tensor:
    """bool (same shape): pixels the render covers (alpha >= hole_alpha; NaN alpha is a hole)."""
    if not 0.0 <= hole_alpha <= 1.0:
        raise ValueError(f"hole_alpha must be in [0, 1], got {hole_alpha}")
    return alpha >= hole_alpha


def _out_dtype(t: Tensor) -> torch.dtype:
    """The floating dtype a map made from ``t`` is returned in (float32 for non-floating inputs)."""
    return t.dtype if t.is_floating_point() else torch.float32


def _check_intrinsics(intrinsics: Tensor, name: str) -> Tensor:
    """(..., 3, 3) float64 copy of pinhole matrices, or ValueError if any is not one."""
    if intrinsics.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: expected [..., 3, 3] intrinsics, got shape {tuple(intrinsics.shape)}")
    k = intrinsics.double()
    if not torch.isfinite(k).all():
        raise ValueError(f"{name}: intrinsics hold NaN or inf")
    if not ((k[..., 0, 0] > 0) & (k[..., 1, 1] > 0)).all():
        raise ValueError(f"{name}: focal lengths fx and fy must be > 0, got {k[..., 0, 0]}, {k[..., 1, 1]}")
    bottom = k[..., 2, :] - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=k.device)
    if not ((bottom.abs().amax(-1) <= 1e-9) & (k[..., 1, 0].abs() <= 1e-9)).all():
        raise ValueError(f"{name}: intrinsics must be [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]")
    return k


def _check_poses(poses: Tensor, name: str) -> Tensor:
    """(..., 4, 4) float64 copy of rigid transforms, or ValueError if any is not one."""
    if poses.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected [..., 4, 4] poses, got shape {tuple(poses.shape)}")
    p = poses.double()
    if not torch.isfinite(p).all():
        raise ValueError(f"{name}: poses hold NaN or inf")
    rot = p[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64, device=p.device)
    ortho = (rot.transpose(-1, -2) @ rot - eye).abs().amax((-1, -2))
    bottom = (p[..., 3, :] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device=p.device)).abs()
    det = torch.linalg.det(rot) if rot.numel() else rot.new_ones(rot.shape[:-2])
    if not ((ortho <= RIGID_TOLERANCE) & (bottom.amax(-1) <= RIGID_TOLERANCE) & (det > 0)).all():
        raise ValueError(
            f"{name}: poses must be rigid (rotation with R^T R = I and det +1 to {RIGID_TOLERANCE}, "
            f"bottom row 0 0 0 1); worst |R^T R - I| {ortho.max().item() if ortho.numel() else 0:.3g}"
        )
    return p


# --------------------------------------------------------------------------------------------
# The maps


def coverage_map(alpha: Tensor, hole_alpha: float = HOLE_ALPHA) -> Tensor:
    """The "no Stereo Forcing" baseline: trust every rendered pixel.

    Args:
        alpha: [..., H, W] rendered alpha (opacity accumulated along each ray), in [0, 1].
        hole_alpha: pixels with alpha below this are holes.

    Returns:
        [..., H, W] u: 1 where ``alpha >= hole_alpha``, 0 in holes, in ``alpha``'s floating dtype
        (float32 otherwise). Binary rather than alpha itself: the rendered condition is already
        alpha-normalised, so a partly covered pixel is no less trustworthy for its low alpha, and
        the baseline weighs every rendered pixel alike.
    """
    return _covered(alpha, hole_alpha).to(_out_dtype(alpha))


def random_map(
    shape: tuple[int, ...] | torch.Size,
    patch_px: int,
    generator: torch.Generator,
    alpha: Tensor,
    hole_alpha: float = HOLE_ALPHA,
) -> Tensor:
    """Diffusion forcing's per-token levels: one uniform level in [0, 1) per square patch.

    Patches are ``patch_px`` x ``patch_px`` pixels, anchored at pixel (0, 0); the last row and
    column of patches are cut to the image. Levels are drawn from ``generator`` (one per patch, in
    row-major order over ``[..., ceil(H / patch_px), ceil(W / patch_px)]``), so a generator seeded
    alike gives the same map.

    Args:
        shape: (..., H, W) of the map, ``alpha``'s shape.
        patch_px: side of one patch, pixels (>= 1).
        generator: the random stream, on ``alpha``'s device.
        alpha: [..., H, W] rendered alpha; holes (alpha < ``hole_alpha``) get u = 0.
        hole_alpha: pixels with alpha below this are holes.

    Returns:
        [..., H, W] u in ``alpha``'s floating dtype (float32 otherwise).
    """
    shape = tuple(shape)
    if len(shape) < 2:
        raise ValueError(f"random_map: shape needs (..., H, W), got {shape}")
    if tuple(alpha.shape) != shape:
        raise ValueError(f"random_map: alpha has shape {tuple(alpha.shape)}, the map {shape}")
    if patch_px < 1:
        raise ValueError(f"random_map: patch_px must be >= 1, got {patch_px}")
    height, width = shape[-2:]
    grid = (*shape[:-2], -(-height // patch_px), -(-width // patch_px))
    dtype = _out_dtype(alpha)
    levels = torch.rand(grid, generator=generator, dtype=torch.float64, device=alpha.device)
    u = levels.repeat_interleave(patch_px, -2).repeat_interleave(patch_px, -1)[..., :height, :width]
    return torch.where(_covered(alpha, hole_alpha), u, 0.0).to(dtype)  # [..., H, W]


def entropy_map(entropy_nats: Tensor, num_bins: int, alpha: Tensor, hole_alpha: float = HOLE_ALPHA) -> Tensor:
    """Trust from the depth distribution's entropy: ``u = 1 - H / log K``, clipped to [0, 1].

    Args:
        entropy_nats: [..., H, W] rendered per-pixel entropy (nats) of Stage 1's depth distribution
            over ``num_bins`` bins (:func:`phigenesis.models.depth_bins.entropy` of each Gaussian,
            composited and normalised by alpha in the renderer), in [0, log K]: 0 for a one-hot
            distribution (u = 1), ``log K`` for a uniform one (u = 0). NaN gives u = 0.
        num_bins: K, the number of depth bins (>= 2).
        alpha: [..., H, W] rendered alpha; holes get u = 0.
        hole_alpha: pixels with alpha below this are holes.

    Returns:
        [..., H, W] u in ``entropy_nats``' floating dtype (float32 otherwise).
    """
    if entropy_nats.shape != alpha.shape:
        raise ValueError(f"entropy_map: entropy {tuple(entropy_nats.shape)} vs alpha {tuple(alpha.shape)}")
    if num_bins < 2:
        raise ValueError(f"entropy_map: need at least 2 bins, got {num_bins}")
    u = (1.0 - entropy_nats.double() / math.log(num_bins)).clamp(0.0, 1.0)
    keep = _covered(alpha, hole_alpha) & ~torch.isnan(u)
    return torch.where(keep, u, 0.0).to(_out_dtype(entropy_nats))


def localization_potential(
    depth_m: Tensor,
    intrinsics: Tensor,
    world_from_camera: Tensor,
    history_intrinsics: Tensor,
    history_world_from_camera: Tensor,
    history_hw: tuple[int, int],
    alpha: Tensor | None = None,
    history_depth_m: Tensor | None = None,
    occlusion_tolerance: float = OCCLUSION_TOLERANCE,
    hole_alpha: float = HOLE_ALPHA,
) -> Tensor:
    """Image motion in the history views per metre of depth along each target pixel's ray (px/m).

    For every target pixel with a finite rendered z-depth ``d > 0``, the point ``d K^-1 (u, v, 1)``
    is carried into each history camera and the norm of ``d(projection)/dd`` is taken in closed form
    (module docstring); a history view adds 0 where the point is behind it, projects outside its
    ``history_hw`` image, or (given ``history_depth_m``) is occluded there. The largest over history
    views is the pixel's LP. Computed in float64, one history camera at a time.

    Args:
        depth_m: [..., H, W] rendered z-depth of the target views (metres along camera z; 0, NaN or
            inf: unknown, LP 0), e.g. [V, H, W].
        intrinsics: [..., 3, 3] target pinhole matrices at H x W (pixel centres at integers).
        world_from_camera: [..., 4, 4] target camera poses (OpenCV axes), world frame, float64.
        history_intrinsics: [N, 3, 3] history pinhole matrices at ``history_hw``.
        history_world_from_camera: [N, 4, 4] history camera poses, same world frame, float64.
        history_hw: (H_h, W_h), the size of every history image.
        alpha: optional [..., H, W] rendered alpha of the targets; LP 0 where below ``hole_alpha``.
        history_depth_m: optional [N, H_h, W_h] the history views' own z-depth (0 = unknown, never
            occludes). A point is occluded in a view when its z there exceeds the depth at the
            pixel it projects to (nearest pixel centre) by more than ``occlusion_tolerance`` times
            that depth.
        occlusion_tolerance: relative depth margin of the occlusion test (>= 0).
        hole_alpha: pixels with alpha below this are holes.

    Returns:
        [..., H, W] LP in px/m, >= 0 and finite, in ``depth_m``'s floating dtype (float32 otherwise).

    Raises:
        ValueError: on mismatched shapes, non-finite or non-rigid poses, intrinsics that are not
            pinhole matrices with fx, fy > 0, or a negative tolerance.

    Example::

        lp = localization_potential(depth_m, k, world_from_camera, hist_k, world_from_hist, (160, 240))
        u = localization_potential_to_u(lp, depth_m, alpha)
    """
    if depth_m.dim() < 2:
        raise ValueError(f"localization_potential: depth needs [..., H, W], got {tuple(depth_m.shape)}")
    lead, (height, width) = depth_m.shape[:-2], depth_m.shape[-2:]
    if intrinsics.shape != (*lead, 3, 3):
        raise ValueError(f"localization_potential: intrinsics {tuple(intrinsics.shape)} for depth {lead}")
    if world_from_camera.shape != (*lead, 4, 4):
        raise ValueError(f"localization_potential: poses {tuple(world_from_camera.shape)} for depth {lead}")
    if history_intrinsics.dim() != 3 or history_world_from_camera.dim() != 3:
        raise ValueError("localization_potential: history cameras need [N, 3, 3] and [N, 4, 4]")
    n_hist = history_intrinsics.shape[0]
    if history_world_from_camera.shape[0] != n_hist:
        raise ValueError(
            f"localization_potential: {n_hist} history intrinsics, "
            f"{history_world_from_camera.shape[0]} history poses"
        )
    h_hist, w_hist = (int(s) for s in history_hw)
    if h_hist < 1 or w_hist < 1:
        raise ValueError(f"localization_potential: history_hw must be positive, got {history_hw}")
    if alpha is not None and alpha.shape != depth_m.shape:
        raise ValueError(
            f"localization_potential: alpha {tuple(alpha.shape)} vs depth {tuple(depth_m.shape)}"
        )
    if history_depth_m is not None and history_depth_m.shape != (n_hist, h_hist, w_hist):
        raise ValueError(
            f"localization_potential: history depth {tuple(history_depth_m.shape)}, "
            f"expected {(n_hist, h_hist, w_hist)}"
        )
    if not occlusion_tolerance >= 0:
        raise ValueError(
            f"localization_potential: occlusion_tolerance must be >= 0, got {occlusion_tolerance}"
        )
    k_tgt = _check_intrinsics(intrinsics, "target").reshape(-1, 3, 3)  # [V, 3, 3]
    pose_tgt = _check_poses(world_from_camera, "target").reshape(-1, 4, 4)  # [V, 4, 4]
    k_hist = _check_intrinsics(history_intrinsics, "history")  # [N, 3, 3]
    pose_hist = _check_poses(history_world_from_camera, "history")  # [N, 4, 4]

    n_views, n_pix = k_tgt.shape[0], height * width
    depth = depth_m.reshape(n_views, n_pix).double()  # [V, P]
    valid = torch.isfinite(depth) & (depth > 0)
    if alpha is not None:
        valid &= _covered(alpha.reshape(n_views, n_pix), hole_alpha)
    depth = torch.where(valid, depth, 1.0)[:, None]  # [V, 1, P]
    rays = pixel_rays(k_tgt, height, width).reshape(n_views, 3, n_pix)  # [V, 3, P] target frame, z = 1
    rot_tgt, t_tgt = pose_tgt[:, :3, :3], pose_tgt[:, :3, 3]  # [V, 3, 3], [V, 3]
    hist_depth = None if history_depth_m is None else history_depth_m.double().reshape(n_hist, -1)

    lp = torch.zeros(n_views, n_pix, dtype=torch.float64, device=depth.device)  # [V, P]
    for n in range(n_hist):
        rot_h, t_h = pose_hist[n, :3, :3], pose_hist[n, :3, 3]
        rot = rot_h.T @ rot_tgt  # [V, 3, 3] history_from_target rotation
        trans = (t_tgt - t_h) @ rot_h  # [V, 3] history_from_target translation, R_h^T (t_tgt - t_h)
        a = rot @ rays  # [V, 3, P] ray directions in the history frame
        x = depth * a + trans[:, :, None]  # [V, 3, P] points in the history frame
        z = x[:, 2]  # [V, P]
        seen = z > MIN_PROJECTION_DEPTH_M
        z = torch.where(seen, z, 1.0)
        xn, yn = x[:, 0] / z, x[:, 1] / z  # [V, P] normalised image coordinates
        fx, skew, cx = k_hist[n, 0, 0], k_hist[n, 0, 1], k_hist[n, 0, 2]
        fy, cy = k_hist[n, 1, 1], k_hist[n, 1, 2]
        u = fx * xn + skew * yn + cx  # [V, P] history pixel coordinates
        v = fy * yn + cy
        seen &= (u >= -0.5) & (u < w_hist - 0.5) & (v >= -0.5) & (v < h_hist - 0.5)
        gx = (a[:, 0] - xn * a[:, 2]) / z  # [V, P] d(x/z)/dd = (a_x z - x a_z) / z^2
        gy = (a[:, 1] - yn * a[:, 2]) / z  # [V, P] d(y/z)/dd
        lp_n = torch.hypot(fx * gx + skew * gy, fy * gy)  # [V, P] px/m
        seen &= torch.isfinite(lp_n)
        if hist_depth is not None:
            col = torch.floor(u + 0.5).clamp(0, w_hist - 1).long()  # nearest pixel centre
            row = torch.floor(v + 0.5).clamp(0, h_hist - 1).long()
            there = hist_depth[n][row * w_hist + col]  # [V, P] history depth at the projection
            seen &= ~((there > 0) & (x[:, 2] > there * (1.0 + occlusion_tolerance)))
        lp = torch.maximum(lp, torch.where(seen, lp_n, 0.0))
    lp = torch.where(valid, lp, 0.0)
    return lp.reshape(depth_m.shape).to(_out_dtype(depth_m))


def depth_bin_width_m(depth_m: Tensor, log_depth_step: float = DEFAULT_LOG_DEPTH_STEP) -> Tensor:
    """(same shape) metres spanned by a log-depth bin of width ``log_depth_step`` centred at each
    depth: ``d (e^(step/2) - e^(-step/2)) = 2 d sinh(step / 2)`` (``DepthBins.step`` for Stage 1's)."""
    return depth_m * (2.0 * math.sinh(log_depth_step / 2.0))


def localization_potential_to_u(
    lp_px_per_m: Tensor,
    depth_m: Tensor,
    alpha: Tensor,
    log_depth_step: float = DEFAULT_LOG_DEPTH_STEP,
    scale_px: float = DEFAULT_SCALE_PX,
    hole_alpha: float = HOLE_ALPHA,
    trust: LpTrust = DEFAULT_LP_TRUST,
) -> Tensor:
    """Trust from localization potential: ``m = LP * delta_d(d)`` pixels moved per depth bin, then
    ``u = exp(-m / scale_px)`` (``trust="stable"``) or ``u = 1 - exp(-m / scale_px)``
    (``trust="localised"``); module docstring.

    Args:
        lp_px_per_m: [..., H, W] LP from :func:`localization_potential`, px/m, >= 0 (inf allowed:
            m = inf).
        depth_m: [..., H, W] the rendered z-depth it was computed at, metres (0, NaN, inf: u = 0).
        alpha: [..., H, W] rendered alpha; holes get u = 0.
        log_depth_step: width of one depth bin in natural log depth (> 0), e.g. ``DepthBins.step``.
        scale_px: pixels per bin at which u = 1/e (stable) or 1 - 1/e (localised), > 0.
        hole_alpha: pixels with alpha below this are holes.
        trust: ``"stable"`` or ``"localised"`` (:data:`LpTrust`).

    Returns:
        [..., H, W] u in [0, 1], never NaN, in ``lp_px_per_m``'s floating dtype (float32 otherwise).
    """
    if not (lp_px_per_m.shape == depth_m.shape == alpha.shape):
        raise ValueError(
            f"localization_potential_to_u: LP {tuple(lp_px_per_m.shape)}, depth {tuple(depth_m.shape)}, "
            f"alpha {tuple(alpha.shape)} differ"
        )
    if not (log_depth_step > 0 and math.isfinite(log_depth_step)):
        raise ValueError(f"localization_potential_to_u: log_depth_step must be > 0, got {log_depth_step}")
    if not (scale_px > 0 and math.isfinite(scale_px)):
        raise ValueError(f"localization_potential_to_u: scale_px must be > 0, got {scale_px}")
    check_lp_trust(trust, "localization_potential_to_u: trust")
    lp = lp_px_per_m.double()
    if torch.isnan(lp).any() or (lp < 0).any():
        raise ValueError("localization_potential_to_u: LP must be >= 0 and not NaN")
    depth = depth_m.double()
    valid = _covered(alpha, hole_alpha) & torch.isfinite(depth) & (depth > 0)
    moved_px = lp * depth_bin_width_m(torch.where(valid, depth, 0.0), log_depth_step)  # px per bin
    valid &= ~torch.isnan(moved_px)  # inf * 0 where a tiny depth's bin width underflows
    decay = -torch.where(valid, moved_px, 0.0) / scale_px
    u = torch.exp(decay) if trust == "stable" else -torch.expm1(decay)
    return torch.where(valid, u, 0.0).clamp(0.0, 1.0).to(_out_dtype(lp_px_per_m))


# --------------------------------------------------------------------------------------------
# Entry point


@dataclass(frozen=True)
class UncertaintyConfig:
    """Parameters of the uncertainty maps; each kind reads the fields it needs."""

    hole_alpha: float = option(
        HOLE_ALPHA, ge=0, le=1, help="rendered alpha below which a pixel is a hole (u = 0)"
    )
    patch_px: int = option(
        DEFAULT_PATCH_PX, ge=1, le=4096, help="random: side of one level's square patch, pixels"
    )
    num_bins: int = option(
        PAPER_DEPTH_BINS.count, ge=2, le=4096, help="entropy: K, bins of Stage 1's depth distribution"
    )
    log_depth_step: float = option(
        DEFAULT_LOG_DEPTH_STEP, gt=0, le=10, help="localization potential: bin width, natural log depth"
    )
    scale_px: float = option(
        DEFAULT_SCALE_PX,
        gt=0,
        le=1e6,
        help="localization potential: pixels per bin at which u = 1/e (stable)",
    )
    occlusion_tolerance: float = option(
        OCCLUSION_TOLERANCE, ge=0, le=10, help="localization potential: relative depth margin"
    )
    lp_trust: LpTrust = option(
        DEFAULT_LP_TRUST, help="localization potential: which points u trusts (module docstring)"
    )

    def __post_init__(self) -> None:
        check_options(self, "UncertaintyConfig")


@dataclass(frozen=True)
class HistoryViews:
    """The N history cameras the target views are localised against, all of one image size.

    ``intrinsics`` [N, 3, 3] pinhole matrices at ``hw``; ``world_from_camera`` [N, 4, 4] float64
    poses (OpenCV axes) in the targets' world frame; ``hw`` (H_h, W_h); ``depth_m`` optional
    [N, H_h, W_h] their own z-depth (metres, 0 = unknown) for the occlusion test.
    """

    intrinsics: Tensor
    world_from_camera: Tensor
    hw: tuple[int, int]
    depth_m: Tensor | None = None


def uncertainty_map(
    kind: UncertaintyKind,
    alpha: Tensor,
    *,
    config: UncertaintyConfig | None = None,
    generator: torch.Generator | None = None,
    entropy_nats: Tensor | None = None,
    depth_m: Tensor | None = None,
    intrinsics: Tensor | None = None,
    world_from_camera: Tensor | None = None,
    history: HistoryViews | None = None,
) -> Tensor:
    """Stereo Forcing's uncertainty map ``u`` in [0, 1] (1 = trust the render) for each target view.

    Args:
        kind: ``"coverage"`` (:func:`coverage_map`), ``"random"`` (:func:`random_map`, needs
            ``generator``), ``"entropy"`` (:func:`entropy_map`, needs ``entropy_nats``) or
            ``"localization_potential"`` (:func:`localization_potential` then
            :func:`localization_potential_to_u`, needs ``depth_m``, ``intrinsics``,
            ``world_from_camera`` and ``history``).
        alpha: [V, H, W] (or [..., H, W]) rendered alpha of the target views; holes get u = 0.
        config: the maps' parameters (defaults: :class:`UncertaintyConfig`).
        generator: the random stream of ``"random"``.
        entropy_nats: [..., H, W] rendered depth entropy (nats) for ``"entropy"``.
        depth_m: [..., H, W] rendered z-depth (metres, 0 = unknown) for ``"localization_potential"``.
        intrinsics: [..., 3, 3] target pinhole matrices at H x W.
        world_from_camera: [..., 4, 4] float64 target camera poses, world frame.
        history: the history cameras.

    Returns:
        [..., H, W] u in [0, 1], 0 in holes.

    Raises:
        ValueError: when an input the kind needs is missing, or any input is invalid.

    Example::

        u = uncertainty_map("entropy", alpha, entropy_nats=entropy, config=UncertaintyConfig(num_bins=64))
        condition = u[:, None] * rendered_latent_input
    """
    if kind not in get_args(UncertaintyKind):
        raise ValueError(f"uncertainty_map: kind must be one of {get_args(UncertaintyKind)}, got {kind!r}")
    c = config if config is not None else UncertaintyConfig()

    def need(value: object, name: str) -> None:
        if value is None:
            raise ValueError(f"uncertainty_map({kind!r}) needs {name}")

    if kind == "coverage":
        return coverage_map(alpha, c.hole_alpha)
    elif kind == "random":
        need(generator, "generator")
        assert generator is not None
        return random_map(alpha.shape, c.patch_px, generator, alpha, c.hole_alpha)
    elif kind == "entropy":
        need(entropy_nats, "entropy_nats")
        assert entropy_nats is not None
        return entropy_map(entropy_nats, c.num_bins, alpha, c.hole_alpha)
    elif kind == "localization_potential":
        need(depth_m, "depth_m")
        need(intrinsics, "intrinsics")
        need(world_from_camera, "world_from_camera")
        need(history, "history")
        assert depth_m is not None and intrinsics is not None and world_from_camera is not None
        assert history is not None
        lp = localization_potential(
            depth_m,
            intrinsics,
            world_from_camera,
            history.intrinsics,
            history.world_from_camera,
            history.hw,
            alpha=alpha,
            history_depth_m=history.depth_m,
            occlusion_tolerance=c.occlusion_tolerance,
            hole_alpha=c.hole_alpha,
        )
        return localization_potential_to_u(
            lp,
            depth_m,
            alpha,
            log_depth_step=c.log_depth_step,
            scale_px=c.scale_px,
            hole_alpha=c.hole_alpha,
            trust=c.lp_trust,
        )
    else:
        assert_never(kind)
