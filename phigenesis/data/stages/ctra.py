"""Motion models fitted over windows of annotated keyframes: what ``interpolate_boxes``' default
method ``ctra`` (constant turn rate and acceleration) is built on.

The models (all in the ground plane, world frame, metres, seconds, radians) describe a box centre
that moves along its heading: heading ``theta(tau) = theta0 + omega * tau``, speed
``v(tau) = v0 + accel * tau`` (negative when reversing), so the centre is

    c(tau) = c0 + e^{i theta0} (v0 F1(tau, omega) + accel F2(tau, omega)),
    F_k(tau, omega) = int_0^tau s^(k - 1) e^{i omega s} ds                     (complex x + iy)

and the annotated yaw is the heading, plus (turning models only) a constant slip angle: a car's
box centre sits ahead of its rear axle, so in a turn it moves at an angle to the box's yaw (in a
steady turn of radius R, ``atan(d / R)`` for a centre d ahead of the axle). A straight
accelerating object never turns its speed round within a fit: where ``v0 + accel * tau`` reaches
zero it stands (it braked to a stop and waits, or it waited and then set off), so there ``tau``
above becomes the time it has moved for (:func:`moving_time`). Nested models:

=========  ==========================  ===================================================
model      free parameters             motion
=========  ==========================  ===================================================
``cv``     c0, v0, theta0              straight at constant speed
``ca``     c0, v0, theta0, accel       straight, constant acceleration (or to/from a stop)
``ctrv``   c0, v0, theta0, omega,      constant turn rate, constant speed
           slip
``ctra``   c0, v0, theta0, accel,      constant turn rate and acceleration
           omega, slip
=========  ==========================  ===================================================

A window's fit is weighted least squares over its keyframes' centres (noise ``sigma_m`` per
coordinate) and yaws (``sigma_rad``): Levenberg-Marquardt from a start that is exact for exact
data (turn rate and heading from a straight-line fit of the yaws, the rest linear given them), so
exact motion of a model is recovered to rounding. The height is a separate straight-line fit.
The noise levels are the caller's or :func:`estimate_noise`'s (from the keyframes of the scene's
moving objects: offboard-smoothed labels hold parked objects still, and their residuals would
drive the estimate to its floor).

:func:`fit_tracks` fits every window of 3 to ``2 * half_window + 1`` consecutive keyframes of each
track piece with every model, keeps per window the model with the lowest BIC, accepts it where
its residuals are consistent with the noise (position and yaw chi-square each below their 99 %
point), and gives each keyframe (anchor) the accepted window fit whose centre at the anchor has
the smallest variance, scaled by the window's reduced chi-square where that exceeds 1 (so the
widest window the motion allows, the simplest model that explains it, and of windows that pass
the test the one whose residuals leave least room for a manoeuvre the model lacks). An anchor
no window explains (manoeuvres on both sides within one keyframe interval) gets no fit; the
caller falls back to an interpolant there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

MotionModel = Literal["cv", "ca", "ctrv", "ctra"]
MOTION_MODELS: tuple[MotionModel, ...] = ("cv", "ca", "ctrv", "ctra")
#: Columns of a parameter row (every model uses this layout; its unused parameters are 0). SLIP
#: is the box's yaw minus the heading of its centre's motion (radians; the turning models only).
#: The last, SENSE, is not fitted: +1 for forward motion, -1 for reversing (see :func:`moving_time`).
X0, Y0, V0, THETA0, ACCEL, OMEGA, SLIP, SENSE = range(8)
PARAMETERS = 8
MODEL_PARAMETERS: dict[MotionModel, tuple[int, ...]] = {
    "cv": (X0, Y0, V0, THETA0),
    "ca": (X0, Y0, V0, THETA0, ACCEL),
    "ctrv": (X0, Y0, V0, THETA0, OMEGA, SLIP),
    "ctra": (X0, Y0, V0, THETA0, ACCEL, OMEGA, SLIP),
}
#: Standard normal quantile of the residual test (99 %).
_GATE_Z = 2.326
#: Series terms of the turn integrals below |omega tau| = 0.5 (the last adds < 1e-17).
_SERIES_TERMS = 16
_ITERATIONS = 8
#: Smallest noise levels used, so exact annotations still give finite chi-squares.
MIN_SIGMA_M = 0.002
MIN_SIGMA_RAD = np.radians(0.1)
#: Noise levels used where a scene has too few keyframe windows to estimate them.
DEFAULT_SIGMA_M = 0.05
DEFAULT_SIGMA_RAD = np.radians(1.0)
#: Windows a class needs for its own noise estimate (else the scene's pooled estimate).
MIN_NOISE_WINDOWS = 8
#: Quantile of the windows' residuals that estimates the noise (a low one: a change of
#: acceleration or turn rate inside a window raises its residual, noise raises all alike), and
#: that quantile of a chi-square variable with 1 and 2 degrees of freedom.
_NOISE_QUANTILE = 0.25
_CHI2_QUANTILE = {1: 0.1015, 2: 0.5754}
#: Average speed (m/s) over about two seconds above which an object counts as moving for the
#: noise estimate (:func:`moving_annotations`).
MOVING_SPEED_MPS = 0.5

Complex = NDArray[np.complex128]
Float = NDArray[np.float64]
Int = NDArray[np.int64]


def turn_integrals(tau: Float, omega: Float) -> tuple[Complex, Complex, Complex]:
    """``F_k(tau) = int_0^tau s^(k-1) e^{i omega s} ds`` for k = 1, 2, 3 (broadcast shapes).

    ``F1`` and ``F2`` are the displacement of unit speed and unit acceleration along a heading
    turning at ``omega`` (rad/s) for ``tau`` seconds (metres, complex x + iy, heading 0 at
    ``tau = 0``); ``F3`` gives their derivatives in omega (dF1 = i F2, dF2 = i F3). A power
    series is used below ``|omega tau| = 0.5``, where the closed forms lose digits.
    """
    tau, omega = np.broadcast_arrays(np.asarray(tau, np.float64), np.asarray(omega, np.float64))
    if not np.any(omega):  # straight motion: the integrals of s^(k-1)
        return tau + 0j, tau**2 / 2 + 0j, tau**3 / 3 + 0j
    out = [np.empty(tau.shape, np.complex128) for _ in range(3)]
    small = np.abs(omega * tau) < 0.5
    t, w = tau[small], omega[small]
    x = 1j * w * t
    # F_k = tau^k sum_n x^n / (n! (n + k)), summed from the last term (Horner).
    series = [np.zeros(t.shape, np.complex128) for _ in range(3)]
    for n in range(_SERIES_TERMS - 1, -1, -1):
        for k in range(3):
            series[k] = series[k] * x / (n + 1) + 1.0 / (n + k + 1)
    for k in range(3):
        out[k][small] = series[k] * t ** (k + 1)
    t, w = tau[~small], omega[~small]
    iw = 1j * w
    e = np.exp(iw * t)
    f1 = (e - 1.0) / iw
    f2 = t * e / iw - f1 / iw
    out[0][~small], out[1][~small] = f1, f2
    out[2][~small] = t * t * e / iw - 2.0 * f2 / iw
    return out[0], out[1], out[2]


@dataclass(frozen=True)
class MotionState:
    """A model's state at given times: (B,) arrays (complex for ground-plane vectors x + iy).

    Attributes:
        center: metres; velocity: m/s; acceleration: m/s^2 (along the heading plus centripetal);
        yaw: heading, radians (unwrapped: continuous with the yaws the model was fitted to);
        yaw_rate: rad/s.
    """

    center: Complex
    velocity: Complex
    acceleration: Complex
    yaw: Float
    yaw_rate: Float


@dataclass(frozen=True)
class MovingTime:
    """How long a model has moved for (see :func:`moving_time`), arrays of the times' shape.

    Attributes:
        tau: at the given times, seconds (the time itself, or the stop/start time beyond it).
        reference: at the reference time (0, or the stop/start time where it stands then).
        standing: where the object stands at the given times.
    """

    tau: Float
    reference: Float
    standing: NDArray[np.bool_]


def moving_time(params: Float, tau: Float) -> MovingTime:
    """The time the models ``params`` (B, 8) have moved for at ``tau`` (B, ...) seconds from
    their reference time.

    A straight accelerating model (omega 0, accel not 0) keeps the sign ``SENSE`` of its speed
    ``v0 + accel * tau``: beyond the time the speed reaches zero (``-v0 / accel``) it stands,
    after it if the speed falls towards zero there (it braked to a stop), before it if it rises
    away from zero (it stood, then set off). Every other model moves all the time.
    """
    p = params.reshape(params.shape[0], *([1] * (np.ndim(tau) - 1)), PARAMETERS)
    tau = np.asarray(tau, np.float64)
    v0, accel, sense = p[..., V0], p[..., ACCEL], p[..., SENSE]
    clips = (accel != 0) & (p[..., OMEGA] == 0)
    zero = np.divide(-v0, accel, out=np.zeros(np.broadcast(v0, accel).shape), where=clips)
    starts = clips & (sense * accel > 0)  # stood until `zero`
    stops = clips & (sense * accel < 0)  # stands from `zero`

    def clip(t: Float) -> Float:
        return np.where(starts, np.maximum(t, zero), np.where(stops, np.minimum(t, zero), t))

    moved = clip(tau)
    return MovingTime(moved, clip(np.zeros_like(moved)), moved != tau)


def _displacement_integrals(params: Float, moved: MovingTime) -> tuple[Complex, Complex, Complex]:
    """The turn integrals F1, F2, F3 from the reference's moving time to the given one (the
    displacement of unit speed, unit acceleration, and its derivative in omega)."""
    omega = params.reshape(params.shape[0], *([1] * (moved.tau.ndim - 1)), PARAMETERS)[..., OMEGA]
    at = turn_integrals(moved.tau, omega)
    if not np.any(moved.reference):
        return at
    ref = turn_integrals(moved.reference, omega)
    return at[0] - ref[0], at[1] - ref[1], at[2] - ref[2]


def motion_state(params: Float, tau: Float) -> MotionState:
    """The state of B models ``params`` (B, 8) at ``tau`` (B,) seconds after their reference time."""
    assert params.ndim == 2 and params.shape[1] == PARAMETERS, params.shape
    moved = moving_time(params, np.asarray(tau, np.float64))
    f1, f2, _ = _displacement_integrals(params, moved)
    v0, accel, omega = params[:, V0], params[:, ACCEL], params[:, OMEGA]
    heading = params[:, THETA0] + omega * moved.tau
    center = params[:, X0] + 1j * params[:, Y0] + np.exp(1j * params[:, THETA0]) * (v0 * f1 + accel * f2)
    speed = np.where(moved.standing, 0.0, v0 + accel * moved.tau)
    direction = np.exp(1j * heading)
    return MotionState(
        center=center,
        velocity=speed * direction,
        acceleration=np.where(moved.standing, 0.0, (accel + 1j * omega * speed) * direction),
        yaw=heading + params[:, SLIP],
        yaw_rate=omega,
    )


def _center_jacobian(params: Float, integrals: tuple[Complex, Complex, Complex]) -> Complex:
    """d center / d params, (..., 8) complex, for params (B, 8) and the displacement integrals
    (B, ...) of :func:`_displacement_integrals`. Where the object stands, or stood at the
    reference, its speed is 0 at the stop (start) time, so that time's own derivatives add
    nothing."""
    f1, f2, f3 = integrals
    p = params.reshape(params.shape[0], *([1] * (f1.ndim - 1)), PARAMETERS)
    e = np.exp(1j * p[..., THETA0])
    v0, accel = p[..., V0], p[..., ACCEL]
    jac = np.zeros((*f1.shape, PARAMETERS), np.complex128)
    jac[..., X0] = 1.0
    jac[..., Y0] = 1j
    jac[..., V0] = e * f1
    jac[..., THETA0] = 1j * e * (v0 * f1 + accel * f2)
    jac[..., ACCEL] = e * f2
    jac[..., OMEGA] = 1j * e * (v0 * f2 + accel * f3)
    return jac


@dataclass(frozen=True)
class WindowFits:
    """Fits of one model to B windows.

    Attributes:
        params: (B, 8) parameter rows (layout :data:`X0` ... :data:`SENSE`; unused ones 0).
        chi2_center: (B,) weighted squared centre residuals (units of the centre noise).
        chi2_yaw: (B,) weighted squared yaw residuals (units of the yaw noise).
        covariance: (B, K, K) covariance of the model's K free parameters.
        model: the model.
    """

    params: Float
    chi2_center: Float
    chi2_yaw: Float
    covariance: Float
    model: MotionModel

    def center_variance(self, tau: Float) -> Float:
        """(B,) variance of the fitted centre (sum over x and y, m^2) at ``tau`` (B,) seconds."""
        free = list(MODEL_PARAMETERS[self.model])
        moved = moving_time(self.params, np.asarray(tau, np.float64))
        jac = _center_jacobian(self.params, _displacement_integrals(self.params, moved))[..., free]  # (B, K)
        g = np.stack([jac.real, jac.imag], axis=1)  # (B, 2, K)
        return np.einsum("bik,bkl,bil->b", g, self.covariance, g)


def _residuals(
    params: Float, tau: Float, center: Complex, yaw: Float, w_center: Float, w_yaw: Float
) -> tuple[Float, Float, Float]:
    """Weighted residuals (B, 3W) (x, y, yaw blocks), their Jacobian (B, 3W, 8) and the
    centre part of the squared residuals (B,)."""
    moved = moving_time(params, tau)
    integrals = _displacement_integrals(params, moved)
    f1, f2, _ = integrals
    jac_c = _center_jacobian(params, integrals) * w_center[..., None]
    e = np.exp(1j * params[:, None, THETA0])
    model_c = params[:, None, X0] + 1j * params[:, None, Y0]
    model_c = model_c + e * (params[:, None, V0] * f1 + params[:, None, ACCEL] * f2)
    r_c = (model_c - center) * w_center
    omega = params[:, None, OMEGA]
    heading = params[:, None, THETA0] + params[:, None, SLIP] + omega * moved.tau  # standing: omega 0
    r_y = (heading - yaw) * w_yaw
    jac_y = np.zeros((*tau.shape, PARAMETERS))
    jac_y[..., THETA0] = 1.0
    jac_y[..., SLIP] = 1.0
    jac_y[..., OMEGA] = moved.tau
    jac_y *= w_yaw[..., None]
    r = np.concatenate([r_c.real, r_c.imag, r_y], axis=1)
    jac = np.concatenate([jac_c.real, jac_c.imag, jac_y], axis=1)
    chi2_c = np.sum(np.abs(r_c) ** 2, axis=1)
    return r, jac, chi2_c


def _weighted_line(tau: Float, value: Float, weight: Float) -> tuple[Float, Float]:
    """Intercept (at tau = 0) and slope of the weighted straight-line fit of each row (B, W);
    slope 0 where the row's times do not spread."""
    sw = weight.sum(axis=1)
    tm = (weight * tau).sum(axis=1) / sw
    vm = (weight * value).sum(axis=1) / sw
    spread = (weight * (tau - tm[:, None]) ** 2).sum(axis=1)
    cross = (weight * (tau - tm[:, None]) * (value - vm[:, None])).sum(axis=1)
    slope = np.divide(cross, spread, out=np.zeros_like(cross), where=spread > 0)
    return vm - slope * tm, slope


