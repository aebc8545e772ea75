"""The gsplat backend (gsplat 1.5.3's CUDA kernels) against the CPU backends, in float32: values,
gradients, centres per camera and the hard cases of tests/test_rasterizer.py.

Needs CUDA and gsplat, so it is skipped in CI; it runs on a GPU machine (the device tool), where the
CPU side is the native kernel if it builds there and the tiled PyTorch path otherwise. Both are held
to the per-pixel reference by the CPU suites, so agreement here ties gsplat to that reference too.
"""

from __future__ import annotations

import pytest
import torch

from phigenesis.models.rasterizer import (
    RenderOutput,
    gsplat_available,
    native_available,
    rasterize,
    resolve_backend,
)
from tests.test_rasterizer import _cameras, _hard_scene, _intrinsics, _scene

pytestmark = pytest.mark.skipif(not gsplat_available(), reason="the gsplat backend needs gsplat and CUDA")

F32 = torch.float32
#: Largest difference allowed in colour, alpha and depth (float32 on both sides; gsplat uses __expf).
ATOL = 1e-4
#: Gradients: largest difference relative to the largest CPU gradient of the same input.
GRAD_RTOL = 2e-3


def _cpu_backend() -> str:
    return "cpu" if native_available() else "torch"


def _render(scene: dict, cams, k, width: int, height: int, backend: str) -> RenderOutput:
    device = "cuda" if backend == "gsplat" else "cpu"
    args = [t.to(device) for t in (*scene.values(), cams, k)]
    return rasterize(*args, width, height, backend=backend)


def _assert_outputs_match(gpu: RenderOutput, cpu: RenderOutput, atol: float = ATOL) -> None:
    gpu = RenderOutput(*(t.cpu() for t in (gpu.features, gpu.depth, gpu.alpha, gpu.radii)))
    torch.testing.assert_close(gpu.features, cpu.features, atol=atol, rtol=0, msg="features")
    torch.testing.assert_close(gpu.alpha, cpu.alpha, atol=atol, rtol=0, msg="alpha")
    # Expected depth is a ratio: compare it where the pixel is not almost empty.
    seen = cpu.alpha > 0.01
    torch.testing.assert_close(gpu.depth[seen], cpu.depth[seen], atol=atol, rtol=atol, msg="depth")
    # Culling may differ only at the image border: gsplat keeps a box that ends within half a pixel
    # outside the last pixel centre (its centres sit at j + 0.5), which touches no pixel.
    both = (gpu.radii > 0) & (cpu.radii > 0)
    assert (gpu.radii > 0).ne(cpu.radii > 0).float().mean() <= 0.02, "culling differs"
    gap = (gpu.radii - cpu.radii)[both].abs()
    assert gap.numel() == 0 or gap.max() <= 1, "radii differ beyond rounding"


def _gradients(scene: dict, cams, k, width: int, height: int, backend: str) -> list[torch.Tensor]:
    device = "cuda" if backend == "gsplat" else "cpu"
    leaves = [t.detach().to(device).requires_grad_() for t in scene.values()]
    out = rasterize(*leaves, cams.to(device), k.to(device), width, height, backend=backend)
    g = torch.Generator().manual_seed(0)
    weights = [
        torch.rand(t.shape, generator=g).to(device) - 0.25 for t in (out.features, out.depth, out.alpha)
    ]
    loss = sum((t * w).sum() for t, w in zip((out.features, out.depth, out.alpha), weights, strict=True))
    return [grad.cpu() for grad in torch.autograd.grad(loss, leaves)]


def _assert_gradients_match(scene: dict, cams, k, width: int, height: int) -> None:
    gpu = _gradients(scene, cams, k, width, height, "gsplat")
    cpu = _gradients(scene, cams, k, width, height, _cpu_backend())
    for name, a, b in zip(scene, gpu, cpu, strict=True):
        assert torch.isfinite(a).all(), name
        scale = b.abs().max().item()
        torch.testing.assert_close(a, b, rtol=0, atol=GRAD_RTOL * scale, msg=name)


@pytest.mark.parametrize(("features", "seed"), [(1, 0), (3, 1), (16, 2), (26, 3)])
def test_gsplat_matches_the_cpu_kernel_on_random_scenes(features, seed):
    scene = _scene(300, seed, features=features, dtype=F32)
    scene["opacities"] = 0.3 + 0.7 * scene["opacities"]  # dense: pixels stop early
    cams, k = _cameras(3, F32), _intrinsics(3, 40, 30, 35.0, F32)
    gpu = _render(scene, cams, k, 40, 30, "gsplat")
    assert gpu.features.shape == (3, 30, 40, features) and gpu.features.is_cuda
    cpu = _render(scene, cams, k, 40, 30, _cpu_backend())
    assert cpu.alpha.max() > 0.99  # opaque somewhere: early stopping is exercised
    _assert_outputs_match(gpu, cpu)
    _assert_gradients_match(scene, cams, k, 40, 30)


