"""Boxes at any time from sparse annotated keyframes (nuScenes' 2 Hz samples): the stage
``interpolate_boxes`` and the library function :func:`interpolate_boxes_at` under it.

nuScenes annotates boxes at 2 Hz keyframes while its six cameras run at 12 Hz, each firing as the
LiDAR's 50 ms revolution passes it: 7 to 49 ms after the revolution starts, so a keyframe's own
images are 1 to 43 ms before its sample's time (the LIDAR_TOP timestamp marks the revolution's
end). The stage gives every frame its boxes at the frame's time and every image its boxes at the
image's own capture time (``CameraImage.boxes``).

Model (``method``; all in the world frame, metres, seconds, radians):

- Annotations are matched by ``track_id`` (the instance token). A track's annotations further apart
  than ``max_gap_s`` are split into pieces that are not interpolated across.
- ``ctra`` (default): a motion model fitted over windows of neighbouring annotations
  (:mod:`phigenesis.data.stages.ctra`): the centre moves along the annotated heading with constant
  turn rate and acceleration (``ctra``) or the simpler ``ctrv`` (constant speed), ``ca``
  (straight, accelerating) or ``cv`` (straight, constant speed). Every window of 3 to ``2 *
  half_window + 1`` annotations of a piece is fitted by weighted least squares to the centres and
  yaws with every model; a window keeps its lowest-BIC model if the residuals are consistent with
  the annotation noise (chi-square test at 99 % for the centres and for the yaws), and each
  annotation takes the accepted fit whose centre there has the least variance: the widest window
  the motion allows with the simplest model that explains it, so a least- squares fit smooths the
  annotation noise that an interpolant through the keyframes copies. The turning models let the
  box's yaw differ from the centre's course by a fitted slip angle (a car's centre is ahead of its
  rear axle). Of windows that pass, the one whose centre at the annotation has the least variance
  (scaled by the reduced chi-square where the residuals exceed the noise) wins. The noise (centre
  per coordinate, yaw) is estimated per class from the keyframes of the scene's moving objects
  (residuals of low-order polynomials through short runs of them; parked objects, which
  offboard-smoothed labels hold still, would drive it to its floor) unless ``noise_m`` /
  ``yaw_noise_deg`` give it. Between two annotations whose fits both span the interval the two
  fits are blended (smoothstep weights: exact where the motion is one model's); where a manoeuvre
  changes inside the interval (neither fit spans it) a cubic Hermite joins the two annotations'
  fitted states (centre, velocity, yaw, yaw rate). An annotation no window explains (manoeuvres on
  both sides within one interval), and every annotation of a piece of fewer than three, uses the
  ``hermite`` state (the annotation and three-point derivatives). Yaw is the fitted heading only
  where the fit is a straight model (``cv``, ``ca``: the centres fix the direction of travel far
  better than noisy annotated yaws); a turning model's yaw, a line in time, misfits real turns by
  more than the annotations' noise (benchmarks/interpolation.py), so there the annotated yaws are
  interpolated as ``hermite`` does (monotone cubic, limited tangents). Yaw is unwrapped along the
  shortest arc between neighbouring annotations and kept within the arc between its values at the
  interval's two annotations; tilt is slerped.
- ``hermite``: cubic Hermite on the centre with tangents from the neighbouring
  annotations (the three-point derivative, exact for constant acceleration: non-uniform central
  differences inside a piece, one-sided at its ends), so velocity and acceleration are continuous
  and turning or accelerating objects follow curves instead of chords. Yaw is a monotone cubic
  Hermite (Fritsch-Carlson limited tangents) on the yaw unwrapped along the shortest arc between
  neighbouring annotations: never the long way round +-pi, never outside the arc between its
  neighbours. Any tilt (pitch/roll) is slerped separately.
- ``linear``: linear centre and full-quaternion slerp at the real timestamp (the devkit's
  ``get_boxes``), with the same track handling as ``hermite``.
- ``asap``: ASAP's ``interp`` strategy, the baseline MagicDrive used (see :func:`asap_boxes`).

For ``ctra``, ``hermite`` and ``linear``:

- Size is interpolated linearly (constant per instance in nuScenes, so in practice held).
- A timestamp equal to an annotation's gives status "annotated" and the annotation's LiDAR point
  count. ``hermite`` and ``linear`` return the annotation exactly. ``ctra`` returns the model's
  pose there (``keyframe_pose="model"``, the default): the fit is a better estimate of the truth
  than one noisy annotation, and the boxes then have no jump at every keyframe (the images next
  to it come from the same fit); ``keyframe_pose="annotation"`` returns the annotation exactly.
- Between annotations: status "interpolated", velocity and (not ``linear``) acceleration from
  the model.
- Before a piece's first or after its last annotation (objects entering or leaving, an object
  seen in one keyframe only, the scene's last keyframe with no successor) boxes continue for
  ``extrapolation_s`` at the end velocity (and, for ``ctra`` and ``hermite``, yaw rate), status
  "extrapolated"; further away there is no box.
- Stationary objects: a piece whose centres all lie within ``stationary_m`` of their median,
  whose least-squares velocity moves it less than ``stationary_m / 2`` over the piece (so a slow
  walker seen briefly is not frozen) and whose yaws lie within ``stationary_yaw_deg`` of their
  circular mean is held at its mean pose
  and size (velocity 0) at every time, its keyframes included, so annotation noise neither
  jitters nor drifts it. Set ``stationary_m = 0`` to turn this off.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, assert_never, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from phigenesis import geometry
from phigenesis.data.records import (
    BOX_STATUSES,
    Boxes,
    Frame,
    KeyframeBoxes,
    LazyFrames,
    Scene,
    frame_geometry,
)
from phigenesis.data.stages import ctra, register_stage
from phigenesis.options import ConfigError, check_options, from_mapping, option

log = logging.getLogger("phigenesis.prep")

InterpolationMethod = Literal["ctra", "hermite", "linear", "asap"]
INTERPOLATION_METHODS: tuple[InterpolationMethod, ...] = get_args(InterpolationMethod)
#: What ``ctra`` returns at an annotation's own time (see the module docstring).
KeyframePose = Literal["model", "annotation"]
KEYFRAME_POSES: tuple[KeyframePose, ...] = get_args(KeyframePose)
ANNOTATED, INTERPOLATED, EXTRAPOLATED = (BOX_STATUSES.index(s) for s in BOX_STATUSES)
#: Indices in :data:`ctra.MOTION_MODELS` of the models whose fitted yaw ``ctra`` uses.
_STRAIGHT_MODELS = (ctra.MOTION_MODELS.index("cv"), ctra.MOTION_MODELS.index("ca"))
#: Bits of a search key given to the time (microseconds); the piece index takes the bits above.
_TIME_BITS = 40
_TIME_OFFSET = 1 << (_TIME_BITS - 2)


@dataclass(frozen=True)
class InterpolateParams:
    """Parameters of :func:`interpolate_boxes_at` and the ``interpolate_boxes`` stage.

    Attributes:
        method: "ctra" (default), "hermite", "linear" or "asap" (see the module docstring).
        extrapolation_s: boxes continue this long (seconds) before a track's first and after its
            last annotation, status "extrapolated" (not used by "asap").
        max_gap_s: annotations of a track further apart (seconds) are not interpolated across;
            at least twice ``extrapolation_s``.
        stationary_m: a track piece whose centres stay within this distance (metres) of their
            median, whose least-squares velocity moves it less than half this over the piece ...
        stationary_yaw_deg: ... and whose yaws stay within this (degrees) of their mean is held
            at its mean pose; 0 m turns holding off.
        asap_steps: ASAP's sub-frames per keyframe interval, keyframe included (``hz_factor``:
            6 for 12 Hz cameras over 2 Hz keyframes).
        half_window: ``ctra``: a fit window reaches at most this many annotations to either
            side of the one it serves (windows of 3 to 2 x this + 1 annotations).
        noise_m: ``ctra``: the annotations' centre noise per coordinate, metres; None: estimated
            per class from the scene's keyframes.
        yaw_noise_deg: ``ctra``: the annotations' yaw noise, degrees; None: estimated likewise.
        keyframe_pose: ``ctra`` at an annotation's own time: "model" (the fitted pose) or
            "annotation" (the annotation exactly).
    """

    method: InterpolationMethod = option("ctra")
    extrapolation_s: float = option(0.5, ge=0, le=3600)
    max_gap_s: float = option(1.5, ge=0, le=86_400)
    stationary_m: float = option(0.3, ge=0, le=1000)
    stationary_yaw_deg: float = option(10.0, ge=0, le=180)
    asap_steps: int = option(6, ge=1, le=1000)
    half_window: int = option(3, ge=1, le=1000)
    noise_m: float | None = option(None, gt=0, le=100)
    yaw_noise_deg: float | None = option(None, gt=0, le=180)
    keyframe_pose: KeyframePose = option("model")

    def __post_init__(self) -> None:
        check_options(self, "InterpolateParams")
        if self.max_gap_s < 2 * self.extrapolation_s:
            raise ConfigError(
                f"InterpolateParams: max_gap_s = {self.max_gap_s}: must be at least twice extrapolation_s "
                f"({self.extrapolation_s}) so the pieces of a track never overlap in time"
            )

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> InterpolateParams:
        return from_mapping(cls, values, "interpolate_boxes")


def interpolate_boxes_at(
    keyframes: Sequence[KeyframeBoxes],
    timestamps_micros: ArrayLike,
    params: InterpolateParams | None = None,
    channel: str | None = None,
) -> list[Boxes]:
    """The boxes at each of ``timestamps_micros``, interpolated from annotated keyframes.

    Args:
        keyframes: annotated keyframes in strictly increasing time order, boxes in the world frame
            (``Scene.keyframes``).
        timestamps_micros: (T,) int64 query times. For "asap" they must be the sweep times of
            ONE sensor in time order (ASAP counts sweeps after each keyframe); for the other
            methods any times in any order.
        params: the method and its parameters (defaults: :class:`InterpolateParams`).
        channel: "asap" only: the camera whose sweeps these are, so each keyframe's annotations
            go to that camera's own keyframe image (``KeyframeBoxes.camera_timestamps_micros``).

    Returns:
        T :class:`Boxes`, world frame, each box with its status (annotated, interpolated or
        extrapolated), velocity and (``ctra`` and ``hermite``) acceleration.

    Example::

        boxes = interpolate_boxes_at(scene.keyframes, [camera.timestamp_micros])[0]
    """
    p = params or InterpolateParams()
    times = np.asarray(timestamps_micros, np.int64).reshape(-1)
    if p.method == "asap":
        return asap_boxes(keyframes, times, p.asap_steps, channel)
    tracks = BoxTracks(keyframes, p)
    return [tracks.at(int(t)) for t in times]


# --------------------------------------------------------------------------------------------
# Track pieces


def _stack_keyframes(keyframes: Sequence[KeyframeBoxes]) -> tuple[Boxes, NDArray[np.int64]]:
    """All annotations as one :class:`Boxes` and their (N,) keyframe times; checks the order."""
    kf_times = np.array([k.timestamp_micros for k in keyframes], np.int64)
    if np.any(np.diff(kf_times) <= 0):
        raise ValueError(
            f"keyframes must be in strictly increasing time order, got times {kf_times.tolist()}"
        )
    for k in keyframes:
        if len(set(k.boxes.track_id)) != len(k.boxes):
            raise ValueError(f"keyframe {k.token or k.timestamp_micros} lists a track_id more than once")
    stacked = Boxes.concatenate([k.boxes for k in keyframes])
    times = np.concatenate([np.full(len(k.boxes), k.timestamp_micros, np.int64) for k in keyframes])
    return stacked, times


def _derivatives(
    values: NDArray[np.float64], t_s: NDArray[np.float64], first: NDArray[np.int64], last: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-annotation time derivatives of ``values`` (N, D) within pieces (``first``/``last``:
    (N,) index of each annotation's piece ends): the three-point derivative (exact for
    quadratics; one-sided at the ends) and the plain secant (forward at a piece's first
    annotation, backward elsewhere). Single annotations get NaN in both."""
    n = len(values)
    idx = np.arange(n)
    nxt, prv = np.minimum(idx + 1, n - 1), np.maximum(idx - 1, 0)
    h_next = (t_s[nxt] - t_s)[:, None]
    h_prev = (t_s - t_s[prv])[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        s_next = (values[nxt] - values) / h_next  # secant to the next annotation
        s_prev = (values - values[prv]) / h_prev
        s_next2 = np.roll(s_next, -1, axis=0)  # secant from the next to the one after
        s_prev2 = np.roll(s_prev, 1, axis=0)
        h_next2 = np.roll(h_next, -1, axis=0)
        h_prev2 = np.roll(h_prev, 1, axis=0)
        interior = (h_next * s_prev + h_prev * s_next) / (h_prev + h_next)
        start = s_next - h_next * (s_next2 - s_next) / (h_next + h_next2)
        end = s_prev + h_prev * (s_prev - s_prev2) / (h_prev + h_prev2)
    count = (last - first + 1)[:, None]
    is_first, is_last = (idx == first)[:, None], (idx == last)[:, None]
    three = np.where(is_first, start, np.where(is_last, end, interior))
    three = np.where(count == 2, np.where(is_first, s_next, s_prev), three)
    secant = np.where(is_first, s_next, s_prev)
    nan = np.full_like(values, np.nan)
    return np.where(count == 1, nan, three), np.where(count == 1, nan, secant)


def _monotone_tangents(
    y0: NDArray[np.float64], y1: NDArray[np.float64], h_s: NDArray[np.float64], m0: NDArray, m1: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fritsch-Carlson limited end tangents of Hermite segments from y0 to y1 (duration h_s):
    a tangent against the secant (or on a flat segment) becomes 0 and each is at most 3x the
    secant, which keeps the curve inside [y0, y1]."""
    d = np.divide(y1 - y0, h_s, out=np.zeros(np.shape(y0)), where=h_s > 0)
    m0 = np.where(m0 * d > 0, np.minimum(np.abs(m0), 3 * np.abs(d)) * np.sign(d), 0.0)
    m1 = np.where(m1 * d > 0, np.minimum(np.abs(m1), 3 * np.abs(d)) * np.sign(d), 0.0)
    return m0, m1


@dataclass(frozen=True)
class _State:
    """Motion states of M boxes: centre (m), velocity (m/s), acceleration (m/s^2), all (M, 3)
    world frame; yaw (M,) rad, unwrapped along the track piece; yaw rate (M,) rad/s."""

    center: NDArray[np.float64]
    velocity: NDArray[np.float64]
    acceleration: NDArray[np.float64]
    yaw: NDArray[np.float64]
    yaw_rate: NDArray[np.float64]


class BoxTracks:
    """A scene's keyframe annotations grouped into track pieces, ready to evaluate at any time.

    Build once per scene (``O(N log N)`` in the N annotations, plus the ``ctra`` window fits,
    about 20 per annotation); :meth:`at` costs one vectorised pass over the P pieces. Methods
    "ctra", "hermite" and "linear" (ASAP is :func:`asap_boxes`).
    """

    def __init__(self, keyframes: Sequence[KeyframeBoxes], params: InterpolateParams | None = None):
        self.params = p = params or InterpolateParams()
        if p.method == "asap":
            raise ValueError("BoxTracks evaluates 'ctra', 'hermite' and 'linear'; use asap_boxes for 'asap'")
        ann, times = _stack_keyframes(keyframes)
        _, track_index = np.unique(np.array(ann.track_id, dtype=object), return_inverse=True)
        order = np.lexsort((times, track_index))
        self.ann = ann.select(order)
        self.times = times[order]
        track = track_index[order]
        n = len(self.times)
        gap_s = np.diff(self.times) * 1e-6
        new_piece = np.ones(n, bool)
        new_piece[1:] = (np.diff(track) != 0) | (gap_s > p.max_gap_s)
        self.piece_start = np.append(np.flatnonzero(new_piece), n).astype(np.int64)
        piece = np.cumsum(new_piece) - 1
        self.first = self.piece_start[piece]
        self.last = self.piece_start[piece + 1] - 1
        self.t0 = int(self.times.min()) if n else 0
        self.keys = (piece.astype(np.int64) << _TIME_BITS) + (self.times - self.t0 + _TIME_OFFSET)
        t_s = (self.times - self.t0) * 1e-6
        # Yaw unwrapped along the shortest arc between neighbouring annotations of a piece.
        step = np.zeros(n)
        if n:
            step[1:] = geometry.angle_difference(self.ann.yaw_world[1:], self.ann.yaw_world[:-1])
        step[new_piece] = 0.0
        cum = np.cumsum(step)
        self.yaw = self.ann.yaw_world[self.first] + cum - cum[self.first]
        # The tilt left when the yaw is taken out (identity for upright boxes).
        self.tilt = geometry.quaternion_canonical(
            geometry.quaternion_multiply(
                geometry.yaw_to_quaternion(-self.ann.yaw_world), self.ann.orientation_world
            )
        )
        velocity = np.nan_to_num(self.ann.velocity_world)  # a single annotation moves at its own
        self.center_rate, self.center_secant = (
            np.where(np.isnan(d), velocity, d)
            for d in _derivatives(self.ann.center_world, t_s, self.first, self.last)
        )
        yaw_rate, _ = _derivatives(self.yaw[:, None], t_s, self.first, self.last)
        self.yaw_rate = np.nan_to_num(yaw_rate[:, 0])
        # Segment i -> i + 1 (the last annotation of a piece starts none): limited yaw tangents.
        nxt = np.minimum(np.arange(n) + 1, max(n - 1, 0))
        self.yaw_m0, self.yaw_m1 = _monotone_tangents(
            self.yaw, self.yaw[nxt], t_s[nxt] - t_s, self.yaw_rate, self.yaw_rate[nxt]
        )
        self._find_stationary()
        self.fits: ctra.TrackFits | None = None
        if p.method == "ctra":
            self._fit_motion(t_s)

    def _fit_motion(self, t_s: NDArray[np.float64]) -> None:
        """``ctra``: fits the motion models over every piece's windows (:func:`ctra.fit_tracks`)
        and sets each annotation's state: its fit's at its time, or the ``hermite`` state (the
        annotation, three-point velocity and yaw rate, unknown acceleration) where it has none."""
        p = self.params
        n = len(t_s)
        sigma_m, sigma_rad = np.full(n, ctra.DEFAULT_SIGMA_M), np.full(n, ctra.DEFAULT_SIGMA_RAD)
        if p.noise_m is None or p.yaw_noise_deg is None:
            ground = self.ann.center_world[:, 0] + 1j * self.ann.center_world[:, 1]
            sigma_m, sigma_rad = ctra.estimate_noise(
                t_s, ground, self.yaw, self.first, self.last, self.ann.class_id
            )
        if p.noise_m is not None:
            sigma_m = np.full(n, max(p.noise_m, ctra.MIN_SIGMA_M))
        if p.yaw_noise_deg is not None:
            sigma_rad = np.full(n, max(np.radians(p.yaw_noise_deg), ctra.MIN_SIGMA_RAD))
        self.fits = ctra.fit_tracks(
            t_s, self.ann.center_world, self.yaw, self.first, self.last, sigma_m, sigma_rad, p.half_window
        )
        state = self._fit_state(np.arange(n), t_s)
        fitted = self.fits.fitted
        # Yaw from the fit only where it is a straight model (the heading then is the direction
        # of travel, which the centres fix far better than noisy annotated yaws); a turning
        # model's yaw is a line in time whose misfit in real turns exceeds the annotations'
        # noise (benchmarks/interpolation.py), so there the annotated yaws are interpolated.
        self.fit_yaw = fitted & np.isin(self.fits.model, _STRAIGHT_MODELS)
        self.state = _State(
            center=np.where(fitted[:, None], state.center, self.ann.center_world),
            velocity=np.where(fitted[:, None], state.velocity, self.center_rate),
            acceleration=np.where(fitted[:, None], state.acceleration, np.nan),
            yaw=np.where(self.fit_yaw, state.yaw, self.yaw),
            yaw_rate=np.where(self.fit_yaw, state.yaw_rate, self.yaw_rate),
        )
        #: The turn rate of each annotation's course (rad/s): its fit's, else the yaw rate.
        self.course_rate = np.where(fitted, state.yaw_rate, self.yaw_rate)

    def _fit_state(self, anchors: NDArray[np.int64], t_s: ArrayLike) -> _State:
        """The fits of annotations ``anchors`` (M,) evaluated at ``t_s`` (seconds from the
        tracks' first annotation; scalar or (M,))."""
        fits = self.fits
        assert fits is not None
        tau = np.asarray(t_s, np.float64) - fits.reference_s[anchors]
        tau = np.broadcast_to(tau, anchors.shape)
        m = ctra.motion_state(fits.params[anchors], tau)
        z0, z_rate = fits.height[anchors, 0], fits.height[anchors, 1]
        return _State(
            center=np.stack([m.center.real, m.center.imag, z0 + z_rate * tau], axis=1),
            velocity=np.stack([m.velocity.real, m.velocity.imag, z_rate], axis=1),
            acceleration=np.stack([m.acceleration.real, m.acceleration.imag, np.zeros_like(tau)], axis=1),
            yaw=m.yaw,
            yaw_rate=m.yaw_rate,
        )

    def model_counts(self) -> dict[str, int]:
        """``ctra``: how many annotations took each motion model, and the "interpolant" (the
        ``hermite`` state: no window explained them, or their piece is shorter than 3)."""
        if self.fits is None:
            return {}
        counts = {name: int(np.sum(self.fits.model == k)) for k, name in enumerate(ctra.MOTION_MODELS)}
        counts["interpolant"] = int(np.sum(~self.fits.fitted))
        return counts

    def _find_stationary(self) -> None:
        p = self.params
        starts, ends = self.piece_start[:-1], self.piece_start[1:]
        count = len(starts)
        self.stationary = np.zeros(count, bool)
        self.still_center = np.zeros((count, 3))
        self.still_yaw = np.zeros(count)
        self.still_size = np.zeros((count, 3))
        if p.stationary_m <= 0:
            return
        for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
            if b - a < 2:
                continue
            c = self.ann.center_world[a:b]
            yaw = self.ann.yaw_world[a:b]
            mean_yaw = float(np.arctan2(np.mean(np.sin(yaw)), np.mean(np.cos(yaw))))
            spread = np.max(np.linalg.norm(c - np.median(c, axis=0), axis=1))
            # Net motion over the piece from the least-squares velocity: a slow walker seen for a
            # second stays within stationary_m of its median but moves steadily; noise does not.
            t = (self.times[a:b] - self.times[a]) * 1e-6
            slope = np.polyfit(t, c, 1)[0]
            moved = np.linalg.norm(slope) * t[-1]
            turn = np.max(np.abs(geometry.angle_difference(yaw, mean_yaw)))
            still = spread <= p.stationary_m and moved <= 0.5 * p.stationary_m
            if still and np.degrees(turn) <= p.stationary_yaw_deg:
                self.stationary[k] = True
                self.still_center[k] = c.mean(axis=0)
                self.still_yaw[k] = mean_yaw
                self.still_size[k] = self.ann.size_lwh[a:b].mean(axis=0)

    @property
    def pieces(self) -> int:
        return len(self.piece_start) - 1

    def at(self, timestamp_micros: int) -> Boxes:
        """The boxes at ``timestamp_micros`` (world frame), in track-id order."""
        p = self.params
        t = int(timestamp_micros)
        count = self.pieces
        if count == 0:
            return Boxes.empty()
        first, last = self.piece_start[:-1], self.piece_start[1:] - 1
        rel = np.clip(t - self.t0 + _TIME_OFFSET, 0, (1 << _TIME_BITS) - 1)
        pos = np.searchsorted(self.keys, (np.arange(count, dtype=np.int64) << _TIME_BITS) + rel, "right") - 1
        before = pos < first
        pos = np.where(before, first, pos)
        exact = ~before & (self.times[pos] == t)
        after = ~before & ~exact & (pos == last)
        inside = ~(before | exact | after)
        dt_s = (t - self.times[pos]) * 1e-6  # negative before the first annotation
        keep = exact | inside | (np.abs(dt_s) <= p.extrapolation_s + 1e-9)
        sel = np.flatnonzero(keep)
        i = pos[sel]
        out = self.ann.select(i)
        out.status = np.where(
            exact[sel], ANNOTATED, np.where(inside[sel], INTERPOLATED, EXTRAPOLATED)
        ).astype(np.uint8)
        out.num_lidar_points = np.where(exact[sel], out.num_lidar_points, -1).astype(np.int32)
        out.velocity_world = np.where(
            np.isfinite(out.velocity_world), out.velocity_world, self.center_rate[i]
        )
        if self.fits is not None and p.keyframe_pose == "model":
            self._set_state(out, exact[sel], i[exact[sel]])
        mid = inside[sel]
        self._interpolate(out, mid, i[mid], t)
        self._extrapolate(out, ~mid & ~exact[sel], i[~mid & ~exact[sel]], dt_s[sel][~mid & ~exact[sel]])
        still = self.stationary[sel]
        if np.any(still):
            piece = sel[still]
            out.center_world[still] = self.still_center[piece]
            out.yaw_world[still] = self.still_yaw[piece]
            out.size_lwh[still] = self.still_size[piece]
            out.velocity_world[still] = 0.0
            out.acceleration_world[still] = 0.0
            out.orientation_world[still] = geometry.quaternion_multiply(
                geometry.yaw_to_quaternion(self.still_yaw[piece]), self.tilt[first[piece]]
            )
        out.yaw_world = geometry.wrap_angle(out.yaw_world)
        return out

    def _set_state(self, out: Boxes, mask: NDArray[np.bool_], i: NDArray[np.int64]) -> None:
        """Fills ``out[mask]`` with the ``ctra`` states of annotations ``i`` (at their times)."""
        if not np.any(mask):
            return
        out.center_world[mask] = self.state.center[i]
        out.velocity_world[mask] = self.state.velocity[i]
        out.acceleration_world[mask] = self.state.acceleration[i]
        out.yaw_world[mask] = self.state.yaw[i]
        out.orientation_world[mask] = geometry.quaternion_multiply(
            geometry.yaw_to_quaternion(self.state.yaw[i]), self.tilt[i]
        )

    def _interpolate(self, out: Boxes, mask: NDArray[np.bool_], i: NDArray[np.int64], t: int) -> None:
        """Fills ``out[mask]`` between annotations ``i`` and ``i + 1`` at time ``t``."""
        if not np.any(mask):
            return
        j = i + 1
        h = (self.times[j] - self.times[i]) * 1e-6
        s = ((t - self.times[i]) * 1e-6 / h)[:, None]
        c0, c1 = self.ann.center_world[i], self.ann.center_world[j]
        out.size_lwh[mask] = self.ann.size_lwh[i] + s * (self.ann.size_lwh[j] - self.ann.size_lwh[i])
        method = self.params.method
        if method == "linear":
            out.center_world[mask] = c0 + s * (c1 - c0)
            out.velocity_world[mask] = (c1 - c0) / h[:, None]
            out.acceleration_world[mask] = np.nan
            q = geometry.quaternion_slerp(
                self.ann.orientation_world[i], self.ann.orientation_world[j], s[:, 0]
            )
            out.orientation_world[mask] = q
            out.yaw_world[mask] = geometry.quaternion_yaw(q)
        elif method == "hermite":
            hh = h[:, None]
            m0, m1 = self.center_rate[i] * hh, self.center_rate[j] * hh
            value, rate, accel = _hermite(c0, m0, c1, m1, s)
            out.center_world[mask] = value
            out.velocity_world[mask] = rate / hh
            out.acceleration_world[mask] = accel / hh**2
            yaw, _, _ = _hermite(
                self.yaw[i, None],
                (self.yaw_m0[i] * h)[:, None],
                self.yaw[j, None],
                (self.yaw_m1[i] * h)[:, None],
                s,
            )
            tilt = geometry.quaternion_slerp(self.tilt[i], self.tilt[j], s[:, 0])
            out.yaw_world[mask] = yaw[:, 0]
            out.orientation_world[mask] = geometry.quaternion_multiply(
                geometry.yaw_to_quaternion(yaw[:, 0]), tilt
            )
        elif method == "ctra":
            self._interpolate_motion(out, mask, i, (t - self.t0) * 1e-6, h, s)
        elif method == "asap":
            raise ValueError("asap is evaluated by asap_boxes")
        else:
            assert_never(method)

    def _interpolate_motion(
        self,
        out: Boxes,
        mask: NDArray[np.bool_],
        i: NDArray[np.int64],
        t_s: float,
        h: NDArray[np.float64],
        s: NDArray[np.float64],
    ) -> None:
        """``ctra`` between annotations ``i`` and ``i + 1`` (interval ``h`` s, fraction ``s``
        (M, 1)) at ``t_s``: the blend of their two fits where both span the interval, else a
        cubic Hermite between their states; yaw kept within the arc between the two states'."""
        fits, state = self.fits, self.state
        assert fits is not None
        j = i + 1
        hh = h[:, None]
        center, rate, accel = _hermite(
            state.center[i], state.velocity[i] * hh, state.center[j], state.velocity[j] * hh, s
        )
        velocity, acceleration = rate / hh, accel / hh**2
        m0, m1 = _monotone_tangents(state.yaw[i], state.yaw[j], h, state.yaw_rate[i], state.yaw_rate[j])
        yaw = _hermite(state.yaw[i, None], (m0 * h)[:, None], state.yaw[j, None], (m1 * h)[:, None], s)[0][
            :, 0
        ]
        spans = fits.fitted[i] & fits.fitted[j] & (fits.window[i, 1] >= j) & (fits.window[j, 0] <= i)
        c = np.flatnonzero(spans)
        if len(c):
            a, b = self._fit_state(i[c], t_s), self._fit_state(j[c], t_s)
            u, hc = s[c], hh[c]
            w = u * u * (3.0 - 2.0 * u)  # smoothstep: (M, 1)
            dw = 6.0 * u * (1.0 - u) / hc
            ddw = (6.0 - 12.0 * u) / hc**2
            gap = b.center - a.center
            center[c] = (1.0 - w) * a.center + w * b.center
            velocity[c] = (1.0 - w) * a.velocity + w * b.velocity + dw * gap
            acceleration[c] = (
                (1.0 - w) * a.acceleration
                + w * b.acceleration
                + 2.0 * dw * (b.velocity - a.velocity)
                + ddw * gap
            )
            both = self.fit_yaw[i[c]] & self.fit_yaw[j[c]]
            yaw[c[both]] = ((1.0 - w[:, 0]) * a.yaw + w[:, 0] * b.yaw)[both]
        yaw = np.clip(yaw, np.minimum(state.yaw[i], state.yaw[j]), np.maximum(state.yaw[i], state.yaw[j]))
        tilt = geometry.quaternion_slerp(self.tilt[i], self.tilt[j], s[:, 0])
        out.center_world[mask] = center
        out.velocity_world[mask] = velocity
        out.acceleration_world[mask] = acceleration
        out.yaw_world[mask] = yaw
        out.orientation_world[mask] = geometry.quaternion_multiply(geometry.yaw_to_quaternion(yaw), tilt)

    def _extrapolate(
        self, out: Boxes, mask: NDArray[np.bool_], i: NDArray[np.int64], dt_s: NDArray[np.float64]
    ) -> None:
        """Fills ``out[mask]``: annotation ``i`` (a piece's first or last) moved by ``dt_s``."""
        if not np.any(mask):
            return
        method = self.params.method
        center, yaw0 = self.ann.center_world[i], self.yaw[i]
        if method == "ctra":
            center, velocity = self.state.center[i], self.state.velocity[i]
            yaw0, yaw_rate = self.state.yaw[i], self.state.yaw_rate[i]
            course_rate = self.course_rate[i]
        elif method == "hermite":
            velocity, yaw_rate = self.center_rate[i], self.yaw_rate[i]
            course_rate = yaw_rate
        else:
            velocity, yaw_rate = self.center_secant[i], np.zeros(len(i))
            course_rate = yaw_rate
        turn = course_rate * dt_s
        # Constant turn rate: the velocity turns with the course (straight where it does not).
        with np.errstate(invalid="ignore", divide="ignore"):
            along = np.where(np.abs(turn) > 1e-9, np.sin(turn) / course_rate, dt_s)
            across = np.where(
                np.abs(turn) > 1e-9, (1.0 - np.cos(turn)) / course_rate, 0.5 * course_rate * dt_s**2
            )
        left = np.stack([-velocity[:, 1], velocity[:, 0], np.zeros(len(i))], axis=1)
        out.center_world[mask] = center + along[:, None] * velocity + across[:, None] * left
        out.velocity_world[mask] = np.cos(turn)[:, None] * velocity + np.sin(turn)[:, None] * left
        out.velocity_world[mask, 2] = velocity[:, 2]
        out.acceleration_world[mask] = np.nan
        yaw = yaw0 + yaw_rate * dt_s
        out.yaw_world[mask] = yaw
        out.orientation_world[mask] = geometry.quaternion_multiply(
            geometry.yaw_to_quaternion(yaw), self.tilt[i]
        )


def _hermite(
    v0: NDArray[np.float64],
    m0: NDArray[np.float64],
    v1: NDArray[np.float64],
    m1: NDArray[np.float64],
    s: NDArray,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Cubic Hermite value and its first and second derivatives in ``s`` (in [0, 1]), with end
    values v0, v1 and end derivatives m0, m1 (per unit of ``s``); all (N, D), ``s`` (N, 1)."""
    s2, s3 = s * s, s * s * s
    value = (2 * s3 - 3 * s2 + 1) * v0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * v1 + (s3 - s2) * m1
    rate = (6 * s2 - 6 * s) * (v0 - v1) + (3 * s2 - 4 * s + 1) * m0 + (3 * s2 - 2 * s) * m1
    accel = (12 * s - 6) * (v0 - v1) + (6 * s - 4) * m0 + (6 * s - 2) * m1
    return value, rate, accel


# --------------------------------------------------------------------------------------------
# ASAP (the baseline)


def asap_boxes(
    keyframes: Sequence[KeyframeBoxes],
    sweep_times_micros: ArrayLike,
    steps: int = 6,
    channel: str | None = None,
) -> list[Boxes]:
    """ASAP's ``interp`` annotations (JeffWang987/ASAP, used by MagicDrive) for one sensor's sweeps.

    Each keyframe K's sweep gets K's annotations as they are. As in ASAP, that is the sensor's own
    keyframe sample_data: for a camera ``channel`` the sweep at
    ``K.camera_timestamps_micros[channel]`` (none if that image is not among the sweeps); where
    K does not give the channel's time (no channel, a source without camera times), the sweep
    nearest K's time within half the keyframe interval. The k-th sweep after it
    (k = 1 .. steps - 1, counted in the sequence, so a dropped sweep shifts the rest) gets the
    boxes at the uniform subdivision time ``t_K + k / steps * (t_{K+1} - t_K)``, NOT its own
    timestamp: linear centre, full-quaternion slerp, size (and class, ids) copied from K,
    velocity the secant, only the objects annotated in both K and K + 1. Sweeps before the
    first keyframe's, after the last keyframe's (its interval has no successor) or beyond
    ``steps - 1`` get no boxes.

    Args:
        keyframes: annotated keyframes in time order.
        sweep_times_micros: (T,) the sensor's sweep times in time order.
        steps: sub-frames per keyframe interval, keyframe included (6 for 12 Hz over 2 Hz).
        channel: the camera whose sweeps these are (None: the LiDAR or frame times).

    Returns:
        T :class:`Boxes` in the world frame.
    """
    times = np.asarray(sweep_times_micros, np.int64).reshape(-1)
    if np.any(np.diff(times) < 0):
        raise ValueError("asap_boxes needs one sensor's sweep times in time order")
    out = [Boxes.empty() for _ in times]
    if len(times) == 0 or not keyframes:
        return out
    key_sweep = _asap_keyframe_sweeps(keyframes, times, channel)
    for k_index, j in enumerate(key_sweep):
        if j is None:
            continue
        out[j] = keyframes[k_index].boxes.select(np.arange(len(keyframes[k_index].boxes)))
        nxt = key_sweep[k_index + 1] if k_index + 1 < len(key_sweep) else None
        if nxt is None:
            continue
        for k, sweep in enumerate(range(j + 1, min(nxt, j + steps)), start=1):
            out[sweep] = _asap_between(keyframes[k_index], keyframes[k_index + 1], k / steps)
    return out


def _asap_keyframe_sweeps(
    keyframes: Sequence[KeyframeBoxes], times: NDArray[np.int64], channel: str | None
) -> list[int | None]:
    """Index into ``times`` of each keyframe's own sweep (see :func:`asap_boxes`), or None."""
    kf_times = np.array([k.timestamp_micros for k in keyframes], np.int64)
    interval = np.diff(kf_times)
    half = 0.5 * np.concatenate([interval[:1], interval]) if len(interval) else np.array([np.inf])
    out: list[int | None] = []
    for kf, t_k, limit in zip(keyframes, kf_times, half, strict=True):
        own = kf.camera_timestamps_micros.get(channel) if channel is not None else None
        if own is not None:
            hits = np.flatnonzero(times == own)
            out.append(int(hits[0]) if len(hits) else None)
            continue
        j = int(np.argmin(np.abs(times - t_k)))
        out.append(j if abs(times[j] - t_k) <= limit else None)
    return out


def _asap_between(a: KeyframeBoxes, b: KeyframeBoxes, fraction: float) -> Boxes:
    """ASAP's ``get_new_ann``: the objects annotated in both a and b at ``fraction`` of the way."""
    index_b = {t: k for k, t in enumerate(b.boxes.track_id)}
    ia = np.array([k for k, t in enumerate(a.boxes.track_id) if t in index_b], np.int64)
    ib = np.array([index_b[a.boxes.track_id[k]] for k in ia], np.int64)
    out = a.boxes.select(ia)
    c0, c1 = a.boxes.center_world[ia], b.boxes.center_world[ib]
    out.center_world = c0 + fraction * (c1 - c0)
    out.velocity_world = (c1 - c0) / ((b.timestamp_micros - a.timestamp_micros) * 1e-6)
    out.orientation_world = geometry.quaternion_slerp(
        a.boxes.orientation_world[ia], b.boxes.orientation_world[ib], np.full(len(ia), fraction)
    ).reshape(-1, 4)
    out.yaw_world = geometry.quaternion_yaw(out.orientation_world).reshape(-1)
    out.status = np.full(len(ia), INTERPOLATED, np.uint8)
    out.num_lidar_points = np.full(len(ia), -1, np.int32)
    return out


# --------------------------------------------------------------------------------------------
# The stage


class _FrameBoxes:
    """Sets a frame's boxes (at the frame time) and each image's boxes (at its own time)."""

    def __init__(self, scene: Scene, params: InterpolateParams):
        self.params = params
        self.tracks: BoxTracks | None = None
        self.asap: dict[tuple[int, str | None], Boxes] = {}
        if params.method == "asap":
            self._schedule_asap(scene)
        else:
            self.tracks = BoxTracks(scene.keyframes, params)

    def _schedule_asap(self, scene: Scene) -> None:
        """ASAP counts sweeps, so it needs every frame's and camera's time up front (geometry)."""
        sequences: dict[str | None, list[tuple[int, int]]] = {None: []}
        for index in range(len(scene.frames)):
            frame = frame_geometry(scene.frames, index)
            sequences[None].append((frame.timestamp_micros, index))
            for cam in frame.cameras:
                sequences.setdefault(cam.name, []).append((cam.timestamp_micros, index))
        for name, seq in sequences.items():
            seq.sort()
            boxes = asap_boxes(scene.keyframes, [t for t, _ in seq], self.params.asap_steps, name)
            for (_, index), b in zip(seq, boxes, strict=True):
                self.asap[(index, name)] = b

    def boxes(self, frame_index: int, name: str | None, timestamp_micros: int) -> Boxes:
        if self.tracks is not None:
            return self.tracks.at(timestamp_micros)
        return self.asap.get((frame_index, name), Boxes.empty())

    def __call__(self, frame: Frame) -> Frame:
        frame.boxes = self.boxes(frame.frame_index, None, frame.timestamp_micros)
        for cam in frame.cameras:
            cam.boxes = self.boxes(frame.frame_index, cam.name, cam.timestamp_micros)
        return frame


@register_stage("interpolate_boxes", params=InterpolateParams)
def interpolate_boxes(scene: Scene, p: InterpolateParams) -> Scene:
    """Stage: boxes at every frame's time (``frame.boxes``) and every image's own time
    (``camera.boxes``) from ``scene.keyframes`` (see the module docstring); lazy per frame. A
    scene without keyframes (every frame carries its own boxes) passes through unchanged."""
    if not scene.keyframes:
        log.info("scene %s: interpolate_boxes skipped: the scene has no keyframes", scene.scene_id)
        return scene
    fill = _FrameBoxes(scene, p)
    stats: dict[str, Any] = {"method": p.method, "keyframes": len(scene.keyframes)}
    if fill.tracks is not None:
        stats |= {
            "extrapolation_s": p.extrapolation_s,
            "tracks": len(set(fill.tracks.ann.track_id)),
            "track_pieces": fill.tracks.pieces,
            "stationary_pieces": int(fill.tracks.stationary.sum()),
        }
        fits = fill.tracks.fits
        if fits is not None:
            stats |= {
                "motion_models": fill.tracks.model_counts(),
                "noise_m": round(float(np.median(fits.sigma_m)), 4) if len(fits.sigma_m) else None,
                "yaw_noise_deg": (
                    round(float(np.degrees(np.median(fits.sigma_rad))), 3) if len(fits.sigma_rad) else None
                ),
            }
    scene.metadata["interpolate_boxes"] = stats
    log.info("scene %s: interpolate_boxes %s", scene.scene_id, stats)
    scene.frames = (
        scene.frames.map(fill) if isinstance(scene.frames, LazyFrames) else [fill(f) for f in scene.frames]
    )
    return scene
