"""Scene editing: an asset inserted into a scene's Gaussians at a pose and time (``phigenesis-render
--insert``; Python: :func:`load_asset`, :class:`AssetPlacement`, :func:`insert_asset`, :func:`asset_box`).

- **Assets** (:func:`load_asset`). A 3D Gaussian Splatting PLY (recognised by its ``scale_0``,
  ``rot_0``, ``opacity`` and ``f_dc_0`` vertex properties; read with
  :func:`phigenesis.export.ply.scene_from_ply`) stays as its Gaussians. A mesh (OBJ, GLB/GLTF
  scenes, whose meshes are joined with their node transforms, PLY meshes, STL, OFF; read with
  trimesh after :mod:`phigenesis.infer.asset_files` has checked what the file claims against its
  size, refused compressed files, and kept the files it refers to inside its own folder) becomes
  surface Gaussians: ``ceil(area / spacing^2)`` points spread over the faces in
  proportion to their areas (a fixed low-discrepancy pattern inside each face: the same file
  always gives the same Gaussians), each a flat, nearly opaque disc lying in its face (standard
  deviations ``DISC_SCALE * spacing`` in the face, ``DISC_THICKNESS * spacing`` along its normal)
  with the colour of the face there (face colours, vertex colours interpolated, or the texture at
  the interpolated UV; a textureless material's colour; uniform grey without any). Every Gaussian is
  labelled with the user's class
  (logits ``ONE_HOT_LOGIT * one_hot``).
- **The asset frame** is the file's own frame in metres (times ``scale``), read as x forward
  (the box's length and heading), y left (width), z up (height); ``up="y"`` reads a Y-up file (glTF's
  convention: +Y up, +Z forward, +X left) into it. The asset's box is the axis-aligned box of its
  vertices (of a Gaussian asset: of the centres of its Gaussians with opacity at least
  ``BOX_MIN_OPACITY``) in that frame, each side at least ``MIN_BOX_SIDE_M``.
- **Placement** (:class:`AssetPlacement`): keyframes of ``(timestamp_micros, world_from_asset)``.
  One keyframe places the asset still for the whole scene. With several, it moves along the path
  they make: position linear and rotation slerped between consecutive keyframes; before the first
  keyframe it waits at the first pose and after the last it stays at the last (held, not hidden: the
  asset is in every frame). Its velocity is the path's (a finite difference over
  ``VELOCITY_STEP_MICROS`` inside the segment at that time; zero while held).
- **Insertion** (:func:`insert_asset`): the asset's Gaussians at their world pose at time ``t``
  joined to the scene's. They move at the path's velocity from there (the scene model's constant
  velocities), so cameras firing shortly after ``t`` see them where the path goes. The rasterizer
  sorts all Gaussians by depth, so the asset hides what is behind it and is hidden by what is in
  front of it.
- **Labels** (:func:`asset_box`, :func:`with_inserted_box`): the asset's box in the world at time
  ``t`` (centre, size, heading, full orientation, velocity; status ``annotated``: it is exact, not
  interpolated; LiDAR points -1, the sweep is not edited) joins the frame's boxes.

Poses on the command line (:func:`parse_keyframe`): ``x,y,z[,yaw_deg][@t_s]``, metres and degrees
(heading about +z, counter-clockwise seen from above), at ``t_s`` seconds after the scene's first
frame; in the world frame of the cache or, with ``frame="ego"``, in the ego frame of the scene's
first frame (``10,0,0`` is ten metres ahead of where the car starts). A path file
(:func:`load_path_file`, JSON or YAML)::

    keyframes:                       # or the list itself
      - t_s: 0.0                     # |t_s| <= 1e6; or timestamp_micros: 1700000000000000 (one kind per file)
        xyz: [10.0, 2.0, 0.0]        # metres
        yaw_deg: 90                  # optional, default 0
      - t_s: 2.0
        world_from_asset: [[1, 0, 0, 20], [0, 1, 0, 2], [0, 0, 1, 0], [0, 0, 0, 1]]   # instead of xyz

Every refusal is an :class:`AssetError` naming the file (or the pose text), the keyframe and what is
wrong.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import yaml

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.records import (
    BOX_STATUSES,
    MAX_BOX_SIZE_M,
    MAX_USER_MICROS,
    Boxes,
    InvalidRecord,
    check_transform,
)
from phigenesis.export.ply import PlyError, scene_from_ply
from phigenesis.infer.asset_files import AssetError, AssetFolder, check_mesh_file, check_textures
from phigenesis.models.gaussians import GaussianScene
from phigenesis.user_files import check_keys, is_number, matrix_problem, read_small_file

log = logging.getLogger(__name__)

#: Most surface Gaussians one mesh asset becomes (the spacing widens to stay within it).
MAX_MESH_GAUSSIANS = 200_000
#: Most faces of a mesh asset (bigger meshes are refused: decimate them first).
MAX_FACES = 5_000_000
#: Most Gaussians of a Gaussian (3DGS PLY) asset.
MAX_ASSET_GAUSSIANS = 10_000_000
#: Default spacing of the surface Gaussians: the mesh's bounding-box diagonal over this.
DEFAULT_SPACING_DIVISOR = 100.0
#: Standard deviation of a disc within its face, in units of the spacing.
DISC_SCALE = 0.7
#: Standard deviation of a disc along its face normal, in units of the spacing.
DISC_THICKNESS = 1e-3
#: Opacity of a surface Gaussian (solid).
DISC_OPACITY = 0.99
#: Colour of a mesh without colours or texture (RGB in [0, 1]).
GREY = (0.5, 0.5, 0.5)
#: Logit of the asset's class in its Gaussians' semantic logits (as ``scene_from_ply``'s one-hot).
ONE_HOT_LOGIT = 10.0
#: Gaussians of a Gaussian asset below this opacity do not count for its box (floaters).
BOX_MIN_OPACITY = 0.1
#: Smallest side of an asset's box, metres (a flat mesh still has a valid box).
MIN_BOX_SIDE_M = 0.01
#: Half-width of the finite difference that gives the path's velocity, microseconds.
VELOCITY_STEP_MICROS = 1000
#: Largest path file read, bytes.
MAX_PATH_FILE_BYTES = 1 << 20
#: Most keyframes of a path.
MAX_KEYFRAMES = 10_000
#: Largest |t_s| of a keyframe, seconds after the scene's first frame (about 11.6 days).
MAX_PATH_SECONDS = 1e6
#: Properties that make a PLY a 3D Gaussian Splatting file rather than a mesh.
GAUSSIAN_PLY_PROPERTIES = ("scale_0", "rot_0", "opacity", "f_dc_0")

UpAxis = Literal["z", "y"]
PoseFrame = Literal["world", "ego"]

#: asset_from_file of a Y-up file (glTF: +Y up, +Z forward, +X left) into x forward, y left, z up.
_Y_UP = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: The plastic number's inverse powers: the R2 low-discrepancy sequence in the unit square.
_R2 = (1 / 1.32471795724474602596, 1 / 1.32471795724474602596**2)


# --------------------------------------------------------------------------------------------
# Assets


@dataclass(frozen=True, eq=False)
class Asset:
    """An asset ready to insert: Gaussians in its own frame and its box there.

    Attributes:
        name: the file's stem.
        path: the file it was read from.
        kind: ``"mesh"`` (surface Gaussians made from a mesh) or ``"gaussians"`` (a 3DGS PLY).
        gaussians: the N Gaussians in the asset frame (metres; static, ``time_s`` 0, time origin 0,
            semantic logits (N, K) one-hot of ``class_id``), on the CPU.
        box_center_local: (3,) float64 centre of the asset's axis-aligned box, asset frame, metres.
        box_size_lwh: (3,) float64 its sides along x, y, z (length, width, height), metres.
        class_id: unified-taxonomy class of the asset (its box's and its Gaussians').
        spacing_m: the surface Gaussians' spacing of a mesh asset (None for a Gaussian asset).
    """

    name: str
    path: Path
    kind: Literal["mesh", "gaussians"]
    gaussians: GaussianScene
    box_center_local: np.ndarray
    box_size_lwh: np.ndarray
    class_id: int
    spacing_m: float | None = None


def class_id_of(class_name: str) -> int:
    """The unified-taxonomy id of ``class_name``; AssetError naming the classes otherwise."""
    if class_name not in tx.CLASS_IDS:
        raise AssetError(f"unknown asset class {class_name!r}; the classes are {', '.join(tx.CLASS_NAMES)}")
    return tx.CLASS_IDS[class_name]


def load_asset(
    path: str | os.PathLike[str],
    *,
    class_name: str,
    spacing_m: float | None = None,
    scale: float = 1.0,
    up: UpAxis = "z",
    num_classes: int = tx.NUM_CLASSES,
) -> Asset:
    """Reads an asset file as Gaussians in its own frame (see the module docstring).

    Args:
        path: a 3DGS PLY, or a mesh: .obj, .glb, .gltf, .ply, .stl or .off (not compressed).
        class_name: the asset's class, one of :data:`phigenesis.taxonomy.CLASS_NAMES`.
        spacing_m: distance between neighbouring surface Gaussians of a mesh, metres after
            ``scale`` (default: the mesh's bounding-box diagonal / 100); it widens so that at most
            :data:`MAX_MESH_GAUSSIANS` are made (logged). Unused for a Gaussian asset.
        scale: the file's units in metres (0.01 for a file in centimetres); scales the Gaussians too.
        up: ``"z"`` (the file is x forward, y left, z up) or ``"y"`` (glTF's Y-up, +Z forward).
        num_classes: K of the semantic logits (19, or 0 for none).

    Raises:
        AssetError: naming the file, for a missing or unreadable file, a compressed file or another
            format, a header claiming more than the file holds (or more Gaussians than
            :data:`MAX_ASSET_GAUSSIANS`), a glTF reference to what does not exist or lies outside the
            asset's folder, a texture of more than ``MAX_TEXTURE_PIXELS``, a file with no faces (or
            no Gaussians), non-finite vertices or Gaussians, a zero-size or too-large asset, too
            many faces, an unknown class, or a non-positive scale or spacing.
    """
    path = Path(path)
    class_id = class_id_of(class_name)
    if not (math.isfinite(scale) and scale > 0):
        raise AssetError(f"{path}: scale must be a positive number, got {scale}")
    if spacing_m is not None and not (math.isfinite(spacing_m) and spacing_m > 0):
        raise AssetError(f"{path}: spacing must be a positive number of metres, got {spacing_m}")
    if up not in ("z", "y"):
        raise AssetError(f"{path}: up must be 'z' or 'y', got {up!r}")
    if not path.is_file():
        what = "not a regular file; an asset is a file" if path.exists() else "no such asset file"
        raise AssetError(f"{path}: {what}")
    rotation = _Y_UP if up == "y" else np.eye(3)
    if _is_gaussian_ply(path):
        return _gaussian_asset(path, class_id, scale, rotation, num_classes)
    return _mesh_asset(path, class_id, spacing_m, scale, rotation, num_classes)


def _is_gaussian_ply(path: Path) -> bool:
    """Whether ``path`` is a PLY whose header declares the 3DGS vertex properties."""
    with path.open("rb") as f:
        head = f.read(1 << 20)
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        return False
    header = head.split(b"end_header", 1)[0].decode("ascii", errors="replace")
    names = {m.group(1) for m in re.finditer(r"^property\s+\S+\s+(\S+)\s*$", header, re.M)}
    return all(p in names for p in GAUSSIAN_PLY_PROPERTIES)


def _logits(n: int, class_id: int, num_classes: int) -> torch.Tensor:
    logits = torch.zeros(n, num_classes)
    if num_classes:
        logits[:, class_id] = ONE_HOT_LOGIT
    return logits


def _static_scene(
    means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray, colors: np.ndarray,
    class_id: int, num_classes: int,
) -> GaussianScene:  # fmt: skip
    n = len(means)

    def f32(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))

    return GaussianScene(
        means=f32(means),
        quats=f32(quats),
        scales=f32(scales),
        opacities=f32(opacities),
        colors=f32(colors),
        semantic_logits=_logits(n, class_id, num_classes),
        velocity=torch.zeros(n, 3),
        dynamic=torch.zeros(n, dtype=torch.bool),
        time_s=torch.zeros(n),
    )


def _box(path: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and sides (each at least MIN_BOX_SIDE_M) of the axis-aligned box of ``points``."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = hi - lo
    if not float(np.linalg.norm(size)) > 0:
        raise AssetError(f"{path}: the asset has zero size (all its points at {_fmt(lo)})")
    if size.max() > MAX_BOX_SIZE_M:
        raise AssetError(
            f"{path}: the asset is {_fmt(size)} m, beyond the {MAX_BOX_SIZE_M:g} m a box may be "
            "(is the scale right?)"
        )
    return (lo + hi) / 2, np.maximum(size, MIN_BOX_SIDE_M)


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v).ravel()) + "]"


def _gaussian_asset(path: Path, class_id: int, scale: float, rotation: np.ndarray, k: int) -> Asset:
    try:
        scene = scene_from_ply(path, max_vertices=MAX_ASSET_GAUSSIANS)
    except PlyError as e:
        why = str(e).removeprefix(f"{path}: ")
        raise AssetError(f"{path}: not a readable 3D Gaussian Splatting PLY: {why}") from None
    n = len(scene)
    if n == 0:
        raise AssetError(f"{path}: the Gaussian PLY has no Gaussians")
    values = {
        name: getattr(scene, name).double().numpy()
        for name in ("means", "quats", "scales", "opacities", "colors")
    }
    bad = ~np.all([np.isfinite(v.reshape(n, -1)).all(axis=1) for v in values.values()], axis=0)
    if bad.any():
        raise AssetError(f"{path}: {int(bad.sum())} of {n} Gaussians have non-finite values")
    means = values["means"] @ rotation.T * scale
    quats = geometry.quaternion_multiply(geometry.matrix_to_quaternion(rotation), values["quats"])
    gaussians = _static_scene(
        means, quats, values["scales"] * scale, values["opacities"], values["colors"], class_id, k
    )
    solid = values["opacities"] >= BOX_MIN_OPACITY
    center, size = _box(path, means[solid] if solid.any() else means)
    return Asset(path.stem, path, "gaussians", gaussians, center, size, class_id)


def _mesh_asset(
    path: Path, class_id: int, spacing_m: float | None, scale: float, rotation: np.ndarray, k: int
) -> Asset:
    meshes = _read_meshes(path)
    vertices = [m.vertices.view(np.ndarray).astype(np.float64) @ rotation.T * scale for m in meshes]
    every = np.concatenate(vertices)
    if not np.isfinite(every).all():
        bad = int((~np.isfinite(every).all(axis=1)).sum())
        raise AssetError(f"{path}: {bad} vertices have non-finite coordinates")
    faces = [np.asarray(m.faces, np.int64) for m in meshes]
    triangles = [v[f] for v, f in zip(vertices, faces, strict=True)]  # (F, 3 corners, 3)
    areas = np.concatenate([_areas(t) for t in triangles])
    total = float(areas.sum())
    if not total > 0:
        raise AssetError(f"{path}: the mesh has zero surface area (every face is degenerate)")
    center, size = _box(path, np.concatenate([t.reshape(-1, 3) for t in triangles]))
    spacing = float(np.linalg.norm(size) / DEFAULT_SPACING_DIVISOR) if spacing_m is None else float(spacing_m)
    count = max(1, math.ceil(total / spacing**2))
    if count > MAX_MESH_GAUSSIANS:
        wider = math.sqrt(total / MAX_MESH_GAUSSIANS)
        log.info(
            "%s: %d Gaussians at %.4g m spacing would be more than %d; spacing widened to %.4g m",
            path, count, spacing, MAX_MESH_GAUSSIANS, wider,
        )  # fmt: skip
        spacing, count = wider, MAX_MESH_GAUSSIANS
    per_face = _allocate(areas, count)
    parts, start = [], 0
    for mesh, tri in zip(meshes, triangles, strict=True):
        n_faces = len(tri)
        counts = per_face[start : start + n_faces]
        start += n_faces
        if counts.sum():
            parts.append(_surface_samples(mesh, tri, counts))
    means = np.concatenate([p[0] for p in parts])
    frames = np.concatenate([p[1] for p in parts])  # (N, 3, 3) asset_from_disc, columns t1, t2, normal
    colors = np.concatenate([p[2] for p in parts])
    n = len(means)
    scales = np.tile([DISC_SCALE * spacing, DISC_SCALE * spacing, DISC_THICKNESS * spacing], (n, 1))
    quats = geometry.matrix_to_quaternion(frames)
    gaussians = _static_scene(means, quats, scales, np.full(n, DISC_OPACITY), colors, class_id, k)
    log.debug("%s: %d faces -> %d surface Gaussians at %.4g m spacing", path, len(areas), n, spacing)
    return Asset(path.stem, path, "mesh", gaussians, center, size, class_id, spacing)


def _read_meshes(path: Path) -> list[Any]:
    """The triangle meshes of a file trimesh reads, node transforms applied (a scene's meshes):
    the file checked first (:func:`~phigenesis.infer.asset_files.check_mesh_file`), the files it
    refers to read from its own folder only, its textures checked before they are decoded."""
    check_mesh_file(path, MAX_FACES)
    # optional heavy dependency: only for mesh assets
    import trimesh

    folder = AssetFolder(path)
    try:
        loaded = trimesh.load(path, process=False, resolver=folder)
    except Exception as e:  # trimesh raises anything from its many loaders
        folder.raise_refused()
        raise AssetError(f"{path}: not a mesh trimesh can read ({type(e).__name__}: {e})") from None
    folder.raise_refused()
    if isinstance(loaded, trimesh.Scene):
        check_textures(path, loaded.geometry.values())
        geoms = list(loaded.dump()) if loaded.geometry else []  # copies (decodes) the textures
    else:
        check_textures(path, [loaded])
        geoms = [loaded]
    meshes = [g for g in geoms if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        kinds = sorted({type(g).__name__ for g in geoms})
        what = f"only {', '.join(kinds)}" if kinds else "nothing"
        raise AssetError(f"{path}: no triangle faces to make Gaussians of (the file holds {what})")
    n_faces = sum(len(m.faces) for m in meshes)
    if n_faces > MAX_FACES:
        raise AssetError(f"{path}: {n_faces} faces, more than {MAX_FACES}; decimate the mesh first")
    for m in meshes:
        f = np.asarray(m.faces)
        if f.min() < 0 or f.max() >= len(m.vertices):
            raise AssetError(f"{path}: a face refers to a vertex the mesh does not have")
    return meshes


def _areas(tri: np.ndarray) -> np.ndarray:
    """(F,) areas of triangles (F, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _allocate(areas: np.ndarray, count: int) -> np.ndarray:
    """(F,) int samples per face, ``count`` in all, proportional to area (largest remainders)."""
    share = areas / areas.sum() * count
    base = np.floor(share).astype(np.int64)
    left = count - int(base.sum())
    if left > 0:
        order = np.argsort(-(share - base), kind="stable")
        base[order[:left]] += 1
    return base


def _surface_samples(mesh: Any, tri: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, ...]:
    """Points, disc frames (N, 3, 3) and colours (N, 3) of ``counts`` samples on each face."""
    face = np.repeat(np.arange(len(tri)), counts)
    # The j-th sample of a face takes the j-th point of the R2 sequence, folded into the triangle.
    first = np.cumsum(counts) - counts
    j = np.arange(len(face)) - first[face] + 1
    u = np.mod(0.5 + _R2[0] * j, 1.0)
    v = np.mod(0.5 + _R2[1] * j, 1.0)
    fold = u + v > 1
    u, v = np.where(fold, 1 - u, u), np.where(fold, 1 - v, v)
    bary = np.stack([1 - u - v, u, v], axis=1)  # (N, 3)
    corners = tri[face]  # (N, 3, 3)
    points = np.einsum("nc,ncd->nd", bary, corners)
    e1 = corners[:, 1] - corners[:, 0]
    normal = np.cross(e1, corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    t1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    frames = np.stack([t1, t2, normal], axis=2)
    return points, frames, _sample_colors(mesh, face, bary)


def _sample_colors(mesh: Any, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N, 3) RGB in [0, 1] of the mesh at the samples (face ``face``, barycentric ``bary``)."""
    # optional heavy dependency: only for mesh assets
    import trimesh

    visual = mesh.visual
    if getattr(visual, "kind", None) == "texture":
        material = getattr(visual, "material", None)
        image = getattr(material, "image", None)
        if image is None:
            image = getattr(material, "baseColorTexture", None)
        uv = getattr(visual, "uv", None)
        if image is not None and uv is not None and len(uv) == len(mesh.vertices):
            corners = np.asarray(uv, np.float64)[np.asarray(mesh.faces)[face]]  # (N, 3, 2)
            at = np.einsum("nc,ncd->nd", bary, corners)
            return trimesh.visual.color.uv_to_color(at, image)[:, :3] / 255.0
        # A material without a texture (or whose UVs do not fit the mesh): its main colour.
        main = np.asarray(getattr(material, "main_color", None) if material is not None else None)
        rgb = main[:3] / 255.0 if main.ndim == 1 and len(main) >= 3 else GREY
        return np.tile(np.asarray(rgb, np.float64), (len(face), 1))
    kind = getattr(visual, "kind", None)
    if kind == "face":
        return np.asarray(visual.face_colors, np.float64)[face, :3] / 255.0
    if kind == "vertex":
        vc = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
        return np.einsum("nc,ncd->nd", bary, vc[np.asarray(mesh.faces)[face]])
    return np.tile(GREY, (len(face), 1))


# --------------------------------------------------------------------------------------------
# Placement


@dataclass(frozen=True)
class Keyframe:
    """One pose of a path as the user gave it: the time (``t_s`` seconds after the scene's first
    frame, or ``timestamp_micros``, or neither for a single pose) and ``pose`` (4, 4), the asset's
    pose in the world (or in the first frame's ego frame: :meth:`AssetPlacement.from_keyframes`)."""

    pose: tuple[tuple[float, ...], ...]  # (4, 4) row-major, a tuple so the keyframe is hashable
    t_s: float | None = None
    timestamp_micros: int | None = None

    @property
    def matrix(self) -> np.ndarray:
        return np.array(self.pose, np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "pose": [list(r) for r in self.pose],
            "t_s": self.t_s,
            "timestamp_micros": self.timestamp_micros,
        }


def _keyframe(pose: np.ndarray, t_s: float | None = None, timestamp_micros: int | None = None) -> Keyframe:
    return Keyframe(tuple(tuple(float(x) for x in row) for row in pose), t_s, timestamp_micros)


@dataclass(frozen=True, eq=False)
class AssetPlacement:
    """Where an asset is at any time: keyframes ``(times_micros[i], world_from_asset[i])``.

    Attributes:
        times_micros: (K,) int64 strictly increasing keyframe times, microseconds.
        world_from_asset: (K, 4, 4) float64 rigid poses of the asset frame in the world.

    One keyframe: still. Several: linear in position and slerped in rotation between consecutive
    keyframes, held at the first pose before the first keyframe and at the last after the last.
    Raises AssetError (naming ``where`` and the keyframe) for non-finite or non-rigid poses or times
    that do not increase.
    """

    times_micros: np.ndarray
    world_from_asset: np.ndarray
    where: str = "placement"

    def __post_init__(self) -> None:
        times = np.asarray(self.times_micros)
        poses = np.asarray(self.world_from_asset)
        if times.ndim != 1 or not 1 <= len(times) <= MAX_KEYFRAMES:
            raise AssetError(f"{self.where}: needs 1 to {MAX_KEYFRAMES} keyframes, got {times.shape}")
        if poses.shape != (len(times), 4, 4):
            raise AssetError(f"{self.where}: poses must be ({len(times)}, 4, 4), got {poses.shape}")
        if not np.issubdtype(times.dtype, np.integer):
            raise AssetError(f"{self.where}: keyframe times must be integer microseconds, got {times.dtype}")
        _check_micros(self.where, [int(t) for t in times])
        checked = np.stack([_rigid(f"{self.where}: keyframe {i}", p) for i, p in enumerate(poses)])
        steps = np.diff(times)
        if (steps <= 0).any():
            i = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise AssetError(
                f"{self.where}: keyframe {i}: time {int(times[i])} us is not after keyframe {i - 1}'s "
                f"{int(times[i - 1])} us (keyframe times must increase)"
            )
        object.__setattr__(self, "times_micros", times.astype(np.int64))
        object.__setattr__(self, "world_from_asset", checked)
        object.__setattr__(self, "_quats", geometry.matrix_to_quaternion(checked[:, :3, :3]))

    @classmethod
    def still(cls, world_from_asset: np.ndarray, timestamp_micros: int = 0) -> AssetPlacement:
        """An asset that stays at ``world_from_asset`` for the whole scene."""
        return cls(np.array([timestamp_micros], np.int64), np.asarray(world_from_asset, np.float64)[None])

    @classmethod
    def from_keyframes(
        cls,
        keyframes: Sequence[Keyframe],
        start_micros: int,
        world_from_frame: np.ndarray | None = None,
        where: str = "placement",
    ) -> AssetPlacement:
        """The placement of ``keyframes`` in a scene whose first frame is at ``start_micros``:
        ``t_s`` counts from it; a keyframe without a time (only one allowed) is at it. Poses are
        ``world_from_frame @ pose`` (``world_from_frame``: the first frame's world_from_ego to give
        poses in its ego frame; None: poses are in the world)."""
        if not keyframes:
            raise AssetError(f"{where}: no keyframe")
        untimed = [i for i, k in enumerate(keyframes) if k.t_s is None and k.timestamp_micros is None]
        if untimed and len(keyframes) > 1:
            raise AssetError(
                f"{where}: keyframe {untimed[0]} has no time; a path of several poses needs one each"
            )
        times = [
            int(start_micros) + round(_seconds(f"{where}: keyframe {i}", k.t_s) * 1e6) if k.t_s is not None
            else int(start_micros) if k.timestamp_micros is None else int(k.timestamp_micros)
            for i, k in enumerate(keyframes)
        ]  # fmt: skip
        _check_micros(where, times)
        base = np.eye(4) if world_from_frame is None else np.asarray(world_from_frame, np.float64)
        poses = np.stack([base @ _rigid(f"{where}: keyframe {i}", k.matrix) for i, k in enumerate(keyframes)])
        return cls(np.array(times, np.int64), poses, where)

    @property
    def moves(self) -> bool:
        """Whether the asset's pose changes over time."""
        return bool(np.any(self.world_from_asset != self.world_from_asset[:1]))

    def pose_at(self, t_micros: int) -> np.ndarray:
        """(4, 4) float64 world_from_asset at ``t_micros`` (a keyframe's pose exactly at its time)."""
        quats = self._quats  # type: ignore[attr-defined]
        return geometry.pose_at_time(self.times_micros, self.world_from_asset, quats, t_micros)

    def _step(self, t_micros: int) -> tuple[int, int]:
        """The times around ``t_micros`` that its velocity is differenced over (equal while held)."""
        times = self.times_micros
        if t_micros < times[0] or t_micros >= times[-1]:
            return int(t_micros), int(t_micros)
        i = int(np.searchsorted(times, t_micros, side="right")) - 1  # segment [times[i], times[i + 1])
        a = max(int(t_micros) - VELOCITY_STEP_MICROS, int(times[i]))
        b = min(int(t_micros) + VELOCITY_STEP_MICROS, int(times[i + 1]))
        return a, b

    def velocity_at(self, t_micros: int, points_local: np.ndarray | None = None) -> np.ndarray:
        """World-frame velocity (m/s) at ``t_micros`` of the asset-frame points ``points_local``
        (N, 3) -> (N, 3), or of the asset's origin -> (3,): the path's finite difference inside the
        segment at ``t_micros`` (the right one at a keyframe); zero before the first keyframe and
        from the last on."""
        pts = np.zeros((1, 3)) if points_local is None else np.asarray(points_local, np.float64)
        a, b = self._step(t_micros)
        if a == b:
            v = np.zeros_like(pts)
        else:
            moved = geometry.transform_points(self.pose_at(b), pts) - geometry.transform_points(
                self.pose_at(a), pts
            )
            v = moved / ((b - a) * 1e-6)
        return v[0] if points_local is None else v


def _check_micros(where: str, times: Sequence[int]) -> None:
    """AssetError naming ``where`` and the keyframe unless every time (microseconds) is within
    +-MAX_USER_MICROS, so that times and their differences stay int64."""
    for i, t in enumerate(times):
        if not -MAX_USER_MICROS < t < MAX_USER_MICROS:
            raise AssetError(f"{where}: keyframe {i}: time {t} us is beyond +-{MAX_USER_MICROS} us")


def _rigid(where: str, pose: Any) -> np.ndarray:
    try:
        return check_transform("world_from_asset", pose)
    except InvalidRecord as e:
        raise AssetError(f"{where}: {e}") from None


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_POSE_RE = re.compile(rf"\s*({_NUMBER}(?:\s*,\s*{_NUMBER}){{2,3}})\s*(?:@\s*({_NUMBER})\s*)?")


def parse_keyframe(text: str) -> Keyframe:
    """A keyframe from ``"x,y,z[,yaw_deg][@t_s]"``: position in metres, heading in degrees about +z
    (counter-clockwise seen from above; default 0), time ``t_s`` in seconds after the scene's first
    frame (default: none, for a single still pose). E.g. ``"12,-3.5,0,90@1.5"``."""
    m = _POSE_RE.fullmatch(text)
    if m is None:
        raise AssetError(f"pose {text!r}: expected x,y,z[,yaw_deg][@t_s] (metres, degrees, seconds)")
    values = [float(x) for x in m.group(1).split(",")]
    t_s = None if m.group(2) is None else float(m.group(2))
    if not all(math.isfinite(v) for v in [*values, 0.0 if t_s is None else t_s]):
        raise AssetError(f"pose {text!r}: every number must be finite")
    if t_s is not None:
        _seconds(f"pose {text!r}", t_s)
    yaw = math.radians(values[3]) if len(values) == 4 else 0.0
    return _keyframe(geometry.yaw_pose_to_transform(values[:3], yaw), t_s)


def parse_pose(text: str) -> np.ndarray:
    """(4, 4) float64 pose of ``"x,y,z[,yaw_deg]"`` (see :func:`parse_keyframe`; no time)."""
    key = parse_keyframe(text)
    if key.t_s is not None:
        raise AssetError(f"pose {text!r}: a pose takes no @time here")
    return key.matrix


def load_path_file(path: str | os.PathLike[str]) -> list[Keyframe]:
    """The keyframes of a JSON or YAML path file (format in the module docstring; a regular file of
    at most :data:`MAX_PATH_FILE_BYTES`), checked: each has one time (``t_s`` within
    +-:data:`MAX_PATH_SECONDS`, or ``timestamp_micros`` in [0, 2^62); the same kind throughout,
    increasing), and ``xyz`` (with an optional ``yaw_deg``) or ``world_from_asset``, plain finite
    numbers (not strings), rigid. Refusals are AssetErrors naming the file and the keyframe."""
    path = Path(path)
    text = read_small_file(path, "path file", AssetError, MAX_PATH_FILE_BYTES)
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError, RecursionError) as e:
        raise AssetError(
            f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: {e}"
        ) from None
    if isinstance(data, Mapping):
        data = check_keys(data, ["keyframes"], str(path), AssetError, noun="field").get("keyframes")
    if not isinstance(data, list) or not 1 <= len(data) <= MAX_KEYFRAMES:
        got = f"{len(data)} keyframes" if isinstance(data, list) else type(data).__name__
        raise AssetError(f"{path}: keyframes must be a list of 1 to {MAX_KEYFRAMES} keyframes, got {got}")
    keyframes = [_keyframe_from_dict(f"{path}: keyframe {i}", k) for i, k in enumerate(data)]
    kinds = {"t_s" if k.t_s is not None else "timestamp_micros" for k in keyframes}
    if len(kinds) > 1:
        raise AssetError(f"{path}: keyframes mix t_s and timestamp_micros; use one kind")
    times = [k.t_s if k.t_s is not None else k.timestamp_micros for k in keyframes]
    for i in range(1, len(times)):
        if not times[i] > times[i - 1]:  # type: ignore[operator]
            raise AssetError(
                f"{path}: keyframe {i}: time {times[i]} is not after keyframe {i - 1}'s {times[i - 1]} "
                "(keyframe times must increase)"
            )
    return keyframes


_KEYFRAME_KEYS = ("t_s", "timestamp_micros", "xyz", "yaw_deg", "world_from_asset")


def _number(where: str, name: str, value: Any) -> float:
    if not is_number(value):
        raise AssetError(f"{where}: {name} must be a finite number, got {value!r}")
    return float(value)


def _seconds(where: str, value: Any) -> float:
    """A keyframe's ``t_s`` (seconds after the scene's first frame), at most :data:`MAX_PATH_SECONDS`
    either way; AssetError naming ``where`` otherwise."""
    t_s = _number(where, "t_s", value)
    if abs(t_s) > MAX_PATH_SECONDS:
        raise AssetError(
            f"{where}: t_s {t_s!r} s is beyond +-{MAX_PATH_SECONDS:g} s of the scene's first frame"
        )
    return t_s


def _keyframe_from_dict(where: str, d: Any) -> Keyframe:
    check_keys(d, _KEYFRAME_KEYS, where, AssetError, noun="field")
    if ("t_s" in d) == ("timestamp_micros" in d):
        raise AssetError(f"{where}: needs exactly one of t_s and timestamp_micros")
    t_s, micros = None, None
    if "t_s" in d:
        t_s = _seconds(where, d["t_s"])
    else:
        value = d["timestamp_micros"]
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < MAX_USER_MICROS:
            raise AssetError(
                f"{where}: timestamp_micros must be an integer in [0, {MAX_USER_MICROS}), got {value!r}"
            )
        micros = int(value)
    if ("xyz" in d) == ("world_from_asset" in d):
        raise AssetError(f"{where}: needs exactly one of xyz (with yaw_deg) and world_from_asset")
    if "world_from_asset" in d:
        if "yaw_deg" in d:
            raise AssetError(f"{where}: yaw_deg goes with xyz, not world_from_asset")
        problem = matrix_problem(d["world_from_asset"], 4, 4)
        if problem is not None:
            raise AssetError(f"{where}: world_from_asset {problem}")
        pose = np.array(d["world_from_asset"], np.float64)
    else:
        xyz = d["xyz"]
        if not (isinstance(xyz, list) and len(xyz) == 3):
            raise AssetError(f"{where}: xyz must be 3 numbers, got {xyz!r}")
        position = [_number(where, "xyz", x) for x in xyz]
        yaw = math.radians(_number(where, "yaw_deg", d.get("yaw_deg", 0.0)))
        pose = geometry.yaw_pose_to_transform(position, yaw)
    return _keyframe(_rigid(where, pose), t_s, micros)


# --------------------------------------------------------------------------------------------
# Insertion and labels


def placed_gaussians(
    asset: Asset, placement: AssetPlacement, t_micros: int, like: GaussianScene
) -> GaussianScene:
    """The asset's Gaussians in the world at ``t_micros``, as a scene like ``like`` (its time
    origin, class count, device and whether it has a depth entropy): reference time ``t``,
    moving at the path's velocity (each Gaussian its own point's), dynamic if the path moves."""
    g = asset.gaussians
    n = len(g)
    pose = placement.pose_at(t_micros)
    local = g.means.double().numpy()
    means = geometry.transform_points(pose, local)  # (N, 3)
    quats = geometry.quaternion_multiply(
        geometry.matrix_to_quaternion(pose[:3, :3]), g.quats.double().numpy()
    )
    velocity = placement.velocity_at(t_micros, local)  # (N, 3)
    k = like.num_classes
    if k == g.num_classes:
        logits = g.semantic_logits
    elif k == 0 or g.num_classes == 0:
        logits = _logits(n, asset.class_id, k)
    else:
        raise ValueError(f"placed_gaussians: the scene has {k} classes, the asset {g.num_classes}")
    device = like.means.device

    def f32(x: np.ndarray | torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=torch.float32).to(device)

    return GaussianScene(
        means=f32(means),
        quats=f32(quats),
        scales=g.scales.to(device),
        opacities=g.opacities.to(device),
        colors=g.colors.to(device),
        semantic_logits=logits.to(device),
        velocity=f32(velocity),
        dynamic=torch.full((n,), placement.moves, dtype=torch.bool, device=device),
        time_s=torch.full((n,), like.seconds(t_micros), dtype=torch.float32, device=device),
        time_origin_micros=like.time_origin_micros,
        depth_entropy=None if like.depth_entropy is None else torch.zeros(n, device=device),
    )


def insert_asset(
    scene: GaussianScene, asset: Asset, placement: AssetPlacement, t_micros: int
) -> GaussianScene:
    """``scene`` with the asset's Gaussians at their pose at ``t_micros`` added after its own
    (:func:`placed_gaussians`). Rendered at ``t_micros`` (``scene.seconds(t_micros)``), the asset is
    where the placement says; depth sorting in the rasterizer does the compositing."""
    return GaussianScene.concatenate([scene, placed_gaussians(asset, placement, t_micros, scene)])


def asset_box(
    asset: Asset, placement: AssetPlacement, t_micros: int, track_id: str = "inserted-0", instance_id: int = 0
) -> Boxes:
    """The asset's box at ``t_micros`` as one world-frame box: centre, sides (x, y, z of the asset
    frame), heading of the asset's +x, full orientation, velocity of the centre; class the
    asset's; status annotated; ``num_lidar_points`` -1 (the LiDAR sweep is not edited);
    ``instance_id`` 0 = none."""
    pose = placement.pose_at(t_micros)
    center = geometry.transform_points(pose, asset.box_center_local[None])
    velocity = placement.velocity_at(t_micros, asset.box_center_local[None])
    return Boxes(
        track_id=[track_id],
        class_id=np.array([asset.class_id], np.uint8),
        center_world=center,
        size_lwh=asset.box_size_lwh[None].astype(np.float64),
        yaw_world=np.array([geometry.matrix_yaw(pose[:3, :3])]),
        velocity_world=velocity,
        status=np.array([BOX_STATUSES.index("annotated")], np.uint8),
        instance_id=np.array([instance_id], np.uint16),
        num_lidar_points=np.array([-1], np.int32),
        orientation_world=geometry.matrix_to_quaternion(pose[:3, :3])[None],
    )


def with_inserted_box(boxes: Boxes, box: Boxes) -> Boxes:
    """``boxes`` with ``box`` appended; AssetError if one of its track ids is already there."""
    taken = sorted(set(boxes.track_id) & set(box.track_id))
    if taken:
        raise AssetError(f"inserted box track id {taken[0]!r} is already a box of the frame; choose another")
    return Boxes.concatenate([boxes, box])


@dataclass(frozen=True)
class InsertSpec:
    """An asset to insert into every frame a render writes (``phigenesis-render --insert``).

    Attributes:
        asset: the asset file (:func:`load_asset`).
        keyframes: its pose(s) (:func:`parse_keyframe`, :func:`load_path_file`).
        class_name: its class (its box's and its Gaussians').
        frame: ``"world"`` (poses in the cache's world frame) or ``"ego"`` (in the ego frame of
            each scene's first frame).
        scale, spacing_m, up: as :func:`load_asset`'s.
        track_id: its box's track id (unique in the frame).
    """

    asset: Path
    keyframes: tuple[Keyframe, ...]
    class_name: str
    frame: PoseFrame = "world"
    scale: float = 1.0
    spacing_m: float | None = None
    up: UpAxis = "z"
    track_id: str = "inserted-0"

    def load(self) -> Asset:
        """The asset, after checking the keyframes make a placement (before any scene is rendered)."""
        if self.frame not in ("world", "ego"):
            raise AssetError(f"{self.asset}: pose frame must be 'world' or 'ego', got {self.frame!r}")
        self.placement(0, np.eye(4))
        return load_asset(
            self.asset, class_name=self.class_name, spacing_m=self.spacing_m, scale=self.scale, up=self.up
        )

    def placement(self, start_micros: int, world_from_first_ego: np.ndarray) -> AssetPlacement:
        """The placement in a scene whose first frame is at ``start_micros`` and pose."""
        base = world_from_first_ego if self.frame == "ego" else None
        return AssetPlacement.from_keyframes(self.keyframes, start_micros, base, f"{self.asset} placement")

    def to_dict(self) -> dict[str, Any]:
        """What a manifest records (the caller adds the file's SHA-256)."""
        return {
            "asset": str(Path(self.asset).resolve()),
            "keyframes": [k.to_dict() for k in self.keyframes],
            "class_name": self.class_name,
            "frame": self.frame,
            "scale": float(self.scale),
            "spacing_m": self.spacing_m,
            "up": self.up,
            "track_id": self.track_id,
        }
