"""The native range-image kernel (phigenesis/data/csrc/range_points.c) against the numpy path it
replaces, on the hard cases of Waymo range images, and the reader's fallback when it cannot be
built. (tests/test_waymo_convert.py runs its truth tests on both paths.)"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from phigenesis.data import native
from phigenesis.data.records import LidarSweep
from phigenesis.data.sources.waymo import convert
from phigenesis.data.sources.waymo.raw import RawFrame, RawLaser, RawLaserCalibration
from tests.test_waymo_convert import _frame_pose, _pixel_pose, rz, transform

pytestmark = pytest.mark.skipif(native.load_range_points() is None, reason="native kernel not built here")

FIELDS = (
    "points_ego",
    "origins_ego",
    "intensity",
    "elongation",
    "beam_index",
    "time_offset_micros",
    "lidar_id",
    "return_index",
)


def _image(rng: np.random.Generator, h: int, w: int, fill: float) -> np.ndarray:
    """A float32 (H, W, 4) range image: ranges in 1..70 m on ``fill`` of the pixels, 0 elsewhere,
    with NaN, +inf, -inf, negative and exactly-zero ranges planted."""
    image = np.zeros((h, w, 4), np.float32)
    hit = rng.random((h, w)) < fill
    image[..., 0] = np.where(hit, rng.uniform(1.0, 70.0, (h, w)), 0.0)
    image[..., 1] = rng.random((h, w))
    image[..., 2] = rng.random((h, w))
    if h * w >= 8:
        flat = image.reshape(-1, 4)
        picks = rng.choice(h * w, 5, replace=False)
        flat[picks, 0] = [np.nan, np.inf, -np.inf, -1.0, 0.0]
    return image


def _frame(lasers: list[RawLaser], cals: list[RawLaserCalibration]) -> RawFrame:
    return RawFrame(
        segment="segment-1",
        timestamp_micros=1_557_862_000_000_000,
        global_from_vehicle=_frame_pose(),
        camera_calibrations=[],
        laser_calibrations=cals,
        images=[],
        lasers=lasers,
        labels=None,
        where="test",
    )


def _sweeps(raw: RawFrame, monkeypatch: pytest.MonkeyPatch) -> tuple[LidarSweep, dict, LidarSweep, dict]:
    """The frame's sweep (and what it left out) through the kernel and through numpy."""
    left_native: dict[str, int] = {}
    fast = convert.lidar_sweep(raw, raw.timestamp_micros, np.eye(4), left_out=left_native)
    with monkeypatch.context() as m:
        m.setattr(convert, "load_range_points", lambda: None)
        left_numpy: dict[str, int] = {}
        slow = convert.lidar_sweep(raw, raw.timestamp_micros, np.eye(4), left_out=left_numpy)
    assert fast is not None and slow is not None
    return fast, left_native, slow, left_numpy


