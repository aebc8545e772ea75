"""Differentiable 3D Gaussian splatting rasterizer in pure PyTorch (CPU first): :func:`rasterize`.

The maths follows 3DGS / gsplat's pinhole EWA path (see docs of ``gsplat.rasterization``), written
from the equations, with the project's conventions (``phigenesis.geometry``):

- cameras use OpenCV axes (x right, y down, z forward) and are given as ``world_from_camera``;
- quaternions are ``w, x, y, z`` and need not be normalised (a zero quaternion means identity);
- integer pixel coordinates are pixel centres: pixel ``(row i, column j)`` sits at ``(u, v) = (j, i)``
  (gsplat and Inria use ``j + 0.5``; give them ``cx + 0.5, cy + 0.5`` for the same image).

Per camera and Gaussian: ``Sigma = R diag(s)^2 R^T``, camera-space mean and covariance, the EWA
Jacobian ``J`` (its ``x/z``, ``y/z`` clamped to 1.3 x the field of view, only inside ``J``), the 2D
covariance ``J Sigma J^T + 0.3 I`` (low-pass dilation). Gaussians with ``z <= near``, opacity below
1/255, a non-finite projection or a box holding no pixel centre are culled.

Compositing follows gsplat 1.5.3 (one set of conventions for every backend, so a model trained on a
CPU renders the same with gsplat on a GPU): a pixel takes the Gaussians front to back by camera z
(ties in index order) with ``alpha = min(0.999, opacity * exp(-sigma))``, skipping ``sigma < 0`` and
``alpha < 1/255``; a Gaussian that would bring the transmittance to ``<= 1e-4`` is not added and ends
the pixel. Each Gaussian's box is per axis, ``ceil(k sqrt(Sigma2d_xx))`` by ``ceil(k sqrt(Sigma2d_yy))``
pixels with ``k = min(3.33, sqrt(2 ln(255 opacity)))`` (gsplat's opacity-aware extent): the bounding box
of the ellipse where alpha reaches 1/255, so the alpha threshold alone decides which pixels a Gaussian
touches and the box only bounds the work.

Backends (:func:`rasterize`, ``backend=``): ``"cpu"`` is the native C++ kernel
(``csrc/rasterize_cpu.cpp``, built on first use by :mod:`phigenesis.models.native`: per-tile depth-sorted
lists, front-to-back compositing with early stop, gradients by back-to-front replay); ``"torch"`` bins
Gaussians into tiles, sorts each tile by depth and composites tiles in batches (cumulative products; with
gradients, a no-grad pass first finds how many of each tile's Gaussians any pixel adds before it stops,
and the checkpointed gradient pass only covers those); ``"gsplat"`` calls gsplat's CUDA kernels;
``"auto"`` (the default) picks gsplat for CUDA tensors when it is installed, else the native kernel on
the CPU when it builds, else the PyTorch path, and logs its choice once. ``$PHIGENESIS_RASTERIZER``
(``cpu`` or ``torch``) overrides what ``"auto"`` picks. :func:`rasterize_reference` loops over all
depth-sorted Gaussians for every pixel with no tiles, and is what the tests compare the others against.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from phigenesis import geometry
from phigenesis.models import native

logger = logging.getLogger(__name__)

#: Low-pass filter added to the diagonal of every 2D covariance (pixels^2).
EPS_2D = 0.3
#: Largest alpha one Gaussian may have at a pixel (gsplat 1.5.3).
MAX_ALPHA = 0.999
#: Contributions with a smaller alpha are skipped.
ALPHA_THRESHOLD = 1.0 / 255.0
#: A pixel stops compositing before the Gaussian that would bring its transmittance to this or below.
TRANSMITTANCE_THRESHOLD = 1e-4
#: Largest box half-width in standard deviations (gsplat's GAUSSIAN_EXTEND); the opacity-aware extent
#: ``sqrt(2 ln(255 opacity))`` is at most 3.329, so it is the alpha threshold that bounds a box.
GAUSSIAN_EXTEND = 3.33
#: Field-of-view margin of the Jacobian clamp: ``x/z`` is clamped to 1.3 x the half-FoV (Inria, gsplat).
FOV_CLAMP_MARGIN = 0.3
#: Scales are clamped to this (metres) so that covariances stay finite in float32.
MAX_SCALE = 1e4
#: Below this squared norm a quaternion is treated as "no rotation" (identity).
QUATERNION_ZERO_SQNORM = 1e-24
#: The constants the native projection (``project``, ``project_backward``) takes after ``near``, in order.
_PROJECTION_CONSTANTS = (EPS_2D, FOV_CLAMP_MARGIN, MAX_SCALE, QUATERNION_ZERO_SQNORM)

Backend = Literal["auto", "cpu", "torch", "gsplat"]
BACKENDS = ("auto", "cpu", "torch", "gsplat")


@dataclass(frozen=True)
class RenderOutput:
    """What :func:`rasterize` returns (C cameras, H x W pixels, F feature channels, N Gaussians)."""

    #: (C, H, W, F) alpha-composited features, with no background (add ``(1 - alpha) * bg`` for one).
    features: Tensor
    #: (C, H, W) expected camera z-depth in metres, ``sum w_i z_i / sum w_i``; 0 where alpha is 0.
    depth: Tensor
    #: (C, H, W) accumulated opacity ``1 - T_final``.
    alpha: Tensor
    #: (C, N) int64 box half-width in pixels, the larger of the two axes; 0 for culled Gaussians.
    radii: Tensor


@dataclass(frozen=True)
class Projection:
    """Per-camera screen-space Gaussians, (C, N, ...)."""

    means2d: Tensor  # (C, N, 2) pixel (u, v)
    conics: Tensor  # (C, N, 3) inverse 2D covariance (A, B, C): sigma = A dx^2/2 + B dx dy + C dy^2/2
    depths: Tensor  # (C, N) camera z in metres
    radii: Tensor  # (C, N, 2) float box half-widths along u and v in pixels (no gradient), 0 if culled
    valid: Tensor  # (C, N) bool


def zero_quaternions_to_identity(quats: Tensor) -> Tensor:
    """(..., 4) wxyz quaternions with those of squared norm at most :data:`QUATERNION_ZERO_SQNORM`
    replaced by the identity (the project's meaning of a zero quaternion), the others unchanged."""
    sq = (quats * quats).sum(-1, keepdim=True)  # (..., 1)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    return torch.where(sq > QUATERNION_ZERO_SQNORM, quats, identity)


def quaternion_to_rotation(quats: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices from (..., 4) wxyz quaternions; zero ones give the identity."""
    q = zero_quaternions_to_identity(quats)
    q = q * torch.rsqrt((q * q).sum(-1, keepdim=True))
    rot = torch.stack(geometry.rotation_entries(*q.unbind(-1)), dim=-1)
    return rot.reshape(*rot.shape[:-1], 3, 3)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    world_from_camera: Tensor,
    intrinsics: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    opacities: Tensor | None = None,
) -> Projection:
    """EWA projection of N Gaussians into C pinhole cameras (shared by every backend).

    ``means`` is (N, 3), or (C, N, 3) for a centre per camera (a moving scene seen by cameras that
    fire at different times). ``opacities`` (N,) set each box's opacity-aware extent and cull
    those below 1/255; without them the extent is :data:`GAUSSIAN_EXTEND` (gsplat's pure-PyTorch
    projection).

    On the CPU, with float32 or float64 tensors, the native extension computes it (the twin of the
    PyTorch code: same formulas in the same order and precision, multi-threaded): where no gradient can
    flow (grad mode off, or no input requires grad) its forward alone, else :class:`_NativeProjection`, its
    forward and its hand-written backward as one autograd step, giving ``means``, ``quats`` and ``scales``
    the gradients autograd gives through the PyTorch code (to rounding). Where ``world_from_camera`` or
    ``intrinsics`` require grad (the native backward has none for them), the inputs do not fit, the
    extension is not built, or ``$PHIGENESIS_PROJECTION`` is ``torch``, the PyTorch code
    (:func:`_project_gaussians_torch`, the reference) does.
    ``radii`` and ``valid`` never carry gradients.
    """
    ext = _native_projection(means, quats, scales, world_from_camera, intrinsics, opacities)
    if ext is not None:
        extend = _box_extend(means.shape[-2], opacities, means.dtype, means.device)
        inputs = (means, quats, scales, world_from_camera, intrinsics)
        sizes = (int(width), int(height), float(near))
        if torch.is_grad_enabled() and any(t.requires_grad for t in inputs):
            means2d, conics, depths, radii, valid = _NativeProjection.apply(
                *(t.contiguous() for t in inputs), extend, *sizes
            )
        else:
            means2d, conics, depths, radii, valid = ext.project(
                *(t.contiguous() for t in inputs), extend, *sizes, *_PROJECTION_CONSTANTS
            )
        return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, valid=valid)
    return _project_gaussians_torch(
        means, quats, scales, world_from_camera, intrinsics, width, height, near, opacities
    )


class _NativeProjection(torch.autograd.Function):
    """The native projection (``ext.project``) and its backward (``ext.project_backward``) as one autograd
    step: gradients reach ``means`` ((N, 3) or (C, N, 3)), ``quats`` (N, 4) and ``scales`` (N, 3) from
    those of ``means2d``, ``conics`` and ``depths``; none reach the cameras (``project_gaussians`` keeps
    cameras that require grad on the PyTorch path) or the box extent. Inputs are contiguous CPU tensors of
    one dtype (float32 or float64); the backward recomputes what it needs from them, nothing else is saved.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, world_from_camera, intrinsics, extend, width, height, near):
        ext = native.load_rasterizer()
        assert ext is not None
        inputs = (means, quats, scales, world_from_camera, intrinsics)
        means2d, conics, depths, radii, valid = ext.project(
            *inputs, extend, width, height, near, *_PROJECTION_CONSTANTS
        )
        ctx.save_for_backward(*inputs)
        ctx.size = (width, height, near)
        ctx.mark_non_differentiable(radii, valid)
        return means2d, conics, depths, radii, valid

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_means2d, grad_conics, grad_depths, _grad_radii, _grad_valid):
        ext = native.load_rasterizer()
        assert ext is not None
        grad_means, grad_quats, grad_scales = ext.project_backward(
            *ctx.saved_tensors,
            grad_means2d.contiguous(),
            grad_conics.contiguous(),
            grad_depths.contiguous(),
            *ctx.size,
            *_PROJECTION_CONSTANTS,
        )
        return grad_means, grad_quats, grad_scales, None, None, None, None, None, None


