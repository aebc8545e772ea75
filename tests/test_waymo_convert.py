"""Waymo raw records -> scene model: matrices, Euler poses, range images, cameras, boxes and frames.

Every expected value is computed in the test from the formulas of the Waymo Open Dataset's own
code (https://github.com/waymo-research/waymo-open-dataset: the camera model in
``src/waymo_open_dataset/wdl_limited/camera/camera_model.cc``, range images to points in
``utils/range_image_utils.py``, boxes in ``label.proto``), written out independently of the library: the
elementary rotations, the range-image polar coordinates, the camera projection with distortion,
the upright box corners.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from phigenesis import geometry
from phigenesis import taxonomy as tx
from phigenesis.data.records import CameraCalibration, CameraImage
from phigenesis.data.sources.waymo import convert, protos
from phigenesis.data.sources.waymo.raw import (
    RawCameraCalibration,
    RawCameraImage,
    RawFrame,
    RawLabels,
    RawLaser,
    RawLaserCalibration,
    WaymoFormatError,
)

# --------------------------------------------------------------------------------------------
# Independent helpers


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return rz(yaw) @ ry(pitch) @ rx(roll)


def transform(rot: np.ndarray, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = t
    return out


def apply(t: np.ndarray, p) -> np.ndarray:
    return (t @ np.append(np.asarray(p, np.float64), 1.0))[:3]


def angles(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(min_value=lo, max_value=hi, allow_nan=False, allow_infinity=False)


# --------------------------------------------------------------------------------------------
# protos.decode_matrix / encode_matrix


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


@pytest.mark.parametrize("shape", [(7,), (3, 5), (2, 3, 4)])
def test_decode_matrix_float_round_trip_bit_exact(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    values = (rng.standard_normal(shape) * 1e3).astype(np.float32)
    flat = values.reshape(-1)
    specials = np.array([np.nan, np.inf, -np.inf, -0.0, -1.5, 1e-40, -3.4e38], np.float32)
    flat[: len(specials)] = specials[: flat.size]
    # A NaN with a payload keeps its bits too.
    flat[-1] = np.array([0x7FC12345], np.uint32).view(np.float32)[0]
    blob = protos.encode_matrix(values)
    out = protos.decode_matrix(blob, np.float32, "range image")
    assert out.dtype == np.float32 and out.shape == shape
    assert_array_equal(_bits(out), _bits(values))
    # The protobuf parser reads the same message.
    msg = protos.MatrixFloat()
    msg.ParseFromString(blob)
    assert list(msg.shape.dims) == list(shape)
    assert_array_equal(_bits(np.asarray(msg.data, np.float32)), _bits(values).reshape(-1))


def test_decode_matrix_float64_input_is_stored_as_float32() -> None:
    values = np.array([[1.0 / 3.0, -2.0e-7], [123456.789, np.pi]])
    out = protos.decode_matrix(protos.encode_matrix(values), np.float32, "m")
    assert_array_equal(out, values.astype(np.float32))


@pytest.mark.parametrize("shape", [(6,), (2, 3), (2, 2, 3)])
def test_decode_matrix_int32_round_trip(shape: tuple[int, ...]) -> None:
    n = int(np.prod(shape))
    values = np.array([-1, 0, 1, -(2**31), 2**31 - 1, -123456, 7, 99, -5, 3, 2, 1][:n], np.int32).reshape(
        shape
    )
    out = protos.decode_matrix(protos.encode_matrix(values), np.int32, "camera projection")
    assert out.dtype == np.int32
    assert_array_equal(out, values)


def _shape_field(dims: list[int], packed: bool) -> bytes:
    # dims < 128: one varint byte each; packed (0x0A, length, values) or one 0x08 tag per value.
    inner = bytes([0x0A, len(dims)]) + bytes(dims) if packed else b"".join(bytes([0x08, d]) for d in dims)
    return bytes([0x12, len(inner)]) + inner


def test_decode_matrix_unpacked_floats_use_the_fallback() -> None:
    values = np.array([[1.5, -2.25, np.inf], [0.0, -0.0, 3.0e5]], np.float32)
    data = b"".join(b"\x0d" + struct.pack("<f", v) for v in values.reshape(-1))
    blob = data + _shape_field([2, 3], packed=False)
    # The protobuf class reads the unpacked encoding (proto2 parsers accept both).
    msg = protos.MatrixFloat()
    msg.ParseFromString(blob)
    assert list(msg.data) == values.reshape(-1).tolist()
    out = protos.decode_matrix(blob, np.float32, "unpacked")
    assert out.shape == (2, 3)
    assert_array_equal(_bits(out), _bits(values))


@pytest.mark.parametrize("shape_first", [False, True])
@pytest.mark.parametrize("packed_dims", [False, True])
def test_decode_matrix_packed_floats_any_field_order(shape_first: bool, packed_dims: bool) -> None:
    values = np.arange(12, dtype=np.float32).reshape(2, 2, 3) - 5.5
    raw = values.tobytes()
    data = bytes([0x0A, len(raw)]) + raw
    shape = _shape_field([2, 2, 3], packed=packed_dims)
    blob = shape + data if shape_first else data + shape
    assert_array_equal(protos.decode_matrix(blob, np.float32, "m"), values)


@pytest.mark.parametrize("dtype", [np.float32, np.int32])
def test_decode_matrix_size_mismatch_names_what(dtype: type) -> None:
    msg = (protos.MatrixFloat if dtype == np.float32 else protos.MatrixInt32)()
    msg.data.extend([1, 2, 3, 4, 5])
    msg.shape.dims.extend([2, 3])
    with pytest.raises(ValueError, match=r"LiDAR TOP return 1.*\[2, 3\].*5 values"):
        protos.decode_matrix(msg.SerializeToString(), dtype, "LiDAR TOP return 1")
    no_shape = (protos.MatrixFloat if dtype == np.float32 else protos.MatrixInt32)()
    no_shape.data.extend([1, 2])
    with pytest.raises(ValueError, match="pixel pose"):
        protos.decode_matrix(no_shape.SerializeToString(), dtype, "pixel pose")


def test_decode_matrix_two_packed_runs_concatenate() -> None:
    # Protobuf parsers concatenate repeated packed runs of one field; so must the decoder.
    a, b = np.array([1.0, 2.0], np.float32), np.array([3.0, 4.0, 5.0, 6.0], np.float32)
    blob = bytes([0x0A, 8]) + a.tobytes() + bytes([0x0A, 16]) + b.tobytes() + _shape_field([3, 2], False)
    assert_array_equal(
        protos.decode_matrix(blob, np.float32, "m"), np.arange(1, 7, dtype=np.float32).reshape(3, 2)
    )


@pytest.mark.parametrize("dtype", [np.float32, np.int32])
def test_decode_matrix_negative_dims_name_what(dtype: type) -> None:
    """Corrupt dims whose product still equals the value count (-2 * -2 == 4) must be reported as a
    bad matrix naming ``what``, like any other shape mismatch."""
    msg = (protos.MatrixFloat if dtype == np.float32 else protos.MatrixInt32)()
    msg.data.extend([1, 2, 3, 4])
    msg.shape.dims.extend([-2, -2])
    with pytest.raises(ValueError, match="LiDAR FRONT return 2"):
        protos.decode_matrix(msg.SerializeToString(), dtype, "LiDAR FRONT return 2")


def test_decode_matrix_garbage_names_what() -> None:
    with pytest.raises(ValueError, match="flow image"):
        protos.decode_matrix(b"\x0a\x7f\x00", np.float32, "flow image")


# --------------------------------------------------------------------------------------------
# geometry: Euler angles as Waymo's per-pixel poses use them


@settings(max_examples=80, deadline=None)
@given(angles(-3.1, 3.1), angles(-1.5, 1.5), angles(-3.1, 3.1))
def test_euler_zyx_round_trip_and_elementary_product(roll: float, pitch: float, yaw: float) -> None:
    m = geometry.euler_zyx_to_matrix(roll, pitch, yaw)
    assert m.shape == (3, 3)
    assert_allclose(m, rz(yaw) @ ry(pitch) @ rx(roll), atol=1e-12)
    assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m) == pytest.approx(1.0, abs=1e-12)
    r, p, y = geometry.matrix_to_euler_zyx(m)
    assert_allclose([r, p, y], [roll, pitch, yaw], atol=1e-9)


def test_euler_zyx_batched() -> None:
    rng = np.random.default_rng(3)
    a = rng.uniform(-1.4, 1.4, (4, 5, 3))
    m = geometry.euler_zyx_to_matrix(a[..., 0], a[..., 1], a[..., 2])
    assert m.shape == (4, 5, 3, 3)
    assert_allclose(m[2, 3], rpy(*a[2, 3]), atol=1e-12)
    r, p, y = geometry.matrix_to_euler_zyx(m)
    assert_allclose(np.stack([r, p, y], -1), a, atol=1e-9)


# --------------------------------------------------------------------------------------------
# LiDAR range images


def _incl_uniform(lo: float, hi: float, h: int) -> np.ndarray:
    """Reference: incl[i] = lo + (i + 0.5) / H * (hi - lo), then reversed (row 0 highest)."""
    return np.array([lo + (i + 0.5) / h * (hi - lo) for i in range(h)])[::-1]


def _azimuth(e: np.ndarray, w: int) -> np.ndarray:
    """Reference: azimuth[c] = pi * (1 - (2c + 1) / W) - atan2(E[1,0], E[0,0])."""
    return np.array([np.pi * (1.0 - (2 * c + 1) / w) for c in range(w)]) - np.arctan2(e[1, 0], e[0, 0])


def _sensor_point(r: float, az: float, incl: float) -> np.ndarray:
    return np.array([r * np.cos(az) * np.cos(incl), r * np.sin(az) * np.cos(incl), r * np.sin(incl)])


def _range_image(rng: np.random.Generator, h: int, w: int, valid: float) -> np.ndarray:
    ri = np.zeros((h, w, 4), np.float32)
    ri[..., 0] = rng.uniform(1.0, 75.0, (h, w))
    drop = rng.random((h, w)) > valid
    ri[..., 0][drop] = rng.choice(np.array([0.0, -1.0], np.float32), int(drop.sum()))
    ri[..., 1] = rng.uniform(0, 1, (h, w))
    ri[..., 2] = rng.uniform(0, 2, (h, w))
    ri[..., 3] = rng.integers(0, 2, (h, w))
    return ri


def _expected_points(ri: np.ndarray, incl: np.ndarray, az: np.ndarray, e: np.ndarray, ret: int) -> dict:
    out: dict[str, list] = {k: [] for k in ("points", "rows", "cols", "intensity", "elongation", "ret")}
    h, w, _ = ri.shape
    for i in range(h):
        for j in range(w):
            r = float(ri[i, j, 0])
            if r <= 0:
                continue
            out["points"].append(apply(e, _sensor_point(r, az[j], incl[i])))
            out["rows"].append(i)
            out["cols"].append(j)
            out["intensity"].append(ri[i, j, 1])
            out["elongation"].append(ri[i, j, 2])
            out["ret"].append(ret)
    return {k: np.array(v) for k, v in out.items()}


def _concat(*parts: dict) -> dict:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def test_laser_points_non_top_uniform_inclinations() -> None:
    rng = np.random.default_rng(5)
    h, w = 9, 16
    lo, hi = -np.pi / 2, np.pi / 6
    e = transform(rz(np.radians(30.0)), (4.1, -0.3, 0.7))
    cal = RawLaserCalibration(2, e, None, lo, hi)
    r1 = _range_image(rng, h, w, 0.7)
    r2 = _range_image(rng, h, w, 0.3)
    r1[0, 0, 0], r1[0, 1, 0], r2[3, 3, 0] = 0.0, -1.0, -1.0
    got = convert.laser_points(RawLaser(2, r1, r2, None), cal, np.eye(4))

    incl, az = _incl_uniform(lo, hi, h), _azimuth(e, w)
    want = _concat(_expected_points(r1, incl, az, e, 0), _expected_points(r2, incl, az, e, 1))
    n = len(want["rows"])
    assert n == int((r1[..., 0] > 0).sum() + (r2[..., 0] > 0).sum())
    assert 0 < n < 2 * h * w
    assert got["points"].shape == (n, 3)
    assert_allclose(got["points"], want["points"], atol=2e-5, rtol=0)
    assert_allclose(got["origins"], np.tile(e[:3, 3], (n, 1)), atol=1e-6)
    assert_array_equal(got["beam"], want["rows"])
    assert got["beam"].dtype == np.uint16
    assert_array_equal(got["return_index"], want["ret"])
    assert got["return_index"].dtype == np.uint8
    assert_array_equal(got["intensity"], want["intensity"].astype(np.float32))
    assert_array_equal(got["elongation"], want["elongation"].astype(np.float32))
    # Columns sweep a 100 ms scan: centre of column c at ((c + 0.5) / W - 0.5) * 100 ms from mid-scan.
    assert_array_equal(got["time_offset"], np.round(((want["cols"] + 0.5) / w - 0.5) * 1e5).astype(np.int32))
    # Meaning of the convention: the vehicle-frame azimuth of a column is pi * (1 - (2c + 1) / W)
    # whatever the mounting yaw (column 0 behind, the middle forward, decreasing clockwise).
    rel = got["points"] - e[:3, 3]
    vehicle_az = np.arctan2(rel[:, 1], rel[:, 0])
    assert_allclose(  # float32 points: about 1e-7 relative
        geometry.angle_difference(vehicle_az, np.pi * (1 - (2 * want["cols"] + 1) / w)), 0.0, atol=2e-6
    )
    # Ranges are kept: distance from the sensor equals the stored range.
    rng_all = np.concatenate([r1[..., 0][r1[..., 0] > 0], r2[..., 0][r2[..., 0] > 0]])
    assert_allclose(np.linalg.norm(rel, axis=1), rng_all, rtol=5e-7)


def test_column_helpers() -> None:
    e = transform(rz(0.4), (0, 0, 0))
    assert_allclose(
        convert.column_azimuths(e, 4),
        [3 * np.pi / 4 - 0.4, np.pi / 4 - 0.4, -np.pi / 4 - 0.4, -3 * np.pi / 4 - 0.4],
    )
    assert_array_equal(convert.column_time_offsets_micros(4), [-37500, -12500, 12500, 37500])
    assert convert.column_time_offsets_micros(4).dtype == np.int32


def test_explicit_beam_inclinations_are_reversed() -> None:
    values = np.array([-0.31, -0.2, -0.05, 0.0, 0.045])  # stored lowest beam first
    cal = RawLaserCalibration(1, np.eye(4), values, -0.31, 0.045)
    assert_array_equal(convert.beam_inclinations(cal, 5), values[::-1])
    uniform = RawLaserCalibration(2, np.eye(4), None, -1.0, 0.5)
    assert_allclose(convert.beam_inclinations(uniform, 3), [0.25, -0.25, -0.75])
    # In points: row 0 is the highest beam.
    ri = np.zeros((5, 4, 4), np.float32)
    ri[:, 2, 0] = 10.0
    pts = convert.laser_points(RawLaser(1, ri, None, None), cal, np.eye(4))
    assert_array_equal(pts["beam"], np.arange(5))
    assert_allclose(pts["points"][:, 2], 10.0 * np.sin(values[::-1]), atol=2e-6)


def test_beam_inclination_count_mismatch() -> None:
    cal = RawLaserCalibration(1, np.eye(4), np.linspace(-0.3, 0.04, 4), -0.3, 0.04)
    with pytest.raises(WaymoFormatError, match=r"LiDAR TOP: 4 beam inclinations.*5 rows"):
        convert.beam_inclinations(cal, 5)
    ri = np.ones((5, 3, 4), np.float32)
    with pytest.raises(WaymoFormatError, match="4 beam inclinations"):
        convert.laser_points(RawLaser(1, ri, None, None), cal, np.eye(4))
    pose = np.zeros((5, 2, 6), np.float32)
    good = RawLaserCalibration(1, np.eye(4), np.linspace(-0.3, 0.04, 5), -0.3, 0.04)
    with pytest.raises(WaymoFormatError, match="pixel pose"):
        convert.laser_points(RawLaser(1, ri, None, pose), good, np.eye(4))


@pytest.fixture(autouse=True, params=["native", "numpy"])
def range_kernel(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Every test here on both range-image paths: the native kernel (where it builds) and numpy."""
    from phigenesis.data.native import load_range_points

    if request.param == "numpy":
        monkeypatch.setattr(convert, "load_range_points", lambda: None)
    elif load_range_points() is None:
        pytest.skip("the native range-image kernel is not built here")
    return str(request.param)


