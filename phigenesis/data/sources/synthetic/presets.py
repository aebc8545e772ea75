"""Named presets of the synthetic source: the real datasets' sensor sizes, in one place.

A preset is a mapping of :class:`~phigenesis.data.sources.synthetic.SyntheticConfig` fields;
``SyntheticConfig.from_preset(name, **overrides)`` builds it (explicit fields win). Each value
below cites its public source:

- WOD paper: Sun et al., "Scalability in Perception for Autonomous Driving: Waymo Open Dataset",
  arXiv:1912.04838 (segments of 20 s at 10 Hz; the LiDARs' fields of view, Table 1).
- WOD repo: https://github.com/waymo-research/waymo-open-dataset (range-image shapes in
  ``src/waymo_open_dataset/v2/perception/compat_v1/lidar_test.py``; image sizes in the
  calibrations of its sample frames).
- Waymo site: https://waymo.com/open/data/perception/ (LiDAR ranges, "truncated to 75 meters",
  "20 meters").
- nuScenes paper: Caesar et al., "nuScenes: A multimodal dataset for autonomous driving",
  arXiv:1903.11027, sensor table (cameras, LIDAR_TOP).
- nuScenes devkit: https://github.com/nutonomy/nuscenes-devkit (issue #133: points per sweep).

- ``waymo``: Waymo Open Dataset Perception (v1.4 TFRecord / v2 Parquet). Five cameras, FRONT,
  FRONT_LEFT and FRONT_RIGHT at 1920 x 1280 and SIDE_LEFT, SIDE_RIGHT at 1920 x 886; five LiDARs
  with two returns each: TOP 64 x 2650 cells (75 m, -17.6 .. +2.4 deg) and four short-range
  LiDARs of 200 x 600 cells (20 m, -90 .. +30 deg). 169,600 + 4 x 120,000 = 649,600 cells per
  return.
- ``nuscenes``: nuScenes v1.0. Six cameras at 1600 x 900, 12 Hz; LIDAR_TOP a Velodyne HDL-32E
  (32 beams, +10 .. -30 deg, 20 Hz spin, 70 m).

The short-range LiDARs' mounts are plausible places on a Pacifica (front bumper, the two front
wings, rear bumper, 0.55 m above the ground), 5 cm outside the faces of the body boxes the Waymo
source assumes for every segment (:data:`phigenesis.data.ego_body.WAYMO_PACIFICA_BOXES`, whose
lower box the real perimeter LiDARs sit just outside), not Waymo's measured extrinsics, which the
public sources do not give. The synthetic car is shorter than a Pacifica, so they stand a little
clear of its rendered body. They are cast as one snapshot at the
frame time (``sectors`` 1): Waymo stores no per-pixel poses for them, so a reader puts their
points in the frame's vehicle frame, which is where a snapshot's points are exactly. They do not
return from the ego car's own body (``ego_returns`` False): those cells stay empty.
"""

from __future__ import annotations

from typing import Any

from phigenesis.data.sources import synthetic_names
from phigenesis.data.sources.synthetic.rigs import LidarSpec

#: Waymo TOP (mid-range) LiDAR: 64 beams x 2650 columns, 75 m, -17.6 .. +2.4 deg (shape from
#: the WOD repo's v2/perception/compat_v1/lidar_test.py, range from the Waymo site text, FOV
#: from the WOD paper's Table 1). Explicit (warped) beam inclinations, as Waymo stores TOP's.
WAYMO_TOP = LidarSpec(
    beams=64,
    columns=2650,
    inclination_top_deg=2.4,
    inclination_bottom_deg=-17.6,
    max_range_m=75.0,
    returns=2,
    name="TOP",
)


