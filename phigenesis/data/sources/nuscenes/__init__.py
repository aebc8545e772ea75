"""The nuScenes source: the JSON tables, camera JPEGs and LIDAR_TOP sweeps, without the devkit.

Entry point: :class:`NuScenesSource` over a :class:`NuScenesConfig` (``dataroot``, ``version``,
scene-name filters, error policy). A scene is a nuScenes scene, its id the scene's name.

Frame model (12 Hz, camera-led):

- **One frame per sweep of the lead camera** (CAM_FRONT), in time order. Every other camera's
  sweeps are matched to the step whose lead image is nearest in time, within half the lead's
  median interval (at most 1 s); a camera keeps its **own** timestamp and ego pose. A camera with
  no sweep near a step (a dropped sweep, "due to system load") is left out of that frame, and a
  sweep that matches no step is not used; both are logged and listed in the scene metadata
  (``camera_gaps``, ``unused_sweeps``). No image is ever reused for two frames. A dropped lead
  sweep drops its step.
- **LiDAR**: a keyframe step takes its sample's LIDAR_TOP keyframe (if within one lead interval
  of the lead image); other steps take the LIDAR_TOP sweep nearest the lead image (within the same
  tolerance, each sweep at most once). The frame's ``timestamp_micros`` and ``world_from_ego`` are
  that sweep's (so a keyframe frame sits exactly at its sample's time, the annotations' time); a
  step without LiDAR uses the lead image's.
  Points are moved into the ego frame of the sweep's timestamp; nuScenes stores no per-point
  times, so time offsets are 0 and ray origins the sensor's mount.
- **Boxes**: a frame whose lead image is a keyframe carries its sample's annotations (status
  "annotated"); other frames carry none. :attr:`Scene.keyframes` holds every sample's
  annotations (``track_id`` = instance token), for the ``interpolate_boxes`` stage. Velocities:
  see :func:`.convert.annotation_velocity`.
- **World**: nuScenes' global frame shifted by frame 0's ego position (no rotation);
  ``global_from_world`` is in the metadata.

Bad input is a :class:`NuScenesError` naming the file, the record (table + token) and the field:
a missing table, a field of the wrong kind (``is_key_frame: "false"``, a list for a token, a
missing ``timestamp``, a 2-element ``translation``, NaN or Inf anywhere, a timestamp that is
negative or after 2100, a non-unit quaternion), a link to a token that does not exist, a repeated
token, a ``filename`` that leads outside the dataroot (absolute, ``..`` or a symlink out; the file
is never read), a missing or malformed image or LiDAR file (a JPEG cut short: found when the scene
is indexed; one that does not decode: when its frame loads), an image whose size differs from its
record's, an unknown category, two sweeps of one channel at one time, samples or frames out of
time order. LiDAR points with non-finite values are not errors: they are dropped and counted in
:attr:`Scene.dropped`. With ``on_error="skip"`` the smallest faulty unit is left out, logged, and
listed in the scene metadata (``skipped``): an annotation (that box), a sample_data (that image or
LiDAR sweep), a sample whose time is out of order (its boxes), a frame whose time is; a file that
cannot be read or decoded when its frame is loaded is left out of that frame and counted in
:attr:`Scene.dropped`. A scene that cannot
be read at all still fails, and the cache run's own ``--on-error skip`` then lists it in the
manifest.

Splits: the official train/val lists live in the devkit's code, not in the data, so this source
filters by scene name (exact or shell patterns) only.
"""

from __future__ import annotations

