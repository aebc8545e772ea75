"""Procedural driving worlds: a road with curves and a junction, its surroundings, and agents.

Deterministic per seed. The layout (world frame, metres, z up; the ego starts at the origin
heading +x, in the right-hand driving lane):

- a main road (two driving lanes and two parking lanes, 12 m wide) made of a straight, an arc,
  a straight holding a four-way junction, a second arc and a long straight; a cross road through
  the junction; lane markings and zebra crossings;
- raised sidewalks with kerbs along every road, grass terrain, buildings with windows, walls,
  street lights, signs, traffic lights at the junction, trees and bushes;
- agents with exact continuous motion: parked vehicles, a lead and a following vehicle,
  oncoming traffic, vehicles turning at the junction, stop-and-go vehicles, and pedestrians who
  walk, stand or cross. Candidate agents whose boxes would overlap the ego's or another agent's
  during the scene are rejected, so the traffic never collides.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.records import Boxes
from phigenesis.data.sources.synthetic import meshes
from phigenesis.data.sources.synthetic.meshes import LabelledMesh
from phigenesis.data.sources.synthetic.motion import Path, Segment, SpeedProfile, Trajectory

ROAD_HALF_WIDTH_M = 6.0
LANE_OFFSET_M = 1.75
PARKING_OFFSET_M = 4.75
SIDEWALK_WIDTH_M = 3.0
SIDEWALK_HEIGHT_M = 0.15
CROSS_ARM_M = 150.0
#: Margin between agents' boxes below which a candidate agent is rejected, metres.
COLLISION_MARGIN_M = 0.4

AgentKind = Literal[
    "parked", "lead", "follower", "oncoming", "turning", "stop_and_go", "walking", "standing", "crossing"
]

VEHICLE_SIZES: dict[int, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    # class: ((length range), (width range), (height range)), metres
    tx.CAR: ((4.0, 4.9), (1.75, 1.95), (1.40, 1.65)),
    tx.TRUCK: ((6.5, 8.5), (2.3, 2.5), (2.8, 3.4)),
    tx.BUS: ((10.5, 12.0), (2.5, 2.6), (3.0, 3.3)),
}


@dataclass
class Agent:
    """A movable object with exact motion.

    Attributes:
        instance_id: 1-based id used in instance maps and boxes.
        track_id: stable string id within the scene.
        class_id: unified taxonomy class.
        kind: how it moves (for analysis, e.g. turning vs straight tracks).
        size_lwh: (3,) box size, metres.
        trajectory: its motion; the box centre is ``trajectory.z_m`` above the world's z = 0.
        mesh: its surface in the body frame.
    """

    instance_id: int
    track_id: str
    class_id: int
    kind: AgentKind
    size_lwh: NDArray[np.float64]
    trajectory: Trajectory
    mesh: LabelledMesh

    @property
    def is_static(self) -> bool:
        return self.trajectory.is_static()


@dataclass
class World:
    """Everything the renderer needs for one scene, with truth at any time ``t`` (seconds from the
    scene's first frame)."""

    static_mesh: LabelledMesh
    agents: list[Agent]
    ego: Trajectory
    ego_mesh: LabelledMesh | None
    sun_direction: NDArray[np.float64]
    duration_s: float
    roads: dict[str, Path] = field(default_factory=dict)

    def world_from_ego(self, t_s: float | NDArray[np.float64]) -> NDArray[np.float64]:
        """(..., 4, 4) ego pose (origin on the ground below the rear axle)."""
        return self.ego.world_from_body(t_s)

    def boxes_at(self, t_s: float, range_m: float | None = None) -> Boxes:
        """Exact boxes of all agents at ``t_s`` (within ``range_m`` of the ego, if given)."""
        ego_xy = self.ego.state(t_s)[0][:2]
        keep, centers, yaws, vels, accels = [], [], [], [], []
        for agent in self.agents:
            pos, yaw, vel, _ = agent.trajectory.state(t_s)
            if range_m is not None and np.hypot(*(pos[:2] - ego_xy)) > range_m:
                continue
            keep.append(agent)
            centers.append(pos)
            yaws.append(float(yaw))
            vels.append(vel)
            accels.append(agent.trajectory.acceleration(t_s))
        m = len(keep)
        return Boxes(
            track_id=[a.track_id for a in keep],
            class_id=np.array([a.class_id for a in keep], np.uint8),
            center_world=np.array(centers).reshape(m, 3),
            size_lwh=np.array([a.size_lwh for a in keep]).reshape(m, 3),
            yaw_world=np.array(yaws),
            velocity_world=np.array(vels).reshape(m, 3),
            status=np.zeros(m, np.uint8),
            instance_id=np.array([a.instance_id for a in keep], np.uint16),
            num_lidar_points=np.full(m, -1, np.int32),
            acceleration_world=np.array(accels).reshape(m, 3),
        )


# --------------------------------------------------------------------------------------------
# Building the world


def build_world(seed: int, duration_s: float, ego_body: bool = True) -> World:
    """Builds a deterministic world for a scene of ``duration_s`` seconds from a seed."""
    rng = np.random.default_rng(seed)
    ego_speed = _ego_speed_profile(rng, duration_s)
    travel_m = float(ego_speed.state(duration_s)[0]) - ego_speed.s0

    # Main road centreline in a local frame, then moved so the ego starts at the origin.
    lead_in = rng.uniform(8.0, 20.0)  # straight road between the ego's start and the first arc
    arc1_len = rng.uniform(25.0, 55.0)
    arc1_k = rng.choice([-1, 1]) / rng.uniform(45.0, 120.0)
    line_b = 80.0  # holds the junction at its middle
    arc2_len = rng.uniform(25.0, 55.0)
    arc2_k = rng.choice([-1, 1]) / rng.uniform(45.0, 120.0)
    back = 120.0  # road behind the ego's start
    covered = lead_in + arc1_len + line_b + arc2_len
    tail = max(120.0, travel_m - covered + 160.0)
    local = Path(
        (0.0, 0.0),
        0.0,
        [
            Segment(back + lead_in),
            Segment(arc1_len, arc1_k),
            Segment(line_b),
            Segment(arc2_len, arc2_k),
            Segment(tail),
        ],
    )
    ego_s0 = back
    ego_local = local.offset(-LANE_OFFSET_M)
    (exy,), (eh,), _ = ego_local.pose(np.array([ego_s0]))
    # New start so that the ego lane's pose at ego_s0 is the origin with heading 0.
    w_from_l = geometry.invert_transform(geometry.yaw_pose_to_transform((exy[0], exy[1], 0.0), eh))
    start = geometry.transform_points(w_from_l, np.array([[*local.start_xy, 0.0]]))[0, :2]
    main = Path(start, local.start_heading - eh, local.segments)
    ego_path = main.offset(-LANE_OFFSET_M)
    ego = Trajectory(ego_path, ego_speed, z_m=0.0)

    s_junction = back + lead_in + arc1_len + line_b / 2
    (jxy,), (jh,), _ = main.pose(np.array([s_junction]))
    cross_dir = jh + np.pi / 2
    cross_start = jxy - CROSS_ARM_M * np.array([np.cos(cross_dir), np.sin(cross_dir)])
    cross = Path(cross_start, cross_dir, [Segment(2 * CROSS_ARM_M)])
    roads = {"main": main, "cross": cross}

    builder = _WorldBuilder(rng, roads, jxy, jh, s_junction)
    static_parts = builder.static_scenery()
    agents = builder.agents(ego, duration_s)

    azimuth = rng.uniform(-np.pi, np.pi)
    elevation = np.radians(rng.uniform(25.0, 60.0))
    sun = np.array(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )

    static_agents = [a.mesh.transformed(a.trajectory.world_from_body(0.0)) for a in agents if a.is_static]
    static_mesh = LabelledMesh.concatenate(static_parts + static_agents)
    return World(
        static_mesh=static_mesh,
        agents=agents,
        ego=ego,
        ego_mesh=meshes.ego_body() if ego_body else None,
        sun_direction=sun,
        duration_s=duration_s,
        roads=roads,
    )


def _ego_speed_profile(rng: np.random.Generator, duration_s: float) -> SpeedProfile:
    """Ego speeds between 3 and 13 m/s with holds and smooth speed changes over the scene."""
    v0 = rng.uniform(5.0, 11.0)
    plan: list[tuple[str, float, float]] = []
    t, v = 0.0, v0
    while t < duration_s + 5.0:
        hold = rng.uniform(0.8, 2.5)
        plan.append(("hold", hold, 0.0))
        target = float(np.clip(v + rng.choice([-1, 1]) * rng.uniform(2.0, 5.0), 3.0, 13.0))
        accel = rng.uniform(0.8, 2.0)
        plan.append(("ramp", target, accel))
        t += hold + abs(target - v) / accel
        v = target
    # s0 is the ego's arc length on its lane at t = 0 (set to 120 m: the road behind it).
    return SpeedProfile.build(0.0, 120.0, v0, plan)


def _anchored_profile(
    v0: float, plan: list[tuple[str, float, float]], t_start: float, anchor_t: float, anchor_s: float
) -> SpeedProfile:
    """A profile starting at ``t_start`` whose arc length at ``anchor_t`` is ``anchor_s``."""
    base = SpeedProfile.build(t_start, 0.0, v0, plan)
    shift = anchor_s - float(base.state(anchor_t)[0])
    return SpeedProfile(base.t0, shift, base.v0, base.phases)


class _WorldBuilder:
    def __init__(
        self,
        rng: np.random.Generator,
        roads: dict[str, Path],
        junction_xy: np.ndarray,
        junction_heading: float,
        s_junction: float,
    ):
        self.rng = rng
        self.roads = roads
        self.jxy = junction_xy
        self.jh = junction_heading
        self.s_junction = s_junction
        self.footprints: list[np.ndarray] = []  # (4, 2) rectangles of placed buildings / props

    # ---------------------------------------------------------------- geometry helpers
    def road_distance(self, xy: np.ndarray) -> np.ndarray:
        """Distance from points (N, 2) to the nearest road centreline."""
        return np.min([p.distance_to(xy, spacing_m=1.0) for p in self.roads.values()], axis=0)

    def in_junction(self, xy: np.ndarray, road: str, margin: float) -> np.ndarray:
        """Points (N, 2) of road ``road`` that lie inside the other road's corridor + margin."""
        other = [p for name, p in self.roads.items() if name != road]
        d = np.min([p.distance_to(xy, spacing_m=0.5) for p in other], axis=0)
        return d < ROAD_HALF_WIDTH_M + margin

    # ---------------------------------------------------------------- static scenery
    def static_scenery(self) -> list[LabelledMesh]:
        parts: list[LabelledMesh] = []
        lo = np.min([p.sample(5.0)[1].min(axis=0) for p in self.roads.values()], axis=0) - 110.0
        hi = np.max([p.sample(5.0)[1].max(axis=0) for p in self.roads.values()], axis=0) + 110.0
        ground = np.array(
            [[lo[0], lo[1], -0.02], [hi[0], lo[1], -0.02], [hi[0], hi[1], -0.02], [lo[0], hi[1], -0.02]]
        )
        parts.append(meshes.ribbon(ground[[0, 3]], ground[[1, 2]], "grass", tx.TERRAIN))
        for name, path in self.roads.items():
            parts += self._road_surface(name, path)
            parts += self._sidewalks(name, path)
        parts += self._junction_corners()
        for name, path in self.roads.items():
            parts += self._roadside(name, path)
        return parts

    def _road_surface(self, name: str, path: Path) -> list[LabelledMesh]:
        s, xy, h = path.sample(0.5)
        n = np.stack([-np.sin(h), np.cos(h)], axis=1)
        # The cross road stops at the main road's edge, so the two surfaces do not overlap.
        keep = np.ones(len(s), bool) if name == "main" else ~self.in_junction(xy, name, -0.05)
        parts = []
        for run in _runs(keep):
            left = np.column_stack([xy[run] + ROAD_HALF_WIDTH_M * n[run], np.zeros(len(run))])
            right = np.column_stack([xy[run] - ROAD_HALF_WIDTH_M * n[run], np.zeros(len(run))])
            parts.append(meshes.ribbon(left, right, "asphalt", tx.ROAD))
        # Markings: dashed centre line, solid parking-lane lines, outside the junction.
        clear = ~self.in_junction(xy, name, SIDEWALK_WIDTH_M)
        dash = clear & (np.mod(s, 9.0) < 3.0)
        parts += self._lines(xy, n, dash, 0.0, 0.12)
        parts += self._lines(xy, n, clear, ROAD_HALF_WIDTH_M - 2.5, 0.12)
        parts += self._lines(xy, n, clear, -(ROAD_HALF_WIDTH_M - 2.5), 0.12)
        # Zebra crossings on the cross road's arms next to the junction.
        if name == "cross":
            for sign in (-1.0, 1.0):
                centre = self.jxy + sign * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 2.0) * np.array(
                    [np.cos(self.jh + np.pi / 2), np.sin(self.jh + np.pi / 2)]
                )
                for k in np.arange(-5, 6):
                    c = centre + k * 1.0 * np.array([np.cos(self.jh), np.sin(self.jh)])
                    parts.append(
                        meshes.box((0.5, 3.0, 0.02), (c[0], c[1], 0.0), "lane_paint", tx.ROAD, self.jh)
                    )
        return parts

    @staticmethod
    def _lines(
        xy: np.ndarray, n: np.ndarray, mask: np.ndarray, offset: float, width: float
    ) -> list[LabelledMesh]:
        parts = []
        for run in _runs(mask):
            c = xy[run] + offset * n[run]
            left = np.column_stack([c + width / 2 * n[run], np.full(len(run), 0.01)])
            right = np.column_stack([c - width / 2 * n[run], np.full(len(run), 0.01)])
            parts.append(meshes.ribbon(left, right, "lane_paint", tx.ROAD))
        return parts

    def _sidewalks(self, name: str, path: Path) -> list[LabelledMesh]:
        _, xy, h = path.sample(0.5)
        n = np.stack([-np.sin(h), np.cos(h)], axis=1)
        parts = []
        for side in (-1.0, 1.0):
            inner = xy + side * ROAD_HALF_WIDTH_M * n
            outer = xy + side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M) * n
            keep = ~self.in_junction(inner, name, 0.0) & ~self.in_junction(outer, name, 0.0)
            for run in _runs(keep):
                top = np.full((len(run), 1), SIDEWALK_HEIGHT_M)
                bottom = np.zeros((len(run), 1))
                a_top, a_bottom = np.hstack([inner[run], top]), np.hstack([inner[run], bottom])
                b_top, b_bottom = np.hstack([outer[run], top]), np.hstack([outer[run], bottom])
                parts.append(meshes.ribbon(a_top, b_top, "sidewalk", tx.SIDEWALK))
                parts.append(meshes.ribbon(a_bottom, a_top, "kerb", tx.SIDEWALK))
                parts.append(meshes.ribbon(b_bottom, b_top, "kerb", tx.SIDEWALK))
        return parts

    def _junction_corners(self) -> list[LabelledMesh]:
        """Sidewalk squares at the four corners of the junction, with a traffic light on each."""
        u = np.array([np.cos(self.jh), np.sin(self.jh)])
        v = np.array([-u[1], u[0]])
        d = ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M / 2
        parts = []
        for a in (-1, 1):
            for b in (-1, 1):
                c = self.jxy + a * d * u + b * d * v
                parts.append(
                    meshes.box(
                        (SIDEWALK_WIDTH_M, SIDEWALK_WIDTH_M, SIDEWALK_HEIGHT_M),
                        (c[0], c[1], SIDEWALK_HEIGHT_M / 2),
                        "sidewalk",
                        tx.SIDEWALK,
                        self.jh,
                    )
                )
                p = self.jxy + a * (ROAD_HALF_WIDTH_M + 0.6) * u + b * (ROAD_HALF_WIDTH_M + 0.6) * v
                parts += _traffic_light(p, self.jh + (np.pi if a > 0 else 0.0))
        return parts

    def _roadside(self, name: str, path: Path) -> list[LabelledMesh]:
        """Buildings, walls, lights, signs, trees and bushes along both sides of a road."""
        rng = self.rng
        parts: list[LabelledMesh] = []
        for side in (-1.0, 1.0):
            # Street furniture on the sidewalk's outer half.
            s = 4.0 + rng.uniform(0, 6)
            while s < path.length - 4.0:
                xy, h, _ = path.pose(np.array([s]))
                nrm = np.array([-np.sin(h[0]), np.cos(h[0])])
                spot = xy[0] + side * (ROAD_HALF_WIDTH_M + 0.5) * nrm
                if not self.in_junction(spot[None], name, SIDEWALK_WIDTH_M + 1.0)[0]:
                    r = rng.uniform()
                    if r < 0.35:
                        parts += _street_light(spot, h[0] + (np.pi / 2 if side > 0 else -np.pi / 2))
                    elif r < 0.55:
                        parts += _sign(spot, h[0] + (np.pi if side > 0 else 0.0), rng)
                    elif r < 0.85:
                        tree_spot = xy[0] + side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M - 0.8) * nrm
                        parts += _tree(tree_spot, SIDEWALK_HEIGHT_M, rng)
                s += rng.uniform(9.0, 22.0)
            # Buildings (or a wall, hedge or trees) behind the sidewalk.
            s = rng.uniform(0, 10)
            while s < path.length:
                frontage = rng.uniform(8.0, 26.0)
                depth = rng.uniform(8.0, 20.0)
                setback = rng.uniform(1.0, 7.0)
                s_mid = s + frontage / 2
                xy, h, _ = path.pose(np.array([s_mid]))
                nrm = np.array([-np.sin(h[0]), np.cos(h[0])])
                centre = xy[0] + side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + setback + depth / 2) * nrm
                rect = _rectangle(centre, h[0], frontage, depth)
                s += frontage + rng.uniform(0.0, 6.0)
                if self._blocked(rect, ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 0.8):
                    continue
                self.footprints.append(rect)
                kind = rng.uniform()
                if kind < 0.78:
                    height = rng.uniform(6.0, 28.0)
                    facade = rng.choice(["facade_cream", "facade_brick", "facade_grey", "facade_white"])
                    parts.append(
                        meshes.box(
                            (frontage, depth, height),
                            (centre[0], centre[1], height / 2),
                            facade,
                            tx.BUILDING,
                            h[0],
                        )
                    )
                    parts.append(
                        meshes.box(
                            (frontage - 0.4, depth - 0.4, 0.3),
                            (centre[0], centre[1], height + 0.15),
                            "roof",
                            tx.BUILDING,
                            h[0],
                        )
                    )
                    if setback > 3.0 and rng.uniform() < 0.5:  # a hedge in front
                        hc = xy[0] + side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 1.0) * nrm
                        parts.append(
                            meshes.box(
                                (frontage * 0.8, 0.9, 1.1),
                                (hc[0], hc[1], 0.55),
                                "foliage",
                                tx.VEGETATION,
                                h[0],
                            )
                        )
                elif kind < 0.88:
                    wc = xy[0] + side * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 0.6) * nrm
                    is_wall = rng.uniform() < 0.5
                    material, cls = ("concrete_wall", tx.WALL) if is_wall else ("fence", tx.FENCE)
                    parts.append(
                        meshes.box(
                            (frontage, 0.25, rng.uniform(1.2, 2.2)), (wc[0], wc[1], 0.8), material, cls, h[0]
                        )
                    )
                else:
                    for _ in range(int(rng.integers(2, 5))):
                        tc = centre + rng.uniform(-frontage / 2, frontage / 2) * np.array(
                            [np.cos(h[0]), np.sin(h[0])]
                        )
                        parts += _tree(tc, 0.0, rng)
        return parts

    def _blocked(self, rect: np.ndarray, road_clearance: float) -> bool:
        samples = np.concatenate(
            [rect, rect.mean(axis=0, keepdims=True), (rect + np.roll(rect, 1, axis=0)) / 2]
        )
        if np.any(self.road_distance(samples) < road_clearance):
            return True
        return any(_rectangles_overlap(rect, other, 0.5) for other in self.footprints)

    # ---------------------------------------------------------------- agents
    def agents(self, ego: Trajectory, duration_s: float) -> list[Agent]:
        rng = self.rng
        times = np.arange(-0.5, duration_s + 0.51, 0.1)
        accepted: list[Agent] = []
        # Footprints (centres (T, 2), yaws (T,), length/width) that new agents must not overlap,
        # over the scene's duration; the ego's box centre lies ahead of its rear-axle origin.
        ego_size = np.array([meshes.EGO_BODY_LENGTH_M, 1.95])
        ego_ahead = meshes.EGO_BODY_REAR_M + meshes.EGO_BODY_LENGTH_M / 2
        ego_pos, ego_yaw, _, _ = ego.state(times)
        ego_centre = ego_pos[:, :2] + ego_ahead * np.stack([np.cos(ego_yaw), np.sin(ego_yaw)], axis=1)
        occupied = [(ego_centre, ego_yaw, ego_size)]

        def try_add(kind: AgentKind, class_id: int, size: np.ndarray, traj: Trajectory) -> bool:
            pos, yaw, _, _ = traj.state(times)
            fp = (pos[:, :2], yaw, size[:2])
            for centre, oyaw, osize in occupied:
                if _boxes_collide(fp, (centre, oyaw, osize), COLLISION_MARGIN_M):
                    return False
            inst = len(accepted) + 1
            mesh = (
                meshes.pedestrian(size) if class_id == tx.PERSON else meshes.vehicle(size, class_id, rng)
            ).with_instance(inst)
            accepted.append(Agent(inst, f"agent-{inst:03d}", class_id, kind, size, traj, mesh))
            occupied.append(fp)
            return True

        main, cross = self.roads["main"], self.roads["cross"]
        ego_lane = main.offset(-LANE_OFFSET_M)
        oncoming = main.offset(LANE_OFFSET_M).reversed()
        north_lane = cross.offset(-LANE_OFFSET_M)  # travels along the cross road's direction
        south_lane = cross.offset(LANE_OFFSET_M).reversed()
        ego_s0 = ego.speed.s0
        ego_vmax = float(np.max(ego.speed.state(times)[1]))

        # Lead vehicle, faster than the ego ever drives, so the gap only grows.
        if rng.uniform() < 0.7:
            size = self._vehicle_size(tx.CAR)
            v = ego_vmax + rng.uniform(0.5, 3.0)
            prof = SpeedProfile(0.0, ego_s0 + rng.uniform(14.0, 30.0), v, [])
            try_add("lead", tx.CAR, size, Trajectory(ego_lane, prof, size[2] / 2))
        # Follower: the ego's own speed profile, some metres behind.
        if rng.uniform() < 0.7:
            size = self._vehicle_size(tx.CAR)
            prof = SpeedProfile(
                ego.speed.t0, ego_s0 - rng.uniform(10.0, 18.0), ego.speed.v0, ego.speed.phases
            )
            try_add("follower", tx.CAR, size, Trajectory(ego_lane, prof, size[2] / 2))
        # Oncoming traffic passing the ego during the scene.
        for _ in range(int(rng.integers(2, 5))):
            cls = self._vehicle_class()
            size = self._vehicle_size(cls)
            v = rng.uniform(6.0, 13.0)
            meet_t = rng.uniform(0.0, duration_s)
            meet_s = oncoming.length - (float(ego.speed.state(meet_t)[0]))  # approx. where it passes the ego
            plan = [
                ("hold", rng.uniform(1.0, 4.0), 0.0),
                ("ramp", v + rng.uniform(-2, 2), rng.uniform(0.5, 1.5)),
            ]
            prof = _anchored_profile(v, plan, 0.0, meet_t, meet_s)
            try_add("oncoming", cls, size, Trajectory(oncoming, prof, size[2] / 2))
        # Stop-and-go: stops at the junction's stop line, waits, drives on.
        for lane in (oncoming, north_lane, south_lane):
            if rng.uniform() < 0.6:
                cls = tx.CAR if rng.uniform() < 0.85 else tx.TRUCK
                size = self._vehicle_size(cls)
                s_stop = self._stop_line_s(lane, size[0])
                v = rng.uniform(7.0, 11.0)
                decel = rng.uniform(1.5, 3.0)
                t_stop = rng.uniform(0.15, 0.7) * duration_s
                plan = [
                    ("hold", 30.0, 0.0),
                    ("ramp", 0.0, decel),
                    ("hold", rng.uniform(1.5, 4.0), 0.0),
                    ("ramp", rng.uniform(7.0, 11.0), rng.uniform(1.0, 2.5)),
                ]
                # Cruise for 30 s, then brake so that the car comes to rest at t_stop on the stop line.
                prof = _anchored_profile(v, plan, t_stop - 30.0 - v / decel, t_stop, s_stop)
                try_add("stop_and_go", cls, size, Trajectory(lane, prof, size[2] / 2))
        # Turning vehicles at the junction.
        for _ in range(int(rng.integers(2, 4))):
            turn = self._turn_path(rng)
            cls = tx.CAR if rng.uniform() < 0.85 else tx.BUS
            size = self._vehicle_size(cls)
            path, s_arc = turn
            v = rng.uniform(7.0, 10.0)
            v_turn = rng.uniform(3.0, 5.0)
            t_arc = rng.uniform(0.1, 0.85) * duration_s
            plan = [
                ("hold", 20.0, 0.0),
                ("ramp", v_turn, rng.uniform(1.5, 2.5)),
                ("hold", 6.0, 0.0),
                ("ramp", v, rng.uniform(1.0, 2.0)),
            ]
            decel_t = (v - v_turn) / plan[1][2]
            prof = _anchored_profile(v, plan, t_arc - 20.0 - decel_t, t_arc, s_arc)
            try_add("turning", cls, size, Trajectory(path, prof, size[2] / 2))
        # Parked vehicles on the parking lanes, away from the junction.
        for name, road in self.roads.items():
            for side in (-1.0, 1.0):
                lane = road.offset(side * PARKING_OFFSET_M)
                s = rng.uniform(0.0, 8.0)
                while s < lane.length:
                    s += rng.uniform(5.5, 13.0)
                    xy, _, _ = lane.pose(np.array([s]))
                    if self.in_junction(xy, name, 14.0)[0] or rng.uniform() > 0.4:
                        continue
                    cls = tx.CAR if rng.uniform() < 0.88 else tx.TRUCK
                    size = self._vehicle_size(cls)
                    flip = np.pi if side > 0 else 0.0
                    try_add(
                        "parked",
                        cls,
                        size,
                        Trajectory(lane, SpeedProfile(0.0, s, 0.0, []), size[2] / 2, flip),
                    )
        # Pedestrians: walking along sidewalks, standing, crossing at the zebra.
        for _ in range(int(rng.integers(6, 12))):
            road_name = "main" if rng.uniform() < 0.75 else "cross"
            road = self.roads[road_name]
            side = rng.choice([-1.0, 1.0])
            walkway = road.offset(side * (ROAD_HALF_WIDTH_M + rng.uniform(0.6, 2.4)))
            # Near the ego's route on the main road, near the junction on the cross road.
            if road_name == "main":
                s_near = ego_s0 + rng.uniform(-20.0, 60.0 + 10.0 * duration_s)
            else:
                s_near = rng.uniform(CROSS_ARM_M - 50.0, CROSS_ARM_M + 50.0)
            if rng.uniform() < 0.5:
                walkway = walkway.reversed()
                s_near = walkway.length - s_near
            size = self._person_size()
            standing = rng.uniform() < 0.25
            v = 0.0 if standing else rng.uniform(0.9, 1.6)
            traj = Trajectory(walkway, SpeedProfile(0.0, s_near, v, []), SIDEWALK_HEIGHT_M + size[2] / 2)
            try_add("standing" if standing else "walking", tx.PERSON, size, traj)
        for sign in (-1.0, 1.0):
            if rng.uniform() < 0.7:
                size = self._person_size()
                u = np.array([np.cos(self.jh), np.sin(self.jh)])
                v_dir = np.array([-u[1], u[0]])
                centre = (
                    self.jxy
                    + sign * (ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 2.0) * v_dir
                    + rng.uniform(-1.0, 1.0) * u
                )
                direction = rng.choice([-1.0, 1.0])
                # From the kerb on one side to the kerb on the other, standing on the road surface.
                half = ROAD_HALF_WIDTH_M - 0.45
                start = centre - direction * half * u
                path = Path(start, self.jh + (0.0 if direction > 0 else np.pi), [Segment(2 * half)])
                t_go = rng.uniform(0.0, 0.6) * duration_s
                walk_v, accel = rng.uniform(1.1, 1.6), 2.0
                cruise_s = (path.length - walk_v**2 / accel) / walk_v  # time at walking speed
                plan = [
                    ("hold", 5.0, 0.0),
                    ("ramp", walk_v, accel),
                    ("hold", cruise_s, 0.0),
                    ("ramp", 0.0, accel),
                ]
                prof = _anchored_profile(0.0, plan, t_go - 5.0, t_go, 0.0)
                try_add("crossing", tx.PERSON, size, Trajectory(path, prof, size[2] / 2))
        return accepted

    def _stop_line_s(self, lane: Path, length: float) -> float:
        """Arc length on ``lane`` where a vehicle's centre stops before the junction."""
        s, xy, _ = lane.sample(0.5)
        d = np.linalg.norm(xy - self.jxy, axis=1)
        before = s < s[np.argmin(d)]
        cand = np.flatnonzero(before & (d >= ROAD_HALF_WIDTH_M + SIDEWALK_WIDTH_M + 1.0 + length / 2))
        return float(s[cand[-1]]) if cand.size else float(s[np.argmin(d)] - 15.0)

    def _turn_path(self, rng: np.random.Generator) -> tuple[Path, float]:
        """A path through the junction from one arm to a perpendicular one, and its arc's start s."""
        arm = rng.integers(0, 4)  # approach direction: 0 = along the main road, 1 = cross road, ...
        h_in = self.jh + arm * np.pi / 2
        right = rng.uniform() < 0.6
        h_out = h_in - np.pi / 2 if right else h_in + np.pi / 2
        u_in = np.array([np.cos(h_in), np.sin(h_in)])
        u_out = np.array([np.cos(h_out), np.sin(h_out)])
        # Lane lines: the right-hand lane of each direction, through the junction centre's offset.
        p_in = self.jxy + LANE_OFFSET_M * np.array([u_in[1], -u_in[0]])
        p_out = self.jxy + LANE_OFFSET_M * np.array([u_out[1], -u_out[0]])
        # Intersection X of p_in + a u_in and p_out + b u_out.
        a = np.linalg.solve(np.column_stack([u_in, -u_out]), p_out - p_in)[0]
        x = p_in + a * u_in
        radius = rng.uniform(5.5, 7.5) if right else rng.uniform(8.5, 11.0)
        lead = 90.0
        start = x - (radius + lead) * u_in
        k = (-1.0 if right else 1.0) / radius
        path = Path(start, h_in, [Segment(lead), Segment(radius * np.pi / 2, k), Segment(120.0)])
        return path, lead

    def _vehicle_class(self) -> int:
        r = self.rng.uniform()
        return tx.CAR if r < 0.8 else (tx.TRUCK if r < 0.92 else tx.BUS)

    def _vehicle_size(self, class_id: int) -> np.ndarray:
        (l0, l1), (w0, w1), (h0, h1) = VEHICLE_SIZES[class_id]
        return np.array([self.rng.uniform(l0, l1), self.rng.uniform(w0, w1), self.rng.uniform(h0, h1)])

    def _person_size(self) -> np.ndarray:
        return np.array(
            [self.rng.uniform(0.45, 0.7), self.rng.uniform(0.55, 0.75), self.rng.uniform(1.55, 1.9)]
        )


