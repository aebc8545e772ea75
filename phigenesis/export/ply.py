"""A :class:`~phigenesis.models.gaussians.GaussianScene` as a 3D Gaussian Splatting PLY, and back.

The file is the binary little-endian PLY of Inria's 3DGS, which gsplat, SuperSplat and most splat
viewers read: one element ``vertex`` (one Gaussian per vertex) whose float32 properties are, in order::

    x y z                       centre, world frame of the scene, metres
    nx ny nz                    normals, always 0 (unused by splatting)
    f_dc_0 f_dc_1 f_dc_2        SH band 0: (rgb - 0.5) / C0, C0 = 0.28209479177387814
    f_rest_0 .. f_rest_{M-1}    higher SH bands, all 0; M = 3 ((d + 1)^2 - 1), 45 for degree d = 3
    opacity                     logit of the opacity (clamped to [1e-6, 1 - 1e-6])
    scale_0 scale_1 scale_2     natural log of the standard deviations in metres (clamped >= 1e-8)
    rot_0 rot_1 rot_2 rot_3     unit quaternion w, x, y, z (world from Gaussian)

and, with ``extras`` (viewers ignore properties they do not know), six more float32 properties::

    semantic_class              argmax of the semantic logits (unified taxonomy id), -1 without logits
    vx vy vz                    velocity, world frame, m/s (0 for static Gaussians)
    dynamic                     1 for Gaussians of moving things, else 0
    time_s                      time of the written centre, seconds after the time origin

Everything is float32, including the integer-valued extras, because several viewers and loaders
assume that every vertex property is a float. Header comments give the frame, the time origin
(``comment time_origin_micros <int>``) and the export time (``comment t_s <float>`` or
``comment t_s none``). The frame is the scene's world frame, not a camera frame: points are plain
world coordinates with no OpenCV/OpenGL axis flip.

Gaussians move at constant velocity, so a 4D scene is written at one instant: :func:`write_ply` with
``t_s`` moves every centre to that time (and writes ``time_s = t_s``); without it each Gaussian is
written at its own reference time. :func:`read_ply` reads any binary little-endian PLY's vertex
properties; :func:`scene_from_ply` decodes the layout above back into a scene.
"""

from __future__ import annotations

import os
import re
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from phigenesis import taxonomy as tx
from phigenesis.data.records import MAX_USER_MICROS
from phigenesis.errors import PhiGenesisError
from phigenesis.models.gaussians import GaussianScene
from phigenesis.models.rasterizer import QUATERNION_ZERO_SQNORM

#: Spherical-harmonics band-0 constant: colour = 0.5 + C0 * f_dc.
SH_C0 = 0.28209479177387814
#: Opacities are clamped to [OPACITY_EPS, 1 - OPACITY_EPS] before the logit.
OPACITY_EPS = 1e-6
#: Scales (metres) are clamped to at least this before the log.
MIN_SCALE = 1e-8
#: Logit given to a Gaussian's ``semantic_class`` in the one-hot logits of :func:`scene_from_ply`.
ONE_HOT_LOGIT = 10.0
#: Properties :func:`scene_from_ply` needs.
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", *(f"scale_{i}" for i in range(3)),
            *(f"rot_{i}" for i in range(4)))  # fmt: skip
#: Extra per-Gaussian properties written after ``rot_3`` when ``extras`` is true.
EXTRAS = ("semantic_class", "vx", "vy", "vz", "dynamic", "time_s")
#: Frame description written into the header.
FRAME_COMMENT = "frame: world frame of the scene, metres, OpenCV-free: points are plain world coordinates"

#: PLY scalar type names and their numpy types (without byte order).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "int64": "i8", "uint64": "u8",
    "float16": "f2", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
#: PLY formats whose header is read (:func:`read_ply` reads the data of the first only).
_FORMATS = ("binary_little_endian", "binary_big_endian", "ascii")
#: Most rows a PLY element may claim (10^15; what a file holds is checked against its size too).
MAX_PLY_ROWS = 10**15
#: Rows of the vertex table filled and written at a time.
_BLOCK_ROWS = 8192
#: Largest finite float32: bigger values would be written as inf.
_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: Longest header read before giving up (bytes).
_MAX_HEADER_BYTES = 1 << 20


