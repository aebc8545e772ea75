"""The native CPU rasterizer against the per-pixel reference (values) and the tiled PyTorch path
(gradients), on random scenes and hard cases; its determinism; the native projection's forward against
the PyTorch one, and when each is used (its backward: tests/test_native_projection_backward.py); and the
fallback where it cannot be built."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from phigenesis.models import native
from phigenesis.models.rasterizer import RenderOutput, native_available, rasterize, rasterize_reference
from tests.test_rasterizer import _cameras, _hard_scene, _intrinsics, _scene

#: Everything but the fallback test needs the extension built here.
needs_native = pytest.mark.skipif(
    not native_available(), reason=f"native build unavailable: {native.failure_reason()}"
)

F64 = torch.float64
F32 = torch.float32


def _assert_values_match(out: RenderOutput, ref: RenderOutput, atol: float) -> None:
    for name in ("features", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=atol, rtol=0, msg=name)
    assert torch.equal(out.radii, ref.radii)


def _loss_weights(out: RenderOutput, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    dtype = out.alpha.dtype
    return (
        torch.rand(out.features.shape, generator=g, dtype=dtype),
        torch.rand(out.depth.shape, generator=g, dtype=dtype),
        torch.rand(out.alpha.shape, generator=g, dtype=dtype) - 0.5,
    )


def _gradients(scene: dict, cams, k, width, height, backend: str, **kw) -> list[torch.Tensor]:
    leaves = [v.detach().clone().requires_grad_() for v in scene.values()]
    out = rasterize(*leaves, cams, k, width, height, backend=backend, **kw)
    wf, wd, wa = _loss_weights(out)
    loss = (out.features * wf).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()
    return list(torch.autograd.grad(loss, leaves))


def _assert_gradients_match(scene: dict, cams, k, width, height, rtol: float = 1e-4, **kw) -> None:
    ours = _gradients(scene, cams, k, width, height, "cpu", **kw)
    theirs = _gradients(scene, cams, k, width, height, "torch", **kw)
    for name, a, b in zip(scene, ours, theirs, strict=True):
        assert torch.isfinite(a).all(), name
        scale = b.abs().max().item()
        torch.testing.assert_close(a, b, rtol=rtol, atol=rtol * scale, msg=name)


@needs_native
@pytest.mark.parametrize(
    ("n", "seed", "features", "width", "height", "tile"),
    [(60, 0, 3, 40, 30, 16), (120, 1, 1, 33, 21, 8), (90, 2, 16, 27, 19, 16), (200, 3, 6, 64, 48, 16)],
)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_native_matches_per_pixel_reference(n, seed, features, width, height, tile, dtype):
    scene = _scene(n, seed, features=features, dtype=dtype)
    scene["opacities"] = 0.3 + 0.7 * scene["opacities"]  # dense: pixels stop early
    args = (*scene.values(), _cameras(3, dtype), _intrinsics(3, width, height, 35.0, dtype), width, height)
    out = rasterize(*args, tile=tile, backend="cpu")
    assert out.features.shape == (3, height, width, features) and out.features.dtype == dtype
    assert out.alpha.max() > 0.99  # opaque somewhere: early stopping is exercised
    _assert_values_match(out, rasterize_reference(*args), atol=1e-5 if dtype == F64 else 1e-4)


@needs_native
@pytest.mark.parametrize(("seed", "features", "tile"), [(4, 3, 16), (5, 8, 8)])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_native_gradients_match_the_pytorch_path(seed, features, tile, dtype):
    scene = _scene(70, seed, features=features, dtype=dtype)
    scene["opacities"] = 0.5 + 0.5 * scene["opacities"]
    _assert_gradients_match(
        scene,
        _cameras(2, dtype),
        _intrinsics(2, 30, 22, 25.0, dtype),
        30,
        22,
        rtol=1e-4 if dtype == F64 else 2e-3,
        tile=tile,
    )


@needs_native
@pytest.mark.parametrize("dtype", [F64, F32])
def test_native_hard_cases_match_reference_and_pytorch_gradients(dtype):
    scene = _hard_scene(dtype)
    extra = {  # 1e-4 m and 1e2 m scales in view, a needle and a zero quaternion are in _hard_scene
        "means": torch.tensor([[0.05, -0.05, 2.0], [0.0, 0.05, 4.0]], dtype=dtype),
        "quats": torch.tensor([[0.7, 0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 0.0]], dtype=dtype),
        "scales": torch.tensor([[1e-4, 1e-4, 1e-4], [1e2, 1e2, 1e2]], dtype=dtype),
        "opacities": torch.tensor([0.95, 0.5], dtype=dtype),
        "features": torch.tensor([[1.0, 0.0, 0.5], [0.2, 0.9, 0.1]], dtype=dtype),
    }
    scene = {key: torch.cat([scene[key], extra[key]]) for key in scene}
    cams, k = _cameras(2, dtype), _intrinsics(2, 24, 16, 20.0, dtype)
    args = (*scene.values(), cams, k, 24, 16)
    out = rasterize(*args, backend="cpu")
    assert out.radii[:, [0, 1, 2, 8, 9]].eq(0).all()  # at, on, behind the camera plane; off-screen
    _assert_values_match(out, rasterize_reference(*args), atol=1e-5 if dtype == F64 else 1e-4)
    _assert_gradients_match(scene, cams, k, 24, 16, rtol=1e-4 if dtype == F64 else 2e-3)


@needs_native
def test_a_hundred_thousand_gaussians_on_one_pixel():
    n = 100_000
    g = torch.Generator().manual_seed(9)
    scene = {
        "means": torch.tensor([[0.0, 0.0, 2.0]], dtype=F64) + torch.rand(n, 3, generator=g, dtype=F64) * 1e-3,
        "quats": torch.randn(n, 4, generator=g, dtype=F64),
        "scales": 0.01 + 0.02 * torch.rand(n, 3, generator=g, dtype=F64),
        "opacities": torch.rand(n, generator=g, dtype=F64) * 0.05,  # faint: thousands before T <= 1e-4
        "features": torch.rand(n, 3, generator=g, dtype=F64),
    }
    cams, k = _cameras(1), _intrinsics(1, 4, 4, 10.0)
    out = rasterize(*scene.values(), cams, k, 4, 4, tile=4, backend="cpu")
    ref = rasterize(*scene.values(), cams, k, 4, 4, tile=4, backend="torch")  # itself held to the reference
    _assert_values_match(out, ref, atol=1e-9)
    assert out.alpha[0, 1:3, 1:3].min() > 0.999 and out.alpha[0, 0].max() == 0  # the four nearest saturate
    _assert_gradients_match(scene, cams, k, 4, 4, tile=4)


@needs_native
def test_empty_scenes_one_pixel_images_and_empty_tiles():
    cams, k = _cameras(2), _intrinsics(2, 12, 10, 10.0)
    none = {k_: v[:0] for k_, v in _scene(3, 0).items()}  # no Gaussians at all
    out = rasterize(*none.values(), cams, k, 12, 10, backend="cpu")
    assert out.features.shape == (2, 10, 12, 3) and out.alpha.abs().max() == 0 and out.radii.shape == (2, 0)
    behind = _scene(6, 1)
    behind["means"] = behind["means"] * torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    out = rasterize(*behind.values(), cams, k, 12, 10, backend="cpu")
    assert out.features.abs().max() == 0 and out.depth.abs().max() == 0 and out.radii.eq(0).all()
    grads = _gradients(behind, cams, k, 12, 10, "cpu")
    assert all(torch.equal(g, torch.zeros_like(g)) for g in grads)
    # One pixel.
    scene = _scene(30, 2)
    args = (*scene.values(), _cameras(2), _intrinsics(2, 1, 1, 2.0), 1, 1)
    _assert_values_match(rasterize(*args, backend="cpu"), rasterize_reference(*args), atol=1e-12)
    _assert_gradients_match(scene, _cameras(2), _intrinsics(2, 1, 1, 2.0), 1, 1)
    # A cluster in one corner of a 70 x 50 image: most tiles hold no Gaussian.
    corner = _scene(40, 3)
    corner["means"] = torch.tensor([-0.9, -0.6, 3.0], dtype=F64) + 0.05 * torch.randn(
        40, 3, generator=torch.Generator().manual_seed(3), dtype=F64
    )
    corner["scales"] = corner["scales"] * 0.2
    k = torch.tensor([[[40.0, 0.0, 34.5], [0.0, 40.0, 24.5], [0.0, 0.0, 1.0]]], dtype=F64)
    args = (*corner.values(), torch.eye(4, dtype=F64)[None], k, 70, 50)
    out = rasterize(*args, backend="cpu")
    assert out.alpha[0, :, 35:].max() == 0 and out.alpha[0, 25:].max() == 0 and out.alpha.max() > 0.5
    _assert_values_match(out, rasterize_reference(*args), atol=1e-12)


@needs_native
def test_native_is_deterministic_and_independent_of_the_thread_count():
    """The kernel's outputs and gradients are bitwise the same for one or two threads (each tile writes
    its own entries; the sums run in list order), and a whole render's gradients repeat exactly."""
    from phigenesis.models.rasterizer import _rasterize_native, project_gaussians

    scene = _scene(150, 6, features=4, dtype=F32)
    scene["opacities"] = 0.5 + 0.5 * scene["opacities"]
    cams, k = _cameras(3, F32), _intrinsics(3, 48, 32, 30.0, F32)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], cams, k, 48, 32, 0.01, scene["opacities"]
    )
    inputs = [
        t.detach().requires_grad_()
        for t in (proj.means2d, proj.conics, scene["opacities"], scene["features"])
    ]
    depths = proj.depths.detach().requires_grad_()

    def run() -> list[torch.Tensor]:
        p = type(proj)(means2d=inputs[0], conics=inputs[1], depths=depths, radii=proj.radii, valid=proj.valid)
        out = _rasterize_native(p, inputs[2], inputs[3], 48, 32, 8)
        wf, wd, wa = _loss_weights(out)
        loss = (out.features * wf).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()
        return [out.features, out.alpha, *torch.autograd.grad(loss, [*inputs, depths])]

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run()
        torch.set_num_threads(2)
        two = run()
        whole = [_gradients(scene, cams, k, 48, 32, "cpu", tile=8) for _ in range(2)]
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, two, strict=True))
    assert all(torch.equal(a, b) for a, b in zip(*whole, strict=True))


