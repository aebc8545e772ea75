"""Writes synthetic scenes as a nuScenes dataset: 13 JSON tables, JPEGs, LIDAR_TOP ``.pcd.bin``.

Layout under ``out``: ``<version>/*.json`` (all 13 tables), ``samples/<channel>/`` (keyframe
files), ``sweeps/<channel>/`` (the others), ``maps/<token>.png`` (a tiny map mask).

Timing of one scene with K keyframes (``start`` = the synthetic scene's first frame time):

- LIDAR_TOP spins at 20 Hz; sweep j's revolution is centred on ``start + j * 50 ms`` and, as in
  nuScenes, its timestamp is the end of the revolution (``+ 25 ms``). Every 10th sweep is a
  keyframe: sample k's timestamp is LiDAR sweep 10k's.
- Cameras run at 12 Hz: step s fires each camera as a revolution centred on ``start + s / 12 s``
  (the frame times of ``SyntheticScene`` at 12 Hz) passes the camera's optical axis, with
  nuScenes' phase: the revolution turns clockwise (seen from above) from azimuth
  :data:`REVOLUTION_START_AZIMUTH_DEG` (rear left), so the cameras fire 7 (CAM_FRONT_LEFT), 15
  (CAM_FRONT), 22 (CAM_FRONT_RIGHT), 30 (CAM_BACK_RIGHT), 40 (CAM_BACK) and 49 ms
  (CAM_BACK_LEFT) after it starts (:func:`camera_timestamp`). Every 6th step is a keyframe: its
  revolution is LiDAR sweep 10k's, so each camera's keyframe image (its ``is_key_frame``
  sample_data) is 1-43 ms before the sample's time, as in nuScenes (scene-0061's first sample:
  43.1, 35.5, 27.6, 20.1, 10.4 and 0.5 ms before it, in that camera order; devkit issue #1100
  counts the same offsets from the previous LiDAR sweep, the revolution's start). The LiDAR
  points themselves are rendered with the renderer's phase (its revolution starts at the rear),
  which only moves when a moving object was seen, not where the points are.
- Points are written in the LIDAR_TOP frame (x right, y forward, z up) at the ego pose of the
  sweep's timestamp (motion-compensated: each return keeps its true world position), as float32
  x, y, z, intensity (the synthetic [0, 1] reflectance x 255) and ring (the beam row, 0 = top).
- Boxes: every agent within ``box_range_m`` at each keyframe, in the global frame, size as
  (width, length, height), rotation (w, x, y, z), real nuScenes category and attribute names.

The global frame is the synthetic world moved by :data:`GLOBAL_OFFSET_M`. Tokens are 32-hex MD5s
of readable keys, so an export is reproducible byte for byte.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.records import encode_rgb
from phigenesis.data.sources.nuscenes.tables import TABLE_NAMES
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene

#: The synthetic world's origin in the exported global frame (metres).
GLOBAL_OFFSET_M = np.array([411.25, 1180.5, 0.0])
KEYFRAME_MICROS = 500_000
LIDAR_MICROS = 50_000
CAMERA_STEPS_PER_KEYFRAME = 6
LIDAR_SWEEPS_PER_KEYFRAME = 10
LIDAR_CHANNEL = "LIDAR_TOP"
#: Azimuth (degrees, ego frame, 0 = forward, +90 = left) where nuScenes' LIDAR_TOP revolution
#: starts and ends; it turns clockwise. Fitted to the keyframe images of real samples (the six
#: cameras then fire within 0.3 ms of scene-0061's first sample's offsets).
REVOLUTION_START_AZIMUTH_DEG = 105.0
#: ego <- LIDAR_TOP rotation: the sensor's x is the ego's right (-y), its y the ego's forward.
EGO_FROM_LIDAR_ROTATION = geometry.rotation_z(-np.pi / 2)
#: Unified class -> the nuScenes category written for it.
UNIFIED_TO_NUSCENES_CATEGORY = {
    tx.CAR: "vehicle.car",
    tx.TRUCK: "vehicle.truck",
    tx.BUS: "vehicle.bus.rigid",
    tx.PERSON: "human.pedestrian.adult",
    tx.RIDER: "human.pedestrian.personal_mobility",
    tx.BICYCLE: "vehicle.bicycle",
    tx.MOTORCYCLE: "vehicle.motorcycle",
}
#: Every nuScenes v1.0 category (23 detection, 9 lidarseg-only), written to category.json.
NUSCENES_CATEGORIES = list(tx.NUSCENES_CATEGORY_IDS)
ATTRIBUTES = (
    "vehicle.moving",
    "vehicle.stopped",
    "vehicle.parked",
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "pedestrian.moving",
)
VISIBILITY_LEVELS = (("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100"))
#: Speed (m/s) above which an agent is "moving".
MOVING_SPEED_MPS = 0.2


def token(*key: object) -> str:
    """A 32-character lowercase hex token for a readable key."""
    return hashlib.md5("/".join(str(k) for k in key).encode()).hexdigest()


def nuscenes_scene_config(config: SyntheticConfig, keyframes: int) -> SyntheticConfig:
    """The synthetic config whose 12 Hz frames are the export's camera steps."""
    if keyframes < 1:
        raise ValueError(f"need at least one keyframe, got {keyframes}")
    return replace(
        config, rig="nuscenes6", frame_rate_hz=12.0, frames=CAMERA_STEPS_PER_KEYFRAME * (keyframes - 1) + 1
    )


