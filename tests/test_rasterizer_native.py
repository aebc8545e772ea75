"""The native CPU rasterizer against the per-pixel reference (values) and the tiled PyTorch path
(gradients), on random scenes and hard cases; its determinism; and the fallback where it cannot be built."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

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


def test_fallback_where_the_extension_cannot_be_built(tmp_path):
    """On a machine with no working compiler the suite's renders still pass through the PyTorch path,
    and the build failure is one warning line."""
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
    warnings = [line for line in lines if line.startswith("WARNING")]
    assert len(warnings) == 1, result.stdout
    assert "native CPU rasterizer not available" in warnings[0] and "PyTorch tiled path" in warnings[0]
    assert "full log:" in warnings[0] and any((tmp_path / "native").glob("*/build-error.log"))
    chosen = [line for line in lines if "rasterize: backend" in line]
    assert len(chosen) == 1 and "'torch'" in chosen[0], result.stdout
    diff = float(next(line for line in lines if line.startswith("MAXDIFF")).split()[1])
    assert diff < 1e-10
    assert any(line.startswith("CPU-REFUSED") and "not available" in line for line in lines)
