"""Tile-based Gaussian rasterizers (native kernel and tiled PyTorch) against the per-pixel reference,
gradients, and hard cases. The native kernel's own suite is tests/test_rasterizer_native.py."""

from __future__ import annotations

import math

import pytest
import torch

from phigenesis.models.rasterizer import (
    MAX_ALPHA,
    TRANSMITTANCE_THRESHOLD,
    RenderOutput,
    gsplat_available,
    native_available,
    rasterize,
    rasterize_reference,
)

F64 = torch.float64
#: Every tile-based backend this machine has (the native one only where it builds).
BACKENDS = [
    "torch",
    pytest.param("cpu", marks=pytest.mark.skipif(not native_available(), reason="no native build")),
]


def _intrinsics(cams: int, width: int, height: int, focal: float, dtype=F64) -> torch.Tensor:
    k = torch.tensor(
        [[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=dtype
    )
    return k[None].repeat(cams, 1, 1)


def _cameras(cams: int, dtype=F64) -> torch.Tensor:
    """Cameras near the origin looking roughly along +z, slightly rotated and shifted."""
    poses = []
    for c in range(cams):
        yaw = 0.15 * c
        pose = torch.eye(4, dtype=dtype)
        pose[0, 0], pose[0, 2], pose[2, 0], pose[2, 2] = (
            math.cos(yaw),
            math.sin(yaw),
            -math.sin(yaw),
            math.cos(yaw),
        )
        pose[:3, 3] = torch.tensor([0.2 * c, -0.1 * c, 0.05 * c], dtype=dtype)
        poses.append(pose)
    return torch.stack(poses)


def _scene(n: int, seed: int, features: int = 3, dtype=F64) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 0.7, 0.8], dtype=dtype))
        + torch.tensor([0.0, 0.0, 3.0], dtype=dtype),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": torch.rand(n, 3, generator=g, dtype=dtype) * 0.25 + 0.01,
        "opacities": torch.rand(n, generator=g, dtype=dtype),
        "features": torch.rand(n, features, generator=g, dtype=dtype),
    }


def _assert_same(a: RenderOutput, b: RenderOutput, atol: float = 1e-5) -> None:
    torch.testing.assert_close(a.features, b.features, atol=atol, rtol=0)
    torch.testing.assert_close(a.alpha, b.alpha, atol=atol, rtol=0)
    torch.testing.assert_close(a.depth, b.depth, atol=atol, rtol=0)
    assert torch.equal(a.radii, b.radii)


def _assert_finite(out: RenderOutput) -> None:
    for t in (out.features, out.depth, out.alpha):
        assert torch.isfinite(t).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("n", "seed", "width", "height", "tile"), [(40, 0, 40, 30, 16), (80, 1, 33, 21, 8)])
def test_tiled_render_matches_per_pixel_reference(n, seed, width, height, tile, backend):
    scene = _scene(n, seed)
    cams = 3
    args = (*scene.values(), _cameras(cams), _intrinsics(cams, width, height, 35.0), width, height)
    fast = rasterize(*args, tile=tile, backend=backend)
    ref = rasterize_reference(*args)
    assert fast.features.shape == (cams, height, width, 3)
    assert fast.depth.shape == fast.alpha.shape == (cams, height, width)
    assert fast.alpha.max() > 0.5  # the scene is actually visible
    _assert_same(fast, ref)