def _native_projection(means, quats, scales, world_from_camera, intrinsics, opacities):
    """The native extension if it may project these inputs (see :func:`project_gaussians`), else ``None``."""
    tensors = (means, quats, scales, world_from_camera, intrinsics)
    if not all(isinstance(t, Tensor) for t in tensors):
        return None
    if torch.is_grad_enabled() and (world_from_camera.requires_grad or intrinsics.requires_grad):
        return None  # the native backward has no gradients for the cameras
    if os.environ.get("PHIGENESIS_PROJECTION", "").strip().lower() == "torch":
        return None  # kept in PyTorch on purpose (to compare, or to debug)
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64) or any(
        t.dtype != dtype or t.device.type != "cpu" or t.layout != torch.strided for t in tensors
    ):
        return None
    if means.ndim not in (2, 3) or world_from_camera.ndim != 3:
        return None
    n, c = means.shape[-2], world_from_camera.shape[0]
    shapes_ok = (
        means.shape in ((n, 3), (c, n, 3))
        and quats.shape == (n, 4)
        and scales.shape == (n, 3)
        and world_from_camera.shape == (c, 4, 4)
        and intrinsics.shape == (c, 3, 3)
    )
    if not shapes_ok or (
        opacities is not None
        and (not isinstance(opacities, Tensor) or opacities.shape != (n,) or opacities.device.type != "cpu")
    ):
        return None
    return native.load_rasterizer()


