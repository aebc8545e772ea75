"""Pipeline specs: loading, validation with clear errors, fingerprints, and stages running in order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from phigenesis.data.pipeline import PipelineSpec, PrepError, fingerprint, load_pipeline, prepare
from phigenesis.data.records import Frame, Scene
from phigenesis.data.shards import CacheReader
from phigenesis.data.stages import STAGES, get_stage, register_stage
from tests.conftest import TINY_PREP_ARGS


def test_bundled_synthetic_pipeline_loads_with_its_defaults():
    spec = load_pipeline("synthetic")
    assert spec.source == "synthetic"
    assert spec.source_params["height"] == 160 and spec.source_params["width"] == 240
    assert spec.contents.camera_truth == ("depth", "semantic", "instance", "flow")
    assert PipelineSpec.from_dict(spec.to_dict()) == spec


def test_a_missing_or_invalid_spec_file_is_named_in_the_error(tmp_path: Path):
    with pytest.raises(PrepError, match=r"nope\.yaml: pipeline spec not found"):
        load_pipeline(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("source: [unclosed\n")
    with pytest.raises(PrepError, match=r"bad\.yaml: not valid YAML"):
        load_pipeline(bad)
    unknown_stage = tmp_path / "stage.yaml"
    unknown_stage.write_text("source: {name: synthetic}\nstages: [{name: no_such_stage}]\n")
    with pytest.raises(PrepError, match=r"stage.yaml: stage 1: unknown stage 'no_such_stage'"):
        load_pipeline(unknown_stage)
    unknown_output = tmp_path / "output.yaml"
    unknown_output.write_text("source: {name: synthetic}\noutput: {camera_truth: [depth, colour]}\n")
    with pytest.raises(PrepError, match=r"output.yaml: output: CacheContents: camera_truth\[1\] = 'colour'"):
        load_pipeline(unknown_output)


def test_unknown_source_parameters_are_refused_before_anything_is_written(tmp_path: Path):
    out = tmp_path / "cache"
    with pytest.raises(PrepError, match=r"^synthetic source parameters: unknown keys \['colour'\]"):
        prepare(out, "synthetic", {"colour": "red"}, progress=False)
    assert not out.exists()


def test_fingerprint_is_stable_and_changes_with_any_argument():
    spec = load_pipeline("synthetic").to_dict()
    base = fingerprint("synthetic", {"frames": 3, "seed": 1}, spec)
    assert base == fingerprint("synthetic", {"seed": 1, "frames": 3}, spec)
    assert base != fingerprint("synthetic", {"frames": 4, "seed": 1}, spec)
    assert base != fingerprint("synthetic", {"frames": 3, "seed": 1}, {**spec, "stages": [{"name": "x"}]})


def test_registering_two_stages_under_one_name_is_refused():
    @register_stage("test_only_identity")
    def identity(scene: Scene, params: dict) -> Scene:
        return scene

    assert get_stage("test_only_identity") is identity
    with pytest.raises(ValueError, match="already registered"):
        register_stage("test_only_identity")(lambda scene, params: scene)
    del STAGES["test_only_identity"]


def test_stages_run_in_spec_order_on_every_frame_before_writing(tmp_path: Path):
    @register_stage("test_only_shift_time")
    def shift_time(scene: Scene, params: dict) -> Scene:
        def shift(frame: Frame) -> Frame:
            frame.timestamp_micros += params["micros"]
            return frame

        return Scene(
            scene.scene_id, scene.source, scene.calibrations, scene.frames.map(shift), scene.metadata
        )

    # Small changes of the frame time only: a frame time far from its cameras' is an invalid record.
    @register_stage("test_only_floor_time")
    def floor_time(scene: Scene, params: dict) -> Scene:
        def floor(frame: Frame) -> Frame:
            frame.timestamp_micros -= frame.timestamp_micros % params["micros"]
            return frame

        return Scene(
            scene.scene_id, scene.source, scene.calibrations, scene.frames.map(floor), scene.metadata
        )

    try:
        base = load_pipeline("synthetic").to_dict()
        base["stages"] = [
            {"name": "test_only_shift_time", "params": {"micros": 7}},
            {"name": "test_only_floor_time", "params": {"micros": 4}},
        ]
        spec = PipelineSpec.from_dict(base)
        args = {**TINY_PREP_ARGS, "scenes": 1, "frames": 2}
        prepare(tmp_path / "staged", "synthetic", args, pipeline=spec, progress=False)
        prepare(tmp_path / "plain", "synthetic", args, progress=False)
        staged, plain = CacheReader(tmp_path / "staged"), CacheReader(tmp_path / "plain")
        for i in range(2):
            t_plain = plain.read(i).column("frame_timestamp_micros")[0].as_py()
            t_staged = staged.read(i).column("frame_timestamp_micros")[0].as_py()
            assert t_staged == (t_plain + 7) // 4 * 4
            assert t_staged != t_plain // 4 * 4 + 7  # what the other order gives
        assert staged.manifest.fingerprint != plain.manifest.fingerprint
        assert np.array_equal(staged.frame(0).lidar.points_ego, plain.frame(0).lidar.points_ego)
    finally:
        STAGES.pop("test_only_shift_time", None)
        STAGES.pop("test_only_floor_time", None)


def test_the_progress_bar_starts_with_the_scene_and_names_its_per_scene_work(tmp_path: Path):
    """A scene's bar starts before its stages' per-scene work (so the rate and the ETA count it)
    and says which stage is running; then one message per written frame."""
    from phigenesis.data.pipeline import SceneTask, process_scene

    spec = load_pipeline("synthetic")
    messages: list[tuple[str, int, int, str]] = []

    class Handle:
        def put(self, item: tuple[str, int, int, str]) -> None:
            messages.append(item)

    args = {**TINY_PREP_ARGS, "scenes": 1, "frames": 2}
    task = SceneTask(str(tmp_path), "synthetic", args, spec.to_dict(), "synthetic-s7-0000")
    (tmp_path / "shards").mkdir()
    result = process_scene(task, Handle())
    assert result.error is None, result.error
    stages = [st.name for st in spec.stages]
    assert messages[: len(stages)] == [("synthetic-s7-0000", 0, 2, f"{s} (per scene)") for s in stages]
    assert messages[len(stages) :] == [("synthetic-s7-0000", 1, 2, ""), ("synthetic-s7-0000", 2, 2, "")]