import fnmatch
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from phigenesis.data.ego_body import NUSCENES_ZOE_BOXES
from phigenesis.data.records import (
    Boxes,
    CameraCalibration,
    CameraImage,
    DroppedValues,
    Frame,
    InvalidRecord,
    KeyframeBoxes,
    LazyFrames,
    Scene,
    increasing_frames,
)
from phigenesis.data.sources import given
from phigenesis.data.sources.nuscenes import convert
from phigenesis.data.sources.nuscenes.convert import OnError, Problems
from phigenesis.data.sources.nuscenes.tables import NuScenesError, NuScenesTables, Record
from phigenesis.options import ConfigError, check_options, from_mapping, option

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
T = TypeVar("T")
#: Widest match between a sweep and a frame's lead image, microseconds (half the lead camera's
#: median interval, at most this): keeps every capture well within the scene model's limit.
MAX_MATCH_MICROS = 1_000_000


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

    dataroot: str = option()
    version: str = option("v1.0-mini")
    scenes: tuple[str, ...] = option(())
    on_error: OnError = option("raise")
    lead_camera: str = option("CAM_FRONT")

    def __post_init__(self) -> None:
        check_options(self, "NuScenesConfig")
        if not self.dataroot:
            raise ConfigError("NuScenesConfig: the nuscenes source needs a dataroot (--dataroot)")

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "nuscenes source parameters") -> NuScenesConfig:
        """The config from plain values (None: the default); a missing dataroot, an unknown key or
        a value outside its type is a :class:`~phigenesis.options.ConfigError` naming ``where``."""
        return from_mapping(cls, {"dataroot": "", **given(values)}, where)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scenes"] = list(self.scenes)
        return d


@dataclass
class Sweep:
    """One usable sample_data record: its fields checked, its links resolved, its file present.

    Attributes:
        record: the sample_data record.
        token: its token.
        channel, modality: its sensor's (``CAM_FRONT``, "camera").
        sample_token: its sample (for a non-keyframe sweep, the next keyframe's).
        timestamp_micros: capture time, microseconds.
        is_key_frame: whether it is its sample's keyframe sweep.
        path: the data file (inside the dataroot).
        global_from_ego: (4, 4) ego pose at ``timestamp_micros`` in nuScenes' global frame.
        ego_from_sensor: (4, 4) the sensor's extrinsic (camera axes OpenCV's).
        calibrated_sensor_token: the calibrated_sensor record it links to.
        calibration: a camera's calibration for its image size (None for LiDAR).
        size: (width, height) of a camera image in pixels, as its record and its JPEG both say.
    """

    record: Record
    token: str
    channel: str
    modality: str
    sample_token: str
    timestamp_micros: int
    is_key_frame: bool
    path: Path
    global_from_ego: NDArray[np.float64]
    ego_from_sensor: NDArray[np.float64]
    calibrated_sensor_token: str
    calibration: CameraCalibration | None = None
    size: tuple[int, int] | None = None


