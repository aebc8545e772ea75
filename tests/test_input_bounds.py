"""Memory bounded by the input, and assets, paths and trajectories refused by name (issue 53, items 3,
8 and 9): what a header claims is checked against the file before anything is allocated; compressed
assets are refused; a glTF refers only to what exists in its own folder; trajectory, path and rig
files are regular files of at most 1 MiB whose times fit int64 microseconds."""

from __future__ import annotations

import bz2
import json
import os
import re
import struct
import subprocess
import sys
import threading
import tracemalloc
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from phigenesis.export.ply import REQUIRED, PlyError, read_ply, scene_from_ply
from phigenesis.infer.asset_files import MAX_TEXTURE_PIXELS, check_mesh_file
from phigenesis.infer.insert import (
    MAX_ASSET_GAUSSIANS,
    AssetError,
    AssetPlacement,
    Keyframe,
    load_asset,
    load_path_file,
    parse_keyframe,
)
from phigenesis.infer.rigs import RigError, load_rig_file
from phigenesis.rollout.runner import TrajectoryError, TrajectoryFrame, load_trajectory_file

#: A crafted small input may make a reader allocate at most this much (tracemalloc peak, bytes).
SMALL_PEAK = 32 << 20
#: The recorded rig a trajectory file is read against: frame at 1000 us, two cameras.
RIG = TrajectoryFrame(1000, np.eye(4), np.stack([np.eye(4)] * 2), np.array([1000, 1010]))
EYE = np.eye(4).tolist()


def traced_peak(fn: Callable[[], Any]) -> tuple[BaseException | None, int]:
    """(the exception ``fn`` raised or None, the peak bytes Python and numpy allocated meanwhile)."""
    tracemalloc.start()
    try:
        fn()
        error = None
    except BaseException as e:  # returned for the test to judge
        error = e
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return error, peak


