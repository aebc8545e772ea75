"""Rigid transforms, quaternions, cameras and upright 3D boxes (numpy, float64).

Conventions, used everywhere in the toolkit:

- A transform is a 4x4 float64 matrix named ``target_from_source``: ``p_target = T @ p_source``
  (``world_from_ego``, ``ego_from_camera``). Points are row-stacked ``(N, 3)`` arrays.
- Quaternions are ``(..., 4)`` arrays ordered ``w, x, y, z`` (Hamilton product, active rotation).
- Yaw is the rotation about +z in radians, wrapped to ``[-pi, pi)``.
- Cameras use OpenCV axes (x right, y down, z forward); a pixel coordinate ``(u, v)`` has u along
  the width, and integer coordinates are pixel centres as in OpenCV (the top-left pixel's centre is
  ``(0, 0)``, its footprint ``[-0.5, 0.5)^2``).
- Distortion is OpenCV's five-coefficient model ``k1, k2, p1, p2, k3``.
- Boxes are upright: centre ``(x, y, z)`` in metres, size ``(length, width, height)`` along the box's
  own x, y, z, and a yaw about +z.

Every function accepts leading batch dimensions where the docstring says ``...``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

#: Below this norm a quaternion is treated as "no rotation given" and normalises to identity.
QUATERNION_ZERO_NORM = 1e-12
#: OpenCV camera axes expressed in a "looking along +x" body frame (x forward, y left, z up, the
#: axes of Waymo's camera frame): camera x (right) = -y, camera y (down) = -z, camera z = +x.
BODY_FROM_OPENCV = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=np.float64)
#: Points closer to the camera plane than this (metres along +z) are not projected.
MIN_PROJECTION_DEPTH_M = 1e-6


# --------------------------------------------------------------------------------------------
# Angles


def wrap_angle(angle_rad: ArrayLike) -> F64:
    """Wraps angles to ``[-pi, pi)``; exact multiples of pi map to ``-pi``."""
    a = np.asarray(angle_rad, dtype=np.float64)
    wrapped = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    # np.mod can return 2*pi for tiny negative inputs through rounding; fold it back.
    return np.where(wrapped >= np.pi, wrapped - 2.0 * np.pi, wrapped)


def angle_difference(a_rad: ArrayLike, b_rad: ArrayLike) -> F64:
    """Signed shortest difference ``a - b`` in ``[-pi, pi)``, so that ``b + diff == a`` modulo 2 pi."""
    return wrap_angle(np.asarray(a_rad, dtype=np.float64) - np.asarray(b_rad, dtype=np.float64))


# --------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z)

IDENTITY_QUATERNION = np.array([1.0, 0.0, 0.0, 0.0])


def quaternion_normalize(q: ArrayLike) -> F64:
    """Unit quaternion ``(..., 4)``; a zero (or non-finite) quaternion becomes the identity."""
    q = np.asarray(q, dtype=np.float64)
    assert q.shape[-1] == 4, q.shape
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    ok = np.isfinite(norm) & (norm > QUATERNION_ZERO_NORM)
    safe = np.where(ok, norm, 1.0)
    return np.where(ok, q / safe, IDENTITY_QUATERNION)


def quaternion_canonical(q: ArrayLike) -> F64:
    """Normalised quaternion with ``w >= 0`` (q and -q are the same rotation)."""
    q = quaternion_normalize(q)
    return np.where(q[..., :1] < 0.0, -q, q)


def quaternion_product_entries(a: Sequence[Any], b: Sequence[Any]) -> list[Any]:
    """The 4 components (w, x, y, z) of the Hamilton product ``a * b`` of quaternions given as their
    components, for any array type with arithmetic (numpy here, torch in the Stage 1 model)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ]


