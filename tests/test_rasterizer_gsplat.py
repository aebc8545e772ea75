"""Our EWA projection (``project_gaussians``) against gsplat 1.5.3's pure-PyTorch oracle, in float64.

The oracle is ``gsplat.cuda._torch_impl._fully_fused_projection`` (plain PyTorch, runs on the CPU and
compiles nothing; ``pip install gsplat==1.5.3``). Conventions mapped between the two: gsplat takes
``camera_from_world`` matrices and puts pixel centres at ``j + 0.5``, so it gets the inverse poses and
``cx + 0.5, cy + 0.5``, and its ``means2d`` are shifted back by 0.5.

Radii differ by design: gsplat's PyTorch twin uses a fixed 3.33-sigma box per axis, ours (like gsplat's
CUDA kernels) the opacity-aware extent ``min(3.33, sqrt(2 ln(255 opacity)))``, which is exactly where
``opacity exp(-sigma)`` falls to 1/255. The radii are checked against that formula evaluated on the
oracle's 2D covariances, and between the exact alpha = 1/255 footprint and gsplat's box.
"""

from __future__ import annotations

import math

import pytest
import torch

from phigenesis.models.rasterizer import project_gaussians

gsplat_torch = pytest.importorskip(
    "gsplat.cuda._torch_impl", reason="gsplat is not installed (pip install gsplat==1.5.3)"
)

F64 = torch.float64
EPS_2D = 0.3
NEAR = 0.01
#: Relative agreement asked of means2d, conics and depths (both sides are float64).
RTOL = 1e-9
#: Float64 unit roundoff; the oracle's det = a c - b^2 loses about ulp * (a c + b^2) / det.
ULP = torch.finfo(F64).eps


def _rotation(yaw: float, pitch: float, roll: float) -> torch.Tensor:
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (math.cos, math.sin))
    rz = torch.tensor([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]], dtype=F64)
    ry = torch.tensor([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]], dtype=F64)
    return ry @ rx @ rz


def _cameras() -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """(world_from_camera (3, 4, 4), intrinsics (3, 3, 3), width, height): one identity camera, two
    rotated and shifted ones; fx != fy and principal points off the image centre."""
    width, height = 48, 30
    poses = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    poses[1, :3, :3] = _rotation(0.2, -0.1, 0.05)
    poses[1, :3, 3] = torch.tensor([0.3, -0.2, 0.1], dtype=F64)
    poses[2, :3, :3] = _rotation(-0.35, 0.15, -0.2)
    poses[2, :3, 3] = torch.tensor([-0.5, 0.1, -0.3], dtype=F64)
    k = torch.tensor(
        [
            [[40.0, 0.0, 23.5], [0.0, 40.0, 14.5], [0.0, 0.0, 1.0]],
            [[35.0, 0.0, 20.0], [0.0, 38.0, 17.25], [0.0, 0.0, 1.0]],
            [[60.0, 0.0, 30.7], [0.0, 55.0, 9.2], [0.0, 0.0, 1.0]],
        ],
        dtype=F64,
    )
    return poses, k, width, height


def _random_scene(n: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([1.5, 1.0, 1.5], dtype=F64)
    means[:, 2] += 2.5  # most in front of the cameras, some behind and some off-screen
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=F64) * 3.0,  # not normalised
        "scales": torch.exp(
            torch.empty(n, 3, dtype=F64).uniform_(math.log(1e-3), math.log(1.0), generator=g)
        ),
        "opacities": torch.rand(n, generator=g, dtype=F64) ** 2,  # some below 1/255
    }