GLOBAL_T = np.array([41234.567, -38765.4321, 123.45])


def _frame_pose() -> np.ndarray:
    return transform(rpy(0.012, -0.021, 1.2), GLOBAL_T)


def _pixel_pose(h: int, w: int, per_pixel: bool) -> np.ndarray:
    """Per-pixel vehicle poses around the frame pose, moving ~1.5 m and turning over the scan."""
    col = np.linspace(-0.5, 0.5, w)[None, :]
    row = np.linspace(-0.5, 0.5, h)[:, None] if per_pixel else np.zeros((h, 1))
    pose = np.zeros((h, w, 6))
    pose[..., 0] = 0.012 + 0.004 * col + 0.01 * row
    pose[..., 1] = -0.021 - 0.003 * col + 0.02 * row
    pose[..., 2] = 1.2 + 0.05 * col - 0.03 * row
    pose[..., 3] = GLOBAL_T[0] + 1.5 * col + 0.2 * row
    pose[..., 4] = GLOBAL_T[1] - 0.8 * col + 0.3 * row
    pose[..., 5] = GLOBAL_T[2] + 0.05 * col - 0.1 * row
    return pose.astype(np.float32)


@pytest.mark.parametrize("per_pixel", [False, True], ids=["per-column", "per-pixel"])
def test_top_laser_with_pixel_poses(per_pixel: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(8)
    h, w = 6, 20
    incl_stored = np.sort(rng.uniform(-0.31, 0.045, h))
    e = transform(rpy(0.002, -0.01, np.radians(-148.0)), (1.43, 0.0, 2.18))
    cal = RawLaserCalibration(1, e, incl_stored, -0.31, 0.045)
    r1 = _range_image(rng, h, w, 0.8)
    r2 = _range_image(rng, h, w, 0.25)
    pose = _pixel_pose(h, w, per_pixel)
    frame_pose = _frame_pose()

    calls: list[int] = []
    original = geometry.euler_zyx_to_matrix

    def spy(roll, pitch, yaw):  # counts the poses turned into matrices
        calls.append(int(np.size(roll)))
        return original(roll, pitch, yaw)

    monkeypatch.setattr(convert.geometry, "euler_zyx_to_matrix", spy)
    vehicle_from_global = geometry.invert_transform(frame_pose)
    got = convert.laser_points(RawLaser(1, r1, r2, pose), cal, vehicle_from_global)

    n1, n2 = int((r1[..., 0] > 0).sum()), int((r2[..., 0] > 0).sum())
    # The fast path converts one pose per column, once for both returns; the per-pixel path one
    # per point of each return.
    assert calls == ([w] if not per_pixel else [n1, n2])

    inv_frame = np.linalg.inv(frame_pose)
    incl, az = incl_stored[::-1], _azimuth(e, w)
    points, origins, rows = [], [], []
    for ri in (r1, r2):
        for i in range(h):
            for j in range(w):
                r = float(ri[i, j, 0])
                if r <= 0:
                    continue
                p = pose[i, j].astype(np.float64)
                t_pix = transform(rz(p[2]) @ ry(p[1]) @ rx(p[0]), p[3:])
                chain = inv_frame @ t_pix @ e
                points.append(apply(chain, _sensor_point(r, az[j], incl[i])))
                origins.append(chain[:3, 3])
                rows.append(i)
    points, origins = np.array(points), np.array(origins)
    assert got["points"].shape == (n1 + n2, 3)
    assert_allclose(got["points"], points, atol=1e-4, rtol=0)
    assert_allclose(got["origins"], origins, atol=1e-4, rtol=0)
    assert_array_equal(got["beam"], rows)
    assert_array_equal(got["return_index"], [0] * n1 + [1] * n2)
    # The ego moved: the ray origins differ along the scan by more than the tolerance.
    assert np.linalg.norm(np.ptp(origins, axis=0)) > 0.5
    # Without the pixel poses the points would be off by metres (the test is not vacuous).
    static = convert.laser_points(RawLaser(1, r1, r2, None), cal, vehicle_from_global)
    assert np.abs(static["points"] - points).max() > 0.5


def test_top_fast_and_slow_paths_agree() -> None:
    rng = np.random.default_rng(9)
    h, w = 5, 12
    e = transform(rz(np.radians(-148.0)), (1.43, 0.0, 2.18))
    cal = RawLaserCalibration(1, e, np.linspace(-0.3, 0.04, h), -0.3, 0.04)
    r1 = _range_image(rng, h, w, 0.9)
    r1[h - 1, w - 1, 0] = 0.0
    pose = _pixel_pose(h, w, per_pixel=False)
    # A different pose at the one pixel without a return makes the per-pixel path run, with the
    # same poses at every point.
    bumped = pose.copy()
    bumped[h - 1, w - 1, 3] += 100.0
    vehicle_from_global = geometry.invert_transform(_frame_pose())
    fast = convert.laser_points(RawLaser(1, r1, None, pose), cal, vehicle_from_global)
    slow = convert.laser_points(RawLaser(1, r1, None, bumped), cal, vehicle_from_global)
    assert len(fast["points"]) == int((r1[..., 0] > 0).sum())
    assert_allclose(slow["points"], fast["points"], atol=2e-5)
    assert_allclose(slow["origins"], fast["origins"], atol=2e-5)


# --------------------------------------------------------------------------------------------
# Cameras

INTRINSIC = np.array([2055.25, 2051.75, 960.7, 640.3, -0.33, 0.12, 0.0009, -0.0012, -0.021])


def _waymo_project(p_cam: np.ndarray, intrinsic: np.ndarray) -> np.ndarray:
    """Waymo's camera model (x forward, y left, z up), pixel 0 = left edge of the first pixel."""
    f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 = intrinsic
    x, y, z = p_cam
    u_n, v_n = -y / x, -z / x
    r2 = u_n * u_n + v_n * v_n
    rd = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    assert 0.8 <= rd <= 1.2
    u_nd = u_n * rd + 2 * p1 * u_n * v_n + p2 * (r2 + 2 * u_n * u_n)
    v_nd = v_n * rd + p1 * (r2 + 2 * v_n * v_n) + 2 * p2 * u_n * v_n
    return np.array([f_u * u_nd + c_u, f_v * v_nd + c_v])


def _raw_camera(name: int = 2, direction: int = 2) -> RawCameraCalibration:
    extrinsic = transform(rpy(0.004, 0.03, np.radians(42.0)), (1.52, 0.25, 2.11))
    return RawCameraCalibration(name, INTRINSIC.copy(), extrinsic, 1920, 1280, direction)


def test_camera_calibration_matches_waymo_projection() -> None:
    raw = _raw_camera()
    cal = convert.camera_calibration(raw)
    assert cal.name == "FRONT_LEFT"
    assert (cal.width, cal.height) == (1920, 1280)
    assert_array_equal(
        cal.intrinsics, [[2055.25, 0.0, 960.7 - 0.5], [0.0, 2051.75, 640.3 - 0.5], [0.0, 0.0, 1.0]]
    )
    assert_array_equal(cal.distortion, [-0.33, 0.12, 0.0009, -0.0012, -0.021])
    # OpenCV axes: camera z is the Waymo camera's x (forward), camera x its -y, camera y its -z.
    r = raw.vehicle_from_camera[:3, :3]
    assert_allclose(cal.ego_from_camera[:3, :3], np.stack([-r[:, 1], -r[:, 2], r[:, 0]], axis=1), atol=0)
    assert_array_equal(cal.ego_from_camera[:3, 3], raw.vehicle_from_camera[:3, 3])

    # Points in the Waymo camera frame, moved to the vehicle frame; both models project them.
    p_cam = np.array(
        [[20.0, 3.0, -1.0], [7.5, -2.5, 1.2], [45.0, 0.0, 0.0], [3.0, 1.1, -0.9], [12.0, -4.0, -2.0]]
    )
    p_vehicle = np.array([apply(raw.vehicle_from_camera, p) for p in p_cam])
    want = np.array([_waymo_project(p, INTRINSIC) for p in p_cam])
    in_cv = geometry.transform_points(geometry.invert_transform(cal.ego_from_camera), p_vehicle)
    uv, valid = geometry.project_points(in_cv, cal.intrinsics, cal.distortion)
    assert valid.all()
    assert_allclose(uv + 0.5, want, atol=1e-9, rtol=0)
    # The optical axis lands on the principal point: Waymo (c_u, c_v) is OpenCV (c_u - 0.5, c_v - 0.5).
    assert_allclose(want[2], INTRINSIC[2:4], atol=1e-9)


@pytest.mark.parametrize(
    ("code", "name"),
    [
        (0, "unknown"),
        (1, "top_to_bottom"),
        (2, "left_to_right"),
        (3, "bottom_to_top"),
        (4, "right_to_left"),
        (5, "global"),
        (17, "unknown"),
    ],
)
def test_rolling_shutter_direction_codes(code: int, name: str) -> None:
    assert convert.camera_calibration(_raw_camera(direction=code)).readout_direction == name


def test_camera_calibration_without_size() -> None:
    raw = _raw_camera(name=3)
    raw.height = 0
    with pytest.raises(WaymoFormatError, match=r"FRONT_RIGHT.*1920x0"):
        convert.camera_calibration(raw)


def _timed_image(direction: str, w: int = 8, h: int = 6) -> CameraImage:
    cal = CameraCalibration(
        "FRONT", w, h, geometry.intrinsic_matrix(10, 10, 4, 3), np.zeros(5), np.eye(4), direction
    )
    return CameraImage(
        cal,
        1_025_000,
        np.eye(4),
        None,
        trigger_micros=1_000_000,
        shutter_micros=3000.0,
        readout_micros=44000.0,
    )


@pytest.mark.parametrize("direction", ["left_to_right", "right_to_left", "top_to_bottom", "bottom_to_top"])
def test_pixel_time_micros_follows_waymo(direction: str) -> None:
    w, h = 8, 6
    img = _timed_image(direction, w, h)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = u + 0.5, v + 0.5  # Waymo pixel coordinates of the OpenCV pixel centres
    line = {
        "left_to_right": x / w,
        "right_to_left": (w - x) / w,
        "top_to_bottom": y / h,
        "bottom_to_top": (h - y) / h,
    }[direction]
    assert_allclose(img.pixel_time_micros(u, v), 1_000_000 + 1500.0 + 44000.0 * line, atol=1e-6)


def test_pixel_time_micros_edges_and_global() -> None:
    w = 8
    img = _timed_image("left_to_right", w)
    start = 1_000_000 + 1500.0
    assert img.pixel_time_micros(np.array(-0.5), np.array(0.0)) == pytest.approx(start)
    assert img.pixel_time_micros(np.array(0.0), np.array(2.0)) == pytest.approx(start + 44000.0 * 0.5 / w)
    assert img.pixel_time_micros(np.array(w - 0.5), np.array(0.0)) == pytest.approx(start + 44000.0)
    rl = _timed_image("right_to_left", w)
    assert rl.pixel_time_micros(np.array(w - 1.0), np.array(0.0)) == pytest.approx(start + 44000.0 * 0.5 / w)
    for direction in ("global", "unknown"):
        t = _timed_image(direction).pixel_time_micros(np.array([0.0, 7.0]), np.array([0.0, 5.0]))
        assert_array_equal(t, [1_025_000.0, 1_025_000.0])


# --------------------------------------------------------------------------------------------
# Boxes


def test_boxes_in_a_tilted_vehicle_frame() -> None:
    pose = transform(rpy(np.radians(2.0), np.radians(3.0), np.radians(25.0)), (812.5, -301.25, 14.0))
    box = np.array(
        [
            [10.0, 2.0, 0.9, 4.5, 1.9, 1.6, 0.3],
            [-5.0, 7.0, 1.0, 0.8, 0.7, 1.8, -2.9],
            [30.0, -12.0, 2.5, 0.2, 0.9, 0.9, 3.1],
            [3.0, -3.0, 0.8, 1.9, 0.6, 1.7, 1.4],
            [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, -1.0],
        ]
    )
    speed = np.array([[8.0, 1.0, 0.1], [1.2, -0.3, 0.0], [0.0, 0.0, 0.0], [4.0, 4.0, 0.2], [0.5, 0.0, 0.0]])
    accel = np.array([[0.5, -0.1, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0], [-1.0, 0.3, 0.0], [0.0, 0.0, 1.0]])
    labels = RawLabels(
        ids=["veh_1", "ped_2", "sign_3", "cyc_4", "unk_5"],
        types=np.array([1, 2, 3, 4, 0], np.int32),
        box=box,
        speed=speed,
        accel=accel,
        num_lidar_points=np.array([120, 30, -1, 55, 0], np.int32),
        num_top_lidar_points=np.array([100, 20, -1, 50, 0], np.int32),
    )
    out = convert.boxes(labels, pose)
    assert out.track_id == ["veh_1", "ped_2", "sign_3", "cyc_4", "unk_5"]
    assert out.class_id.tolist() == [
        tx.CLASS_IDS["car"],
        tx.CLASS_IDS["person"],
        tx.CLASS_IDS["traffic_sign"],
        tx.CLASS_IDS["rider"],
        255,
    ]
    assert_array_equal(out.size_lwh, box[:, 3:6])
    assert_array_equal(out.num_lidar_points, [120, 30, -1, 55, 0])
    rot = pose[:3, :3]
    assert_allclose(out.center_world, box[:, :3] @ rot.T + pose[:3, 3], atol=1e-9)
    assert_allclose(out.velocity_world, speed @ rot.T, atol=1e-12)
    assert_allclose(out.acceleration_world, accel @ rot.T, atol=1e-12)

    signs = [
        (1, 1, -1),
        (-1, 1, -1),
        (-1, -1, -1),
        (1, -1, -1),
        (1, 1, 1),
        (-1, 1, 1),
        (-1, -1, 1),
        (1, -1, 1),
    ]
    corners = out.corners_world()
    assert corners.shape == (5, 8, 3)
    for k, (cx, cy, cz, length, width, height, heading) in enumerate(box):
        c, s = np.cos(heading), np.sin(heading)
        for i, (sx, sy, sz) in enumerate(signs):
            x, y, z = sx * length / 2, sy * width / 2, sz * height / 2
            in_vehicle = (cx + c * x - s * y, cy + s * x + c * y, cz + z)
            assert_allclose(corners[k, i], apply(pose, in_vehicle), atol=1e-9)
        forward = rot @ np.array([c, s, 0.0])
        assert out.yaw_world[k] == pytest.approx(np.arctan2(forward[1], forward[0]), abs=1e-12)
    # The boxes keep the vehicle's tilt: their up axis is the vehicle's, not the world's.
    up = geometry.quaternion_to_matrix(out.orientation_world)[:, :, 2]
    assert_allclose(up, np.tile(rot[:, 2], (5, 1)), atol=1e-12)
    assert np.degrees(np.arccos(rot[2, 2])) > 3.0


def test_boxes_empty() -> None:
    out = convert.boxes(RawLabels.empty(), np.eye(4))
    assert len(out) == 0
    assert out.corners_world().shape == (0, 8, 3)


# --------------------------------------------------------------------------------------------
# Camera panoptic labels

SEM = {2: "car", 20: "road", 25: "sky", 21: "road", 9: "person", 23: "sidewalk", 15: "pole"}


#: A real 8 x 4 JPEG: images are checked against their calibration's size.
JPEG_8X4 = cv2.imencode(".jpg", np.zeros((4, 8, 3), np.uint8))[1].tobytes()


def _panoptic_image(png: bytes | None, mapping: dict[int, int], divisor: int = 1000) -> RawCameraImage:
    return RawCameraImage(
        name=1,
        jpeg=JPEG_8X4,
        global_from_vehicle=np.eye(4),
        velocity_linear=np.zeros(3),
        velocity_angular=np.zeros(3),
        pose_timestamp=1.0,
        shutter=0.003,
        trigger_time=0.98,
        readout_done_time=1.03,
        panoptic_label=png,
        panoptic_label_divisor=divisor,
        instance_to_global=mapping,
    )


def _panoptic() -> tuple[np.ndarray, bytes]:
    codes = np.array(
        [
            [2001, 2001, 2002, 20000, 20000, 25000, 25000, 0],
            [2001, 2002, 2002, 20000, 21000, 25000, 0, 0],
            [9005, 9005, 20000, 21000, 21000, 1000, 1000, 28000],
            [9005, 23000, 23000, 15000, 20000, 20000, 2007, 2007],
        ],
        np.uint16,
    )
    ok, buf = cv2.imencode(".png", codes)
    assert ok
    return codes, buf.tobytes()


def test_camera_labels_panoptic_mapping() -> None:
    codes, png = _panoptic()
    mapping = {1: 17, 2: 4, 5: 33, 7: 60000}
    labels = convert.camera_labels(_panoptic_image(png, mapping), 4, 8, "seg frame 3")
    assert labels is not None
    want_sem = np.full(codes.shape, 255, np.uint8)
    for code, name in SEM.items():
        want_sem[codes // 1000 == code] = tx.CLASS_IDS[name]
    assert_array_equal(labels.semantic, want_sem)
    # 0 undefined, 1 ego vehicle, 28 static: ignored.
    assert (labels.semantic[codes // 1000 == 0] == 255).all()
    assert (labels.semantic[codes // 1000 == 1] == 255).all()
    assert labels.semantic[1, 4] == tx.ROAD  # lane marker
    want_inst = np.vectorize(lambda c: {0: 0, **mapping}[int(c) % 1000])(codes)
    assert labels.instance.dtype == np.uint16
    assert_array_equal(labels.instance, want_inst)
    assert labels.instance[0, 2] == 4 and labels.instance[3, 7] == 60000 and labels.instance[0, 3] == 0

    # Without a mapping the local ids are kept.
    local = convert.camera_labels(_panoptic_image(png, {}), 4, 8, "w")
    assert_array_equal(local.instance, codes % 1000)

    assert convert.camera_labels(_panoptic_image(None, {}), 4, 8, "w") is None


def test_camera_labels_errors() -> None:
    _, png = _panoptic()
    with pytest.raises(WaymoFormatError, match=r"seg frame 3.*shape \(4, 8\).*\(5, 8\)"):
        convert.camera_labels(_panoptic_image(png, {}), 5, 8, "seg frame 3")
    with pytest.raises(
        WaymoFormatError, match=r"seg frame 3: panoptic_label holds 9 bytes that are not a PNG"
    ):
        convert.camera_labels(_panoptic_image(b"not a png", {}), 4, 8, "seg frame 3")
    with pytest.raises(WaymoFormatError, match="divisor 0"):
        convert.camera_labels(_panoptic_image(png, {}, divisor=0), 4, 8, "seg frame 3")
    with pytest.raises(
        WaymoFormatError, match=r"maps local id 1 to 70000, not an instance id in \[0, 65535\]"
    ):
        convert.camera_labels(_panoptic_image(png, {1: 70000}), 4, 8, "seg frame 3")


# --------------------------------------------------------------------------------------------
# Frames


def _small_cam(name: int, direction: int = 2) -> RawCameraCalibration:
    return RawCameraCalibration(
        name,
        np.array([10.0, 10.0, 4.0, 2.0, 0, 0, 0, 0, 0]),
        transform(rz(0.1 * name), (1.0, 0, 2.0)),
        8,
        4,
        direction,
    )


def _raw_frame(images: list[int], cams: list[int], lasers: bool = True) -> RawFrame:
    key = 1_557_862_000_123_456
    pose = transform(rpy(0.01, -0.02, 0.7), GLOBAL_T)
    _, png = _panoptic()
    raw_images = []
    for name in images:
        im = _panoptic_image(png, {1: 5}) if name == 1 else _panoptic_image(None, {})
        im.name = name
        im.global_from_vehicle = transform(rpy(0.01, -0.02, 0.71), GLOBAL_T + np.array([0.4, 0.1, 0.0]))
        im.pose_timestamp = key * 1e-6 + 0.0412
        im.trigger_time = key * 1e-6 + 0.027
        im.shutter = 0.003
        im.readout_done_time = key * 1e-6 + 0.027 + 0.003 + 0.044
        raw_images.append(im)
    rng = np.random.default_rng(2)
    laser_list, laser_cals = [], []
    if lasers:
        laser_cals = [
            RawLaserCalibration(2, transform(rz(0.3), (4.0, 0, 0.5)), None, -1.5, 0.5),
            RawLaserCalibration(
                1, transform(rz(-2.6), (1.4, 0, 2.2)), np.linspace(-0.3, 0.04, 3), -0.3, 0.04
            ),
        ]
        laser_list = [
            RawLaser(2, _range_image(rng, 4, 6, 0.5), None, None),
            RawLaser(
                1, _range_image(rng, 3, 10, 0.8), _range_image(rng, 3, 10, 0.2), _pixel_pose(3, 10, False)
            ),
        ]
    labels = RawLabels(
        ["a"],
        np.array([1], np.int32),
        np.array([[5.0, 1.0, 0.5, 4.0, 2.0, 1.5, 0.2]]),
        np.zeros((1, 3)),
        np.zeros((1, 3)),
        np.array([10], np.int32),
        np.array([9], np.int32),
    )
    return RawFrame(
        segment="segment-123_456",
        timestamp_micros=key,
        global_from_vehicle=pose,
        camera_calibrations=[_small_cam(c) for c in cams],
        laser_calibrations=laser_cals,
        images=raw_images,
        lasers=laser_list,
        labels=labels,
        where="/data/seg.tfrecord (record 3 at byte 4096)",
    )


def test_frame_conversion() -> None:
    raw = _raw_frame(images=[1], cams=[4, 1])
    origin = GLOBAL_T + np.array([1.0, -2.0, 0.5])
    out = convert.frame(raw, 3, origin)
    assert out.scene_id == "segment-123_456" and out.frame_index == 3
    assert out.timestamp_micros == raw.timestamp_micros + 50_000
    assert out.source_timestamp_micros == raw.timestamp_micros
    # World = global shifted by the origin, rotation unchanged.
    assert_array_equal(out.world_from_ego[:3, :3], raw.global_from_vehicle[:3, :3])
    assert_allclose(out.world_from_ego[:3, 3], raw.global_from_vehicle[:3, 3] - origin, atol=1e-9)
    assert_allclose(out.world_from_ego[:3, 3], [-1.0, 2.0, -0.5], atol=1e-9)

    assert [c.name for c in out.cameras] == ["FRONT", "SIDE_LEFT"]
    front, side = out.cameras
    assert front.image_bytes == JPEG_8X4
    im = raw.images[0]
    assert front.timestamp_micros == round(im.pose_timestamp * 1e6)
    assert_allclose(front.world_from_ego[:3, 3], im.global_from_vehicle[:3, 3] - origin, atol=1e-9)
    assert_array_equal(front.world_from_ego[:3, :3], im.global_from_vehicle[:3, :3])
    assert front.trigger_micros == raw.timestamp_micros + 27_000
    # Epoch seconds in float64 resolve ~0.2 us: the durations are exact to about that.
    assert front.shutter_micros == pytest.approx(3000.0, abs=1e-6)
    assert front.readout_micros == pytest.approx(44000.0, abs=0.5)
    assert front.labels is not None and front.labels.semantic.shape == (4, 8)
    assert front.calibration.readout_direction == "left_to_right"
    assert side.image_bytes is None
    assert side.timestamp_micros == out.timestamp_micros
    assert_array_equal(side.world_from_ego, out.world_from_ego)
    assert side.calibration.name == "SIDE_LEFT"

    # Boxes are in the shifted world.
    assert_allclose(out.boxes.center_world[0], apply(out.world_from_ego, [5.0, 1.0, 0.5]), atol=1e-9)

    # LiDAR: TOP first, then FRONT, in the vehicle frame, ids = laser code - 1.
    lidar = out.lidar
    assert lidar is not None and lidar.timestamp_micros == out.timestamp_micros
    vfg = geometry.invert_transform(raw.global_from_vehicle)
    top = convert.laser_points(raw.lasers[1], raw.laser_calibrations[1], vfg)
    front_l = convert.laser_points(raw.lasers[0], raw.laser_calibrations[0], vfg)
    assert_array_equal(lidar.lidar_id, [0] * len(top["beam"]) + [1] * len(front_l["beam"]))
    assert_allclose(lidar.points_ego, np.concatenate([top["points"], front_l["points"]]), atol=1e-5)
    assert_array_equal(lidar.return_index, np.concatenate([top["return_index"], front_l["return_index"]]))


def test_frame_without_lasers_has_no_sweep() -> None:
    out = convert.frame(_raw_frame(images=[], cams=[1], lasers=False), 0, np.zeros(3))
    assert out.lidar is None
    assert [c.image_bytes for c in out.cameras] == [None]


def test_frame_image_without_calibration() -> None:
    raw = _raw_frame(images=[1, 3], cams=[1, 2])
    with pytest.raises(WaymoFormatError) as err:
        convert.frame(raw, 0, np.zeros(3))
    msg = str(err.value)
    assert "FRONT_RIGHT" in msg
    assert raw.where in msg


def test_frame_laser_without_calibration_names_the_frame() -> None:
    raw = _raw_frame(images=[], cams=[1])
    raw.laser_calibrations = raw.laser_calibrations[:1]  # FRONT only; TOP has range images
    with pytest.raises(WaymoFormatError) as err:
        convert.frame(raw, 0, np.zeros(3))
    assert raw.where in str(err.value) and "TOP" in str(err.value)


def test_frame_duplicate_images() -> None:
    raw = _raw_frame(images=[1, 1], cams=[1])
    with pytest.raises(WaymoFormatError, match="two images of camera FRONT"):
        convert.frame(raw, 0, np.zeros(3))