def _start(tau: Float, center: Complex, yaw: Float, weight: Float, model: MotionModel) -> Float:
    """Start parameters: heading and turn rate from the yaws, the rest by linear least squares
    (without stops), and the sense of motion."""
    free = MODEL_PARAMETERS[model]
    p = np.zeros((len(tau), PARAMETERS))
    theta0, omega = _weighted_line(tau, yaw, weight)
    if OMEGA in free:
        p[:, OMEGA] = omega
        p[:, THETA0] = theta0
    else:
        p[:, THETA0] = (weight * yaw).sum(axis=1) / weight.sum(axis=1)
    f1, f2, _ = turn_integrals(tau, p[:, None, OMEGA])
    e = np.exp(1j * p[:, None, THETA0])
    cols = [np.ones_like(f1), np.full_like(f1, 1j), e * f1]
    if ACCEL in free:
        cols.append(e * f2)
    design = np.stack(cols, axis=-1) * weight[..., None]
    a = np.concatenate([design.real, design.imag], axis=1)
    b = np.concatenate([(center * weight).real, (center * weight).imag], axis=1)
    ata = np.einsum("bij,bik->bjk", a, a) + 1e-12 * np.eye(a.shape[-1])
    sol = np.linalg.solve(ata, np.einsum("bij,bi->bj", a, b)[..., None])[..., 0]
    p[:, X0], p[:, Y0], p[:, V0] = sol[:, 0], sol[:, 1], sol[:, 2]
    if ACCEL in free:
        p[:, ACCEL] = sol[:, 3]
    # The sense of motion: the sign of the speed at the window's mean time (forward if none).
    tm = (weight * tau).sum(axis=1) / weight.sum(axis=1)
    p[:, SENSE] = np.where(p[:, V0] + p[:, ACCEL] * tm < 0, -1.0, 1.0)
    return p