def property_names(sh_degree: int = 3, extras: bool = True) -> list[str]:
    """The vertex property names :func:`write_ply` writes, in file order."""
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names + (list(EXTRAS) if extras else [])


# ----------------------------------------------------------------------------------------------- write


def write_ply(
    scene: GaussianScene,
    path: str | os.PathLike[str],
    *,
    t_s: float | None = None,
    sh_degree: int = 3,
    extras: bool = True,
) -> Path:
    """Writes ``scene`` to ``path`` as a binary little-endian 3DGS PLY (layout in the module docstring).

    Args:
        scene: the Gaussians (any device; gradients are ignored).
        path: the file to write; its folder must exist. It is written under a temporary name in the
            same folder and renamed into place, so a failed write leaves ``path`` as it was.
        t_s: export time in seconds after ``scene.time_origin_micros``: centres are moved to it
            (``means + velocity * (t_s - time_s)``). None writes each Gaussian at its own ``time_s``.
        sh_degree: SH degree of the layout (0..3); the ``f_rest`` coefficients are all zero.
        extras: also write ``semantic_class vx vy vz dynamic time_s`` after ``rot_3``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: if a Gaussian has a non-finite value in a written field (the message names the
            path and how many Gaussians are bad); nothing is written then.
    """
    path = Path(path)
    names = property_names(sh_degree, extras)
    columns = _encode(scene, t_s, extras)
    _check_finite(columns, path)
    header = _header(names, len(scene), scene.time_origin_micros, t_s)
    _write_atomically(path, header, _vertex_blocks(columns, names))
    return path


def _numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float64).numpy()


def _encode(scene: GaussianScene, t_s: float | None, extras: bool) -> dict[str, np.ndarray]:
    """Non-zero columns of the vertex table (float64), by property name."""
    n = len(scene)
    means = _numpy(scene.means if t_s is None else scene.means_at(float(t_s)))
    f_dc = (_numpy(scene.colors) - 0.5) / SH_C0
    opacity = np.clip(_numpy(scene.opacities), OPACITY_EPS, 1.0 - OPACITY_EPS)
    log_scale = np.log(np.maximum(_numpy(scene.scales), MIN_SCALE))
    quats = _normalise_quats(_numpy(scene.quats))
    cols = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    cols |= {f"f_dc_{i}": f_dc[:, i] for i in range(3)}
    cols["opacity"] = np.log(opacity) - np.log1p(-opacity)
    cols |= {f"scale_{i}": log_scale[:, i] for i in range(3)}
    cols |= {f"rot_{i}": quats[:, i] for i in range(4)}
    if extras:
        velocity = _numpy(scene.velocity)
        if scene.num_classes:
            cols["semantic_class"] = _numpy(scene.semantic_logits).argmax(axis=1).astype(np.float64)
        else:
            cols["semantic_class"] = np.full(n, -1.0)
        cols |= {"vx": velocity[:, 0], "vy": velocity[:, 1], "vz": velocity[:, 2]}
        cols["dynamic"] = scene.dynamic.detach().cpu().numpy().astype(np.float64)
        cols["time_s"] = np.full(n, float(t_s)) if t_s is not None else _numpy(scene.time_s)
    return cols