def _assert_same(fast: LidarSweep, slow: LidarSweep) -> None:
    for name in FIELDS:
        a, b = getattr(fast, name), getattr(slow, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.flags.c_contiguous, name
        if a.dtype.kind == "f":
            assert_allclose(
                a, b, rtol=0, atol=1e-5, err_msg=name
            )  # FMA contraction may differ in the last bit
        else:
            assert_array_equal(a, b, err_msg=name)


def test_the_kernel_gives_the_numpy_paths_sweep_on_a_rig_with_every_hard_case(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(3)
    top = RawLaserCalibration(1, transform(rz(-2.6), (1.4, 0, 2.2)), np.linspace(-0.3, 0.04, 16), -0.3, 0.04)
    front = RawLaserCalibration(2, transform(rz(0.3), (4.0, 0, 0.5)), None, -1.5, 0.5)
    side = RawLaserCalibration(3, transform(rz(1.6), (2.0, 1.0, 0.9)), None, -1.5, 0.5)
    rear = RawLaserCalibration(5, transform(rz(3.1), (-1.0, 0.0, 0.9)), None, -1.5, 0.5)
    per_pixel = _pixel_pose(7, 9, per_pixel=True)  # poses vary within columns: the numpy path
    lasers = [
        RawLaser(1, _image(rng, 16, 50, 0.8), _image(rng, 16, 50, 0.1), _pixel_pose(16, 50, False)),
        RawLaser(2, _image(rng, 20, 30, 0.05), None, None),  # sparse, one return
        RawLaser(3, np.zeros((4, 6, 4), np.float32), _image(rng, 4, 6, 0.5), None),  # empty first return
        RawLaser(5, _image(rng, 7, 9, 0.6), None, per_pixel),
    ]
    raw = _frame(lasers, [top, front, side, rear])
    fast, left_fast, slow, left_slow = _sweeps(raw, monkeypatch)
    _assert_same(fast, slow)
    assert (
        left_fast == left_slow and left_fast[convert.INVALID_POINTS] == 5 * 3
    )  # NaN, +inf and -inf in 5 images
    assert set(np.unique(fast.lidar_id)) == {0, 1, 2, 4}
    # Returns in row-major order per laser and return, as the numpy path's flatnonzero gives them.
    top_first = (fast.lidar_id == 0) & (fast.return_index == 0)
    assert np.all(np.diff(fast.beam_index[top_first].astype(int)) >= 0)


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (9, 1), (3, 2650)])
def test_tiny_and_wide_images_agree(shape: tuple[int, int], monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(sum(shape))
    h, w = shape
    image = _image(rng, h, w, 0.7)
    if h * w == 1:
        image[0, 0, 0] = 12.5
    cal = RawLaserCalibration(1, transform(rz(0.2), (1.0, 0.0, 2.0)), np.linspace(-0.3, 0.04, h), -0.3, 0.04)
    raw = _frame([RawLaser(1, image, None, _pixel_pose(h, w, False))], [cal])
    fast, _, slow, _ = _sweeps(raw, monkeypatch)
    _assert_same(fast, slow)
    if h * w == 1:  # one return, at its range from its ray's origin
        assert len(fast.points_ego) == 1
        assert_allclose(np.linalg.norm(fast.points_ego[0] - fast.origins_ego[0]), 12.5, rtol=1e-6)


def test_a_frame_without_any_return_gives_an_empty_sweep_on_both_paths(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cal = RawLaserCalibration(2, transform(rz(0.3), (4.0, 0, 0.5)), None, -1.5, 0.5)
    raw = _frame([RawLaser(2, np.zeros((5, 8, 4), np.float32), None, None)], [cal])
    fast, _, slow, _ = _sweeps(raw, monkeypatch)
    assert len(fast.points_ego) == len(slow.points_ego) == 0
    _assert_same(fast, slow)


def test_the_kernel_refuses_geometry_that_does_not_fit_the_image() -> None:
    kernel = native.load_range_points()
    assert kernel is not None
    image = np.ones((4, 6, 4), np.float32)
    image[1, 2, 0] = 0.0  # no return
    rays = [np.ones(4, np.float32), np.ones(4, np.float32)] + [np.ones((3, 6), np.float32)] * 3
    out = kernel.gather(image, *rays, np.arange(6, dtype=np.int32))
    assert set(out) == set(native.OUTPUT_FIELDS)
    assert all(len(a) == 23 for a in out.values())  # exactly the returns, not the capacity
    assert_allclose(out["points"], 3.0)  # (1 * 1 + 1 * 1) * 1 + 1 on every axis
    assert_array_equal(out["beam"], np.repeat(np.arange(4), 6)[np.arange(24) != 8])
    assert_array_equal(out["time_offset"], np.tile(np.arange(6), 4)[np.arange(24) != 8])
    with pytest.raises(ValueError, match="does not fit a 4 x 6 range image"):
        kernel.gather(image, *rays, np.zeros(5, np.int32))
    with pytest.raises(ValueError, match="C-order float32"):
        kernel.gather(image.astype(np.float64), *rays, np.zeros(6, np.int32))
    with pytest.raises(ValueError, match="int32"):
        kernel.gather(image, *rays, np.zeros(6, np.int64))


def test_without_a_compiler_the_reader_falls_back_to_numpy_with_one_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("PHIGENESIS_NATIVE_DIR", str(tmp_path / "native"))
    monkeypatch.setattr(native, "_library", None)
    monkeypatch.setattr(native, "_failure", None)
    monkeypatch.setattr(native, "_compiler", lambda: None)
    with caplog.at_level(logging.WARNING, logger="phigenesis.data.native"):
        assert native.load_range_points() is None
        assert native.load_range_points() is None
    assert [r.getMessage() for r in caplog.records] == [
        "native data kernels not available: no C compiler (cc, gcc or clang) on PATH; "
        "converting range images and testing rays against boxes with numpy, and checksumming "
        "shard rows twice"
    ]
    assert native.load_crc32c_combine() is None
    assert native.load_ray_box() is None
    cal = RawLaserCalibration(2, transform(rz(0.3), (4.0, 0, 0.5)), None, -1.5, 0.5)
    image = _image(np.random.default_rng(1), 5, 8, 0.5)
    sweep = convert.lidar_sweep(_frame([RawLaser(2, image, None, None)], [cal]), 0, np.eye(4))
    assert sweep is not None and len(sweep.points_ego) == int((image[..., 0] > 0).sum() - 1)  # +inf left out


def test_a_failed_compile_is_one_line_naming_the_compiler(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    broken = tmp_path / "broken.c"
    broken.write_text("this is not C;\n")
    monkeypatch.setenv("PHIGENESIS_NATIVE_DIR", str(tmp_path / "native"))
    monkeypatch.setattr(native, "SOURCES", (*native.SOURCES, broken))
    monkeypatch.setattr(native, "_library", None)
    monkeypatch.setattr(native, "_failure", None)
    with caplog.at_level(logging.WARNING, logger="phigenesis.data.native"):
        assert native.load_range_points() is None
    (record,) = caplog.records
    assert "failed" in record.getMessage() and "\n" not in record.getMessage()
    assert not list((tmp_path / "native").rglob("*.so"))  # nothing half-built left to load
