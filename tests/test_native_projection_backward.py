"""The native projection's backward (``project_backward`` in csrc/project_cpu.cpp, through
``rasterizer._NativeProjection``) against autograd through the PyTorch projection
(``_project_gaussians_torch``, the reference): gradients of means, quats and scales for random upstream
gradients on random and hard scenes, gradcheck, the dispatch of ``project_gaussians`` under grad, and
whole renders' gradients with the native projection and with the PyTorch one."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis.models import native, rasterizer
from phigenesis.models.rasterizer import (
    FOV_CLAMP_MARGIN,
    MAX_SCALE,
    _box_extend,
    _NativeProjection,
    _project_gaussians_torch,
    project_gaussians,
    rasterize,
)
from tests.test_rasterizer import _cameras, _hard_scene, _intrinsics, _scene
from tests.test_rasterizer_native import _stress_scene

pytestmark = pytest.mark.skipif(
    native.load_rasterizer() is None, reason=f"native build unavailable: {native.failure_reason()}"
)

F64 = torch.float64
F32 = torch.float32
NAMES = ("means", "quats", "scales")
#: Agreement asked of the native gradients: relative, and an absolute floor as a fraction of the largest
#: reference gradient of the tensor (terms of opposite signs cancel in a sum, and the two sides add them in
#: other orders).
TOL = {F64: (1e-9, 1e-12), F32: (1e-4, 1e-5)}
#: Absolute agreement below which two gradients are both zero: where a gradient is zero by symmetry
#: (three scales at the MAX_SCALE clamp make the covariance isotropic, so no rotation changes it), both
#: sides return what is left of cancelling terms of size scale^2, about 1e-28 (hypothesis found it).
ZERO_GRADIENT = {F64: 1e-20, F32: 1e-12}


def _upstream(proj: rasterizer.Projection, seed: int) -> tuple[torch.Tensor, ...]:
    """Random gradients of means2d, conics and depths."""
    g = torch.Generator().manual_seed(seed)
    return tuple(
        torch.randn(t.shape, generator=g, dtype=t.dtype) for t in (proj.means2d, proj.conics, proj.depths)
    )


def _gradients(project, scene: dict, cams, k, width: int, height: int, near: float = 0.01, seed: int = 0):
    """(projection, gradients of means, quats, scales) of ``project`` for a random upstream gradient."""
    leaves = [scene[name].detach().clone().requires_grad_() for name in NAMES]
    proj = project(*leaves, cams, k, width, height, near, scene.get("opacities"))
    upstream = _upstream(proj, seed)
    grads = torch.autograd.grad((proj.means2d, proj.conics, proj.depths), leaves, upstream, allow_unused=True)
    return proj, [torch.zeros_like(x) if g is None else g for x, g in zip(leaves, grads, strict=True)]


def _assert_gradients_match(scene: dict, cams, k, width: int, height: int, near: float = 0.01, seed: int = 0):
    proj, ours = _gradients(project_gaussians, scene, cams, k, width, height, near, seed)
    assert type(proj.means2d.grad_fn).__name__ == "_NativeProjectionBackward", proj.means2d.grad_fn
    _, ref = _gradients(_project_gaussians_torch, scene, cams, k, width, height, near, seed)
    rtol, floor = TOL[scene["means"].dtype]
    for name, a, b in zip(NAMES, ours, ref, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert torch.isfinite(a).all() and torch.isfinite(b).all(), name
        atol = max(floor * b.abs().max().item() if b.numel() else 0.0, ZERO_GRADIENT[b.dtype])
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol, msg=name)
    return ours


def _per_camera(scene: dict, cams: int, seed: int) -> dict:
    dtype = scene["means"].dtype
    shift = torch.randn(cams, 1, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 0.3
    return {**scene, "means": scene["means"][None] + shift}


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("per_camera", [False, True])
@pytest.mark.parametrize(("n", "cams", "seed"), [(7, 1, 0), (60, 3, 1), (3000, 15, 2)])
def test_gradients_match_autograd_on_random_scenes(n, cams, seed, per_camera, dtype):
    """Small scenes take PyTorch's unfused loop for the camera-space rotation, large ones BLAS."""
    scene = _scene(n, seed, dtype=dtype)
    if per_camera:
        scene = _per_camera(scene, cams, seed)
    _assert_gradients_match(scene, _cameras(cams, dtype), _intrinsics(cams, 40, 30, 35.0, dtype), 40, 30)