def _normalise_quats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z); (near-)zero ones become the identity, as in the rasterizer."""
    sqnorm = (q * q).sum(axis=1, keepdims=True)
    zero = sqnorm < QUATERNION_ZERO_SQNORM
    unit = np.where(zero, np.array([1.0, 0.0, 0.0, 0.0]), q / np.sqrt(np.where(zero, 1.0, sqnorm)))
    return unit


def _check_finite(columns: dict[str, np.ndarray], path: Path) -> None:
    bad = np.zeros(len(next(iter(columns.values()))), dtype=bool)
    fields = set()
    for name, values in columns.items():
        nonfinite = ~(np.abs(values) <= _FLOAT32_MAX)  # NaN, inf and what float32 cannot hold
        if nonfinite.any():
            bad |= nonfinite
            fields.add(_FIELD_OF.get(name, name))
    if bad.any():
        raise ValueError(
            f"{path}: not written: {int(bad.sum())} of {bad.size} Gaussians have non-finite values "
            f"(in {', '.join(sorted(fields))})"
        )


#: Scene field behind each written property (for error messages).
_FIELD_OF = {
    **dict.fromkeys(("x", "y", "z"), "means"),
    **dict.fromkeys(("f_dc_0", "f_dc_1", "f_dc_2"), "colors"),
    "opacity": "opacities",
    **dict.fromkeys(("scale_0", "scale_1", "scale_2"), "scales"),
    **dict.fromkeys(("rot_0", "rot_1", "rot_2", "rot_3"), "quats"),
    **dict.fromkeys(("vx", "vy", "vz"), "velocity"),
}


def _header(names: list[str], count: int, time_origin_micros: int, t_s: float | None) -> bytes:
    when = "none (each Gaussian at its own time_s)" if t_s is None else repr(float(t_s))
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment PhiGenesis Gaussian scene, 3D Gaussian Splatting layout",
        f"comment {FRAME_COMMENT}",
        f"comment time_origin_micros {int(time_origin_micros)}",
        f"comment t_s {when}",
        f"element vertex {count}",
        *(f"property float {name}" for name in names),
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


def _vertex_blocks(columns: dict[str, np.ndarray], names: list[str]) -> Iterator[np.ndarray]:
    """The float32 vertex table, ``_BLOCK_ROWS`` rows at a time, properties not in ``columns`` zero.

    Blocks small enough to stay in cache make filling the wide, mostly-zero table several times
    faster than filling it whole. Each block is a view of one reused buffer: write it before the next.
    """
    n = len(columns["x"])
    index = np.array([names.index(name) for name in columns])
    values = np.stack(list(columns.values()), axis=1).astype("<f4")
    buffer = np.zeros((min(n, _BLOCK_ROWS), len(names)), dtype="<f4")
    for start in range(0, n, _BLOCK_ROWS):
        block = buffer[: min(_BLOCK_ROWS, n - start)]
        block[:, index] = values[start : start + len(block)]
        yield block


def _write_atomically(path: Path, header: bytes, blocks: Iterable[np.ndarray]) -> None:
    """Writes ``header`` then the ``blocks``' bytes to a temporary file beside ``path``, then renames it."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(header)
            for block in blocks:
                f.write(memoryview(np.ascontiguousarray(block).reshape(-1).view(np.uint8)))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# ------------------------------------------------------------------------------------------------ read


class PlyError(PhiGenesisError, ValueError):
    """A PLY file that cannot be read: the message names the file, the element or property and
    what is wrong."""


@dataclass(frozen=True)
class _Property:
    name: str
    type: str  # numpy type code without byte order ("f4", "u1"); of the items for a list
    count_type: str | None = None  # a list property's length type; None for a scalar


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: list[_Property]


@dataclass(frozen=True)
class _Header:
    size: int  # bytes, up to and including the "end_header" line
    format: str  # one of _FORMATS
    comments: list[str]
    elements: list[_Element]


