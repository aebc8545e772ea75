"""Tests for the 3D Gaussian Splatting PLY export: layout, encodings, time, round trip and errors."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.testing import assert_allclose, assert_array_equal

from phigenesis.export import ply
from phigenesis.export.ply import read_ply, read_ply_comments, scene_from_ply, write_ply
from phigenesis.models.gaussians import GaussianScene

#: SH band-0 constant, 1 / (2 sqrt(pi)), written out independently of the module.
C0 = 0.5 / np.sqrt(np.pi)

#: The Inria 3DGS vertex layout for SH degree 3, spelled out by hand.
INRIA_DEGREE_3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)
EXTRAS = ["semantic_class", "vx", "vy", "vz", "dynamic", "time_s"]


def random_scene(
    n: int = 300, k: int = 19, seed: int = 0, origin: int = 1_700_000_000_123_456
) -> GaussianScene:
    """A scene with random everything; about half the Gaussians are dynamic (the rest have zero velocity)."""
    g = torch.Generator().manual_seed(seed)
    dynamic = torch.rand(n, generator=g) < 0.5
    velocity = torch.randn(n, 3, generator=g) * 5.0 * dynamic[:, None]
    return GaussianScene(
        means=torch.randn(n, 3, generator=g) * 40.0,
        quats=torch.randn(n, 4, generator=g) * 3.0,  # not normalised: the writer normalises
        scales=torch.exp(torch.randn(n, 3, generator=g) * 1.5 - 2.0),
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        colors=torch.rand(n, 3, generator=g),
        semantic_logits=torch.randn(n, k, generator=g),
        velocity=velocity,
        dynamic=dynamic,
        time_s=torch.rand(n, generator=g) * 10.0,
        time_origin_micros=origin,
    )


def header_of(path: Path) -> tuple[bytes, list[str]]:
    """The raw header (through ``end_header\\n``) and its vertex property names, parsed by hand."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end]
    names = [line.split()[2] for line in header.decode().splitlines() if line.startswith("property float ")]
    return header, names


def test_round_trip_recovers_the_scene(tmp_path: Path) -> None:
    scene = random_scene()
    path = write_ply(scene, tmp_path / "scene.ply")
    back = scene_from_ply(path)

    assert len(back) == len(scene)
    assert back.time_origin_micros == scene.time_origin_micros
    assert_allclose(back.means.numpy(), scene.means.numpy(), rtol=1e-6, atol=0)
    assert_allclose(back.colors.numpy(), scene.colors.numpy(), atol=1e-6)
    assert_allclose(back.opacities.numpy(), scene.opacities.numpy(), atol=1e-6)
    assert_allclose(back.scales.numpy(), scene.scales.numpy(), rtol=1e-5)
    q = scene.quats.numpy().astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    qb = back.quats.numpy().astype(np.float64)
    sign = np.sign((q * qb).sum(axis=1, keepdims=True))  # q and -q are the same rotation
    assert_allclose(qb * sign, q, atol=1e-6)
    assert_allclose(np.linalg.norm(qb, axis=1), 1.0, atol=1e-6)
    assert_array_equal(back.velocity.numpy(), scene.velocity.numpy())
    assert_array_equal(back.dynamic.numpy(), scene.dynamic.numpy())
    assert_array_equal(back.time_s.numpy(), scene.time_s.numpy())
    assert back.semantic_logits.shape == (len(scene), 19)
    assert_array_equal(back.semantic_logits.argmax(1).numpy(), scene.semantic_logits.argmax(1).numpy())