def _box_extend(n: int, opacities: Tensor | None, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(N,) box half-width in standard deviations, the values :func:`_project_gaussians_torch` computes
    (the same element-wise ops on the same values wherever the opacity reaches the alpha threshold; 0
    elsewhere, which culls those Gaussians as its ``valid & visible`` does), in fewer passes."""
    with torch.no_grad():
        if opacities is None:
            return torch.full((n,), GAUSSIAN_EXTEND, dtype=dtype, device=device)
        opac = opacities.detach().to(dtype)
        visible = opac >= ALPHA_THRESHOLD
        extend = opac.clamp(min=ALPHA_THRESHOLD).div_(ALPHA_THRESHOLD).log_().mul_(2.0).sqrt_()
        return torch.where(visible, extend.clamp_(max=GAUSSIAN_EXTEND), 0.0)


def _project_gaussians_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    world_from_camera: Tensor,
    intrinsics: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    opacities: Tensor | None = None,
) -> Projection:
    """The PyTorch projection (differentiable; the reference the native one is held to)."""
    n = means.shape[-2]
    rot = quaternion_to_rotation(quats)  # (N, 3, 3)
    m = rot * scales.clamp(min=-MAX_SCALE, max=MAX_SCALE)[:, None, :]  # (N, 3, 3) = R diag(s)
    r_wc = world_from_camera[:, :3, :3]  # (C, 3, 3)
    t_wc = world_from_camera[:, :3, 3]  # (C, 3)
    r_cw = r_wc.transpose(1, 2)  # rigid inverse
    rotated = torch.einsum("cij,nj->cni" if means.ndim == 2 else "cij,cnj->cni", r_cw, means)
    means_c = rotated - torch.einsum("cij,cj->ci", r_cw, t_wc)[:, None]
    x, y, z = means_c.unbind(-1)  # (C, N)
    valid = z > near
    z_safe = torch.where(valid, z, torch.ones_like(z))  # keeps culled Gaussians free of inf and nan grads
    fx, fy = intrinsics[:, 0, 0, None], intrinsics[:, 1, 1, None]  # (C, 1)
    cx, cy = intrinsics[:, 0, 2, None], intrinsics[:, 1, 2, None]
    u = fx * x / z_safe + cx  # (C, N), unclamped
    v = fy * y / z_safe + cy
    # Jacobian of the projection, its x/z, y/z clamped to the (margin-widened) field of view.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - 0.5 - cx) / fx + FOV_CLAMP_MARGIN * tan_x
    lim_x_neg = (cx + 0.5) / fx + FOV_CLAMP_MARGIN * tan_x
    lim_y_pos = (height - 0.5 - cy) / fy + FOV_CLAMP_MARGIN * tan_y
    lim_y_neg = (cy + 0.5) / fy + FOV_CLAMP_MARGIN * tan_y
    tx = torch.maximum(torch.minimum(x / z_safe, lim_x_pos), -lim_x_neg)
    ty = torch.maximum(torch.minimum(y / z_safe, lim_y_pos), -lim_y_neg)
    zeros = torch.zeros_like(z_safe)
    jac = torch.stack(
        [fx / z_safe, zeros, -fx * tx / z_safe, zeros, fy / z_safe, -fy * ty / z_safe], dim=-1
    ).reshape(*z.shape, 2, 3)  # (C, N, 2, 3)
    # Sigma2d = T T^T with T = J R_cw R diag(s) (2 x 3); det(T T^T) from the 2x2 minors of T
    # (Cauchy-Binet) is never negative and avoids the cancellation of a c - b^2 for thin splats.
    t2 = jac @ (r_cw[:, None] @ m[None])  # (C, N, 2, 3)
    cov = t2 @ t2.transpose(-1, -2)  # (C, N, 2, 2)
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    p, q = t2[..., 0, :], t2[..., 1, :]  # (C, N, 3)
    minors = p[..., [0, 0, 1]] * q[..., [1, 2, 2]] - p[..., [1, 2, 2]] * q[..., [0, 0, 1]]
    det = (minors * minors).sum(-1) + EPS_2D * (a + c) + EPS_2D * EPS_2D  # det(Sigma2d + eps I) > 0
    a, c = a + EPS_2D, c + EPS_2D
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)  # (C, N, 3)
    means2d = torch.stack([u, v], dim=-1)  # (C, N, 2)
    with torch.no_grad():
        extend = torch.full((n,), GAUSSIAN_EXTEND, dtype=means.dtype, device=means.device)
        if opacities is not None:
            opac = opacities.detach().to(means.dtype)
            visible = opac >= ALPHA_THRESHOLD
            extend = torch.sqrt(
                2.0 * torch.log(torch.where(visible, opac, torch.ones_like(opac)) / ALPHA_THRESHOLD)
            )
            extend = torch.where(visible, extend.clamp(max=GAUSSIAN_EXTEND), torch.zeros_like(extend))
            valid = valid & visible
        radii = torch.ceil(extend[:, None] * torch.sqrt(torch.stack([a, c], dim=-1)))  # (C, N, 2)
        valid = (
            valid
            & torch.isfinite(means2d).all(-1)
            & torch.isfinite(conics).all(-1)
            & torch.isfinite(radii).all(-1)
            & (radii > 0).all(-1)
        )
        # Off-screen: the box holds no pixel centre.
        rx, ry = radii.unbind(-1)
        valid &= (u + rx >= 0) & (u - rx <= width - 1) & (v + ry >= 0) & (v - ry <= height - 1)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii))
    assert means2d.shape == (world_from_camera.shape[0], n, 2), means2d.shape
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii, valid=valid)


def _check_inputs(means, quats, scales, opacities, features, world_from_camera, intrinsics) -> None:
    n = means.shape[-2]
    c = world_from_camera.shape[0]
    assert means.shape in ((n, 3), (c, n, 3)), means.shape
    assert quats.shape == (n, 4), quats.shape
    assert scales.shape == (n, 3), scales.shape
    assert opacities.shape == (n,), opacities.shape
    assert features.ndim == 2 and features.shape[0] == n, features.shape
    assert world_from_camera.shape == (c, 4, 4), world_from_camera.shape
    assert intrinsics.shape == (c, 3, 3), intrinsics.shape


def _alphas(means2d: Tensor, conics: Tensor, opac: Tensor, radii: Tensor, px: Tensor, py: Tensor) -> Tensor:
    """Alpha of Gaussians at pixels (broadcasting; ``radii`` (..., 2)), 0 outside the box, where sigma
    is negative or alpha is below the threshold."""
    dx = means2d[..., 0] - px
    dy = means2d[..., 1] - py
    sigma = 0.5 * (conics[..., 0] * dx * dx + conics[..., 2] * dy * dy) + conics[..., 1] * dx * dy
    alpha = torch.clamp(opac * torch.exp(-sigma.clamp(min=0.0)), max=MAX_ALPHA)
    keep = (
        (dx.abs() <= radii[..., 0]) & (dy.abs() <= radii[..., 1]) & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    )
    return torch.where(keep, alpha, torch.zeros_like(alpha))


def _composite_tiles(
    means2d: Tensor, conics: Tensor, opac: Tensor, radii: Tensor, feats: Tensor, px: Tensor, py: Tensor
) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of B tiles of P pixels over K depth-sorted (padded) Gaussians.

    ``means2d`` (B, K, 2), ``conics`` (B, K, 3), ``opac`` (B, K) (padding has opacity 0), ``radii`` (B, K, 2),
    ``feats`` (B, K, F+1) with depth as the last channel, ``px``/``py`` (B, P). Returns (B, P, F+1)
    accumulated features and (B, P) alpha.
    """
    alpha = _alphas(
        means2d[:, None], conics[:, None], opac[:, None], radii[:, None], px[..., None], py[..., None]
    )  # (B, P, K)
    one_minus = 1.0 - alpha
    with torch.no_grad():
        t_incl = torch.cumprod(one_minus, dim=-1)  # transmittance after each Gaussian
        keep = t_incl > TRANSMITTANCE_THRESHOLD  # monotone: once false, false for the rest
    one_minus = torch.where(keep, one_minus, torch.ones_like(one_minus))
    t_after = torch.cumprod(one_minus, dim=-1)  # (B, P, K)
    t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], dim=-1)
    weights = (1.0 - one_minus) * t_before  # (B, P, K)
    acc = weights @ feats  # (B, P, F+1)
    return acc, 1.0 - t_after[..., -1]


