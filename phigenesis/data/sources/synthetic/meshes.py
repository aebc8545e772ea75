"""Triangle meshes with per-face labels, built from trimesh primitives and ribbons.

A :class:`LabelledMesh` carries, for every face, the material (colour, texture, LiDAR
reflectivity), the semantic class and the instance id, so a ray hit's primitive id gives the
truth labels directly. Object meshes are built in their body frame (x forward, y left, z up,
origin at the box centre); the static world is built in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.sources.synthetic.materials import MATERIAL_IDS


@dataclass
class LabelledMesh:
    """Triangles with per-face labels.

    Attributes:
        vertices: (V, 3) float64 metres.
        faces: (F, 3) int32 vertex indices.
        material: (F,) uint8 index into MATERIALS.
        semantic: (F,) uint8 unified class id.
        instance: (F,) uint16 instance id (0 for stuff).
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int32]
    material: NDArray[np.uint8]
    semantic: NDArray[np.uint8]
    instance: NDArray[np.uint16]

    @classmethod
    def empty(cls) -> LabelledMesh:
        return cls(
            np.zeros((0, 3)),
            np.zeros((0, 3), np.int32),
            np.zeros(0, np.uint8),
            np.zeros(0, np.uint8),
            np.zeros(0, np.uint16),
        )

    @classmethod
    def from_trimesh(
        cls, mesh: trimesh.Trimesh, material: str, semantic: int, instance: int = 0
    ) -> LabelledMesh:
        f = len(mesh.faces)
        return cls(
            np.asarray(mesh.vertices, dtype=np.float64),
            np.asarray(mesh.faces, dtype=np.int32),
            np.full(f, MATERIAL_IDS[material], np.uint8),
            np.full(f, semantic, np.uint8),
            np.full(f, instance, np.uint16),
        )

    @staticmethod
    def concatenate(meshes: list[LabelledMesh]) -> LabelledMesh:
        meshes = [m for m in meshes if len(m.faces)]
        if not meshes:
            return LabelledMesh.empty()
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return LabelledMesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]).astype(np.int32),
            np.concatenate([m.material for m in meshes]),
            np.concatenate([m.semantic for m in meshes]),
            np.concatenate([m.instance for m in meshes]),
        )

    def transformed(self, target_from_source: NDArray[np.float64]) -> LabelledMesh:
        return LabelledMesh(
            geometry.transform_points(target_from_source, self.vertices),
            self.faces,
            self.material,
            self.semantic,
            self.instance,
        )

    def with_instance(self, instance: int) -> LabelledMesh:
        return LabelledMesh(
            self.vertices,
            self.faces,
            self.material,
            self.semantic,
            np.full(len(self.faces), instance, np.uint16),
        )


def box(
    extents: tuple[float, float, float],
    center: tuple[float, float, float],
    material: str,
    semantic: int,
    yaw: float = 0.0,
) -> LabelledMesh:
    """Axis-aligned (then yawed) box of size ``extents`` centred at ``center``."""
    t = geometry.yaw_pose_to_transform(center, yaw)
    return LabelledMesh.from_trimesh(trimesh.creation.box(extents=extents, transform=t), material, semantic)