def read_ply(path: str | os.PathLike[str], max_vertices: int | None = None) -> dict[str, np.ndarray]:
    """The vertex properties of a binary little-endian PLY, by name, in file order.

    Each value is a 1-D array (one entry per vertex) of the property's type (float32 for ``float``,
    float64 for ``double``, uint8 for ``uchar``, int32 for ``int``, ...). Elements before ``vertex``
    are skipped; list properties (faces) are supported only after the vertex element. The sizes the
    header claims are checked against the file's size before anything is allocated, so memory is
    bounded by the file, whatever its header says.

    Args:
        path: the file.
        max_vertices: the most vertices read (None: any number the file holds).

    Raises:
        PlyError: naming the file, if it is not a PLY, is ASCII or big-endian, has no vertex
            element, claims more vertices than ``max_vertices``, or is shorter (naming the element,
            the bytes it claims and the bytes present) or, with nothing after the vertices, longer
            than its header says.
    """
    path = Path(path)
    with path.open("rb") as f:
        header = _read_header(f, path)
        if header.format != "binary_little_endian":
            raise PlyError(
                f"{path}: PLY format {header.format!r} is not supported; only binary_little_endian is"
            )
        vertex_index = _vertex_index(header, path)
        vertex = header.elements[vertex_index]
        if max_vertices is not None and vertex.count > max_vertices:
            raise PlyError(
                f"{path}: element vertex claims {vertex.count} vertices, more than the {max_vertices} read"
            )
        starts = _element_starts(f, header, path, vertex_index + 1)
        dtype = np.dtype([(p.name, "<" + p.type) for p in vertex.properties])
        f.seek(starts[vertex_index])
        buf = bytearray(vertex.count * dtype.itemsize)  # within the file: _element_starts checked it
        if f.readinto(buf) < len(buf):  # the file shrank since
            raise PlyError(f"{path}: truncated: the {vertex.count} vertices end past the end of the file")
        if vertex_index == len(header.elements) - 1 and f.read(1):
            raise PlyError(f"{path}: more data after the {vertex.count} vertices than the header declares")
    table = np.frombuffer(buf, dtype=dtype, count=vertex.count)
    return {name: np.ascontiguousarray(table[name]) for name in dtype.names or ()}


def check_ply_size(path: str | os.PathLike[str]) -> None:
    """Checks that every element of a binary PLY (either byte order; any PLY, mesh or not) fits in
    the file, before a reader allocates what its header claims. Rows with list properties count as
    long as the element's first row (as trimesh reads them). ASCII PLYs are not checked: a text
    reader's memory is bounded by the text.

    Raises:
        PlyError: naming the file, for a header :func:`read_ply` cannot parse (formats aside), or
            naming the element, the bytes it claims and the bytes present, for an element that
            does not fit.
    """
    path = Path(path)
    with path.open("rb") as f:
        header = _read_header(f, path)
        if header.format != "ascii":
            _element_starts(f, header, path, len(header.elements))


def _element_starts(f: BinaryIO, header: _Header, path: Path, stop: int) -> list[int]:
    """Byte offsets of the first ``stop`` binary elements in the file, after checking that each
    one's rows (``count`` times its first row's size) fit in what follows it; PlyError naming the
    element otherwise."""
    order = "<" if header.format == "binary_little_endian" else ">"
    file_size = os.fstat(f.fileno()).st_size
    starts, pos = [], header.size
    for element in header.elements[:stop]:
        row = _row_bytes(f, element, pos, order, path)
        claimed, left = element.count * row, file_size - pos
        if claimed > left:
            raise PlyError(
                f"{path}: truncated: element {element.name!r} claims {element.count} rows of {row} bytes "
                f"({claimed} bytes) but only {left} bytes follow"
            )
        starts.append(pos)
        pos += claimed
    return starts


def _row_bytes(f: BinaryIO, element: _Element, start: int, order: str, path: Path) -> int:
    """Bytes of the first row of ``element``, which starts at byte ``start``; a list property's
    length is read from that row (0 where the file ends first: the element's claim fails then)."""
    row = 0
    for p in element.properties:
        if p.count_type is None:
            row += np.dtype(p.type).itemsize
            continue
        count_type = np.dtype(order + p.count_type)
        f.seek(start + row)
        raw = f.read(count_type.itemsize) if element.count else b""
        length = int(np.frombuffer(raw, count_type)[0]) if len(raw) == count_type.itemsize else 0
        if length < 0:
            raise PlyError(f"{path}: element {element.name!r} property {p.name!r}: list length {length}")
        row += count_type.itemsize + length * np.dtype(p.type).itemsize
    return row


