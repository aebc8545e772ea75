"""How many places declare each option (issue 49, "Options declared 3-5 times"), and which command-line
flags are options of a config.

A config's option is declared by its dataclass field (type, default, range, help); every other place
that restates it is a further declaration: a hand check in ``__post_init__``, an entry of the class
docstring's ``Attributes:``, each argparse flag for it, each flag's own range check (an argparse
``type`` that checks a range, or ``choices``), each flag's literal default, each keyword copy
``option=args.flag`` in a command, and the prose (README.md, docs/*.md) that names it. The counts
are static (the source's AST), so they measure the code as written.

Print the table (the issue's "before" and "after" numbers)::

    python -m tests.test_option_declarations

The flag test lists every flag of every console command: each maps to exactly one field of the
config its command builds, or is on :data:`NOT_OPTIONS` (paths, run controls). It is an
``xfail(strict=True)`` while flags do not map, so it documents the gap and fails (XPASS) once closed.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
import textwrap
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLI = ROOT / "phigenesis" / "cli"
#: Prose that may restate an option (docs/reference/ is generated, not a declaration).
PROSE = (
    "README.md",
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("guide/*.md")),
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("design/*.md")),
    "docs/experiments.md",
)
#: argparse types (phigenesis.cli.common and the commands) that check a range of their own.
RANGE_TYPES = frozenset(
    {"positive", "positive_float", "unit_interval", "time_after_frame_s", "size_hw", "_shift", "_camera_step"}
)


@dataclass(frozen=True)
class Flag:
    """One ``add_argument`` call: where (file, function, the parser variable), its option strings,
    its dest, and whether it restates a range (type or choices) or a default (a literal)."""

    file: str
    function: str
    receiver: str
    options: tuple[str, ...]
    dest: str
    range_check: bool
    literal_default: bool
    line: int


@dataclass(frozen=True)
class Copy:
    """A keyword ``name=...`` in a call inside a command function, and the ``args.X`` it reads."""

    file: str
    function: str
    keyword: str
    dests: tuple[str, ...]
    line: int


def _name(node: ast.AST | None) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return ""


def _literal(node: ast.AST | None) -> bool:
    """Whether a default restates a value (a literal), rather than reading it from the config
    (``defaults.anchor``) or giving none (None, [])."""
    if node is None:
        return False
    try:
        value = ast.literal_eval(node)
    except ValueError:
        return False
    return not (value is None or value is False or value == [] or value == ())


def _args_read(node: ast.AST) -> tuple[str, ...]:
    """The flags (``args.X``) a keyword's value copies: of ``args.x or fallback`` only ``x`` (the
    fallback's own reads, ``trained_uncertainty(args.ckpt)``, are not the option's flag)."""
    if isinstance(node, ast.BoolOp):
        return _args_read(node.values[0])
    return tuple(
        n.attr
        for n in ast.walk(node)
        if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "args"
    )


def scan(sources: dict[str, str]) -> tuple[list[Flag], list[Copy]]:
    """The flags and keyword copies of ``sources`` (file name -> Python source)."""
    flags, copies = [], []
    for file, source in sorted(sources.items()):
        for fn in ast.walk(ast.parse(source)):
            if not isinstance(fn, ast.FunctionDef):
                continue
            for node in ast.walk(fn):
                if not isinstance(node, ast.Call):
                    continue
                if isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
                    options = tuple(
                        a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)
                    )
                    kw = {k.arg: k.value for k in node.keywords if k.arg}
                    long = [o for o in options if o.startswith("--")] or list(options)
                    dest = kw["dest"].value if "dest" in kw else long[0].lstrip("-").replace("-", "_")
                    flags.append(
                        Flag(
                            file,
                            fn.name,
                            _name(node.func.value),
                            options,
                            dest,
                            _name(kw.get("type")) in RANGE_TYPES or "choices" in kw,
                            _literal(kw.get("default")),
                            node.lineno,
                        )
                    )
                    continue
                for k in node.keywords:
                    if k.arg:
                        copies.append(Copy(file, fn.name, k.arg, _args_read(k.value), k.lineno))
            for node in ast.walk(fn):  # {"keyframes": args.keyframes} handed on as keywords
                if isinstance(node, ast.Dict):
                    for key, value in zip(node.keys, node.values, strict=True):
                        if isinstance(key, ast.Constant) and isinstance(key.value, str) and _args_read(value):
                            copies.append(Copy(file, fn.name, key.value, _args_read(value), key.lineno))
    return flags, copies


def cli_sources() -> dict[str, str]:
    """The command modules (reference.py builds the docs, it is no command)."""
    return {p.name: p.read_text() for p in sorted(CLI.glob("*.py")) if p.name != "reference.py"}


@dataclass(frozen=True)
class Scope:
    """Where a config's options reach the command line: the parsers' ``add_argument`` calls
    (file, function, parser variable) and the functions that copy the flags into the config."""

    flags: tuple[tuple[str, str, str], ...] = ()
    copies: tuple[tuple[str, str], ...] = ()


#: The configs measured for the issue and where the command line restates their options.
MEASURED: dict[str, Scope] = {
    "phigenesis.rollout.runner.GenerateOptions": Scope(
        flags=(
            ("generate.py", "build_parser", "parser"),
            ("eval.py", "build_parser", "d"),
            ("common.py", "add_anchor_options", "parser"),
        ),
        copies=(("generate.py", "_generate"), ("eval.py", "_stage2")),
    ),
    "phigenesis.data.stages.projection.params.ProjectParams": Scope(),
    "phigenesis.train.stage1.Stage1TrainConfig": Scope(
        flags=(("train.py", "build_parser", "g"),), copies=(("train.py", "_train_stage1"),)
    ),
}


def _class(path: str) -> type:
    module, name = path.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def post_init_mentions(cls: type) -> set[str]:
    """The fields a config's ``__post_init__`` checks by hand (``self.x``; not ``check_options``)."""
    fn = cls.__dict__.get("__post_init__")
    if fn is None:
        return set()
    tree = ast.parse(textwrap.dedent(inspect.getsource(fn)))
    return {
        n.attr
        for n in ast.walk(tree)
        if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "self"
    }


