"""What a mesh asset's file claims, checked against the file before a reader allocates for it, and
the files an asset refers to, read only from its own folder.

``phigenesis-render --insert`` reads meshes with trimesh (:func:`phigenesis.infer.insert.load_asset`),
whose readers allocate what a header claims. :func:`check_mesh_file` checks a file first, so that
memory stays bounded by the input:

- **Formats**: .obj, .off, .ply, .stl, .glb and .gltf. Compressed files and archives (.bz2, .gz,
  .zip, .xz, ..., also recognised by their first bytes) are refused, not unpacked: every check here
  compares what a file claims with the file's size, and a compressed file's size says nothing about
  what it unpacks to (785 bytes of bzip2 unpack to 3.4 GB); unpacking within a limit would still put
  the whole unpacked file in memory before a check of its own, and trimesh reads an archive's members
  through a resolver of its own. Unpacking is one command for the user.
- **Binary STL**: the triangle count of the header against the file's size (84 + 50 n bytes), and
  at most ``max_faces`` triangles, before trimesh reads them.
- **Binary PLY**: each element's rows against the file's size
  (:func:`phigenesis.export.ply.check_ply_size`).
- **glTF and GLB** (:func:`check_gltf`): the GLB's chunks against the file; each buffer's
  ``byteLength`` against the bytes its file, data URI or BIN chunk holds; each buffer view inside its
  buffer; each accessor inside its buffer view (one without a view, whose zeros trimesh allocates, at
  most as large as the buffers); every index (buffer, view, accessor, image, texture, material, mesh,
  node, scene) refers to one that exists and nodes form trees; images at most
  :data:`MAX_TEXTURE_PIXELS`.
- OBJ, OFF and ASCII PLY or STL are text: what trimesh makes of them is bounded by the text.

Files an asset refers to (an OBJ's MTL file and textures, a glTF's buffers and images, a PLY's
``TextureFile``) are read through :class:`AssetFolder`: relative paths inside the asset's folder
only (no absolute path, no URI scheme, no ``..`` or symlink out of it, and no fallback to a file of
the same name), regular files only, images within :data:`MAX_TEXTURE_PIXELS`. After trimesh has read
a file, :func:`check_textures` checks every texture it opened before anything decodes one.

Every refusal is an :class:`AssetError` naming the asset file, the record (``buffers[1]``,
``textures[0].source``, the referred file) and what is wrong.
"""

from __future__ import annotations

import base64
import binascii
import io
import json
import os
import re
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from PIL import Image

from phigenesis.errors import PhiGenesisError
from phigenesis.export.ply import PlyError, check_ply_size
from phigenesis.user_files import read_regular_file

#: The formats an asset file may have (by suffix).
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")
#: Most pixels of a texture (4096 x 4096; 64 MiB as RGBA bytes).
MAX_TEXTURE_PIXELS = 4096 * 4096

#: Suffixes of compressed files and archives, and what they are.
_COMPRESSED_SUFFIXES = {
    ".bz2": "bzip2", ".gz": "gzip", ".tgz": "gzip", ".xz": "xz", ".lzma": "lzma", ".zst": "zstd",
    ".zip": "zip", ".7z": "7-Zip", ".tar": "tar", ".rar": "RAR", ".3mf": "3MF (zip)", ".zae": "zip",
}  # fmt: skip
#: First bytes of compressed files, and what they are.
_COMPRESSED_MAGIC = {
    b"BZh": "bzip2", b"\x1f\x8b": "gzip", b"\xfd7zXZ\x00": "xz", b"\x28\xb5\x2f\xfd": "zstd",
    b"PK\x03\x04": "zip", b"7z\xbc\xaf\x27\x1c": "7-Zip", b"Rar!": "RAR",
}  # fmt: skip
#: Bytes of a binary STL's header and of each of its triangles.
_STL_HEADER_BYTES, _STL_TRIANGLE_BYTES = 84, 50
#: A URI scheme (``file:``, ``http:``; also a Windows drive ``C:``).
_URI_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")
#: glTF component types and their bytes; element types and their components.
_GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_GLTF_TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
#: GLB magic, version and chunk types.
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = b"glTF", 0x4E4F534A, 0x004E4942
#: Where a glTF material refers to a texture (paths of keys inside a material).
_MATERIAL_TEXTURES = (
    ("pbrMetallicRoughness", "baseColorTexture"),
    ("pbrMetallicRoughness", "metallicRoughnessTexture"),
    ("normalTexture",),
    ("occlusionTexture",),
    ("emissiveTexture",),
)