# --------------------------------------------------------------------------------------------
# Props and 2D helpers


def _street_light(xy: np.ndarray, facing: float) -> list[LabelledMesh]:
    height = 7.0
    arm_dir = np.array([np.cos(facing), np.sin(facing)])
    arm = xy + 0.9 * arm_dir
    lamp = xy + 1.8 * arm_dir
    return [
        meshes.cylinder(0.09, height, (xy[0], xy[1], height / 2), "metal", tx.POLE),
        meshes.box((1.8, 0.08, 0.08), (arm[0], arm[1], height - 0.1), "metal", tx.POLE, facing),
        meshes.box((0.6, 0.25, 0.12), (lamp[0], lamp[1], height - 0.2), "light_housing", tx.POLE, facing),
    ]


def _sign(xy: np.ndarray, facing: float, rng: np.random.Generator) -> list[LabelledMesh]:
    material = rng.choice(["sign_red", "sign_blue", "sign_white"])
    return [
        meshes.cylinder(0.04, 2.6, (xy[0], xy[1], 1.3), "metal", tx.POLE, sections=8),
        meshes.box((0.06, 0.65, 0.65), (xy[0], xy[1], 2.45), material, tx.TRAFFIC_SIGN, facing),
    ]


def _traffic_light(xy: np.ndarray, facing: float) -> list[LabelledMesh]:
    return [
        meshes.cylinder(0.08, 4.2, (xy[0], xy[1], 2.1), "metal", tx.POLE),
        meshes.box((0.35, 0.35, 1.0), (xy[0], xy[1], 3.9), "light_housing", tx.TRAFFIC_LIGHT, facing),
    ]