@needs_native
def test_auto_picks_the_native_kernel_on_cpu_and_the_env_var_overrides(monkeypatch):
    from phigenesis.models.rasterizer import resolve_backend

    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    monkeypatch.setenv("PHIGENESIS_RASTERIZER", "torch")
    assert resolve_backend("auto", torch.device("cpu")) == "torch"
    monkeypatch.setenv("PHIGENESIS_RASTERIZER", "fast")
    with pytest.raises(ValueError, match="PHIGENESIS_RASTERIZER"):
        resolve_backend("auto", torch.device("cpu"))
    with pytest.raises(ValueError, match="backend must be one of"):
        resolve_backend("cuda", torch.device("cpu"))


# --- The native projection (csrc/project_cpu.cpp) against the PyTorch one -------------------------------

#: Tolerances of the native projection against the PyTorch path: relative, and an absolute floor (pixels,
#: 1/pixels^2, metres) at ~100x the rounding of the largest terms of each value (u = fx x / z + cx near
#: u = 0 keeps the rounding of cx, a needle's conic B the rounding of its large products). Both paths
#: evaluate the same operations in the same order and precision, so on an FMA CPU with MKL they agree
#: bitwise; only a BLAS that rounds the camera-space rotation differently can move the last bits.
_PROJECTION_TOL = {
    F64: {"rtol": 1e-12, "means2d": 1e-12, "conics": 1e-14, "depths": 1e-14},
    F32: {"rtol": 1e-5, "means2d": 1e-4, "conics": 1e-6, "depths": 1e-6},
}


