"""The synthetic presets have the real datasets' sensor sizes; the waymo preset's five LiDARs and
two returns round-trip through the Waymo v1 and v2 writers and readers; render_scale keeps the
full image size; phigenesis-synth refuses a preset that does not fit the format."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from phigenesis.cli import synth as synth_cli
from phigenesis.data.sources.synthetic import SyntheticConfig, SyntheticScene
from phigenesis.data.sources.synthetic.nuscenes_export import render_lidar_sweep
from phigenesis.data.sources.synthetic.presets import PRESETS
from phigenesis.data.sources.synthetic.rigs import camera_calibrations
from phigenesis.data.sources.synthetic.waymo_export import export_waymo
from phigenesis.data.sources.waymo import WaymoConfig, WaymoSource
from phigenesis.errors import PrepError
from phigenesis.options import ConfigError
from phigenesis.synth import synth


def test_waymo_preset_has_the_real_camera_sizes() -> None:
    cfg = SyntheticConfig.from_preset("waymo")
    cals, _ = camera_calibrations(cfg.rig, cfg.height, cfg.width, cfg.uniform_image_size)
    sizes = {c.name: (c.width, c.height) for c in cals}
    assert sizes == {
        "FRONT": (1920, 1280),
        "FRONT_LEFT": (1920, 1280),
        "FRONT_RIGHT": (1920, 1280),
        "SIDE_LEFT": (1920, 886),
        "SIDE_RIGHT": (1920, 886),
    }
    assert sum(w * h for w, h in sizes.values()) == 10_775_040
    assert cfg.rate_hz == 10.0


def test_waymo_preset_has_five_lidars_with_two_returns_at_the_real_sizes() -> None:
    cfg = SyntheticConfig.from_preset("waymo")
    lidars = {s.name: s for s in cfg.lidars}
    assert list(lidars) == ["TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR"]
    top = lidars["TOP"]
    assert (top.beams, top.columns, top.max_range_m) == (64, 2650, 75.0)
    incl = np.degrees(top.inclinations_rad())
    assert incl[0] == pytest.approx(2.4) and incl[-1] == pytest.approx(-17.6)
    assert np.all(np.diff(incl) < 0)
    for name in ("FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR"):
        s = lidars[name]
        assert (s.beams, s.columns, s.max_range_m, s.inclinations) == (200, 600, 20.0, "min_max")
        incl = np.degrees(s.inclinations_rad())
        # Cell-centred between -90 and +30 deg: 0.6 deg rows, the first 0.3 deg inside each edge.
        assert incl[0] == pytest.approx(29.7) and incl[-1] == pytest.approx(-89.7)
        assert s.sectors == 1 and not s.ego_returns
    assert all(s.returns == 2 for s in cfg.lidars)
    assert sum(s.cells for s in cfg.lidars) == 649_600
    # Mounted on the ego body's outside: front bumper, the two sides, the rear.
    assert lidars["FRONT"].position_m[0] > 3.5 and lidars["REAR"].position_m[0] < -0.6
    assert lidars["SIDE_LEFT"].position_m[1] > 0.9 > -0.9 > lidars["SIDE_RIGHT"].position_m[1]
    assert [lidars[n].yaw_deg for n in ("FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")] == [0, 90, -90, 180]


def test_nuscenes_preset_has_the_real_sizes_and_about_35k_points_per_sweep() -> None:
    cfg = SyntheticConfig.from_preset("nuscenes", height=45, width=80, scenes=1, frames=12)
    full = SyntheticConfig.from_preset("nuscenes")
    cals, _ = camera_calibrations(full.rig, full.height, full.width, full.uniform_image_size)
    assert [(c.width, c.height) for c in cals] == [(1600, 900)] * 6
    assert full.rate_hz == 12.0 and full.extra_lidars == ()
    lidar = full.lidar
    assert (lidar.beams, lidar.max_range_m) == (32, 70.0)
    incl = np.degrees(lidar.inclinations_rad())
    assert incl[0] == pytest.approx(10.0) and incl[-1] == pytest.approx(-30.0)
    scene = SyntheticScene(cfg, 0)
    assert scene.spin_period_s == 0.05  # 20 Hz
    n = len(render_lidar_sweep(scene, 0)["beam"])
    assert 30_000 <= n <= 40_000, n


def test_from_dict_rebuilds_a_preset_config_with_its_extra_lidars() -> None:
    cfg = SyntheticConfig.from_preset("waymo", height=64, width=96)
    again = SyntheticConfig.from_dict(cfg.to_dict())
    assert again == cfg and again.extra_lidars[3].name == "REAR"
    with pytest.raises(ConfigError, match="extra_lidars"):
        SyntheticConfig.from_dict({"extra_lidars": [{"beams": 0}]})
    with pytest.raises(ConfigError, match="unknown synthetic preset 'kitti'"):
        SyntheticConfig.from_preset("kitti")


def test_defaults_have_one_lidar_and_no_second_returns() -> None:
    cfg = SyntheticConfig(scenes=1, frames=1, height=24, width=32)
    assert cfg.extra_lidars == () and cfg.render_scale == 1 and cfg.lidar.returns == 1
    scene = SyntheticScene(cfg, 0)
    lidar = scene.render_geometry(0).lidar
    assert lidar is not None and lidar.return_index is None and set(np.unique(lidar.lidar_id)) == {0}


#: The waymo preset, small: 48 x 72 images, every LiDAR at a tenth of its columns (TOP 64 x 265,
#: short-range 50 x 60 over the same fields of view), two returns, 2 frames.
SMALL_WAYMO = SyntheticConfig.from_preset(
    "waymo",
    scenes=1,
    frames=2,
    seed=3,
    height=48,
    width=72,
    lidar=replace(PRESETS["waymo"]["lidar"], columns=265, second_return_fraction=1.0),
    extra_lidars=tuple(
        replace(s, beams=50, columns=60, second_return_fraction=1.0) for s in PRESETS["waymo"]["extra_lidars"]
    ),
)


@pytest.fixture(scope="module")
def small_waymo(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    root = tmp_path_factory.mktemp("waymo_preset")
    export_waymo(SMALL_WAYMO, root / "v1", "v1")
    export_waymo(SMALL_WAYMO, root / "v2", "v2")
    scene = SyntheticScene(SMALL_WAYMO, 0)
    return {"v1": root / "v1", "v2": root / "v2", "truth": [scene.render_frame(k) for k in range(2)]}


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_five_lidars_and_two_returns_read_back_as_the_synthetic_truth(
    small_waymo: dict[str, object], version: str
) -> None:
    source = WaymoSource(WaymoConfig(input=str(small_waymo[version])))
    scene = source.load(source.scene_ids()[0])
    for k, want in enumerate(small_waymo["truth"]):  # type: ignore[arg-type]
        got = scene.frames[k]
        gl, wl = got.lidar, want.lidar
        assert gl is not None and wl is not None and len(gl) == len(wl)
        # Waymo's laser ids as the reader maps them (name code - 1): TOP 0 .. REAR 4.
        assert set(np.unique(gl.lidar_id)) == {0, 1, 2, 3, 4}
        np.testing.assert_array_equal(gl.lidar_id, wl.lidar_id)
        np.testing.assert_array_equal(gl.return_index, wl.return_index)
        assert set(np.unique(gl.return_index)) == {0, 1}
        for lidar_id in range(5):
            assert np.count_nonzero((gl.lidar_id == lidar_id) & (gl.return_index == 0)) > 100
        # Second returns lie behind a first return of the same cell (vegetation passed through).
        assert np.count_nonzero(gl.return_index == 1) > 20
        np.testing.assert_allclose(gl.points_ego, wl.points_ego, atol=2e-4)
        np.testing.assert_allclose(gl.origins_ego, wl.origins_ego, atol=2e-4)
        np.testing.assert_array_equal(gl.beam_index, wl.beam_index)
        np.testing.assert_array_equal(gl.intensity, wl.intensity)
        top = gl.lidar_id == 0
        # Within half a sector (plus a column: 265 columns do not split evenly into 16 sectors).
        bound = 100_000 / SMALL_WAYMO.lidar.sectors / 2 + 100_000 / SMALL_WAYMO.lidar.columns
        assert np.abs(gl.time_offset_micros[top] - wl.time_offset_micros[top]).max() <= bound
        # Short-range LiDARs are snapshots at the frame time; the reader spreads them over the scan.
        assert np.all(wl.time_offset_micros[~top] == 0)
        assert np.abs(gl.time_offset_micros[~top]).max() <= 50_000
        # The short-range LiDARs see no further than 20 m and never the ego body.
        short = ~top
        dist = np.linalg.norm(wl.points_ego[short] - wl.origins_ego[short], axis=1)
        assert dist.max() <= 20.0 + 1e-3
        assert not np.any(wl.semantic[short] == 255)


def test_second_returns_are_farther_than_the_first_return_of_their_cell(
    small_waymo: dict[str, object],
) -> None:
    scene = SyntheticScene(SMALL_WAYMO, 0)
    _, raws = scene.render_frame_and_lidar(0, images=False)
    for raw in raws:
        ri = raw["return_index"]
        first = {
            (b, c): r
            for b, c, r in zip(
                raw["beam"][ri == 0], raw["column"][ri == 0], raw["range_m"][ri == 0], strict=True
            )
        }
        for b, c, r in zip(
            raw["beam"][ri == 1], raw["column"][ri == 1], raw["range_m"][ri == 1], strict=True
        ):
            assert r > first[(b, c)]


def test_render_scale_gives_images_and_truth_of_the_full_size() -> None:
    cfg = SyntheticConfig(scenes=1, frames=1, height=50, width=75, render_scale=2, uniform_image_size=False)
    frame = SyntheticScene(cfg, 0).render_frame(0)
    exact = SyntheticScene(replace(cfg, render_scale=1), 0).render_frame(0)
    for cam, ref in zip(frame.cameras, exact.cameras, strict=True):
        h, w = cam.calibration.height, cam.calibration.width
        assert (w, h) == (ref.calibration.width, ref.calibration.height)
        assert cam.decode_image().shape == (h, w, 3)
        assert cam.truth is not None and ref.truth is not None
        assert cam.truth.depth_m.shape == cam.truth.semantic.shape == (h, w)
        assert cam.truth.flow_world_mps.shape == (h, w, 3)
        # Truth is the nearest coarse pixel's: equal to the exact truth away from edges.
        same = np.mean(cam.truth.semantic == ref.truth.semantic)
        assert same > 0.9, same
        # Nearest resizing never blends classes: every label is one the coarse render holds.
        assert set(np.unique(cam.truth.semantic)) <= set(np.unique(ref.truth.semantic)) | {0}
    assert frame.cameras[3].calibration.height == 35  # SIDE_LEFT: 50 * 886 / 1280


def test_cli_rejects_a_preset_that_does_not_fit_the_format(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    code = synth_cli.main(
        ["--format", "nuscenes", "--preset", "waymo", "--frames", "1", "--out", str(tmp_path)]
    )
    err = capsys.readouterr().err
    assert code != 0
    assert "preset 'waymo'" in err and "format 'nuscenes'" in err
    with pytest.raises(ConfigError, match="preset 'nuscenes' does not match format 'waymo-v1'"):
        synth("waymo-v1", tmp_path, preset="nuscenes")
    assert not any(tmp_path.iterdir())


def test_prep_synthetic_takes_a_preset_and_explicit_values_override_it(tmp_path):
    from phigenesis import prep
    from phigenesis.data.schema import lidar_of
    from phigenesis.data.shards import CacheReader, Manifest

    summary = prep.synthetic(
        tmp_path / "c", preset="waymo", scenes=1, frames=1, height=64, width=96, progress=False
    )
    assert summary.frames_written == 1
    arguments = Manifest.load(tmp_path / "c").arguments
    assert (arguments["height"], arguments["width"], arguments["uniform_image_size"]) == (64, 96, False)
    assert (arguments["lidar"]["beams"], arguments["lidar"]["columns"]) == (64, 2650)
    assert [lidar["name"] for lidar in arguments["extra_lidars"]] == [
        "FRONT",
        "SIDE_LEFT",
        "SIDE_RIGHT",
        "REAR",
    ]
    sweep = lidar_of(CacheReader(tmp_path / "c").read(0))
    assert set(np.unique(sweep.lidar_id)) == {0, 1, 2, 3, 4}
    assert set(np.unique(sweep.return_index)) == {0, 1}


def test_a_waymo_preset_export_converts_with_the_waymo_sources_body(tmp_path):
    # The short-range LiDARs sit outside the Pacifica boxes the Waymo source assumes for every
    # segment; inside them, the source's sensor check refuses the scene.
    from phigenesis import prep
    from phigenesis.synth import synth

    synth("waymo-v1", tmp_path / "v1", preset="waymo", frames=1, height=64, width=96)
    summary = prep.waymo(tmp_path / "cache", input=tmp_path / "v1", progress=False)
    assert summary.frames_written == 1


def test_a_pipeline_spec_may_give_the_extra_lidars_as_mappings():
    from phigenesis.data.pipeline import PipelineSpec, load_pipeline
    from phigenesis.data.sources.synthetic.presets import preset_values

    spec = load_pipeline("synthetic").to_dict()
    spec["source"]["params"].update(preset_values("waymo"))  # LiDARs as mappings, as YAML holds them
    loaded = PipelineSpec.from_dict(spec, "spec.yaml")
    assert [lidar["name"] for lidar in loaded.source_params["extra_lidars"]] == [
        "FRONT",
        "SIDE_LEFT",
        "SIDE_RIGHT",
        "REAR",
    ]
    spec["source"]["params"]["extra_lidars"][1]["beams"] = 0
    with pytest.raises(
        PrepError, match=r"extra_lidars\[1\]: LidarSpec: beams = 0: must be an integer in \[1, 1024\]"
    ):
        PipelineSpec.from_dict(spec, "spec.yaml")
