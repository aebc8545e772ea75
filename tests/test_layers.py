"""The package's layers (docs/design/layers.md): every import between its parts, inside
functions and by ``importlib.import_module`` too, goes down the layers, never up or sideways; and an
import inside a function says why it is there."""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "phigenesis"

#: Each part of the package (a subpackage, or a single-file module at the top) and its layer: a part
#: imports parts of lower layers and itself, never a higher layer nor another part of its own layer.
#: Layer 0 (core) is the exception: its single-file modules may import one another.
LAYERS: dict[str, int] = {
    # core: conventions and helpers every layer shares
    "version": 0,
    "_open3d": 0,
    "errors": 0,
    "geometry": 0,
    "limits": 0,
    "malloc_tuning": 0,
    "native_cache": 0,
    "options": 0,
    "taxonomy": 0,
    "torch_files": 0,
    "user_files": 0,
    # networks, their registry and checkpoint reading, and the math on their outputs
    "models": 1,
    # sources, stages, caches, clips (the prep's segmenter stage runs a model)
    "data": 2,
    # what training, generation and evaluation share: Stage 2's conditions, configs and runner;
    # Gaussians to and from PLY files
    "rollout": 3,
    "export": 3,
    # the library's entry points, independent of one another
    "train": 4,
    "infer": 4,
    "eval": 4,
    "prep": 4,
    "synth": 4,
    # command lines, and the package's public API (its __init__, which loads each name on first use)
    "cli": 5,
    "phigenesis": 5,
}
CORE = 0


@dataclass(frozen=True)
class Import:
    """One import in a module: the module it names (absolute), where, and whether inside a function."""

    module: str
    line: int
    in_function: bool


def module_name(path: Path, root: Path) -> str:
    """``phigenesis.data.clips`` of ``root/phigenesis/data/clips.py`` (a package: its ``__init__``)."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _string_import(node: ast.Call) -> str | None:
    """The module a call ``importlib.import_module("phigenesis.x")`` or ``__import__(...)`` names:
    a string, or an f-string's text before its first placeholder (``f"phigenesis.data.stages.{n}"``)."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        return str(arg.values[0].value).rstrip(".")
    return None


def imports_of(source: str, module: str, is_package: bool = False) -> list[Import]:
    """Every import in a module's ``source``: statements at any depth (inside functions, under
    ``if TYPE_CHECKING``) and string imports (:func:`_string_import`). ``from a import b`` names
    ``a.b`` (a submodule, or a name in ``a``: both belong to ``a``'s part)."""
    tree = ast.parse(source)
    parents: dict[ast.AST, ast.AST] = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            parents[child] = node

    def in_function(node: ast.AST) -> bool:
        while node in parents:
            node = parents[node]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                return True
        return False

    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(node, module, is_package)
            names = [f"{base}.{alias.name}" if base else alias.name for alias in node.names]
        elif isinstance(node, ast.Call):
            named = _string_import(node)
            names = [named] if named else []
        found += [Import(name, node.lineno, in_function(node)) for name in names]
    return found


def part_of(module: str) -> str | None:
    """The part (key of :data:`LAYERS`) a ``phigenesis`` module belongs to; None outside it."""
    parts = module.split(".")
    if parts[0] != "phigenesis":
        return None
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "phigenesis"


def layer_violations(sources: dict[str, tuple[str, bool]]) -> list[str]:
    """Every import of ``sources`` (module name -> (source, is_package)) that goes up a layer or
    sideways within one, or comes from a part :data:`LAYERS` does not place, as
    ``"module:line imports other (layer a -> b)"``."""
    problems = []
    for module, (source, is_package) in sorted(sources.items()):
        src = part_of(module)
        if src is None or src not in LAYERS or (src == "phigenesis" and module.count(".") > 0):
            problems.append(f"{module}: a part of the package LAYERS does not place")
            continue
        for imp in imports_of(source, module, is_package):
            dst = part_of(imp.module)
            if dst is None or dst == src:
                continue
            a, b = LAYERS[src], LAYERS[dst]
            if b < a or (a == b == CORE):
                continue
            where = " (inside a function)" if imp.in_function else ""
            problems.append(f"{module}:{imp.line} imports {imp.module}{where} (layer {a} {src} -> {b} {dst})")
    return problems


def package_sources(root: Path = PACKAGE) -> dict[str, tuple[str, bool]]:
    return {
        module_name(path, root): (path.read_text(), path.name == "__init__.py")
        for path in sorted(root.rglob("*.py"))
    }


def _has_comment(lines: list[str], line: int) -> bool:
    """Whether the import at 1-based ``line`` carries a comment: on its line, or above it or above
    the run of imports it ends."""
    if "#" in lines[line - 1]:
        return True
    above = line - 2
    while above >= 0 and lines[above].strip().startswith(("import ", "from ")):
        above -= 1
    return above >= 0 and lines[above].strip().startswith("#")