class AssetError(PhiGenesisError, ValueError):
    """An asset, pose or path that cannot be used: the message names the file (or the pose text),
    the keyframe and what is wrong."""


def check_mesh_file(path: Path, max_faces: int) -> None:
    """Checks a mesh asset file before trimesh reads it (see the module docstring): its format, and
    what its header claims against its size. Raises :class:`AssetError` naming the file."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(_STL_HEADER_BYTES)
    name = path.name.lower()
    packed = next((v for k, v in _COMPRESSED_SUFFIXES.items() if name.endswith(k)), None)
    packed = packed or next((v for k, v in _COMPRESSED_MAGIC.items() if head.startswith(k)), None)
    if packed is not None:
        raise AssetError(
            f"{path}: a compressed file ({packed}); unpack it first: assets are read uncompressed, so "
            "that what a file claims can be checked against its size"
        )
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise AssetError(f"{path}: not an asset format; assets are {' '.join(MESH_SUFFIXES)} files")
    if suffix == ".stl":
        _check_stl(path, head, size, max_faces)
    elif suffix == ".ply":
        try:
            check_ply_size(path)
        except PlyError as e:
            raise AssetError(str(e)) from None
    elif suffix in (".gltf", ".glb"):
        check_gltf(path)


def _check_stl(path: Path, head: bytes, size: int, max_faces: int) -> None:
    """A binary STL's triangle count against the file's size and ``max_faces``; an ASCII STL (it
    starts with ``solid`` and is not binary by size) passes."""
    count = int.from_bytes(head[80:84], "little") if len(head) == _STL_HEADER_BYTES else 0
    claimed = _STL_HEADER_BYTES + _STL_TRIANGLE_BYTES * count
    if len(head) == _STL_HEADER_BYTES and claimed == size:
        if count > max_faces:
            raise AssetError(f"{path}: {count} triangles, more than {max_faces}; decimate the mesh first")
        return
    if head.lstrip().startswith(b"solid"):
        return
    raise AssetError(
        f"{path}: binary STL header claims {count} triangles ({claimed} bytes) "
        f"but the file holds {size} bytes"
    )


# --------------------------------------------------------------------------------------------
# Files an asset refers to


def referenced_file(asset: Path, name: str, what: str) -> Path:
    """The file ``name`` that the asset file ``asset`` refers to (``what``: the record that does),
    resolved inside the asset's folder. Raises :class:`AssetError` naming the asset, the record and
    the name for an absolute path or URI, a path leaving the folder (``..``, a symlink out), or
    anything but an existing regular file."""
    where = f"{asset}: {what} {name!r}"
    if not name or "\0" in name:
        raise AssetError(f"{where}: not a file name")
    if _URI_SCHEME.match(name) or name.startswith(("/", "\\")) or os.path.isabs(name):
        raise AssetError(f"{where}: an absolute path or URI; an asset refers only to files in its own folder")
    folder = asset.parent.resolve()
    target = (folder / name).resolve()
    if not target.is_relative_to(folder):
        raise AssetError(f"{where}: leaves the asset's folder {folder}")
    if not target.exists():
        raise AssetError(f"{where}: no such file in the asset's folder {folder}")
    if not target.is_file():
        raise AssetError(f"{where}: not a regular file")
    return target


def read_referenced(asset: Path, name: str, what: str) -> bytes:
    """The bytes of :func:`referenced_file` (a regular file, opened without blocking)."""
    return read_regular_file(referenced_file(asset, name, what), f"file {what}", AssetError)


def check_image(data: bytes, where: str) -> None:
    """Raises :class:`AssetError` starting with ``where`` unless ``data`` is an image Pillow reads
    of at most :data:`MAX_TEXTURE_PIXELS` pixels (only its header is read: nothing is decoded)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as image:
                width, height = image.size
    except Image.UnidentifiedImageError:
        raise AssetError(f"{where}: not an image Pillow can read") from None
    except Image.DecompressionBombError as e:
        raise AssetError(
            f"{where}: {e}; the most a texture may have is {MAX_TEXTURE_PIXELS} pixels"
        ) from None
    except Exception as e:  # Pillow raises many kinds for what is not an image
        raise AssetError(f"{where}: not an image Pillow can read ({type(e).__name__}: {e})") from None
    _check_pixels(width, height, where)