def _project_both(*args, **kw):
    from phigenesis.models.rasterizer import _project_gaussians_torch, project_gaussians

    with torch.no_grad():
        return project_gaussians(*args, **kw), _project_gaussians_torch(*args, **kw)


def _assert_projections_match(ours, ref) -> None:
    dtype = ref.means2d.dtype
    tol = _PROJECTION_TOL[dtype]
    for name in ("means2d", "conics", "depths"):
        a, b = getattr(ours, name), getattr(ref, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        if name == "means2d":
            # u = f x / z + c: the depth's own allowed difference, relative to z, carries into u. It
            # matters only for centres within millimetres of the camera plane (near = 0), where float32
            # rounding of z alone moves u by pixels (-114,692 px at z = 0.7 mm came out 4.7 px apart).
            z = ref.depths.abs().double()[..., None]
            slack = b.abs().double() * tol["depths"] / z.clamp(min=1e-30)
            near_plane = torch.isfinite(slack) & (slack > tol["means2d"])
            a = torch.where(near_plane, b, a)  # those are checked here, the rest by assert_close
            close = (ours.means2d.double() - b.double()).abs() <= tol["means2d"] + slack
            assert bool(close[near_plane].all()), name
        torch.testing.assert_close(a, b, rtol=tol["rtol"], atol=tol[name], equal_nan=True, msg=name)
    assert ours.radii.shape == ref.radii.shape and ours.radii.dtype == ref.radii.dtype
    assert ours.valid.shape == ref.valid.shape and ours.valid.dtype == torch.bool
    if dtype == F64:
        assert torch.equal(ours.radii, ref.radii) and torch.equal(ours.valid, ref.valid)
        return
    # float32: a radius is ceil(extend sqrt(Sigma2d_ii + eps)); where that product lies within float32
    # rounding of an integer, a last-bit difference upstream (a BLAS that rounds the rotation otherwise)
    # moves the ceil by one, and with it maybe the off-screen test. Radii of millions of pixels (a
    # Gaussian across the camera plane) carry float32's relative rounding as well: the reference's
    # matmuls block differently with the thread count, and 88,087,104 px came out 176 px apart (2e-6).
    # Allowed: differences up to 1 + 1e-5 of the radius anywhere; the ceil may flip where its
    # argument's rounding (~1e-6 of it) spans an integer, which is common above 10^4 px and rare
    # below 10^3 px: there, flips in at most 1 in 10^4 of the (camera, Gaussian) pairs (none at all
    # in small scenes).
    budget = ref.valid.numel() // 10_000
    diff = (ours.radii - ref.radii).abs().double()
    radius = ref.radii.abs().double()
    assert bool((diff <= 1 + 1e-5 * radius).all())
    assert int(((diff > 0) & (radius < 1e3)).any(-1).sum()) <= budget
    assert int(ours.valid.ne(ref.valid).sum()) <= budget


def _projection_args(
    scene: dict, cams: int, width: int, height: int, focal: float, dtype, near: float = 0.01
):
    return (
        scene["means"],
        scene["quats"],
        scene["scales"],
        _cameras(cams, dtype),
        _intrinsics(cams, width, height, focal, dtype),
        width,
        height,
        near,
        scene["opacities"],
    )


@needs_native
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("per_camera", [False, True])
@pytest.mark.parametrize(("n", "cams", "seed"), [(7, 2, 0), (60, 3, 1), (4000, 5, 2)])
def test_native_projection_matches_pytorch_on_random_scenes(n, cams, seed, per_camera, dtype):
    """Small scenes take PyTorch's own loop for the rotation einsum, large ones BLAS: both covered."""
    scene = _scene(n, seed, dtype=dtype)
    if per_camera:
        shift = torch.randn(cams, 1, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 0.3
        scene["means"] = scene["means"][None] + shift
    ours, ref = _project_both(*_projection_args(scene, cams, 40, 30, 35.0, dtype))
    assert ref.valid.float().mean() > 0.3 and ref.radii.max() > 3  # a real scene, partly in view
    _assert_projections_match(ours, ref)
    # Without opacities the box extent is GAUSSIAN_EXTEND for all.
    _assert_projections_match(*_project_both(*_projection_args(scene, cams, 40, 30, 35.0, dtype)[:8]))


def _stress_scene(n: int, dtype) -> dict:
    """Scales from 1e-9 to 1e6 (past MAX_SCALE) with random anisotropy, needles, zero and tiny quaternions,
    centres on, behind and just past the near plane, a hair in front of the camera and at its centre,
    opacities around 1/255."""
    g = torch.Generator().manual_seed(11)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.0, 2.0], dtype=dtype)
    means[:, 2] += 2.0
    means[: n // 10, 2] = 0.01  # exactly on the near plane of the first camera (identity pose)
    means[n // 10 : n // 5, 2] = torch.linspace(-0.02, 0.04, n // 5 - n // 10, dtype=dtype)
    means[n // 5 : n // 5 + 20, 2] = 4 * torch.finfo(dtype).tiny  # with near = 0: inf and nan projections
    means[-1] = 0.0
    log_scale = torch.rand(n, 3, generator=g, dtype=dtype) * 15.0 - 9.0  # 1e-9 .. 1e6
    scales = torch.pow(torch.tensor(10.0, dtype=dtype), log_scale)
    scales[::7, 1:] = 1e-9  # needles
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[::5] = 0.0
    quats[1::11] *= 1e-13  # squared norm ~1e-26: treated as zero
    quats[2::11] *= 1e-11  # squared norm ~1e-22: normalised
    opacities = torch.rand(n, generator=g, dtype=dtype)
    opacities[::3] *= 2.0 / 255.0  # many around and below the alpha threshold
    opacities[::13] = 1.0 / 255.0
    opacities[::17] = 0.0
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities}


@needs_native
@pytest.mark.parametrize("dtype", [F64, F32])
def test_native_projection_matches_pytorch_on_hard_cases(dtype):
    hard = _hard_scene(dtype)
    extra = {  # the native hard-case test's extras: 1e-4 m and 1e2 m scales, a zero quaternion
        "means": torch.tensor([[0.05, -0.05, 2.0], [0.0, 0.05, 4.0]], dtype=dtype),
        "quats": torch.tensor([[0.7, 0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 0.0]], dtype=dtype),
        "scales": torch.tensor([[1e-4, 1e-4, 1e-4], [1e2, 1e2, 1e2]], dtype=dtype),
        "opacities": torch.tensor([0.95, 0.002], dtype=dtype),  # the second is below 1/255
    }
    hard = {key: torch.cat([hard[key], extra[key]]) for key in extra}
    ours, ref = _project_both(*_projection_args(hard, 2, 24, 16, 20.0, dtype))
    assert ref.radii[:, [0, 1, 2, 8, 9, 11]].eq(0).all() and ref.valid[:, [4, 5, 6, 7]].any()
    _assert_projections_match(ours, ref)
    # The same per camera, and without opacities.
    per_camera = {
        **hard,
        "means": hard["means"][None] + torch.tensor([[[0.0, 0, 0]], [[0.1, 0, 0.2]]], dtype=dtype),
    }
    _assert_projections_match(*_project_both(*_projection_args(per_camera, 2, 24, 16, 20.0, dtype)))
    _assert_projections_match(*_project_both(*_projection_args(hard, 2, 24, 16, 20.0, dtype)[:8]))

    stress = _stress_scene(3000, dtype)
    for near in (0.01, 0.0):  # near 0: centres on the camera plane project to inf and nan
        ours, ref = _project_both(*_projection_args(stress, 3, 48, 32, 30.0, dtype, near=near))
        assert ref.valid.any() and not ref.valid.all()
        _assert_projections_match(ours, ref)
    assert not torch.isfinite(ref.means2d).all()  # the inf and nan cases were there


@needs_native
@pytest.mark.parametrize("dtype", [F64, F32])
def test_native_projection_of_empty_scenes_and_one_pixel_images(dtype):
    scene = _scene(20, 3, dtype=dtype)
    none = {key: value[:0] for key, value in scene.items()}
    for per_camera in (False, True):
        empty = {**none, "means": none["means"][None].expand(2, 0, 3)} if per_camera else none
        ours, ref = _project_both(*_projection_args(empty, 2, 12, 10, 10.0, dtype))
        assert (
            ours.means2d.shape == (2, 0, 2) and ours.radii.shape == (2, 0, 2) and ours.valid.shape == (2, 0)
        )
        _assert_projections_match(ours, ref)
    no_cameras = _projection_args(scene, 2, 12, 10, 10.0, dtype)
    ours, ref = _project_both(
        scene["means"], *no_cameras[1:3], no_cameras[3][:0], no_cameras[4][:0], *no_cameras[5:]
    )
    assert ours.means2d.shape == (0, 20, 2)
    _assert_projections_match(ours, ref)
    ours, ref = _project_both(*_projection_args(scene, 2, 1, 1, 2.0, dtype))  # one pixel
    assert ref.valid.any()
    _assert_projections_match(ours, ref)


@needs_native
def test_native_projection_takes_non_contiguous_inputs_and_any_thread_count():
    scene = _scene(500, 4, dtype=F32)
    args = _projection_args(scene, 3, 40, 30, 35.0, F32)
    strided = (
        scene["means"].t().contiguous().t(),
        torch.cat([scene["quats"], scene["quats"]], 1)[:, :4],
        scene["scales"].flip(0).flip(0),
        *args[3:],
    )
    assert not strided[0].is_contiguous() and not strided[1].is_contiguous()
    _assert_projections_match(*_project_both(*strided))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one, _ = _project_both(*args)
        torch.set_num_threads(2)
        two, _ = _project_both(*args)
    finally:
        torch.set_num_threads(threads)
    for name in ("means2d", "conics", "depths", "radii", "valid"):
        assert torch.equal(getattr(one, name), getattr(two, name)), name


@needs_native
def test_projection_dispatch_keeps_camera_gradients_on_the_pytorch_path(monkeypatch):
    """With grad mode on and means, quats or scales requiring grad, the native projection and its backward
    run (tests/test_native_projection_backward.py checks those gradients); with poses or intrinsics
    requiring grad, the PyTorch projection, and gradients flow; with grad mode off (or no input requiring
    grad) the native forward alone."""
    from phigenesis.models import rasterizer

    calls = []
    torch_path = rasterizer._project_gaussians_torch

    def counting(*args, **kw):
        calls.append(1)
        return torch_path(*args, **kw)

    monkeypatch.setattr(rasterizer, "_project_gaussians_torch", counting)
    scene = _scene(40, 5)
    args = list(_projection_args(scene, 2, 30, 20, 25.0, F64))
    for index in (0, 1, 2, 3, 4):  # means, quats, scales, poses, intrinsics
        leaf = args[index].clone().requires_grad_()
        call = [*args[:index], leaf, *args[index + 1 :]]
        calls.clear()
        proj = rasterizer.project_gaussians(*call)
        native_backward = type(proj.conics.grad_fn).__name__ == "_NativeProjectionBackward"
        assert native_backward == (index < 3) and bool(calls) == (index >= 3)
        assert proj.conics.requires_grad and not proj.radii.requires_grad
        (grad,) = torch.autograd.grad(proj.means2d.sum() + proj.conics.sum() + proj.depths.sum(), leaf)
        assert torch.isfinite(grad).all() and grad.abs().max() > 0
        calls.clear()
        with torch.no_grad():
            fast = rasterizer.project_gaussians(*call)
        assert not calls and not fast.means2d.requires_grad
        _assert_projections_match(fast, torch_path(*args))
    calls.clear()
    opac = scene["opacities"].clone().requires_grad_()  # no gradient reaches opacities through a projection
    fast = rasterizer.project_gaussians(*args[:8], opac)
    assert not calls and not fast.means2d.requires_grad
    calls.clear()
    with pytest.raises(RuntimeError):  # mixed dtypes: the PyTorch path gets them, and refuses them
        rasterizer.project_gaussians(*args[:3], args[3].float(), *args[4:])
    assert calls


@needs_native
@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_rendering_under_no_grad_matches_rendering_with_gradients(backend, dtype):
    scene = _scene(150, 6, features=4, dtype=dtype)
    scene["opacities"] = 0.3 + 0.7 * scene["opacities"]
    cams, k = _cameras(3, dtype), _intrinsics(3, 40, 30, 35.0, dtype)
    leaves = {key: value.clone().requires_grad_() for key, value in scene.items()}
    with_grad = rasterize(*leaves.values(), cams, k, 40, 30, backend=backend)
    assert with_grad.features.requires_grad
    with torch.no_grad():
        without = rasterize(*leaves.values(), cams, k, 40, 30, backend=backend)
    assert with_grad.alpha.max() > 0.9
    for name in ("features", "depth", "alpha"):
        torch.testing.assert_close(
            getattr(without, name), getattr(with_grad, name).detach(), atol=1e-6, rtol=0
        )
    assert torch.equal(without.radii, with_grad.radii)


def test_the_build_directory_hashes_every_source(tmp_path, monkeypatch):
    """A change to the projection's source alone makes a fresh build (and the bindings' source too)."""
    copies = []
    for source in native.SOURCES:
        copy = tmp_path / source.name
        copy.write_bytes(source.read_bytes())
        copies.append(copy)
    monkeypatch.setattr(native, "SOURCES", tuple(copies))
    first = native.build_directory()
    copies[1].write_bytes(copies[1].read_bytes() + b"\n// changed\n")
    second = native.build_directory()
    copies[0].write_bytes(copies[0].read_bytes() + b"\n// changed\n")
    assert len({first, second, native.build_directory()}) == 3
    assert [s.name for s in native.SOURCES] == ["rasterize_cpu.cpp", "project_cpu.cpp"]


_FALLBACK = textwrap.dedent(
    """
    import logging, sys, torch
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    sys.path.insert(0, {repo!r})
    from tests.test_rasterizer import _cameras, _intrinsics, _scene
    from phigenesis.models.rasterizer import rasterize, rasterize_reference
    scene = _scene(40, 0)
    args = (*scene.values(), _cameras(2), _intrinsics(2, 20, 14, 20.0), 20, 14)
    out, ref = rasterize(*args), rasterize_reference(*args)
    rasterize(*args)  # a second render logs nothing new
    pairs = ((out.features, ref.features), (out.alpha, ref.alpha))
    print("MAXDIFF", max((a - b).abs().max().item() for a, b in pairs))
    try:
        rasterize(*args, backend="cpu")
    except RuntimeError as error:
        print("CPU-REFUSED", error)
    """
)


def _run_without_a_compiler(tmp_path: Path) -> list[str]:
    """The lines :data:`_FALLBACK` prints (logs included) in a fresh process whose compiler always
    fails, with its native builds in ``tmp_path / "native"``."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "CXX": "/bin/false", "PHIGENESIS_NATIVE_DIR": str(tmp_path / "native")}
    env.pop("PHIGENESIS_RASTERIZER", None)
    result = subprocess.run(
        [sys.executable, "-c", _FALLBACK.format(repo=repo)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    diff = float(next(line for line in lines if line.startswith("MAXDIFF")).split()[1])
    assert diff < 1e-10
    assert any(line.startswith("CPU-REFUSED") and "not available" in line for line in lines)
    chosen = [line for line in lines if "rasterize: backend" in line]
    assert len(chosen) == 1 and "'torch'" in chosen[0], result.stdout
    return lines


def test_fallback_where_the_extension_cannot_be_built(tmp_path):
    """On a machine with no working compiler the suite's renders still pass through the PyTorch path,
    and the build failure is one warning line."""
    lines = _run_without_a_compiler(tmp_path)
    warnings = [line for line in lines if line.startswith("WARNING")]
    assert len(warnings) == 1, lines
    assert "native CPU rasterizer not available" in warnings[0] and "PyTorch tiled path" in warnings[0]
    assert "full log:" in warnings[0] and any((tmp_path / "native").glob("*/build-error.log"))


def test_a_build_killed_midway_does_not_hang_the_next_one(tmp_path, monkeypatch):
    """PyTorch marks a build in progress with a ``lock`` file that a killed build leaves behind, and
    waits for it to go: every later process hung. Under the flock the next process holds, that file
    is a leftover: it is removed with a warning and the build runs (here it fails: no compiler)."""
    monkeypatch.setenv("PHIGENESIS_NATIVE_DIR", str(tmp_path / "native"))
    leftover = native.build_directory() / "lock"
    leftover.parent.mkdir(parents=True)
    leftover.touch()
    lines = _run_without_a_compiler(tmp_path)  # a hang fails it by its timeout
    warnings = [line for line in lines if line.startswith("WARNING")]
    assert len(warnings) == 2, lines
    assert str(leftover) in warnings[0] and "killed before it finished" in warnings[0]
    assert "native CPU rasterizer not available" in warnings[1]
    assert not leftover.exists()


def test_every_checkout_builds_from_the_same_staged_sources(tmp_path, monkeypatch):
    """Two checkouts of the same sources at different paths share one build folder and compile the
    same staged copies (before, the second rewrote the folder's build.ninja and compiled again);
    staging again writes nothing."""
    staged = []
    for checkout in ("a", "b"):
        copies = []
        for source in native.SOURCES:
            copy = tmp_path / checkout / source.name
            copy.parent.mkdir(exist_ok=True)
            copy.write_bytes(source.read_bytes())
            copies.append(copy)
        monkeypatch.setattr(native, "SOURCES", tuple(copies))
        build = native.build_directory()
        staged.append((build, native.stage_sources(tmp_path / "build")))
    (build_a, paths_a), (build_b, paths_b) = staged
    assert build_a == build_b and paths_a == paths_b
    assert [p.parent for p in paths_a] == [tmp_path / "build" / "src"] * 2
    assert [p.read_bytes() for p in paths_a] == [s.read_bytes() for s in native.SOURCES]
    before = [(p.stat().st_ino, p.stat().st_mtime_ns) for p in paths_a]
    assert native.stage_sources(tmp_path / "build") == paths_a
    assert [(p.stat().st_ino, p.stat().st_mtime_ns) for p in paths_a] == before


_HOLD_BUILD_LOCK = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from phigenesis.native_cache import build_lock
    with build_lock(Path(sys.argv[1])) as held:
        print("HELD", held, flush=True)
        if sys.argv[2] == "die":
            os._exit(9)  # killed inside the build: no cleanup runs
        time.sleep(60)
    """
)


def test_the_build_lock_dies_with_its_holder(tmp_path):
    """While a live process holds the build lock, no other can take it; once its holder is killed
    mid-build it is free at once (a flock, not a file whose existence is the lock)."""
    import fcntl

    def try_take() -> bool:
        fd = os.open(tmp_path / ".build.lock", os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            return False
        finally:
            os.close(fd)

    live = subprocess.Popen(
        [sys.executable, "-c", _HOLD_BUILD_LOCK, str(tmp_path), "live"], stdout=subprocess.PIPE, text=True
    )
    try:
        assert live.stdout.readline().strip() == "HELD True"
        assert not try_take()
    finally:
        live.kill()
        live.wait()
    dead = subprocess.run(
        [sys.executable, "-c", _HOLD_BUILD_LOCK, str(tmp_path), "die"], capture_output=True, text=True
    )
    assert dead.returncode == 9 and dead.stdout.strip() == "HELD True", dead.stderr
    assert try_take()