def fit_windows(
    tau: Float,
    center: Complex,
    yaw: Float,
    weight: Float,
    sigma_m: Float,
    sigma_rad: Float,
    model: MotionModel,
) -> WindowFits:
    """Weighted least-squares fits of ``model`` to B windows of W keyframes.

    Args:
        tau: (B, W) keyframe times, seconds from each window's reference time.
        center: (B, W) complex box centres x + iy, metres, world frame.
        yaw: (B, W) yaws, radians, unwrapped along each window (shortest arcs).
        weight: (B, W) 1 for the keyframes of a window, 0 for padding.
        sigma_m: (B,) centre noise per coordinate, metres; sigma_rad: (B,) yaw noise, radians.
        model: one of :data:`MOTION_MODELS`.

    Returns:
        The fits (parameters relative to each window's reference time).
    """
    assert tau.shape == center.shape == yaw.shape == weight.shape and tau.ndim == 2, tau.shape
    free = np.array(MODEL_PARAMETERS[model])
    k = len(free)
    w_center = weight / sigma_m[:, None]
    w_yaw = weight / sigma_rad[:, None]
    p = _start(tau, center, yaw, weight, model)
    r, jac, chi2_c = _residuals(p, tau, center, yaw, w_center, w_yaw)
    cost = np.einsum("bi,bi->b", r, r)
    damping = np.full(len(p), 1e-4)
    eye = np.eye(k)
    for _ in range(_ITERATIONS):
        jf = jac[..., free]
        h = np.einsum("bij,bik->bjk", jf, jf)
        g = np.einsum("bij,bi->bj", jf, r)
        scale = np.diagonal(h, axis1=1, axis2=2)[:, None, :] * eye + 1e-12 * eye
        step = -np.linalg.solve(h + damping[:, None, None] * scale, g[..., None])[..., 0]
        trial = p.copy()
        trial[:, free] += step
        r_t, jac_t, chi2_t = _residuals(trial, tau, center, yaw, w_center, w_yaw)
        cost_t = np.einsum("bi,bi->b", r_t, r_t)
        better = cost_t < cost
        p = np.where(better[:, None], trial, p)
        r = np.where(better[:, None], r_t, r)
        jac = np.where(better[:, None, None], jac_t, jac)
        chi2_c = np.where(better, chi2_t, chi2_c)
        size = np.abs(step).max(axis=1) / (1.0 + np.abs(p[:, free]).max(axis=1))
        converged = bool(np.all(size <= 1e-10))
        cost = np.where(better, cost_t, cost)
        damping = np.where(better, damping * 0.3, damping * 10.0)
        if converged:
            break
    jf = jac[..., free]
    covariance = np.linalg.pinv(np.einsum("bij,bik->bjk", jf, jf), hermitian=True)
    return WindowFits(p, chi2_c, cost - chi2_c, covariance, model)