def _read_header(f: BinaryIO, path: Path) -> _Header:
    first = f.readline(16).rstrip(b"\r\n")
    if first != b"ply":
        raise PlyError(f"{path}: not a PLY file (it starts with {first[:16]!r}, not 'ply')")
    comments: list[str] = []
    elements: list[_Element] = []
    fmt = None
    while True:
        raw = f.readline(_MAX_HEADER_BYTES)
        if not raw.endswith(b"\n") or f.tell() > _MAX_HEADER_BYTES:
            raise PlyError(f"{path}: PLY header has no end_header line")
        line = raw.decode("ascii", errors="replace").strip()
        word, _, rest = line.partition(" ")
        if word == "end_header":
            break
        if word == "format":
            fmt = rest.split()[0] if rest.split() else ""
            if fmt not in _FORMATS:
                raise PlyError(f"{path}: PLY format {fmt!r} is not supported; only binary_little_endian is")
        elif word in ("comment", "obj_info"):
            comments.append(rest)
        elif word == "element":
            elements.append(_parse_element(rest, path))
        elif word == "property":
            if not elements:
                raise PlyError(f"{path}: PLY property before any element: {line!r}")
            elements[-1].properties.append(_parse_property(rest, path))
        elif line:
            raise PlyError(f"{path}: unexpected PLY header line {line!r}")
    if fmt is None:
        raise PlyError(f"{path}: PLY header has no format line")
    return _Header(size=f.tell(), format=fmt, comments=comments, elements=elements)


def _parse_element(rest: str, path: Path) -> _Element:
    parts = rest.split()
    if len(parts) != 2 or not parts[1].isdigit():
        raise PlyError(f"{path}: bad PLY element line 'element {rest}'")
    if len(parts[1]) > len(str(MAX_PLY_ROWS)) or int(parts[1]) > MAX_PLY_ROWS:
        raise PlyError(f"{path}: element {parts[0]!r} claims {parts[1]} rows, more than {MAX_PLY_ROWS}")
    return _Element(parts[0], int(parts[1]), [])


def _parse_property(rest: str, path: Path) -> _Property:
    parts = rest.split()
    if len(parts) == 4 and parts[0] == "list" and parts[1] in _PLY_TYPES and parts[2] in _PLY_TYPES:
        return _Property(parts[3], _PLY_TYPES[parts[2]], _PLY_TYPES[parts[1]])
    if len(parts) != 2 or parts[0] not in _PLY_TYPES:
        raise PlyError(f"{path}: unsupported PLY property 'property {rest}'")
    return _Property(parts[1], _PLY_TYPES[parts[0]])


def _vertex_index(header: _Header, path: Path) -> int:
    """Index of the vertex element, after checking that it and the elements before it hold no lists."""
    for i, element in enumerate(header.elements):
        if any(p.count_type is not None for p in element.properties):
            what = "the vertex element" if element.name == "vertex" else f"element {element.name!r} before it"
            raise PlyError(f"{path}: list properties in {what} are not supported")
        if element.name == "vertex":
            names = [p.name for p in element.properties]
            duplicates = sorted({n for n in names if names.count(n) > 1})
            if duplicates:
                raise PlyError(f"{path}: repeated vertex properties {duplicates}")
            return i
    raise PlyError(f"{path}: PLY file has no vertex element")


def read_ply_comments(path: str | os.PathLike[str]) -> list[str]:
    """The header's ``comment`` (and ``obj_info``) lines of a PLY, without the keyword."""
    path = Path(path)
    with path.open("rb") as f:
        return _read_header(f, path).comments


# ---------------------------------------------------------------------------------------------- decode


