"""The declared-options mechanism (phigenesis.options): types, ranges, unknown keys, where an error names."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import pytest

from phigenesis.options import ConfigError, check_options, check_values, from_mapping, option, same_as

Kind = Literal["a", "b"]


@dataclass(frozen=True)
class _Config:
    steps: int = option(10, ge=1)
    lr: float = option(1e-3, gt=0, le=1)
    flag: bool = option(True)
    kind: Kind = option("a")
    weights: dict[str, float] = option(factory=lambda: {"rgb": 1.0}, ge=0, keys=("rgb", "depth"))
    size: tuple[int, int] = option((1, 2), ge=1)
    threads: int | None = option(None, ge=1)
    far: float = option(math.inf, gt=0, allow_inf=True)

    def __post_init__(self) -> None:
        check_options(self, "_Config")


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"steps": True}, "steps = True: must be an integer in [1, inf)"),
        ({"steps": "2"}, "steps = '2': must be an integer"),
        ({"steps": 2.0}, "steps = 2.0: must be an integer"),
        ({"steps": 0}, "steps = 0: must be an integer in [1, inf)"),
        ({"lr": 1e30}, "lr = 1e+30: must be a number in (0, 1]"),
        ({"lr": float("nan")}, "lr = nan: must be a number in (0, 1]"),
        ({"lr": -1.0}, "lr = -1.0: must be a number in (0, 1]"),
        ({"flag": "yes"}, "flag = 'yes': must be true or false"),
        ({"kind": "c"}, "kind = 'c': must be one of 'a', 'b'"),
        ({"weights": {"rgb": float("nan")}}, "weights.rgb = nan: must be a number in [0, inf)"),
        ({"weights": {"rgb": -1}}, "weights.rgb = -1: must be a number in [0, inf)"),
        ({"weights": {"colour": 1.0}}, "weights.colour: unknown key; weights takes ['rgb', 'depth']"),
        ({"weights": [1.0]}, "weights = [1.0]: must be a mapping"),
        ({"size": [1]}, "size = [1]: must be a list of 2"),
        ({"size": [1, 0]}, "size = [1, 0]: must be a list of 2"),
        ({"threads": 0}, "threads = 0: must be an integer in [1, inf) or null"),
        ({"far": float("nan")}, "far = nan: must be a number in (0, inf) (infinity allowed)"),
        ({"zzz": 1}, "unknown keys ['zzz']; known: ['far', 'flag', 'kind', 'lr', 'size', 'steps'"),
        ([1, 2], "must be a mapping of options (key: value), got a list"),
        ("steps", "must be a mapping of options (key: value), got the string 'steps'"),
    ],
)
def test_a_value_outside_its_type_or_range_names_the_file_key_value_and_range(values, message):
    with pytest.raises(ConfigError) as e:
        from_mapping(_Config, values, "configs/x.yaml")
    assert str(e.value).startswith("configs/x.yaml: ")
    assert message in str(e.value)


def test_values_are_stored_as_their_type_holds_them():
    c = from_mapping(_Config, {"lr": 1, "size": [3, 4], "far": float("inf"), "threads": 2}, "x")
    assert c.lr == 1.0 and isinstance(c.lr, float)
    assert c.size == (3, 4)
    assert c.far == math.inf
    assert c.threads == 2
    assert from_mapping(_Config, None, "x") == _Config()


def test_checks_apply_when_built_in_code_too():
    with pytest.raises(ConfigError, match=r"^_Config: steps = -1: must be an integer in \[1, inf\)$"):
        _Config(steps=-1)


@dataclass(frozen=True)
class _Inner:
    beams: int = option(64, ge=1, le=1024)

    def __post_init__(self) -> None:
        check_options(self, "_Inner")


@dataclass(frozen=True)
class _Outer:
    name: str = option("x")
    inner: _Inner = option(factory=_Inner)

    def __post_init__(self) -> None:
        check_options(self, "_Outer")


def _error(cls: type, values: object) -> str:
    with pytest.raises(ConfigError) as e:
        from_mapping(cls, values, "x")
    return str(e.value)


def test_a_nested_config_is_built_from_its_mapping_with_its_own_checks():
    assert from_mapping(_Outer, {"inner": {"beams": 16}}, "x.yaml").inner == _Inner(16)
    assert _Outer(inner=_Inner(8)).inner.beams == 8
    assert _error(_Outer, {"inner": {"beams": 0}}) == (
        "x: _Outer: inner: _Inner: beams = 0: must be an integer in [1, 1024]"
    )
    assert _error(_Outer, {"inner": {"beam": 16}}).startswith(
        "x: _Outer: inner: unknown keys ['beam'] (did you mean 'beams'?)"
    )
    assert "inner = 3: must be _Inner" in _error(_Outer, {"inner": 3})


def test_some_options_are_checked_without_building_the_config():
    assert check_values(_Config, {"lr": 1, "size": [3, 4]}, "spec") == {"lr": 1.0, "size": (3, 4)}
    assert check_values(_Config, None, "spec") == {}
    with pytest.raises(ConfigError, match=r"^spec: _Config: steps = 0: must be an integer in \[1, inf\)$"):
        check_values(_Config, {"steps": 0}, "spec")
    with pytest.raises(ConfigError, match=r"^spec: unknown keys \['zzz'\]"):
        check_values(_Config, {"zzz": 1}, "spec")
    with pytest.raises(ConfigError, match=r"^spec: must be a mapping of options"):
        check_values(_Config, [1], "spec")


def test_an_unknown_key_names_the_known_key_it_is_closest_to():
    guessed = "x: unknown keys ['stpes'] (did you mean 'steps'?); known: ["
    assert _error(_Config, {"stpes": 3}).startswith(guessed)
    assert _error(_Config, {"zzz": 3}).startswith("x: unknown keys ['zzz']; known: [")


@dataclass(frozen=True)
class _Passes:
    steps: int = same_as(_Config, "steps")
    weights: dict[str, float] = same_as(_Config, "weights")

    def __post_init__(self) -> None:
        check_options(self, "_Passes")


def test_an_option_passed_on_is_declared_once_with_the_same_default_and_range():
    assert _Passes().steps == 10 and _Passes().weights == {"rgb": 1.0}
    assert _Passes().weights is not _Passes().weights  # a factory default stays a factory
    with pytest.raises(ConfigError, match=r"^_Passes: steps = 0: must be an integer in \[1, inf\)$"):
        _Passes(steps=0)
    with pytest.raises(AttributeError, match="declares no option 'nope'"):
        same_as(_Config, "nope")