def camera_trigger_micros(yaw_deg: float) -> int:
    """When a camera whose optical axis points at azimuth ``yaw_deg`` (ego frame, 0 = forward,
    +90 = left) fires: microseconds after the start of the LiDAR revolution, which turns
    clockwise from :data:`REVOLUTION_START_AZIMUTH_DEG` in :data:`LIDAR_MICROS`."""
    behind = np.mod(REVOLUTION_START_AZIMUTH_DEG - yaw_deg, 360.0)
    return round(behind / 360.0 * LIDAR_MICROS)


def camera_timestamp(scene: SyntheticScene, step: int, camera_index: int) -> int:
    """The nuScenes timestamp of camera ``camera_index``'s image of 12 Hz step ``step``: its
    trigger time in the revolution centred on the step's frame time."""
    start = scene.frame_micros[step] - LIDAR_MICROS // 2
    return start + camera_trigger_micros(scene.specs[camera_index].yaw_deg)


def lidar_timestamp(scene: SyntheticScene, sweep: int) -> int:
    """The nuScenes timestamp (end of revolution) of LiDAR sweep ``sweep``."""
    return scene.config.start_micros + sweep * LIDAR_MICROS + LIDAR_MICROS // 2


def render_lidar_sweep(scene: SyntheticScene, sweep: int) -> dict[str, np.ndarray]:
    """The renderer's output for LiDAR sweep ``sweep`` (revolution centred 25 ms before its stamp)."""
    rng = np.random.default_rng([*scene.seed_sequence, 20, sweep])
    centre = scene.config.start_micros + sweep * LIDAR_MICROS
    return scene.renderer.render_lidar(
        scene.config.lidar, centre, scene.config.start_micros, scene.spin_period_s, rng
    )


def ego_from_lidar(scene: SyntheticScene) -> np.ndarray:
    return geometry.make_transform(EGO_FROM_LIDAR_ROTATION, scene.config.lidar.position_m)


def _pose(transform: np.ndarray) -> tuple[list[float], list[float]]:
    quaternion = geometry.matrix_to_quaternion(transform[:3, :3])
    return [float(x) for x in transform[:3, 3]], [float(x) for x in quaternion]


def _to_global(world_from_x: np.ndarray) -> np.ndarray:
    out = np.array(world_from_x, dtype=np.float64)
    out[:3, 3] += GLOBAL_OFFSET_M
    return out


def _attribute(class_id: int, speed: float) -> str:
    moving = speed > MOVING_SPEED_MPS
    if class_id == tx.PERSON:
        return "pedestrian.moving" if moving else "pedestrian.standing"
    if class_id in (tx.BICYCLE, tx.MOTORCYCLE, tx.RIDER):
        return "cycle.with_rider"
    return "vehicle.moving" if moving else "vehicle.stopped"


def _link(records: list[dict[str, Any]]) -> None:
    """Sets the prev/next tokens of a time-ordered list of records."""
    for i, rec in enumerate(records):
        rec["prev"] = records[i - 1]["token"] if i else ""
        rec["next"] = records[i + 1]["token"] if i + 1 < len(records) else ""