def imports_inside_functions(sources: dict[str, tuple[str, bool]]) -> tuple[int, list[str]]:
    """(how many import statements sit inside functions, ``"module:line"`` of those without a
    comment saying why)."""
    count, bare = 0, []
    for module, (source, is_package) in sources.items():
        lines = source.splitlines()
        statement_lines = {
            n.lineno for n in ast.walk(ast.parse(source)) if isinstance(n, (ast.Import, ast.ImportFrom))
        }
        imports = imports_of(source, module, is_package)
        statements = {imp.line for imp in imports if imp.in_function and imp.line in statement_lines}
        count += len(statements)
        bare += [f"{module}:{line}" for line in sorted(statements) if not _has_comment(lines, line)]
    return count, bare


# --------------------------------------------------------------------------------------------


def test_every_import_in_the_package_goes_down_the_layers() -> None:
    assert layer_violations(package_sources()) == []


def test_every_part_of_the_package_has_a_layer() -> None:
    tops = {
        p.stem
        for p in PACKAGE.iterdir()
        if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()
    }
    assert tops <= set(LAYERS), sorted(tops - set(LAYERS))


def _with(module: str, source: str, is_package: bool = False) -> dict[str, tuple[str, bool]]:
    return {**package_sources(), module: (source, is_package)}


def test_an_upward_import_at_the_top_of_a_module_is_found() -> None:
    problems = layer_violations(
        _with("phigenesis.models.planted", "from phigenesis.train.stage1 import train_stage1\n")
    )
    assert problems == [
        "phigenesis.models.planted:1 imports phigenesis.train.stage1.train_stage1 (layer 1 models -> 4 train)"
    ]


def test_an_upward_import_inside_a_function_is_found() -> None:
    source = "def f():\n    x = 1\n    from phigenesis.infer import generate\n    return generate, x\n"
    problems = layer_violations(_with("phigenesis.data.stages.planted", source))
    assert problems == [
        "phigenesis.data.stages.planted:3 imports phigenesis.infer.generate (inside a function) "
        "(layer 2 data -> 4 infer)"
    ]


def test_a_relative_upward_import_is_found() -> None:
    source = "def f():\n    from ...train import runner\n    return runner\n"
    problems = layer_violations(_with("phigenesis.data.stages.planted", source))
    assert problems == [
        "phigenesis.data.stages.planted:2 imports phigenesis.train.runner (inside a function) "
        "(layer 2 data -> 4 train)"
    ]


def test_an_import_between_train_infer_and_eval_is_found() -> None:
    problems = layer_violations(_with("phigenesis.train.planted", "import phigenesis.eval.stage1 as s\n"))
    assert problems == ["phigenesis.train.planted:1 imports phigenesis.eval.stage1 (layer 4 train -> 4 eval)"]


def test_a_string_import_up_the_layers_is_found() -> None:
    source = (
        "import importlib\n\n\ndef f(name):\n"
        '    importlib.import_module("phigenesis.cli.train")\n'
        '    return importlib.import_module(f"phigenesis.rollout.{name}")\n'
    )
    problems = layer_violations(_with("phigenesis.models.planted", source))
    assert problems == [
        "phigenesis.models.planted:5 imports phigenesis.cli.train (inside a function) "
        "(layer 1 models -> 5 cli)",
        "phigenesis.models.planted:6 imports phigenesis.rollout (inside a function) "
        "(layer 1 models -> 3 rollout)",
    ]


def test_a_module_outside_the_layers_is_found() -> None:
    problems = layer_violations(_with("phigenesis.newpart", "import numpy\n"))
    assert problems == ["phigenesis.newpart: a part of the package LAYERS does not place"]


def test_imports_down_the_layers_and_within_a_part_pass() -> None:
    source = (
        "from phigenesis import taxonomy\nfrom phigenesis.models.checkpoint import load_checkpoint\n"
        "from . import clips\nfrom .stages import semantics\n"
    )
    assert layer_violations(_with("phigenesis.data.planted", source)) == []


def test_imports_inside_functions_are_counted_with_the_ones_that_say_nothing() -> None:
    source = (
        "import os\n\n\ndef f():\n    # optional: only for g\n    import ray\n"
        "    from ray.util import queue\n"
        "    x = 1\n    import yaml\n    return ray, queue, yaml, x\n\n\ndef g():\n"
        "    import json  # cheap, but a test\n    return json\n"
    )
    count, bare = imports_inside_functions({"phigenesis.planted": (source, False)})
    assert count == 4
    assert bare == ["phigenesis.planted:9"]


def test_every_import_inside_a_function_says_why() -> None:
    count, bare = imports_inside_functions(package_sources())
    assert bare == [], f"{len(bare)} of {count} imports inside functions have no comment"


@pytest.mark.parametrize("part", ["train", "infer", "eval"])
def test_train_infer_and_eval_import_none_of_one_another(part: str) -> None:
    others = {"train", "infer", "eval"} - {part}
    sources = package_sources()
    found = [
        f"{module}:{imp.line} {imp.module}"
        for module, (source, is_package) in sources.items()
        if part_of(module) == part
        for imp in imports_of(source, module, is_package)
        if part_of(imp.module) in others
    ]
    assert found == []