def _used_per_tile(
    means2d: Tensor, conics: Tensor, opac: Tensor, radii: Tensor, feats: Tensor, px: Tensor, py: Tensor
) -> Tensor:
    """(B,) how many of each tile's sorted Gaussians come before the last one any pixel adds."""
    alpha = _alphas(
        means2d[:, None], conics[:, None], opac[:, None], radii[:, None], px[..., None], py[..., None]
    )  # (B, P, K)
    t_incl = torch.cumprod(1.0 - alpha, dim=-1)
    added = (alpha > 0) & (t_incl > TRANSMITTANCE_THRESHOLD)  # (B, P, K)
    slot = torch.arange(1, alpha.shape[-1] + 1, device=alpha.device)
    return torch.where(added, slot, 0).amax(dim=(1, 2))


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    world_from_camera: Tensor,
    intrinsics: Tensor,
    width: int,
    height: int,
    *,
    near: float = 0.01,
    tile: int = 16,
    max_batch_elements: int = 1 << 22,
    backend: Backend = "auto",
) -> RenderOutput:
    """Renders N 3D Gaussians into C pinhole cameras, differentiably (tile-based).

    Args:
        means: (N, 3) centres in the world frame, metres; or (C, N, 3), each camera's own (the
            centres at each camera's capture time, for a moving scene and a rolling rig).
        quats: (N, 4) rotations, ``w, x, y, z``, world from Gaussian; need not be normalised, zero = identity.
        scales: (N, 3) standard deviations along the Gaussian's axes, metres (post-activation; clamped to
            ``MAX_SCALE``).
        opacities: (N,) opacities in [0, 1] (post-activation).
        features: (N, F) any per-Gaussian features (RGB colours, embeddings), composited linearly.
        world_from_camera: (C, 4, 4) rigid camera poses, OpenCV camera axes.
        intrinsics: (C, 3, 3) pinhole matrices ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, integer pixel
            coordinates at pixel centres.
        width, height: image size in pixels.
        near: Gaussians with camera z at or below this (metres) are culled.
        tile: tile side in pixels (``"cpu"`` and ``"torch"``; gsplat uses 16).
        max_batch_elements: the ``"torch"`` backend composites tiles in batches of at most about this
            many (pixel, Gaussian) pairs; bounds its peak memory.
        backend: ``"auto"``, ``"cpu"`` (native kernel), ``"torch"`` (tiled PyTorch) or ``"gsplat"``
            (CUDA tensors, gsplat installed); see the module docstring. All follow the same conventions.

    Returns:
        :class:`RenderOutput` with ``features`` (C, H, W, F), ``depth`` (C, H, W), ``alpha`` (C, H, W)
        and ``radii`` (C, N).

    Example::

        >>> import torch
        >>> out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...     torch.full((1, 3), 0.1), torch.tensor([0.9]), torch.ones(1, 3), torch.eye(4)[None],
        ...     torch.tensor([[[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]]]), 32, 24)
        >>> out.features.shape, round(out.depth[0, 12, 16].item(), 3)
        (torch.Size([1, 24, 32, 3]), 2.0)
    """
    _check_inputs(means, quats, scales, opacities, features, world_from_camera, intrinsics)
    chosen = resolve_backend(backend, means.device, means.dtype)
    if chosen == "gsplat":
        return _rasterize_gsplat(
            means, quats, scales, opacities, features, world_from_camera, intrinsics, width, height, near
        )
    proj = project_gaussians(
        means, quats, scales, world_from_camera, intrinsics, width, height, near, opacities
    )
    if chosen == "cpu":
        return _rasterize_native(proj, opacities, features, width, height, tile)
    return _rasterize_torch(proj, opacities, features, width, height, tile, max_batch_elements)


