"""Memory bounded by the input, and files refused by name (issue 53, items 3, 8 and 9): what a PLY
header claims is checked against the file before anything is allocated; trajectory and rig files are
regular files of at most 1 MiB whose times fit int64 microseconds."""

from __future__ import annotations

import json
import os
import threading
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from phigenesis.export.ply import REQUIRED, PlyError, read_ply, scene_from_ply
from phigenesis.infer.generate import TrajectoryError, TrajectoryFrame, load_trajectory_file
from phigenesis.infer.insert import MAX_ASSET_GAUSSIANS, AssetError, load_asset
from phigenesis.infer.rigs import RigError, load_rig_file

#: A crafted small input may make a reader allocate at most this much (tracemalloc peak, bytes).
SMALL_PEAK = 32 << 20
#: The recorded rig a trajectory file is read against: frame at 1000 us, two cameras.
RIG = TrajectoryFrame(1000, np.eye(4), np.stack([np.eye(4)] * 2), np.array([1000, 1010]))
EYE = np.eye(4).tolist()


def traced_peak(fn: Callable[[], Any]) -> tuple[BaseException | None, int]:
    """(the exception ``fn`` raised or None, the peak bytes Python and numpy allocated meanwhile)."""
    tracemalloc.start()
    try:
        fn()
        error = None
    except BaseException as e:  # returned for the test to judge
        error = e
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return error, peak


def gaussian_ply(path: Path, count: int | str, data_bytes: int = 14_000, before: str = "") -> Path:
    """A 3DGS PLY header claiming ``count`` vertices, followed by ``data_bytes`` zero bytes."""
    header = f"ply\nformat binary_little_endian 1.0\n{before}element vertex {count}\n"
    header += "".join(f"property float {p}\n" for p in REQUIRED) + "end_header\n"
    path.write_bytes(header.encode() + bytes(data_bytes))
    return path


def returns_without_blocking(fn: Callable[[], Any], fifo: Path) -> BaseException | None:
    """The exception ``fn`` raises (None if none); fails the test if ``fn`` blocks on ``fifo``
    (after unblocking it by opening the FIFO for writing)."""
    outcome: dict[str, BaseException] = {}

    def run() -> None:
        try:
            fn()
        except BaseException as e:  # returned for the test to judge
            outcome["error"] = e

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(20)
    if thread.is_alive():
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(20)
        pytest.fail(f"reading {fifo} blocked until a writer opened it")
    return outcome.get("error")


# --------------------------------------------------------------------------------------------
# 3DGS PLY assets: claimed rows against the file's size


@pytest.mark.parametrize("count", [10**7, 10**9])
def test_a_ply_claiming_more_rows_than_its_bytes_names_the_element_and_both_sizes(
    tmp_path: Path, count: int
) -> None:
    path = gaussian_ply(tmp_path / "claims.ply", count)
    error, peak = traced_peak(lambda: read_ply(path))
    assert isinstance(error, PlyError)
    row = 4 * len(REQUIRED)
    assert str(error) == (
        f"{path}: truncated: element 'vertex' claims {count} rows of {row} bytes ({count * row} bytes) "
        "but only 14000 bytes follow"
    )
    assert peak < SMALL_PEAK
    with pytest.raises(AssetError, match="truncated: element 'vertex' claims 10000000 rows"):
        load_asset(gaussian_ply(tmp_path / "at_max.ply", MAX_ASSET_GAUSSIANS), class_name="car")


@pytest.mark.parametrize("count", ["1" + "0" * 30, "9" * 5000])
def test_an_absurd_row_count_is_refused_without_parsing_it_to_the_end(tmp_path: Path, count: str) -> None:
    path = gaussian_ply(tmp_path / "absurd.ply", count)
    error, peak = traced_peak(lambda: scene_from_ply(path))
    assert isinstance(error, PlyError)
    assert str(error).startswith(f"{path}: element 'vertex' claims {count[:8]}")
    assert str(error).endswith("rows, more than 1000000000000000")
    assert peak < SMALL_PEAK


def test_an_element_before_the_vertices_that_claims_too_much_is_named(tmp_path: Path) -> None:
    path = gaussian_ply(
        tmp_path / "camera.ply", 2, 2 * 56, before="element camera 5000000\nproperty double fx\n"
    )
    with pytest.raises(PlyError, match=r"element 'camera' claims 5000000 rows of 8 bytes \(40000000 bytes\)"):
        read_ply(path)