def _check_pixels(width: int, height: int, where: str) -> None:
    if width * height > MAX_TEXTURE_PIXELS:
        raise AssetError(
            f"{where}: {width} x {height} pixels, more than the {MAX_TEXTURE_PIXELS} a texture may have; "
            "downscale it"
        )


def check_textures(asset: Path, geometries: Iterable[Any]) -> None:
    """Checks every texture trimesh opened for ``geometries`` (their materials' images, not yet
    decoded) against :data:`MAX_TEXTURE_PIXELS`, then decodes it (a texture whose header is fine but
    whose data are not would otherwise fail later, naming nothing); AssetError naming the asset file
    otherwise."""
    for geometry in geometries:
        material = getattr(getattr(geometry, "visual", None), "material", None)
        for image in _images_of(material):
            _check_pixels(*image.size, f"{asset}: a texture")
            try:
                image.load()
            except Exception as e:  # Pillow raises OSError, SyntaxError, ValueError, ...
                raise AssetError(
                    f"{asset}: a texture of {image.size[0]} x {image.size[1]} pixels does not decode "
                    f"({type(e).__name__}: {e})"
                ) from None


def _images_of(material: Any) -> Iterator[Any]:
    """The PIL images a trimesh material (or a MultiMaterial's materials) holds."""
    if material is None:
        return
    for value in vars(material).values():
        values = value.values() if isinstance(value, dict) else value if isinstance(value, list) else [value]
        for v in values:
            if isinstance(v, Image.Image):
                yield v
            elif hasattr(v, "main_color"):  # a material inside a MultiMaterial
                yield from _images_of(v)


def _image_suffixes() -> set[str]:
    return set(Image.registered_extensions())


class AssetFolder:
    """A trimesh resolver (trimesh's readers call ``get``, ``[name]``, ``keys`` and ``file_name``;
    this class does not import trimesh, which takes a second) that reads only regular files inside
    the asset's folder, as :func:`read_referenced` does, and checks images (by suffix) with
    :func:`check_image`.

    trimesh's readers drop a texture or material they cannot read without a word, so a refusal is
    also kept in :attr:`refused`; :meth:`raise_refused` raises the first after trimesh returns.
    """

    def __init__(self, asset: Path):
        self.asset = Path(asset)
        self.file_name = self.asset.name
        self.refused: list[AssetError] = []

    def get(self, name: str) -> bytes:
        """The bytes of the file ``name`` refers to; FileNotFoundError (kept in :attr:`refused`)."""
        try:
            data = read_referenced(self.asset, name, "refers to")
            if Path(name).suffix.lower() in _image_suffixes():
                check_image(data, f"{self.asset}: image {name!r}")
        except AssetError as e:
            self.refused.append(e)
            raise FileNotFoundError(str(e)) from None
        return data

    def __getitem__(self, name: str) -> bytes:
        return self.get(name)

    def __contains__(self, name: str) -> bool:
        return False

    def write(self, name: str, data: Any) -> None:
        raise PermissionError(f"{self.asset}: assets are read, never written")

    def namespaced(self, namespace: str) -> AssetFolder:
        raise FileNotFoundError(f"{self.asset}: {namespace!r}: assets do not read archives")

    def keys(self) -> Iterator[str]:
        return iter(())

    def raise_refused(self) -> None:
        """Raises the first refusal, if any."""
        if self.refused:
            raise self.refused[0]


# --------------------------------------------------------------------------------------------
# glTF and GLB


def check_gltf(path: Path) -> None:
    """Checks a .gltf or .glb file's sizes, references and images (module docstring) before trimesh
    reads it. Raises :class:`AssetError` naming the file, the record and what is wrong."""
    doc, bin_chunk = _gltf_document(path)
    _Gltf(path, doc, bin_chunk).check()