def scene_from_ply(path: str | os.PathLike[str], max_vertices: int | None = None) -> GaussianScene:
    """Decodes a 3DGS PLY (written by :func:`write_ply` or another 3DGS tool) into a scene on the CPU.

    Inverts the encodings: colours ``0.5 + C0 * f_dc`` clipped to [0, 1] (higher SH bands are
    dropped), opacities ``sigmoid(opacity)``, scales ``exp(scale)`` (metres), quaternions normalised
    (w, x, y, z). Positions are world-frame metres as stored. Without the extras, velocities are zero,
    no Gaussian is dynamic, semantic logits are (N, 0) and ``time_s`` is the header's ``t_s`` (else 0).
    With ``semantic_class``, logits are ``10 * one_hot`` over the 19 unified classes (a row of zeros for
    class -1). ``time_origin_micros`` comes from the header comment (else 0). ``max_vertices``: the
    most Gaussians read (None: any number the file holds), checked before reading them.

    Raises:
        PlyError: naming the file, for anything :func:`read_ply` rejects, missing required
            properties (listed), semantic classes outside -1..18, or a time comment beyond
            +-2^62 microseconds (``time_origin_micros``) or not a finite time (``t_s``).
    """
    path = Path(path)
    props = read_ply(path, max_vertices)
    missing = [name for name in REQUIRED if name not in props]
    if missing:
        raise PlyError(f"{path}: not a 3D Gaussian Splatting PLY: missing vertex properties {missing}")
    origin, t_header = _time_comments(read_ply_comments(path), path)
    n = len(props["x"])

    def stack(*names: str) -> np.ndarray:
        return np.stack([props[name].astype(np.float64) for name in names], axis=1).reshape(n, len(names))

    colors = np.clip(0.5 + SH_C0 * stack("f_dc_0", "f_dc_1", "f_dc_2"), 0.0, 1.0)
    opacity = 1.0 / (1.0 + np.exp(-props["opacity"].astype(np.float64)))
    velocity = stack("vx", "vy", "vz") if all(v in props for v in ("vx", "vy", "vz")) else np.zeros((n, 3))
    dynamic = props["dynamic"] > 0.5 if "dynamic" in props else (velocity != 0).any(axis=1)
    default_time = 0.0 if t_header is None else t_header
    time_s = props["time_s"].astype(np.float64) if "time_s" in props else np.full(n, default_time)
    values = {
        "means": stack("x", "y", "z"),
        "quats": _normalise_quats(stack("rot_0", "rot_1", "rot_2", "rot_3")),
        "scales": np.exp(stack("scale_0", "scale_1", "scale_2")),
        "opacities": opacity,
        "colors": colors,
        "semantic_logits": _one_hot_logits(props.get("semantic_class"), n, path),
        "velocity": velocity,
        "time_s": time_s,
    }
    tensors = {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) for k, v in values.items()}
    return GaussianScene(**tensors, dynamic=torch.from_numpy(dynamic), time_origin_micros=origin)


def _time_comments(comments: list[str], path: Path) -> tuple[int, float | None]:
    """``time_origin_micros`` (0 if absent) and ``t_s`` (None if absent, "none" or not a number) from
    header comments; PlyError naming the file and the comment for a time beyond +-MAX_USER_MICROS."""
    origin, t_s = 0, None
    for comment in comments:
        if m := re.fullmatch(r"time_origin_micros\s+(-?\d+)", comment.strip()):
            text = m.group(1)
            origin = int(text) if len(text) <= 20 else MAX_USER_MICROS  # never a 4300-digit parse
            if not -MAX_USER_MICROS < origin < MAX_USER_MICROS:
                shown = text if len(text) <= 24 else text[:24] + "..."
                raise PlyError(f"{path}: comment time_origin_micros {shown} is beyond +-{MAX_USER_MICROS} us")
        elif (m := re.fullmatch(r"t_s\s+(\S+).*", comment.strip())) and m.group(1) != "none":
            try:
                t_s = float(m.group(1))
            except ValueError:
                t_s = None
            if t_s is not None and not abs(t_s) * 1e6 < MAX_USER_MICROS:
                raise PlyError(
                    f"{path}: comment t_s {m.group(1)} is not a time within +-{MAX_USER_MICROS} us"
                )
    return origin, t_s


def _one_hot_logits(classes: np.ndarray | None, n: int, path: Path) -> np.ndarray:
    if classes is None:
        return np.zeros((n, 0))
    ids = np.rint(classes.astype(np.float64))
    bad = (ids != classes) | (ids < -1) | (ids >= tx.NUM_CLASSES)
    if bad.any():
        raise PlyError(
            f"{path}: {int(bad.sum())} semantic_class values are not integers in -1..{tx.NUM_CLASSES - 1}"
        )
    logits = np.zeros((n, tx.NUM_CLASSES))
    known = ids >= 0
    logits[np.flatnonzero(known), ids[known].astype(np.int64)] = ONE_HOT_LOGIT
    return logits
