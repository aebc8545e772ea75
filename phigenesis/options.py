"""Declared options: every value of every config has a type and an allowed range, declared once beside
its default, and checked whenever the config is built (from a YAML file, a checkpoint's header, a
pipeline spec or code).

A config is a dataclass whose fields are declared with :func:`option`; its ``__post_init__`` calls
:func:`check_options` first, then whatever checks relate fields to each other. The field's type
annotation is its type (``int``, ``float``, ``bool``, ``str``, ``Literal[...]``, ``X | None``,
``tuple[int, ...]``, ``dict[str, float]``); the bounds are :func:`option`'s keywords::

    @dataclass(frozen=True)
    class TrainConfig:
        steps: int = option(1000, ge=1, le=10**9, help="optimiser steps")
        lr: float = option(2e-3, gt=0, le=1, help="peak learning rate")
        weights: dict[str, float] = option(factory=dict, ge=0, le=1e3, keys=("rgb", "depth"))

        def __post_init__(self) -> None:
            check_options(self, "TrainConfig")

The rules, the same for every config:

- an ``int`` is an integer (``true``, ``2.0`` and ``"2"`` are not); a ``float`` is a number (an
  integer is taken as its float), finite unless the field allows infinity, and never NaN; a
  ``bool`` is ``true`` or ``false`` (not ``'yes'``); a ``str`` is a string;
- the bounds (``ge``, ``gt``, ``le``, ``lt``) apply to a number, to each item of a sequence of
  numbers and to each value of a mapping of numbers; ``keys`` lists the keys a mapping may hold;
- a field whose type is itself a config (a dataclass of options) takes a mapping of its options;
- a value outside its type or range raises :class:`ConfigError` naming the key, the value and what
  is allowed; :func:`from_mapping` adds the file (or record) it came from.

:func:`from_mapping` is the one loader of a mapping of options (a YAML file's, a checkpoint header's,
a stage's parameters): anything but a mapping, or an unknown key, is a :class:`ConfigError` naming
the file and the known keys. :func:`check_values` checks some options of a config the same way
without building it (a partial config that another source completes).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass
from typing import Any, Literal, TypeVar, get_args, get_origin

from phigenesis.errors import PhiGenesisError

__all__ = [
    "Bounds",
    "ConfigError",
    "check_options",
    "check_values",
    "from_mapping",
    "option",
    "option_bounds",
    "same_as",
]

T = TypeVar("T")

#: The metadata key of a field's :class:`Bounds`.
BOUNDS_KEY = "phigenesis.bounds"
#: The metadata key of a field's help text.
HELP_KEY = "phigenesis.help"


class ConfigError(PhiGenesisError, ValueError):
    """A config value of the wrong type or outside its range, an unknown key, or a config that is
    not a mapping. The message names where the config came from, the key, the value and what the
    key allows."""


@dataclass(frozen=True)
class Bounds:
    """The allowed range of a numeric option (or of each item of a numeric sequence or mapping).

    Attributes:
        ge, gt, le, lt: inclusive and exclusive lower and upper bounds (None: unbounded).
        allow_inf: whether a float may be infinite (NaN never is allowed).
        keys: the keys a mapping may hold (None: any string key).
    """

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    allow_inf: bool = False
    keys: tuple[str, ...] | None = None

    def contains(self, x: float) -> bool:
        """Whether the number ``x`` lies within the bounds."""
        if math.isnan(x) or (math.isinf(x) and not self.allow_inf):
            return False
        return not (
            (self.ge is not None and x < self.ge)
            or (self.gt is not None and x <= self.gt)
            or (self.le is not None and x > self.le)
            or (self.lt is not None and x >= self.lt)
        )

    def interval(self) -> str:
        """The range in interval notation: ``[1, inf)``, ``(0, 1]``."""
        low = "[" if self.gt is None else "("
        high = "]" if self.lt is None else ")"
        lo = self.gt if self.gt is not None else self.ge
        hi = self.lt if self.lt is not None else self.le
        lo_text = "-inf" if lo is None else _number_text(lo)
        hi_text = "inf" if hi is None else _number_text(hi)
        if lo is None:
            low = "("
        if hi is None:
            high = ")"
        return f"{low}{lo_text}, {hi_text}{high}"

    def is_bounded(self) -> bool:
        return any(v is not None for v in (self.ge, self.gt, self.le, self.lt))


def _number_text(x: float) -> str:
    """A bound as a user would write it: integers in full (``1000000000``), other numbers short."""
    if isinstance(x, int) or (float(x).is_integer() and abs(x) < 1e15):
        return str(int(x))
    return f"{x:g}"


def option(
    default: Any = MISSING,
    *,
    factory: Any = MISSING,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    allow_inf: bool = False,
    keys: Sequence[str] | None = None,
    help: str = "",
) -> Any:
    """A dataclass field with a default (or a ``factory`` of defaults), its allowed range and its
    help text (see the module docstring)."""
    bounds = Bounds(ge, gt, le, lt, allow_inf, tuple(keys) if keys is not None else None)
    metadata = {BOUNDS_KEY: bounds, HELP_KEY: help}
    if factory is not MISSING:
        return dataclasses.field(default_factory=factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def same_as(cls: type, name: str) -> Any:
    """A field declared as the field ``name`` of the config ``cls`` is (its default, range and
    help): for a config that passes an option on to another, so the option is declared once."""
    source = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if source is None:
        raise AttributeError(f"{cls.__name__} declares no option {name!r}")
    if source.default_factory is not MISSING:
        return dataclasses.field(default_factory=source.default_factory, metadata=source.metadata)
    return dataclasses.field(default=source.default, metadata=source.metadata)


def option_bounds(field: dataclasses.Field) -> Bounds:
    """The bounds a field was declared with (no bounds for a plain field)."""
    return field.metadata.get(BOUNDS_KEY, Bounds())


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class _Invalid(Exception):
    """A value that does not fit its type or range: what it must be instead."""


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _describe(hint: Any, bounds: Bounds) -> str:
    """What a value of type ``hint`` within ``bounds`` is, in words."""
    origin, args = get_origin(hint), get_args(hint)
    interval = f" in {bounds.interval()}" if bounds.is_bounded() else ""
    if hint is int:
        return f"an integer{interval}"
    if hint is float:
        return f"a number{interval}" + (" (infinity allowed)" if bounds.allow_inf else " (finite)")
    if hint is bool:
        return "true or false"
    if hint is str:
        return "a string"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (types.UnionType, typing.Union):
        parts = [_describe(a, bounds) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or null" if type(None) in args else "")
    if origin is tuple or origin is list:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list, each item {_describe(args[0], bounds)}"
        if args:
            return f"a list of {len(args)}: " + ", ".join(_describe(a, bounds) for a in args)
        return "a list"
    if origin is dict or hint is dict:
        keys = f" with keys among {list(bounds.keys)}" if bounds.keys else ""
        if len(args) == 2 and args[1] is not Any:
            return f"a mapping{keys}, each value {_describe(args[1], bounds)}"
        return f"a mapping{keys}"
    return getattr(hint, "__name__", str(hint))


def _check(value: Any, hint: Any, bounds: Bounds) -> Any:
    """``value`` as the type ``hint`` holds it (an integer as a float, a list as a tuple), or
    :class:`_Invalid` saying what it must be."""
    origin, args = get_origin(hint), get_args(hint)
    if hint is Any or hint is object:
        return value
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool) and bounds.contains(value):
            return value
        raise _Invalid(_describe(hint, bounds))
    if hint is float:
        if _is_number(value) and bounds.contains(float(value)):
            return float(value)
        raise _Invalid(_describe(hint, bounds))
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _Invalid("true or false")
    if hint is str:
        if isinstance(value, str):
            return value
        raise _Invalid("a string")
    if origin is Literal:
        if any(value == a and type(value) is type(a) for a in args):
            return value
        raise _Invalid(_describe(hint, bounds))
    if origin in (types.UnionType, typing.Union):
        if value is None and type(None) in args:
            return None
        for arm in args:
            if arm is type(None):
                continue
            try:
                return _check(value, arm, bounds)
            except _Invalid:
                continue
        raise _Invalid(_describe(hint, bounds))
    if origin in (tuple, list) or hint in (tuple, list):
        if not isinstance(value, list | tuple):
            raise _Invalid(_describe(hint, bounds))
        try:
            if len(args) == 2 and args[1] is Ellipsis:
                items = [_check(v, args[0], bounds) for v in value]
            elif args:
                if len(value) != len(args):
                    raise _Invalid(_describe(hint, bounds))
                items = [_check(v, a, bounds) for v, a in zip(value, args, strict=True)]
            else:
                items = list(value)
        except _Invalid:
            raise _Invalid(_describe(hint, bounds)) from None
        return tuple(items) if (origin or hint) is tuple else items
    if origin is dict or hint is dict:
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise _Invalid(_describe(hint, bounds))
        if bounds.keys is not None and not set(value) <= set(bounds.keys):
            raise _Invalid(_describe(hint, bounds))
        item = args[1] if len(args) == 2 else Any
        try:
            return {k: _check(v, item, bounds) for k, v in value.items()}
        except _Invalid:
            raise _Invalid(_describe(hint, bounds)) from None
    if isinstance(hint, type):
        if isinstance(value, hint):
            return value
        raise _Invalid(_describe(hint, bounds))
    return value


def _first_bad_item(value: Any, hint: Any, bounds: Bounds) -> tuple[str, Any, Any] | None:
    """The key (``.name`` or ``[i]``), value and type of the first item of a mapping or sequence
    that does not fit, so that an error names ``weights.rgb`` rather than the whole mapping."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (types.UnionType, typing.Union):
        arms = [a for a in args if a is not type(None)]
        if len(arms) != 1:
            return None
        hint, origin, args = arms[0], get_origin(arms[0]), get_args(arms[0])
    if (origin is dict or hint is dict) and isinstance(value, Mapping):
        item = args[1] if len(args) == 2 else Any
        for k, v in value.items():
            if bounds.keys is not None and k not in bounds.keys:
                return f".{k}", v, None
            try:
                _check(v, item, bounds)
            except _Invalid:
                return f".{k}", v, item
    if origin in (tuple, list) and isinstance(value, list | tuple) and len(args) == 2 and args[1] is Ellipsis:
        for i, v in enumerate(value):
            try:
                _check(v, args[0], bounds)
            except _Invalid:
                return f"[{i}]", v, args[0]
    return None