def _gltf_document(path: Path) -> tuple[dict[str, Any], tuple[int, int] | None]:
    """The JSON of a .gltf or .glb file and, for a GLB, its BIN chunk (byte offset, length)."""
    if path.suffix.lower() == ".gltf":
        return _json_of(path, path.read_bytes()), None
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(12)
        if len(head) < 12 or head[:4] != _GLB_MAGIC:
            raise AssetError(f"{path}: not a GLB file (it does not start with 'glTF')")
        version, length = int.from_bytes(head[4:8], "little"), int.from_bytes(head[8:12], "little")
        if version != 2:
            raise AssetError(f"{path}: GLB version {version}; only glTF 2 is read")
        if length != size:
            raise AssetError(f"{path}: the GLB header claims {length} bytes but the file holds {size} bytes")
        chunks, pos = [], 12
        while pos < length:
            f.seek(pos)
            chunk_head = f.read(8)
            chunk_length = int.from_bytes(chunk_head[:4], "little") if len(chunk_head) == 8 else 0
            if len(chunk_head) < 8 or pos + 8 + chunk_length > length:
                raise AssetError(
                    f"{path}: GLB chunk {len(chunks)} at byte {pos} claims {chunk_length} bytes "
                    f"but only {max(length - pos - 8, 0)} follow"
                )
            chunks.append((int.from_bytes(chunk_head[4:], "little"), pos + 8, chunk_length))
            pos += 8 + chunk_length
        if not chunks or chunks[0][0] != _GLB_JSON:
            raise AssetError(f"{path}: the GLB's first chunk is not its JSON")
        f.seek(chunks[0][1])
        doc = _json_of(path, f.read(chunks[0][2]))
    bins = [(start, n) for kind, start, n in chunks[1:] if kind == _GLB_BIN]
    return doc, bins[0] if bins else None


