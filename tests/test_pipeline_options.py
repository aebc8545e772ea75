"""Every value of a pipeline spec has a type and a range, checked when the spec loads: the outputs,
the source's parameters, and every stage's parameters (built into the stage's parameter class),
so that a typo or a value out of range fails before any scene is read, naming the spec file, the
stage and the key; the command line's source overrides go through the same checks."""

from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import pytest

from phigenesis.cli import prep as prep_cli
from phigenesis.data.pipeline import (
    PipelineSpec,
    PrepError,
    StageSpec,
    bundled_pipelines,
    load_pipeline,
    prepare,
)
from phigenesis.data.schema import CacheContents
from phigenesis.data.sources import SOURCE_NAMES, source_config
from phigenesis.data.sources.synthetic import SyntheticSource
from phigenesis.data.stages import STAGE_PARAMS, STAGES, get_stage, register_stage, stage_params
from phigenesis.data.stages.densify import DENSIFIERS, DensifyParams, method_params, register_densifier
from phigenesis.data.stages.project import ProjectParams
from phigenesis.options import ConfigError, option_bounds

SPEC = """\
name: typo
source:
  name: synthetic
  params: {{height: 60, width: 90, lidar: {{beams: 16, columns: 256, sectors: 8}}}}
stages:
  - name: aggregate_lidar
    params: {{voxel_m: 0.02}}
  - name: project_depth
    params: {project}
output:
  lidar: {lidar}
  shard_max_bytes: {shard_max_bytes}
"""


def _spec(
    tmp_path: Path, project: str = "{}", lidar: str = "true", shard_max_bytes: str = "268435456"
) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC.format(project=project, lidar=lidar, shard_max_bytes=shard_max_bytes))
    return path


def _load_error(path: Path) -> str:
    with pytest.raises(PrepError) as e:
        load_pipeline(path)
    return str(e.value)


