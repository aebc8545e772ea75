"""Camera rigs to re-render a cache with: a named rig, a YAML rig file, or a random draw.

A :class:`Rig` is a tuple of :class:`~phigenesis.data.records.CameraCalibration` (ego frame x forward,
y left, z up, metres; camera axes OpenCV: x right, y down, z forward) and, per camera, the time it
fires after the frame's time (int microseconds). :func:`resolve_rig` turns what a user gave
``phigenesis-render --rig`` into a checked rig:

- ``waymo5`` / ``nuscenes6`` (:func:`named_rig`): the synthetic source's rigs, as pinhole cameras
  (no distortion) at one image size, firing when the synthetic rig fires (as its LiDAR sweeps past
  each camera's optical axis);
- ``random`` (:func:`random_rig`): fields of view, image size and mounting drawn from
  :class:`RandomRigRanges` around a base rig (the source's own), reproducible from a seed;
- anything else is a YAML rig file (:func:`load_rig_file`).

Every refusal is a :class:`RigError` naming the file (or "rig"), the camera (index and name) and the
field. YAML rig file (read with ``yaml.safe_load`` only; at most 1 MiB and 32 cameras)::

    name: my_rig                  # optional, default the file's stem
    cameras:
      - name: FRONT               # unique within the rig
        width: 144                # pixels, 8 .. 8192
        height: 96
        intrinsics: [[120.0, 0, 71.5], [0, 120.0, 47.5], [0, 0, 1]]   # OpenCV K, pixels
        distortion: [0, 0, 0, 0, 0]     # optional (default zeros): OpenCV k1 k2 p1 p2 k3
        ego_from_camera: [[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.6], [0, 0, 0, 1]]
        time_offset_micros: 0     # optional: fires this long after the frame's time, |.| <= 1 s
      - name: LEFT
        width: 144
        height: 96
        fx: 80.0                  # instead of intrinsics: fx, fy, cx, cy (all four)
        fy: 80.0
        cx: 71.5
        cy: 47.5
        position_m: [1.4, 0.2, 1.6]     # instead of ego_from_camera: the optical centre, ego frame
        yaw_deg: 90               # optical axis azimuth: 0 forward, +90 left
        pitch_deg: 5              # optional, positive looks down
        roll_deg: 0               # optional, about the optical axis, positive turns the image top right

``position_m`` / ``yaw_deg`` / ``pitch_deg`` / ``roll_deg`` give ``ego_from_camera`` =
``[Rz(yaw) @ Ry(pitch) @ Rx(roll) @ BODY_FROM_OPENCV | position]``, the synthetic rigs' construction
(:func:`phigenesis.geometry.euler_zyx_to_matrix` order). :meth:`Rig.to_dict` writes the full matrices
and :meth:`Rig.from_dict` reads the same format (a file's parsed YAML, a cache's ``rendered_rig``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from phigenesis import geometry
from phigenesis.data.ego_body import sensor_in_box
from phigenesis.data.records import MAX_IMAGE_SIDE, CameraCalibration, InvalidRecord
from phigenesis.data.sources.synthetic import LIDAR_SPIN_PERIOD_S
from phigenesis.data.sources.synthetic.rigs import RIGS, camera_calibrations
from phigenesis.errors import PhiGenesisError
from phigenesis.user_files import read_small_file

NAMED_RIGS: tuple[str, ...] = ("waymo5", "nuscenes6")
#: Largest rig file (bytes), most cameras in a rig, smallest image side (pixels).
MAX_RIG_FILE_BYTES = 1 << 20
MAX_CAMERAS = 32
MIN_IMAGE_SIDE = 8
#: Largest |time offset| of a camera from its frame's time, microseconds.
MAX_TIME_OFFSET_MICROS = 1_000_000
#: Tries per camera to draw a random mounting outside the ego body before giving up.
RANDOM_TRIES = 100

_TOP_KEYS = {"name", "seed", "cameras"}
_CAMERA_KEYS = {
    "name", "width", "height", "intrinsics", "fx", "fy", "cx", "cy", "distortion", "ego_from_camera",
    "position_m", "yaw_deg", "pitch_deg", "roll_deg", "time_offset_micros", "readout_direction",
}  # fmt: skip


class RigError(PhiGenesisError, ValueError):
    """A rig that cannot be used: the message names the file (or "rig"), the camera and the field."""


@dataclass(frozen=True, eq=False)
class Rig:
    """A camera rig: calibrations (ego frame, OpenCV camera axes) and firing times.

    Attributes:
        name: ``waymo5``, the YAML file's stem, ``random``, ...
        cameras: the cameras (at least one, unique names; :func:`check_rig` checks).
        time_offsets_micros: per camera, when it fires after the frame's time (int microseconds).
        seed: the seed of a random rig, else None.
    """

    name: str
    cameras: tuple[CameraCalibration, ...]
    time_offsets_micros: tuple[int, ...]
    seed: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "time_offsets_micros", tuple(int(t) for t in self.time_offsets_micros))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Rig) and self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict[str, Any]:
        """The rig as JSON-able lists (matrices as nested lists; the YAML rig file format)."""
        cameras = []
        for cal, offset in zip(self.cameras, self.time_offsets_micros, strict=True):
            cam: dict[str, Any] = {
                "name": cal.name,
                "width": cal.width,
                "height": cal.height,
                "intrinsics": cal.intrinsics.tolist(),
                "distortion": cal.distortion.tolist(),
                "ego_from_camera": cal.ego_from_camera.tolist(),
                "time_offset_micros": int(offset),
            }
            if cal.readout_direction != "global":
                cam["readout_direction"] = cal.readout_direction
            cameras.append(cam)
        return {"name": self.name, "seed": self.seed, "cameras": cameras}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "rig") -> Rig:
        """The rig of :meth:`to_dict`'s format (see the module docstring), validated; every refusal
        is a :class:`RigError` starting with ``where`` (the file)."""
        if not isinstance(d, Mapping):
            raise RigError(f"{where}: a rig must be a mapping with 'cameras', got {type(d).__name__}")
        _no_unknown_keys(where, d, _TOP_KEYS)
        name, seed = d.get("name"), d.get("seed")
        if not isinstance(name, str) or not name:
            raise RigError(f"{where}: name must be a non-empty string, got {name!r}")
        if seed is not None and not _is_int(seed):
            raise RigError(f"{where}: seed must be an integer or null, got {seed!r}")
        cams = d.get("cameras")
        if not isinstance(cams, list) or not 1 <= len(cams) <= MAX_CAMERAS:
            got = f"{len(cams)} cameras" if isinstance(cams, list) else repr(cams)
            raise RigError(f"{where}: cameras must be a list of 1 to {MAX_CAMERAS} cameras, got {got}")
        parsed = [_camera_from_dict(f"{where}: camera {i}", c) for i, c in enumerate(cams)]
        rig = cls(name, tuple(c for c, _ in parsed), tuple(t for _, t in parsed), seed)
        return check_rig(rig, None, where)


def _no_unknown_keys(where: str, d: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(str(k) for k in d if k not in allowed)
    if unknown:
        raise RigError(f"{where}: unknown field {', '.join(unknown)}; the fields are {sorted(allowed)}")


def _numbers(where: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` (nested lists of int/float) as a finite float64 array of ``shape``."""
    try:
        arr = np.array(value, dtype=object)
    except ValueError:
        arr = np.array(None, dtype=object)
    if arr.shape != shape:
        raise RigError(f"{where} must be {'x'.join(map(str, shape))} numbers, got {value!r}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in arr.flat):
        raise RigError(f"{where} must hold only numbers, got {value!r}")
    try:
        out = arr.astype(np.float64)
    except OverflowError:
        raise RigError(f"{where} must be finite, got {value!r}") from None
    if not np.all(np.isfinite(out)):
        raise RigError(f"{where} must be finite, got {out.tolist()}")
    return out


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _int(where: str, value: Any) -> int:
    if not _is_int(value):
        raise RigError(f"{where} must be an integer, got {value!r}")
    return int(value)


def ego_from_angles(
    position_m: Any, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0
) -> np.ndarray:
    """(4, 4) ``ego_from_camera`` (OpenCV camera axes) of a camera at ``position_m`` (ego frame,
    metres) whose optical axis has azimuth ``yaw_deg`` (0 forward, +90 left) and looks
    ``pitch_deg`` down, rolled ``roll_deg`` about its axis (positive turns the image's top right):
    the synthetic rigs' ``Rz(yaw) @ Ry(pitch)``, then ``Rx(roll)``, then BODY_FROM_OPENCV."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    rot_y = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rot_x = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    body = geometry.rotation_z(math.radians(yaw_deg)) @ rot_y @ rot_x
    return geometry.make_transform(body @ geometry.BODY_FROM_OPENCV, position_m)


def _camera_from_dict(where: str, c: Any) -> tuple[CameraCalibration, int]:
    """One camera of a rig dict and its time offset; ``where`` is ``"<file>: camera <i>"``."""
    if not isinstance(c, Mapping):
        raise RigError(f"{where}: a camera must be a mapping, got {c!r}")
    name = c.get("name")
    if not isinstance(name, str) or not name:
        raise RigError(f"{where}: name must be a non-empty string, got {name!r}")
    where = f"{where} ({name})"
    _no_unknown_keys(where, c, _CAMERA_KEYS)
    for key in ("width", "height"):
        if key not in c:
            raise RigError(f"{where}: missing field {key}")
        side = _int(f"{where} {key}", c[key])
        if not MIN_IMAGE_SIDE <= side <= MAX_IMAGE_SIDE:
            raise RigError(f"{where} {key} is {side} pixels, not in [{MIN_IMAGE_SIDE}, {MAX_IMAGE_SIDE}]")
    pinhole = [key for key in ("fx", "fy", "cx", "cy") if key in c]
    if "intrinsics" in c and pinhole:
        raise RigError(f"{where}: give intrinsics or fx/fy/cx/cy, not both")
    if "intrinsics" in c:
        k = _numbers(f"{where} intrinsics", c["intrinsics"], (3, 3))
    elif len(pinhole) == 4:
        fx, fy, cx, cy = (_numbers(f"{where} {key}", c[key], ()) for key in ("fx", "fy", "cx", "cy"))
        k = geometry.intrinsic_matrix(float(fx), float(fy), float(cx), float(cy))
    else:
        missing = [key for key in ("fx", "fy", "cx", "cy") if key not in c] if pinhole else ["intrinsics"]
        raise RigError(f"{where}: missing field {', '.join(missing)}")
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise RigError(f"{where} intrinsics: focal lengths must be positive, got fx {k[0, 0]}, fy {k[1, 1]}")
    distortion = _numbers(f"{where} distortion", c.get("distortion", [0.0] * 5), (5,))
    angles = [key for key in ("position_m", "yaw_deg", "pitch_deg", "roll_deg") if key in c]
    if "ego_from_camera" in c and angles:
        raise RigError(f"{where}: give ego_from_camera or position_m/yaw_deg, not both")
    if "ego_from_camera" in c:
        ego_from_camera = _numbers(f"{where} ego_from_camera", c["ego_from_camera"], (4, 4))
    elif "position_m" in c and "yaw_deg" in c:
        deg = {
            key: float(_numbers(f"{where} {key}", c[key], ()))
            for key in ("yaw_deg", "pitch_deg", "roll_deg")
            if key in c
        }
        position = _numbers(f"{where} position_m", c["position_m"], (3,))
        ego_from_camera = ego_from_angles(position, **deg)
    else:
        missing = (
            [key for key in ("position_m", "yaw_deg") if key not in c] if angles else ["ego_from_camera"]
        )
        raise RigError(f"{where}: missing field {', '.join(missing)}")
    offset = _int(f"{where} time_offset_micros", c.get("time_offset_micros", 0))
    try:
        cal = CameraCalibration(
            name,
            c["width"],
            c["height"],
            k,
            distortion,
            ego_from_camera,
            c.get("readout_direction", "global"),
        )
    except InvalidRecord as e:
        raise RigError(f"{where}: {e}") from None
    return cal, offset


def named_rig(name: str, height: int, width: int) -> Rig:
    """The synthetic source's rig ``name`` (:data:`NAMED_RIGS`) as pinhole cameras (no distortion),
    every image ``height`` x ``width`` pixels; camera i fires when the synthetic rig's does: as the
    LiDAR, sweeping clockwise from the rear through the front at the frame's time, passes its
    optical axis (microseconds, within half a spin period of the frame's time)."""
    if name not in NAMED_RIGS:
        raise RigError(f"rig {name!r}: unknown; the named rigs are {NAMED_RIGS}")
    try:
        cals, specs = camera_calibrations(name, height, width, uniform_size=True)
    except InvalidRecord as e:
        raise RigError(f"rig {name}: {e}") from None
    pinhole = tuple(
        CameraCalibration(c.name, c.width, c.height, c.intrinsics, np.zeros(5), c.ego_from_camera)
        for c in cals
    )
    spin_micros = LIDAR_SPIN_PERIOD_S[name] * 1e6
    offsets = []
    for spec in specs:
        fraction = np.mod(np.pi - np.radians(spec.yaw_deg), 2 * np.pi) / (2 * np.pi)
        offsets.append(round(float((fraction - 0.5) * spin_micros)))
    return Rig(name, pinhole, tuple(offsets))


def load_rig_file(path: str | os.PathLike[str]) -> Rig:
    """The rig of a YAML rig file (format in the module docstring), checked by :func:`check_rig`
    without an ego body. Raises :class:`RigError` naming the file, the camera and the field."""
    path = Path(path)
    text = read_small_file(path, "rig file", RigError, MAX_RIG_FILE_BYTES)
    try:
        d = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as e:
        raise RigError(f"{path}: not a YAML rig file ({' '.join(str(e).split())})") from None
    if not isinstance(d, Mapping):
        raise RigError(f"{path}: a rig file must hold a mapping with 'cameras', got {type(d).__name__}")
    return Rig.from_dict({"name": path.stem, **d}, where=str(path))


def check_rig(rig: Rig, ego_boxes: list[dict[str, list[float]]] | None = None, where: str = "rig") -> Rig:
    """Returns ``rig`` after checking it: at least one camera, unique names, one time offset per
    camera, each within 1 s, and (with ``ego_boxes``, ego frame, see :mod:`phigenesis.data.ego_body`)
    no camera centre inside the ego body. Raises :class:`RigError` starting with ``where``."""
    if not rig.cameras:
        raise RigError(f"{where}: cameras: the rig has no camera")
    if len(rig.time_offsets_micros) != len(rig.cameras):
        raise RigError(
            f"{where}: time_offsets_micros: {len(rig.time_offsets_micros)} offsets "
            f"for {len(rig.cameras)} cameras"
        )
    seen: dict[str, int] = {}
    for i, (cal, offset) in enumerate(zip(rig.cameras, rig.time_offsets_micros, strict=True)):
        camera = f"{where}: camera {i} ({cal.name})"
        if cal.name in seen:
            raise RigError(f"{camera} name: duplicate, camera {seen[cal.name]} has the same name")
        seen[cal.name] = i
        if abs(offset) > MAX_TIME_OFFSET_MICROS:
            raise RigError(f"{camera} time_offset_micros: {offset} is beyond +-{MAX_TIME_OFFSET_MICROS} us")
        for j, box in enumerate(ego_boxes or []):
            centre = cal.ego_from_camera[:3, 3]
            if sensor_in_box(centre, box):
                xyz = ", ".join(f"{v:.3f}" for v in centre)
                raise RigError(
                    f"{camera} ego_from_camera: its centre ({xyz}) m (ego frame) lies inside ego body box "
                    f"{j} (centre {box['center_ego']} m, size l/w/h {box['size_lwh']} m); it would see "
                    "nothing but the ego body: mount it outside the body"
                )
    return rig


def _range(where: str, pair: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise RigError(f"random rig ranges {where}: must be (lo, hi), got {pair!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise RigError(f"random rig ranges {where}: must be finite with lo <= hi, got ({lo}, {hi})")
    return lo, hi


@dataclass(frozen=True)
class RandomRigRanges:
    """What :func:`random_rig` draws, uniformly in ``(lo, hi)`` per camera unless said otherwise."""

    hfov_deg: tuple[float, float] = (40.0, 100.0)  # horizontal field of view, degrees, within (1, 170)
    extrinsics: bool = True  # False: only fields of view and size are drawn, mountings are the base's
    height_m: tuple[float, float] = (1.4, 2.2)  # mounting height: z of the camera centre, metres
    pitch_deg: tuple[float, float] = (-5.0, 10.0)  # downward tilt, degrees (positive looks down)
    yaw_jitter_deg: tuple[float, float] = (-15.0, 15.0)  # added to the base camera's yaw, degrees
    lateral_offset_m: tuple[float, float] = (-0.3, 0.3)  # added to the base camera's y, metres
    sizes_hw: tuple[tuple[int, int], ...] = ((96, 144), (128, 192), (96, 160))  # one per rig, pixels

    def __post_init__(self) -> None:
        for key in ("hfov_deg", "height_m", "pitch_deg", "yaw_jitter_deg", "lateral_offset_m"):
            object.__setattr__(self, key, _range(key, getattr(self, key)))
        if not (self.hfov_deg[0] > 1.0 and self.hfov_deg[1] < 170.0):
            raise RigError(f"random rig ranges hfov_deg: {self.hfov_deg} must lie within (1, 170) degrees")
        sizes = tuple(tuple(s) for s in self.sizes_hw)
        ok = all(len(s) == 2 and all(_is_int(v) and 8 <= v <= 4096 for v in s) for s in sizes)
        if not sizes or not ok:
            raise RigError(
                f"random rig ranges sizes_hw: {self.sizes_hw} must be (height, width) in [8, 4096]"
            )
        object.__setattr__(self, "sizes_hw", tuple((int(h), int(w)) for h, w in sizes))


def random_rig(
    base: Rig, ranges: RandomRigRanges, seed: int, *, ego_boxes: list[dict[str, list[float]]] | None = None
) -> Rig:
    """A random rig with ``base``'s camera names and time offsets, deterministic for the arguments.

    One image size (of ``ranges.sizes_hw``) for all cameras; per camera a horizontal field of view
    (``fx = fy = 0.5 * width / tan(hfov / 2)``, principal point at the image centre, no distortion)
    and, with ``ranges.extrinsics``, a mounting: the base camera's optical-axis azimuth plus a jitter,
    a drawn pitch and no roll (the image x axis horizontal), at the base camera's position with its
    y shifted and its z (height, metres) drawn. A mounting whose centre falls in ``ego_boxes`` is
    drawn again (up to :data:`RANDOM_TRIES` times). Without extrinsics the base's ego_from_camera is
    kept. Named ``random``, with ``seed`` recorded."""
    if not _is_int(seed) or seed < 0:
        raise RigError(f"random rig: seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    h, w = ranges.sizes_hw[int(rng.integers(len(ranges.sizes_hw)))]
    cameras = []
    for i, cal in enumerate(base.cameras):
        fx = 0.5 * w / math.tan(math.radians(rng.uniform(*ranges.hfov_deg)) / 2)
        k = geometry.intrinsic_matrix(fx, fx, (w - 1) / 2.0, (h - 1) / 2.0)
        ego_from_camera = cal.ego_from_camera
        if ranges.extrinsics:
            axis = cal.ego_from_camera[:3, 2]  # the optical axis (camera +z) in the ego frame
            base_yaw = math.degrees(math.atan2(axis[1], axis[0]))
            for _ in range(RANDOM_TRIES):
                yaw = base_yaw + rng.uniform(*ranges.yaw_jitter_deg)
                pitch = rng.uniform(*ranges.pitch_deg)
                x, y = cal.ego_from_camera[:2, 3]
                position = (x, y + rng.uniform(*ranges.lateral_offset_m), rng.uniform(*ranges.height_m))
                if not any(sensor_in_box(position, box) for box in ego_boxes or []):
                    break
            else:
                raise RigError(
                    f"random rig (seed {seed}): camera {i} ({cal.name}) ego_from_camera: {RANDOM_TRIES} "
                    f"draws of height_m {ranges.height_m} and lateral_offset_m {ranges.lateral_offset_m} "
                    "all put it inside the ego body; raise height_m"
                )
            ego_from_camera = ego_from_angles(position, yaw, pitch)
        cameras.append(CameraCalibration(cal.name, w, h, k, np.zeros(5), ego_from_camera))
    return Rig("random", tuple(cameras), base.time_offsets_micros, int(seed))


def resolve_rig(
    spec: str,
    *,
    base: Rig,
    height: int,
    width: int,
    seed: int = 0,
    ranges: RandomRigRanges | None = None,
    ego_boxes: list[dict[str, list[float]]] | None = None,
) -> Rig:
    """The rig ``phigenesis-render --rig spec`` means, checked against ``ego_boxes`` (ego frame).

    Args:
        spec: a name of :data:`NAMED_RIGS` (at ``height`` x ``width`` pixels), ``"random"``
            (:func:`random_rig` around ``base`` from ``ranges`` and ``seed``), or a YAML rig file.
        base: the source's own rig (the random rigs' base).
        ego_boxes: the ego body; no camera centre may lie inside it (None: not checked).
    """
    if spec in NAMED_RIGS:
        rig = named_rig(spec, height, width)
    elif spec == "random":
        rig = random_rig(base, ranges or RandomRigRanges(), seed, ego_boxes=ego_boxes)
    elif Path(spec).is_file():
        rig = load_rig_file(spec)
    else:
        raise RigError(
            f"rig {spec!r}: no such rig file, and not a rig name: choose one of "
            f"{', '.join((*NAMED_RIGS, 'random'))} or a YAML rig file"
        )
    return check_rig(rig, ego_boxes, where=spec)


assert set(NAMED_RIGS) == set(RIGS), (NAMED_RIGS, sorted(RIGS))

__all__ = [
    "NAMED_RIGS",
    "RandomRigRanges",
    "Rig",
    "RigError",
    "check_rig",
    "ego_from_angles",
    "load_rig_file",
    "named_rig",
    "random_rig",
    "resolve_rig",
]