def _hard_cases(dtype) -> dict:
    """tests/test_rasterizer.py's hard scene (centres at, on and behind the camera plane, just past the
    near plane, huge, tiny and needle scales, a zero quaternion, far off-screen) and more: centres exactly
    on the near plane, needles and flat disks of 1e-4 m, scales of 1e-4 m, 1e2 m, exactly MAX_SCALE and
    beyond it either way, a tiny quaternion taken as zero and unnormalised ones, and centres far outside
    the field of view in front of and behind the camera (the Jacobian's FoV clamp active)."""
    hard = _hard_scene(dtype)
    del hard["features"]
    rows = [  # centre, quaternion, scales
        ([0.2, -0.1, 0.01], [0.9, 0.1, 0.2, 0.3], [0.1, 0.2, 0.05]),  # on the near plane (camera 0)
        ([0.1, 0.1, 0.005], [1.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.1]),  # between the camera and near plane
        ([0.05, -0.05, 2.0], [0.7, 0.1, -0.2, 0.3], [1e-4, 1e-4, 1e-4]),
        ([0.1, 0.0, 3.0], [0.3, -0.5, 0.2, 0.6], [1e-4, 1e-4, 0.3]),  # needle: near-singular 2D covariance
        ([0.0, 0.1, 3.0], [0.3, 0.5, -0.2, 0.6], [1e-4, 0.3, 0.2]),  # a flat disk seen from any side
        ([0.0, 0.05, 4.0], [0.0, 0.0, 0.0, 0.0], [1e2, 1e2, 1e2]),
        ([0.0, 0.05, 6.0], [20.0, -3.0, 5.0, 1.0], [MAX_SCALE, 0.1, -MAX_SCALE]),  # unnormalised
        ([0.3, 0.05, 6.0], [0.01, 0.02, -0.03, 0.005], [2e4, -3e4, 0.2]),  # beyond MAX_SCALE
        ([0.1, 0.0, 2.0], [1e-13, 1e-13, 0.0, 0.0], [0.1, 0.2, 0.3]),  # squared norm 2e-26: zero
        ([0.1, 0.0, 2.0], [1e-11, 0.0, 1e-11, 0.0], [0.1, 0.2, 0.3]),  # squared norm 2e-22: normalised
        ([40.0, -3.0, 2.0], [0.8, 0.1, 0.3, -0.2], [0.5, 0.1, 0.2]),  # far right: tx clamped
        ([-50.0, 30.0, 2.0], [0.8, -0.1, 0.3, 0.2], [0.5, 0.1, 0.2]),  # far left and down
        ([3.0, -60.0, 1.5], [0.2, 0.1, 0.9, -0.2], [0.5, 0.3, 0.2]),  # far up
        ([9.0, -7.0, -3.0], [0.2, 0.1, 0.9, -0.2], [0.5, 0.3, 0.2]),  # behind, z_safe = 1: clamped too
    ]
    extra = {
        "means": torch.tensor([r[0] for r in rows], dtype=dtype),
        "quats": torch.tensor([r[1] for r in rows], dtype=dtype),
        "scales": torch.tensor([r[2] for r in rows], dtype=dtype),
        "opacities": torch.full((len(rows),), 0.8, dtype=dtype),
    }
    return {key: torch.cat([hard[key], extra[key]]) for key in extra}


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("per_camera", [False, True])
def test_gradients_match_autograd_on_hard_cases(per_camera, dtype):
    scene = _hard_cases(dtype)
    if per_camera:
        scene = _per_camera(scene, 2, 3)
    cams, k = _cameras(2, dtype), _intrinsics(2, 24, 16, 20.0, dtype)
    _, grad_quats, grad_scales = _assert_gradients_match(scene, cams, k, 24, 16)
    zero_quats = (scene["quats"] * scene["quats"]).sum(-1) <= rasterizer.QUATERNION_ZERO_SQNORM
    assert zero_quats.sum() == 3 and grad_quats[zero_quats].eq(0).all()  # the identity stands in
    beyond = scene["scales"].abs() > MAX_SCALE
    assert beyond.sum() == 5 and grad_scales[beyond].eq(0).all()
    at_limit = scene["scales"].abs() == MAX_SCALE
    assert at_limit.sum() == 2 and grad_scales[at_limit].ne(0).all()  # the clamp passes its bounds' gradient