def test_encodings_match_independent_formulas(tmp_path: Path) -> None:
    scene = random_scene(n=50, seed=3)
    props = read_ply(write_ply(scene, tmp_path / "scene.ply"))
    rgb = scene.colors.numpy().astype(np.float64)
    o = scene.opacities.numpy().astype(np.float64)
    s = scene.scales.numpy().astype(np.float64)
    q = scene.quats.numpy().astype(np.float64)
    q /= np.sqrt((q**2).sum(axis=1, keepdims=True))

    assert all(v.dtype == np.float32 for v in props.values())
    for i in range(3):
        assert_allclose(props[f"f_dc_{i}"], (rgb[:, i] - 0.5) / C0, rtol=1e-6, atol=1e-6)
        assert_allclose(props[f"scale_{i}"], np.log(s[:, i]), rtol=1e-6, atol=1e-6)
        assert_array_equal(props[f"n{'xyz'[i]}"], 0.0)
    assert_allclose(props["opacity"], np.log(o / (1.0 - o)), rtol=1e-5, atol=1e-5)
    for i in range(4):
        assert_allclose(props[f"rot_{i}"], q[:, i], atol=1e-7)
    assert_array_equal(np.stack([props[f"f_rest_{i}"] for i in range(45)]), 0.0)
    assert_array_equal(props["semantic_class"], scene.semantic_logits.numpy().argmax(1).astype(np.float32))
    assert_array_equal(props["dynamic"], scene.dynamic.numpy().astype(np.float32))


def test_clamps_keep_degenerate_values_finite(tmp_path: Path) -> None:
    scene = random_scene(n=4, seed=1)
    scene = GaussianScene(
        **{**scene.__dict__, "opacities": torch.tensor([0.0, 1.0, 0.5, 0.5]),
           "scales": torch.tensor([[0.0, 1.0, 1.0]] * 4), "quats": torch.zeros(4, 4)}
    )  # fmt: skip
    props = read_ply(write_ply(scene, tmp_path / "clamped.ply"))
    logit_max = np.log((1 - 1e-6) / 1e-6)
    assert_allclose(props["opacity"][:3], [-logit_max, logit_max, 0.0], rtol=1e-4, atol=1e-6)
    assert_allclose(props["scale_0"], np.log(1e-8), rtol=1e-6)
    assert_array_equal(props["rot_0"], 1.0)  # a zero quaternion is the identity, as in the rasterizer
    assert_array_equal(props["rot_1"], 0.0)


@pytest.mark.parametrize(("sh_degree", "extras"), [(3, True), (3, False), (0, True), (0, False)])
def test_header_property_order(tmp_path: Path, sh_degree: int, extras: bool) -> None:
    path = write_ply(random_scene(n=5), tmp_path / "s.ply", sh_degree=sh_degree, extras=extras)
    header, names = header_of(path)
    expected = INRIA_DEGREE_3 if sh_degree == 3 else [n for n in INRIA_DEGREE_3 if not n.startswith("f_rest")]
    expected = expected + (EXTRAS if extras else [])
    assert names == expected
    assert sum(n.startswith("f_rest_") for n in names) == (45 if sh_degree == 3 else 0)
    lines = header.decode().splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 5" in lines
    assert list(read_ply(path)) == expected


def test_file_size_is_header_plus_vertices(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ply, "_BLOCK_ROWS", 10)  # several blocks and a partial last one
    n = 123
    scene = random_scene(n=n)
    path = write_ply(scene, tmp_path / "s.ply")
    header, names = header_of(path)
    assert len(names) == 3 + 3 + 3 + 45 + 1 + 3 + 4 + 6
    assert path.stat().st_size == len(header) + n * 4 * len(names)
    # Decode the body by hand: row-major float32, one row of len(names) values per Gaussian.
    body = np.frombuffer(path.read_bytes()[len(header) :], dtype="<f4").reshape(n, len(names))
    assert_array_equal(body[:, :3], scene.means.numpy())
    assert_array_equal(body[:, names.index("time_s")], scene.time_s.numpy())


def test_header_comments_give_frame_origin_and_time(tmp_path: Path) -> None:
    scene = random_scene(n=3, origin=42)
    comments = read_ply_comments(write_ply(scene, tmp_path / "a.ply", t_s=2.25))
    assert any("world frame" in c and "OpenCV-free" in c for c in comments)
    assert "time_origin_micros 42" in comments
    assert "t_s 2.25" in comments
    comments = read_ply_comments(write_ply(scene, tmp_path / "b.ply"))
    assert any(c.startswith("t_s none") for c in comments)