def chi2_limit(dof: Float) -> Float:
    """The 99 % point of the chi-square distribution with ``dof`` degrees of freedom
    (Wilson-Hilferty; within 1 % of the exact value from 1 degree of freedom up)."""
    d = np.maximum(np.asarray(dof, np.float64), 1e-9)
    return d * (1.0 - 2.0 / (9.0 * d) + _GATE_Z * np.sqrt(2.0 / (9.0 * d))) ** 3


def degrees_of_freedom(model: MotionModel, count: Float) -> tuple[Float, Float]:
    """Residual degrees of freedom of the centres and of the yaws of a window of ``count``
    keyframes (the heading and turn rate are counted on the yaw side)."""
    free = MODEL_PARAMETERS[model]
    turn = OMEGA in free
    center = 2 * count - (len(free) - 1 - turn)
    return center, count - 1 - turn


@dataclass(frozen=True)
class TrackFits:
    """The fit each keyframe (anchor) of a scene's track pieces got (N anchors).

    Attributes:
        params: (N, 8) the anchor's window fit (layout as :data:`X0` ...), relative to
            ``reference_s``; rows of anchors without a fit are 0.
        reference_s: (N,) the fit's reference time, seconds on the caller's time axis.
        height: (N, 2) the fit's height line (metres at the reference time, m/s).
        window: (N, 2) first and last annotation index of the fit's window (inclusive).
        model: (N,) index into :data:`MOTION_MODELS`, -1 where no window explains the anchor.
        sigma_m: (N,) centre noise used for the anchor's class, metres.
        sigma_rad: (N,) yaw noise used for the anchor's class, radians.
    """

    params: Float
    reference_s: Float
    height: Float
    window: Int
    model: Int
    sigma_m: Float
    sigma_rad: Float

    @property
    def fitted(self) -> NDArray[np.bool_]:
        return self.model >= 0