def _tie_scene(dtype, width: int, height: int, k: torch.Tensor) -> dict:
    """Centres whose x/z or y/z equals a bound of the Jacobian's FoV clamp exactly, for the identity
    camera: z = 1, or z <= near where z_safe = 1, so that x/z_safe = x."""
    fx, fy, cx, cy = k[0, 0, 0], k[0, 1, 1], k[0, 0, 2], k[0, 1, 2]
    # The bounds as _project_gaussians_torch computes them, to the last bit.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - 0.5 - cx) / fx + FOV_CLAMP_MARGIN * tan_x
    lim_x_neg = (cx + 0.5) / fx + FOV_CLAMP_MARGIN * tan_x
    lim_y_pos = (height - 0.5 - cy) / fy + FOV_CLAMP_MARGIN * tan_y
    lim_y_neg = (cy + 0.5) / fy + FOV_CLAMP_MARGIN * tan_y
    zero = torch.zeros_like(fx)
    xs = torch.stack([lim_x_pos, -lim_x_neg, zero, lim_x_pos, -lim_x_neg])
    ys = torch.stack([zero, lim_y_pos, -lim_y_neg, lim_y_pos, -lim_y_neg])
    zs = torch.tensor([1.0, 1.0, 1.0, -2.0, 0.0], dtype=dtype)  # the last two are culled (z_safe = 1)
    g = torch.Generator().manual_seed(3)
    return {
        "means": torch.stack([xs, ys, zs], -1),
        "quats": torch.randn(5, 4, generator=g, dtype=dtype),
        "scales": 0.05 + 0.2 * torch.rand(5, 3, generator=g, dtype=dtype),
    }


@pytest.mark.parametrize("dtype", [F64, F32])
def test_gradients_match_autograd_on_the_projection_stress_scene(dtype):
    """tests/test_rasterizer_native.py's stress scene (scales from 1e-9 m to 1e6 m, needles, zero and tiny
    quaternions, centres on, behind and just past the near plane); with near = 0, centres a hair in front
    of the camera plane project to inf and nan: the gradients are non-finite in the same places and agree
    elsewhere."""
    scene = _stress_scene(3000, dtype)
    cams, k = _cameras(3, dtype), _intrinsics(3, 48, 32, 30.0, dtype)
    _assert_gradients_match(scene, cams, k, 48, 32)
    _, ours = _gradients(project_gaussians, scene, cams, k, 48, 32, near=0.0)
    _, ref = _gradients(_project_gaussians_torch, scene, cams, k, 48, 32, near=0.0)
    rtol, floor = TOL[dtype]
    for name, a, b in zip(NAMES, ours, ref, strict=True):
        finite = torch.isfinite(b)
        assert not finite.all() and torch.equal(torch.isfinite(a), finite), name
        atol = floor * b[finite].abs().max().item()
        torch.testing.assert_close(a[finite], b[finite], rtol=rtol, atol=atol, msg=name)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_fov_clamp_ties_split_the_gradient_as_torch_does(dtype):
    """At a bound, torch.minimum and torch.maximum give each side half the gradient."""
    width, height = 40, 30
    cams, k = _cameras(1, dtype), _intrinsics(1, width, height, 35.0, dtype)
    scene = _tie_scene(dtype, width, height, k)
    _assert_gradients_match(scene, cams, k, width, height, seed=4)


def test_a_tie_gets_the_mean_of_the_gradients_either_side():
    """So the ties above test something: a hair inside the bounds the clamp passes all of x/z's gradient
    through the Jacobian, a hair outside none, and at the bound half (float64)."""
    width, height = 40, 30
    cams, k = _cameras(1), _intrinsics(1, width, height, 35.0)
    scene = _tie_scene(F64, width, height, k)

    def means_grad(factor: float) -> torch.Tensor:  # through the conics alone (where the clamp acts)
        means = (scene["means"] * torch.tensor([factor, factor, 1.0], dtype=F64)).requires_grad_()
        proj = project_gaussians(means, scene["quats"], scene["scales"], cams, k, width, height)
        (grad,) = torch.autograd.grad(proj.conics, means, _upstream(proj, 4)[1])
        return grad

    tie, inside, outside = means_grad(1.0), means_grad(1 - 1e-10), means_grad(1 + 1e-10)
    assert (inside - outside).abs().max() > 1e-2 * inside.abs().max()
    torch.testing.assert_close(tie, (inside + outside) / 2, rtol=1e-6, atol=1e-8 * inside.abs().max().item())


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("per_camera", [False, True])
@pytest.mark.parametrize("cams", [0, 2])
def test_an_empty_scene_or_no_cameras_gives_zero_gradients(cams, per_camera, dtype):
    n = 0 if cams else 5
    scene = {name: value[:n] for name, value in _scene(5, 0, dtype=dtype).items()}
    if per_camera:
        scene["means"] = scene["means"][None].expand(cams, n, 3)
    cameras = _cameras(2, dtype)[:cams]
    grads = _assert_gradients_match(scene, cameras, _intrinsics(cams, 12, 10, 10.0, dtype), 12, 10)
    assert [tuple(g.shape) for g in grads] == [tuple(scene[name].shape) for name in NAMES]
    assert all(g.abs().sum() == 0 for g in grads)


