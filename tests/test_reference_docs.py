"""docs/reference/ says what the code does: the committed files are exactly what
``python -m phigenesis.cli.reference`` generates from the parsers, the schema and the configs, and
the check notices a change to any of them."""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path

import pytest
import tomllib

from phigenesis.cli import reference
from phigenesis.cli.common import Parser, positive
from phigenesis.options import check_options, option

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / reference.REFERENCE_DIR


@pytest.fixture(scope="module")
def generated() -> dict[str, str]:
    """The files as the code generates them (built once: the parsers import torch)."""
    return reference.reference_files()


def test_committed_reference_docs_are_what_the_code_generates(tmp_path: Path, generated: dict[str, str]):
    reference.write_reference(tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["README.md", "cli.md", "configs.md", "schema.md"]
    stale = [
        n
        for n in names
        if not (COMMITTED / n).is_file() or (COMMITTED / n).read_text() != (tmp_path / n).read_text()
    ]
    assert stale == [], (
        f"docs/reference/ is stale ({', '.join(stale)}): regenerate it from the repository root with "
        f"`{reference.REGENERATE}` and commit the result"
    )
    assert reference.stale_files(COMMITTED, generated) == []


def test_the_check_reports_a_committed_file_that_was_edited(tmp_path: Path, generated: dict[str, str]):
    shutil.copytree(COMMITTED, tmp_path, dirs_exist_ok=True)
    with (tmp_path / "configs.md").open("a") as f:
        f.write("an edit by hand\n")
    (tmp_path / "schema.md").unlink()
    assert reference.stale_files(tmp_path, generated) == ["schema.md", "configs.md"]


def test_every_console_command_is_documented():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert {prog: target.split(":")[0] for prog, target in scripts.items()} == dict(reference.COMMANDS)
    assert all(target.endswith(":main") for target in scripts.values())


def _parser(extra: bool = False, help_text: str = "frames to write") -> argparse.ArgumentParser:
    parser = Parser(prog="phigenesis-planted", description="A planted command.")
    parser.add_argument("--frames", type=positive, default=10, help=help_text)
    if extra:
        parser.add_argument("--planted", choices=("a", "b"), help="a planted flag")
    return parser


def test_a_new_flag_or_a_changed_help_changes_cli_md():
    base = reference.cli_markdown([("phigenesis-planted", _parser())])
    with_flag = reference.cli_markdown([("phigenesis-planted", _parser(extra=True))])
    assert base != with_flag
    assert "| `--planted` | one of a, b | - | a planted flag |" in with_flag
    assert "[--planted {a,b}]" in with_flag
    assert "| `--frames` | integer >= 1 | `10` | frames to write |" in base
    assert reference.cli_markdown([("phigenesis-planted", _parser(help_text="other"))]) != base


def test_a_changed_help_string_makes_the_committed_cli_md_stale(
    monkeypatch: pytest.MonkeyPatch, generated: dict[str, str]
):
    parsers = reference.build_parsers()
    _, parser = parsers[-1]
    action = next(a for a in parser._actions if a.option_strings == ["--out"])
    monkeypatch.setattr(action, "help", "a planted help string")
    text = reference.cli_markdown(parsers)
    assert text != generated["cli.md"] and "a planted help string" in text


@dataclasses.dataclass(frozen=True)
class _Inner:
    """An inner config.

    Attributes:
        size: side in pixels.
    """

    size: int = option(8, ge=1, le=64)


@dataclasses.dataclass(frozen=True)
class _Planted:
    """A planted config.

    Attributes:
        steps, batch: how long and how wide (one entry for two keys).
        mode: the mode; it goes on
            over two lines.
        rate ... weights: a span of fields.
    """

    steps: int = option(1000, ge=1, le=10**9)
    batch: int | None = option(None, gt=0, lt=5)
    mode: str = option("a", help="the help wins over the docstring")
    rate: float = option(0.5, ge=0, le=1, allow_inf=False)
    weights: dict[str, float] = option(factory=lambda: {"rgb": 1.0}, ge=0, keys=("rgb", "depth"))
    inner: _Inner = option(factory=_Inner)

    def __post_init__(self) -> None:
        check_options(self, "_Planted")


def test_configs_md_shows_each_option_type_default_range_and_help():
    group = reference.ConfigGroup("Planted", "Planted configs.", [("_Planted", _Planted)])
    text = reference.configs_markdown([group])
    assert (
        "| `steps` | int | `1000` | [1, 1000000000] | how long and how wide (one entry for two keys). |"
        in text
    )
    assert (
        "| `batch` | int or null | `null` | (0, 5) | how long and how wide (one entry for two keys). |"
        in text
    )
    assert "| `mode` | str | `a` | - | the help wins over the docstring |" in text
    assert (
        "| `weights` | mapping of float | `{rgb: 1.0}` | [0, inf); keys: rgb, depth | a span of fields. |"
        in text
    )
    assert "| `inner` | [_Inner](#_inner) | its defaults ([_Inner](#_inner)) | - | - |" in text
    assert "## Nested configs" in text and "| `size` | int | `8` | [1, 64] | side in pixels. |" in text


def test_attribute_docs_read_multi_name_and_continued_entries():
    docs = reference.attribute_docs(_Planted)
    assert docs["steps"] == docs["batch"] == "how long and how wide (one entry for two keys)."
    assert docs["mode"] == "the mode; it goes on over two lines."
    assert docs["rate"] == docs["weights"] == "a span of fields."
    assert "inner" not in docs
    assert reference.attribute_docs(_Inner) == {"size": "side in pixels."}


def test_a_same_as_option_takes_the_help_of_the_option_it_copies(generated: dict[str, str]):
    # GenerateOptions.voxel_m is declared same_as(BufferConfig, "voxel_m")
    section = generated["configs.md"].split("### GenerateOptions", 1)[1].split("\n### ", 1)[0]
    assert "| `voxel_m` | float | `0.2` | (0, 100] | voxel edge for de-duplication, metres |" in section


def test_schema_md_documents_every_column_with_its_switch(generated: dict[str, str]):
    from phigenesis.data.schema import TRUTH_MAPS, CacheContents, frame_schema

    everything = CacheContents(
        camera_truth=TRUTH_MAPS,
        depth=True,
        pseudo_semantics=True,
        range_view=True,
        lidar_range_image=True,
        scene_flow=True,
    )
    text = generated["schema.md"]

    def paths(fields, prefix=""):
        import pyarrow as pa

        for f in fields:
            yield prefix + f.name
            t = f.type
            if isinstance(t, pa.ListType) and isinstance(t.value_type, pa.StructType):
                yield from paths(t.value_type, prefix + f.name + "[].")
            elif isinstance(t, pa.StructType):
                yield from paths(t, prefix + f.name + ".")

    columns = list(paths(frame_schema(everything)))
    assert len(columns) > 100
    missing = [c for c in columns if f"| `{c}` |" not in text]
    assert missing == []
    assert "| `cameras[].depth_dense_png` | `binary` | m/256 | camera | yes | `depth` |" in text
    assert "| `lidar.flow_world_mps` | `list<float>` | m/s | world | yes | `lidar` and `scene_flow` |" in text
    assert (
        "| `cameras[].truth_flow_png` | `binary` | m/s | world | yes | `camera_truth` lists `flow` |" in text
    )


def test_an_unknown_column_group_stops_the_generator():
    with pytest.raises(ValueError, match="planted"):
        reference.switch_words("planted")


def test_the_command_line_writes_and_checks(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert reference.main(["--out", str(tmp_path)]) == 0
    assert reference.main(["--out", str(tmp_path), "--check"]) == 0
    (tmp_path / "README.md").write_text("stale\n")
    assert reference.main(["--out", str(tmp_path), "--check"]) == 1
    assert f"stale: {tmp_path / 'README.md'}" in capsys.readouterr().out


#: Configs of options that configs.md leaves out: how a spec is held in memory, not what a YAML
#: file holds (configs.md describes the spec's keys in words, from pipeline.SPEC_KEYS).
NOT_IN_CONFIGS_MD = {"phigenesis.data.pipeline.PipelineSpec", "phigenesis.data.pipeline.StageSpec"}


def _configs_in_the_package() -> set[str]:
    """Every class of the package whose ``__post_init__`` calls ``check_options`` (a config)."""
    import ast

    found = set()
    for path in sorted((ROOT / "phigenesis").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ClassDef):
                continue
            calls = [
                n
                for item in node.body
                if isinstance(item, ast.FunctionDef) and item.name == "__post_init__"
                for n in ast.walk(item)
                if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "check_options"
            ]
            if calls:
                found.add(f"{module}.{node.name}")
    return found


def test_configs_md_documents_every_config_of_the_package(generated: dict[str, str]):
    configs = _configs_in_the_package()
    assert len(configs) > 20 and configs >= NOT_IN_CONFIGS_MD
    missing = sorted(c for c in configs - NOT_IN_CONFIGS_MD if f"`{c}`" not in generated["configs.md"])
    assert missing == [], "add them to phigenesis.cli.reference.config_groups"


def test_configs_md_documents_every_registered_stage(generated: dict[str, str]):
    from phigenesis.data.stages import STAGES, get_stage

    get_stage("aggregate_lidar")
    assert len(STAGES) >= 10
    for name in STAGES:
        fn = getattr(STAGES[name], "__wrapped__", STAGES[name])
        if fn.__module__.startswith("phigenesis.data.stages"):  # not stages other tests register
            assert f"\n### {name}\n" in generated["configs.md"], name