def _rasterize_torch(
    proj: Projection,
    opacities: Tensor,
    features: Tensor,
    width: int,
    height: int,
    tile: int,
    max_batch_elements: int,
) -> RenderOutput:
    """The tiled pure-PyTorch backend."""
    device, dtype = proj.means2d.device, proj.means2d.dtype
    n, f = features.shape
    num_cams = proj.means2d.shape[0]
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    num_tiles = tiles_x * tiles_y

    # Bin: every (camera, Gaussian) goes to all tiles its box touches (one pixel of slack, harmless
    # because the per-pixel box test decides), sorted by (camera, tile) then depth.
    with torch.no_grad():
        rx, ry = proj.radii.unbind(-1)
        u, v = proj.means2d[..., 0], proj.means2d[..., 1]
        big = float(max(width, height) + 2)
        j0 = torch.floor((u - rx - 1).clamp(-big, 2 * big)).long().clamp(min=0)
        j1 = torch.ceil((u + rx + 1).clamp(-big, 2 * big)).long().clamp(max=width - 1)
        i0 = torch.floor((v - ry - 1).clamp(-big, 2 * big)).long().clamp(min=0)
        i1 = torch.ceil((v + ry + 1).clamp(-big, 2 * big)).long().clamp(max=height - 1)
        on_screen = proj.valid & (j0 <= j1) & (i0 <= i1)
        radii_out = proj.radii.amax(-1).long()
        cam_idx, g_idx = torch.nonzero(on_screen, as_tuple=True)  # (M,)
        order = torch.argsort(proj.depths[cam_idx, g_idx], stable=True)
        cam_idx, g_idx = cam_idx[order], g_idx[order]
        tx0, tx1 = j0[cam_idx, g_idx] // tile, j1[cam_idx, g_idx] // tile
        ty0, ty1 = i0[cam_idx, g_idx] // tile, i1[cam_idx, g_idx] // tile
        nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
        counts = nx * ny  # (M,)
        src = torch.repeat_interleave(torch.arange(cam_idx.numel(), device=device), counts)  # (I,)
        first = torch.cumsum(counts, 0) - counts
        k = torch.arange(src.numel(), device=device) - first[src]
        tile_id = (ty0[src] + k // nx[src]) * tiles_x + tx0[src] + k % nx[src]
        key = cam_idx[src] * num_tiles + tile_id  # (I,) global tile key
        order = torch.argsort(key, stable=True)  # stable: depth order kept inside a tile
        key, src = key[order], src[order]
        isect_cam, isect_g = cam_idx[src], g_idx[src]
        tile_keys, tile_counts = torch.unique_consecutive(key, return_counts=True)
        tile_start = torch.cumsum(tile_counts, 0) - tile_counts

    feats_d = torch.cat([features.to(dtype)[None].expand(num_cams, n, f), proj.depths[..., None]], -1)
    out = torch.zeros(num_cams * num_tiles, tile * tile, f + 1, dtype=dtype, device=device)
    alpha_out = torch.zeros(num_cams * num_tiles, tile * tile, dtype=dtype, device=device)
    local = torch.arange(tile * tile, device=device)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (proj.means2d, proj.conics, proj.depths, opacities, features)
    )

    def batches(counts: Tensor):  # tiles in batches of similar Gaussian counts, the largest first
        by_count = torch.argsort(counts, descending=True)
        counts_list = counts[by_count].tolist()
        pos = 0
        while pos < len(counts_list) and counts_list[pos] > 0:
            kmax = counts_list[pos]
            size = max(1, max_batch_elements // (kmax * tile * tile))
            yield by_count[pos : pos + size], kmax
            pos += size

    def gather(batch: Tensor, kmax: int, counts: Tensor) -> tuple[Tensor, ...]:
        with torch.no_grad():
            slot = torch.arange(kmax, device=device)
            pad = slot[None] >= counts[batch, None]  # (B, K)
            index = torch.where(pad, torch.zeros((), dtype=torch.long), tile_start[batch, None] + slot)
            cams, gids = isect_cam[index], isect_g[index]  # (B, K)
            tid = tile_keys[batch] % num_tiles
            px = ((tid % tiles_x) * tile)[:, None] + local % tile  # (B, P)
            py = ((tid // tiles_x) * tile)[:, None] + local // tile
        opac = torch.where(pad, torch.zeros((), dtype=dtype), opacities.to(dtype)[gids])
        return (
            proj.means2d[cams, gids],
            proj.conics[cams, gids],
            opac,
            proj.radii[cams, gids],
            feats_d[cams, gids],
            px.to(dtype),
            py.to(dtype),
        )

    counts = tile_counts
    if need_grad:
        # Gradient pass only over each tile's Gaussians up to the last one any of its pixels adds
        # (the rest get exactly zero weight): a cheap no-grad pass finds where every pixel stopped.
        counts = tile_counts.clone()
        with torch.no_grad():
            for batch, kmax in batches(tile_counts):
                counts[batch] = _used_per_tile(*gather(batch, kmax, tile_counts))
    keys, accs, alphas = [], [], []
    for batch, kmax in batches(counts):
        args = gather(batch, kmax, counts)
        acc, alpha = (
            checkpoint(_composite_tiles, *args, use_reentrant=False) if need_grad else _composite_tiles(*args)
        )
        keys.append(tile_keys[batch])
        accs.append(acc)
        alphas.append(alpha)
    if keys:
        index = torch.cat(keys)
        out = out.index_copy(0, index, torch.cat(accs))
        alpha_out = alpha_out.index_copy(0, index, torch.cat(alphas))

    def untile(x: Tensor) -> Tensor:  # (C*T, P, ...) -> (C, H, W, ...)
        x = x.reshape(num_cams, tiles_y, tiles_x, tile, tile, *x.shape[2:])
        x = x.transpose(2, 3).reshape(num_cams, tiles_y * tile, tiles_x * tile, *x.shape[5:])
        return x[:, :height, :width]

    acc_img, alpha_img = untile(out), untile(alpha_out)
    depth = acc_img[..., f] / alpha_img.clamp(min=1e-10)
    return RenderOutput(features=acc_img[..., :f], depth=depth, alpha=alpha_img, radii=radii_out)


def rasterize_reference(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    world_from_camera: Tensor,
    intrinsics: Tensor,
    width: int,
    height: int,
    *,
    near: float = 0.01,
) -> RenderOutput:
    """Same image as :func:`rasterize`, the slow obvious way: for every camera, the Gaussians one by one
    in depth order, each tested at every pixel; a per-pixel transmittance and stop flag. For tests.

    It always projects with the PyTorch code (:func:`_project_gaussians_torch`), never the native twin,
    so that a test holding a native backend to it compares against code the native extension did not
    compute."""
    _check_inputs(means, quats, scales, opacities, features, world_from_camera, intrinsics)
    f = features.shape[1]
    proj = _project_gaussians_torch(
        means, quats, scales, world_from_camera, intrinsics, width, height, near, opacities
    )
    py, px = torch.meshgrid(
        torch.arange(height, dtype=means.dtype, device=means.device),
        torch.arange(width, dtype=means.dtype, device=means.device),
        indexing="ij",
    )
    images, depths, alphas = [], [], []
    for cam in range(world_from_camera.shape[0]):
        trans = torch.ones(height, width, dtype=means.dtype, device=means.device)
        done = torch.zeros(height, width, dtype=torch.bool, device=means.device)
        color = torch.zeros(height, width, f, dtype=means.dtype, device=means.device)
        depth = torch.zeros(height, width, dtype=means.dtype, device=means.device)
        for g in torch.argsort(proj.depths[cam], stable=True).tolist():
            if not proj.valid[cam, g]:
                continue
            alpha = _alphas(
                proj.means2d[cam, g], proj.conics[cam, g], opacities[g], proj.radii[cam, g], px, py
            )  # (H, W)
            next_trans = trans * (1.0 - alpha)
            stop = (alpha > 0) & (next_trans <= TRANSMITTANCE_THRESHOLD)
            done = done | stop
            add = (alpha > 0) & ~done
            weight = torch.where(add, alpha * trans, torch.zeros_like(alpha))
            color = color + weight[..., None] * features[g]
            depth = depth + weight * proj.depths[cam, g]
            trans = torch.where(add, next_trans, trans)
        alpha_img = 1.0 - trans
        images.append(color)
        depths.append(depth / alpha_img.clamp(min=1e-10))
        alphas.append(alpha_img)
    radii = proj.radii.amax(-1).long()  # 0 where culled
    return RenderOutput(
        features=torch.stack(images), depth=torch.stack(depths), alpha=torch.stack(alphas), radii=radii
    )


class _NativeComposite(torch.autograd.Function):
    """The native kernel's binning and compositing as one autograd step over the projection's outputs."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, depths, radii, width, height, tile):
        ext = native.load_rasterizer()
        assert ext is not None
        feat, depth_sum, alpha, final_t, used, offsets, entries, slots = ext.forward(
            means2d, conics, opacities, features, depths, radii, width, height, tile
        )
        ctx.save_for_backward(
            means2d, conics, opacities, features, depths, radii, final_t, used, offsets, entries, slots
        )
        ctx.size = (width, height, tile)
        return feat, depth_sum, alpha

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_feat, grad_depth_sum, grad_alpha):
        ext = native.load_rasterizer()
        assert ext is not None
        saved = ctx.saved_tensors
        width, height, tile = ctx.size
        g_m2d, g_conics, g_opac, g_feat, g_depths = ext.backward(
            *saved,
            grad_feat.contiguous(),
            grad_depth_sum.contiguous(),
            grad_alpha.contiguous(),
            width,
            height,
            tile,
        )
        return g_m2d, g_conics, g_opac, g_feat, g_depths, None, None, None, None


def _rasterize_native(
    proj: Projection, opacities: Tensor, features: Tensor, width: int, height: int, tile: int
) -> RenderOutput:
    """The native C++ backend (CPU tensors, float32 or float64)."""
    dtype = proj.means2d.dtype
    radii = proj.radii.to(torch.int32)  # 0 where culled
    feat, depth_sum, alpha = _NativeComposite.apply(
        proj.means2d.contiguous(),
        proj.conics.contiguous(),
        opacities.to(dtype).contiguous(),
        features.to(dtype).contiguous(),
        proj.depths.contiguous(),
        radii.contiguous(),
        width,
        height,
        tile,
    )
    depth = depth_sum / alpha.clamp(min=1e-10)
    return RenderOutput(features=feat, depth=depth, alpha=alpha, radii=radii.amax(-1).long())


def native_available() -> bool:
    """Whether the native CPU kernel is built (building it on first call)."""
    return native.load_rasterizer() is not None


def gsplat_available() -> bool:
    """Whether the optional gsplat backend can run (gsplat importable and CUDA present)."""
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return torch.cuda.is_available()


_announced: set[tuple[str, str]] = set()


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype | None = None) -> str:
    """The backend that renders tensors on ``device`` (of ``dtype``, where given) when ``backend`` is asked
    for; ``"auto"`` logs its choice and why, once per process and choice. gsplat renders float32 only, so
    ``"auto"`` gives CUDA tensors of another dtype to the PyTorch path, and ``"gsplat"`` refuses them."""
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        override = os.environ.get("PHIGENESIS_RASTERIZER", "auto").strip().lower() or "auto"
        if override not in BACKENDS:
            raise ValueError(f"PHIGENESIS_RASTERIZER must be one of {BACKENDS}, got {override!r}")
        if override != "auto":
            chosen, why = override, "set by PHIGENESIS_RASTERIZER"
        elif device.type == "cuda" and gsplat_available() and dtype not in (None, torch.float32):
            chosen, why = "torch", f"{dtype} CUDA tensors (gsplat renders float32 only)"
        elif device.type == "cuda" and gsplat_available():
            chosen, why = "gsplat", "CUDA tensors and gsplat installed"
        elif device.type == "cpu" and native_available():
            chosen, why = "cpu", "the native CPU kernel is built"
        elif device.type == "cpu":
            chosen, why = "torch", f"the native CPU kernel is not available ({native.failure_reason()})"
        else:
            chosen, why = "torch", f"{device.type} tensors without gsplat"
        if (chosen, why) not in _announced:
            _announced.add((chosen, why))
            logger.info("rasterize: backend %r (%s)", chosen, why)
        backend = chosen
    if backend == "gsplat" and dtype not in (None, torch.float32):
        raise ValueError(f"rasterize: backend 'gsplat' renders float32 only, got {dtype}")
    if backend == "cpu":
        if device.type != "cpu":
            raise ValueError(f"rasterize: backend 'cpu' needs CPU tensors, got {device.type}")
        if not native_available():
            raise RuntimeError(
                f"rasterize: the native CPU kernel is not available: {native.failure_reason()}"
            )
    return backend


def _rasterize_gsplat(
    means, quats, scales, opacities, features, world_from_camera, intrinsics, width, height, near
) -> RenderOutput:
    """gsplat 1.5.3's CUDA kernels with this module's conventions (float32 CUDA tensors).

    Where gsplat's own inputs mean something else, they are mapped first: pixel centres at ``j + 0.5``
    (``cx, cy`` shifted), ``camera_from_world`` view matrices, a zero quaternion as the identity (gsplat
    would normalise it to NaN) and scales clamped to :data:`MAX_SCALE`. Centres per camera (C, N, 3) go
    in as gsplat's batch dimension: one call, camera c of batch c."""
    if not gsplat_available() or not means.is_cuda:
        raise RuntimeError("backend='gsplat' needs gsplat installed, CUDA and CUDA tensors")
    # optional CUDA backend
    import gsplat

    num_cams = world_from_camera.shape[0]
    quats = zero_quaternions_to_identity(quats)
    scales = scales.clamp(min=-MAX_SCALE, max=MAX_SCALE)
    shift = torch.zeros_like(intrinsics)
    shift[:, 0, 2] = shift[:, 1, 2] = 0.5  # gsplat puts pixel centres at j + 0.5
    viewmats, ks = torch.linalg.inv(world_from_camera), intrinsics + shift
    per_camera = means.ndim == 3
    if per_camera:  # batch c: camera c alone, with its own centres
        n = means.shape[1]
        quats, scales = (t[None].expand(num_cams, n, t.shape[-1]) for t in (quats, scales))
        opacities = opacities[None].expand(num_cams, n)
        features = features[None].expand(num_cams, *features.shape)
        viewmats, ks = viewmats[:, None], ks[:, None]
    colors, alphas, meta = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        features,
        viewmats,
        ks,
        width,
        height,
        near_plane=near,
        eps2d=EPS_2D,
        packed=False,
        tile_size=16,
        render_mode="RGB+ED",
    )
    radii = meta["radii"]  # (..., C, N, 2) per axis (gsplat 1.5); (..., C, N) in older releases
    if radii.ndim == means.ndim + 1:
        radii = radii.amax(-1)
    if per_camera:  # (C, 1, ...) -> (C, ...)
        colors, alphas, radii = colors[:, 0], alphas[:, 0], radii[:, 0]
    return RenderOutput(
        features=colors[..., :-1], depth=colors[..., -1], alpha=alphas[..., 0], radii=radii.long()
    )


__all__ = [
    "BACKENDS",
    "RenderOutput",
    "gsplat_available",
    "native_available",
    "project_gaussians",
    "quaternion_to_rotation",
    "rasterize",
    "rasterize_reference",
    "resolve_backend",
]