def _tree(xy: np.ndarray, z0: float, rng: np.random.Generator) -> list[LabelledMesh]:
    trunk_h = rng.uniform(1.8, 3.5)
    crown = rng.uniform(1.4, 3.0)
    return [
        meshes.cylinder(
            rng.uniform(0.12, 0.25),
            trunk_h,
            (xy[0], xy[1], z0 + trunk_h / 2),
            "bark",
            tx.VEGETATION,
            sections=8,
        ),
        meshes.blob(crown, (xy[0], xy[1], z0 + trunk_h + crown * 0.8), "foliage", tx.VEGETATION, rng),
    ]


def _rectangle(centre: np.ndarray, heading: float, length: float, width: float) -> np.ndarray:
    """(4, 2) corners of a rectangle with its length along ``heading``."""
    u = np.array([np.cos(heading), np.sin(heading)])
    v = np.array([-u[1], u[0]])
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    return centre + (signs[:, :1] * length / 2) * u + (signs[:, 1:] * width / 2) * v


def _rectangles_overlap(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    """Separating-axis test of two convex quads (4, 2), grown by ``margin``."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for e in edges:
            axis = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            pa, pb = a @ axis, b @ axis
            if pa.max() + margin < pb.min() or pb.max() + margin < pa.min():
                return False
    return True


def _boxes_collide(
    a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray], margin: float
) -> bool:
    """Whether two moving 2D boxes overlap at any common time sample.

    Each box is (centres (T, 2), yaws (T,), size (2,) length/width); static boxes may give a
    single sample, broadcast over time.
    """
    ca, ya, sa = a
    cb, yb, sb = b
    ca, cb = np.broadcast_arrays(np.atleast_2d(ca), np.atleast_2d(cb))
    ya, yb = np.broadcast_arrays(np.atleast_1d(ya), np.atleast_1d(yb))
    # Quick reject by circumscribed circles.
    reach = 0.5 * (np.hypot(*sa) + np.hypot(*sb)) + margin
    close = np.sum((ca - cb) ** 2, axis=1) <= reach**2
    if not np.any(close):
        return False
    ca, cb, ya, yb = ca[close], cb[close], ya[close], yb[close]

    def corners(c: np.ndarray, y: np.ndarray, s: np.ndarray) -> np.ndarray:
        u = np.stack([np.cos(y), np.sin(y)], axis=1)
        v = np.stack([-u[:, 1], u[:, 0]], axis=1)
        signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
        return (
            c[:, None]
            + signs[None, :, :1] * (s[0] / 2 + margin / 2) * u[:, None]
            + signs[None, :, 1:] * (s[1] / 2 + margin / 2) * v[:, None]
        )

    pa, pb = corners(ca, ya, sa), corners(cb, yb, sb)  # (T, 4, 2)
    separated = np.zeros(len(ca), bool)
    for y in (ya, ya + np.pi / 2, yb, yb + np.pi / 2):
        axis = np.stack([np.cos(y), np.sin(y)], axis=1)[:, None, :]
        qa, qb = np.sum(pa * axis, -1), np.sum(pb * axis, -1)
        separated |= (qa.max(1) < qb.min(1)) | (qb.max(1) < qa.min(1))
    return bool(np.any(~separated))


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index runs (length >= 2) of consecutive True values."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    runs = np.split(idx, breaks + 1)
    return [r for r in runs if len(r) >= 2]