def test_gradcheck_in_float64():
    """Finite differences through the autograd Function itself, shared and per-camera centres (a scene
    clear of the kinks: the near plane, the FoV clamp's bounds)."""
    scene = _scene(6, 7)
    cams, k = _cameras(2), _intrinsics(2, 20, 16, 18.0)
    extend = _box_extend(6, scene["opacities"], F64, torch.device("cpu"))

    def project(means, quats, scales):
        return _NativeProjection.apply(means, quats, scales, cams, k, extend, 20, 16, 0.01)[:3]

    for means in (scene["means"], _per_camera(scene, 2, 1)["means"]):
        inputs = tuple(t.clone().requires_grad_() for t in (means, scene["quats"], scene["scales"]))
        assert torch.autograd.gradcheck(project, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("dtype", [F64, F32])
def test_projection_under_grad_is_bitwise_the_no_grad_forward(dtype):
    scene = _scene(500, 8, dtype=dtype)
    args = (_cameras(3, dtype), _intrinsics(3, 40, 30, 35.0, dtype), 40, 30, 0.01, scene["opacities"])
    leaves = [scene[name].clone().requires_grad_() for name in NAMES]
    with_grad = project_gaussians(*leaves, *args)
    assert type(with_grad.means2d.grad_fn).__name__ == "_NativeProjectionBackward"
    assert not with_grad.radii.requires_grad and not with_grad.valid.requires_grad
    with torch.no_grad():
        without = project_gaussians(*leaves, *args)
    for name in ("means2d", "conics", "depths", "radii", "valid"):
        assert torch.equal(getattr(with_grad, name), getattr(without, name)), name


def _render_gradients(scene: dict, cams, k, width: int, height: int, backend: str) -> list[torch.Tensor]:
    leaves = [value.detach().clone().requires_grad_() for value in scene.values()]
    out = rasterize(*leaves, cams, k, width, height, backend=backend)
    g = torch.Generator().manual_seed(0)
    loss = sum((t * torch.rand(t.shape, generator=g, dtype=t.dtype)).sum() for t in (out.features, out.depth))
    loss = loss + (out.alpha * (torch.rand(out.alpha.shape, generator=g, dtype=out.alpha.dtype) - 0.5)).sum()
    return list(torch.autograd.grad(loss, leaves))


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_render_gradients_are_the_same_with_either_projection(monkeypatch, backend, dtype):
    scene = _scene(150, 9, features=4, dtype=dtype)
    scene["opacities"] = 0.3 + 0.7 * scene["opacities"]
    cams, k = _cameras(3, dtype), _intrinsics(3, 40, 30, 35.0, dtype)
    ours = _render_gradients(scene, cams, k, 40, 30, backend)
    monkeypatch.setattr(rasterizer, "_native_projection", lambda *args: None)
    ref = _render_gradients(scene, cams, k, 40, 30, backend)
    rtol, floor = TOL[dtype]
    for name, a, b in zip(scene, ours, ref, strict=True):
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, rtol=rtol, atol=floor * b.abs().max().item(), msg=name)


def test_cameras_that_require_grad_keep_the_pytorch_projection():
    scene = _scene(30, 10)
    cams, k = _cameras(2), _intrinsics(2, 30, 20, 25.0)
    means = scene["means"].clone().requires_grad_()
    for index, camera_input in enumerate((cams, k)):
        leaf = camera_input.clone().requires_grad_()
        args = [cams, k]
        args[index] = leaf
        proj = project_gaussians(means, scene["quats"], scene["scales"], *args, 30, 20)
        assert type(proj.means2d.grad_fn).__name__ != "_NativeProjectionBackward"
        grads = torch.autograd.grad(proj.conics.sum() + proj.means2d.sum(), [means, leaf])
        assert all(torch.isfinite(g).all() and g.abs().max() > 0 for g in grads)
    # Only some of means, quats and scales need gradients: the Function, and only theirs come back.
    scales = scene["scales"].clone().requires_grad_()
    proj = project_gaussians(scene["means"], scene["quats"], scales, cams, k, 30, 20)
    assert type(proj.means2d.grad_fn).__name__ == "_NativeProjectionBackward"
    (grad,) = torch.autograd.grad(proj.conics.sum(), [scales])
    assert grad.abs().max() > 0