def gaussian_ply(path: Path, count: int | str, data_bytes: int = 14_000, before: str = "") -> Path:
    """A 3DGS PLY header claiming ``count`` vertices, followed by ``data_bytes`` zero bytes."""
    header = f"ply\nformat binary_little_endian 1.0\n{before}element vertex {count}\n"
    header += "".join(f"property float {p}\n" for p in REQUIRED) + "end_header\n"
    path.write_bytes(header.encode() + bytes(data_bytes))
    return path


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` RGB pixels (its data is empty)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    )


def png_bomb(side: int) -> bytes:
    """A real, decodable ``side`` x ``side`` black RGB PNG: a few hundred KB that decode to side^2 x 3
    bytes (built row by row, so building it takes no memory)."""
    packer = zlib.compressobj(9)
    row = bytes(1 + 3 * side)
    idat = b"".join(packer.compress(row) for _ in range(side)) + packer.flush()
    header = png_header(side, side)
    return (
        header[: header.index(b"IDAT") - 4]
        + struct.pack(">I", len(idat))
        + b"IDAT"
        + idat
        + (struct.pack(">I", zlib.crc32(b"IDAT" + idat)) + header[header.index(b"IEND") - 4 :])
    )


def textured_quad() -> trimesh.Trimesh:
    """A 2 x 1 m quad with UVs and a 2 x 1 pixel texture (red left, green right)."""
    from PIL import Image

    vertices = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    image = Image.fromarray(np.array([[[255, 0, 0], [0, 255, 0]]], np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], visual=visual, process=False)


def gltf_folder(folder: Path, edit: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """The textured quad as ``folder/model.gltf`` with its buffers beside it, its JSON edited."""
    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(textured_quad()))
    folder.mkdir(parents=True, exist_ok=True)
    doc = json.loads(files.pop("model.gltf"))
    for name, data in files.items():
        (folder / name).write_bytes(data)
    if edit is not None:
        edit(doc)
    (folder / "model.gltf").write_text(json.dumps(doc))
    return folder / "model.gltf"


def returns_without_blocking(fn: Callable[[], Any], fifo: Path) -> BaseException | None:
    """The exception ``fn`` raises (None if none); fails the test if ``fn`` blocks on ``fifo``
    (after unblocking it by opening the FIFO for writing)."""
    outcome: dict[str, BaseException] = {}

    def run() -> None:
        try:
            fn()
        except BaseException as e:  # returned for the test to judge
            outcome["error"] = e

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(20)
    if thread.is_alive():
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(20)
        pytest.fail(f"reading {fifo} blocked until a writer opened it")
    return outcome.get("error")


# --------------------------------------------------------------------------------------------
# 3DGS PLY assets: claimed rows against the file's size


def test_a_14_kb_gaussian_ply_claiming_3e7_vertices_is_refused_before_allocating(tmp_path: Path) -> None:
    path = gaussian_ply(tmp_path / "big.ply", 3 * 10**7)
    error, peak = traced_peak(lambda: load_asset(path, class_name="car"))
    assert isinstance(error, AssetError)
    assert str(error).startswith(f"{path}: not a readable 3D Gaussian Splatting PLY: element vertex claims ")
    assert f"more than the {MAX_ASSET_GAUSSIANS}" in str(error)
    assert peak < SMALL_PEAK


@pytest.mark.parametrize("count", [10**7, 10**9])
def test_a_ply_claiming_more_rows_than_its_bytes_names_the_element_and_both_sizes(
    tmp_path: Path, count: int
) -> None:
    path = gaussian_ply(tmp_path / "claims.ply", count)
    error, peak = traced_peak(lambda: read_ply(path))
    assert isinstance(error, PlyError)
    row = 4 * len(REQUIRED)
    assert str(error) == (
        f"{path}: truncated: element 'vertex' claims {count} rows of {row} bytes ({count * row} bytes) "
        "but only 14000 bytes follow"
    )
    assert peak < SMALL_PEAK
    with pytest.raises(AssetError, match="truncated: element 'vertex' claims 10000000 rows"):
        load_asset(gaussian_ply(tmp_path / "at_max.ply", MAX_ASSET_GAUSSIANS), class_name="car")


@pytest.mark.parametrize("count", ["1" + "0" * 30, "9" * 5000])
def test_an_absurd_row_count_is_refused_without_parsing_it_to_the_end(tmp_path: Path, count: str) -> None:
    path = gaussian_ply(tmp_path / "absurd.ply", count)
    error, peak = traced_peak(lambda: scene_from_ply(path))
    assert isinstance(error, PlyError)
    assert str(error).startswith(f"{path}: element 'vertex' claims {count[:8]}")
    assert str(error).endswith("rows, more than 1000000000000000")
    assert peak < SMALL_PEAK


def test_an_element_before_the_vertices_that_claims_too_much_is_named(tmp_path: Path) -> None:
    path = gaussian_ply(
        tmp_path / "camera.ply", 2, 2 * 56, before="element camera 5000000\nproperty double fx\n"
    )
    with pytest.raises(PlyError, match=r"element 'camera' claims 5000000 rows of 8 bytes \(40000000 bytes\)"):
        read_ply(path)


def test_a_time_origin_beyond_int64_microseconds_is_refused(tmp_path: Path) -> None:
    path = gaussian_ply(tmp_path / "origin.ply", 1, 56)
    text = path.read_bytes().replace(
        b"element", b"comment time_origin_micros 99999999999999999999\nelement", 1
    )
    path.write_bytes(text)
    with pytest.raises(
        PlyError, match=r"origin\.ply: comment time_origin_micros 99999999999999999999 is beyond"
    ):
        scene_from_ply(path)


# --------------------------------------------------------------------------------------------
# Mesh assets: compressed files, binary STL and PLY meshes


def test_a_compressed_mesh_is_refused_without_unpacking_it(tmp_path: Path) -> None:
    stl = bz2.BZ2Compressor(9)
    triangles = 200_000  # 10 MB unpacked; the 785 bytes unpack to 3.4 GB
    packed = stl.compress(bytes(80) + struct.pack("<I", triangles))
    packed += b"".join(stl.compress(bytes(50 * 10_000)) for _ in range(triangles // 10_000)) + stl.flush()
    path = tmp_path / "bomb.stl.bz2"
    path.write_bytes(packed)
    assert path.stat().st_size < 2000
    error, peak = traced_peak(lambda: load_asset(path, class_name="car"))
    assert isinstance(error, AssetError)
    assert str(error).startswith(f"{path}: a compressed file (bzip2); unpack it first")
    assert peak < SMALL_PEAK
    disguised = tmp_path / "disguised.stl"  # gzip data under a mesh suffix: known by its first bytes
    disguised.write_bytes(zlib.compressobj(wbits=31).compress(b"solid x\n") + b"\0" * 20)
    with pytest.raises(AssetError, match=r"disguised\.stl: a compressed file \(gzip\)"):
        load_asset(disguised, class_name="car")


def test_an_asset_that_is_a_fifo_or_a_device_is_refused_without_reading(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.obj"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero"), tmp_path):
        with pytest.raises(AssetError, match=rf"^{path}: not a regular file; an asset is a file"):
            load_asset(path, class_name="car")


def test_a_binary_stl_whose_triangle_count_disagrees_with_its_size_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "claims.stl"
    path.write_bytes(bytes(80) + struct.pack("<I", 10**9) + bytes(100))
    claims = "binary STL header claims 1000000000 triangles (50000000084 bytes) but the file holds 184 bytes"
    with pytest.raises(AssetError, match=re.escape(f"{path}: {claims}")):
        load_asset(path, class_name="car")
    two = tmp_path / "two.stl"
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]]).export(two)
    check_mesh_file(two, max_faces=2)
    with pytest.raises(AssetError, match=r"two\.stl: 2 triangles, more than 1; decimate"):
        check_mesh_file(two, max_faces=1)


def test_a_binary_ply_mesh_claiming_more_faces_than_its_bytes_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "mesh.ply"
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1000000000\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertices = struct.pack(">9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
    path.write_bytes(header.encode() + vertices + struct.pack(">B3i", 3, 0, 1, 2))
    error, peak = traced_peak(lambda: load_asset(path, class_name="car"))
    assert isinstance(error, AssetError)
    assert str(error) == (
        f"{path}: truncated: element 'face' claims 1000000000 rows of 13 bytes (13000000000 bytes) "
        "but only 13 bytes follow"
    )
    assert peak < SMALL_PEAK


# --------------------------------------------------------------------------------------------
# glTF: references that exist, inside the asset's folder


def test_a_gltf_quad_with_uvs_and_a_colour_but_no_texture_takes_the_colour(tmp_path: Path) -> None:
    def untextured(doc: dict[str, Any]) -> None:
        doc.pop("textures"), doc.pop("images")
        pbr = doc["materials"][0]["pbrMetallicRoughness"]
        pbr.pop("baseColorTexture")
        pbr["baseColorFactor"] = [1.0, 0.0, 0.0, 1.0]

    asset = load_asset(gltf_folder(tmp_path / "a", untextured), class_name="car", spacing_m=0.1)
    np.testing.assert_array_equal(asset.gaussians.colors.numpy(), np.tile([1.0, 0.0, 0.0], (200, 1)))


#: Marks a key to delete in :func:`set_in`.
DELETE = object()


def set_in(doc: Any, keys: tuple[Any, ...], value: Any) -> None:
    """Sets ``doc[k0][k1]...`` to ``value`` (deletes it for DELETE)."""
    for key in keys[:-1]:
        doc = doc[key]
    if value is DELETE:
        del doc[keys[-1]]
    else:
        doc[keys[-1]] = value


@pytest.mark.parametrize(
    ("keys", "value", "message"),
    [
        (("textures", 0, "source"), 5,
         "textures[0].source: refers to images[5], which does not exist (the file has 1)"),
        (("images",), DELETE,
         "textures[0].source: refers to images[0], which does not exist (the file has 0)"),
        (("materials", 0, "pbrMetallicRoughness", "baseColorTexture", "index"), 3,
         "materials[0].pbrMetallicRoughness.baseColorTexture.index: refers to textures[3]"),
        (("meshes", 0, "primitives", 0, "indices"), 70,
         "meshes[0].primitives[0].indices: refers to accessors[70]"),
        (("scenes", 0, "nodes"), [7], "scenes[0].nodes: refers to nodes[7]"),
        (("nodes", 0, "children"), [0], "nodes[0].children: nodes[0] is its own child"),
        (("accessors", 1, "count"), 10**12, "accessors[1]: claims 1000000000000 elements of 12 bytes"),
        (("bufferViews", 1, "byteLength"), 10**9,
         "bufferViews[1]: bytes 0 to 1000000000 lie outside buffers[1] (48 bytes)"),
        (("buffers", 1, "byteLength"), 10**9,
         "buffers[1]: byteLength 1000000000 claims more than the 48 bytes its file 'gltf_buffer_1.bin' "
         "holds"),
    ],
)  # fmt: skip
def test_a_gltf_referring_to_what_does_not_exist_is_refused_naming_the_record(
    tmp_path: Path, keys: tuple[Any, ...], value: Any, message: str
) -> None:
    path = gltf_folder(tmp_path / "a", lambda doc: set_in(doc, keys, value))
    with pytest.raises(AssetError, match="^" + re.escape(f"{path}: {message}")):
        load_asset(path, class_name="car", spacing_m=0.1)


def test_a_bufferless_accessor_cannot_claim_more_than_the_buffers(tmp_path: Path) -> None:
    def zeros(doc: dict[str, Any]) -> None:
        doc["accessors"][1].pop("bufferView")
        doc["accessors"][1]["count"] = 10**8

    path = gltf_folder(tmp_path / "a", zeros)
    error, peak = traced_peak(lambda: load_asset(path, class_name="car"))
    assert isinstance(error, AssetError)
    assert (
        "accessors[1]: has no bufferView and claims 100000000 x 12 bytes, more than the file's buffers"
        in str(error)
    )
    assert peak < SMALL_PEAK


@pytest.mark.parametrize("uri", ["/etc/gltf_buffer_1.bin", "file:///etc/gltf_buffer_1.bin"])
def test_an_absolute_buffer_uri_is_refused_not_read_from_the_assets_folder(tmp_path: Path, uri: str) -> None:
    path = gltf_folder(tmp_path / "a", lambda d: d["buffers"][1].update(uri=uri))
    assert (path.parent / "gltf_buffer_1.bin").is_file()  # the same-named file it used to read
    with pytest.raises(AssetError, match=rf"^{path}: buffers\[1\]\.uri '{uri}': an absolute path or URI"):
        load_asset(path, class_name="car")


def test_a_buffer_symlinked_out_of_the_assets_folder_is_refused(tmp_path: Path) -> None:
    path = gltf_folder(tmp_path / "a")
    outside = tmp_path / "outside.bin"
    (path.parent / "gltf_buffer_1.bin").rename(outside)
    (path.parent / "gltf_buffer_1.bin").symlink_to(outside)
    with pytest.raises(
        AssetError, match=r"buffers\[1\]\.uri 'gltf_buffer_1\.bin': leaves the asset's folder"
    ):
        load_asset(path, class_name="car")


def test_a_missing_or_oversized_texture_image_is_refused_naming_the_image(tmp_path: Path) -> None:
    def to_file(doc: dict[str, Any]) -> None:
        doc["images"] = [{"uri": "texture.png"}]

    missing = gltf_folder(tmp_path / "a", to_file)
    with pytest.raises(
        AssetError, match=r"images\[0\]\.uri 'texture\.png': no such file in the asset's folder"
    ):
        load_asset(missing, class_name="car")
    (missing.parent / "texture.png").write_bytes(png_header(100_000, 100_000))
    with pytest.raises(
        AssetError,
        match=rf"images\[0\]: .*pixels.*the most a texture may have is {MAX_TEXTURE_PIXELS} pixels",
    ):
        load_asset(missing, class_name="car")
    (missing.parent / "texture.png").write_bytes(png_header(5000, 5000))
    with pytest.raises(
        AssetError, match=r"images\[0\]: 5000 x 5000 pixels, more than the 16777216 a texture"
    ):
        load_asset(missing, class_name="car")
    (missing.parent / "texture.png").write_bytes(b"not a PNG at all")
    with pytest.raises(AssetError, match=r"images\[0\]: not an image Pillow can read$"):
        load_asset(missing, class_name="car")
    (missing.parent / "texture.png").write_bytes(png_header(4, 4))  # a header, then no pixels
    with pytest.raises(AssetError, match=r"model\.gltf: a texture of 4 x 4 pixels does not decode"):
        load_asset(missing, class_name="car")


def test_a_glb_whose_header_or_chunks_claim_more_than_the_file_is_refused(tmp_path: Path) -> None:
    glb = trimesh.Scene(textured_quad()).export(file_type="glb")
    path = tmp_path / "quad.glb"
    path.write_bytes(glb[:8] + struct.pack("<I", 10**9) + glb[12:])
    with pytest.raises(
        AssetError, match=rf"quad\.glb: the GLB header claims 1000000000 bytes but the file holds {len(glb)}"
    ):
        load_asset(path, class_name="car")
    json_length = struct.unpack("<I", glb[12:16])[0]
    bin_at = 20 + json_length
    path.write_bytes(glb[:bin_at] + struct.pack("<I", 10**9) + glb[bin_at + 4 :])
    with pytest.raises(AssetError, match=rf"quad\.glb: GLB chunk 1 at byte {bin_at} claims 1000000000 bytes"):
        load_asset(path, class_name="car")
    path.write_bytes(glb)
    assert len(load_asset(path, class_name="car", spacing_m=0.1).gaussians) == 200


# --------------------------------------------------------------------------------------------
# OBJ: its MTL file and textures come from its own folder


def test_an_obj_material_library_outside_its_folder_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "asset"
    folder.mkdir()
    (folder / "shared.mtl").write_text("newmtl red\nKd 1 0 0\n")  # a same-named file in the folder
    obj = "mtllib {}\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    for name, why in [
        ("/etc/shared.mtl", "an absolute path or URI"),
        ("../shared.mtl", "leaves the asset's folder"),
    ]:
        (folder / "tri.obj").write_text(obj.format(name))
        with pytest.raises(AssetError, match=rf"tri\.obj: refers to '{name}': {why}"):
            load_asset(folder / "tri.obj", class_name="car")
    (folder / "tri.obj").write_text(obj.format("shared.mtl"))
    np.testing.assert_array_equal(
        load_asset(folder / "tri.obj", class_name="car").gaussians.colors[0], [1, 0, 0]
    )


def test_an_obj_texture_of_too_many_pixels_is_refused_before_decoding(tmp_path: Path) -> None:
    (tmp_path / "t.mtl").write_text("newmtl t\nmap_Kd bomb.png\n")
    (tmp_path / "bomb.png").write_bytes(png_header(20_000, 20_000))
    (tmp_path / "t.obj").write_text(
        "mtllib t.mtl\nusemtl t\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    )
    with pytest.raises(AssetError, match=r"t\.obj: image 'bomb\.png': .*pixels"):
        load_asset(tmp_path / "t.obj", class_name="car")


# --------------------------------------------------------------------------------------------
# Trajectory, path and rig files


def write_trajectory(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc))
    return path


def test_a_trajectory_that_is_not_a_small_regular_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match=r"^/dev/zero: not a regular file; a trajectory file must be"):
        load_trajectory_file("/dev/zero", 1, RIG, 1000)
    with pytest.raises(TrajectoryError, match=rf"^{tmp_path}: a folder"):
        load_trajectory_file(tmp_path, 1, RIG, 1000)
    big = tmp_path / "big.json"
    big.write_text(" " * (1 << 20) + "{}")
    with pytest.raises(TrajectoryError, match=r"big\.json: larger than 1048576 bytes"):
        load_trajectory_file(big, 1, RIG, 1000)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    error = returns_without_blocking(lambda: load_trajectory_file(fifo, 1, RIG, 1000), fifo)
    assert isinstance(error, TrajectoryError) and str(error).startswith(f"{fifo}: not a regular file")


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"frames": [{"timestamp_micros": 2**63, "world_from_ego": EYE}]},
         r"frames\[0\]\.timestamp_micros: 9223372036854775808 is not below 4611686018427387904"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[str(x) for x in r] for r in EYE]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is '1\.0', not a finite number"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": EYE, "speed": 3}]},
         r"frames\[0\]: unknown key 'speed'; the keys are timestamp_micros, world_from_ego"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": EYE}], "fps": 10},
         r"unknown key 'fps'; the keys are frames"),
        ({"frames": [{"timestamp_micros": "5000", "world_from_ego": EYE}]},
         r"frames\[0\]\.timestamp_micros: '5000' is not an integer"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[True, 0, 0, 0], *EYE[1:]]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is True, not a finite number"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[10**400, 0, 0, 0], *EYE[1:]]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is 1000"),
    ],
)  # fmt: skip
def test_a_trajectory_entry_is_refused_naming_the_file_the_entry_and_the_key(
    tmp_path: Path, doc: Any, message: str
) -> None:
    path = write_trajectory(tmp_path / "t.json", doc)
    with pytest.raises(TrajectoryError, match=rf"^{path}: {message}"):
        load_trajectory_file(path, 1, RIG, 1000)


def test_a_deeply_nested_trajectory_is_an_error_not_a_crash(tmp_path: Path) -> None:
    path = tmp_path / "deep.json"
    path.write_text("[" * 200_000)
    with pytest.raises(TrajectoryError, match=r"deep\.json: not a JSON trajectory \(RecursionError"):
        load_trajectory_file(path, 1, RIG, 1000)


def test_a_good_trajectory_loads_with_the_rigs_camera_offsets(tmp_path: Path) -> None:
    pose = np.eye(4)
    pose[0, 3] = 2.5
    doc = {"frames": [{"timestamp_micros": 5000, "world_from_ego": pose.tolist()}]}
    (frame,) = load_trajectory_file(write_trajectory(tmp_path / "t.json", doc), 1, RIG, 1000)
    assert frame.timestamp_micros == 5000
    np.testing.assert_array_equal(frame.camera_timestamp_micros, [5000, 5010])
    np.testing.assert_array_equal(frame.world_from_ego, pose)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[{"t_s": 1e300, "xyz": [0, 0, 0]}]', r"keyframe 0: t_s 1e\+300 s is beyond \+-1e\+06 s"),
        ('[{"t_s": -1000001, "xyz": [0, 0, 0]}]', r"keyframe 0: t_s -1000001\.0 s is beyond"),
        ('[{"timestamp_micros": 9223372036854775807, "xyz": [0, 0, 0]}]',
         r"keyframe 0: timestamp_micros must be an integer in \[0, 4611686018427387904\)"),
        ('[{"t_s": 0, "xyz": [1e999, 0, 0]}]', r"keyframe 0: xyz must be a finite number"),
        ('[{"t_s": 0, "world_from_asset": [["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]',
         r"keyframe 0: world_from_asset \[0\]\[0\] is '1', not a finite number"),
    ],
)  # fmt: skip
def test_a_path_keyframe_beyond_int64_microseconds_is_refused(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "path.json"
    path.write_text(text)
    with pytest.raises(AssetError, match=rf"^{path}: {message}"):
        AssetPlacement.from_keyframes(load_path_file(path), 1_000_000)


def test_a_pose_or_keyframe_time_beyond_int64_microseconds_is_refused() -> None:
    with pytest.raises(AssetError, match=r"pose '1,2,3@1e300': t_s 1e\+300 s is beyond"):
        parse_keyframe("1,2,3@1e300")
    far = Keyframe(tuple(tuple(r) for r in EYE), t_s=1e300)
    with pytest.raises(AssetError, match=r"placement: keyframe 0: t_s 1e\+300 s is beyond"):
        AssetPlacement.from_keyframes([far], 0)
    late = Keyframe(tuple(tuple(r) for r in EYE), t_s=1.0)
    with pytest.raises(AssetError, match=r"placement: keyframe 0: time 4611686018428387904 us is beyond"):
        AssetPlacement.from_keyframes([late], 2**62)
    placed = AssetPlacement.from_keyframes(
        [parse_keyframe("1,2,3@1e6"), parse_keyframe("1,2,3@-1e6")][::-1], 0
    )
    np.testing.assert_array_equal(placed.times_micros, [-(10**12), 10**12])


def test_a_rig_file_that_is_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    error = returns_without_blocking(lambda: load_rig_file(fifo), fifo)
    assert isinstance(error, RigError) and str(error).startswith(f"{fifo}: not a regular file")


def test_a_path_file_that_is_not_a_regular_file_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    error = returns_without_blocking(lambda: load_path_file(fifo), fifo)
    assert isinstance(error, AssetError) and str(error).startswith(f"{fifo}: not a regular file")
    with pytest.raises(AssetError, match=r"^/dev/zero: not a regular file"):
        load_path_file("/dev/zero")


# --------------------------------------------------------------------------------------------
# Peak memory of every crafted small input, measured in a process of its own

_MEASURE = """
import json, sys
import numpy as np
from phigenesis.errors import PhiGenesisError
from phigenesis.rollout.runner import TrajectoryFrame, load_trajectory_file
from phigenesis.infer.insert import load_asset
rig = TrajectoryFrame(1000, np.eye(4), np.stack([np.eye(4)] * 2), np.array([1000, 1010]))
outcomes = {}
for path in sys.argv[1:]:
    try:
        if path.endswith(".json") or path == "/dev/zero":
            load_trajectory_file(path, 1, rig, 1000)
        else:
            load_asset(path, class_name="car")
        outcomes[path] = "loaded"
    except PhiGenesisError as e:
        outcomes[path] = "refused: " + str(e)
    except BaseException as e:
        outcomes[path] = f"{type(e).__name__}: {e}"
# VmHWM, not ru_maxrss: a process exec'd from pytest keeps pytest's peak in ru_maxrss
peak_kb = int(open("/proc/self/status").read().split("VmHWM:")[1].split()[0])
print(json.dumps({"outcomes": outcomes, "max_rss_kb": peak_kb}))
"""


def test_every_crafted_small_input_is_refused_under_500_mb(tmp_path: Path) -> None:
    """The issue's inputs and their kin, each refused with an error naming it, in one process whose
    peak RSS (numpy and torch imported, about 270 MB of it) stays under 500 MB."""
    bomb = bz2.BZ2Compressor(9)
    stl_bomb = tmp_path / "bomb.stl.bz2"
    stl_bomb.write_bytes(
        bomb.compress(bytes(80) + struct.pack("<I", 10**6)) + bomb.compress(bytes(50 * 10**6)) + bomb.flush()
    )
    textured = gltf_folder(tmp_path / "textured", lambda d: d.update(images=[{"uri": "bomb.png"}]))
    (textured.parent / "bomb.png").write_bytes(png_bomb(9000))  # decodes to 243 MB
    zeros = gltf_folder(
        tmp_path / "zeros",
        lambda d: (d["accessors"][1].pop("bufferView"), d["accessors"][1].update(count=10**9)),
    )
    inputs = [
        gaussian_ply(tmp_path / "a.ply", 3 * 10**7),
        gaussian_ply(tmp_path / "b.ply", 10**9),
        gaussian_ply(tmp_path / "c.ply", 10**30),
        stl_bomb,
        textured,
        zeros,
        write_trajectory(
            tmp_path / "t.json", {"frames": [{"timestamp_micros": 2**63, "world_from_ego": EYE}]}
        ),
        Path("/dev/zero"),
    ]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    run = subprocess.run(
        [sys.executable, "-c", _MEASURE, *map(str, inputs)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout.splitlines()[-1])
    for path in inputs:
        outcome = report["outcomes"][str(path)]
        assert outcome.startswith(f"refused: {path}: "), outcome
    assert report["max_rss_kb"] < 500 * 1024, report
