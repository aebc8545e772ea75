"""The reference docs under ``docs/reference/``, generated from the code: the command lines from their
argparse parsers (``cli.md``), the cache's Arrow schema from its columns' metadata (``schema.md``)
and the configs from their declared options (``configs.md``), with an index (``README.md``).

Regenerate them with ``python -m phigenesis.cli.reference`` (``--check`` only reports the stale
files, exit status 1 if any); ``tests/test_reference_docs.py`` fails when the committed files differ
from what the code generates. The output depends on nothing but the code: no terminal width, no
paths, no dates.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import re
import sys
import types
import typing
from collections.abc import Iterable, Sequence
from dataclasses import MISSING
from pathlib import Path
from typing import Any, Literal

from phigenesis.cli.common import Parser, plain_text
from phigenesis.options import BOUNDS_KEY, HELP_KEY, option_bounds

#: Where the generated files live, relative to the repository root.
REFERENCE_DIR = Path("docs") / "reference"
#: The command that regenerates them (from the repository root).
REGENERATE = "python -m phigenesis.cli.reference"
HEADER = f"<!-- Generated from the code by `{REGENERATE}`: do not edit by hand. -->\n"

#: The console commands (``[project.scripts]`` of pyproject.toml) and their modules, each with a
#: ``build_parser()``; tests/test_reference_docs.py checks this list against pyproject.toml.
COMMANDS: tuple[tuple[str, str], ...] = (
    ("phigenesis-prep", "phigenesis.cli.prep"),
    ("phigenesis-synth", "phigenesis.cli.synth"),
    ("phigenesis-train", "phigenesis.cli.train"),
    ("phigenesis-export", "phigenesis.cli.export"),
    ("phigenesis-eval", "phigenesis.cli.eval"),
    ("phigenesis-generate", "phigenesis.cli.generate"),
    ("phigenesis-render", "phigenesis.cli.render"),
)

# --------------------------------------------------------------------------------------------
# Markdown helpers

_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`~?([^`]+)`")
_LITERAL = re.compile(r"``(.+?)``", re.S)


def markdown_text(text: str) -> str:
    """reStructuredText inline markup as Markdown: ``literal`` and Sphinx roles (``:func:`x```)
    as code spans; whitespace (line breaks of a docstring) as single spaces."""
    text = _ROLE.sub(lambda m: f"`{m.group(1)}`", text)
    text = _LITERAL.sub(lambda m: f"`{m.group(1)}`", text)
    return " ".join(text.split())


def cell(text: str) -> str:
    """``text`` as one Markdown table cell (pipes escaped, on one line, "" as a dash)."""
    text = " ".join(str(text).split()).replace("|", "\\|")
    return text or "-"


def table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def anchor(title: str) -> str:
    """The anchor GitHub gives a heading ``title``."""
    text = re.sub(r"[^\w\- ]", "", title.strip().lower())
    return text.replace(" ", "-")


def code(text: Any) -> str:
    return f"`{text}`"


# --------------------------------------------------------------------------------------------
# cli.md: the command lines from their parsers

#: What each argparse ``type`` of the command lines takes, in words.
TYPE_WORDS = {
    "int": "integer",
    "float": "number",
    "str": "text",
    "positive": "integer >= 1",
    "positive_float": "number > 0",
    "unit_interval": "number in [0, 1]",
    "size_hw": "HxW (pixels)",
    "time_after_frame_s": "seconds in [-86400, 86400]",
    "_shift": "metres (a finite number)",
    "_camera_step": "CAMERA:STEP",
}


def _type_words(action: argparse.Action) -> str:
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return "one of " + ", ".join(str(c) for c in action.choices)
    kind = action.type
    if kind is None:
        return "text"
    name = getattr(kind, "__name__", type(kind).__name__)
    if name in TYPE_WORDS:
        return TYPE_WORDS[name]
    doc = inspect.getdoc(kind) or ""
    return doc.split("\n")[0].removeprefix("argparse type: ").rstrip(".") or name


def _value_words(action: argparse.Action) -> str:
    """What a flag takes: a switch, or its values (how many, of what type)."""
    if action.nargs == 0:
        return "switch"
    words = _type_words(action)
    if action.nargs == "+":
        words = f"one or more: {words}"
    elif action.nargs == "*":
        words = f"zero or more: {words}"
    elif action.nargs == "?":
        words = f"optional: {words}"
    elif isinstance(action.nargs, int) and action.nargs > 1:
        words = f"{action.nargs} x {words}"
    if isinstance(action, argparse._AppendAction):
        words += " (repeatable)"
    return words


def _default_words(action: argparse.Action) -> str:
    if action.required:
        return "required"
    default = action.default
    if action.nargs == 0 or default is None or default == [] or default is argparse.SUPPRESS:
        return ""
    if getattr(action.type, "__name__", "") == "size_hw" and isinstance(default, tuple):
        return code("x".join(str(v) for v in default))
    if isinstance(default, list | tuple):
        return code(" ".join(str(v) for v in default))
    return code(default)


def _args_text(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = parser._get_formatter()
    if action.option_strings:
        return formatter._format_args(action, formatter._get_default_metavar_for_optional(action))
    return formatter._format_args(action, formatter._get_default_metavar_for_positional(action))


def usage_line(prog: str, parser: argparse.ArgumentParser) -> str:
    """The usage of ``parser`` on one line (argparse's wraps at the terminal's width)."""
    parts = [prog]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            parts.append("{" + ",".join(action.choices) + "} ...")
            continue
        if not action.option_strings:
            parts.append(_args_text(parser, action))
            continue
        text = action.option_strings[0]
        if action.nargs != 0:
            text += " " + _args_text(parser, action)
        parts.append(text if action.required else f"[{text}]")
    return " ".join(parts)


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, help, parser) of each subcommand of ``parser``, in the order they were added."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            out += [(name, helps.get(name, ""), sub) for name, sub in action.choices.items()]
    return out


def flags_table(parser: argparse.ArgumentParser) -> str:
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            continue
        name = ", ".join(action.option_strings) or (action.metavar or action.dest)
        help_text = "show this help and exit" if isinstance(action, argparse._HelpAction) else action.help
        rows.append(
            (
                code(name),
                "switch" if isinstance(action, argparse._HelpAction) else _value_words(action),
                _default_words(action),
                plain_text(help_text or ""),
            )
        )
    return table(("Flag", "Takes", "Default", "Help"), rows)


def command_markdown(prog: str, parser: argparse.ArgumentParser) -> str:
    """One command's section of cli.md: its description, usage and flags, then each subcommand's."""
    out = [f"## {prog}\n"]
    if parser.description:
        out.append(markdown_text(parser.description) + "\n")
    out.append(f"```\n{usage_line(prog, parser)}\n```\n")
    subs = _subcommands(parser)
    if subs:
        out.append(
            "Subcommands: " + ", ".join(f"[{n}](#{anchor(f'{prog} {n}')})" for n, _, _ in subs) + ".\n"
        )
    out.append(flags_table(parser))
    for name, help_text, sub in subs:
        out.append(f"### {prog} {name}\n")
        if help_text:
            text = markdown_text(plain_text(help_text)).rstrip(".")
            out.append(text[:1].upper() + text[1:] + ".\n")
        if sub.description and sub.description != help_text:
            out.append(markdown_text(sub.description) + "\n")
        out.append(f"```\n{usage_line(f'{prog} {name}', sub)}\n```\n")
        out.append(flags_table(sub))
        if sub.epilog:
            out.append("```\n" + sub.epilog.strip("\n") + "\n```\n")
    return "\n".join(out)


def build_parsers(
    commands: Sequence[tuple[str, str]] = COMMANDS,
) -> list[tuple[str, argparse.ArgumentParser]]:
    """Each command's parser, built (its ``build_parser()``) and not run."""
    return [(prog, importlib.import_module(module).build_parser()) for prog, module in commands]