def quaternion_multiply(a: ArrayLike, b: ArrayLike) -> F64:
    """Hamilton product ``a * b`` of ``(..., 4)`` quaternions: rotate by b first, then by a."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.stack(quaternion_product_entries(np.moveaxis(a, -1, 0), np.moveaxis(b, -1, 0)), axis=-1)


def quaternion_conjugate(q: ArrayLike) -> F64:
    """Conjugate (the inverse rotation for a unit quaternion)."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotation_entries(w: Any, x: Any, y: Any, z: Any) -> list[Any]:
    """The 9 entries (row-major) of the rotation matrix of the unit quaternion (w, x, y, z), for
    any array type with arithmetic (numpy here, torch in the rasterizer)."""
    return [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]


def quaternion_to_matrix(q: ArrayLike) -> F64:
    """Rotation matrices ``(..., 3, 3)`` from quaternions ``(..., 4)`` (normalised first)."""
    m = np.stack(rotation_entries(*np.moveaxis(quaternion_normalize(q), -1, 0)), axis=-1)
    return m.reshape(*m.shape[:-1], 3, 3)


def matrix_to_quaternion(rotation: ArrayLike) -> F64:
    """Quaternions ``(..., 4)`` with ``w >= 0`` from rotation matrices ``(..., 3, 3)``.

    Uses the largest of the four diagonal combinations (Shepperd), so it stays accurate near
    180-degree rotations where ``w`` is small.
    """
    r = np.asarray(rotation, dtype=np.float64)
    assert r.shape[-2:] == (3, 3), r.shape
    m00, m01, m02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    m10, m11, m12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    m20, m21, m22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    # Four candidates; each row of `cands` is 4*(component)*q for the pivot component.
    t = np.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        axis=-1,
    )
    pivot = np.argmax(t, axis=-1)
    cands = np.stack(
        [
            np.stack([t[..., 0], m21 - m12, m02 - m20, m10 - m01], axis=-1),
            np.stack([m21 - m12, t[..., 1], m01 + m10, m02 + m20], axis=-1),
            np.stack([m02 - m20, m01 + m10, t[..., 2], m12 + m21], axis=-1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, t[..., 3]], axis=-1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4 components)
    q = np.take_along_axis(cands, pivot[..., None, None], axis=-2)[..., 0, :]
    return quaternion_canonical(q)


def quaternion_slerp(q0: ArrayLike, q1: ArrayLike, fraction: ArrayLike) -> F64:
    """Spherical interpolation along the shorter arc, ``fraction`` in [0, 1] (extrapolates outside).

    q1 is sign-flipped when ``dot(q0, q1) < 0`` so the path is the short one; nearly equal
    quaternions fall back to normalised linear interpolation, which is exact to first order there.
    """
    q0 = quaternion_normalize(q0)
    q1 = quaternion_normalize(q1)
    f = np.asarray(fraction, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-8
    safe_sin = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - f, np.sin((1.0 - f) * theta) / safe_sin)
    w1 = np.where(near, f, np.sin(f * theta) / safe_sin)
    return quaternion_normalize(w0 * q0 + w1 * q1)


def yaw_to_quaternion(yaw_rad: ArrayLike) -> F64:
    """Quaternion ``(..., 4)`` of a rotation by ``yaw`` about +z."""
    half = 0.5 * np.asarray(yaw_rad, dtype=np.float64)
    zeros = np.zeros_like(half)
    return np.stack([np.cos(half), zeros, zeros, np.sin(half)], axis=-1)


def quaternion_yaw(q: ArrayLike) -> F64:
    """Heading of the rotated +x axis projected on the xy plane, in ``[-pi, pi)``.

    For a pure yaw rotation this is the yaw itself; for rotations with pitch and roll it is the
    heading of the body's forward axis (what a box heading means).
    """
    r = quaternion_to_matrix(q)
    return wrap_angle(np.arctan2(r[..., 1, 0], r[..., 0, 0]))


def matrix_yaw(rotation: ArrayLike) -> F64:
    """Heading of the rotated +x axis of rotation matrices ``(..., 3, 3)`` (or 4x4), ``[-pi, pi)``."""
    r = np.asarray(rotation, dtype=np.float64)
    return wrap_angle(np.arctan2(r[..., 1, 0], r[..., 0, 0]))


def rotation_z(yaw_rad: ArrayLike) -> F64:
    """Rotation matrices ``(..., 3, 3)`` about +z."""
    yaw = np.asarray(yaw_rad, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(yaw), np.ones_like(yaw)
    m = np.stack([c, -s, zeros, s, c, zeros, zeros, zeros, ones], axis=-1)
    return m.reshape(*yaw.shape, 3, 3)


# --------------------------------------------------------------------------------------------
# Rigid transforms (4x4)


def euler_zyx_to_matrix(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> F64:
    """Rotation ``(..., 3, 3)`` = Rz(yaw) @ Ry(pitch) @ Rx(roll) (3-2-1 Euler angles, as Waymo)."""
    roll, pitch, yaw = np.broadcast_arrays(
        np.asarray(roll_rad, np.float64), np.asarray(pitch_rad, np.float64), np.asarray(yaw_rad, np.float64)
    )
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    out = np.empty((*roll.shape, 3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def matrix_to_euler_zyx(rotation: ArrayLike) -> tuple[F64, F64, F64]:
    """(roll, pitch, yaw) radians of a rotation ``(..., 3, 3)``; inverse of :func:`euler_zyx_to_matrix`
    for pitch in (-pi/2, pi/2)."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = -np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    yaw = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return roll, pitch, yaw


def make_transform(rotation: ArrayLike, translation: ArrayLike) -> F64:
    """4x4 transforms ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    batch = np.broadcast_shapes(r.shape[:-2], t.shape[:-1])
    out = np.zeros((*batch, 4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def pose_to_transform(translation: ArrayLike, quaternion: ArrayLike) -> F64:
    """4x4 ``target_from_source`` from the source origin's position and orientation in target."""
    return make_transform(quaternion_to_matrix(quaternion), translation)


def pose_at_time(times: ArrayLike, poses: ArrayLike, quaternions: ArrayLike, t: float) -> F64:
    """The 4x4 pose at time ``t`` of a track of ``poses`` (K, 4, 4) at strictly increasing ``times``
    (K,) whose rotations are ``quaternions`` (K, 4) wxyz: position linear and rotation slerped
    between the two times around ``t``, a recorded pose exactly at its time, the nearest end's pose
    held outside the recorded span."""
    times = np.asarray(times)
    poses = np.asarray(poses, dtype=np.float64)
    j = int(np.searchsorted(times, t))
    if j < len(times) and times[j] == t:
        return poses[j].copy()
    if j == 0 or j == len(times):
        return poses[0 if j == 0 else -1].copy()
    i = j - 1
    s = (t - times[i]) / (times[j] - times[i])
    q = quaternion_slerp(quaternions[i], quaternions[j], s)
    return pose_to_transform((1 - s) * poses[i, :3, 3] + s * poses[j, :3, 3], q)


def yaw_pose_to_transform(translation: ArrayLike, yaw_rad: ArrayLike) -> F64:
    """4x4 transforms of upright poses (rotation about +z only)."""
    return make_transform(rotation_z(yaw_rad), translation)


def invert_transform(transform: ArrayLike) -> F64:
    """Inverse of rigid 4x4 transforms ``(..., 4, 4)`` (uses R^T, exact for rotations)."""
    t = np.asarray(transform, dtype=np.float64)
    assert t.shape[-2:] == (4, 4), t.shape
    r_inv = np.swapaxes(t[..., :3, :3], -1, -2)
    return make_transform(r_inv, -np.einsum("...ij,...j->...i", r_inv, t[..., :3, 3]))


def transform_points(transform: ArrayLike, points: ArrayLike) -> F64:
    """Applies a 4x4 ``target_from_source`` to points ``(..., N, 3)`` in the source frame."""
    t = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    assert t.shape[-2:] == (4, 4) and p.shape[-1] == 3, (t.shape, p.shape)
    return p @ np.swapaxes(t[..., :3, :3], -1, -2) + t[..., None, :3, 3]


def transform_directions(transform: ArrayLike, directions: ArrayLike) -> F64:
    """Rotates direction vectors ``(..., N, 3)`` (no translation)."""
    t = np.asarray(transform, dtype=np.float64)
    return np.asarray(directions, dtype=np.float64) @ np.swapaxes(t[..., :3, :3], -1, -2)


def orthonormalize_rotation(rotation: ArrayLike) -> F64:
    """Nearest proper rotation (SVD) to a nearly orthonormal 3x3 matrix, e.g. one read as float32."""
    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, -1] *= d[..., None]
    return u @ vt


# --------------------------------------------------------------------------------------------
# Cameras: pinhole with OpenCV distortion (k1, k2, p1, p2, k3)


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> F64:
    """3x3 OpenCV camera matrix K."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _as_distortion(distortion: ArrayLike | None) -> F64:
    d = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64).reshape(-1)
    assert d.shape == (5,), f"distortion must be (k1, k2, p1, p2, k3), got shape {d.shape}"
    return d


def _radial(r2: F64, d: F64) -> F64:
    return 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))


def distort_normalized(xy: ArrayLike, distortion: ArrayLike | None) -> F64:
    """Applies OpenCV distortion to normalised image coordinates ``(..., 2)`` (x/z, y/z)."""
    d = _as_distortion(distortion)
    xy = np.asarray(xy, dtype=np.float64)
    if not d.any():
        return xy.copy()
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = _radial(r2, d)
    xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x)
    yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y
    return np.stack([xd, yd], axis=-1)


def max_monotonic_radius(distortion: ArrayLike | None, search_limit: float = 10.0) -> float:
    """Largest undistorted radius r (normalised units) up to which ``r * radial(r^2)`` increases.

    Beyond it the radial model folds back and far-off-axis points would land inside the image;
    projection marks them invalid. Returns ``search_limit`` if no turning point is found below it.
    """
    d = _as_distortion(distortion)
    # d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6, a cubic in s = r^2.
    # Solved in u = 1/s (u^3 + 3 k1 u^2 + 5 k2 u + 7 k3, monic), so a tiny k3 neither overflows the
    # companion matrix nor swamps the small roots; the smallest positive s is the largest positive u.
    roots = np.roots([1.0, 3 * d[0], 5 * d[1], 7 * d[4]])
    real = roots[np.isreal(roots)].real if roots.size else np.empty(0)
    positive = real[real > 0]
    if positive.size == 0 or positive.max() <= 1.0 / search_limit**2:
        return float(search_limit)
    return float(min(1.0 / np.sqrt(positive.max()), search_limit))


def project_points(
    points_camera: ArrayLike,
    intrinsics: ArrayLike,
    distortion: ArrayLike | None = None,
    min_depth_m: float = MIN_PROJECTION_DEPTH_M,
) -> tuple[F64, NDArray[np.bool_]]:
    """Projects camera-frame points ``(N, 3)`` (OpenCV axes, metres) to pixels.

    Returns ``(uv, valid)``: ``uv`` is ``(N, 2)`` float64 pixel coordinates (u along the width),
    NaN where invalid; ``valid`` is ``(N,)`` and is False for points behind or on the camera plane
    (``z <= min_depth_m``), non-finite points, and points beyond the distortion model's monotonic
    radius (where the polynomial folds back). Points outside the image bounds stay valid; use
    :func:`in_image` for that test.
    """
    p = np.asarray(points_camera, dtype=np.float64)
    assert p.ndim == 2 and p.shape[1] == 3, p.shape
    k = np.asarray(intrinsics, dtype=np.float64)
    assert k.shape == (3, 3), k.shape
    d = _as_distortion(distortion)
    z = p[:, 2]
    # Column-wise tests: a reduction along the short axis is several times slower.
    valid = np.isfinite(p[:, 0]) & np.isfinite(p[:, 1]) & np.isfinite(z) & (z > min_depth_m)
    safe_z = np.where(valid, z, 1.0)
    # Invalid rows (inf, NaN) are zeroed so that no inf * 0 reaches the arithmetic below.
    xy = np.where(valid[:, None], p[:, :2] / safe_z[:, None], 0.0)
    if np.any(d != 0.0):
        r2 = xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1]
        valid &= r2 <= max_monotonic_radius(d) ** 2
        xy = distort_normalized(xy, d)
    uv = np.empty_like(xy)
    uv[:, 0] = k[0, 0] * xy[:, 0] + k[0, 1] * xy[:, 1] + k[0, 2]
    uv[:, 1] = k[1, 1] * xy[:, 1] + k[1, 2]
    uv[~valid] = np.nan
    return uv, valid


def in_image(uv: ArrayLike, width: int, height: int) -> NDArray[np.bool_]:
    """True for pixel coordinates inside ``[-0.5, W - 0.5) x [-0.5, H - 0.5)`` (pixel footprints)."""
    uv = np.asarray(uv, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return (
            (uv[..., 0] >= -0.5)
            & (uv[..., 0] < width - 0.5)
            & (uv[..., 1] >= -0.5)
            & (uv[..., 1] < height - 0.5)
        )


def undistort_normalized(xy_distorted: ArrayLike, distortion: ArrayLike | None, iterations: int = 20) -> F64:
    """Inverts :func:`distort_normalized` with Newton's method on ``(..., 2)`` coordinates.

    Converges to machine precision inside the monotonic region within a few iterations; the
    result for points that no undistorted point maps to (outside the folded model) is the last
    iterate, clamped to the monotonic radius.
    """
    d = _as_distortion(distortion)
    target = np.asarray(xy_distorted, dtype=np.float64)
    if not np.any(d != 0.0):
        return target.copy()
    k1, k2, p1, p2, k3 = d
    r_max = max_monotonic_radius(d)
    xy = target.copy()
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = _radial(r2, d)
        dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
        fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - target[..., 0]
        fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - target[..., 1]
        j00 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
        j01 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
        j10 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
        j11 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
        det = j00 * j11 - j01 * j10
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step_x = (j11 * fx - j01 * fy) / det
        step_y = (j00 * fy - j10 * fx) / det
        xy = xy - np.stack([step_x, step_y], axis=-1)
        r = np.linalg.norm(xy, axis=-1, keepdims=True)
        xy = np.where(r > r_max, xy * (r_max / np.maximum(r, 1e-300)), xy)
    return xy


def unproject_pixels(
    uv: ArrayLike,
    intrinsics: ArrayLike,
    distortion: ArrayLike | None = None,
    depth_m: ArrayLike | None = None,
) -> F64:
    """Pixels ``(N, 2)`` to camera-frame rays or points ``(N, 3)`` (OpenCV axes).

    Without ``depth_m`` returns rays with ``z = 1`` (so a z-depth d gives the point ``d * ray``);
    with ``depth_m`` (``(N,)``, metres along +z) returns the 3D points.
    """
    uv = np.asarray(uv, dtype=np.float64)
    assert uv.ndim == 2 and uv.shape[1] == 2, uv.shape
    k = np.asarray(intrinsics, dtype=np.float64)
    y_d = (uv[:, 1] - k[1, 2]) / k[1, 1]
    x_d = (uv[:, 0] - k[0, 2] - k[0, 1] * y_d) / k[0, 0]
    xy = undistort_normalized(np.stack([x_d, y_d], axis=-1), distortion)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    if depth_m is None:
        return rays
    depth = np.asarray(depth_m, dtype=np.float64).reshape(-1)
    assert depth.shape == (len(uv),), (depth.shape, uv.shape)
    return rays * depth[:, None]


def pixel_grid(width: int, height: int) -> F64:
    """Pixel-centre coordinates ``(H * W, 2)`` as (u, v), row-major (v slowest)."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)


# --------------------------------------------------------------------------------------------
# Upright 3D boxes

#: Corner signs in box coordinates (Waymo order): bottom face then top face, counter-clockwise
#: seen from above, starting at (+l/2, +w/2, -h/2).
BOX_CORNER_SIGNS = np.array(
    [
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, -1],
        [1, -1, -1],
        [1, 1, 1],
        [-1, 1, 1],
        [-1, -1, 1],
        [1, -1, 1],
    ],
    dtype=np.float64,
)

#: Corner index pairs of the 12 box edges, for drawing.
BOX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))


def box_corners(center: ArrayLike, size_lwh: ArrayLike, yaw_rad: ArrayLike) -> F64:
    """Corners ``(..., 8, 3)`` of upright boxes (order: :data:`BOX_CORNER_SIGNS`)."""
    return rotated_box_corners(center, size_lwh, rotation_z(yaw_rad))


def rotated_box_corners(center: ArrayLike, size_lwh: ArrayLike, rotation: ArrayLike) -> F64:
    """Corners ``(..., 8, 3)`` of boxes with any orientation ``rotation`` ``(..., 3, 3)`` (box -> frame)."""
    c = np.asarray(center, dtype=np.float64)
    s = np.asarray(size_lwh, dtype=np.float64)
    local = 0.5 * s[..., None, :] * BOX_CORNER_SIGNS  # (..., 8, 3)
    return local @ np.swapaxes(np.asarray(rotation, dtype=np.float64), -1, -2) + c[..., None, :]


def points_in_box(
    points: ArrayLike, center: ArrayLike, size_lwh: ArrayLike, yaw_rad: float, margin_m: float = 0.0
) -> NDArray[np.bool_]:
    """Mask ``(N,)`` of points ``(N, 3)`` inside one upright box enlarged by ``margin_m`` per side.

    Points on the boundary count as inside.
    """
    p = np.asarray(points, dtype=np.float64)
    assert p.ndim == 2 and p.shape[1] == 3, p.shape
    local = (p - np.asarray(center, dtype=np.float64)) @ rotation_z(yaw_rad)  # world->box: R^T p
    half = 0.5 * np.asarray(size_lwh, dtype=np.float64) + margin_m
    # A nanometre of slack: the product's last bit depends on how many rows BLAS gets, and a
    # point on a face must not be inside in one call and outside in another.
    return np.all(np.abs(local) <= half + 1e-9, axis=1)


def points_in_boxes(
    points: ArrayLike, centers: ArrayLike, sizes_lwh: ArrayLike, yaws_rad: ArrayLike, margin_m: float = 0.0
) -> NDArray[np.int64]:
    """Index ``(N,)`` of the first box ``(M, ...)`` containing each point, or -1 if none."""
    p = np.asarray(points, dtype=np.float64)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    sizes = np.asarray(sizes_lwh, dtype=np.float64).reshape(-1, 3)
    yaws = np.asarray(yaws_rad, dtype=np.float64).reshape(-1)
    out = np.full(len(p), -1, dtype=np.int64)
    # Coarse sphere test first: only points near a box go through the exact test. The sphere must
    # hold the margin-enlarged box (half-diagonal of half + margin), with slack for rounding.
    radii = np.linalg.norm(0.5 * sizes + margin_m, axis=1) * (1.0 + 1e-9) + 1e-9
    for i in range(len(centers)):
        near = np.flatnonzero(np.sum((p - centers[i]) ** 2, axis=1) <= radii[i] ** 2)
        if near.size == 0:
            continue
        inside = near[points_in_box(p[near], centers[i], sizes[i], yaws[i], margin_m)]
        inside = inside[out[inside] < 0]
        out[inside] = i
    return out