def _windows(first: Int, last: Int, sizes: range) -> Int:
    """(M, 2) first and last index of every window of consecutive annotations of a piece whose
    size is in ``sizes`` (``first``/``last``: (N,) each annotation's piece ends)."""
    starts = np.flatnonzero(np.arange(len(first)) == first) if len(first) else np.zeros(0, np.int64)
    rows = []
    for a in starts:
        b = int(last[a])
        for lo in range(int(a), b + 1):
            for size in sizes:
                if lo + size - 1 <= b:
                    rows.append((lo, lo + size - 1))
    return np.array(rows, np.int64).reshape(-1, 2)


def _gather(windows: Int, times_s: Float, center: Complex, yaw: Float, height: Float) -> tuple:
    """Padded (M, W) arrays of the windows' keyframes: tau from each window's middle keyframe,
    centre, yaw, height and weights (1 inside the window)."""
    size = windows[:, 1] - windows[:, 0] + 1
    width = int(size.max()) if len(size) else 1
    index = windows[:, :1] + np.arange(width)[None]
    weight = (index <= windows[:, 1:2]).astype(np.float64)
    index = np.minimum(index, windows[:, 1:2])
    reference = times_s[(windows[:, 0] + windows[:, 1]) // 2]
    tau = times_s[index] - reference[:, None]
    return reference, tau, center[index], yaw[index], height[index], weight


def _polynomial_residuals(tau: Float, values: Float, degree: int) -> Float:
    """Squared residuals (B,) of least-squares polynomials of ``degree`` in ``tau`` (B, W)
    through each row of ``values`` (B, W, D), summed over the D components."""
    scale = np.maximum(np.abs(tau).max(axis=1, keepdims=True), 1e-9)  # conditioning only
    design = np.stack([(tau / scale) ** k for k in range(degree + 1)], axis=-1)  # (B, W, degree + 1)
    q, _ = np.linalg.qr(design)
    fitted = q @ (np.swapaxes(q, 1, 2) @ values)
    return np.sum((values - fitted) ** 2, axis=(1, 2))


def _pooled_by_class(
    values: Float, window_class: NDArray, moving: NDArray[np.bool_], classes: NDArray, default: float
) -> Float:
    """Per-annotation value: the lower quartile of ``values`` (one per window) over the moving
    windows of the annotation's class, or over the scene's moving windows where the class has
    too few. Windows of objects that stand are left out: offboard-smoothed labels hold a parked
    object still, so its residuals say nothing of the noise on moving ones and would drive the
    estimate to its floor. A scene with too few moving windows pools all its windows the same
    way (by class, else the scene), and one with too few windows gets ``default``."""
    out = np.full(len(classes), default)
    use = moving if moving.sum() >= MIN_NOISE_WINDOWS else np.ones(len(values), bool)
    if use.sum() < MIN_NOISE_WINDOWS:
        return out
    pooled = float(np.quantile(values[use], _NOISE_QUANTILE))
    for cls in np.unique(classes):
        mine = (window_class == cls) & use
        enough = mine.sum() >= MIN_NOISE_WINDOWS
        out[classes == cls] = np.quantile(values[mine], _NOISE_QUANTILE) if enough else pooled
    return out


def moving_annotations(times_s: Float, center: Complex, first: Int, last: Int) -> NDArray[np.bool_]:
    """(N,) whether each annotation's object moves: its centre moves at least
    :data:`MOVING_SPEED_MPS` on average between the annotations two before and two after it
    (fewer at a piece's ends), a span long enough that annotation noise of 20 cm does not make
    a standing object look moving."""
    n = len(times_s)
    idx = np.arange(n)
    lo, hi = np.maximum(idx - 2, first), np.minimum(idx + 2, last)
    span = times_s[hi] - times_s[lo]
    chord = np.abs(center[hi] - center[lo])
    return (span > 0) & (chord >= MOVING_SPEED_MPS * np.maximum(span, 1.5))


def estimate_noise(
    times_s: Float, center: Complex, yaw: Float, first: Int, last: Int, class_id: NDArray
) -> tuple[Float, Float]:
    """Per-annotation centre noise (metres per coordinate) and yaw noise (radians), from the
    residuals of low-order polynomials in time through short runs of consecutive keyframes of
    moving objects (:func:`moving_annotations`).

    Yaw: straight lines through every three consecutive yaws of a piece (1 degree of freedom;
    exact for a constant turn rate). Centre: cubics through every five consecutive centres (x
    and y: 2 degrees of freedom; exact for constant jerk, so within millimetres for constant
    turn rate and acceleration). A run counts if all its annotations move. Each is pooled by
    class as the lower quartile of the runs' residuals scaled to a variance (a run with a
    manoeuvre in it has a larger residual, noise raises all alike); a class with fewer than
    :data:`MIN_NOISE_WINDOWS` runs takes the scene's pooled value, a scene with fewer the
    defaults (:data:`DEFAULT_SIGMA_M`, :data:`DEFAULT_SIGMA_RAD`). Never below
    :data:`MIN_SIGMA_M` / :data:`MIN_SIGMA_RAD`.
    """
    classes = np.asarray(class_id)
    moving = moving_annotations(times_s, center, first, last)
    out = []
    for size, degree, values, dof, default in (
        (3, 1, yaw[:, None], 1, DEFAULT_SIGMA_RAD),
        (5, 3, np.stack([center.real, center.imag], axis=-1), 2, DEFAULT_SIGMA_M),
    ):
        windows = _windows(first, last, range(size, size + 1))
        index = windows[:, :1] + np.arange(size)[None]
        tau = times_s[index] - times_s[index[:, size // 2 : size // 2 + 1]]
        variance = _polynomial_residuals(tau, values[index], degree) / _CHI2_QUANTILE[dof]
        runs_moving = moving[index].all(axis=1)
        out.append(
            np.sqrt(_pooled_by_class(variance, classes[windows[:, 0]], runs_moving, classes, default**2))
        )
    sigma_rad, sigma_m = out
    return np.maximum(sigma_m, MIN_SIGMA_M), np.maximum(sigma_rad, MIN_SIGMA_RAD)


def fit_tracks(
    times_s: Float,
    center: Float,
    yaw: Float,
    first: Int,
    last: Int,
    sigma_m: Float,
    sigma_rad: Float,
    half_window: int = 3,
) -> TrackFits:
    """Chooses and fits a motion model for every annotation (anchor) of a scene's track pieces.

    Args:
        times_s: (N,) annotation times, seconds, sorted within each piece.
        center: (N, 3) box centres, metres, world frame.
        yaw: (N,) yaws, radians, unwrapped along each piece (shortest arcs between neighbours).
        first, last: (N,) index of the first and last annotation of each annotation's piece.
        sigma_m, sigma_rad: (N,) the centre (metres per coordinate) and yaw (radians) noise.
        half_window: windows reach at most this many keyframes to either side of an anchor.

    Returns:
        Per anchor its fit (see :class:`TrackFits` and the module docstring for the rule).
    """
    n = len(times_s)
    assert center.shape == (n, 3) and yaw.shape == (n,), (center.shape, yaw.shape)
    out = TrackFits(
        params=np.zeros((n, PARAMETERS)),
        reference_s=np.zeros(n),
        height=np.zeros((n, 2)),
        window=np.zeros((n, 2), np.int64),
        model=np.full(n, -1, np.int64),
        sigma_m=sigma_m,
        sigma_rad=sigma_rad,
    )
    windows = _windows(first, last, range(3, 2 * half_window + 2))
    if not len(windows):
        return out
    ground = center[:, 0] + 1j * center[:, 1]
    reference, tau, c, y, z, weight = _gather(windows, times_s, ground, yaw, center[:, 2])
    fits = [
        fit_windows(tau, c, y, weight, sigma_m[windows[:, 0]], sigma_rad[windows[:, 0]], model)
        for model in MOTION_MODELS
    ]
    winner, accepted = _choose_models(fits, weight.sum(axis=1))
    window_index, anchor = _best_window_per_anchor(fits, winner, accepted, windows, tau, half_window)
    params = np.stack([f.params for f in fits])[winner[window_index], window_index]
    height0, height_rate = _weighted_line(tau, z, weight)
    out.params[anchor] = params
    out.reference_s[anchor] = reference[window_index]
    out.height[anchor] = np.stack([height0, height_rate], axis=1)[window_index]
    out.window[anchor] = windows[window_index]
    out.model[anchor] = winner[window_index]
    return out


def _choose_models(fits: list[WindowFits], count: Float) -> tuple[Int, NDArray[np.bool_]]:
    """Per window (fits of every model, windows of ``count`` keyframes) the model with the
    lowest BIC (chi-square + parameters x log observations), and whether its residuals are
    consistent with the noise (centre and yaw chi-square each within their 99 % point)."""
    bic = np.stack(
        [f.chi2_center + f.chi2_yaw + len(MODEL_PARAMETERS[f.model]) * np.log(3 * count) for f in fits]
    )
    winner = np.argmin(bic, axis=0)
    dofs = [degrees_of_freedom(f.model, count) for f in fits]
    chi2_c = np.choose(winner, [f.chi2_center for f in fits])
    chi2_y = np.choose(winner, [f.chi2_yaw for f in fits])
    dof_c = np.choose(winner, [d[0] for d in dofs])
    dof_y = np.choose(winner, [d[1] for d in dofs])
    return winner, (chi2_c <= chi2_limit(dof_c)) & (chi2_y <= chi2_limit(dof_y))


def _best_window_per_anchor(
    fits: list[WindowFits],
    winner: Int,
    accepted: NDArray[np.bool_],
    windows: Int,
    tau: Float,
    half_window: int,
) -> tuple[Int, Int]:
    """For every anchor some accepted window reaches (within ``half_window`` of both its ends),
    the window whose winning fit's centre has the least variance at the anchor: (window index,
    anchor index) pairs, one per such anchor."""
    anchor = windows[:, :1] + np.arange(tau.shape[1])[None]  # (M, W) annotation index per slot
    reach = (anchor <= windows[:, 1:2]) & (anchor - windows[:, :1] <= half_window)
    reach &= (windows[:, 1:2] - anchor <= half_window) & accepted[:, None]
    w_idx, slot = np.nonzero(reach)
    if not len(w_idx):
        return w_idx, w_idx
    variance = np.empty(len(w_idx))
    for m, f in enumerate(fits):
        mine = winner[w_idx] == m
        if np.any(mine):
            rows = w_idx[mine]
            sub = WindowFits(
                f.params[rows], f.chi2_center[rows], f.chi2_yaw[rows], f.covariance[rows], f.model
            )
            count = windows[rows, 1] - windows[rows, 0] + 1
            dof_c, dof_y = degrees_of_freedom(f.model, count)
            reduced = (f.chi2_center[rows] + f.chi2_yaw[rows]) / np.maximum(dof_c + dof_y, 1)
            # The covariance scaled by the reduced chi-square where the residuals exceed the
            # noise: a window that fits worse than the noise explains carries its misfit (a
            # manoeuvre the model lacks) into its variance, so a narrower window that fits wins.
            variance[mine] = sub.center_variance(tau[rows, slot[mine]]) * np.maximum(reduced, 1.0)
    a_idx = anchor[w_idx, slot]
    order = np.lexsort((variance, a_idx))  # by anchor, least variance first
    first_of_anchor = order[np.r_[True, a_idx[order][1:] != a_idx[order][:-1]]]
    return w_idx[first_of_anchor], a_idx[first_of_anchor]