def prose_mentions(name: str, flags: list[str], texts: dict[str, str]) -> int:
    """How many prose files name the option: `` `name` ``, ``name:`` at a line's start (YAML) or
    one of its flags."""
    pattern = re.compile(
        rf"`{re.escape(name)}[`=: ]|^\s*{re.escape(name)}:"
        + "".join(rf"|{re.escape(f)}(?![\w-])" for f in flags),
        re.M,
    )
    return sum(bool(pattern.search(text)) for text in texts.values())


def declarations(
    cls: type, scope: Scope, flags: list[Flag], copies: list[Copy], prose: dict[str, str]
) -> dict[str, Counter[str]]:
    """For each option of ``cls``: how many places declare it, by kind."""
    # the reference generator reads Attributes sections the same way the docs do
    from phigenesis.cli.reference import attribute_docs

    docs, checked = attribute_docs(cls), post_init_mentions(cls)
    in_flags = [f for f in flags if (f.file, f.function, f.receiver) in scope.flags]
    in_copies = [c for c in copies if (c.file, c.function) in scope.copies]
    out = {}
    for field in dataclasses.fields(cls):
        name = field.name
        copied = [c for c in in_copies if c.keyword == name]
        dests = {name} | {d for c in copied for d in c.dests}
        own = [f for f in in_flags if f.dest in dests]
        out[name] = Counter(
            {
                "field": 1,
                "docstring": int(name in docs),
                "post_init": int(name in checked),
                "flag": len(own),
                "flag_range": sum(f.range_check for f in own),
                "flag_default": sum(f.literal_default for f in own),
                "copy": len(copied),
                "prose": prose_mentions(
                    name, [o for f in own for o in f.options if o.startswith("--")], prose
                ),
            }
        )
    return out


#: The kinds the issue names (field, __post_init__ check, flag, the flag's range check, copy, prose).
ISSUE_KINDS = ("field", "post_init", "flag", "flag_range", "copy", "prose")


def measure() -> dict[str, dict[str, Counter[str]]]:
    flags, copies = scan(cli_sources())
    prose = {p: (ROOT / p).read_text() for p in PROSE if (ROOT / p).is_file()}
    return {
        path.rsplit(".", 1)[1]: declarations(_class(path), s, flags, copies, prose)
        for path, s in MEASURED.items()
    }


# --------------------------------------------------------------------------------------------
# Flags -> options