def cli_markdown(parsers: Sequence[tuple[str, argparse.ArgumentParser]]) -> str:
    out = [
        HEADER,
        "# Command-line reference\n",
        "Every console command of the package and its subcommands, from their argparse parsers. "
        "Exit status of every command: 0 done, 1 an unexpected error (a bug), 2 an input the toolkit "
        "cannot use, 130 interrupted (`phigenesis-prep verify` adds its own: see there).\n",
        "\n".join(f"- [{prog}](#{anchor(prog)})" for prog, _ in parsers) + "\n",
    ]
    out += [command_markdown(prog, parser) for prog, parser in parsers]
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# configs.md: the configs from their declared options


def _own_docstring(cls: type) -> str:
    """The class's own docstring ("" for a dataclass without one: not its generated signature)."""
    doc = cls.__dict__.get("__doc__") or ""
    if doc.startswith(cls.__name__ + "("):
        return ""
    return inspect.cleandoc(doc)


def summary(obj: Any) -> str:
    """The first paragraph of a class's or function's docstring, as Markdown."""
    doc = _own_docstring(obj) if isinstance(obj, type) else inspect.cleandoc(obj.__doc__ or "")
    return markdown_text(doc.split("\n\n", 1)[0]) if doc else ""


def _field_span(cls: type, names: str) -> list[str]:
    """The fields an entry names: ``a`` itself, or ``a ... b`` every field from a to b."""
    if "..." not in names:
        return [names]
    first, last = (n.strip() for n in names.split("...", 1))
    order = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else []
    if first in order and last in order:
        return order[order.index(first) : order.index(last) + 1]
    return [first, last]


