"""Surface materials of the synthetic world: colour, procedural texture and LiDAR reflectivity."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Texture(IntEnum):
    """Procedural texture families (see renderer.shade)."""

    PLAIN = 0
    NOISE = 1  # value noise: asphalt, grass, foliage
    TILES = 2  # a 1 m grid of joints: sidewalks
    FACADE = 3  # windows on a 3 m x 3.2 m grid: buildings
    BRICK = 4  # walls


@dataclass(frozen=True)
class Material:
    """A surface type.

    Attributes:
        name: for debugging.
        color_linear: base RGB in linear light, [0, 1].
        texture: texture family.
        texture_freq_per_m: spatial frequency of the texture's noise.
        texture_amplitude: relative strength of the texture's variation.
        reflectivity: LiDAR return strength in [0, 1] (retro-reflective signs near 1).
        tint_by_instance: colour comes from the object's instance id (car paint, clothing).
    """

    name: str
    color_linear: tuple[float, float, float]
    texture: Texture = Texture.PLAIN
    texture_freq_per_m: float = 1.0
    texture_amplitude: float = 0.0
    reflectivity: float = 0.3
    tint_by_instance: bool = False


MATERIALS: tuple[Material, ...] = (
    Material("asphalt", (0.055, 0.055, 0.06), Texture.NOISE, 3.0, 0.35, 0.12),
    Material("lane_paint", (0.75, 0.75, 0.70), Texture.NOISE, 6.0, 0.10, 0.75),
    Material("sidewalk", (0.30, 0.28, 0.26), Texture.TILES, 2.0, 0.20, 0.30),
    Material("kerb", (0.40, 0.40, 0.38), Texture.NOISE, 5.0, 0.15, 0.35),
    Material("grass", (0.06, 0.14, 0.03), Texture.NOISE, 1.5, 0.55, 0.45),
    Material("facade_cream", (0.55, 0.45, 0.32), Texture.FACADE, 2.0, 0.12, 0.30),
    Material("facade_brick", (0.35, 0.12, 0.07), Texture.FACADE, 4.0, 0.20, 0.28),
    Material("facade_grey", (0.25, 0.26, 0.28), Texture.FACADE, 2.0, 0.12, 0.30),
    Material("facade_white", (0.70, 0.70, 0.68), Texture.FACADE, 2.0, 0.08, 0.35),
    Material("roof", (0.08, 0.07, 0.07), Texture.NOISE, 2.0, 0.30, 0.20),
    Material("metal", (0.25, 0.26, 0.27), Texture.PLAIN, 1.0, 0.0, 0.55),
    Material("sign_red", (0.60, 0.03, 0.03), Texture.PLAIN, 1.0, 0.0, 0.95),
    Material("sign_blue", (0.02, 0.10, 0.55), Texture.PLAIN, 1.0, 0.0, 0.95),
    Material("sign_white", (0.80, 0.80, 0.80), Texture.PLAIN, 1.0, 0.0, 0.95),
    Material("light_housing", (0.02, 0.02, 0.02), Texture.PLAIN, 1.0, 0.0, 0.20),
    Material("foliage", (0.03, 0.10, 0.02), Texture.NOISE, 2.5, 0.70, 0.50),
    Material("bark", (0.10, 0.06, 0.03), Texture.NOISE, 4.0, 0.40, 0.30),
    Material("car_paint", (0.5, 0.5, 0.5), Texture.PLAIN, 1.0, 0.0, 0.60, tint_by_instance=True),
    Material("glass", (0.02, 0.025, 0.035), Texture.PLAIN, 1.0, 0.0, 0.08),
    Material("tyre", (0.012, 0.012, 0.012), Texture.PLAIN, 1.0, 0.0, 0.05),
    Material("skin", (0.55, 0.33, 0.22), Texture.PLAIN, 1.0, 0.0, 0.35),
    Material("clothing", (0.3, 0.3, 0.3), Texture.NOISE, 8.0, 0.15, 0.30, tint_by_instance=True),
    Material("ego_paint", (0.60, 0.61, 0.62), Texture.PLAIN, 1.0, 0.0, 0.60),
    Material("concrete_wall", (0.32, 0.31, 0.29), Texture.BRICK, 1.0, 0.15, 0.35),
    Material("fence", (0.20, 0.16, 0.12), Texture.NOISE, 3.0, 0.30, 0.30),
)
MATERIAL_IDS: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}

# Per-material arrays for vectorised shading.
COLOR = np.array([m.color_linear for m in MATERIALS], dtype=np.float32)
TEXTURE = np.array([int(m.texture) for m in MATERIALS], dtype=np.int32)
TEXTURE_FREQ = np.array([m.texture_freq_per_m for m in MATERIALS], dtype=np.float32)
TEXTURE_AMPLITUDE = np.array([m.texture_amplitude for m in MATERIALS], dtype=np.float32)
REFLECTIVITY = np.array([m.reflectivity for m in MATERIALS], dtype=np.float32)
TINT_BY_INSTANCE = np.array([m.tint_by_instance for m in MATERIALS], dtype=bool)

#: Paint colours of vehicles (linear RGB), picked by instance id.
VEHICLE_PAINTS = np.array(
    [
        (0.70, 0.70, 0.70),
        (0.02, 0.02, 0.02),
        (0.35, 0.36, 0.38),
        (0.50, 0.03, 0.02),
        (0.03, 0.08, 0.35),
        (0.80, 0.78, 0.74),
        (0.08, 0.18, 0.10),
        (0.45, 0.30, 0.05),
    ],
    dtype=np.float32,
)
#: Clothing colours of pedestrians.
CLOTHING = np.array(
    [(0.05, 0.05, 0.12), (0.35, 0.05, 0.05), (0.15, 0.15, 0.15), (0.05, 0.2, 0.08), (0.5, 0.45, 0.35)],
    dtype=np.float32,
)


def instance_tint(instance_id: np.ndarray, material_id: np.ndarray) -> np.ndarray:
    """Linear RGB ``(N, 3)`` of instance-tinted materials (paint or clothing by instance id)."""
    inst = instance_id.astype(np.int64)
    is_clothing = material_id == MATERIAL_IDS["clothing"]
    paint = VEHICLE_PAINTS[(inst * 7 + 3) % len(VEHICLE_PAINTS)]
    cloth = CLOTHING[(inst * 5 + 1) % len(CLOTHING)]
    return np.where(is_clothing[:, None], cloth, paint)