@pytest.mark.parametrize("backend", BACKENDS)
def test_centres_per_camera_equal_one_render_per_camera(backend):
    scene = _scene(50, 4)
    cams, width, height = 3, 30, 20
    poses, k = _cameras(cams), _intrinsics(cams, width, height, 30.0)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.1, 0.2], [-0.4, 0.2, 0.5]], dtype=F64)
    per_camera = scene["means"][None] + shift[:, None]  # (C, N, 3)
    rest = [scene[k_] for k_ in ("quats", "scales", "opacities")]
    feats = scene["features"].clone().requires_grad_(True)
    means = per_camera.clone().requires_grad_(True)
    together = rasterize(means, *rest, feats, poses, k, width, height, backend=backend)
    (together.features.sum() + together.depth.sum()).backward()
    grads = means.grad.clone(), feats.grad.clone()
    means.grad = feats.grad = None
    for c in range(cams):
        one = rasterize(
            means[c], *rest, feats, poses[c : c + 1], k[c : c + 1], width, height, backend=backend
        )
        _assert_same(
            RenderOutput(*(getattr(together, f)[c : c + 1] for f in ("features", "depth", "alpha", "radii"))),
            one,
            1e-12,
        )
        (one.features.sum() + one.depth.sum()).backward()
    torch.testing.assert_close(means.grad, grads[0], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(feats.grad, grads[1], atol=1e-10, rtol=1e-10)
    with pytest.raises(AssertionError):
        rasterize(per_camera[:2], *rest, scene["features"], poses, k, width, height, backend=backend)


def test_tiled_render_matches_reference_in_float32_and_small_batches():
    scene = _scene(60, 2, dtype=torch.float32)
    args = (*scene.values(), _cameras(2, torch.float32), _intrinsics(2, 24, 20, 30.0, torch.float32), 24, 20)
    fast, ref = rasterize(*args, tile=4, max_batch_elements=64, backend="torch"), rasterize_reference(*args)
    torch.testing.assert_close(fast.features, ref.features, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.alpha, ref.alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.depth, ref.depth, atol=1e-5, rtol=1e-5)  # metres, float32


def test_tiled_gradients_match_reference_gradients_with_early_stopping():
    scene = _scene(60, 3)
    scene["opacities"] = 0.7 + 0.3 * scene["opacities"]  # dense enough that pixels stop early
    scene = {k: v.requires_grad_() for k, v in scene.items()}
    args = (*scene.values(), _cameras(2), _intrinsics(2, 20, 16, 20.0), 20, 16)
    weights = torch.rand(2, 16, 20, 4, generator=torch.Generator().manual_seed(0), dtype=F64)

    def loss(out: RenderOutput) -> torch.Tensor:
        return (out.features * weights[..., :3]).sum() + (out.depth * weights[..., 3]).sum() + out.alpha.sum()

    fast = torch.autograd.grad(loss(rasterize(*args, tile=8, backend="torch")), list(scene.values()))
    ref = torch.autograd.grad(loss(rasterize_reference(*args)), list(scene.values()))
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_finite_differences(backend):
    scene = _scene(4, 4)
    scene["means"] = torch.tensor(
        [[0.0, 0.0, 2.0], [0.1, 0.05, 2.5], [-0.1, 0.0, 3.0], [0.05, -0.1, 1.8]], dtype=F64
    )
    scene["scales"] = torch.tensor(
        [[0.1, 0.08, 0.05], [0.12, 0.1, 0.1], [0.2, 0.15, 0.1], [0.06, 0.1, 0.08]], dtype=F64
    )
    scene["opacities"] = torch.tensor([0.6, 0.5, 0.7, 0.4], dtype=F64)
    cams, k = _cameras(1), _intrinsics(1, 10, 8, 12.0)

    def render(means, scales, opacities, features, quats):
        out = rasterize(means, quats, scales, opacities, features, cams, k, 10, 8, tile=4, backend=backend)
        return out.features, out.depth, out.alpha

    inputs = tuple(
        scene[name].clone().requires_grad_() for name in ("means", "scales", "opacities", "features", "quats")
    )
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_in_front_of_camera_renders_at_projected_pixel_with_its_depth(backend):
    width, height = 32, 24
    k = torch.tensor([[[50.0, 0.0, 10.0], [0.0, 50.0, 7.0], [0.0, 0.0, 1.0]]], dtype=F64)
    pose = torch.eye(4, dtype=F64)[None]
    pose[0, :3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=F64)  # camera away from the origin
    # World point 4 m along +z from the camera, 0.4 m right and 0.2 m down: pixel (10 + 5, 7 + 2.5).
    means = pose[0, :3, 3][None] + torch.tensor([[0.4, 0.2, 4.0]], dtype=F64)
    out = rasterize(
        means,
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
        torch.full((1, 3), 0.05, dtype=F64),
        torch.tensor([0.8], dtype=F64),
        torch.tensor([[0.2, 0.5, 1.0]], dtype=F64),
        pose,
        k,
        width,
        height,
        backend=backend,
    )
    peak = torch.nonzero(out.alpha[0] == out.alpha[0].max())
    rows, cols = peak[:, 0].tolist(), peak[:, 1].tolist()
    assert set(cols) == {15} and set(rows) == {9, 10}  # v = 9.5 lies between rows 9 and 10
    assert out.depth[0, 9, 15].item() == pytest.approx(4.0, abs=1e-9)
    assert out.alpha[0, 0, 0] == 0 and out.depth[0, 0, 0] == 0
    torch.testing.assert_close(
        out.features[0, 9, 15] / out.alpha[0, 9, 15], torch.tensor([0.2, 0.5, 1.0], dtype=F64)
    )
    # EWA by hand: Sigma2d = s^2 J J^T + 0.3 I, J = [[f/z, 0, -f x/z^2], [0, f/z, -f y/z^2]].
    s2, f, x, y, z = 0.05**2, 50.0, 0.4, 0.2, 4.0
    a = s2 * (f / z) ** 2 * (1 + (x / z) ** 2) + 0.3
    c = s2 * (f / z) ** 2 * (1 + (y / z) ** 2) + 0.3
    b = s2 * f * f * x * y / z**4
    # The mean is at (15, 9.5): pixel (row 9, column 15) is 0.5 px away along v only.
    expected = 0.8 * math.exp(-0.5 * 0.25 * a / (a * c - b * b))
    assert out.alpha[0, 9, 15].item() == pytest.approx(expected, rel=1e-9)


def _hard_scene(dtype) -> dict[str, torch.Tensor]:
    means = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # at the camera centre
            [0.3, 0.1, 0.0],  # on the camera plane
            [0.0, 0.0, -2.0],  # behind
            [0.0, 0.0, 0.0101],  # just past the near plane, very close
            [0.0, 0.0, 2.0],  # zero quaternion
            [0.1, 0.0, 3.0],  # huge scales
            [0.0, 0.1, 3.0],  # tiny scales
            [-0.1, 0.0, 2.5],  # a needle: near-singular 2D covariance
            [500.0, 0.0, 1.0],  # far off-screen
            [0.2, 0.2, 1e-7],  # almost on the camera plane, off-axis
        ],
        dtype=dtype,
    )
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype).repeat(len(means), 1)
    quats[4] = 0.0
    quats[7] = torch.tensor([0.9, 0.3, 0.2, 0.1], dtype=dtype)
    scales = torch.full((len(means), 3), 0.1, dtype=dtype)
    scales[5] = 1e6
    scales[6] = 1e-9
    scales[7] = torch.tensor([3.0, 1e-8, 1e-8], dtype=dtype)
    opacities = torch.full((len(means),), 0.9, dtype=dtype)
    features = torch.rand(len(means), 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_hard_cases_render_finite_values_and_gradients(dtype, backend):
    scene = {k: v.requires_grad_() for k, v in _hard_scene(dtype).items()}
    args = (*scene.values(), _cameras(2, dtype), _intrinsics(2, 24, 16, 20.0, dtype), 24, 16)
    out = rasterize(*args, backend=backend)
    _assert_finite(out)
    assert out.radii[:, [0, 1, 2, 8, 9]].eq(0).all()  # culled: at, on, behind the camera plane, off-screen
    (out.features.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for name, tensor in scene.items():
        assert torch.isfinite(tensor.grad).all(), name
    ref = rasterize_reference(*(a.detach() if torch.is_tensor(a) else a for a in args))
    _assert_same(
        rasterize(*(a.detach() if torch.is_tensor(a) else a for a in args), backend=backend), ref, atol=1e-4
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_many_overlapping_gaussians_stop_at_the_transmittance_threshold(backend):
    n = 2000
    g = torch.Generator().manual_seed(6)
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=F64) + torch.rand(n, 3, generator=g, dtype=F64) * 1e-3
    means.requires_grad_()
    scene = {
        "means": means,
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64).repeat(n, 1),
        "scales": torch.full((n, 3), 2.0, dtype=F64),  # 10 px wide: alpha is capped everywhere
        "opacities": torch.full((n,), 1.0, dtype=F64, requires_grad=True),
        "features": torch.rand(n, 2, generator=g, dtype=F64),
    }
    args = (*scene.values(), _cameras(1), _intrinsics(1, 8, 8, 10.0), 8, 8)
    out = rasterize(*args, tile=4, backend=backend)
    _assert_finite(out)
    # Near the centre every Gaussian has alpha ~0.9975: the frontmost leaves T ~2.5e-3 and the next
    # would take it to ~6e-6 <= 1e-4, so it is not added and the pixel ends with the first alone.
    first = int(torch.argmin(means[:, 2]))
    alone = rasterize_reference(*(t[first : first + 1].detach() for t in scene.values()), *args[5:])
    centre_alpha = out.alpha[0, 3:5, 3:5]
    torch.testing.assert_close(centre_alpha, alone.alpha[0, 3:5, 3:5], atol=1e-12, rtol=0)
    assert (1 - centre_alpha).min() > TRANSMITTANCE_THRESHOLD and (centre_alpha < MAX_ALPHA).all()
    out.alpha.sum().backward()
    assert torch.isfinite(means.grad).all() and torch.isfinite(scene["opacities"].grad).all()
    _assert_same(out, rasterize_reference(*(a.detach() if torch.is_tensor(a) else a for a in args)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_is_capped_at_gsplats_0_999(backend):
    # Opacity 1 at a pixel centre: alpha = min(0.999, 1); a second Gaussian behind would bring T from
    # 1e-3 to 1e-6 <= 1e-4, so it is not added.
    k = torch.tensor([[[10.0, 0.0, 2.0], [0.0, 10.0, 2.0], [0.0, 0.0, 1.0]]], dtype=F64)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], dtype=F64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64).repeat(2, 1)
    out = rasterize(
        means,
        quats,
        torch.full((2, 3), 0.2, dtype=F64),
        torch.ones(2, dtype=F64),
        torch.eye(2, dtype=F64),
        torch.eye(4, dtype=F64)[None],
        k,
        5,
        5,
        backend=backend,
    )
    assert out.alpha[0, 2, 2].item() == pytest.approx(MAX_ALPHA, abs=1e-15)
    assert out.features[0, 2, 2].tolist() == pytest.approx([MAX_ALPHA, 0.0], abs=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_renders_zeros(backend):
    scene = _scene(5, 7)
    scene["means"] = scene["means"] * torch.tensor([1.0, 1.0, -1.0], dtype=F64)  # all behind the camera
    out = rasterize(*scene.values(), _cameras(1), _intrinsics(1, 12, 10, 10.0), 12, 10, backend=backend)
    assert out.features.abs().max() == 0 and out.alpha.max() == 0 and out.depth.max() == 0
    assert out.radii.eq(0).all()


@pytest.mark.skipif(not gsplat_available(), reason="gsplat backend needs gsplat and CUDA")
def test_gsplat_backend_roughly_matches_torch():  # pragma: no cover - needs a GPU
    scene = {k: v.float().cuda() for k, v in _scene(50, 8).items()}
    args = (*scene.values(), _cameras(2).float().cuda(), _intrinsics(2, 40, 30, 35.0).float().cuda(), 40, 30)
    ours, theirs = rasterize(*args, backend="torch"), rasterize(*args, backend="gsplat")
    # One set of conventions: only float32 rounding (and gsplat's __expf) separates the two.
    assert (ours.features - theirs.features).abs().max() < 1e-4
