"""The unified semantic taxonomy: Cityscapes' 19 training classes plus ignore.

Every source maps its own labels into these ids; boxes use the same ids for their class, so one
table serves semantics and detection. Ids are uint8; 255 means ignore / unlabelled (the ego car's
own body, pixels a dataset does not label).
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "road",
    "sidewalk",
    "building",
    "wall",
    "fence",
    "pole",
    "traffic_light",
    "traffic_sign",
    "vegetation",
    "terrain",
    "sky",
    "person",
    "rider",
    "car",
    "truck",
    "bus",
    "train",
    "motorcycle",
    "bicycle",
)
NUM_CLASSES = len(CLASS_NAMES)
IGNORE_ID = 255

CLASS_IDS: dict[str, int] = {name: i for i, name in enumerate(CLASS_NAMES)}

ROAD = CLASS_IDS["road"]
SIDEWALK = CLASS_IDS["sidewalk"]
BUILDING = CLASS_IDS["building"]
WALL = CLASS_IDS["wall"]
FENCE = CLASS_IDS["fence"]
POLE = CLASS_IDS["pole"]
TRAFFIC_LIGHT = CLASS_IDS["traffic_light"]
TRAFFIC_SIGN = CLASS_IDS["traffic_sign"]
VEGETATION = CLASS_IDS["vegetation"]
TERRAIN = CLASS_IDS["terrain"]
SKY = CLASS_IDS["sky"]
PERSON = CLASS_IDS["person"]
RIDER = CLASS_IDS["rider"]
CAR = CLASS_IDS["car"]
TRUCK = CLASS_IDS["truck"]
BUS = CLASS_IDS["bus"]
TRAIN = CLASS_IDS["train"]
MOTORCYCLE = CLASS_IDS["motorcycle"]
BICYCLE = CLASS_IDS["bicycle"]

#: Classes whose objects are "things" with instances and boxes.
THING_IDS: frozenset[int] = frozenset({PERSON, RIDER, CAR, TRUCK, BUS, TRAIN, MOTORCYCLE, BICYCLE})
#: Things that deform (their points cannot be accumulated rigidly over time).
NON_RIGID_IDS: frozenset[int] = frozenset({PERSON, RIDER})
#: The ground a level camera's rays meet: what Stage 1's ground gate learns to find.
GROUND_IDS: frozenset[int] = frozenset({ROAD, SIDEWALK, TERRAIN})

#: The Cityscapes colour palette (RGB), indexed by class id; ignore is black.
PALETTE_RGB = np.zeros((256, 3), dtype=np.uint8)
PALETTE_RGB[:NUM_CLASSES] = np.array(
    [
        (128, 64, 128),
        (244, 35, 232),
        (70, 70, 70),
        (102, 102, 156),
        (190, 153, 153),
        (153, 153, 153),
        (250, 170, 30),
        (220, 220, 0),
        (107, 142, 35),
        (152, 251, 152),
        (70, 130, 180),
        (220, 20, 60),
        (255, 0, 0),
        (0, 0, 142),
        (0, 0, 70),
        (0, 60, 100),
        (0, 80, 100),
        (0, 0, 230),
        (119, 11, 32),
    ],
    dtype=np.uint8,
)


def class_name(class_id: int) -> str:
    """Name of a class id, ``"ignore"`` for 255."""
    if class_id == IGNORE_ID:
        return "ignore"
    if not 0 <= class_id < NUM_CLASSES:
        raise ValueError(f"class id {class_id} is not in the unified taxonomy (0..{NUM_CLASSES - 1}, 255)")
    return CLASS_NAMES[class_id]


#: nuScenes category names (detection and lidarseg, v1.0) -> unified class id. Classes Cityscapes
#: has no place for (animals, cones, debris, trailers, racks, strollers, noise, the ego car) are
#: ignored, as Waymo's are; a barrier is a fence; ambulances and construction vehicles are trucks;
#: a person on a scooter or skateboard is a rider.
NUSCENES_CATEGORY_IDS: dict[str, int] = {
    "animal": IGNORE_ID,
    "human.pedestrian.adult": PERSON,
    "human.pedestrian.child": PERSON,
    "human.pedestrian.construction_worker": PERSON,
    "human.pedestrian.personal_mobility": RIDER,
    "human.pedestrian.police_officer": PERSON,
    "human.pedestrian.stroller": IGNORE_ID,
    "human.pedestrian.wheelchair": PERSON,
    "movable_object.barrier": FENCE,
    "movable_object.debris": IGNORE_ID,
    "movable_object.pushable_pullable": IGNORE_ID,
    "movable_object.trafficcone": IGNORE_ID,
    "static_object.bicycle_rack": IGNORE_ID,
    "vehicle.bicycle": BICYCLE,
    "vehicle.bus.bendy": BUS,
    "vehicle.bus.rigid": BUS,
    "vehicle.car": CAR,
    "vehicle.construction": TRUCK,
    "vehicle.emergency.ambulance": TRUCK,
    "vehicle.emergency.police": CAR,
    "vehicle.motorcycle": MOTORCYCLE,
    "vehicle.trailer": IGNORE_ID,
    "vehicle.truck": TRUCK,
    # lidarseg-only categories
    "noise": IGNORE_ID,
    "flat.driveable_surface": ROAD,
    "flat.other": IGNORE_ID,
    "flat.sidewalk": SIDEWALK,
    "flat.terrain": TERRAIN,
    "static.manmade": BUILDING,
    "static.other": IGNORE_ID,
    "static.vegetation": VEGETATION,
    "vehicle.ego": IGNORE_ID,
}