def test_t_s_moves_dynamic_gaussians_only(tmp_path: Path) -> None:
    scene = random_scene(n=200, seed=5)
    t = 3.5
    props = read_ply(write_ply(scene, tmp_path / "t.ply", t_s=t))
    xyz = np.stack([props["x"], props["y"], props["z"]], axis=1)
    m = scene.means.numpy().astype(np.float64)
    v = scene.velocity.numpy().astype(np.float64)
    dt = t - scene.time_s.numpy().astype(np.float64)
    expected = m + v * dt[:, None]
    assert_allclose(xyz, expected, rtol=1e-5, atol=1e-4)
    dyn = scene.dynamic.numpy()
    assert dyn.any() and (~dyn).any()
    assert_array_equal(xyz[~dyn], scene.means.numpy()[~dyn])  # static: exactly where they were
    assert np.abs(xyz[dyn] - m[dyn]).max() > 1.0  # dynamic ones really moved
    assert_array_equal(props["time_s"], np.float32(t))  # centres are now at time t
    # Decoded, the scene is the same 4D scene: positions at any other time agree.
    back = scene_from_ply(tmp_path / "t.ply")
    assert_allclose(back.means_at(7.0).numpy(), scene.means_at(7.0).numpy(), rtol=1e-5, atol=1e-4)


def test_without_t_s_each_gaussian_is_at_its_own_time(tmp_path: Path) -> None:
    scene = random_scene(n=20, seed=6)
    props = read_ply(write_ply(scene, tmp_path / "own.ply"))
    assert_array_equal(props["x"], scene.means[:, 0].numpy())
    assert_array_equal(props["time_s"], scene.time_s.numpy())


def test_empty_scene_is_a_valid_ply(tmp_path: Path) -> None:
    empty = random_scene().select(torch.zeros(300, dtype=torch.bool))
    path = write_ply(empty, tmp_path / "empty.ply")
    header, names = header_of(path)
    assert path.stat().st_size == len(header)
    assert b"element vertex 0\n" in header
    props = read_ply(path)
    assert list(props) == names and all(v.shape == (0,) for v in props.values())
    back = scene_from_ply(path)
    assert len(back) == 0 and back.semantic_logits.shape == (0, 19)


def test_scene_without_semantics_writes_minus_one(tmp_path: Path) -> None:
    scene = random_scene(n=7, k=0)
    path = write_ply(scene, tmp_path / "nosem.ply")
    assert_array_equal(read_ply(path)["semantic_class"], -1.0)
    back = scene_from_ply(path)
    assert back.semantic_logits.shape == (7, 19)
    assert_array_equal(back.semantic_logits.numpy(), 0.0)


def test_without_extras_decodes_static_scene_at_export_time(tmp_path: Path) -> None:
    scene = random_scene(n=10, seed=2, origin=-5)
    back = scene_from_ply(write_ply(scene, tmp_path / "plain.ply", t_s=1.5, extras=False))
    assert back.semantic_logits.shape == (10, 0)
    assert_array_equal(back.velocity.numpy(), 0.0)
    assert not back.dynamic.any()
    assert_array_equal(back.time_s.numpy(), 1.5)
    assert back.time_origin_micros == -5


@pytest.mark.parametrize(
    ("field", "index"), [("means", (0, 1)), ("scales", (1, 2)), ("opacities", (2,)), ("means", (3, 0))]
)
def test_non_finite_values_raise_and_write_nothing(
    tmp_path: Path, field: str, index: tuple[int, ...]
) -> None:
    scene = random_scene(n=10)
    bad = {"means": scene.means.clone(), "scales": scene.scales.clone(), "opacities": scene.opacities.clone()}
    bad[field][index] = float("nan") if field != "scales" else float("inf")
    bad["means"][7, 2] = float("-inf")  # a second bad Gaussian
    scene = GaussianScene(**{**scene.__dict__, **bad})
    target = tmp_path / "bad.ply"
    target.write_bytes(b"previous contents")
    with pytest.raises(ValueError, match=r"bad\.ply.*2 of 10 Gaussians"):
        write_ply(scene, target)
    assert target.read_bytes() == b"previous contents"  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]  # no temporary file left