def _nested_item(hint: Any) -> type | None:
    """The config class ``X`` of a ``tuple[X, ...]`` field whose items are configs (dataclasses),
    else None."""
    args = typing.get_args(hint)
    tuple_of = typing.get_origin(hint) is tuple and len(args) == 2 and args[1] is Ellipsis
    if tuple_of and isinstance(args[0], type) and dataclasses.is_dataclass(args[0]):
        return args[0]
    return None


def _checked_value(field: dataclasses.Field, hint: Any, value: Any, label: str) -> Any:
    """``value`` of ``field`` (type ``hint``) as its type holds it; a mapping given for a nested
    config (a field whose type is a dataclass of options) is built with :func:`from_mapping`.
    Raises :class:`ConfigError` (``LABEL: KEY = VALUE: must be ...``) if it does not fit."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, Mapping):
        return from_mapping(hint, value, f"{label}: {field.name}")
    item = _nested_item(hint)
    if item is not None and isinstance(value, list | tuple):  # a tuple of nested configs
        value = tuple(
            from_mapping(item, v, f"{label}: {field.name}[{i}]") if isinstance(v, Mapping) else v
            for i, v in enumerate(value)
        )
    bounds = option_bounds(field)
    try:
        return _check(value, hint, bounds)
    except _Invalid as e:
        item = _first_bad_item(value, hint, bounds)
        if item is None:
            raise ConfigError(f"{label}: {field.name} = {_short(value)}: must be {e}") from None
        suffix, shown, item_hint = item
        key = field.name + suffix
        if item_hint is None:
            raise ConfigError(
                f"{label}: {key}: unknown key; {field.name} takes {list(bounds.keys)}"
            ) from None
        raise ConfigError(
            f"{label}: {key} = {_short(shown)}: must be {_describe(item_hint, bounds)}"
        ) from None


def check_options(config: Any, label: str) -> None:
    """Checks every field of the dataclass instance ``config`` against its declared type and
    bounds, storing each value as its type holds it (an integer given for a float as a float, a
    list given for a tuple as a tuple, a mapping given for a nested config as that config).
    Raises :class:`ConfigError` (``LABEL: KEY = VALUE: must be ...``) for the first value that
    does not fit."""
    hints = _hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        checked = _checked_value(field, hints[field.name], value, label)
        if checked is not value:
            object.__setattr__(config, field.name, checked)


def check_values(cls: type, values: Any, where: str) -> dict[str, Any]:
    """Some of the options of ``cls`` (a partial config: a pipeline spec's source defaults, which
    the command line completes), each checked against its declared type and range as
    :func:`from_mapping` checks them, without building ``cls`` (so the options left out and the
    checks relating options to each other wait until it is built). Returns the values as their
    types hold them; raises :class:`ConfigError` naming ``where`` as :func:`from_mapping` does."""
    values = _known_mapping(cls, values, where)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = _hints(cls)
    try:
        return {k: _checked_value(fields[k], hints[k], v, cls.__name__) for k, v in values.items()}
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


def _known_mapping(cls: type, values: Any, where: str) -> Mapping[str, Any]:
    """``values`` (None: empty) if it is a mapping of options of ``cls``; otherwise a
    :class:`ConfigError` naming ``where`` and the known keys."""
    if values is None:
        return {}
    if not isinstance(values, Mapping):
        raise ConfigError(f"{where}: must be a mapping of options (key: value), got {_kind(values)}")
    known = [f.name for f in dataclasses.fields(cls)]
    bad = sorted(str(k) for k in values if k not in known)
    if bad:
        close = [m for k in bad for m in difflib.get_close_matches(k, known, n=1)]
        guess = f" (did you mean {', '.join(map(repr, close))}?)" if close else ""
        raise ConfigError(f"{where}: unknown keys {bad}{guess}; known: {sorted(known)}")
    return values


def from_mapping(cls: type[T], values: Any, where: str, **extra: Any) -> T:
    """The config ``cls`` from a mapping of options read from ``where`` (a file, a checkpoint, a
    pipeline stage): anything but a mapping, an unknown key, or a value outside its type or range
    raises :class:`ConfigError` naming ``where``, the key, the value and what is allowed.
    ``extra`` are keyword arguments given beside the mapping (overrides from the command line)."""
    values = _known_mapping(cls, values, where)
    try:
        return cls(**{**values, **extra})
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {' '.join(str(e).split())}") from None


def _kind(value: Any) -> str:
    """A YAML/JSON value's kind in the words a user knows: a list, a string, a number."""
    if isinstance(value, list | tuple):
        return "a list"
    if isinstance(value, str):
        return f"the string {_short(value)}"
    if isinstance(value, bool):
        return f"the value {value}"
    if _is_number(value):
        return f"the number {value!r}"
    return f"a {type(value).__name__}"