def test_gsplat_centres_per_camera_equal_one_render_per_camera():
    scene = _scene(120, 4, dtype=F32)
    cams, k = _cameras(3, F32), _intrinsics(3, 36, 24, 30.0, F32)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.1, 0.2], [-0.4, 0.2, 0.5]])
    per_camera = dict(scene, means=scene["means"][None] + shift[:, None])  # (C, N, 3)
    together = _render(per_camera, cams, k, 36, 24, "gsplat")
    for c in range(3):
        one = _render(
            dict(scene, means=per_camera["means"][c]), cams[c : c + 1], k[c : c + 1], 36, 24, "gsplat"
        )
        for name in ("features", "depth", "alpha", "radii"):
            torch.testing.assert_close(
                getattr(together, name)[c : c + 1], getattr(one, name), atol=1e-6, rtol=0, msg=name
            )
    _assert_outputs_match(together, _render(per_camera, cams, k, 36, 24, _cpu_backend()))
    _assert_gradients_match(per_camera, cams, k, 36, 24)


def test_gsplat_hard_cases_match_the_cpu_kernel():
    """At, on and behind the camera plane, just past the near plane, a zero quaternion (identity), 1e6
    scales (clamped to MAX_SCALE as the CPU paths do), 1e-9 and 1e-4 scales, a needle, 1e2 scales."""
    scene = _hard_scene(F32)
    extra = {
        "means": torch.tensor([[0.05, -0.05, 2.0], [0.0, 0.05, 4.0]]),
        "quats": torch.tensor([[0.7, 0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 0.0]]),
        "scales": torch.tensor([[1e-4, 1e-4, 1e-4], [1e2, 1e2, 1e2]]),
        "opacities": torch.tensor([0.95, 0.5]),
        "features": torch.tensor([[1.0, 0.0, 0.5], [0.2, 0.9, 0.1]]),
    }
    scene = {key: torch.cat([scene[key], extra[key]]) for key in scene}
    cams, k = _cameras(2, F32), _intrinsics(2, 24, 16, 20.0, F32)
    gpu = _render(scene, cams, k, 24, 16, "gsplat")
    for t in (gpu.features, gpu.depth, gpu.alpha):
        assert torch.isfinite(t).all()
    assert gpu.radii[:, [0, 1, 2, 8, 9]].eq(0).all()  # at, on, behind the camera plane; off-screen
    _assert_outputs_match(gpu, _render(scene, cams, k, 24, 16, _cpu_backend()))
    _assert_gradients_match(scene, cams, k, 24, 16)


def test_gsplat_a_hundred_thousand_gaussians_on_one_pixel():
    n = 100_000
    g = torch.Generator().manual_seed(9)
    scene = {
        "means": torch.tensor([[0.0, 0.0, 2.0]]) + torch.rand(n, 3, generator=g) * 1e-3,
        "quats": torch.randn(n, 4, generator=g),
        "scales": 0.01 + 0.02 * torch.rand(n, 3, generator=g),
        "opacities": torch.rand(n, generator=g) * 0.05,  # faint: thousands before T <= 1e-4
        "features": torch.rand(n, 3, generator=g),
    }
    cams, k = _cameras(1, F32), _intrinsics(1, 4, 4, 10.0, F32)
    gpu = _render(scene, cams, k, 4, 4, "gsplat")
    assert gpu.alpha[0, 1:3, 1:3].min() > 0.999
    _assert_outputs_match(gpu, _render(scene, cams, k, 4, 4, _cpu_backend()))


def test_gsplat_empty_scenes_and_one_pixel_images():
    scene = _scene(20, 7, dtype=F32)
    behind = dict(scene, means=scene["means"] * torch.tensor([1.0, 1.0, -1.0]))
    out = _render(behind, _cameras(2, F32), _intrinsics(2, 12, 10, 10.0, F32), 12, 10, "gsplat")
    assert out.features.abs().max() == 0 and out.alpha.max() == 0 and out.depth.max() == 0
    assert out.radii.eq(0).all()
    cams, k = _cameras(2, F32), _intrinsics(2, 1, 1, 1.0, F32)
    one = _render(scene, cams, k, 1, 1, "gsplat")
    assert one.features.shape == (2, 1, 1, 3)
    _assert_outputs_match(one, _render(scene, cams, k, 1, 1, _cpu_backend()))


def test_auto_picks_gsplat_for_float32_cuda_tensors_only():
    cuda = torch.device("cuda")
    assert resolve_backend("auto", cuda, F32) == "gsplat"
    assert resolve_backend("auto", cuda, torch.float64) == "torch"
    with pytest.raises(ValueError, match="float32 only"):
        resolve_backend("gsplat", cuda, torch.float64)