def cylinder(
    radius: float,
    height: float,
    center: tuple[float, float, float],
    material: str,
    semantic: int,
    axis: str = "z",
    sections: int = 10,
) -> LabelledMesh:
    """Cylinder along the x, y or z axis centred at ``center``."""
    t = np.eye(4)
    if axis == "y":
        t[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    elif axis == "x":
        t[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    t[:3, 3] = center
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=sections, transform=t)
    return LabelledMesh.from_trimesh(mesh, material, semantic)


def blob(
    radius: float,
    center: tuple[float, float, float],
    material: str,
    semantic: int,
    rng: np.random.Generator,
    roughness: float = 0.18,
) -> LabelledMesh:
    """An irregular sphere (tree canopy, bush): an icosphere with radially jittered vertices."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    v = np.asarray(mesh.vertices)
    v = v * (1.0 + roughness * rng.uniform(-1, 1, size=(len(v), 1))) * radius + np.asarray(center)
    return LabelledMesh(
        v,
        np.asarray(mesh.faces, np.int32),
        np.full(len(mesh.faces), MATERIAL_IDS[material], np.uint8),
        np.full(len(mesh.faces), semantic, np.uint8),
        np.zeros(len(mesh.faces), np.uint16),
    )


def ribbon(
    left_xyz: NDArray[np.float64], right_xyz: NDArray[np.float64], material: str, semantic: int
) -> LabelledMesh:
    """Quads between two polylines of equal length ``(K, 3)`` (roads, sidewalk tops, kerb faces)."""
    k = len(left_xyz)
    assert right_xyz.shape == (k, 3) and k >= 2, (left_xyz.shape, right_xyz.shape)
    vertices = np.concatenate([left_xyz, right_xyz]).astype(np.float64)
    i = np.arange(k - 1)
    a, b, c, d = i, i + 1, k + i, k + i + 1
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    f = len(faces)
    return LabelledMesh(
        vertices,
        faces,
        np.full(f, MATERIAL_IDS[material], np.uint8),
        np.full(f, semantic, np.uint8),
        np.zeros(f, np.uint16),
    )


# --------------------------------------------------------------------------------------------
# Objects, in their body frame (origin at the box centre, x forward).


def vehicle(size_lwh: NDArray[np.float64], class_id: int, rng: np.random.Generator) -> LabelledMesh:
    """A car, truck or bus of the given box size: body, cabin or windows, and wheels."""
    l, w, h = (float(x) for x in size_lwh)
    z0 = -h / 2  # ground
    clearance = 0.25 if class_id == tx.CAR else 0.4
    wheel_r = 0.32 if class_id == tx.CAR else 0.5
    parts = []
    if class_id == tx.CAR:
        body_h = 0.55 * h
        parts.append(
            box((l, w, body_h - clearance), (0, 0, z0 + (clearance + body_h) / 2), "car_paint", class_id)
        )
        cab_l = l * rng.uniform(0.45, 0.55)
        cab_x = -l * rng.uniform(0.02, 0.10)
        cab_h = h - body_h
        parts.append(
            box((cab_l, w * 0.9, cab_h * 0.8), (cab_x, 0, z0 + body_h + cab_h * 0.4), "glass", class_id)
        )
        parts.append(
            box(
                (cab_l * 0.95, w * 0.88, cab_h * 0.2),
                (cab_x, 0, z0 + body_h + cab_h * 0.9),
                "car_paint",
                class_id,
            )
        )
    elif class_id == tx.TRUCK:
        cab_l = 2.2
        parts.append(
            box(
                (cab_l - 0.04, w, h * 0.75 - clearance),
                (l / 2 - cab_l / 2 - 0.02, 0, z0 + (clearance + h * 0.75) / 2),
                "car_paint",
                class_id,
            )
        )
        # The windscreen stands 4 cm proud of the cab's front and ends flush with the box's front.
        parts.append(box((0.15, w * 0.85, h * 0.2), (l / 2 - 0.075, 0, z0 + h * 0.6), "glass", class_id))
        cargo_l = l - cab_l - 0.3
        parts.append(
            box(
                (cargo_l, w, h - clearance),
                (-l / 2 + cargo_l / 2, 0, z0 + (clearance + h) / 2),
                "facade_white",
                class_id,
            )
        )
    else:  # bus
        # The window band stands 2 cm proud of the body on each side, within the box's width.
        parts.append(
            box((l, w - 0.04, h - clearance), (0, 0, z0 + (clearance + h) / 2), "car_paint", class_id)
        )
        parts.append(box((l * 0.96, w, h * 0.3), (0, 0, z0 + h * 0.6), "glass", class_id))
    axle = l / 2 - max(0.8, 0.18 * l)
    for x in (axle, -axle):
        for y in (w / 2 - 0.15, -(w / 2 - 0.15)):
            parts.append(
                cylinder(wheel_r, 0.28, (x, y, z0 + wheel_r), "tyre", class_id, axis="y", sections=12)
            )
    return LabelledMesh.concatenate(parts)


def pedestrian(size_lwh: NDArray[np.float64]) -> LabelledMesh:
    """A person standing upright in a box of the given size: legs, torso, arms, head."""
    _, w, h = (float(x) for x in size_lwh)
    z0 = -h / 2
    leg_h, torso_h, head_r = 0.47 * h, 0.33 * h, 0.1 * h
    parts = [
        box((0.16, 0.14, leg_h), (0, w * 0.17, z0 + leg_h / 2), "clothing", tx.PERSON),
        box((0.16, 0.14, leg_h), (0, -w * 0.17, z0 + leg_h / 2), "clothing", tx.PERSON),
        box((0.26, w * 0.62, torso_h), (0, 0, z0 + leg_h + torso_h / 2), "clothing", tx.PERSON),
        box((0.1, 0.1, torso_h * 0.95), (0, w * 0.4, z0 + leg_h + torso_h / 2), "clothing", tx.PERSON),
        box((0.1, 0.1, torso_h * 0.95), (0, -w * 0.4, z0 + leg_h + torso_h / 2), "clothing", tx.PERSON),
    ]
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=head_r)
    sphere.apply_translation((0, 0, z0 + leg_h + torso_h + head_r * 0.95))
    parts.append(LabelledMesh.from_trimesh(sphere, "skin", tx.PERSON))
    return LabelledMesh.concatenate(parts)


#: The ego car's body in the ego frame (origin on the ground below the rear axle), metres.
EGO_BODY_LENGTH_M = 4.1
EGO_BODY_REAR_M = -0.6


def ego_body() -> LabelledMesh:
    """The ego car, labelled ignore (255): a low hood in front of the cameras, a cabin behind them.

    Roof cameras (Waymo) do not see it; cameras low on the car (nuScenes' rear camera) see parts
    of it, and the LiDAR's lowest beams hit it, as on real vehicles.
    """
    front = EGO_BODY_REAR_M + EGO_BODY_LENGTH_M
    parts = [
        box(
            (EGO_BODY_LENGTH_M, 1.8, 0.45),
            ((EGO_BODY_REAR_M + front) / 2, 0, 0.525),
            "ego_paint",
            tx.IGNORE_ID,
        ),
        box((2.8, 1.8, 0.2), (EGO_BODY_REAR_M + 1.4, 0, 0.85), "ego_paint", tx.IGNORE_ID),
        box((1.8, 1.6, 0.35), (0.6, 0, 1.125), "glass", tx.IGNORE_ID),
        box((1.7, 1.5, 0.04), (0.6, 0, 1.32), "ego_paint", tx.IGNORE_ID),
    ]
    for x in (0.0, 2.6):
        for y in (0.78, -0.78):
            parts.append(cylinder(0.31, 0.22, (x, y, 0.31), "tyre", tx.IGNORE_ID, axis="y", sections=12))
    return LabelledMesh.concatenate(parts)
