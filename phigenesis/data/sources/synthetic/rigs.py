"""Sensor rigs of the synthetic source: camera layouts modelled on Waymo and nuScenes, and a LiDAR.

Camera mounting (ego frame: x forward, y left, z up, metres) and fields of view follow the real
rigs closely enough for the geometry to be realistic; image sizes are configurable (default
160 x 240, the paper's Waymo resolution).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from phigenesis import geometry
from phigenesis.data.records import CameraCalibration
from phigenesis.data.sources.synthetic_names import RIG_NAMES, RigName  # noqa: F401 (re-exported)
from phigenesis.options import ConfigError, check_options, option

BODY_FROM_OPENCV = geometry.BODY_FROM_OPENCV


@dataclass(frozen=True)
class CameraSpec:
    """One camera of a rig.

    Attributes:
        name: dataset-style camera name.
        yaw_deg: optical axis azimuth in the ego frame (0 = forward, +90 = left).
        pitch_deg: downward tilt of the optical axis (positive looks down).
        hfov_deg: horizontal field of view.
        position_m: (x, y, z) of the optical centre in the ego frame.
        distortion: OpenCV (k1, k2, p1, p2, k3).
        height_scale: image height relative to the configured height (Waymo side cameras are shorter).
    """

    name: str
    yaw_deg: float
    pitch_deg: float
    hfov_deg: float
    position_m: tuple[float, float, float]
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    height_scale: float = 1.0


# Waymo's five cameras look forward and to the sides (about 50 degrees wide each, 1920 wide images),
# with a small measured radial distortion; they fire in the order the LiDAR sweeps past them.
_WAYMO_DISTORTION = (0.035, -0.012, 0.0004, -0.0003, 0.0)
WAYMO5: tuple[CameraSpec, ...] = (
    CameraSpec("FRONT", 0.0, 1.0, 50.4, (1.55, 0.0, 2.10), _WAYMO_DISTORTION),
    CameraSpec("FRONT_LEFT", 45.0, 1.0, 50.4, (1.50, 0.10, 2.10), _WAYMO_DISTORTION),
    CameraSpec("FRONT_RIGHT", -45.0, 1.0, 50.4, (1.50, -0.10, 2.10), _WAYMO_DISTORTION),
    CameraSpec("SIDE_LEFT", 90.0, 1.0, 50.4, (1.20, 0.15, 2.10), _WAYMO_DISTORTION, 886 / 1280),
    CameraSpec("SIDE_RIGHT", -90.0, 1.0, 50.4, (1.20, -0.15, 2.10), _WAYMO_DISTORTION, 886 / 1280),
)

# nuScenes' six cameras cover 360 degrees: 70 degree cameras and a 110 degree rear one; the
# images are rectified (no distortion).
NUSCENES6: tuple[CameraSpec, ...] = (
    CameraSpec("CAM_FRONT", 0.0, 0.0, 70.0, (1.70, 0.00, 1.55)),
    CameraSpec("CAM_FRONT_RIGHT", -55.0, 0.0, 70.0, (1.55, -0.49, 1.50)),
    CameraSpec("CAM_FRONT_LEFT", 55.0, 0.0, 70.0, (1.52, 0.49, 1.51)),
    CameraSpec("CAM_BACK", 180.0, 0.0, 110.0, (0.03, 0.00, 1.57)),
    CameraSpec("CAM_BACK_LEFT", 110.0, 0.0, 70.0, (1.04, 0.48, 1.56)),
    CameraSpec("CAM_BACK_RIGHT", -110.0, 0.0, 70.0, (1.05, -0.48, 1.56)),
)

RIGS: dict[str, tuple[CameraSpec, ...]] = {"waymo5": WAYMO5, "nuscenes6": NUSCENES6}
#: Frame (LiDAR sweep) rate of each rig, Hz: Waymo runs at 10 Hz; nuScenes cameras at 12 Hz.
RIG_FRAME_RATE_HZ: dict[str, float] = {"waymo5": 10.0, "nuscenes6": 12.0}


def camera_calibrations(
    rig: str, height: int, width: int, uniform_size: bool = True
) -> tuple[list[CameraCalibration], list[CameraSpec]]:
    """Calibrations of a rig's cameras at the given image size (per-camera heights if not uniform)."""
    if rig not in RIGS:
        raise ValueError(f"unknown rig {rig!r}; choose one of {sorted(RIGS)}")
    cals = []
    for spec in RIGS[rig]:
        h = height if uniform_size else max(8, round(height * spec.height_scale))
        fx = 0.5 * width / np.tan(np.radians(spec.hfov_deg) / 2)
        k = geometry.intrinsic_matrix(fx, fx, (width - 1) / 2.0, (h - 1) / 2.0)
        body = geometry.rotation_z(np.radians(spec.yaw_deg)) @ _rotation_y(np.radians(spec.pitch_deg))
        ego_from_camera = geometry.make_transform(body @ BODY_FROM_OPENCV, spec.position_m)
        cals.append(CameraCalibration(spec.name, width, h, k, np.array(spec.distortion), ego_from_camera))
    return cals, list(RIGS[rig])