def attribute_docs(cls: type) -> dict[str, str]:
    """Each field's text in the ``Attributes:`` section of ``cls``'s docstring (Google style; an
    entry may name several fields: ``steps, batch_size: ...``, or a
    span of them in declaration order: ``max_depth_m ... keep_tau: ...``)."""
    lines = _own_docstring(cls).splitlines()
    start = next((i for i, line in enumerate(lines) if line.strip() == "Attributes:"), None)
    if start is None:
        return {}
    base = len(lines[start]) - len(lines[start].lstrip())
    entries: list[tuple[list[str], list[str]]] = []
    indent = None
    for line in lines[start + 1 :]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if depth <= base:
            break
        indent = depth if indent is None else indent
        match = re.match(r"([\w ,.]+):(?:\s|$)(.*)", line.strip())
        if depth == indent and match:
            names = [n.strip() for n in match.group(1).split(",") if n.strip()]
            entries.append(([m for n in names for m in _field_span(cls, n)], [match.group(2)]))
        elif entries:
            entries[-1][1].append(line.strip())
    return {name: markdown_text(" ".join(text)) for names, text in entries for name in names}


def _is_config(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def type_words(hint: Any) -> str:
    """A field's type annotation in the words of a YAML file: ``int``, ``one of "a", "b"``,
    ``list of float``, ``mapping of float``, a link to a nested config."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any or hint is object:
        return "any"
    if hint in (int, float, bool, str):
        return hint.__name__
    if origin is Literal:
        return "one of " + ", ".join(f'"{a}"' for a in args)
    if origin in (types.UnionType, typing.Union):
        arms = [type_words(a) for a in args if a is not type(None)]
        return " or ".join(arms) + (" or null" if type(None) in args else "")
    if origin in (tuple, list) or hint in (tuple, list):
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {type_words(args[0])}"
        if args:
            return "[" + ", ".join(type_words(a) for a in args) + "]"
        return "list"
    if origin is dict or hint is dict:
        if len(args) == 2 and args[1] is not Any:
            return f"mapping of {type_words(args[1])}"
        return "mapping"
    if _is_config(hint):
        return f"[{hint.__name__}](#{anchor(hint.__name__)})"
    return getattr(hint, "__name__", str(hint))


def value_text(value: Any) -> str:
    """A default as YAML writes it (``null``, ``true``, ``[1, 2]``, ``{a: 1}``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {value_text(v)}" for k, v in value.items()) + "}"
    return str(value)


def _default(field: dataclasses.Field, hint: Any) -> str:
    if field.default is not MISSING:
        value = field.default
    elif field.default_factory is not MISSING:
        value = field.default_factory()
    else:
        return "required"
    if dataclasses.is_dataclass(value):
        return f"its defaults ([{type(value).__name__}](#{anchor(type(value).__name__)}))"
    return code(value_text(value))


def range_words(field: dataclasses.Field) -> str:
    bounds = option_bounds(field)
    parts = [bounds.interval()] if bounds.is_bounded() else []
    if bounds.allow_inf:
        parts.append("infinity allowed")
    if bounds.keys:
        parts.append("keys: " + ", ".join(bounds.keys))
    return "; ".join(parts)


def field_help(cls: type, field: dataclasses.Field, shared: dict[int, str]) -> str:
    """A field's help: its ``option(help=...)``, else its entry in the class's ``Attributes:``,
    else (a field declared ``same_as`` another config's) the help of the field it copies."""
    text = field.metadata.get(HELP_KEY) or attribute_docs(cls).get(field.name, "")
    if not text and BOUNDS_KEY in field.metadata:
        text = shared.get(id(field.metadata[BOUNDS_KEY]), "")
    return markdown_text(text)


def _shared_helps(classes: Iterable[type]) -> dict[int, str]:
    """The help of every field of ``classes`` that has one, keyed by its Bounds object's id: a
    field declared with ``same_as`` holds the very Bounds of the field it copies."""
    out: dict[int, str] = {}
    for cls in classes:
        docs = attribute_docs(cls)
        for f in dataclasses.fields(cls):
            text = f.metadata.get(HELP_KEY) or docs.get(f.name)
            if text and BOUNDS_KEY in f.metadata:
                out.setdefault(id(f.metadata[BOUNDS_KEY]), text)
    return out


def nested_configs(cls: type) -> list[type]:
    """The configs nested in ``cls``'s fields (a field of a config type, or a list of them)."""
    out = []
    for hint in typing.get_type_hints(cls).values():
        for candidate in (hint, *typing.get_args(hint)):
            if _is_config(candidate) and candidate not in out:
                out.append(candidate)
    return out


def options_table(cls: type, shared: dict[int, str]) -> str:
    hints = typing.get_type_hints(cls)
    if not dataclasses.fields(cls):
        return "No options: its mapping is empty (any key is an error).\n"
    rows = [
        (
            code(f.name),
            type_words(hints[f.name]),
            _default(f, hints[f.name]),
            range_words(f),
            field_help(cls, f, shared),
        )
        for f in dataclasses.fields(cls)
    ]
    return table(("Key", "Type", "Default", "Range", "Help"), rows)


def config_markdown(cls: type, shared: dict[int, str], heading: str = "###", title: str | None = None) -> str:
    """One config's section: its name, module, summary and the table of its options."""
    out = [f"{heading} {title or cls.__name__}\n", f"`{cls.__module__}.{cls.__qualname__}`\n"]
    text = summary(cls)
    if text:
        out.append(text + "\n")
    out.append(options_table(cls, shared))
    return "\n".join(out)


@dataclasses.dataclass
class ConfigGroup:
    """A section of configs.md: a title, what its configs are, and the configs."""

    title: str
    intro: str
    configs: list[tuple[str, type]]  # (heading, config class)
    notes: dict[str, str] = dataclasses.field(default_factory=dict)  # heading -> a line above its table


def config_groups() -> list[ConfigGroup]:
    """The configs of configs.md, found through the registries (stages, sources, models)."""
    # the library's configs: importing them loads torch (3-5 s), only when the docs are built
    from phigenesis.data.pipeline import SOURCE_KEYS, SPEC_KEYS, STAGE_KEYS, PipelineSpec
    from phigenesis.data.schema import CacheContents
    from phigenesis.data.sources import SOURCE_NAMES, source_config
    from phigenesis.data.stages import STAGE_PARAMS, STAGES, get_stage
    from phigenesis.models import list_models
    from phigenesis.models.adapter import AdapterConfig
    from phigenesis.models.buffer import BufferConfig
    from phigenesis.models.dit import DiTConfig
    from phigenesis.models.segformer import SegFormerConfig
    from phigenesis.models.stage1 import Stage1Config
    from phigenesis.models.uncertainty import UncertaintyConfig
    from phigenesis.models.vae import VideoVAEConfig
    from phigenesis.rollout.config import Stage2DataConfig, Stage2TrainConfig
    from phigenesis.rollout.runner import GenerateOptions
    from phigenesis.train.segmenter import SegmenterTrainConfig
    from phigenesis.train.stage1 import Stage1TrainConfig
    from phigenesis.train.vae import VAETrainConfig

    get_stage("aggregate_lidar")  # registers the built-in stages
    shard = next(f for f in dataclasses.fields(PipelineSpec) if f.name == "shard_max_bytes")
    shard_words = f"int in {range_words(shard)}, default {shard.default}: a shard's size limit in bytes"
    stages, notes = [], {}
    shown: dict[type, str] = {}
    # Only the toolkit's own stages: a plugin (or a test) registering more must not change the docs.
    builtin = sorted(n for n in STAGES if _is_builtin_stage(STAGES[n]))
    for name in builtin:
        params = STAGE_PARAMS[name]
        fn = getattr(STAGES[name], "__wrapped__", STAGES[name])
        note = summary(fn)
        if params is None:
            notes[name] = (note + " " if note else "") + "Takes no declared parameters."
            continue
        if params in shown:
            note += f" Takes the parameters of [{shown[params]}](#{anchor(shown[params])})."
        shown.setdefault(params, name)
        stages.append((name, params))
        notes[name] = note.strip()
    stage_names = builtin
    family = {
        Stage1Config: "stage1",
        VideoVAEConfig: "vae",
        DiTConfig: "dit",
        SegFormerConfig: "segformer",
    }
    model_notes = {
        cls.__name__: "Registered variants: " + ", ".join(code(n) for n in list_models(fam)) + "."
        for cls, fam in family.items()
    }
    return [
        ConfigGroup(
            "Pipeline specs",
            "A pipeline spec (`pipelines/*.yaml`, or a YAML file given to `phigenesis-prep --pipeline`) "
            f"holds the keys {', '.join(code(k) for k in SPEC_KEYS)}: `source` a mapping of "
            f"{', '.join(code(k) for k in SOURCE_KEYS)} ([Sources](#sources)), "
            "`stages` a list of mappings of "
            f"{', '.join(code(k) for k in STAGE_KEYS)} ([Stages](#stages)), and `output` the keys of "
            "[CacheContents](#cachecontents) (which optional columns the cache stores: "
            f"[schema.md](schema.md)) and `shard_max_bytes` ({shard_words}).",
            [("CacheContents", CacheContents)],
            {"CacheContents": "A spec's `output`."},
        ),
        ConfigGroup(
            "Sources",
            "A spec's `source.params` (defaults the command line's flags override), one config per "
            "source: " + ", ".join(code(n) for n in SOURCE_NAMES) + ".",
            [(source_config(name).__name__, source_config(name)) for name in SOURCE_NAMES],
            {source_config(name).__name__: f"The `{name}` source's `params`." for name in SOURCE_NAMES},
        ),
        ConfigGroup(
            "Stages",
            "A spec's `stages[i].params`: the parameters of each registered stage, in alphabetical "
            "order. Registered stages: "
            + ", ".join(f"[{n}](#{anchor(n)})" if n in dict(stages) else code(n) for n in stage_names)
            + ".",
            stages,
            notes,
        ),
        ConfigGroup(
            "Training",
            "The YAML config of each trainer (`phigenesis-train stage1|stage2 --config FILE`; "
            "`configs/`); the segmenter and VAE trainers take their options as flags.",
            [
                ("Stage1TrainConfig", Stage1TrainConfig),
                ("Stage2TrainConfig", Stage2TrainConfig),
                ("Stage2DataConfig", Stage2DataConfig),
                ("VAETrainConfig", VAETrainConfig),
                ("SegmenterTrainConfig", SegmenterTrainConfig),
            ],
        ),
        ConfigGroup(
            "Generation",
            "How a Stage 2 rollout samples (`phigenesis-generate` and `phigenesis-eval stage2` flags).",
            [("GenerateOptions", GenerateOptions)],
        ),
        ConfigGroup(
            "Models",
            "The configs of the model families: a trainer's `model_overrides` replace fields of its "
            "variant's config.",
            [
                ("Stage1Config", Stage1Config),
                ("AdapterConfig", AdapterConfig),
                ("VideoVAEConfig", VideoVAEConfig),
                ("DiTConfig", DiTConfig),
                ("UncertaintyConfig", UncertaintyConfig),
                ("BufferConfig", BufferConfig),
                ("SegFormerConfig", SegFormerConfig),
            ],
            model_notes,
        ),
    ]


def configs_markdown(groups: Sequence[ConfigGroup]) -> str:
    listed = [cls for g in groups for _, cls in g.configs]
    nested: list[type] = []
    for cls in listed:
        for inner in nested_configs(cls):
            if inner not in listed and inner not in nested:
                listed.append(inner)  # nested configs of nested configs too
                nested.append(inner)
    shared = _shared_helps(listed)
    out = [
        HEADER,
        "# Config reference\n",
        "Every config of the toolkit, from its dataclass of declared options "
        "(`phigenesis.options`): each key's type, default, allowed range and help. A value of the "
        "wrong type or outside its range, and an unknown key, is an error naming the file and the key. "
        "Ranges are intervals: `[a, b]` includes its ends, `(a, b)` excludes them.\n",
        "\n".join(f"- [{g.title}](#{anchor(g.title)})" for g in groups)
        + ("\n- [Nested configs](#nested-configs)" if nested else "")
        + "\n",
    ]
    for group in groups:
        out.append(f"## {group.title}\n\n{group.intro}\n")
        for heading, cls in group.configs:
            section = config_markdown(cls, shared, title=heading)
            note = group.notes.get(heading) or group.notes.get(cls.__name__)
            if note:
                head, rest = section.split("\n", 1)
                section = f"{head}\n\n{note}\n{rest}"
            out.append(section)
    if nested:
        out.append("## Nested configs\n\nConfigs that are the value of a key of the configs above.\n")
        out += [config_markdown(cls, shared) for cls in nested]
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# schema.md: the cache's columns from their metadata


def arrow_type_words(t: Any) -> str:
    """An Arrow type in short: ``double[3]`` (fixed-size list), ``list<float>``, ``binary``."""
    import pyarrow as pa  # the data layer's dependency: loaded with the schema anyway

    if isinstance(t, pa.FixedSizeListType):
        return f"{arrow_type_words(t.value_type)}[{t.list_size}]"
    if isinstance(t, pa.ListType):
        return f"list<{arrow_type_words(t.value_type)}>"
    return str(t)


def switch_words(group: str | None) -> str:
    """Which ``output`` keys of a pipeline spec (``CacheContents``) store a column of ``group``."""
    # the schema's module: the CLI layer may import the data layer
    from phigenesis.data.schema import CacheContents

    known = {f.name for f in dataclasses.fields(CacheContents)}
    if group is None:
        return "always"
    if group.startswith("truth_"):
        return f"`camera_truth` lists `{group.removeprefix('truth_')}`"
    if group == "lidar_truth":
        return "`lidar` and `lidar_truth`"
    if group == "lidar_scene_flow":
        return "`lidar` and `scene_flow`"
    if group in known:
        return f"`{group}`"
    raise ValueError(f"column group {group!r}: say which output keys store it (switch_words)")


def _columns_rows(
    cls: type, prefix: str, parent_switch: str, out: list[tuple[str, ...]], seen: list[type]
) -> None:
    for f in dataclasses.fields(cls):
        meta = f.metadata
        name = prefix + f.name
        switch = switch_words(meta["group"])
        if cls.__name__ == "FrameColumns" and f.name == "lidar":
            switch = "`lidar`"  # the sweep's own switch (frame_schema leaves it out without lidar)
        if switch == "always":
            switch = parent_switch
        nested = meta["arrow"] if isinstance(meta["arrow"], type) else None
        if nested is not None and nested not in seen:
            seen.append(nested)
        if nested is not None:
            kind = "list<struct>" if meta["repeated"] else "struct"
            type_text = f"{kind} ([{nested.__name__}](#{anchor(nested.__name__)}))"
        else:
            type_text = code(arrow_type_words(meta["arrow"]))
        nullable = "yes" if meta["nullable"] or meta["repeated"] else "no"
        out.append(
            (code(name), type_text, meta["unit"], meta["frame"], nullable, switch, markdown_text(meta["doc"]))
        )
        if nested is not None:
            child = name + ("[]." if meta["repeated"] else ".")
            _columns_rows(nested, child, switch, out, seen)


def schema_markdown() -> str:
    # the schema's module: the CLI layer may import the data layer
    from phigenesis.data import schema

    rows: list[tuple[str, ...]] = []
    seen: list[type] = [schema.FrameColumns]
    _columns_rows(schema.FrameColumns, "", "always", rows, seen)
    contents = [f.name for f in dataclasses.fields(schema.CacheContents)]
    docs = attribute_docs(schema.CacheContents)
    meta = schema.frame_schema().metadata or {}
    out = [
        HEADER,
        "# Cache schema\n",
        "The cache's Arrow schema, from the metadata of its columns' declarations "
        "(`phigenesis.data.schema`).\n",
        *(markdown_text(p) + "\n" for p in schema.__doc__.split("\n\n")[1:]),
        f"Schema version: `{schema.SCHEMA_VERSION}`. Schema metadata: "
        + ", ".join(f"`{k.decode()}`" for k in sorted(meta))
        + ". Every column's metadata holds `doc` and, where they apply, `unit` and `frame` (a point's "
        "or a pose's frame; `a<-b` maps frame b to frame a).\n",
        "## Output switches\n",
        "Which optional columns a cache holds is its pipeline spec's `output` "
        "([configs.md](configs.md#cachecontents)); a column marked *always* is in every cache.\n",
        table(("Output key", "Stores"), [(code(k), docs.get(k, "")) for k in contents]),
        "## Columns\n",
        "One row per frame. A nested column is named by its path: `cameras[].image` is the field "
        "`image` of each entry of the list `cameras`.\n",
        table(("Column", "Arrow type", "Unit", "Frame", "Nullable", "Stored when", "Description"), rows),
        "## Structs\n",
        "Each struct type and where it appears.\n",
    ]
    for cls in seen:
        paths = [r[0] for r in rows if f"[{cls.__name__}]" in r[1]] or ["the row"]
        fields = ", ".join(code(f.name) for f in dataclasses.fields(cls))
        out.append(
            f"### {cls.__name__}\n\n`{cls.__module__}.{cls.__name__}` at {', '.join(paths)}: {fields}.\n"
        )
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# README.md and the files


def index_markdown() -> str:
    return "\n".join(
        [
            HEADER,
            "# Reference\n",
            "Generated from the code, so it says what the code does:\n",
            "- [cli.md](cli.md): every command and subcommand, its usage and flags (from the argparse "
            "parsers);",
            "- [schema.md](schema.md): the cache's Arrow columns, their types, units, frames and which "
            "`output` switch stores them (from the columns' metadata);",
            "- [configs.md](configs.md): every config's keys, types, defaults, ranges and help: the "
            "pipeline specs, sources and stages, the trainers, generation and the models (from the "
            "dataclasses of declared options).\n",
            f"After changing a parser, a column or an option, regenerate them from the repository root "
            f"with `{REGENERATE}`; `tests/test_reference_docs.py` fails while they are stale.\n",
        ]
    )


def reference_files(
    parsers: Sequence[tuple[str, argparse.ArgumentParser]] | None = None,
    groups: Sequence[ConfigGroup] | None = None,
) -> dict[str, str]:
    """The text of each file of docs/reference/, by name."""
    return {
        "README.md": index_markdown(),
        "cli.md": cli_markdown(build_parsers() if parsers is None else parsers),
        "schema.md": schema_markdown(),
        "configs.md": configs_markdown(config_groups() if groups is None else groups),
    }


def _tidy(text: str) -> str:
    """One blank line between blocks, one newline at the end."""
    return re.sub(r"\n{3,}", "\n\n", text).strip("\n") + "\n"


def _is_builtin_stage(stage: object) -> bool:
    """Whether a registered stage function is one of the toolkit's (defined in phigenesis.data.stages)."""
    fn = getattr(stage, "__wrapped__", stage)
    return getattr(fn, "__module__", "").startswith("phigenesis.data.stages")


def write_reference(out_dir: str | Path = REFERENCE_DIR) -> list[Path]:
    """Writes the reference files into ``out_dir`` (created if missing); returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, text in reference_files().items():
        path = out / name
        path.write_text(_tidy(text), encoding="utf-8")
        paths.append(path)
    return paths


def stale_files(out_dir: str | Path, files: dict[str, str] | None = None) -> list[str]:
    """The names of the reference files in ``out_dir`` that differ from what the code generates
    (or are missing)."""
    files = reference_files() if files is None else files
    out = Path(out_dir)
    return [
        name
        for name, text in files.items()
        if not (out / name).is_file() or (out / name).read_text(encoding="utf-8") != _tidy(text)
    ]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="python -m phigenesis.cli.reference", description=__doc__)
    parser.add_argument(
        "--out", default=str(REFERENCE_DIR), help=f"folder to write (default {REFERENCE_DIR})"
    )
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file is stale")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.check:
        stale = stale_files(args.out)
        for name in stale:
            print(f"stale: {Path(args.out) / name} (regenerate: {REGENERATE})")
        return 1 if stale else 0
    for path in write_reference(args.out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