def test_a_time_origin_beyond_int64_microseconds_is_refused(tmp_path: Path) -> None:
    path = gaussian_ply(tmp_path / "origin.ply", 1, 56)
    text = path.read_bytes().replace(
        b"element", b"comment time_origin_micros 99999999999999999999\nelement", 1
    )
    path.write_bytes(text)
    with pytest.raises(
        PlyError, match=r"origin\.ply: comment time_origin_micros 99999999999999999999 is beyond"
    ):
        scene_from_ply(path)


# --------------------------------------------------------------------------------------------
# Trajectory, path and rig files


def write_trajectory(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc))
    return path


def test_a_trajectory_that_is_not_a_small_regular_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryError, match=r"^/dev/zero: not a regular file; a trajectory file must be"):
        load_trajectory_file("/dev/zero", 1, RIG, 1000)
    with pytest.raises(TrajectoryError, match=rf"^{tmp_path}: a folder"):
        load_trajectory_file(tmp_path, 1, RIG, 1000)
    big = tmp_path / "big.json"
    big.write_text(" " * (1 << 20) + "{}")
    with pytest.raises(TrajectoryError, match=r"big\.json: larger than 1048576 bytes"):
        load_trajectory_file(big, 1, RIG, 1000)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    error = returns_without_blocking(lambda: load_trajectory_file(fifo, 1, RIG, 1000), fifo)
    assert isinstance(error, TrajectoryError) and str(error).startswith(f"{fifo}: not a regular file")


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"frames": [{"timestamp_micros": 2**63, "world_from_ego": EYE}]},
         r"frames\[0\]\.timestamp_micros: 9223372036854775808 is not below 4611686018427387904"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[str(x) for x in r] for r in EYE]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is '1\.0', not a finite number"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": EYE, "speed": 3}]},
         r"frames\[0\]: unknown key 'speed'; the keys are timestamp_micros, world_from_ego"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": EYE}], "fps": 10},
         r"unknown key 'fps'; the keys are frames"),
        ({"frames": [{"timestamp_micros": "5000", "world_from_ego": EYE}]},
         r"frames\[0\]\.timestamp_micros: '5000' is not an integer"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[True, 0, 0, 0], *EYE[1:]]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is True, not a finite number"),
        ({"frames": [{"timestamp_micros": 5000, "world_from_ego": [[10**400, 0, 0, 0], *EYE[1:]]}]},
         r"frames\[0\]\.world_from_ego: \[0\]\[0\] is 1000"),
    ],
)  # fmt: skip
def test_a_trajectory_entry_is_refused_naming_the_file_the_entry_and_the_key(
    tmp_path: Path, doc: Any, message: str
) -> None:
    path = write_trajectory(tmp_path / "t.json", doc)
    with pytest.raises(TrajectoryError, match=rf"^{path}: {message}"):
        load_trajectory_file(path, 1, RIG, 1000)


def test_a_deeply_nested_trajectory_is_an_error_not_a_crash(tmp_path: Path) -> None:
    path = tmp_path / "deep.json"
    path.write_text("[" * 200_000)
    with pytest.raises(TrajectoryError, match=r"deep\.json: not a JSON trajectory \(RecursionError"):
        load_trajectory_file(path, 1, RIG, 1000)


def test_a_good_trajectory_loads_with_the_rigs_camera_offsets(tmp_path: Path) -> None:
    pose = np.eye(4)
    pose[0, 3] = 2.5
    doc = {"frames": [{"timestamp_micros": 5000, "world_from_ego": pose.tolist()}]}
    (frame,) = load_trajectory_file(write_trajectory(tmp_path / "t.json", doc), 1, RIG, 1000)
    assert frame.timestamp_micros == 5000
    np.testing.assert_array_equal(frame.camera_timestamp_micros, [5000, 5010])
    np.testing.assert_array_equal(frame.world_from_ego, pose)


def test_a_rig_file_that_is_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    error = returns_without_blocking(lambda: load_rig_file(fifo), fifo)
    assert isinstance(error, RigError) and str(error).startswith(f"{fifo}: not a regular file")
