"""The nuScenes source: the JSON tables, camera JPEGs and LIDAR_TOP sweeps, without the devkit.

Entry point: :class:`NuScenesSource` over a :class:`NuScenesConfig` (``dataroot``, ``version``,
scene-name filters, error policy). A scene is a nuScenes scene, its id the scene's name.

Frame model (12 Hz, camera-led):

- **One frame per sweep of the lead camera** (CAM_FRONT), in time order. Every other camera's
  sweeps are matched to the step whose lead image is nearest in time, within half the lead's median
  interval; a camera keeps its **own** timestamp and ego pose. A camera with no sweep near a step
  (a dropped sweep, "due to system load") is left out of that frame, and a sweep that matches no
  step is not used; both are logged and listed in the scene metadata (``camera_gaps``,
  ``unused_sweeps``). No image is ever reused for two frames. A dropped lead sweep drops its step.
- **LiDAR**: a keyframe step takes its sample's LIDAR_TOP keyframe; other steps take the LIDAR_TOP
  sweep nearest the lead image (within the same tolerance, each sweep at most once). The frame's
  ``timestamp_micros`` and ``world_from_ego`` are that sweep's (so a keyframe frame sits exactly at
  its sample's time, the annotations' time); a step without LiDAR uses the lead image's.
  Points are moved into the ego frame of the sweep's timestamp; nuScenes stores no per-point
  times, so time offsets are 0 and ray origins the sensor's mount.
- **Boxes**: a frame whose lead image is a keyframe carries its sample's annotations (status
  "annotated"); other frames carry none. :attr:`Scene.keyframes` holds every sample's
  annotations (``track_id`` = instance token), for the ``interpolate_boxes`` stage. Velocities:
  see :func:`.convert.annotation_velocity`.
- **World**: nuScenes' global frame shifted by frame 0's ego position (no rotation);
  ``global_from_world`` is in the metadata.

Bad input: a missing table, a link to a token that does not exist, a missing or malformed image
or LiDAR file, an unknown category raise :class:`NuScenesError` naming the table, token or file.
With ``on_error="skip"`` the faulty record (a sample_data, an annotation) is left out, logged, and
listed in the scene metadata (``skipped``); a scene that cannot be read at all still fails, and
the cache run's own ``--on-error skip`` then lists it in the manifest.

Splits: the official train/val lists live in the devkit's code, not in the data, so this source
filters by scene name (exact or shell patterns) only.
"""

from __future__ import annotations

import fnmatch
import logging
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraImage,
    Frame,
    KeyframeBoxes,
    LazyFrames,
    Scene,
)
from phigenesis.data.sources.nuscenes import convert
from phigenesis.data.sources.nuscenes.convert import OnError, Problems
from phigenesis.data.sources.nuscenes.tables import NuScenesError, NuScenesTables, Record

SOURCE_NAME = "nuscenes"
LIDAR_CHANNEL = "LIDAR_TOP"
#: nuScenes' camera order (the rig order of the scene's calibrations); others follow by name.
CAMERA_ORDER = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
log = logging.getLogger("phigenesis.nuscenes")


@dataclass(frozen=True)
class NuScenesConfig:
    """What to convert.

    Attributes:
        dataroot: the folder holding ``<version>/``, ``samples/``, ``sweeps/`` and ``maps/``.
        version: the table folder, e.g. ``v1.0-mini`` or ``v1.0-trainval``.
        scenes: scene names or shell patterns to keep (empty: all).
        on_error: "raise" at the first bad record, or "skip" it and record what was skipped.
        lead_camera: the camera whose sweeps define the 12 Hz steps.
    """

    dataroot: str
    version: str = "v1.0-mini"
    scenes: tuple[str, ...] = ()
    on_error: OnError = "raise"
    lead_camera: str = "CAM_FRONT"

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenes", tuple(self.scenes or ()))
        if self.on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {self.on_error!r}")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> NuScenesConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown nuscenes source parameters {unknown}; known: {sorted(known)}")
        if not values.get("dataroot"):
            raise ValueError("the nuscenes source needs a dataroot (--dataroot)")
        return cls(**{k: v for k, v in values.items() if v is not None})

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scenes"] = list(self.scenes)
        return d