@pytest.fixture
def no_scene_is_read(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Scenes the synthetic source was asked to load (none may be)."""
    loaded: list[str] = []

    def load(self: SyntheticSource, scene_id: str) -> Any:
        loaded.append(scene_id)
        raise AssertionError(f"scene {scene_id} was read")

    monkeypatch.setattr(SyntheticSource, "load", load)
    return loaded


# --------------------------------------------------------------------------------------------
# The inputs


def test_an_output_flag_that_is_not_true_or_false_fails_when_the_spec_loads(tmp_path: Path):
    path = _spec(tmp_path, lidar="'yes'")
    assert _load_error(path) == f"{path}: output: CacheContents: lidar = 'yes': must be true or false"


@pytest.mark.parametrize("size", ["0", "-5", "2.5", "true", "1099511627777"])
def test_a_shard_size_outside_its_range_fails_when_the_spec_loads(tmp_path: Path, size: str):
    path = _spec(tmp_path, shard_max_bytes=size)
    assert _load_error(path).startswith(
        f"{path}: output: PipelineSpec: shard_max_bytes = {size.replace('true', 'True')}: "
        "must be an integer in [1, 1099511627776]"
    )


# --------------------------------------------------------------------------------------------
# Stage parameters


@pytest.mark.parametrize(
    ("project", "message"),
    [
        ("{visibilty: splat}", "unknown keys ['visibilty'] (did you mean 'visibility'?); known: ["),
        ("{max_range_m: -5}", "ProjectParams: max_range_m = -5: must be a number in (0, 1000] (finite)"),
        ("{threads: 2.5}", "ProjectParams: threads = 2.5: must be an integer in [1, 256]"),
        ("{window: 4}", "ProjectParams: window = 4: must be odd"),
        ("[1, 2]", "params: must be a mapping (key: value), got list"),
    ],
)
def test_a_stage_parameter_typo_or_bad_value_fails_at_spec_load_naming_the_stage_and_key(
    tmp_path: Path, no_scene_is_read: list[str], project: str, message: str
):
    path = _spec(tmp_path, project=project)
    assert _load_error(path).startswith(f"{path}: stage 2 (project_depth): {message}")
    out = tmp_path / "cache"
    with pytest.raises(PrepError, match="stage 2 \\(project_depth\\)"):
        prepare(out, "synthetic", {"scenes": 1, "frames": 1}, pipeline=path, progress=False)
    assert no_scene_is_read == [] and not out.exists()


def test_every_densifier_parameter_is_checked_at_spec_load_for_the_method_named(tmp_path: Path):
    for params, message in [
        (
            {"method": "ipbasic", "window_ref_px": 3.0},
            "method 'ipbasic' takes no parameters ['window_ref_px']",
        ),
        ({"method": "planar", "occlusion_tau": -0.1}, "occlusion_tau = -0.1: must be a number in [0, 10]"),
        (
            {"method": "magic"},
            "method = 'magic': must be one of ['guided', 'ipbasic', 'planar', 'planar_guided']",
        ),
        ({"fallback": "guided"}, "fallback = 'guided': must not need the image"),
        ({"min_sparse_coverage": 2}, "min_sparse_coverage = 2: must be a number in [0, 1]"),
    ]:
        spec = load_pipeline("synthetic").to_dict()
        spec["stages"][2] = {"name": "densify_depth", "params": params}
        with pytest.raises(PrepError) as e:
            PipelineSpec.from_dict(spec, "mine.yaml")
        assert str(e.value).startswith(f"mine.yaml: stage 3 (densify_depth): DensifyParams: {message}")
    params = stage_params(
        "densify_depth", {"method": "planar_guided", "max_fill_ref_px": 6, "window_ref_px": 4}
    )
    assert params.method_kwargs("ipbasic") == {"max_fill_ref_px": 6.0}  # the fallback's share


def test_a_spec_with_an_unknown_stage_or_key_fails_naming_it(tmp_path: Path):
    spec = load_pipeline("synthetic").to_dict()
    for change, message in [
        ({"stage": []}, "x.yaml: unknown keys ['stage']; known: ['name', 'source', 'stages', 'output']"),
        ({"stages": [{"name": "nope"}]}, "x.yaml: stage 1: unknown stage 'nope'; registered stages: ["),
        ({"stages": [{"name": "range_view", "parms": {}}]}, "x.yaml: stage 1: unknown keys ['parms']"),
        ({"stages": {"name": "range_view"}}, "x.yaml: stages must be a list"),
        ({"source": {"name": "kitti"}}, "x.yaml: source: unknown source 'kitti'; available: synthetic"),
        ({"name": 3}, "x.yaml: PipelineSpec: name = 3: must be a string"),
    ]:
        with pytest.raises(PrepError) as e:
            PipelineSpec.from_dict({**spec, **change}, "x.yaml")
        assert str(e.value).startswith(message), str(e.value)


def test_a_spec_built_in_code_is_checked_the_same_way():
    with pytest.raises(ConfigError, match=r"^stage project_depth: ProjectParams: window = 4: must be odd$"):
        StageSpec("project_depth", {"window": 4})
    with pytest.raises(ConfigError, match=r"^StageSpec: unknown stage 'nope'"):
        StageSpec("nope")
    with pytest.raises(ConfigError, match=r"^PipelineSpec: source synthetic params: .* height = 3:"):
        PipelineSpec("x", "synthetic", {"height": 3})
    with pytest.raises(ConfigError, match=r"^PipelineSpec: shard_max_bytes = 0: must be an integer in \[1, "):
        PipelineSpec("x", "synthetic", shard_max_bytes=0)


def test_a_registered_stage_takes_its_parameters_built_or_as_a_mapping():
    project = get_stage("project_depth")
    assert stage_params("project_depth", {"window": 5}) == ProjectParams(window=5)
    seen: list[Any] = []

    @register_stage("test_only_params", params=ProjectParams)
    def record(scene: Any, params: ProjectParams) -> Any:
        seen.append(params)
        return scene

    try:
        get_stage("test_only_params")(None, {"window": 3})
        get_stage("test_only_params")(None, ProjectParams(window=5))
        assert seen == [ProjectParams(window=3), ProjectParams(window=5)]
        with pytest.raises(ValueError, match="already registered"):
            register_stage("test_only_params", params=ProjectParams)(lambda scene, params: scene)
    finally:
        STAGES.pop("test_only_params", None)
        STAGE_PARAMS.pop("test_only_params", None)
    assert project.__wrapped__.__name__ == "project_depth"


def test_a_densifier_whose_parameters_are_not_declared_is_refused():
    with pytest.raises(ValueError, match=r"parameters \['strength'\] are not declared in DensifyParams"):

        @register_densifier("test_only_undeclared")
        def undeclared(sparse_m, sparse_confidence, rgb, focal_px, *, strength: float = 1.0):
            raise AssertionError("never runs")

    assert "test_only_undeclared" not in DENSIFIERS


# --------------------------------------------------------------------------------------------
# Source parameters: in the spec, and the command line's overrides


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (
            "{height: -3}",
            "source synthetic params: SyntheticConfig: height = -3: must be an integer in [8, 100000]",
        ),
        (
            "{lidar: {beams: 0}}",
            "SyntheticConfig: lidar: LidarSpec: beams = 0: must be an integer in [1, 1024]",
        ),
        ("{jpeg_quality: 101}", "SyntheticConfig: jpeg_quality = 101: must be an integer in [1, 100]"),
        ("{rig: waymo6}", "SyntheticConfig: rig = 'waymo6': must be one of 'waymo5', 'nuscenes6'"),
        ("{hieght: 60}", "source synthetic params: unknown keys ['hieght'] (did you mean 'height'?)"),
    ],
)
def test_a_source_parameter_out_of_range_fails_when_the_spec_loads(tmp_path: Path, params: str, message: str):
    path = tmp_path / "spec.yaml"
    path.write_text(f"source: {{name: synthetic, params: {params}}}\n")
    error = _load_error(path)
    assert error.startswith(f"{path}: ") and message in error


def test_a_partial_source_config_is_checked_key_by_key(tmp_path: Path):
    """The bundled waymo spec names no input (the command line does): its other values are checked."""
    assert load_pipeline("waymo").source_params == {"format": "auto", "check_crc": True}
    path = tmp_path / "w.yaml"
    path.write_text("source: {name: waymo, params: {format: v3, check_crc: true}}\n")
    assert _load_error(path) == (
        f"{path}: source waymo params: WaymoConfig: format = 'v3': must be one of 'auto', 'v1', 'v2'"
    )


def test_command_line_source_overrides_go_through_the_same_checks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_scene_is_read: list[str]
):
    out = tmp_path / "cache"
    with pytest.raises(PrepError, match=r"^synthetic source parameters: SyntheticConfig: box_range_m = -1: "):
        prepare(out, "synthetic", {"box_range_m": -1}, progress=False)
    code = prep_cli.main(["synthetic", "--out", str(out), "--seed", "-1", "--no-progress"])
    assert code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "phigenesis-prep: error: synthetic source parameters: SyntheticConfig: seed = -1: must be an integer "
        "in [0, 4294967295]"
    )
    assert no_scene_is_read == [] and not out.exists()


def test_the_prep_command_reports_a_bad_spec_as_an_input_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_scene_is_read: list[str]
):
    path = _spec(tmp_path, project="{visibilty: splat}")
    out = tmp_path / "cache"
    code = prep_cli.main(["synthetic", "--out", str(out), "--pipeline", str(path), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith(
        f"phigenesis-prep: error: {path}: stage 2 (project_depth): unknown keys ['visibilty']"
    )
    assert len(err.splitlines()) == 1
    assert no_scene_is_read == [] and not out.exists()


# --------------------------------------------------------------------------------------------
# What ships


@pytest.mark.parametrize("name", bundled_pipelines())
def test_every_bundled_spec_loads_and_round_trips(name: str):
    spec = load_pipeline(name)
    assert PipelineSpec.from_dict(spec.to_dict()) == spec
    for stage in spec.stages:
        assert stage_params(stage.name, stage.params) is not None


def _is_numeric(hint: Any) -> bool:
    """Whether values of ``hint`` are or hold numbers (int or float, not bool)."""
    if hint in (int, float):
        return True
    if get_origin(hint) is Literal:
        return False
    return any(_is_numeric(a) for a in get_args(hint) if a is not Ellipsis)


def _config_classes() -> dict[str, type]:
    """Every stage's parameter class, every source's config and the classes nested in them."""
    get_stage("range_view")  # imports (so registers) every built-in stage
    found = {f"stage {n}": cls for n, cls in STAGE_PARAMS.items() if cls is not None}
    found |= {f"source {n}": source_config(n) for n in SOURCE_NAMES}
    found |= {"output": CacheContents, "spec": PipelineSpec}
    todo = list(found.values())
    while todo:
        cls = todo.pop()
        for hint in typing.get_type_hints(cls).values():
            for inner in (hint, *get_args(hint)):
                if (
                    isinstance(inner, type)
                    and dataclasses.is_dataclass(inner)
                    and inner not in found.values()
                ):
                    found[inner.__name__] = inner
                    todo.append(inner)
    return found


def test_every_builtin_stage_registers_its_parameter_class():
    get_stage("range_view")
    builtin = {n for n, fn in STAGES.items() if fn.__module__.startswith("phigenesis.")}
    assert builtin and all(STAGE_PARAMS[n] is not None for n in builtin), builtin


def test_every_numeric_option_of_every_stage_and_source_has_a_lower_and_an_upper_bound():
    """A new field without a declared range fails here."""
    unbounded = []
    classes = _config_classes()
    assert {"ProjectParams", "CompletionParams", "DensifyParams", "LidarSpec", "SyntheticConfig"} <= {
        c.__name__ for c in classes.values()
    }
    for cls in classes.values():
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            hint = hints[field.name]
            if not _is_numeric(hint):
                continue
            b = option_bounds(field)
            lower = b.ge if b.ge is not None else b.gt
            upper = b.le if b.le is not None else b.lt
            if lower is None or upper is None or math.isinf(upper) or b.allow_inf:
                unbounded.append(f"{cls.__name__}.{field.name}")
    assert unbounded == []


def test_every_densifier_parameter_is_declared_and_every_default_is_in_range():
    for method in DENSIFIERS:
        for key, default in method_params(method).items():
            assert key in {f.name for f in dataclasses.fields(DensifyParams)}, (method, key)
            if default is not None:  # the method's own default fits the declared range
                DensifyParams(method=method, **{key: default})
    for cls in _config_classes().values():
        if cls not in (PipelineSpec, StageSpec):  # every default in range; a source's input given
            fields = dataclasses.fields(cls)
            cls(**{f.name: "x" for f in fields if dataclasses.MISSING is f.default is f.default_factory})


def test_union_and_tuple_hints_count_as_numeric_only_when_they_hold_numbers():
    assert (
        _is_numeric(int | None) and _is_numeric(tuple[float, float, float]) and _is_numeric(dict[str, float])
    )
    assert not _is_numeric(tuple[str, ...]) and not _is_numeric(Literal["a", "b"]) and not _is_numeric(bool)
    assert not _is_numeric(str | None)