#: The configs each command (and subcommand) builds from its flags.
COMMAND_CONFIGS: dict[str, tuple[str, ...]] = {
    "phigenesis-prep synthetic": ("phigenesis.data.sources.synthetic.SyntheticConfig",),
    "phigenesis-prep waymo": ("phigenesis.data.sources.waymo.WaymoConfig",),
    "phigenesis-prep nuscenes": ("phigenesis.data.sources.nuscenes.NuScenesConfig",),
    "phigenesis-synth": ("phigenesis.data.sources.synthetic.SyntheticConfig",),
    "phigenesis-train segmenter": ("phigenesis.train.segmenter.SegmenterTrainConfig",),
    "phigenesis-train vae": ("phigenesis.train.vae.VAETrainConfig",),
    "phigenesis-train stage1": ("phigenesis.train.stage1.Stage1TrainConfig",),
    "phigenesis-train stage2": ("phigenesis.rollout.config.Stage2TrainConfig",),
    "phigenesis-eval stage2": ("phigenesis.rollout.runner.GenerateOptions",),
    "phigenesis-generate": ("phigenesis.rollout.runner.GenerateOptions",),
}

#: Flags that are not options of a config, by kind: what a run reads and writes, how it runs.
NOT_OPTIONS: frozenset[str] = frozenset(
    {
        # every command
        "-h",
        "-v",
        # inputs and outputs: paths, not settings
        "--out",
        "--shards",
        "--ckpt",
        "--stage1",
        "--config",
        "--pipeline",
        "--picture",
        "--latents",
        "--init",
        "--pretrained",
        "--fid-model",
        "--export-ply",
        "cache",
        # run control: how the run goes, not what it computes
        "--workers",
        "--executor",
        "--ray-address",
        "--overwrite",
        "--on-error",
        "--no-progress",
        "--resume",
        "--stop-after",
        "--time-limit-min",
        "--threads",
        "--format",
    }
)


def _commands() -> list[tuple[str, object]]:
    # the generator builds the parsers without running them
    from phigenesis.cli.reference import _subcommands, build_parsers

    out: list[tuple[str, object]] = []
    for prog, parser in build_parsers():
        subs = _subcommands(parser)
        out += [(f"{prog} {name}", sub) for name, _, sub in subs] if subs else [(prog, parser)]
    return out


def flag_map() -> list[tuple[str, str, str]]:
    """(command, flag, what it is): ``field Config.name``, ``allow-listed`` or ``unmapped`` (or
    ``ambiguous: ...`` when it matches several fields). A flag matches a field by its dest, or by
    the keyword its command copies it to (``vae_checkpoint=args.vae``)."""
    _, copies = scan(cli_sources())
    aliases: dict[str, set[str]] = {}
    for c in copies:
        for d in c.dests:
            aliases.setdefault(d, set()).add(c.keyword)
    rows = []
    for command, parser in _commands():
        fields = {
            f.name: f"{_class(p).__name__}.{f.name}"
            for p in COMMAND_CONFIGS.get(command, ())
            for f in dataclasses.fields(_class(p))
        }
        for action in parser._actions:  # type: ignore[attr-defined]
            if not action.option_strings and action.dest == "command":
                continue
            flag = (action.option_strings or [action.dest])[0]
            names = {action.dest} | aliases.get(action.dest, set())
            hits = sorted({fields[n] for n in names if n in fields})
            if len(hits) == 1:
                rows.append((command, flag, f"field {hits[0]}"))
            elif len(hits) > 1:
                rows.append((command, flag, "ambiguous: " + ", ".join(hits)))
            elif flag in NOT_OPTIONS or any(o in NOT_OPTIONS for o in action.option_strings):
                rows.append((command, flag, "allow-listed"))
            else:
                rows.append((command, flag, "unmapped"))
    return rows


def _flag_summary() -> tuple[int, int, list[str]]:
    rows = flag_map()
    mapped = sum(r[2].startswith("field") for r in rows)
    allowed = sum(r[2] == "allow-listed" for r in rows)
    unmapped = [
        f"{c} {f}" + ("" if s == "unmapped" else f" ({s})")
        for c, f, s in rows
        if not s.startswith(("field", "allow"))
    ]
    return mapped, allowed, unmapped


# --------------------------------------------------------------------------------------------
# Tests


PLANTED_CLI = {
    "common.py": """
def add_shared(parser):
    parser.add_argument("--anchor", type=unit_interval, default=defaults.anchor, help="x")
""",
    "gen.py": """
def build_parser():
    parser = Parser()
    parser.add_argument("--steps", type=positive, default=10, help="steps")
    parser.add_argument("--kind", choices=("a", "b"), help="kind")
    parser.add_argument("--vae", help="a checkpoint")
    parser.add_argument("--seed", type=int, default=0, help="seed")
    add_shared(parser)
    return parser


def _run(args):
    options = Options(
        steps=args.steps,
        anchor=args.anchor,
        kind=args.kind or fallback(args.vae),
        ckpt=args.vae,
        seed=args.seed,
    )
    return run(options, **({"steps": args.steps} if args.steps else {}))
""",
}