def _rotation_y(angle_rad: float) -> np.ndarray:
    """Rotation about +y; a positive angle tilts +x downwards (towards -z)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


#: How a LiDAR's beam elevations are laid out and stored in Waymo's calibration: "explicit" rows
#: follow :attr:`LidarSpec.inclination_warp` and are written as ``beam_inclinations`` (Waymo's
#: TOP); "min_max" rows are uniformly spaced, cell-centred, between the bottom and top elevation
#: and written as ``beam_inclination_min``/``max`` only (Waymo's short-range LiDARs).
InclinationLayout = Literal["explicit", "min_max"]


@dataclass(frozen=True)
class LidarSpec:
    """A spinning multi-beam LiDAR (Waymo-TOP-like by default).

    Attributes:
        beams: number of lasers (rows); row 0 is the highest beam.
        columns: azimuth steps per revolution.
        inclination_top_deg, inclination_bottom_deg: elevation of the highest/lowest beam
            ("explicit" layout) or the top/bottom edge of the field of view ("min_max").
        inclination_warp: >1 packs beams more densely near the top (horizon), as real sensors do
            ("explicit" layout only).
        inclinations: the beam layout, see :data:`InclinationLayout`.
        position_m: sensor origin in the ego frame.
        yaw_deg: mounting yaw about the ego z axis (0 = facing forward, +90 = left). Columns keep
            Waymo's range-image convention (column 0 at the ego's rear, whatever the yaw), so the
            yaw changes no ray, only the stored extrinsic.
        max_range_m, min_range_m: returns outside are dropped.
        range_noise_m: standard deviation of Gaussian range noise.
        dropout: probability of losing any return, before the reflectance-dependent losses.
        sectors: the sweep is ray cast in this many time slices; a point's time is its slice's time.
            One sector is a snapshot at the frame time (ego pose and agents at that time).
        returns: 1, or 2 for a second return behind semi-transparent surfaces (vegetation).
        second_return_fraction: with ``returns`` 2, the fraction of kept returns on vegetation
            whose pulse passes through and returns again from the next surface behind.
        second_return_gap_m: the least separation of the two returns along the ray (metres).
        ego_returns: False: rays that hit the ego car's own body give no return (an empty cell).
        name: the sensor's name in the dataset's files (Waymo: TOP, FRONT, SIDE_LEFT, ...).
    """

    beams: int = option(64, ge=1, le=1024)
    columns: int = option(1024, ge=1, le=100_000)
    inclination_top_deg: float = option(2.5, ge=-90, le=90)
    inclination_bottom_deg: float = option(-22.0, ge=-90, le=90)
    inclination_warp: float = option(1.6, gt=0, le=100)
    position_m: tuple[float, float, float] = option((1.2, 0.0, 2.15), ge=-100, le=100)
    max_range_m: float = option(75.0, gt=0, le=1000)
    min_range_m: float = option(1.0, ge=0, le=1000)
    range_noise_m: float = option(0.02, ge=0, le=10)
    dropout: float = option(0.01, ge=0, le=1)
    sectors: int = option(16, ge=1, le=100_000)
    inclinations: InclinationLayout = option("explicit")
    yaw_deg: float = option(0.0, ge=-180, le=180)
    returns: int = option(1, ge=1, le=2)
    second_return_fraction: float = option(0.5, ge=0, le=1)
    second_return_gap_m: float = option(0.5, gt=0, le=100)
    ego_returns: bool = option(True)
    name: str = option("TOP")

    def __post_init__(self) -> None:
        check_options(self, "LidarSpec")
        if self.columns < self.sectors:
            raise ConfigError(
                f"LidarSpec: columns = {self.columns}: must be at least sectors ({self.sectors})"
            )
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(
                f"LidarSpec: min_range_m = {self.min_range_m}: must be below max_range_m ({self.max_range_m})"
            )

    @property
    def cells(self) -> int:
        """Range-image cells per return (beams x columns)."""
        return self.beams * self.columns

    def inclinations_rad(self) -> np.ndarray:
        """(beams,) elevation angles, row 0 highest (for "min_max", exactly as Waymo's readers
        compute them from the minimum and maximum: cell-centred, uniform)."""
        if self.inclinations == "min_max":
            lo, hi = np.radians(self.inclination_bottom_deg), np.radians(self.inclination_top_deg)
            return (lo + (np.arange(self.beams) + 0.5) / self.beams * (hi - lo))[::-1].copy()
        u = np.linspace(0.0, 1.0, self.beams)
        warped = u**self.inclination_warp
        deg = self.inclination_top_deg + (self.inclination_bottom_deg - self.inclination_top_deg) * warped
        return np.radians(deg)

    def ego_from_sensor(self) -> np.ndarray:
        """(4, 4) the sensor's mounting: its yaw and position in the ego frame."""
        rotation = geometry.rotation_z(np.radians(self.yaw_deg)) + 0.0  # + 0.0: no -0.0 entries
        return geometry.make_transform(rotation, self.position_m)

    def column_azimuths_rad(self) -> np.ndarray:
        """(columns,) azimuth of each column in the ego frame: column 0 just left of the rear,
        decreasing (clockwise seen from above) through the front at the middle column, as Waymo."""
        c = np.arange(self.columns)
        return np.pi * (1.0 - (2.0 * c + 1.0) / self.columns)