@dataclass
class Sweep:
    """One usable sample_data record (its file exists, its links resolve).

    Attributes:
        global_from_ego: (4, 4) ego pose at ``timestamp_micros`` in nuScenes' global frame.
    """

    record: Record
    channel: str
    modality: str
    timestamp_micros: int
    path: Path
    global_from_ego: NDArray[np.float64]
    calibrated_sensor: Record

    @property
    def is_key_frame(self) -> bool:
        return bool(self.record.get("is_key_frame"))


class NuScenesSource:
    """The scenes of one nuScenes version, each loaded as a :class:`Scene` with lazy frames."""

    name = SOURCE_NAME

    def __init__(self, config: NuScenesConfig):
        self.config = config

    @cached_property
    def tables(self) -> NuScenesTables:
        return NuScenesTables(self.config.dataroot, self.config.version)

    @cached_property
    def _scenes_by_name(self) -> dict[str, Record]:
        out: dict[str, Record] = {}
        for rec in self.tables["scene"].values():
            name = str(rec.get("name") or rec["token"])
            if name in out:
                raise NuScenesError(f"table 'scene' has two scenes named {name!r}")
            out[name] = rec
        return out

    def scene_ids(self) -> list[str]:
        pats = self.config.scenes
        names = sorted(self._scenes_by_name)
        ids = [s for s in names if not pats or any(fnmatch.fnmatchcase(s, p) for p in pats)]
        if not ids:
            where = self.tables.root
            raise NuScenesError(f"{where}: no scene matches {list(pats)}" if pats else f"{where}: no scenes")
        return ids

    def arguments(self) -> dict[str, Any]:
        return self.config.to_dict()

    def load(self, scene_id: str) -> Scene:
        if scene_id not in self._scenes_by_name:
            raise KeyError(f"{self.tables.root} has no scene named {scene_id!r}")
        return _SceneReader(self.tables, self._scenes_by_name[scene_id], self.config).scene()