@dataclass(frozen=True)
class _Options:
    """Planted.

    Attributes:
        steps: how many.
    """

    steps: int = 10
    anchor: float = 1.0
    kind: str = "a"
    ckpt: str = ""
    unused: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind == "b" and self.steps < 2:
            raise ValueError("planted")


def test_the_counter_finds_each_kind_of_declaration():
    flags, copies = scan(PLANTED_CLI)
    scope = Scope(
        flags=(("gen.py", "build_parser", "parser"), ("common.py", "add_shared", "parser")),
        copies=(("gen.py", "_run"),),
    )
    prose = {"README.md": "Pass `--steps 5`; the `kind` of run.\n", "docs/x.md": "```yaml\nsteps: 3\n```\n"}
    counts = declarations(_Options, scope, flags, copies, prose)
    assert counts["steps"] == Counter(
        field=1, docstring=1, post_init=1, flag=1, flag_range=1, flag_default=1, copy=2, prose=2
    )
    assert counts["anchor"] == Counter(field=1, flag=1, flag_range=1, copy=1)  # default read from the config
    assert counts["kind"] == Counter(field=1, post_init=1, flag=1, flag_range=1, copy=1, prose=1)
    assert counts["ckpt"] == Counter(field=1, flag=1, copy=1)  # --vae copied as ckpt=args.vae
    assert counts["unused"] == Counter(field=1)
    assert counts["seed"] == Counter(
        field=1, flag=1, flag_default=1, copy=1
    )  # a literal 0 restates the default


def test_every_measured_config_and_scope_exists():
    flags, copies = scan(cli_sources())
    declared = {(f.file, f.function, f.receiver) for f in flags}
    functions = {(c.file, c.function) for c in copies}
    for path, scope in MEASURED.items():
        assert dataclasses.is_dataclass(_class(path))
        assert set(scope.flags) <= declared, path
        assert set(scope.copies) <= functions, path
    counts = measure()
    assert all(c["field"] == 1 for options in counts.values() for c in options.values())
    # GenerateOptions reaches two commands: some option of it is a flag and a copy in both
    assert max(c["copy"] for c in counts["GenerateOptions"].values()) >= 2


def test_every_command_config_is_a_config_of_options():
    for command, paths in COMMAND_CONFIGS.items():
        for path in paths:
            assert dataclasses.is_dataclass(_class(path)), command
    commands = {c for c, _ in _commands()}
    assert set(COMMAND_CONFIGS) <= commands


_MAPPED, _ALLOWED, _UNMAPPED = _flag_summary()


@pytest.mark.xfail(
    bool(_UNMAPPED),
    strict=True,
    reason=f"issue 49: {len(_UNMAPPED)} flags are options no config declares ({_MAPPED} map to a field, "
    f"{_ALLOWED} are allow-listed)",
)
def test_every_flag_is_one_option_or_allow_listed():
    assert _UNMAPPED == []


def main() -> None:
    counts = measure()
    for cls, options in counts.items():
        print(f"\n{cls} ({len(options)} options)")
        print(
            f"{'option':26s} "
            + " ".join(f"{k:>12s}" for k in (*ISSUE_KINDS, "docstring", "flag_default"))
            + "  total"
        )
        totals = []
        for name, c in options.items():
            total = sum(c[k] for k in ISSUE_KINDS)
            totals.append(total)
            print(
                f"{name:26s} "
                + " ".join(f"{c[k]:12d}" for k in (*ISSUE_KINDS, "docstring", "flag_default"))
                + f"  {total:5d}"
            )
        code = [sum(c[k] for k in ISSUE_KINDS if k != "prose") for c in options.values()]
        with_all = [sum(c.values()) for c in options.values()]
        for label, values in (
            ("code (field, post_init, flag, flag_range, copy)", code),
            ("+ prose (the issue's kinds)", totals),
            ("+ docstring entries and literal flag defaults", with_all),
        ):
            print(f"  per option, {label}: mean {sum(values) / len(values):.2f}, max {max(values)}")
    mapped, allowed, unmapped = _flag_summary()
    print(f"\nflags: {mapped} map to one config field, {allowed} allow-listed, {len(unmapped)} unmapped:")
    for flag in unmapped:
        print(f"  {flag}")


if __name__ == "__main__":
    main()
