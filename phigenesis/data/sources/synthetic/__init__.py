"""Procedural driving scenes with exact truth, rendered by ray casting.

Entry points: :class:`SyntheticConfig` (what to generate) and :func:`synthetic_scene` (one scene,
with lazily rendered frames). :class:`SyntheticSource` enumerates the scenes of a run.

Time: scene time ``t`` in seconds is ``(timestamp_micros - start_micros) / 1e6``; frame k is at
``start_micros + round(k * 1e6 / frame_rate_hz)``. A frame's LiDAR revolution is centred on its
timestamp; each camera fires when the revolution passes its optical axis (rolling through the rig
as Waymo's and nuScenes' cameras do), so every image has its own timestamp and ego pose.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import numpy as np

from phigenesis import geometry
from phigenesis.data.records import (
    Boxes,
    CameraImage,
    Frame,
    LazyFrames,
    LidarSweep,
    Scene,
    encode_rgb,
)
from phigenesis.data.sources import given
from phigenesis.data.sources.synthetic import meshes
from phigenesis.data.sources.synthetic.renderer import Renderer
from phigenesis.data.sources.synthetic.rigs import (
    RIG_FRAME_RATE_HZ,
    LidarSpec,
    RigName,
    camera_calibrations,
)
from phigenesis.data.sources.synthetic.world import World, build_world
from phigenesis.options import ConfigError, check_options, from_mapping, option

SOURCE_NAME = "synthetic"
#: The ego car's body as boxes in the ego frame (what the cameras and LiDAR may see of it),
#: each a centre and size (length, width, height) in metres: the lower body, the cabin's base and
#: the cabin (see :func:`meshes.ego_body`).
_BODY_FRONT_M = meshes.EGO_BODY_REAR_M + meshes.EGO_BODY_LENGTH_M
EGO_BOXES = [
    {"center_ego": [(meshes.EGO_BODY_REAR_M + _BODY_FRONT_M) / 2, 0.0, 0.375], "size_lwh": [4.1, 1.8, 0.75]},
    {"center_ego": [meshes.EGO_BODY_REAR_M + 1.4, 0.0, 0.85], "size_lwh": [2.8, 1.8, 0.2]},
    {"center_ego": [0.6, 0.0, 1.145], "size_lwh": [1.8, 1.6, 0.39]},
]
#: The spin period of the LiDAR per rig (s): Waymo's spins at 10 Hz, nuScenes' at 20 Hz.
LIDAR_SPIN_PERIOD_S = {"waymo5": 0.1, "nuscenes6": 0.05}


@dataclass(frozen=True)
class SyntheticConfig:
    """What the synthetic source generates (every field changes the output; all are recorded).

    A scene's world (road lengths, agents' timing) is laid out for the scene's duration, so the
    same seed with another frame count or rate gives another scene; truth is exact at any time.

    Attributes:
        scenes: number of scenes.
        frames: frames per scene.
        seed: base seed; scene i uses the seed sequence (seed, i).
        rig: camera rig, "waymo5" or "nuscenes6".
        height, width: image size in pixels.
        uniform_image_size: False gives Waymo's side cameras their real, shorter aspect.
        frame_rate_hz: frame (LiDAR sweep) rate; None = the rig's (10 Hz Waymo, 12 Hz nuScenes).
        lidar: the (first) LiDAR's parameters.
        extra_lidars: further LiDARs (Waymo's short-range ones), each with its own parameters;
            a sweep's points carry ``lidar_id`` 0 for ``lidar`` and i + 1 for ``extra_lidars[i]``.
        render_scale: images and their per-pixel truth are ray cast at 1/render_scale of the
            size in each axis and resized to the full size (images bilinear, depth, labels and
            flow nearest); the LiDAR is always cast at full density. For cost benchmarks, where
            the size of the data matters and its pixel content little: at edges the truth is
            then that of the nearest coarse pixel, not of the pixel itself.
        jpeg_quality: quality of the stored JPEG images.
        ego_body: render the ego car's own body (seen by low cameras and the LiDAR).
        shadows: cast sun shadows.
        box_range_m: frames list the boxes of agents within this distance of the ego.
        start_micros: timestamp of each scene's first frame.
    """

    scenes: int = option(2, ge=1, le=1_000_000)
    frames: int = option(40, ge=1, le=100_000)
    seed: int = option(0, ge=0, le=2**32 - 1)
    rig: RigName = option("waymo5")
    height: int = option(160, ge=8, le=100_000)
    width: int = option(240, ge=8, le=100_000)
    uniform_image_size: bool = option(True)
    frame_rate_hz: float | None = option(None, gt=0, le=1000)
    lidar: LidarSpec = option(factory=LidarSpec)
    extra_lidars: tuple[LidarSpec, ...] = option(())
    render_scale: int = option(1, ge=1, le=64)
    jpeg_quality: int = option(95, ge=1, le=100)
    ego_body: bool = option(True)
    shadows: bool = option(True)
    box_range_m: float = option(80.0, gt=0, le=1000)
    start_micros: int = option(1_600_000_000_000_000, ge=0, le=2**62)

    def __post_init__(self) -> None:
        if isinstance(self.extra_lidars, list | tuple):  # mappings (a spec's YAML) -> LidarSpec
            specs = tuple(
                from_mapping(LidarSpec, s, f"SyntheticConfig: extra_lidars[{i}]")
                if isinstance(s, Mapping)
                else s
                for i, s in enumerate(self.extra_lidars)
            )
            object.__setattr__(self, "extra_lidars", specs)
        check_options(self, "SyntheticConfig")

    @classmethod
    def from_preset(cls, name: str, **overrides: Any) -> SyntheticConfig:
        """The config of preset ``name`` (see :mod:`.presets`: ``waymo``, ``nuscenes``), with
        ``overrides`` (further fields, or fields that replace the preset's)."""
        # presets imports this package
        from phigenesis.data.sources.synthetic.presets import PRESETS

        if name not in PRESETS:
            raise ConfigError(f"unknown synthetic preset {name!r}; choose one of {', '.join(PRESETS)}")
        return cls.from_dict({**PRESETS[name], **overrides}, where=f"synthetic preset {name!r}")

    @property
    def lidars(self) -> tuple[LidarSpec, ...]:
        """Every LiDAR, ``lidar`` first; a point's ``lidar_id`` is its LiDAR's index here."""
        return (self.lidar, *self.extra_lidars)

    @property
    def rate_hz(self) -> float:
        return float(self.frame_rate_hz or RIG_FRAME_RATE_HZ[self.rig])

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "synthetic source parameters") -> SyntheticConfig:
        """A config from plain values (as in a pipeline spec, ``lidar`` a mapping of
        :class:`LidarSpec`'s; None: the default); an unknown key or a value outside its type or
        range is a :class:`~phigenesis.options.ConfigError` naming ``where``."""
        return from_mapping(cls, given(values), where)

    def scene_ids(self) -> list[str]:
        return [f"synthetic-s{self.seed}-{i:04d}" for i in range(self.scenes)]


class SyntheticSource:
    """The scenes of a synthetic run, each built on demand (worlds are cheap, frames are not)."""

    name = SOURCE_NAME

    def __init__(self, config: SyntheticConfig):
        self.config = config

    def scene_ids(self) -> list[str]:
        return self.config.scene_ids()

    def arguments(self) -> dict[str, Any]:
        return self.config.to_dict()

    def load(self, scene_id: str) -> Scene:
        ids = self.scene_ids()
        if scene_id not in ids:
            raise KeyError(f"synthetic run has no scene {scene_id!r} (has {ids[0]} .. {ids[-1]})")
        return synthetic_scene(self.config, ids.index(scene_id))


class SyntheticScene:
    """Renders the frames of one synthetic scene; also answers truth queries at any time."""

    def __init__(self, config: SyntheticConfig, index: int):
        self.config = config
        self.index = index
        self.scene_id = config.scene_ids()[index]
        self.seed_sequence = (int(config.seed), int(index))
        self.calibrations, self.specs = camera_calibrations(
            config.rig, config.height, config.width, config.uniform_image_size
        )
        self.spin_period_s = LIDAR_SPIN_PERIOD_S[config.rig]
        self.frame_micros = [
            config.start_micros + round(k * 1e6 / config.rate_hz) for k in range(config.frames)
        ]
        self.duration_s = (self.frame_micros[-1] - config.start_micros) * 1e-6 + self.spin_period_s

    @cached_property
    def world(self) -> World:
        seed = int(np.random.SeedSequence(self.seed_sequence).generate_state(1)[0])
        return build_world(seed, self.duration_s, ego_body=self.config.ego_body)

    @cached_property
    def renderer(self) -> Renderer:
        return Renderer(self.world, shadows=self.config.shadows)

    def seconds(self, timestamp_micros: int) -> float:
        return (int(timestamp_micros) - self.config.start_micros) * 1e-6

    def world_from_ego(self, timestamp_micros: int) -> np.ndarray:
        """Exact (4, 4) ego pose at any time."""
        return self.world.world_from_ego(self.seconds(timestamp_micros))

    def world_from_ego_many(self, timestamps_micros: np.ndarray) -> np.ndarray:
        """Exact (N, 4, 4) ego poses at N times."""
        t = (np.asarray(timestamps_micros, np.int64) - self.config.start_micros) * 1e-6
        return self.world.world_from_ego(t)

    def boxes_at(self, timestamp_micros: int, range_m: float | None = None) -> Boxes:
        """Exact boxes at any time (all agents, or those within ``range_m`` of the ego)."""
        return self.world.boxes_at(self.seconds(timestamp_micros), range_m)

    def camera_time_micros(self, frame_micros: int, camera_index: int) -> int:
        """When camera ``camera_index`` fires in the revolution centred on ``frame_micros``.

        The LiDAR sweeps clockwise from the rear (azimuth +pi) through the front (0, at the frame
        time); a camera fires as the sweep crosses its optical axis.
        """
        yaw = np.radians(self.specs[camera_index].yaw_deg)
        fraction = np.mod(np.pi - yaw, 2 * np.pi) / (2 * np.pi)
        return int(frame_micros + round((fraction - 0.5) * self.spin_period_s * 1e6))

    def render_frame(self, frame_index: int) -> Frame:
        """Frame ``frame_index`` with its images, LiDAR sweep, boxes and exact truth."""
        return self.render_frame_and_lidar(frame_index)[0]

    def render_frame_and_lidar(
        self, frame_index: int, images: bool = True
    ) -> tuple[Frame, list[dict[str, np.ndarray]]]:
        """The frame, and its LiDAR sweeps as the renderer returned them, one dict per LiDAR of
        ``config.lidars`` (with each point's beam, column, measured range and return: what a
        range-image writer needs). ``images=False`` skips the cameras' images and truth maps
        (their times and poses stay): the frame's geometry only."""
        cfg = self.config
        t_micros = self.frame_micros[frame_index]
        world_from_ego = self.world_from_ego(t_micros)
        rng = np.random.default_rng([*self.seed_sequence, frame_index])
        cameras = []
        for i, cal in enumerate(self.calibrations):
            cam_micros = self.camera_time_micros(t_micros, i)
            cam_pose = self.world_from_ego(cam_micros)
            image_bytes, truth = None, None
            if images:
                rgb, truth = self.renderer.render_camera(
                    cal, cam_pose, self.seconds(cam_micros), render_scale=cfg.render_scale
                )
                image_bytes = encode_rgb(rgb, "jpeg", cfg.jpeg_quality)
            cameras.append(
                CameraImage(
                    calibration=cal,
                    timestamp_micros=cam_micros,
                    world_from_ego=cam_pose,
                    image_bytes=image_bytes,
                    image_format="jpeg",
                    truth=truth,
                )
            )
        raws = self.renderer.render_lidars(cfg.lidars, t_micros, cfg.start_micros, self.spin_period_s, rng)
        lidar = self._lidar(raws, t_micros, world_from_ego)
        boxes = self.boxes_at(t_micros, cfg.box_range_m)
        if lidar.instance is not None and len(boxes):
            counts = np.bincount(lidar.instance, minlength=int(boxes.instance_id.max()) + 1)
            boxes.num_lidar_points = counts[boxes.instance_id].astype(np.int32)
        frame = Frame(
            scene_id=self.scene_id,
            frame_index=frame_index,
            timestamp_micros=t_micros,
            world_from_ego=world_from_ego,
            cameras=cameras,
            lidar=lidar,
            boxes=boxes,
        )
        return frame, raws

    def render_geometry(self, frame_index: int) -> Frame:
        """Frame ``frame_index`` without images or truth maps (poses, LiDAR, boxes): about 5x
        cheaper than :meth:`render_frame`, for scene-wide stages."""
        return self.render_frame_and_lidar(frame_index, images=False)[0]

    def _lidar(
        self, raws: list[dict[str, np.ndarray]], t_micros: int, world_from_ego: np.ndarray
    ) -> LidarSweep:
        """The sweep of every LiDAR (``lidar_id`` its index in ``config.lidars``), in order;
        ``return_index`` only where some LiDAR has second returns (None: all first returns)."""
        ego_from_world = geometry.invert_transform(world_from_ego)

        def cat(key: str) -> np.ndarray:
            return raws[0][key] if len(raws) == 1 else np.concatenate([r[key] for r in raws])

        lidar_id = np.concatenate([np.full(len(r["beam"]), i, np.uint8) for i, r in enumerate(raws)])
        two_returns = any(spec.returns > 1 for spec in self.config.lidars)
        return LidarSweep(
            timestamp_micros=t_micros,
            world_from_ego=world_from_ego,
            points_ego=geometry.transform_points(ego_from_world, cat("points_world")).astype(np.float32),
            intensity=cat("intensity"),
            beam_index=cat("beam"),
            origins_ego=geometry.transform_points(ego_from_world, cat("origins_world")).astype(np.float32),
            time_offset_micros=(cat("time_micros") - t_micros).astype(np.int32),
            lidar_id=lidar_id,
            semantic=cat("semantic"),
            instance=cat("instance"),
            return_index=cat("return_index") if two_returns else None,
        )

    def scene(self) -> Scene:
        return Scene(
            scene_id=self.scene_id,
            source=SOURCE_NAME,
            calibrations=list(self.calibrations),
            frames=LazyFrames(self.config.frames, self.render_frame, self.render_geometry),
            metadata={
                "rig": self.config.rig,
                "seed": list(self.seed_sequence),
                "frame_rate_hz": self.config.rate_hz,
                "lidar_spin_period_s": self.spin_period_s,
                "ego_boxes": EGO_BOXES,
            },
        )


def synthetic_scene(config: SyntheticConfig, index: int) -> Scene:
    """Scene ``index`` of a synthetic run, with frames rendered when accessed."""
    return SyntheticScene(config, index).scene()


__all__ = ["SyntheticConfig", "SyntheticScene", "SyntheticSource", "synthetic_scene"]
