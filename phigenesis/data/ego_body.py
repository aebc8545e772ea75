"""The recording vehicles' bodies as boxes in the ego frame, and the check that none holds a sensor.

A body is a list of axis-aligned boxes in the ego frame (x forward, y left, z up, metres), each
``{"center_ego": [x, y, z], "size_lwh": [length, width, height]}``: the format sources put in a
scene's ``metadata["ego_boxes"]`` and :func:`phigenesis.data.stages.aggregate.ego_boxes_of` reads.
The depth stages drop LiDAR returns inside the body (grown by a margin) and give the pixels whose
rays enter it no depth.

A body must sit below and around the sensors, never over them: a camera centre inside a box makes
every pixel of that camera "ego body", so a wrong body silently erases the camera's depth.
:func:`check_sensors_outside` turns that into an error naming the scene, the sensor and the box.
Each body here is a lower body up to the bonnet and belt line, a cabin that stops below the
roof-mounted sensors, and small boxes filling the rest where no camera can see them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from phigenesis import geometry
from phigenesis.errors import PrepError

#: One box of a body: centre and size (length, width, height), metres, ego frame.
EgoBox = dict[str, list[float]]


def box_between(x_m: tuple[float, float], half_width_m: float, z_m: tuple[float, float]) -> EgoBox:
    """The ego box spanning ``x_m`` (rear, front) and ``z_m`` (bottom, top), centred on y = 0 and
    ``half_width_m`` to each side (metres, ego frame)."""
    (x0, x1), (z0, z1) = x_m, z_m
    assert x1 > x0 and z1 > z0 and half_width_m > 0, (x_m, half_width_m, z_m)
    return {
        "center_ego": [round((x0 + x1) / 2, 4), 0.0, round((z0 + z1) / 2, 4)],
        "size_lwh": [round(x1 - x0, 4), round(2 * half_width_m, 4), round(z1 - z0, 4)],
    }


# nuScenes' Renault Zoe (ZE 40; nuscenes-devkit issue #777 names the model). Ego origin: the centre
# of the rear axle projected onto the ground (devkit issues #161 and #997), so z is height above
# the road. Dimensions as in autonomousvision/py123d (get_nuscenes_renault_zoe_parameters, after
# Renault's and Wikipedia's specifications): length 4.084 m, width 1.730 m without mirrors, height
# 1.562 m, wheelbase 2.588 m, centre 1.385 m ahead of the rear axle, so the rear bumper is at
# x = -0.657 m and the front one at 3.427 m. The sensors (calibrated_sensor, nuScenes v1.0): cameras
# 1.50-1.59 m high at the roof's edges (CAM_FRONT x 1.70 m, CAM_BACK x 0.03 m, the side ones at
# |y| 0.48-0.49 m), LIDAR_TOP at (0.94, 0, 1.84) m. The roof itself (1.562 m) is higher than the
# front cameras, so one box of the car's size would hold every camera; the cabin stops at 1.45 m.
# CAM_BACK sees the tailgate in the bottom ~100 of its 900 rows (nerfstudio pull request #1679,
# which masks them): the cabin's rear edge at x = -0.27 m puts the body's top edge there.
ZOE_REAR_M, ZOE_FRONT_M, ZOE_HALF_WIDTH_M = -0.657, 3.427, 0.865
NUSCENES_ZOE_BOXES: list[EgoBox] = [
    # Lower body from the rear bumper to the windscreen's base, up to the belt line.
    box_between((ZOE_REAR_M, 2.40), ZOE_HALF_WIDTH_M, (0.0, 0.95)),
    # The bonnet, lower towards the front bumper (out of CAM_FRONT's view, as in its images).
    box_between((2.40, ZOE_FRONT_M), ZOE_HALF_WIDTH_M, (0.0, 0.80)),
    # Cabin from the top of the tailgate to the top of the windscreen, below every camera.
    box_between((-0.27, 1.45), 0.70, (0.95, 1.45)),
    # The sloping rear window below the cabin's rear edge.
    box_between((-0.55, -0.27), 0.70, (0.95, 1.20)),
    # The roof between the cameras, up to the roof's height: behind CAM_BACK's view and on the far
    # side of every other camera's, it holds the LiDAR's returns off the roof (the HDL-32E's lowest
    # beam, -30.7 deg, meets the roof about 0.5 m from the sensor).
    box_between((0.15, 1.35), 0.40, (1.45, 1.60)),
]

# Waymo's Chrysler Pacifica. Vehicle frame origin: the centre of the rear axle, z up, at road level
# (in the sample frame, the bottoms of the boxes within 10 m lie between -0.18 and +0.04 m; py123d
# puts the van's centre at height / 2 too). Dimensions as in nuPlan's devkit
# (get_pacifica_parameters, the same vehicle): rear axle to front bumper 4.049 m, to rear bumper
# 1.127 m, height 1.777 m, wheelbase 3.089 m; width 2.02 m without mirrors (Chrysler: 79.6 in;
# nuPlan's 2.297 m includes them). The sensors (calibrations of the Waymo sample frames,
# shared/data/waymo): cameras at z 2.115 m (x 1.43-1.54 m), TOP LiDAR at (1.43, 0, 2.18) m, the
# perimeter LiDARs on the body's surface: FRONT (4.07, 0, 0.69), REAR (-1.155, 0, 0.46),
# SIDE_LEFT/RIGHT (3.245, +-1.025, 0.98) m. A single box of the van's size would hold no roof
# sensor, but its top would reach 2.5 m ahead of the FRONT camera, 0.34 m below it, and cover every
# pixel more than 7.7 deg below its horizon (the lower 28 % of its rows): the bonnet and windscreen
# are lower boxes.
PACIFICA_REAR_M, PACIFICA_FRONT_M, PACIFICA_HALF_WIDTH_M = -1.127, 4.049, 1.0
WAYMO_PACIFICA_BOXES: list[EgoBox] = [
    # Lower body, bumper to bumper, up to the bonnet and belt line (the perimeter LiDARs sit on its
    # faces, just outside).
    box_between((PACIFICA_REAR_M, PACIFICA_FRONT_M), PACIFICA_HALF_WIDTH_M, (0.0, 1.05)),
    # Cabin from the (near-vertical) tailgate to the top of the windscreen, up to the roof.
    box_between((-1.0, 1.9), 0.95, (1.05, 1.777)),
    # The lower windscreen and the bonnet's rear, below every camera's view.
    box_between((1.9, 2.9), 0.95, (1.05, 1.40)),
]


def sensor_in_box(position_ego: ArrayLike, box: Mapping[str, list[float]]) -> bool:
    """Whether an ego-frame position (metres) lies inside an ego box (its faces included)."""
    p = np.asarray(position_ego, np.float64).reshape(1, 3)
    return bool(geometry.points_in_box(p, box["center_ego"], box["size_lwh"], 0.0)[0])


def check_sensors_outside(
    scene_id: str,
    ego_boxes: list[EgoBox],
    sensors: Mapping[str, ArrayLike],
    boxes_from: str = "the scene metadata's ego_boxes",
) -> None:
    """Raises :class:`~phigenesis.errors.PrepError` if an ego box holds a sensor.

    Args:
        scene_id: named in the message.
        ego_boxes: the body (ego frame, see the module docstring).
        sensors: ego-frame positions (metres) by a name for the message ("camera CAM_FRONT",
            "LiDAR (lidar_id 0)"): camera centres, LiDAR origins.
        boxes_from: where the boxes came from, for the message.
    """
    for sensor, position in sensors.items():
        for i, box in enumerate(ego_boxes):
            if sensor_in_box(position, box):
                xyz = ", ".join(f"{v:.3f}" for v in np.asarray(position, np.float64).reshape(3))
                raise PrepError(
                    f"scene {scene_id}: the {sensor} at ({xyz}) m (ego frame) lies inside ego box {i} "
                    f"(centre {box['center_ego']} m, size l/w/h {box['size_lwh']} m) of {boxes_from}; "
                    "it would see nothing but the ego body and give no depth. The body must sit below "
                    "and around the sensors: give the vehicle's boxes in the scene's metadata "
                    '"ego_boxes"'
                )


def camera_centres(calibrations: list) -> dict[str, NDArray[np.float64]]:
    """Ego-frame optical centres (metres) of ``CameraCalibration`` s, keyed "camera <name>"."""
    return {f"camera {c.name}": np.asarray(c.ego_from_camera, np.float64)[:3, 3] for c in calibrations}


def lidar_origins(origins_ego: NDArray[np.floating], lidar_id: NDArray[np.integer]) -> dict[str, NDArray]:
    """The median ray origin (ego frame, metres) of each LiDAR of a sweep, keyed by
    :func:`lidar_name`.

    Origins move with the ego through a revolution (Waymo's TOP, the synthetic LiDAR); the median
    is the mount position at about the sweep's reference time."""
    origins = np.asarray(origins_ego, np.float64)
    assert origins.ndim == 2 and origins.shape[1] == 3, origins.shape
    ids = np.asarray(lidar_id)
    return {lidar_name(int(k)): np.median(origins[ids == k], axis=0) for k in np.unique(ids)}


def lidar_name(lidar_id: int) -> str:
    """How messages name a LiDAR of a sweep (its ``lidar_id``)."""
    return f"LiDAR (lidar_id {lidar_id})"


__all__ = [
    "NUSCENES_ZOE_BOXES",
    "WAYMO_PACIFICA_BOXES",
    "EgoBox",
    "box_between",
    "camera_centres",
    "check_sensors_outside",
    "lidar_name",
    "lidar_origins",
    "sensor_in_box",
]