def waymo_short_range(name: str, position_m: tuple[float, float, float], yaw_deg: float) -> LidarSpec:
    """A Waymo short-range LiDAR: 200 beams x 600 columns, 20 m, -90 .. +30 deg (shape
    from the WOD repo's compat_v1/lidar_test.py, range "20 meters" from the Waymo site text, FOV from
    the WOD paper), uniform inclinations stored as min/max, two returns, cast as a snapshot."""
    return LidarSpec(
        beams=200,
        columns=600,
        inclination_top_deg=30.0,
        inclination_bottom_deg=-90.0,
        inclinations="min_max",
        position_m=position_m,
        yaw_deg=yaw_deg,
        max_range_m=20.0,
        min_range_m=0.3,
        sectors=1,
        returns=2,
        ego_returns=False,
        name=name,
    )


#: Waymo's four short-range LiDARs, 5 cm outside the Pacifica body box (front 4.049 m, rear
#: -1.127 m, sides +-1.0 m; ego_body.WAYMO_PACIFICA_BOXES), in Waymo's laser order FRONT,
#: SIDE_LEFT, SIDE_RIGHT, REAR.
WAYMO_SHORT_RANGE: tuple[LidarSpec, ...] = (
    waymo_short_range("FRONT", (4.10, 0.0, 0.55), 0.0),
    waymo_short_range("SIDE_LEFT", (2.9, 1.05, 0.55), 90.0),
    waymo_short_range("SIDE_RIGHT", (2.9, -1.05, 0.55), -90.0),
    waymo_short_range("REAR", (-1.18, 0.0, 0.55), 180.0),
)

#: nuScenes LIDAR_TOP, a Velodyne HDL-32E: 32 beams, +10 .. -30 deg, 20 Hz (the nuscenes6 rig's
#: spin), 70 m (nuScenes paper, sensor table), mounted at nuScenes' roof position.
#: The real sweep holds about 34-35k points (nuScenes devkit issue #133)
#: out of ~2170 firings per beam (1.39 M points/s at 20 Hz). The synthetic streets return ~85 % of
#: the rays (real ones about half), so the columns are chosen for the valid count instead: 1084
#: columns gave 26.7-31.0k valid points (9 sweeps, seeds 0-2; 26.5 per column), so 1300 columns
#: give ~34.5k.
NUSCENES_LIDAR_TOP = LidarSpec(
    beams=32,
    columns=1300,
    inclination_top_deg=10.0,
    inclination_bottom_deg=-30.0,
    inclination_warp=1.0,
    position_m=(0.94, 0.0, 1.84),
    max_range_m=70.0,
    name="LIDAR_TOP",
)

#: Named presets: SyntheticConfig fields per preset name.
PRESETS: dict[str, dict[str, Any]] = {
    "waymo": {
        "rig": "waymo5",  # WOD repo: five cameras
        "height": 1280,  # WOD repo: FRONT, FRONT_LEFT, FRONT_RIGHT 1920 x 1280
        "width": 1920,
        "uniform_image_size": False,  # WOD repo: SIDE_LEFT, SIDE_RIGHT 1920 x 886
        "frame_rate_hz": 10.0,  # WOD paper: 10 Hz
        "lidar": WAYMO_TOP,
        "extra_lidars": WAYMO_SHORT_RANGE,
    },
    "nuscenes": {
        "rig": "nuscenes6",  # nuScenes paper: six cameras
        "height": 900,  # nuScenes paper: 1600 x 900
        "width": 1600,
        "uniform_image_size": True,
        "frame_rate_hz": 12.0,  # nuScenes paper: cameras at 12 Hz
        "lidar": NUSCENES_LIDAR_TOP,
    },
}
PRESET_NAMES: tuple[str, ...] = tuple(PRESETS)
if PRESET_NAMES != synthetic_names.PRESET_NAMES:  # the command lines' choices come from there
    raise ImportError(f"presets {PRESET_NAMES} differ from synthetic_names.PRESET_NAMES")


def preset_values(name: str) -> dict[str, Any]:
    """Preset ``name``'s fields as plain values (LiDARs as mappings), as a pipeline spec or a
    command line's overrides hold them; a :class:`~phigenesis.options.ConfigError` names the
    presets for an unknown name."""
    # the package imports this module: a top-level import would be circular
    from phigenesis.data.sources.synthetic import SyntheticConfig

    full = SyntheticConfig.from_preset(name).to_dict()
    return {key: full[key] for key in PRESETS[name]}