def _json_of(path: Path, data: bytes) -> dict[str, Any]:
    try:
        doc = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as e:
        raise AssetError(f"{path}: not glTF JSON ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict):
        raise AssetError(f"{path}: not glTF JSON (an object), got {type(doc).__name__}")
    return doc


def _is_index(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


class _Gltf:
    """The checks of one glTF document; ``bin_chunk`` is a GLB's BIN chunk (offset, length)."""

    def __init__(self, path: Path, doc: dict[str, Any], bin_chunk: tuple[int, int] | None):
        self.path, self.doc, self.bin_chunk = path, doc, bin_chunk

    def error(self, where: str, problem: str) -> AssetError:
        return AssetError(f"{self.path}: {where}: {problem}")

    def items(self, key: str) -> list[dict[str, Any]]:
        """The top-level list ``key`` (empty if absent), each item an object."""
        value = self.doc.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self.error(key, "must be a list of objects")
        return value

    def ref(self, where: str, value: Any, key: str) -> int:
        """``value``, after checking it is an index into the top-level list ``key``."""
        n = len(self.items(key))
        if not _is_index(value) or value >= n:
            raise self.error(where, f"refers to {key}[{value!r}], which does not exist (the file has {n})")
        return int(value)

    def size(self, where: str, value: Any) -> int:
        if not _is_index(value):
            raise self.error(where, f"must be a non-negative integer, got {value!r}")
        return int(value)

    def check(self) -> None:
        buffers = [self.buffer_length(i, b) for i, b in enumerate(self.items("buffers"))]
        views = [self.view_length(i, v, buffers) for i, v in enumerate(self.items("bufferViews"))]
        for i, a in enumerate(self.items("accessors")):
            self.check_accessor(i, a, views, sum(buffers))
        for i, image in enumerate(self.items("images")):
            self.check_image(i, image)
        for i, texture in enumerate(self.items("textures")):
            if "source" in texture:
                self.ref(f"textures[{i}].source", texture["source"], "images")
            if "sampler" in texture:
                self.ref(f"textures[{i}].sampler", texture["sampler"], "samplers")
        for i, material in enumerate(self.items("materials")):
            self.check_material(i, material)
        for i, mesh in enumerate(self.items("meshes")):
            self.check_mesh(i, mesh)
        self.check_nodes()

    def buffer_length(self, i: int, b: dict[str, Any]) -> int:
        """buffers[i]'s byteLength, checked against the bytes its source holds."""
        where = f"buffers[{i}]"
        length = self.size(f"{where}.byteLength", b.get("byteLength"))
        uri = b.get("uri")
        if uri is None:
            if i != 0 or self.bin_chunk is None:
                raise self.error(where, "has no uri and is not the BIN chunk of a GLB")
            present, source = self.bin_chunk[1], "the GLB's BIN chunk"
        elif not isinstance(uri, str):
            raise self.error(f"{where}.uri", f"must be a string, got {type(uri).__name__}")
        elif (k := uri.find("base64,")) >= 0:  # trimesh decodes whatever follows "base64,"
            present, source = len(self.decode(f"{where}.uri", uri[k + 7 :])), "data URI"
        else:
            file = referenced_file(self.path, uri, f"{where}.uri")
            present, source = file.stat().st_size, f"file {uri!r}"
        if length > present:
            raise self.error(
                where, f"byteLength {length} claims more than the {present} bytes its {source} holds"
            )
        return length

    def decode(self, where: str, payload: str) -> bytes:
        try:
            return base64.b64decode(payload)
        except (binascii.Error, ValueError) as e:
            raise self.error(where, f"not base64 data ({e})") from None

    def view_length(self, i: int, v: dict[str, Any], buffers: list[int]) -> int:
        """bufferViews[i]'s byteLength, checked to lie inside its buffer."""
        where = f"bufferViews[{i}]"
        buffer = self.ref(f"{where}.buffer", v.get("buffer"), "buffers")
        offset = self.size(f"{where}.byteOffset", v.get("byteOffset", 0))
        length = self.size(f"{where}.byteLength", v.get("byteLength"))
        if offset + length > buffers[buffer]:
            raise self.error(
                where,
                f"bytes {offset} to {offset + length} lie outside buffers[{buffer}] "
                f"({buffers[buffer]} bytes)",
            )
        stride = v.get("byteStride")
        if stride is not None and not (_is_index(stride) and 4 <= stride <= 252):
            raise self.error(f"{where}.byteStride", f"must be an integer in [4, 252], got {stride!r}")
        return length

    def check_accessor(self, i: int, a: dict[str, Any], views: list[int], buffer_bytes: int) -> None:
        """accessors[i]'s data inside its buffer view (or, without one, at most ``buffer_bytes``)."""
        where = f"accessors[{i}]"
        component = _GLTF_COMPONENT_BYTES.get(a.get("componentType"))  # type: ignore[arg-type]
        components = _GLTF_TYPE_COMPONENTS.get(a.get("type"))  # type: ignore[arg-type]
        if component is None or components is None:
            raise self.error(
                where, f"unknown componentType {a.get('componentType')!r} or type {a.get('type')!r}"
            )
        count = self.size(f"{where}.count", a.get("count"))
        element = component * components
        if "bufferView" not in a:
            if count * element > buffer_bytes:
                raise self.error(
                    where,
                    f"has no bufferView and claims {count} x {element} bytes, more than the file's "
                    f"buffers hold ({buffer_bytes} bytes)",
                )
            return
        view = self.ref(f"{where}.bufferView", a["bufferView"], "bufferViews")
        offset = self.size(f"{where}.byteOffset", a.get("byteOffset", 0))
        stride = self.items("bufferViews")[view].get("byteStride") or element
        if stride < element:
            raise self.error(where, f"elements of {element} bytes do not fit the view's byteStride {stride}")
        needed = offset + (count - 1) * stride + element if count else offset
        if needed > views[view]:
            raise self.error(
                where,
                f"claims {count} elements of {element} bytes ({needed} bytes with offset and stride) "
                f"but bufferViews[{view}] holds {views[view]} bytes",
            )

    def check_image(self, i: int, image: dict[str, Any]) -> None:
        """images[i]: its bytes exist (a view, a data URI or a file in the asset's folder) and are an
        image of at most MAX_TEXTURE_PIXELS (KTX2 images, which trimesh skips, are not opened)."""
        where = f"images[{i}]"
        if "bufferView" in image:
            view = self.items("bufferViews")[
                self.ref(f"{where}.bufferView", image["bufferView"], "bufferViews")
            ]
            data = self.view_bytes(view)
        elif isinstance(uri := image.get("uri"), str):
            k = uri.find("base64,")
            data = (
                self.decode(f"{where}.uri", uri[k + 7 :])
                if k >= 0
                else read_referenced(self.path, uri, f"{where}.uri")
            )
        else:
            raise self.error(where, "has neither a bufferView nor a uri")
        if image.get("mimeType") != "image/ktx2":
            check_image(data, f"{self.path}: {where}")

    def view_bytes(self, view: dict[str, Any]) -> bytes:
        """The bytes of a (checked) buffer view."""
        b = self.items("buffers")[view["buffer"]]
        offset, length = view.get("byteOffset", 0), view["byteLength"]
        uri = b.get("uri")
        if uri is None:
            assert self.bin_chunk is not None
            with self.path.open("rb") as f:
                f.seek(self.bin_chunk[0] + offset)
                return f.read(length)
        if (k := uri.find("base64,")) >= 0:
            return self.decode("buffer", uri[k + 7 :])[offset : offset + length]
        return read_referenced(self.path, uri, "buffer")[offset : offset + length]

    def check_material(self, i: int, material: dict[str, Any]) -> None:
        """materials[i]'s texture references."""
        for keys in _MATERIAL_TEXTURES:
            info: Any = material
            for key in keys:
                info = info.get(key) if isinstance(info, dict) else None
            if info is None:
                continue
            where = f"materials[{i}].{'.'.join(keys)}"
            if not isinstance(info, dict):
                raise self.error(where, "must be an object with an index")
            self.ref(f"{where}.index", info.get("index"), "textures")

    def check_mesh(self, i: int, mesh: dict[str, Any]) -> None:
        """meshes[i]'s primitives: their accessors and materials exist."""
        primitives = mesh.get("primitives")
        if not isinstance(primitives, list) or not all(isinstance(p, dict) for p in primitives):
            raise self.error(f"meshes[{i}].primitives", "must be a list of objects")
        for j, p in enumerate(primitives):
            where = f"meshes[{i}].primitives[{j}]"
            attributes = p.get("attributes", {})
            targets = p.get("targets", [])
            if not isinstance(attributes, dict) or not isinstance(targets, list):
                raise self.error(where, "attributes must be an object and targets a list")
            for t in [attributes, *targets]:
                if not isinstance(t, dict):
                    raise self.error(f"{where}.targets", "must be a list of objects")
                for name, index in t.items():
                    self.ref(f"{where}.{name}", index, "accessors")
            if "indices" in p:
                self.ref(f"{where}.indices", p["indices"], "accessors")
            if "material" in p:
                self.ref(f"{where}.material", p["material"], "materials")

    def check_nodes(self) -> None:
        """Nodes refer to meshes and nodes that exist and form trees (no node with two parents, no
        cycle); scenes refer to nodes that exist."""
        nodes = self.items("nodes")
        parent: dict[int, int] = {}
        for i, node in enumerate(nodes):
            if "mesh" in node:
                self.ref(f"nodes[{i}].mesh", node["mesh"], "meshes")
            children = node.get("children", [])
            if not isinstance(children, list):
                raise self.error(f"nodes[{i}].children", "must be a list of node indices")
            for child in children:
                c = self.ref(f"nodes[{i}].children", child, "nodes")
                if c == i or c in parent:
                    problem = "is its own child" if c == i else "has two parents"
                    raise self.error(f"nodes[{i}].children", f"nodes[{c}] {problem} (nodes must form trees)")
                parent[c] = i
        reached = [i for i in range(len(nodes)) if i not in parent]
        for i in reached:  # grows while walked: every root's descendants
            reached.extend(int(c) for c in nodes[i].get("children", []))
        if len(reached) < len(nodes):
            cycle = min(set(range(len(nodes))) - set(reached))
            raise self.error(f"nodes[{cycle}]", "is its own ancestor (nodes must form trees)")
        for i, scene in enumerate(self.items("scenes")):
            roots = scene.get("nodes", [])
            if not isinstance(roots, list):
                raise self.error(f"scenes[{i}].nodes", "must be a list of node indices")
            for node in roots:
                self.ref(f"scenes[{i}].nodes", node, "nodes")
        if "scene" in self.doc:
            self.ref("scene", self.doc["scene"], "scenes")
