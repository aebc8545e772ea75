"""Continuous-time motion on the ground plane: paths of lines and arcs, speed profiles, trajectories.

Everything is analytic, so positions, headings and velocities exist at any time (any sensor rate)
and are exact: the synthetic truth the rest of the toolkit is measured against.
Units: metres, seconds, radians; positions in the world frame (z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from phigenesis import geometry

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Segment:
    """A line (curvature 0) or a circular arc of signed curvature (1/m, positive turns left)."""

    length_m: float
    curvature_per_m: float = 0.0


class Path:
    """A tangent-continuous planar curve made of lines and arcs, parameterised by arc length s.

    Beyond its ends the path continues as straight lines along the end tangents, so ``pose(s)``
    is defined for every s (objects can start before and finish after the modelled part).
    """

    def __init__(self, start_xy: ArrayLike, start_heading_rad: float, segments: list[Segment]):
        if not segments:
            raise ValueError("a path needs at least one segment")
        self.start_xy = np.asarray(start_xy, dtype=np.float64).reshape(2)
        self.start_heading = float(start_heading_rad)
        self.segments = list(segments)
        lengths = np.array([s.length_m for s in self.segments])
        if np.any(lengths <= 0):
            raise ValueError(f"segment lengths must be positive, got {lengths}")
        self.curvatures = np.array([s.curvature_per_m for s in self.segments])
        self.s_start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(lengths.sum())
        # Start state (x, y, heading) of every segment.
        xs, hs = [self.start_xy], [self.start_heading]
        for seg in self.segments:
            xy, h = _advance(xs[-1], hs[-1], seg.curvature_per_m, seg.length_m)
            xs.append(xy)
            hs.append(h)
        self._seg_xy = np.array(xs)
        self._seg_heading = np.array(hs)

    @property
    def end_xy(self) -> F64:
        return self._seg_xy[-1]

    @property
    def end_heading(self) -> float:
        return float(self._seg_heading[-1])

    def pose(self, s: ArrayLike) -> tuple[F64, F64, F64]:
        """Position ``(..., 2)``, heading ``(...)`` and curvature ``(...)`` at arc lengths ``s``."""
        s = np.asarray(s, dtype=np.float64)
        flat = s.reshape(-1)
        idx = np.clip(np.searchsorted(self.s_start, flat, side="right") - 1, 0, len(self.segments) - 1)
        local = flat - self.s_start[idx]
        kappa = self.curvatures[idx].copy()
        # Before the start / after the end: straight extensions.
        before = flat < 0.0
        after = flat > self.length
        kappa[before | after] = 0.0
        origin = self._seg_xy[idx].copy()
        heading0 = self._seg_heading[idx].copy()
        origin[after] = self._seg_xy[-1]
        heading0[after] = self._seg_heading[-1]
        local[after] = flat[after] - self.length
        xy, heading = _advance(origin, heading0, kappa, local)
        return xy.reshape(*s.shape, 2), heading.reshape(s.shape), kappa.reshape(s.shape)

    def offset(self, left_m: float) -> Path:
        """The parallel path ``left_m`` metres to the left (negative: right), same direction."""
        segs = []
        for seg in self.segments:
            scale = 1.0 - seg.curvature_per_m * left_m
            if scale <= 0:
                raise ValueError(
                    f"offset {left_m} m is beyond the centre of an arc of radius {1 / seg.curvature_per_m}"
                )
            segs.append(Segment(seg.length_m * scale, seg.curvature_per_m / scale))
        normal = np.array([-np.sin(self.start_heading), np.cos(self.start_heading)])
        return Path(self.start_xy + left_m * normal, self.start_heading, segs)

    def reversed(self) -> Path:
        """The same curve travelled from its end to its start."""
        segs = [Segment(s.length_m, -s.curvature_per_m) for s in reversed(self.segments)]
        return Path(self.end_xy, self.end_heading + np.pi, segs)

    def extended(self, before_m: float = 0.0, after_m: float = 0.0) -> Path:
        """The path with straight pieces added before its start and after its end."""
        segs = list(self.segments)
        start_xy = self.start_xy
        if before_m > 0:
            start_xy = self.start_xy - before_m * np.array(
                [np.cos(self.start_heading), np.sin(self.start_heading)]
            )
            segs.insert(0, Segment(before_m))
        if after_m > 0:
            segs.append(Segment(after_m))
        return Path(start_xy, self.start_heading, segs)

    def sample(self, spacing_m: float) -> tuple[F64, F64, F64]:
        """Arc lengths, positions and headings every ``spacing_m`` metres (ends included)."""
        n = max(2, int(np.ceil(self.length / spacing_m)) + 1)
        s = np.linspace(0.0, self.length, n)
        xy, heading, _ = self.pose(s)
        return s, xy, heading

    def distance_to(self, points_xy: ArrayLike, spacing_m: float = 0.5) -> F64:
        """Approximate distance (within ``spacing_m / 2``) from points ``(N, 2)`` to the path."""
        _, xy, _ = self.sample(spacing_m)
        p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        d2 = np.sum((p[:, None, :] - xy[None, :, :]) ** 2, axis=-1)
        return np.sqrt(d2.min(axis=1))


def _advance(xy0: ArrayLike, heading0: ArrayLike, kappa: ArrayLike, ds: ArrayLike) -> tuple[F64, F64]:
    """Moves along a line/arc of curvature ``kappa`` by ``ds`` from ``(xy0, heading0)``."""
    xy0 = np.asarray(xy0, dtype=np.float64)
    h0 = np.asarray(heading0, dtype=np.float64)
    k = np.asarray(kappa, dtype=np.float64)
    ds = np.asarray(ds, dtype=np.float64)
    h1 = h0 + k * ds
    # Chord of length ds * sinc(k ds / 2) along the mean heading: exact for arcs and lines, and
    # without the cancellation of (sin(h1) - sin(h0)) / k for nearly straight arcs.
    half = 0.5 * k * ds
    chord = ds * np.sinc(half / np.pi)
    dx = chord * np.cos(h0 + half)
    dy = chord * np.sin(h0 + half)
    return xy0 + np.stack([dx, dy], axis=-1), h1


@dataclass(frozen=True)
class SpeedPhase:
    """Constant acceleration (m/s^2) for a duration (s)."""

    duration_s: float
    accel_mps2: float


class SpeedProfile:
    """Arc length s(t) from piecewise-constant acceleration, starting at ``s0``, ``v0`` at ``t0``.

    Before ``t0`` the object moves at ``v0``; after the last phase it keeps its final speed.
    Phases are built so the speed never goes negative (use :meth:`build`).
    """

    def __init__(self, t0_s: float, s0_m: float, v0_mps: float, phases: list[SpeedPhase]):
        self.t0 = float(t0_s)
        self.s0 = float(s0_m)
        self.v0 = float(v0_mps)
        self.phases = list(phases)
        ts, ss, vs = [self.t0], [self.s0], [self.v0]
        for ph in self.phases:
            ss.append(ss[-1] + vs[-1] * ph.duration_s + 0.5 * ph.accel_mps2 * ph.duration_s**2)
            vs.append(vs[-1] + ph.accel_mps2 * ph.duration_s)
            ts.append(ts[-1] + ph.duration_s)
        if min(vs) < -1e-9:
            raise ValueError(f"speed profile goes negative: knot speeds {vs}")
        self._t = np.array(ts)
        self._s = np.array(ss)
        self._v = np.maximum(np.array(vs), 0.0)
        self._a = np.array([p.accel_mps2 for p in self.phases] + [0.0])

    @classmethod
    def build(
        cls, t0_s: float, s0_m: float, v0_mps: float, plan: list[tuple[str, float, float]]
    ) -> SpeedProfile:
        """Profile from a plan of ``("ramp", target_speed, |accel|)`` and ``("hold", seconds, 0)``."""
        phases, v = [], v0_mps
        for kind, a, b in plan:
            if kind == "hold":
                if a > 0:
                    phases.append(SpeedPhase(a, 0.0))
            elif kind == "ramp":
                target, accel = max(a, 0.0), abs(b)
                if accel <= 0:
                    raise ValueError("a ramp needs a positive acceleration magnitude")
                if abs(target - v) > 1e-9:
                    phases.append(SpeedPhase(abs(target - v) / accel, np.sign(target - v) * accel))
                    v = target  # a skipped ramp leaves the speed as it is (no drift from the plan)
            else:
                raise ValueError(f"unknown speed plan step {kind!r}")
        return cls(t0_s, s0_m, v0_mps, phases)

    @property
    def end_time_s(self) -> float:
        return float(self._t[-1])

    def state(self, t_s: ArrayLike) -> tuple[F64, F64, F64]:
        """Arc length (m), speed (m/s) and acceleration (m/s^2) at times ``t_s``."""
        t = np.asarray(t_s, dtype=np.float64)
        idx = np.clip(np.searchsorted(self._t, t, side="right") - 1, 0, len(self._t) - 1)
        before = t < self.t0
        dt = t - self._t[idx]
        a = np.where(before, 0.0, self._a[idx])
        v_knot = self._v[idx]
        s = np.where(before, self.s0 + self.v0 * (t - self.t0), self._s[idx] + v_knot * dt + 0.5 * a * dt**2)
        v = np.where(before, self.v0, v_knot + a * dt)
        return s, np.maximum(v, 0.0), a


@dataclass
class Trajectory:
    """An object moving along a path with a speed profile; its box centre is ``z_m`` above ground.

    ``yaw_offset_rad`` turns the body relative to the direction of travel (pi for reversing).
    """

    path: Path
    speed: SpeedProfile
    z_m: float = 0.0
    yaw_offset_rad: float = 0.0

    def state(self, t_s: ArrayLike) -> tuple[F64, F64, F64, F64]:
        """Position ``(..., 3)``, yaw ``(...)``, velocity ``(..., 3)`` (m/s) and yaw rate (rad/s)."""
        s, v, _ = self.speed.state(t_s)
        xy, heading, kappa = self.path.pose(s)
        z = np.full((*s.shape, 1), self.z_m)
        pos = np.concatenate([xy, z], axis=-1)
        vel = np.stack([v * np.cos(heading), v * np.sin(heading), np.zeros_like(v)], axis=-1)
        yaw = geometry.wrap_angle(heading + self.yaw_offset_rad)
        return pos, yaw, vel, v * kappa

    def acceleration(self, t_s: ArrayLike) -> F64:
        """Acceleration ``(..., 3)`` of the centre, m/s^2: along the path plus centripetal."""
        s, v, a = self.speed.state(t_s)
        _, heading, kappa = self.path.pose(s)
        c, sn = np.cos(heading), np.sin(heading)
        normal = v * v * kappa
        return np.stack([a * c - normal * sn, a * sn + normal * c, np.zeros_like(v)], axis=-1)

    def world_from_body(self, t_s: ArrayLike) -> F64:
        """(..., 4, 4) pose of the body frame (x forward, z up, origin at the box centre)."""
        pos, yaw, _, _ = self.state(t_s)
        return geometry.yaw_pose_to_transform(pos, yaw)

    def is_static(self) -> bool:
        return self.speed.v0 == 0.0 and all(p.accel_mps2 == 0.0 for p in self.speed.phases)
