"""The synthetic source's rig and preset names, for command lines that list them as choices
without importing the renderer (its meshes need trimesh and scipy, which a ``--help`` should not load)."""

from __future__ import annotations

from typing import Literal, get_args

#: The synthetic camera rigs (:mod:`phigenesis.data.sources.synthetic.rigs`).
RigName = Literal["waymo5", "nuscenes6"]
RIG_NAMES: tuple[RigName, ...] = get_args(RigName)
#: The real-size presets (:data:`phigenesis.data.sources.synthetic.presets.PRESETS` has these keys).
PRESET_NAMES: tuple[str, ...] = ("waymo", "nuscenes")
