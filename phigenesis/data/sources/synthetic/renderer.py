"""Ray-cast rendering of a synthetic world with Open3D: camera images with exact truth, and LiDAR.

The static world is one Open3D ``RaycastingScene`` built once; moving agents and the ego body go
into a small scene rebuilt for each capture time, and each ray keeps the nearer of the two hits.
Camera rays are cast with a direction whose camera-z component is 1, so the hit distance is the
z-depth itself. A spinning LiDAR is cast in time slices (sectors), each with its own ego pose and
agent positions; a point's time is its sector's time. Several LiDARs of one revolution share the
moving bodies of each capture time. A second return is the next surface behind foliage: the ray
is cast again from a little behind its first hit (see :meth:`Renderer._second_returns`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis._open3d import open3d
from phigenesis.data.records import CameraCalibration, CameraTruth
from phigenesis.data.sources.synthetic import materials as mt
from phigenesis.data.sources.synthetic.meshes import LabelledMesh
from phigenesis.data.sources.synthetic.rigs import LidarSpec
from phigenesis.data.sources.synthetic.world import World

_INVALID = np.uint32(0xFFFFFFFF)
SKY_ZENITH = np.array([0.10, 0.22, 0.55], np.float32)
SKY_HORIZON = np.array([0.55, 0.62, 0.72], np.float32)
HAZE_DISTANCE_M = 900.0


@dataclass
class Bodies:
    """Moving bodies (agents and the ego) at one time, in one ray-casting scene."""

    scene: object  # open3d.t.geometry.RaycastingScene
    meshes: list[LabelledMesh]
    world_from_body: NDArray[np.float64]  # (K, 4, 4)
    velocity: NDArray[np.float64]  # (K, 3) m/s of the body origin
    yaw_rate: NDArray[np.float64]  # (K,) rad/s


@dataclass
class Hits:
    """Nearest surface along each of N rays."""

    t: NDArray[np.float64]  # (N,) hit parameter in units of the ray direction's length; inf = miss
    normal: NDArray[np.float32]  # (N, 3) world-frame normal facing the ray origin
    material: NDArray[np.int32]  # (N,)
    semantic: NDArray[np.uint8]  # (N,), SKY where missed
    instance: NDArray[np.uint16]  # (N,)
    body: NDArray[np.int32]  # (N,) index into Bodies, -1 for static surfaces and misses

    @property
    def hit(self) -> NDArray[np.bool_]:
        return np.isfinite(self.t)


class Renderer:
    """Renders cameras and the LiDAR of one world at any time ``t_s`` (seconds from the first frame)."""

    def __init__(self, world: World, shadows: bool = True):
        o3d = open3d()
        self._o3d = o3d
        self.world = world
        self.shadows = shadows
        self.static_scene = self._scene([world.static_mesh])
        self.moving = [a for a in world.agents if not a.is_static]
        self._rays: dict[tuple, NDArray[np.float64]] = {}

    # ------------------------------------------------------------------ scenes and casting
    def _scene(
        self, parts: list[LabelledMesh], transforms: list[NDArray[np.float64]] | None = None
    ) -> object:
        o3d = self._o3d
        scene = o3d.t.geometry.RaycastingScene()
        for i, mesh in enumerate(parts):
            v = (
                mesh.vertices
                if transforms is None
                else geometry.transform_points(transforms[i], mesh.vertices)
            )
            scene.add_triangles(
                o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
            )
        return scene

    def bodies_at(self, t_s: float, near_xy: NDArray | None = None, radius_m: float = np.inf) -> Bodies:
        """The ray-casting scene of the moving bodies at ``t_s`` (those whose centre is within
        ``radius_m`` of ``near_xy``, if given; the ego body always)."""
        meshes, poses, vels, rates = [], [], [], []
        for agent in self.moving:
            pos, yaw, vel, rate = agent.trajectory.state(t_s)
            if near_xy is not None and np.hypot(*(pos[:2] - near_xy)) > radius_m:
                continue
            meshes.append(agent.mesh)
            poses.append(geometry.yaw_pose_to_transform(pos, yaw))
            vels.append(vel)
            rates.append(float(rate))
        if self.world.ego_mesh is not None:
            pos, yaw, vel, rate = self.world.ego.state(t_s)
            meshes.append(self.world.ego_mesh)
            poses.append(geometry.yaw_pose_to_transform(pos, yaw))
            vels.append(vel)
            rates.append(float(rate))
        k = len(meshes)
        return Bodies(
            scene=self._scene(meshes, poses),
            meshes=meshes,
            world_from_body=np.array(poses).reshape(k, 4, 4),
            velocity=np.array(vels).reshape(k, 3),
            yaw_rate=np.array(rates),
        )

    def _cast_one(self, scene: object, origins: NDArray, dirs: NDArray) -> dict[str, NDArray]:
        rays = self._o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))
        ans = scene.cast_rays(rays)
        return {k: ans[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_ids", "primitive_normals")}

    def cast(self, origins: NDArray, dirs: NDArray, bodies: Bodies) -> Hits:
        """Nearest hits of rays ``(N, 3)`` against the static world and the moving ``bodies``."""
        hits = self.cast_static(origins, dirs)
        self.merge_bodies(hits, origins, dirs, bodies)
        return finish_hits(hits, dirs)

    def cast_static(self, origins: NDArray, dirs: NDArray) -> Hits:
        """Hits against the static world only (normals not yet oriented; see :func:`finish_hits`)."""
        static = self._cast_one(self.static_scene, origins, dirs)
        ok = static["geometry_ids"] != _INVALID
        prim = np.where(ok, static["primitive_ids"], 0).astype(np.int64)
        sm = self.world.static_mesh
        return Hits(
            t=np.where(ok, static["t_hit"].astype(np.float64), np.inf),
            normal=static["primitive_normals"],
            material=np.where(ok, sm.material[prim], 0).astype(np.int32),
            semantic=np.where(ok, sm.semantic[prim], tx.SKY).astype(np.uint8),
            instance=np.where(ok, sm.instance[prim], 0).astype(np.uint16),
            body=np.full(len(origins), -1, np.int32),
        )

    def merge_bodies(
        self, hits: Hits, origins: NDArray, dirs: NDArray, bodies: Bodies, ray_index: NDArray | None = None
    ) -> None:
        """Replaces, in place, the hits of rays ``ray_index`` (default all) that a body occludes."""
        if not bodies.meshes:
            return
        idx = np.arange(len(origins)) if ray_index is None else ray_index
        dyn = self._cast_one(bodies.scene, origins[idx], dirs[idx])
        gid = dyn["geometry_ids"]
        closer = (gid != _INVALID) & (dyn["t_hit"] < hits.t[idx])
        sel = idx[closer]
        g = gid[closer].astype(np.int64)
        p = dyn["primitive_ids"][closer].astype(np.int64)
        hits.t[sel] = dyn["t_hit"][closer]
        hits.normal[sel] = dyn["primitive_normals"][closer]
        hits.body[sel] = g
        for k in np.unique(g):
            m = bodies.meshes[k]
            mask = g == k
            hits.material[sel[mask]] = m.material[p[mask]]
            hits.semantic[sel[mask]] = m.semantic[p[mask]]
            hits.instance[sel[mask]] = m.instance[p[mask]]

    # ------------------------------------------------------------------ cameras
    def render_camera(
        self,
        calibration: CameraCalibration,
        world_from_ego: NDArray[np.float64],
        t_s: float,
        bodies: Bodies | None = None,
        render_scale: int = 1,
    ) -> tuple[NDArray[np.uint8], CameraTruth]:
        """RGB image (H, W, 3) uint8 and exact truth of one camera at time ``t_s``.

        ``render_scale`` > 1: cast at 1/render_scale of the size in each axis (rounded up) and
        resized to (H, W): the image bilinearly, depth, labels and flow by nearest neighbour (so
        truth is the nearest coarse pixel's; inexact at edges). For cost benchmarks.
        """
        if render_scale > 1:
            coarse = scaled_calibration(calibration, render_scale)
            rgb, truth = self.render_camera(coarse, world_from_ego, t_s, bodies)
            return upsample(rgb, truth, calibration.width, calibration.height)
        h, w = calibration.height, calibration.width
        rays_cam = self.camera_rays(calibration)  # (H*W, 3), z = 1
        world_from_camera = world_from_ego @ calibration.ego_from_camera
        dirs = geometry.transform_directions(world_from_camera, rays_cam)
        origins = np.broadcast_to(world_from_camera[:3, 3], dirs.shape)
        bodies = self.bodies_at(t_s) if bodies is None else bodies
        hits = self.cast(origins, dirs, bodies)
        points = origins + dirs * np.where(hits.hit, hits.t, 0.0)[:, None]
        rgb = self._shade(hits, origins, dirs, points, bodies)
        depth = np.where(hits.hit, hits.t, 0.0).astype(np.float32)
        flow = surface_velocity(hits, points, bodies).astype(np.float32)
        truth = CameraTruth(
            depth_m=depth.reshape(h, w),
            semantic=hits.semantic.reshape(h, w),
            instance=hits.instance.reshape(h, w),
            flow_world_mps=flow.reshape(h, w, 3),
        )
        return to_srgb8(rgb).reshape(h, w, 3), truth

    def camera_rays(self, calibration: CameraCalibration) -> NDArray[np.float64]:
        """:func:`camera_rays`, computed once per calibration (undistortion is iterative)."""
        key = (
            calibration.width,
            calibration.height,
            calibration.intrinsics.tobytes(),
            calibration.distortion.tobytes(),
        )
        if key not in self._rays:
            self._rays[key] = camera_rays(calibration)
        return self._rays[key]

    def _shade(
        self, hits: Hits, origins: NDArray, dirs: NDArray, points: NDArray, bodies: Bodies
    ) -> NDArray[np.float32]:
        """Linear RGB (N, 3): textured albedo, sun + sky light with cast shadows, haze, sky."""
        n = len(dirs)
        rgb = np.empty((n, 3), np.float32)
        hit = hits.hit
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        # Sky: a gradient with elevation plus a glow around the sun.
        elev = np.clip(unit[:, 2], 0.0, 1.0)[:, None]
        sky = SKY_HORIZON + (SKY_ZENITH - SKY_HORIZON) * np.sqrt(elev)
        sun = self.world.sun_direction.astype(np.float32)
        glow = np.clip(unit @ sun, 0.0, 1.0) ** 64
        rgb[:] = sky + 0.6 * glow[:, None]
        if not np.any(hit):
            return rgb
        idx = np.flatnonzero(hit)
        p = points[idx]
        nrm = hits.normal[idx]
        mat = hits.material[idx]
        # Textures live in the body frame of moving objects so they move with them.
        local = p.copy()
        for k in np.unique(hits.body[idx]):
            if k < 0:
                continue
            m = hits.body[idx] == k
            local[m] = geometry.transform_points(geometry.invert_transform(bodies.world_from_body[k]), p[m])
        albedo = albedo_at(local, nrm, mat, hits.instance[idx])
        lit = np.clip(nrm @ sun, 0.0, None)
        if self.shadows and np.any(lit > 0):
            sunny = np.flatnonzero(lit > 0)
            o = p[sunny] + 0.03 * nrm[sunny]
            d = np.broadcast_to(sun, o.shape)
            blocked = self._occluded(self.static_scene, o, d) | (
                self._occluded(bodies.scene, o, d) if len(bodies.meshes) else False
            )
            lit[sunny[blocked]] = 0.0
        ambient = 0.28 + 0.12 * nrm[:, 2]
        color = albedo * (ambient + 1.25 * lit)[:, None]
        dist = np.linalg.norm(p - origins[idx], axis=1)
        haze = (1.0 - np.exp(-dist / HAZE_DISTANCE_M))[:, None].astype(np.float32)
        rgb[idx] = color * (1 - haze) + SKY_HORIZON * haze
        return rgb

    def _occluded(self, scene: object, origins: NDArray, dirs: NDArray) -> NDArray[np.bool_]:
        rays = self._o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))
        return scene.test_occlusions(rays).numpy().astype(bool)

    # ------------------------------------------------------------------ LiDAR
    def render_lidar(
        self,
        spec: LidarSpec,
        frame_time_micros: int,
        start_micros: int,
        spin_period_s: float,
        rng: np.random.Generator,
    ) -> dict[str, NDArray]:
        """One LiDAR revolution centred on the frame time, as arrays of the returned points.

        Returns a dict with ``points_world`` (N, 3) float64, ``origins_world`` (N, 3),
        ``time_micros`` (N,) int64, ``beam`` (N,) uint16, ``column`` (N,) uint16 (azimuth step),
        ``range_m`` (N,) float64 measured range, ``intensity`` (N,) float32, ``semantic`` (N,)
        uint8, ``instance`` (N,) uint16, ``return_index`` (N,) uint8 (0 first, 1 second return;
        the first returns in row-major cell order, then the second returns); and
        ``sector_micros`` (sectors,) int64 with ``sector_of_column`` (columns,) int64 (when each
        column was measured).
        """
        return self.render_lidars([spec], frame_time_micros, start_micros, spin_period_s, rng)[0]

    def render_lidars(
        self,
        specs: list[LidarSpec] | tuple[LidarSpec, ...],
        frame_time_micros: int,
        start_micros: int,
        spin_period_s: float,
        rng: np.random.Generator,
    ) -> list[dict[str, NDArray]]:
        """:meth:`render_lidar` of each of ``specs`` in one revolution (the moving bodies of each
        capture time built once for all of them); the random draws are made LiDAR by LiDAR."""
        reach = max(s.max_range_m for s in specs) + 8.0  # bodies whose centre can be in range
        cache: dict[int, Bodies] = {}  # capture time -> bodies
        return [
            self._render_one_lidar(spec, frame_time_micros, start_micros, spin_period_s, rng, cache, reach)
            for spec in specs
        ]

    def _render_one_lidar(
        self,
        spec: LidarSpec,
        frame_time_micros: int,
        start_micros: int,
        spin_period_s: float,
        rng: np.random.Generator,
        bodies_cache: dict[int, Bodies],
        reach: float,
    ) -> dict[str, NDArray]:
        incl = spec.inclinations_rad()
        az = spec.column_azimuths_rad()
        beams, cols = len(incl), len(az)
        # Directions in the ego axes (a mounting yaw changes no ray: columns are fixed in the ego
        # frame), rows = beams, columns = azimuth order.
        ci, si = np.cos(incl)[:, None], np.sin(incl)[:, None]
        d_sensor = np.stack(
            [ci * np.cos(az)[None], ci * np.sin(az)[None], np.broadcast_to(si, (beams, cols))], axis=-1
        )
        sector_of_col = (np.arange(cols) * spec.sectors) // cols
        offsets = np.round(
            ((np.arange(spec.sectors) + 0.5) / spec.sectors - 0.5) * spin_period_s * 1e6
        ).astype(np.int64)
        sector_micros = frame_time_micros + offsets
        sector_s = (sector_micros - start_micros) * 1e-6
        sector_poses = self.world.world_from_ego(sector_s)  # (sectors, 4, 4)
        mount = np.asarray(spec.position_m, dtype=np.float64)
        origins = np.empty((beams, cols, 3))
        dirs = np.empty((beams, cols, 3))
        for k in range(spec.sectors):
            cols_k = sector_of_col == k
            pose = sector_poses[k]
            origins[:, cols_k] = geometry.transform_points(pose, mount[None])[0]
            dirs[:, cols_k] = geometry.transform_directions(pose, d_sensor[:, cols_k].reshape(-1, 3)).reshape(
                beams, -1, 3
            )
        origins = origins.reshape(-1, 3)
        dirs = dirs.reshape(-1, 3)
        ray_sector = np.broadcast_to(sector_of_col[None], (beams, cols)).reshape(-1)
        # Static world for all rays at once, then each sector's moving bodies at its own time.
        hits = self.cast_static(origins, dirs)
        sector_bodies = []
        ego_hit = np.zeros(len(dirs), bool)
        for k in range(spec.sectors):
            key = int(sector_micros[k])
            if key not in bodies_cache:
                bodies_cache[key] = self.bodies_at(sector_s[k], sector_poses[k, :2, 3], reach)
            bodies = bodies_cache[key]
            sector_bodies.append(bodies)
            rays_k = np.flatnonzero(ray_sector == k)
            self.merge_bodies(hits, origins, dirs, bodies, rays_k)
            if not spec.ego_returns and self.world.ego_mesh is not None:
                ego_hit[rays_k] = hits.body[rays_k] == len(bodies.meshes) - 1
        hits = finish_hits(hits, dirs)
        first = self._returns(spec, hits, dirs, ~ego_hit, rng)
        beam = np.repeat(np.arange(beams, dtype=np.uint16), cols)
        column = np.tile(np.arange(cols, dtype=np.uint16), beams)
        keep, rng_range, intensity = first
        sel = np.flatnonzero(keep)
        parts = [(sel, rng_range[sel], intensity[sel], hits.semantic[sel], hits.instance[sel])]
        if spec.returns == 2:
            parts.append(
                self._second_returns(
                    spec, hits, keep, rng_range, origins, dirs, ray_sector, sector_bodies, rng
                )
            )
        idx = np.concatenate([p[0] for p in parts])
        ranges = np.concatenate([p[1] for p in parts])
        return {
            "column": column[idx],
            "range_m": ranges,
            "sector_micros": sector_micros,
            "sector_of_column": sector_of_col,
            "points_world": origins[idx] + dirs[idx] * ranges[:, None],
            "origins_world": origins[idx],
            "time_micros": sector_micros[ray_sector[idx]],
            "beam": beam[idx],
            "intensity": np.concatenate([p[2] for p in parts]),
            "semantic": np.concatenate([p[3] for p in parts]),
            "instance": np.concatenate([p[4] for p in parts]),
            "return_index": np.concatenate([np.full(len(p[0]), i, np.uint8) for i, p in enumerate(parts)]),
        }

    def _returns(
        self, spec: LidarSpec, hits: Hits, dirs: NDArray, allowed: NDArray[np.bool_], rng: np.random.Generator
    ) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float32]]:
        """(kept, measured range, intensity) of every ray's hit: the noise, range gate and losses
        of ``spec`` applied (rays not ``allowed`` are never kept)."""
        cos_inc = np.abs(np.sum(hits.normal * dirs, axis=1))
        intensity = (mt.REFLECTIVITY[hits.material] * cos_inc).astype(np.float32)
        rng_range = hits.t + rng.normal(0.0, spec.range_noise_m, size=len(dirs))
        # Gate on the measured (noisy) range, as the returned points are at that range.
        keep = hits.hit & (rng_range >= spec.min_range_m) & (rng_range <= spec.max_range_m) & allowed
        keep &= rng.uniform(size=len(dirs)) >= spec.dropout
        # Weak returns (dark or grazing surfaces, far away) are lost more often.
        p_loss = 0.5 * np.exp(-25.0 * intensity / (1.0 + (np.where(keep, hits.t, 0.0) / 40.0) ** 2))
        keep &= rng.uniform(size=len(dirs)) >= p_loss
        return keep, rng_range, intensity

    def _second_returns(
        self,
        spec: LidarSpec,
        hits: Hits,
        keep: NDArray[np.bool_],
        rng_range: NDArray[np.float64],
        origins: NDArray,
        dirs: NDArray,
        ray_sector: NDArray,
        sector_bodies: list[Bodies],
        rng: np.random.Generator,
    ) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        """Second returns: a ``second_return_fraction`` of the kept returns on vegetation pass
        through the foliage and return from the next surface at least ``second_return_gap_m``
        behind the first hit (cast again from there, against the same sector's bodies). Returns
        (ray index, measured range, intensity, semantic, instance) of the second returns."""
        through = keep & (hits.semantic == tx.VEGETATION)
        through &= rng.uniform(size=len(dirs)) < spec.second_return_fraction
        rays = np.flatnonzero(through)
        start = hits.t[rays] + spec.second_return_gap_m
        o2 = origins[rays] + dirs[rays] * start[:, None]
        d2 = dirs[rays]
        behind = self.cast_static(o2, d2)
        sector = ray_sector[rays]
        for k in np.unique(sector):
            self.merge_bodies(behind, o2, d2, sector_bodies[k], np.flatnonzero(sector == k))
        behind = finish_hits(behind, d2)
        behind.t = behind.t + start  # range from the sensor
        allowed = np.ones(len(rays), bool)
        if not spec.ego_returns and self.world.ego_mesh is not None:
            for k in np.unique(sector):
                m = sector == k
                allowed[m] = behind.body[m] != len(sector_bodies[k].meshes) - 1
        kept2, range2, intensity2 = self._returns(spec, behind, d2, allowed, rng)
        kept2 &= range2 > rng_range[rays]  # the noise never puts the second return first
        sel = np.flatnonzero(kept2)
        # The pulse lost part of its energy in the foliage.
        intensity2 = (0.5 * intensity2[sel]).astype(np.float32)
        return rays[sel], range2[sel], intensity2, behind.semantic[sel], behind.instance[sel]


# --------------------------------------------------------------------------------------------
# Shading helpers


def finish_hits(hits: Hits, dirs: NDArray) -> Hits:
    """Orients the hits' normals towards the ray origins (meshes have arbitrary winding)."""
    flip = np.sum(hits.normal * dirs, axis=1) > 0
    hits.normal = np.where(flip[:, None], -hits.normal, hits.normal).astype(np.float32)
    return hits


def scaled_calibration(calibration: CameraCalibration, scale: int) -> CameraCalibration:
    """``calibration`` at 1/scale of its size in each axis (rounded up), seeing the same field of
    view: focal lengths and principal point scaled by the size ratio of each axis (pixel centres
    at integer coordinates, so the image edges stay where they were)."""
    w = -(-calibration.width // scale)
    h = -(-calibration.height // scale)
    sx, sy = w / calibration.width, h / calibration.height
    k = calibration.intrinsics.copy()
    k[0, 0] *= sx
    k[0, 1] *= sx
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 1] *= sy
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return replace(calibration, width=w, height=h, intrinsics=k)


def upsample(
    rgb: NDArray[np.uint8], truth: CameraTruth, width: int, height: int
) -> tuple[NDArray[np.uint8], CameraTruth]:
    """A coarse render resized to (height, width): the image bilinearly (area-weighted where it
    shrinks), depth, labels and flow by nearest neighbour (no blended classes or depths)."""
    size = (width, height)
    nearest = cv2.INTER_NEAREST
    big = CameraTruth(
        depth_m=cv2.resize(truth.depth_m, size, interpolation=nearest),
        semantic=cv2.resize(truth.semantic, size, interpolation=nearest),
        instance=cv2.resize(truth.instance, size, interpolation=nearest),
        flow_world_mps=cv2.resize(truth.flow_world_mps, size, interpolation=nearest),
    )
    return cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR), big


def camera_rays(calibration: CameraCalibration) -> NDArray[np.float64]:
    """Camera-frame rays ``(H * W, 3)`` through every pixel centre, row-major, with z = 1."""
    uv = geometry.pixel_grid(calibration.width, calibration.height)
    return geometry.unproject_pixels(uv, calibration.intrinsics, calibration.distortion)


def surface_velocity(hits: Hits, points: NDArray[np.float64], bodies: Bodies) -> NDArray[np.float64]:
    """World-frame velocity (N, 3) of the hit surface points: v + omega x r for moving bodies."""
    flow = np.zeros((len(points), 3))
    moving = hits.body >= 0
    if np.any(moving):
        k = hits.body[moving]
        r = points[moving] - bodies.world_from_body[k, :3, 3]
        w = bodies.yaw_rate[k]
        flow[moving] = bodies.velocity[k] + np.stack([-w * r[:, 1], w * r[:, 0], np.zeros_like(w)], axis=1)
    return flow


def value_noise(p: NDArray[np.float64]) -> NDArray[np.float32]:
    """Smooth 3D value noise in [0, 1] at points (N, 3) (one octave, lattice spacing 1)."""
    base = np.floor(p)
    f = (p - base).astype(np.float32)
    i = base.astype(np.int64)
    u = f * f * (3 - 2 * f)
    out = np.zeros(len(p), np.float32)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                h = _hash3(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
                wx = u[:, 0] if dx else 1 - u[:, 0]
                wy = u[:, 1] if dy else 1 - u[:, 1]
                wz = u[:, 2] if dz else 1 - u[:, 2]
                out += h * wx * wy * wz
    return out


def _hash3(x: NDArray[np.int64], y: NDArray[np.int64], z: NDArray[np.int64]) -> NDArray[np.float32]:
    h = (x * 73856093) ^ (y * 19349663) ^ (z * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return ((h & 0xFFFFFF).astype(np.float32)) / np.float32(0xFFFFFF)


def fbm(p: NDArray[np.float64], octaves: int = 3) -> NDArray[np.float32]:
    """Fractal sum of value noise in [0, 1]."""
    total = np.zeros(len(p), np.float32)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(p * (2.0**o) + 17.0 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def albedo_at(
    local: NDArray[np.float64],
    normal: NDArray[np.float32],
    material: NDArray[np.int32],
    instance: NDArray[np.uint16],
) -> NDArray[np.float32]:
    """Textured base colour (N, 3) at texture-space points (world or body frame)."""
    color = mt.COLOR[material].copy()
    tinted = mt.TINT_BY_INSTANCE[material]
    if np.any(tinted):
        color[tinted] = mt.instance_tint(instance[tinted], material[tinted])
    freq = mt.TEXTURE_FREQ[material][:, None]
    amp = mt.TEXTURE_AMPLITUDE[material]
    tex = mt.TEXTURE[material]
    noise = fbm(local * freq)
    color *= (1.0 + amp * 2.0 * (noise - 0.5))[:, None]
    tiles = tex == mt.Texture.TILES
    if np.any(tiles):
        g = np.abs(local[tiles, :2] - np.round(local[tiles, :2]))
        joint = (g.min(axis=1) < 0.025) & (normal[tiles, 2] > 0.5)
        color[np.flatnonzero(tiles)[joint]] *= 0.55
    facade = tex == mt.Texture.FACADE
    if np.any(facade):
        nrm = normal[facade]
        vertical = np.abs(nrm[:, 2]) < 0.5
        tangent = np.stack([-nrm[:, 1], nrm[:, 0]], axis=1)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-6)
        u = np.sum(local[facade, :2] * tangent, axis=1)
        z = local[facade, 2]
        fu = np.mod(u / 3.0, 1.0)
        fz = np.mod((z - 0.6) / 3.2, 1.0)
        window = vertical & (z > 1.2) & (fu > 0.22) & (fu < 0.78) & (fz > 0.3) & (fz < 0.8)
        sel = np.flatnonzero(facade)[window]
        color[sel] = np.array([0.03, 0.045, 0.06], np.float32) * (0.8 + 0.4 * noise[sel, None])
        frame = vertical & (z > 1.2) & ~window & (fu > 0.18) & (fu < 0.82) & (fz > 0.26) & (fz < 0.84)
        color[np.flatnonzero(facade)[frame]] *= 0.6
    brick = tex == mt.Texture.BRICK
    if np.any(brick):
        z = local[brick, 2]
        color[np.flatnonzero(brick)[np.mod(z, 0.3) < 0.03]] *= 0.6
    return np.clip(color, 0.0, 1.0)


def to_srgb8(linear: NDArray[np.float32], exposure: float = 1.6) -> NDArray[np.uint8]:
    """Linear RGB to 8-bit sRGB with a soft shoulder so highlights do not clip harshly."""
    x = np.asarray(linear, np.float32) * exposure
    x = x / (1.0 + 0.15 * x)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.clip(x, 0.0031308, None), 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)