def test_values_too_large_for_float32_raise(tmp_path: Path) -> None:
    scene = random_scene(n=4)
    means = scene.means.double()
    means[1, 0] = 1e300
    scene = GaussianScene(**{**scene.__dict__, "means": means})
    with pytest.raises(ValueError, match="1 of 4 Gaussians"):
        write_ply(scene, tmp_path / "big.ply")
    assert not list(tmp_path.iterdir())


def test_truncated_file_raises_with_path(tmp_path: Path) -> None:
    path = write_ply(random_scene(n=30), tmp_path / "cut.ply")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(ValueError, match=r"cut\.ply.*truncated"):
        read_ply(path)
    with pytest.raises(ValueError, match=r"cut\.ply.*truncated"):
        scene_from_ply(path)


def test_trailing_bytes_raise(tmp_path: Path) -> None:
    path = write_ply(random_scene(n=3), tmp_path / "long.ply")
    path.write_bytes(path.read_bytes() + b"\0\0\0\0")
    with pytest.raises(ValueError, match=r"long\.ply.*more data"):
        read_ply(path)


def test_not_ply_ascii_and_missing_properties_raise(tmp_path: Path) -> None:
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(ValueError, match=r"junk\.ply.*not a PLY"):
        read_ply(junk)
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.ply.*not a PLY"):
        read_ply(empty)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n")
    with pytest.raises(ValueError, match=r"ascii\.ply.*'ascii'.*not supported"):
        read_ply(ascii_ply)
    no_end = tmp_path / "noend.ply"
    no_end.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n")
    with pytest.raises(ValueError, match=r"noend\.ply.*end_header"):
        read_ply(no_end)
    points = tmp_path / "points.ply"
    points.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
        b"property float x\nproperty float y\nproperty float z\nproperty float opacity\nend_header\n"
        + struct.pack("<4f", 1, 2, 3, 0)
    )
    with pytest.raises(ValueError, match=r"points\.ply.*missing.*'f_dc_0'.*'rot_3'") as info:
        scene_from_ply(points)
    assert "'x'" not in str(info.value) and "'opacity'" not in str(info.value)


def test_read_ply_handles_mixed_types_and_leading_elements(tmp_path: Path) -> None:
    """A hand-made PLY: a 2-item 'camera' element before the vertices, and non-float properties."""
    path = tmp_path / "mixed.ply"
    header = (
        b"ply\r\nformat binary_little_endian 1.0\ncomment made by hand\n"
        b"element camera 2\nproperty double fx\nproperty uchar id\n"
        b"element vertex 3\nproperty double x\nproperty uchar red\nproperty int label\nproperty float w\n"
        b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    cameras = struct.pack("<dB", 500.0, 1) + struct.pack("<dB", 600.0, 2)
    rows = [(1.5, 255, -7, 0.25), (-2.0, 0, 123456, 1.0), (1e-300, 17, 0, -3.0)]
    vertices = b"".join(struct.pack("<dBif", *row) for row in rows)
    face = struct.pack("<B3i", 3, 0, 1, 2)
    path.write_bytes(header + cameras + vertices + face)
    props = read_ply(path)
    assert list(props) == ["x", "red", "label", "w"]
    assert props["x"].dtype == np.float64 and props["red"].dtype == np.uint8
    assert props["label"].dtype == np.int32 and props["w"].dtype == np.float32
    assert_array_equal(props["x"], [1.5, -2.0, 1e-300])
    assert_array_equal(props["red"], [255, 0, 17])
    assert_array_equal(props["label"], [-7, 123456, 0])
    assert_array_equal(props["w"], [0.25, 1.0, -3.0])
    assert read_ply_comments(path) == ["made by hand"]