class NuScenesSource:
    """The scenes of one nuScenes version, each loaded as a :class:`Scene` with lazy frames."""

    name = SOURCE_NAME

    def __init__(self, config: NuScenesConfig):
        self.config = config
        self._left_out_scenes: list[NuScenesError] = []  # scene records no scene id can name

    @cached_property
    def tables(self) -> NuScenesTables:
        tables = NuScenesTables(self.config.dataroot, self.config.version)
        self._apply_policy(tables.load_problems)
        return tables

    def _apply_policy(self, problems: list[NuScenesError]) -> None:
        """Records no scene can use (no token, a repeated token or scene name): ``raise`` raises the
        first; ``skip`` logs each (they are left out)."""
        if problems and self.config.on_error == "raise":
            raise problems[0]
        for problem in problems:
            log.warning("left out: %s", problem)

    @cached_property
    def _scenes_by_name(self) -> dict[str, Record]:
        tables = self.tables
        named: list[tuple[str, Record]] = []
        problems: list[NuScenesError] = []
        for rec in tables["scene"].values():
            try:
                named.append((tables.field("scene", rec, "name", "text"), rec))
            except NuScenesError as e:
                problems.append(e)
        counts = Counter(name for name, _ in named)
        problems += [
            tables.error("scene", rec, f"'name' {name!r} is the name of another scene too")
            for name, rec in named
            if counts[name] > 1
        ]
        self._apply_policy(problems)
        self._left_out_scenes = problems
        return {name: rec for name, rec in named if counts[name] == 1}

    def scene_ids(self) -> list[str]:
        pats = self.config.scenes
        names = sorted(self._scenes_by_name)
        ids = [s for s in names if not pats or any(fnmatch.fnmatchcase(s, p) for p in pats)]
        if not ids:
            where = self.tables.root
            message = f"{where}: no scene matches {list(pats)}" if pats else f"{where}: no scenes"
            if self._left_out_scenes:
                message += (
                    f" ({len(self._left_out_scenes)} left out, the first as {self._left_out_scenes[0]})"
                )
            raise NuScenesError(message)
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
        self.name = tables.field("scene", scene, "name", "text")
        self.config = config
        self.dropped = DroppedValues()
        self.problems = Problems(config.on_error, self.name, self.dropped)
        self._calibrations: dict[tuple[str, tuple[int, int]], CameraCalibration] = {}
        timeline = tables.timeline(scene)
        for token, error in timeline.rejected:
            self.problems.report(f"sample {token}", error)
        #: The samples whose time is valid and in order (the keyframes); all samples give sweeps.
        self.samples = [s for s in timeline.samples if s["token"] in timeline.times]
        self.sweeps = self._sweeps(timeline.samples)
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
    def _sweeps(self, samples: list[Record]) -> dict[str, list[Sweep]]:
        """The usable sweeps of ``samples`` per channel in time order: each checked
        (:meth:`_sweep`), none sharing its time with another of its channel, and a camera's all
        of one calibration."""
        by_channel: dict[str, list[Sweep]] = {}
        for sample in samples:
            for sd in sorted(
                self.tables.sample_data_by_sample.get(sample["token"], []), key=lambda r: r["token"]
            ):
                sweep = self.problems.attempt(f"sample_data {sd['token']}", lambda sd=sd: self._sweep(sd))
                if sweep is not None:
                    by_channel.setdefault(sweep.channel, []).append(sweep)
        usable: dict[str, list[Sweep]] = {}
        for channel, sweeps in by_channel.items():
            camera = sweeps[0].modality == "camera"
            sweeps = self._distinct_times(sorted(sweeps, key=lambda s: (s.timestamp_micros, s.token)))
            sweeps = self._one_calibration(sweeps) if camera and sweeps else sweeps
            if sweeps:
                usable[channel] = sweeps
        return usable

    def _sweep(self, sd: Record) -> Sweep | None:
        """``sd`` as a :class:`Sweep` with every field it needs checked, or None for a sensor that
        is not read (radar, other LiDARs)."""
        tables = self.tables
        channel, modality = tables.channel(sd)
        if modality == "radar" or (modality == "lidar" and channel != LIDAR_CHANNEL):
            return None
        ego = tables.follow("sample_data", sd, "ego_pose_token", "ego_pose")
        cs = tables.follow("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
        path = tables.data_path("sample_data", sd, "filename")
        camera: dict[str, Any] = {}
        if modality == "camera":
            size = self._image_size(sd, path)
            camera = {"calibration": self._camera_calibration(cs, channel, size), "size": size}
        else:
            convert.check_pcd_bin(path, tables.named_by("sample_data", sd, "filename"))
        return Sweep(
            record=sd,
            token=sd["token"],
            channel=channel,
            modality=modality,
            sample_token=tables.field("sample_data", sd, "sample_token", "token"),
            timestamp_micros=tables.field("sample_data", sd, "timestamp", "timestamp"),
            is_key_frame=tables.field("sample_data", sd, "is_key_frame", "bool"),
            path=path,
            global_from_ego=convert.pose(tables, "ego_pose", ego),
            ego_from_sensor=convert.pose(tables, "calibrated_sensor", cs),
            calibrated_sensor_token=cs["token"],
            **camera,
        )

    def _camera_calibration(self, cs: Record, channel: str, size: tuple[int, int]) -> CameraCalibration:
        """The calibration of ``cs`` for images of ``size`` (width, height), made once."""
        key = (cs["token"], size)
        if key not in self._calibrations:
            self._calibrations[key] = convert.camera_calibration(self.tables, cs, channel, *size)
        return self._calibrations[key]

    def _image_size(self, sd: Record, path: Path) -> tuple[int, int]:
        """(width, height) in pixels that ``sd`` gives its image, checked against the JPEG's own."""
        size = (
            self.tables.field("sample_data", sd, "width", "pixels"),
            self.tables.field("sample_data", sd, "height", "pixels"),
        )
        actual = convert.jpeg_size(path, self.tables.named_by("sample_data", sd, "filename"))
        if actual != size:
            raise self.tables.error(
                "sample_data",
                sd,
                f"'width' x 'height' is {size[0]}x{size[1]}, but its image {path} is {actual[0]}x{actual[1]}",
            )
        return size

    def _distinct_times(self, sweeps: list[Sweep]) -> list[Sweep]:
        """``sweeps`` (of one channel) without those sharing their time with another: which of
        them was taken then is unknowable, so none is used."""
        at: dict[int, list[str]] = {}
        for s in sweeps:
            at.setdefault(s.timestamp_micros, []).append(s.token)
        for s in sweeps:
            others = [t for t in at[s.timestamp_micros] if t != s.token]
            if others:
                error = self.tables.error(
                    "sample_data",
                    s.record,
                    f"'timestamp' {s.timestamp_micros} is also the time of {s.channel} sample_data "
                    + ", ".join(repr(t) for t in others),
                )
                self.problems.report(f"sample_data {s.token}", error)
        return [s for s in sweeps if len(at[s.timestamp_micros]) == 1]

    def _one_calibration(self, sweeps: list[Sweep]) -> list[Sweep]:
        """A camera's ``sweeps`` that share the calibrated sensor and image size of most of them
        (the scene has one calibration per camera); the others are reported and left out."""
        key = Counter((s.calibrated_sensor_token, s.size) for s in sweeps).most_common(1)[0][0]
        for s in sweeps:
            if (s.calibrated_sensor_token, s.size) != key:
                error = self.tables.error(
                    "sample_data",
                    s.record,
                    f"its calibrated sensor {s.calibrated_sensor_token!r} and size {s.size} differ from "
                    f"those of the other {s.channel} sweeps ({key[0]!r}, {key[1]})",
                )
                self.problems.report(f"sample_data {s.token}", error)
        return [s for s in sweeps if (s.calibrated_sensor_token, s.size) == key]

    def _camera_channels(self) -> list[str]:
        cams = [c for c, s in self.sweeps.items() if s[0].modality == "camera"]
        if not cams:
            raise self.tables.error(
                "scene", self.record, "has no usable camera image (all are missing or were left out)"
            )
        return sorted(
            cams, key=lambda c: (CAMERA_ORDER.index(c) if c in CAMERA_ORDER else len(CAMERA_ORDER), c)
        )

    def _calibration(self, sweep: Sweep) -> CameraCalibration:
        assert sweep.calibration is not None, sweep.token
        return sweep.calibration

    # ---------------------------------------------------------------- the 12 Hz steps
    def _steps(self) -> list[dict[str, Any]]:
        lead_name = self.config.lead_camera if self.config.lead_camera in self.cameras else self.cameras[0]
        lead = self.sweeps[lead_name]
        lead_t = np.array([s.timestamp_micros for s in lead], np.int64)
        tolerance = 0.5 * float(np.median(np.diff(lead_t))) if len(lead_t) > 1 else 50_000.0
        tolerance = min(tolerance, MAX_MATCH_MICROS)
        steps: list[dict[str, Any]] = [{"cameras": {lead_name: s}, "lead": s} for s in lead]
        for cam in self.cameras:
            if cam != lead_name:
                for k, sweep in self._match(self.sweeps[cam], lead_t, tolerance).items():
                    steps[k]["cameras"][cam] = sweep
        self._attach_lidar(steps, lead_t, tolerance)
        steps = self._in_time_order(steps)
        for k, step in enumerate(steps):
            for cam in self.cameras:
                if cam not in step["cameras"]:
                    lead_micros = step["lead"].timestamp_micros
                    self.camera_gaps.append({"step": k, "camera": cam, "lead_micros": lead_micros})
                    log.warning(
                        "scene %s: step %d has no %s image (left out of the frame)", self.name, k, cam
                    )
        return steps

    def _in_time_order(self, steps: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """``steps`` whose frame times strictly increase (the most of them); a frame out of order
        (its LiDAR sweep's time is) is reported and left out, its sweeps unused."""
        kept_at = set(increasing_frames([step["timestamp_micros"] for step in steps]))
        keep = [k in kept_at for k in range(len(steps))]
        for step, kept in zip(steps, keep, strict=True):
            if kept:
                continue
            lead: Sweep = step["lead"]
            lidar: Sweep | None = step["lidar"]
            timed = f"LIDAR_TOP sample_data {lidar.token!r}'s" if lidar is not None else "its own"
            error = self.tables.error(
                "sample_data",
                lead.record,
                f"the frame it leads has the time {step['timestamp_micros']} ({timed} 'timestamp'), "
                "out of order with the frames around it",
            )
            self.problems.report(f"frame of sample_data {lead.token}", error)
            for sweep in [*step["cameras"].values(), *([lidar] if lidar is not None else [])]:
                self._unused(sweep, "its frame is out of time order")
        return [step for step, kept in zip(steps, keep, strict=True) if kept]

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
        self.unused_sweeps.append(sweep.token)
        log.warning("scene %s: %s sweep %s is not used (%s)", self.name, sweep.channel, sweep.token, why)

    def _attach_lidar(self, steps: list[dict[str, Any]], lead_t: NDArray[np.int64], tolerance: float) -> None:
        lidar = self.sweeps.get(LIDAR_CHANNEL, [])
        key_lidar = {s.sample_token: s for s in lidar if s.is_key_frame}
        lidar_t = np.array([s.timestamp_micros for s in lidar], np.int64)
        used: set[str] = set()
        for k, step in enumerate(steps):
            lead: Sweep = step["lead"]
            chosen = self._keyframe_lidar(key_lidar, lead, tolerance) if lead.is_key_frame else None
            if chosen is None and len(lidar):
                j = int(np.argmin(np.abs(lidar_t - lead_t[k])))
                if abs(int(lidar_t[j]) - int(lead_t[k])) <= tolerance:
                    chosen = lidar[j]
            if chosen is not None and chosen.token in used:
                chosen = None
            if chosen is None:
                log.warning("scene %s: step %d has no LIDAR_TOP sweep", self.name, k)
            else:
                used.add(chosen.token)
            step["lidar"] = chosen
            timed = chosen if chosen is not None else lead
            step["timestamp_micros"] = timed.timestamp_micros
            step["pose"] = timed.global_from_ego

    def _keyframe_lidar(self, key_lidar: dict[str, Sweep], lead: Sweep, tolerance: float) -> Sweep | None:
        """The LIDAR_TOP keyframe of the keyframe image ``lead``'s sample, if it lies within one
        lead interval (twice ``tolerance``, microseconds) of it; else None (the nearest sweep is
        taken instead)."""
        chosen = key_lidar.get(lead.sample_token)
        if chosen is not None and abs(chosen.timestamp_micros - lead.timestamp_micros) > 2 * tolerance:
            log.warning(
                "scene %s: LIDAR_TOP keyframe %s is %d us from its keyframe image %s: not its frame's sweep",
                self.name,
                chosen.token,
                chosen.timestamp_micros - lead.timestamp_micros,
                lead.token,
            )
            return None
        return chosen

    # ---------------------------------------------------------------- boxes
    def _keyframes(self) -> list[KeyframeBoxes]:
        keyframes = [
            convert.keyframe_boxes(self.tables, s, self.origin_global, self.problems, self.unknown_velocity)
            for s in self.samples
        ]
        tokens = sorted({t for kf in keyframes for t in kf.boxes.track_id})
        ids = {t: i + 1 for i, t in enumerate(tokens)}
        # Each camera's own keyframe image of a sample (its is_key_frame sample_data), which
        # fires as the LiDAR revolution ending at the sample's time passes the camera.
        key_images: dict[str, dict[str, int]] = {}
        for cam in self.cameras:
            for sweep in self.sweeps[cam]:
                if sweep.is_key_frame:
                    key_images.setdefault(sweep.sample_token, {})[cam] = sweep.timestamp_micros
        for kf in keyframes:
            kf.boxes.instance_id = np.array([ids[t] % 65536 for t in kf.boxes.track_id], np.uint16)
            kf.camera_timestamps_micros = key_images.get(kf.token, {})
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
        left_out: list[NuScenesError] = []
        cameras = []
        for cam in self.cameras:
            sweep: Sweep | None = step["cameras"].get(cam)
            if sweep is not None:
                image = _collect(left_out, lambda sweep=sweep: self._camera_image(sweep, images))
                cameras += [image] if image is not None else []
        lidar_sweep: Sweep | None = step["lidar"]
        lidar = None
        if lidar_sweep is not None:
            lidar = _collect(
                left_out,
                lambda: convert.lidar_sweep(
                    lidar_sweep.path,
                    self._named_by(lidar_sweep),
                    lidar_sweep.timestamp_micros,
                    world_from_global @ lidar_sweep.global_from_ego,
                    lidar_sweep.ego_from_sensor,
                    self.dropped,
                    index,
                ),
            )
        self.problems.in_frame(index, left_out)
        lead: Sweep = step["lead"]
        boxes = Boxes.empty()
        if lead.is_key_frame:
            boxes = next((kf.boxes for kf in self.keyframes if kf.token == lead.sample_token), Boxes.empty())
        try:
            return Frame(
                scene_id=self.name,
                frame_index=index,
                timestamp_micros=step["timestamp_micros"],
                world_from_ego=world_from_global @ step["pose"],
                cameras=cameras,
                lidar=lidar,
                boxes=boxes,
            )
        except InvalidRecord as e:
            where = self.tables.error("sample_data", lead.record, f"as the lead image of frame {index}")
            raise convert.scene_model_error(where, e) from None

    def _named_by(self, sweep: Sweep) -> str:
        return self.tables.named_by("sample_data", sweep.record, "filename")

    def _camera_image(self, sweep: Sweep, with_bytes: bool) -> CameraImage:
        """The image of a camera sweep in the world frame, its JPEG read (and checked to decode:
        :meth:`CameraImage.check_image`) if ``with_bytes``."""
        try:
            image = CameraImage(
                calibration=self.calibrations[sweep.channel],
                timestamp_micros=sweep.timestamp_micros,
                world_from_ego=self.world_from_global @ sweep.global_from_ego,
                image_bytes=convert.read_image(sweep.path, self._named_by(sweep)) if with_bytes else None,
                image_format="jpeg",
            )
            image.check_image()
            return image
        except InvalidRecord as e:
            where = self.tables.error("sample_data", sweep.record, f"as an image ({sweep.path})")
            raise convert.scene_model_error(where, e) from None

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
            frames=LazyFrames(
                len(self.steps),
                self.frame,
                lambda i: self.frame(i, images=False),
                timestamps_micros=[step["timestamp_micros"] for step in self.steps],
            ),
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
                "ego_boxes": NUSCENES_ZOE_BOXES,
            },
            keyframes=self.keyframes,
            dropped=self.dropped,
        )


def _collect(errors: list[NuScenesError], fn: Callable[[], T]) -> T | None:
    """``fn()``, or None after appending its :class:`NuScenesError` to ``errors``."""
    try:
        return fn()
    except NuScenesError as e:
        errors.append(e)
        return None


__all__ = ["NuScenesConfig", "NuScenesError", "NuScenesSource"]