class _Tables:
    """The 13 tables being written, plus the fixed ones (sensors, categories, attributes)."""

    def __init__(self, channels: Iterable[str]):
        self.t: dict[str, list[dict[str, Any]]] = {name: [] for name in TABLE_NAMES}
        for ch in channels:
            modality = "lidar" if ch == LIDAR_CHANNEL else "camera"
            self.t["sensor"].append({"token": token("sensor", ch), "channel": ch, "modality": modality})
        for i, name in enumerate(NUSCENES_CATEGORIES):
            self.t["category"].append(
                {
                    "token": token("category", name),
                    "name": name,
                    "description": f"nuScenes {name}",
                    "index": i,
                }
            )
        for name in ATTRIBUTES:
            self.t["attribute"].append({"token": token("attribute", name), "name": name, "description": name})
        for tok, level in VISIBILITY_LEVELS:
            self.t["visibility"].append({"token": tok, "level": level, "description": f"visibility {level}"})

    def write(self, root: Path) -> list[Path]:
        root.mkdir(parents=True, exist_ok=True)
        paths = []
        for name, rows in self.t.items():
            path = root / f"{name}.json"
            path.write_text(json.dumps(rows, indent=1))
            paths.append(path)
        return paths


class _SceneWriter:
    """Renders one synthetic scene and appends its records to the tables."""

    def __init__(self, scene: SyntheticScene, index: int, keyframes: int, out: Path, tables: _Tables):
        self.scene = scene
        self.keyframes = keyframes
        self.out = out
        self.tables = tables
        self.log_name = f"n000-synthetic-s{scene.config.seed}-{index:04d}"
        self.name = f"scene-{scene.config.seed % 1000:03d}{index:04d}"
        self.written: list[Path] = []
        #: Keyframe k's LiDAR instance ids per point (for the annotations' num_lidar_pts).
        self.key_lidar_instances: dict[int, np.ndarray] = {}

    def _calibrated_sensor(self, channel: str, ego_from_sensor: np.ndarray, k: np.ndarray | None) -> str:
        tok = token(self.log_name, "calibrated_sensor", channel)
        translation, rotation = _pose(ego_from_sensor)
        self.tables.t["calibrated_sensor"].append(
            {
                "token": tok,
                "sensor_token": token("sensor", channel),
                "translation": translation,
                "rotation": rotation,
                "camera_intrinsic": [] if k is None else k.tolist(),
            }
        )
        return tok

    def _sample_data(
        self, channel: str, timestamp: int, key: bool, data: bytes, ext: str, size: tuple[int, int], cs: str
    ) -> dict[str, Any]:
        folder = "samples" if key else "sweeps"
        rel = f"{folder}/{channel}/{self.log_name}__{channel}__{timestamp}.{ext}"
        path = self.out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        self.written.append(path)
        sd_token = token(self.log_name, channel, timestamp)
        translation, rotation = _pose(_to_global(self.scene.world_from_ego(timestamp)))
        ego = {"token": sd_token, "timestamp": timestamp, "rotation": rotation, "translation": translation}
        self.tables.t["ego_pose"].append(ego)
        return {
            "token": sd_token,
            "sample_token": "",
            "ego_pose_token": sd_token,
            "calibrated_sensor_token": cs,
            "timestamp": timestamp,
            "fileformat": "pcd" if ext == "pcd.bin" else ext,
            "is_key_frame": key,
            "height": size[0],
            "width": size[1],
            "filename": rel,
            "prev": "",
            "next": "",
        }

    def write(self, dropped: set[tuple[str, int]]) -> None:
        scene, t = self.scene, self.tables.t
        sample_times = [lidar_timestamp(scene, LIDAR_SWEEPS_PER_KEYFRAME * k) for k in range(self.keyframes)]
        samples = [
            {"token": token(self.log_name, "sample", k), "timestamp": ts} for k, ts in enumerate(sample_times)
        ]
        scene_token = token(self.log_name, "scene")
        for s in samples:
            s["scene_token"] = scene_token
        _link(samples)
        records: list[dict[str, Any]] = []
        # LiDAR at 20 Hz.
        lidar_cs = self._calibrated_sensor(LIDAR_CHANNEL, ego_from_lidar(scene), None)
        lidar_records = []
        lidar_from_world_base = geometry.invert_transform(ego_from_lidar(scene))
        for j in range(LIDAR_SWEEPS_PER_KEYFRAME * (self.keyframes - 1) + 1):
            stamp = lidar_timestamp(scene, j)
            raw = render_lidar_sweep(scene, j)
            lidar_from_world = lidar_from_world_base @ geometry.invert_transform(scene.world_from_ego(stamp))
            xyz = geometry.transform_points(lidar_from_world, raw["points_world"])
            pts = np.column_stack([xyz, raw["intensity"] * 255.0, raw["beam"]]).astype("<f4")
            key = j % LIDAR_SWEEPS_PER_KEYFRAME == 0
            if key:
                self.key_lidar_instances[j // LIDAR_SWEEPS_PER_KEYFRAME] = raw["instance"]
            lidar_records.append(
                self._sample_data(LIDAR_CHANNEL, stamp, key, pts.tobytes(), "pcd.bin", (0, 0), lidar_cs)
            )
        records += lidar_records
        # Cameras at 12 Hz, each at its own time in the step's revolution.
        for i, cal in enumerate(scene.calibrations):
            cs = self._calibrated_sensor(cal.name, cal.ego_from_camera, cal.intrinsics)
            cam_records = []
            for step in range(len(scene.frame_micros)):
                key = step % CAMERA_STEPS_PER_KEYFRAME == 0
                if (cal.name, step) in dropped:
                    continue
                stamp = camera_timestamp(scene, step, i)
                pose, t_s = scene.world_from_ego(stamp), scene.seconds(stamp)
                rgb, _ = scene.renderer.render_camera(cal, pose, t_s, render_scale=scene.config.render_scale)
                jpeg = encode_rgb(rgb, "jpeg", scene.config.jpeg_quality)
                size = (cal.height, cal.width)
                cam_records.append(self._sample_data(cal.name, stamp, key, jpeg, "jpg", size, cs))
            records += cam_records
            _link(cam_records)
        _link(lidar_records)
        self._assign_samples(records, samples)
        t["sample_data"] += records
        t["sample"] += samples
        self._annotations(samples)
        log_token = token(self.log_name, "log")
        t["log"].append(
            {
                "token": log_token,
                "logfile": self.log_name,
                "vehicle": "n000",
                "date_captured": "2020-09-13",
                "location": "synthetic",
            }
        )
        t["scene"].append(
            {
                "token": scene_token,
                "name": self.name,
                "description": f"synthetic scene {scene.scene_id}",
                "log_token": log_token,
                "nbr_samples": len(samples),
                "first_sample_token": samples[0]["token"],
                "last_sample_token": samples[-1]["token"],
            }
        )

    @staticmethod
    def _assign_samples(records: list[dict[str, Any]], samples: list[dict[str, Any]]) -> None:
        """Keyframes point to their sample; other sweeps to the next sample (as nuScenes)."""
        times = np.array([s["timestamp"] for s in samples])
        for rec in records:
            if rec["is_key_frame"]:
                k = int(np.argmin(np.abs(times - rec["timestamp"])))
            else:
                k = min(int(np.searchsorted(times, rec["timestamp"], side="left")), len(samples) - 1)
            rec["sample_token"] = samples[k]["token"]

    def _annotations(self, samples: list[dict[str, Any]]) -> None:
        scene, t = self.scene, self.tables.t
        by_instance: dict[str, list[dict[str, Any]]] = {}
        categories: dict[str, str] = {}
        for k, sample in enumerate(samples):
            stamp = sample["timestamp"]
            boxes = scene.boxes_at(stamp, scene.config.box_range_m)
            counts = np.bincount(
                self.key_lidar_instances[k], minlength=int(boxes.instance_id.max(initial=0)) + 1
            )
            for b in range(len(boxes)):
                cls = int(boxes.class_id[b])
                if cls not in UNIFIED_TO_NUSCENES_CATEGORY:
                    continue
                inst = token(self.log_name, "instance", boxes.track_id[b])
                categories[inst] = UNIFIED_TO_NUSCENES_CATEGORY[cls]
                length, width, height = (float(x) for x in boxes.size_lwh[b])
                iid = int(boxes.instance_id[b])
                ann = {
                    "token": token(self.log_name, "annotation", boxes.track_id[b], k),
                    "sample_token": sample["token"],
                    "instance_token": inst,
                    "visibility_token": "4",
                    "attribute_tokens": [
                        token("attribute", _attribute(cls, float(np.linalg.norm(boxes.velocity_world[b]))))
                    ],
                    "translation": [float(x) for x in boxes.center_world[b] + GLOBAL_OFFSET_M],
                    "size": [width, length, height],
                    "rotation": [float(x) for x in boxes.orientation_world[b]],
                    "num_lidar_pts": int(counts[iid]) if iid < len(counts) else 0,
                    "num_radar_pts": 0,
                }
                by_instance.setdefault(inst, []).append(ann)
        for inst, anns in by_instance.items():
            _link(anns)
            t["sample_annotation"] += anns
            t["instance"].append(
                {
                    "token": inst,
                    "category_token": token("category", categories[inst]),
                    "nbr_annotations": len(anns),
                    "first_annotation_token": anns[0]["token"],
                    "last_annotation_token": anns[-1]["token"],
                }
            )


def _map_png(out: Path, map_token: str) -> Path:
    path = out / "maps" / f"{map_token}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    mask = np.zeros((8, 8), np.uint8)
    mask[2:6, :] = 255  # a road across the map
    if not cv2.imwrite(str(path), mask):
        raise OSError(f"could not write {path}")
    return path


def export_nuscenes(
    config: SyntheticConfig,
    out: str | os.PathLike[str],
    *,
    keyframes: int = 3,
    version: str = "v1.0-mini",
    dropped: Iterable[tuple[str, int]] = (),
) -> list[Path]:
    """Renders every scene of ``config`` and writes them under ``out`` as one nuScenes ``version``.

    Args:
        config: the synthetic scenes (the rig becomes nuscenes6, the rate 12 Hz; ``frames`` is
            replaced by the steps of ``keyframes`` keyframes: 6 (K - 1) + 1).
        out: the dataroot to write.
        keyframes: 2 Hz keyframes (samples) per scene; the scene lasts (K - 1) / 2 s.
        version: the table folder's name.
        dropped: (camera name, step) pairs of non-keyframe camera sweeps not to write (nuScenes
            drops some "due to system load"), in every scene.

    Returns:
        The files written (tables, map, images, LiDAR).
    """
    if config.extra_lidars:
        names = [s.name for s in config.extra_lidars]
        raise ValueError(f"nuScenes export writes one LiDAR (LIDAR_TOP); the config has extra LiDARs {names}")
    out = Path(out)
    cfg = nuscenes_scene_config(config, keyframes)
    dropped_set = {(str(c), int(s)) for c, s in dropped}
    for camera, step in sorted(dropped_set):
        if step % CAMERA_STEPS_PER_KEYFRAME == 0 or not 0 < step < cfg.frames:
            raise ValueError(
                f"cannot drop {camera} step {step}: only non-keyframe steps (not multiples of 6) "
                f"below {cfg.frames} can be dropped"
            )
    channels = [LIDAR_CHANNEL]
    tables: _Tables | None = None
    written: list[Path] = []
    log_tokens = []
    for index in range(cfg.scenes):
        scene = SyntheticScene(cfg, index)
        if tables is None:
            channels += [c.name for c in scene.calibrations]
            unknown = {c for c, _ in dropped_set} - set(channels)
            if unknown:
                raise ValueError(f"cannot drop sweeps of unknown cameras {sorted(unknown)}")
            tables = _Tables(channels)
        writer = _SceneWriter(scene, index, keyframes, out, tables)
        writer.write(dropped_set)
        written += writer.written
        log_tokens.append(tables.t["log"][-1]["token"])
    assert tables is not None
    map_token = token("map", "synthetic")
    written.append(_map_png(out, map_token))
    tables.t["map"].append(
        {
            "token": map_token,
            "log_tokens": log_tokens,
            "category": "semantic_prior",
            "filename": f"maps/{map_token}.png",
        }
    )
    return tables.write(out / version) + written