def _hard_scene() -> dict[str, torch.Tensor]:
    """Gaussians at the near plane, far outside the field of view (the Jacobian clamp), needles,
    zero and unnormalised quaternions, tiny and large scales, opacities at the 1/255 threshold."""
    rows = [
        # (mean, quat, scales, opacity)
        ((0.0, 0.0, NEAR + 1e-6), (1, 0, 0, 0), (0.01, 0.01, 0.01), 0.9),  # just past the near plane
        ((0.001, -0.001, NEAR + 1e-3), (0.9, 0.1, 0.2, 0.3), (0.05, 0.02, 0.01), 0.9),
        ((0.0, 0.0, NEAR), (1, 0, 0, 0), (0.01, 0.01, 0.01), 0.9),  # at the near plane: culled
        ((0.0, 0.0, NEAR - 1e-6), (1, 0, 0, 0), (0.01, 0.01, 0.01), 0.9),  # just before it: culled
        ((0.0, 0.0, -1.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # behind
        ((6.0, 0.0, 2.0), (1, 0, 0, 0), (1.5, 1.5, 1.5), 0.9),  # x/z = 3: clamped, still on screen
        ((-6.0, 0.5, 2.0), (0.7, 0.0, 0.7, 0.0), (2.0, 1.0, 0.5), 0.9),  # clamped on the other side
        ((0.2, 4.0, 1.5), (0.5, 0.5, 0.5, 0.5), (0.8, 1.2, 0.3), 0.9),  # y/z clamped
        ((0.1, -5.0, 1.2), (1, 0, 0, 0), (1.0, 2.0, 1.0), 0.9),
        ((50.0, 30.0, 2.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 0.9),  # far off-screen: culled
        ((-0.1, 0.0, 2.5), (0.9, 0.3, 0.2, 0.1), (3.0, 1e-8, 1e-8), 0.9),  # needle
        ((0.3, 0.1, 0.5), (0.2, 0.9, -0.3, 0.1), (2.0, 1e-6, 1e-7), 0.7),  # needle close to the camera
        ((0.0, 0.2, 3.0), (0.0, 0.0, 0.0, 0.0), (0.2, 0.1, 0.05), 0.5),  # zero quaternion
        ((0.1, 0.1, 2.0), (30.0, -10.0, 5.0, 2.0), (0.1, 0.3, 0.02), 0.5),  # unnormalised quaternion
        ((0.0, 0.0, 4.0), (1, 0, 0, 0), (1e-9, 1e-9, 1e-9), 0.5),  # tiny: only the 0.3 px dilation
        ((0.2, -0.1, 3.0), (0.6, 0.2, 0.7, 0.1), (200.0, 50.0, 0.01), 0.5),  # huge disc
        ((0.1, 0.0, 2.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 1.0 / 255.0 + 1e-9),  # barely visible
        ((-0.1, 0.0, 2.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 1.0 / 255.0 - 1e-9),  # never reaches 1/255
        ((0.0, 0.1, 2.0), (1, 0, 0, 0), (0.1, 0.1, 0.1), 1.0),
    ]
    cols = list(zip(*rows, strict=True))
    return {
        "means": torch.tensor(cols[0], dtype=F64),
        "quats": torch.tensor(cols[1], dtype=F64),
        "scales": torch.tensor(cols[2], dtype=F64),
        "opacities": torch.tensor(cols[3], dtype=F64),
    }


def _oracle(scene: dict[str, torch.Tensor], poses: torch.Tensor, k: torch.Tensor, width: int, height: int):
    """gsplat's projection in our conventions: (means2d, conics, depths, radii_3.33, cov2d with eps)."""
    covars, _ = gsplat_torch._quat_scale_to_covar_preci(
        scene["quats"], scene["scales"], compute_covar=True, compute_preci=False
    )  # (N, 3, 3)
    shift = torch.zeros_like(k)
    shift[:, 0, 2] = shift[:, 1, 2] = 0.5  # gsplat's pixel centres are at j + 0.5
    viewmats = torch.linalg.inv(poses)  # camera_from_world
    radii, means2d, depths, conics, _ = gsplat_torch._fully_fused_projection(
        scene["means"], covars, viewmats, k + shift, width, height, eps2d=EPS_2D, near_plane=NEAR
    )
    means_c, covars_c = gsplat_torch._world_to_cam(scene["means"], covars, viewmats)
    _, cov2d = gsplat_torch._persp_proj(means_c, covars_c, k + shift, width, height)  # (C, N, 2, 2)
    cov2d = cov2d + EPS_2D * torch.eye(2, dtype=F64)
    return means2d - 0.5, conics, depths, radii.to(F64), cov2d


def _ours(scene: dict[str, torch.Tensor], poses: torch.Tensor, k: torch.Tensor, width: int, height: int):
    return project_gaussians(
        scene["means"], scene["quats"], scene["scales"], poses, k, width, height, NEAR, scene["opacities"]
    )


def _max_rel_error(ours: torch.Tensor, theirs: torch.Tensor, mask: torch.Tensor, scale: torch.Tensor):
    """Largest |ours - theirs| / scale over the masked (C, N) entries, and where it is."""
    err = ((ours - theirs).abs() / scale).amax(-1) if ours.ndim == 3 else (ours - theirs).abs() / scale
    err = torch.where(mask, err, torch.zeros_like(err))
    worst = divmod(int(err.argmax()), err.shape[1])
    return float(err.max()), worst


SCENES = {
    "random_seed0": lambda: _random_scene(400, 0),
    "random_seed1": lambda: _random_scene(400, 1),
    "hard_cases": _hard_scene,
}


@pytest.mark.parametrize("name", list(SCENES))
def test_means_conics_and_depths_match_gsplat_torch_projection(name):
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    ours = _ours(scene, poses, k, width, height)
    means2d, conics, depths, _, cov2d = _oracle(scene, poses, k, width, height)
    c, n = depths.shape
    assert ours.means2d.shape == (c, n, 2) and ours.conics.shape == (c, n, 3), ours.means2d.shape
    assert ours.depths.shape == ours.valid.shape == (c, n), ours.depths.shape

    torch.testing.assert_close(ours.depths, depths, rtol=RTOL, atol=1e-12)
    front = depths > NEAR  # gsplat projects everything; ours only what lies past the near plane
    assert front.any()
    assert not (ours.valid & ~front).any(), "a Gaussian at or before the near plane is kept"
    err, at = _max_rel_error(ours.means2d, means2d, front, means2d.abs().amax(-1, keepdim=True) + 1.0)
    assert err < RTOL, f"means2d: relative error {err:.3g} at (camera, Gaussian) {at}"
    # Conics relative to their largest entry, plus the oracle's own cancellation in det = a c - b^2.
    a, b, cc = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det = a * cc - b * b
    oracle_rtol = RTOL + 8 * ULP * (a * cc + b * b) / det  # (C, N)
    err = ((ours.conics - conics).abs().amax(-1) / conics.abs().amax(-1)) / oracle_rtol
    err = torch.where(front, err, torch.zeros_like(err))
    worst = divmod(int(err.argmax()), n)
    assert err.max() < 1, f"conics: {float(err.max()):.3g} x the tolerance at (camera, Gaussian) {worst}"


@pytest.mark.parametrize("name", list(SCENES))
def test_radii_are_the_opacity_aware_extent_of_gsplat_covariances(name):
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    ours = _ours(scene, poses, k, width, height)
    _, _, depths, _, cov2d = _oracle(scene, poses, k, width, height)
    c, n = depths.shape
    assert ours.radii.shape == (c, n, 2), ours.radii.shape
    opac = scene["opacities"].expand(c, n)
    extend = torch.sqrt(2.0 * torch.log((255.0 * opac).clamp(min=1.0))).clamp(max=3.33)  # (C, N)
    exact = extend[..., None] * torch.sqrt(torch.stack([cov2d[..., 0, 0], cov2d[..., 1, 1]], -1))
    expected = torch.ceil(exact)  # (C, N, 2)
    on_boundary = ((exact - exact.round()).abs() < 1e-6).any(-1)  # ceil may go either way there
    check = ours.valid & ~on_boundary
    assert check.any()
    bad = check[..., None] & (ours.radii != expected)
    assert not bad.any(), (
        f"radii {ours.radii[bad][:5].tolist()} where the formula gives {expected[bad][:5].tolist()}"
    )
    assert ours.radii[~ours.valid].eq(0).all(), "culled Gaussians must have radius 0"


@pytest.mark.parametrize("name", list(SCENES))
def test_radii_without_opacities_are_gsplat_torch_radii(name):
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    ours = project_gaussians(scene["means"], scene["quats"], scene["scales"], poses, k, width, height, NEAR)
    _, _, _, gsplat_radii, cov2d = _oracle(scene, poses, k, width, height)
    exact = 3.33 * torch.sqrt(torch.stack([cov2d[..., 0, 0], cov2d[..., 1, 1]], -1))
    on_boundary = ((exact - exact.round()).abs() < 1e-6).any(-1)
    check = ours.valid & ~on_boundary
    assert check.any()
    bad = check[..., None] & (ours.radii != gsplat_radii)
    assert not bad.any(), f"radii {ours.radii[bad][:5].tolist()}, gsplat {gsplat_radii[bad][:5].tolist()}"


@pytest.mark.parametrize("name", list(SCENES))
def test_radii_lie_between_the_alpha_footprint_and_gsplat_torch_box(name):
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    ours = _ours(scene, poses, k, width, height)
    _, _, _, gsplat_radii, cov2d = _oracle(scene, poses, k, width, height)
    v = ours.valid
    # Where opacity * exp(-sigma) >= 1/255: the ellipse d^T Sigma2d^-1 d <= 2 ln(255 opacity).
    opac = scene["opacities"].expand(v.shape)
    reach = 2.0 * torch.log((255.0 * opac).clamp(min=1.0))  # (C, N)
    footprint = torch.sqrt(reach[..., None] * torch.stack([cov2d[..., 0, 0], cov2d[..., 1, 1]], -1))
    assert (ours.radii[v] >= footprint[v] * (1 - 1e-12)).all(), "the support cuts visible alpha off"
    assert (ours.radii[v] <= gsplat_radii[v]).all(), "larger than gsplat's 3.33-sigma box"
    assert (gsplat_radii[v] > 0).all(), "kept by us, culled by gsplat"


@pytest.mark.parametrize("name", list(SCENES))
def test_culling_agrees_with_gsplat_up_to_the_half_pixel_convention(name):
    """Ours keeps a Gaussian iff it is past the near plane, can reach alpha 1/255 and its box meets
    the image; the on-screen test is checked only away from the half-pixel band where our
    (pixel centres) and gsplat's (image edges at -0.5 and W - 0.5) conventions could differ."""
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    ours = _ours(scene, poses, k, width, height)
    means2d, _, depths, _, cov2d = _oracle(scene, poses, k, width, height)
    c, n = depths.shape
    opac = scene["opacities"].expand(c, n)
    extend = torch.sqrt(2.0 * torch.log((255.0 * opac).clamp(min=1.0))).clamp(max=3.33)
    r = torch.ceil(extend[..., None] * torch.sqrt(torch.stack([cov2d[..., 0, 0], cov2d[..., 1, 1]], -1)))
    lo, hi = means2d - r, means2d + r  # (C, N, 2) box in our pixel coordinates
    size = torch.tensor([width, height], dtype=F64)
    alive = (depths > NEAR) & (opac >= 1.0 / 255.0 + 1e-12)
    surely_in = alive & ((hi >= 0.0) & (lo <= size - 1)).all(-1)  # holds a pixel centre
    maybe_in = alive & ((hi > -0.5) & (lo < size - 0.5)).all(-1)  # meets the image rectangle
    assert surely_in.any() and (~maybe_in).any()
    assert not (surely_in & ~ours.valid).any(), (
        f"culled though on screen: {torch.nonzero(surely_in & ~ours.valid)}"
    )
    assert not (ours.valid & ~maybe_in).any(), (
        f"kept though off screen: {torch.nonzero(ours.valid & ~maybe_in)}"
    )


@pytest.mark.parametrize("name", ["random_seed0", "hard_cases"])
def test_projection_gradients_match_gsplat_torch_projection(name):
    scene = SCENES[name]()
    poses, k, width, height = _cameras()
    front = _oracle(scene, poses, k, width, height)[2] > NEAR + 1e-4  # no gradients at the near plane
    g = torch.Generator().manual_seed(1)
    w_means = torch.randn(*front.shape, 2, generator=g, dtype=F64) * front[..., None]
    w_conics = torch.randn(*front.shape, 3, generator=g, dtype=F64) * front[..., None]
    w_depths = torch.randn(*front.shape, generator=g, dtype=F64) * front

    def grads(project) -> list[torch.Tensor]:
        leaves = {key: scene[key].clone().requires_grad_() for key in ("means", "quats", "scales")}
        means2d, conics, depths = project({**scene, **leaves})
        # Conics weighted by their size so that tiny and huge Gaussians count alike.
        scale = conics.detach().abs().amax(-1, keepdim=True)
        loss = (means2d * w_means).sum() + (conics / scale * w_conics).sum() + (depths * w_depths).sum()
        return list(torch.autograd.grad(loss, list(leaves.values())))

    def ours(s):
        p = _ours(s, poses, k, width, height)
        return p.means2d, p.conics, p.depths

    def theirs(s):
        return _oracle(s, poses, k, width, height)[:3]

    # A zero quaternion is the identity for us (no gradient) and 0 / max(|q|, 1e-12) for gsplat.
    rotated = scene["quats"].norm(dim=-1) > 0
    for key, a, b in zip(("means", "quats", "scales"), grads(ours), grads(theirs), strict=True):
        if key == "quats":
            a, b = a[rotated], b[rotated]
        scale = b.abs().amax(-1, keepdim=True) + 1e-8 * b.abs().max()  # isotropic: d/dq is roundoff
        err = (a - b).abs() / scale
        assert err.max() < 1e-6, (
            f"d/d{key}: relative error {float(err.max()):.3g} at {divmod(int(err.argmax()), 3)}"
        )