class _SceneReader:
    """Resolves one scene's records once; frames are read from files on demand."""

    def __init__(self, tables: NuScenesTables, scene: Record, config: NuScenesConfig):
        self.tables = tables
        self.record = scene
        self.name = str(scene.get("name") or scene["token"])
        self.config = config
        self.problems = Problems(config.on_error, self.name)
        self.samples = tables.scene_samples(scene)
        self.sweeps = self._sweeps()
        self.cameras = self._camera_channels()
        self.calibrations = {c: self._calibration(self.sweeps[c][0]) for c in self.cameras}
        self.camera_gaps: list[dict[str, Any]] = []
        self.unused_sweeps: list[str] = []
        self.steps = self._steps()
        origin = self.steps[0]["pose"][:3, 3].copy()
        self.origin_global = origin
        self.world_from_global = np.eye(4)
        self.world_from_global[:3, 3] = -origin
        self.unknown_velocity: list[str] = []
        self.keyframes = self._keyframes()

    # ---------------------------------------------------------------- records
    def _sweeps(self) -> dict[str, list[Sweep]]:
        by_channel: dict[str, list[Sweep]] = {}
        for sample in self.samples:
            for sd in sorted(
                self.tables.sample_data_by_sample.get(sample["token"], []), key=lambda r: r["token"]
            ):
                sweep = self.problems.attempt(f"sample_data {sd['token']}", lambda sd=sd: self._sweep(sd))
                if sweep is not None:
                    by_channel.setdefault(sweep.channel, []).append(sweep)
        for sweeps in by_channel.values():
            sweeps.sort(key=lambda s: s.timestamp_micros)
        return by_channel

    def _sweep(self, sd: Record) -> Sweep | None:
        tables = self.tables
        channel, modality = tables.channel(sd)
        if modality not in ("camera", "lidar") or (modality == "lidar" and channel != LIDAR_CHANNEL):
            return None  # radar is not read
        ego = tables.follow("sample_data", sd, "ego_pose_token", "ego_pose")
        cs = tables.follow("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
        path = tables.dataroot / str(sd.get("filename", ""))
        if not sd.get("filename") or not path.is_file():
            raise NuScenesError(f"{path}: file of sample_data {sd['token']!r} ({channel}) is missing")
        if modality == "lidar" and path.stat().st_size % (4 * convert.PCD_FLOATS):
            raise NuScenesError(
                f"{path}: {path.stat().st_size} bytes is not a whole number of 5-float points"
            )
        return Sweep(sd, channel, modality, int(sd["timestamp"]), path, convert.pose(ego), cs)

    def _camera_channels(self) -> list[str]:
        cams = [c for c, s in self.sweeps.items() if s[0].modality == "camera"]
        if not cams:
            raise NuScenesError(f"scene {self.name!r} ({self.record['token']}) has no camera images")
        return sorted(
            cams, key=lambda c: (CAMERA_ORDER.index(c) if c in CAMERA_ORDER else len(CAMERA_ORDER), c)
        )

    def _calibration(self, sweep: Sweep) -> CameraCalibration:
        sd = sweep.record
        return convert.camera_calibration(sweep.channel, sweep.calibrated_sensor, sd["width"], sd["height"])

    # ---------------------------------------------------------------- the 12 Hz steps
    def _steps(self) -> list[dict[str, Any]]:
        lead_name = self.config.lead_camera if self.config.lead_camera in self.cameras else self.cameras[0]
        lead = self.sweeps[lead_name]
        lead_t = np.array([s.timestamp_micros for s in lead], np.int64)
        tolerance = 0.5 * float(np.median(np.diff(lead_t))) if len(lead_t) > 1 else 50_000.0
        steps: list[dict[str, Any]] = [{"cameras": {lead_name: s}, "lead": s} for s in lead]
        for cam in self.cameras:
            if cam != lead_name:
                for k, sweep in self._match(self.sweeps[cam], lead_t, tolerance).items():
                    steps[k]["cameras"][cam] = sweep
        for k, step in enumerate(steps):
            for cam in self.cameras:
                if cam not in step["cameras"]:
                    self.camera_gaps.append({"step": k, "camera": cam, "lead_micros": int(lead_t[k])})
                    log.warning(
                        "scene %s: step %d has no %s image (left out of the frame)", self.name, k, cam
                    )
        self._attach_lidar(steps, lead_t, tolerance)
        return steps

    def _match(self, sweeps: list[Sweep], lead_t: NDArray[np.int64], tolerance: float) -> dict[int, Sweep]:
        """Each step's nearest sweep within ``tolerance``; a sweep serves at most one step."""
        best: dict[int, Sweep] = {}
        for sweep in sweeps:
            dt = np.abs(lead_t - sweep.timestamp_micros)
            k = int(np.argmin(dt))
            if dt[k] > tolerance:
                self._unused(sweep, "no lead image within tolerance")
                continue
            if k in best:
                keep, drop = sorted((best[k], sweep), key=lambda s: abs(s.timestamp_micros - int(lead_t[k])))
                self._unused(drop, f"step {k} has a nearer one")
                best[k] = keep
            else:
                best[k] = sweep
        return best

    def _unused(self, sweep: Sweep, why: str) -> None:
        self.unused_sweeps.append(sweep.record["token"])
        log.warning(
            "scene %s: %s sweep %s is not used (%s)", self.name, sweep.channel, sweep.record["token"], why
        )

    def _attach_lidar(self, steps: list[dict[str, Any]], lead_t: NDArray[np.int64], tolerance: float) -> None:
        lidar = self.sweeps.get(LIDAR_CHANNEL, [])
        key_lidar = {s.record["sample_token"]: s for s in lidar if s.is_key_frame}
        lidar_t = np.array([s.timestamp_micros for s in lidar], np.int64)
        used: set[str] = set()
        for k, step in enumerate(steps):
            lead: Sweep = step["lead"]
            chosen = key_lidar.get(lead.record["sample_token"]) if lead.is_key_frame else None
            if chosen is None and len(lidar):
                j = int(np.argmin(np.abs(lidar_t - lead_t[k])))
                if abs(int(lidar_t[j]) - int(lead_t[k])) <= tolerance:
                    chosen = lidar[j]
            if chosen is not None and chosen.record["token"] in used:
                chosen = None
            if chosen is None:
                log.warning("scene %s: step %d has no LIDAR_TOP sweep", self.name, k)
            else:
                used.add(chosen.record["token"])
            step["lidar"] = chosen
            timed = chosen if chosen is not None else lead
            step["timestamp_micros"] = timed.timestamp_micros
            step["pose"] = timed.global_from_ego

    # ---------------------------------------------------------------- boxes
    def _keyframes(self) -> list[KeyframeBoxes]:
        keyframes = [
            convert.keyframe_boxes(self.tables, s, self.origin_global, self.problems, self.unknown_velocity)
            for s in self.samples
        ]
        tokens = sorted({t for kf in keyframes for t in kf.boxes.track_id})
        ids = {t: i + 1 for i, t in enumerate(tokens)}
        for kf in keyframes:
            kf.boxes.instance_id = np.array([ids[t] % 65536 for t in kf.boxes.track_id], np.uint16)
        if self.unknown_velocity:
            log.info(
                "scene %s: %d boxes annotated once without a stationary attribute get velocity 0",
                self.name,
                len(self.unknown_velocity),
            )
        return keyframes

    # ---------------------------------------------------------------- frames
    def frame(self, index: int, images: bool = True) -> Frame:
        step = self.steps[index]
        world_from_global = self.world_from_global
        cameras = []
        for cam in self.cameras:
            sweep: Sweep | None = step["cameras"].get(cam)
            if sweep is None:
                continue
            cameras.append(
                CameraImage(
                    calibration=self.calibrations[cam],
                    timestamp_micros=sweep.timestamp_micros,
                    world_from_ego=world_from_global @ sweep.global_from_ego,
                    image_bytes=_read_bytes(sweep) if images else None,
                    image_format="jpeg",
                )
            )
        lidar_sweep: Sweep | None = step["lidar"]
        lidar = None
        if lidar_sweep is not None:
            lidar = convert.lidar_sweep(
                lidar_sweep.path,
                lidar_sweep.timestamp_micros,
                world_from_global @ lidar_sweep.global_from_ego,
                convert.pose(lidar_sweep.calibrated_sensor),
            )
        lead: Sweep = step["lead"]
        boxes = Boxes.empty()
        if lead.is_key_frame:
            boxes = next(
                (kf.boxes for kf in self.keyframes if kf.token == lead.record["sample_token"]), Boxes.empty()
            )
        return Frame(
            scene_id=self.name,
            frame_index=index,
            timestamp_micros=step["timestamp_micros"],
            world_from_ego=world_from_global @ step["pose"],
            cameras=cameras,
            lidar=lidar,
            boxes=boxes,
        )

    def scene(self) -> Scene:
        log_record = self.problems.attempt(
            f"log of scene {self.name}", lambda: self.tables.follow("scene", self.record, "log_token", "log")
        )
        log_record = log_record or {}
        global_from_world = np.eye(4)
        global_from_world[:3, 3] = self.origin_global
        return Scene(
            scene_id=self.name,
            source=SOURCE_NAME,
            calibrations=[self.calibrations[c] for c in self.cameras],
            frames=LazyFrames(len(self.steps), self.frame, lambda i: self.frame(i, images=False)),
            metadata={
                "format": "nuscenes",
                "version": self.tables.version,
                "dataroot": str(self.tables.dataroot),
                "scene_token": self.record["token"],
                "description": str(self.record.get("description", "")),
                "location": str(log_record.get("location", "")),
                "vehicle": str(log_record.get("vehicle", "")),
                "date_captured": str(log_record.get("date_captured", "")),
                "global_from_world": global_from_world.reshape(-1).tolist(),
                "keyframes": len(self.keyframes),
                "lead_camera": self.steps[0]["lead"].channel,
                "camera_gaps": self.camera_gaps,
                "unused_sweeps": self.unused_sweeps,
                "velocity_unknown": self.unknown_velocity,
                "skipped": self.problems.items,
            },
            keyframes=self.keyframes,
        )


def _read_bytes(sweep: Sweep) -> bytes:
    try:
        return sweep.path.read_bytes()
    except OSError as e:
        raise NuScenesError(
            f"{sweep.path}: cannot read the image of sample_data {sweep.record['token']!r} ({e})"
        ) from None


__all__ = ["NuScenesConfig", "NuScenesError", "NuScenesSource"]