def test_phigenesis_projection_torch_keeps_the_pytorch_projection(monkeypatch):
    scene = _scene(30, 11)
    cams, k = _cameras(2), _intrinsics(2, 30, 20, 25.0)
    means = scene["means"].clone().requires_grad_()
    monkeypatch.setenv("PHIGENESIS_PROJECTION", "torch")
    proj = project_gaussians(means, scene["quats"], scene["scales"], cams, k, 30, 20)
    assert type(proj.means2d.grad_fn).__name__ != "_NativeProjectionBackward"
    monkeypatch.setenv("PHIGENESIS_PROJECTION", "auto")
    native_proj = project_gaussians(means, scene["quats"], scene["scales"], cams, k, 30, 20)
    assert type(native_proj.means2d.grad_fn).__name__ == "_NativeProjectionBackward"
    torch.testing.assert_close(proj.conics, native_proj.conics)


def test_gradients_flow_through_non_contiguous_and_expanded_inputs():
    """Per-camera centres made by expanding one set (the backward's (C, N, 3) gradient is summed back by
    autograd), transposed and sliced inputs."""
    scene = _scene(80, 11, dtype=F32)
    cams, k = _cameras(3, F32), _intrinsics(3, 40, 30, 35.0, F32)
    leaves = [scene[name].clone().requires_grad_() for name in NAMES]
    inputs = (
        leaves[0][None].expand(3, 80, 3),
        torch.cat([leaves[1], leaves[1]], 1)[:, :4],
        leaves[2].t().contiguous().t(),
    )
    proj = project_gaussians(*inputs, cams, k, 40, 30)
    assert type(proj.means2d.grad_fn).__name__ == "_NativeProjectionBackward"
    upstream = _upstream(proj, 5)
    ours = torch.autograd.grad((proj.means2d, proj.conics, proj.depths), leaves, upstream)
    ref_proj = _project_gaussians_torch(*inputs, cams, k, 40, 30)
    ref = torch.autograd.grad((ref_proj.means2d, ref_proj.conics, ref_proj.depths), leaves, upstream)
    for name, a, b in zip(NAMES, ours, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * b.abs().max().item(), msg=name)


def test_gradients_are_bitwise_the_same_for_any_thread_count():
    scene = _per_camera(_scene(3000, 12, dtype=F32), 5, 2)
    cams, k = _cameras(5, F32), _intrinsics(5, 40, 30, 35.0, F32)
    threads = torch.get_num_threads()
    try:
        runs = []
        for count in (1, 2, 2):
            torch.set_num_threads(count)
            runs.append(_gradients(project_gaussians, scene, cams, k, 40, 30)[1])
    finally:
        torch.set_num_threads(threads)
    for other in runs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(runs[0], other, strict=True))


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 12),
    cams=st.integers(1, 4),
    per_camera=st.booleans(),
    log_scale=st.floats(-4.0, 4.5),
    spread=st.floats(0.1, 20.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_gradients_match_autograd_on_any_small_scene(n, cams, per_camera, log_scale, spread, seed):
    """Centres spread from near the axis to far outside the view and behind the cameras, scales from
    1e-4 m to past MAX_SCALE, a zero quaternion in every fifth, float64."""
    g = torch.Generator().manual_seed(seed)
    scene = {
        "means": torch.randn(n, 3, generator=g, dtype=F64) * spread
        + torch.tensor([0.0, 0.0, 2.0], dtype=F64),
        "quats": torch.randn(n, 4, generator=g, dtype=F64) * torch.rand(n, 1, generator=g, dtype=F64) * 3,
        "scales": 10.0 ** (log_scale + torch.randn(n, 3, generator=g, dtype=F64)),
        "opacities": torch.rand(n, generator=g, dtype=F64),
    }
    scene["quats"][::5] = 0.0
    if per_camera:
        scene = _per_camera(scene, cams, seed)
    _assert_gradients_match(scene, _cameras(cams), _intrinsics(cams, 24, 18, 20.0), 24, 18, seed=seed)
