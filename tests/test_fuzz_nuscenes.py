"""Fuzzing the nuScenes source: mutated tables and LiDAR files either convert to a cache that
holds only finite values, or fail with a PrepError-family message naming the file.

Each case changes one field of one record of a tiny export (a wrong type, a missing key, NaN,
Inf, a huge or negative number, the string "false" for a bool, a list for a token, a dangling
token, a ``../`` filename, a duplicate token, a truncated list), or damages one ``.pcd.bin``
(NaN/Inf/huge points, truncated, empty). Cases are drawn from a fixed seed. Every case runs
through ``phigenesis.prep.nuscenes`` (into a small cache, with only ``interpolate_boxes``) under
both error policies, in a worker process whose address space is capped at its size after
start-up + 2 GiB and which must answer within :data:`CASE_SECONDS`; scene failures are checked
to be input errors (``SceneResult.error_is_input``), not toolkit bugs.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import multiprocessing
import os
import random
import resource
import traceback
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from phigenesis import prep
from phigenesis.data import pipeline
from phigenesis.errors import PrepError
from tests.cache_checks import non_finite_values
from tests.test_nuscenes_hostile import CHEAP_PIPELINE, VERSION, export_tiny_nuscenes

SEED = 14
#: Mutated tables (at least 50) and damaged LiDAR files per run.
TABLE_CASES = 56
PCD_CASES = 6
#: A case (both policies) answers within this, seconds; it takes ~0.3 s.
CASE_SECONDS = 30.0
#: What a case may allocate beyond the worker's size after start-up, bytes.
MEMORY_HEADROOM = 2 * 2**30
POLICIES = ("raise", "skip")
#: Tables the reader uses, weighted towards the big ones; visibility and map are not read.
TABLE_WEIGHTS = {
    "sample_data": 6,
    "sample_annotation": 6,
    "ego_pose": 3,
    "calibrated_sensor": 3,
    "sample": 3,
    "sensor": 1,
    "instance": 2,
    "category": 1,
    "attribute": 1,
    "scene": 1,
    "log": 1,
    "visibility": 1,
}
DANGLING = "0" * 32


class _Delete:
    """Stands for "remove the field" in a mutation."""

    def __repr__(self) -> str:
        return "<missing>"


DELETE = _Delete()


@dataclass(frozen=True)
class Case:
    """One mutated dataset.

    Attributes:
        name: what was changed, e.g. ``sample_data[12].timestamp = NaN``.
        root: the mutated dataroot (resolved).
        files: the files an error may name: the one that was changed (a table's JSON or a
            ``.pcd.bin``); for a record whose token was made invalid, which nothing can link to
            any more, also every table (a link to it fails naming the record that links).
    """

    name: str
    root: str
    files: tuple[str, ...]

    def named_in(self, message: str) -> bool:
        return any(f in message for f in self.files)


# --------------------------------------------------------------------------------------------
# Mutations


def _number_mutations(value: float) -> list[tuple[str, Any]]:
    return [
        ("NaN", math.nan),
        ("Infinity", math.inf),
        ("-Infinity", -math.inf),
        ("1e300", 1e300),
        ("10**30", 10**30),
        ("-1", -1),
        ("-1e9", -1e9),
        ("a string", str(value)),
        ("a list", [value]),
        ("true", True),
    ]


def _string_mutations(key: str, value: str) -> list[tuple[str, Any]]:
    if key == "filename":
        return [
            ("../", f"../../{value}"),
            ("absolute", "/etc/hostname"),
            ("no file", f"{value}.gone"),
            ("empty", ""),
        ]
    if key.endswith("token") or key in ("prev", "next"):
        return [("dangling", DANGLING), ("a list", [value]), ("a number", 5), ("null", None)]
    return [("a number", 5), ("a list", [value]), ("null", None)]


def _list_mutations(value: list[Any]) -> list[tuple[str, Any]]:
    if value and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
        return [
            ("truncated", value[:-1]),
            ("a NaN entry", [math.nan, *value[1:]]),
            ("an Inf entry", [*value[:-1], math.inf]),
            ("a 1e300 entry", [1e300, *value[1:]]),
            ("a string entry", [str(value[0]), *value[1:]]),
            ("empty", []),
            ("a number", 1.0),
        ]
    if value and all(isinstance(x, list) for x in value):  # a camera matrix
        return [
            ("truncated", value[:-1]),
            ("a truncated row", [value[0][:-1], *value[1:]]),
            ("a NaN entry", [[math.nan, *value[0][1:]], *value[1:]]),
            ("a number", 1.0),
        ]
    if all(isinstance(x, str) for x in value):  # token lists
        return [("nested", [value]), ("dangling", [DANGLING]), ("a string", "x")]
    return [("a number", 1.0)]


def bad_values(key: str, value: Any, other_tokens: list[str]) -> list[tuple[str, Any]]:
    """(label, value) of every mutation of field ``key`` holding ``value`` (``DELETE`` removes
    it); ``other_tokens`` are the other records' tokens of the table (for a duplicate token)."""
    out: list[tuple[str, Any]] = [("missing", DELETE)]
    if key == "token":
        return [*out, ("a duplicate token", other_tokens[0]), ("a list", [value])]
    if isinstance(value, bool):
        return [*out, ('"false"', "false"), ('"true"', "true"), ("0", 0), ("null", None)]
    if isinstance(value, (int, float)):
        return out + _number_mutations(value)
    if isinstance(value, str):
        return out + _string_mutations(key, value)
    if isinstance(value, list):
        return out + _list_mutations(value)
    return out


#: Cases every run includes (table, field, label; on a random record with that field): one of each
#: kind of damage.
FORCED: tuple[tuple[str, str, str], ...] = (
    ("sample_data", "is_key_frame", '"false"'),
    ("sample", "timestamp", "missing"),
    ("sample_annotation", "size", "missing"),
    ("sample_data", "sample_token", "a list"),
    ("sample_annotation", "instance_token", "dangling"),
    ("sample_annotation", "translation", "a NaN entry"),
    ("ego_pose", "rotation", "an Inf entry"),
    ("sample_data", "timestamp", "10**30"),
    ("sample_data", "timestamp", "-1"),
    ("sample_data", "filename", "../"),
    ("sample_annotation", "token", "a duplicate token"),
    ("calibrated_sensor", "translation", "truncated"),
)


def table_cases(
    tables: dict[str, list[dict[str, Any]]], rng: random.Random
) -> Iterator[tuple[str, int, str, str, Any]]:
    """(table, record index, field, label, new value) of :data:`TABLE_CASES` distinct mutations:
    the :data:`FORCED` ones first, then random ones."""
    seen: set[tuple[str, int, str, str]] = set()
    names = sorted(TABLE_WEIGHTS)
    weights = [TABLE_WEIGHTS[n] for n in names]
    forced = list(FORCED)
    while len(seen) < TABLE_CASES:
        if forced:
            table, key, label = forced.pop(0)
            candidates = [i for i, r in enumerate(tables[table]) if key in r]
        else:
            table = rng.choices(names, weights)[0]
            candidates = list(range(len(tables[table])))
            key = label = ""
        i = rng.choice(candidates)
        record = tables[table][i]
        key = key or rng.choice(sorted(record))
        others = [r["token"] for r in tables[table] if r["token"] != record["token"]]
        options = dict(bad_values(key, record[key], others))
        label = label or rng.choice(sorted(options))
        if (table, i, key, label) not in seen:
            seen.add((table, i, key, label))
            yield table, i, key, label, options[label]


def _clone(base: Path, root: Path, replaced: Path) -> None:
    """``base`` as hard links under ``root``, except ``replaced`` (relative), which the caller writes."""
    for path in sorted(base.rglob("*")):
        rel = path.relative_to(base)
        if path.is_dir():
            (root / rel).mkdir(parents=True, exist_ok=True)
        elif rel != replaced:
            os.link(path, root / rel)


def make_table_case(base: Path, out: Path, tables: dict[str, list[dict[str, Any]]], mutation: tuple) -> Case:
    """The dataroot ``out`` with one field of one record changed."""
    table, i, key, label, value = mutation
    rel = Path(VERSION) / f"{table}.json"
    _clone(base, out, rel)
    rows = [dict(r) for r in tables[table]]
    if value is DELETE:
        del rows[i][key]
    else:
        rows[i][key] = value
    (out / rel).write_text(json.dumps(rows))
    files = [str(out / rel)]
    if key == "token" and not isinstance(value, str):
        files += [str(p) for p in sorted((out / VERSION).glob("*.json"))]
    return Case(f"{table}[{i}].{key} = {label}", str(out), tuple(files))


PCD_DAMAGE = ("NaN points", "Inf points", "huge points", "truncated", "empty", "trailing bytes")


def make_pcd_case(base: Path, out: Path, damage: str, rng: random.Random) -> Case:
    """The dataroot ``out`` with one LiDAR file damaged."""
    files = sorted(p.relative_to(base) for p in base.rglob("*.pcd.bin"))
    rel = rng.choice(files)
    _clone(base, out, rel)
    data = (base / rel).read_bytes()
    points = np.frombuffer(data, "<f4").reshape(-1, 5).copy()
    rows = rng.sample(range(len(points)), k=max(1, len(points) // 10))
    if damage == "NaN points":
        points[rows, rng.randrange(5)] = np.nan
    elif damage == "Inf points":
        points[rows, rng.randrange(3)] = -np.inf
    elif damage == "huge points":
        points[rows, :3] = 3e38
    data = {
        "truncated": data[: len(data) - 7],
        "empty": b"",
        "trailing bytes": data + b"\x00\x01\x02",
    }.get(damage, points.tobytes())
    (out / rel).write_bytes(data)
    return Case(f"{rel} {damage}", str(out), (str(out / rel),))


# --------------------------------------------------------------------------------------------
# The worker process


def _address_space_bytes() -> int:
    """This process's virtual size (VmSize), bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise OSError("no VmSize in /proc/self/status")


def _limit_memory(headroom: int) -> None:
    """Caps this process's address space at its current size + ``headroom`` bytes."""
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _address_space_bytes() + headroom
    resource.setrlimit(
        resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard)
    )


def _serve(conn: Connection, headroom: int, warm_up: tuple[str, str]) -> None:
    """Worker: converts ``warm_up`` (a dataroot and an output folder: everything a conversion
    loads is then loaded), caps its address space, then runs each (case root, policy, output
    folder) it receives through ``prep.nuscenes`` and sends back what happened, until None."""
    logging.disable(logging.WARNING)  # the skipped records' warnings: thousands of lines
    original = pipeline.process_scene
    results: list[Any] = []

    def recording(task: Any, progress: Any = None) -> Any:  # the SceneResults of the run
        result = original(task, progress)
        results.append(result)
        return result

    pipeline.process_scene = recording
    _run_case(warm_up[0], "raise", warm_up[1])
    _limit_memory(headroom)
    conn.send("ready")
    while (job := conn.recv()) is not None:
        results.clear()
        outcome = _run_case(*job)
        outcome["scene_errors"] = [(r.error, r.error_is_input) for r in results if r.error is not None]
        conn.send(outcome)


def _run_case(root: str, policy: str, out: str) -> dict[str, Any]:
    try:
        summary = prep.nuscenes(out, dataroot=root, pipeline=CHEAP_PIPELINE, on_error=policy, progress=False)  # type: ignore[arg-type]
        return {"converted": True, "frames": summary.frames_written, "non_finite": non_finite_values(out)}
    except PrepError as e:
        return {"converted": False, "error": str(e)}
    except Exception as e:  # anything else (MemoryError included) is what the harness looks for
        return {"crashed": f"{type(e).__name__}: {e}\n{traceback.format_exc()}"}


class Worker:
    """A worker process with capped memory, restarted after a case that hangs or kills it."""

    def __init__(self, warm_up: tuple[str, str]):
        self.warm_up = warm_up
        self._start()

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        args = (child, MEMORY_HEADROOM, self.warm_up)
        self.process = ctx.Process(target=_serve, args=args, daemon=True)
        self.process.start()
        child.close()
        if not self.conn.poll(120) or self.conn.recv() != "ready":
            raise RuntimeError("the fuzz worker did not start")

    def run(self, root: str, policy: str, out: str) -> dict[str, Any]:
        """The outcome of one case, or ``crashed`` if the worker hangs past CASE_SECONDS or dies."""
        try:
            self.conn.send((root, policy, out))
            if self.conn.poll(CASE_SECONDS):
                return self.conn.recv()
            why = f"no answer within {CASE_SECONDS} s (a hang)"
        except (EOFError, OSError) as e:
            why = f"the worker died ({type(e).__name__}, exit code {self.process.exitcode})"
        self.close()
        self._start()
        return {"crashed": why, "scene_errors": []}

    def close(self) -> None:
        if self.process.is_alive():
            with contextlib.suppress(OSError):
                self.conn.send(None)
            self.process.join(5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()


# --------------------------------------------------------------------------------------------
# The test


def problems_of(case: Case, policy: str, outcome: dict[str, Any]) -> list[str]:
    """What is wrong with a case's outcome (empty if it converted cleanly or failed properly)."""
    where = f"{case.name} [{policy}]"
    if "crashed" in outcome:
        return [f"{where}: {outcome['crashed']}"]
    out = []
    for error, is_input in outcome["scene_errors"]:
        if not is_input:
            out.append(f"{where}: a scene failed with a toolkit bug: {error}")
        elif not case.named_in(error):
            out.append(f"{where}: a scene's error does not name {case.files[0]}: {error}")
    if outcome["converted"]:
        out += [f"{where}: non-finite value in the cache: {p}" for p in outcome["non_finite"]]
    elif not case.named_in(outcome["error"]):
        out.append(f"{where}: the error does not name {case.files[0]}: {outcome['error']}")
    return out


def policies_of(k: int) -> tuple[str, ...]:
    """The error policies case ``k`` runs under: both for the forced cases and the LiDAR files,
    one (alternating) for the random ones, to keep the test short."""
    if k < len(FORCED) or k >= TABLE_CASES:
        return POLICIES
    return (POLICIES[k % 2],)


@pytest.fixture(scope="module")
def fuzz_base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return export_tiny_nuscenes(tmp_path_factory.mktemp("fuzz-base") / "data").resolve()


def test_mutated_nuscenes_inputs_convert_to_finite_caches_or_fail_naming_the_file(
    fuzz_base: Path, tmp_path: Path
) -> None:
    rng = random.Random(SEED)
    tables = {t: json.loads((fuzz_base / VERSION / f"{t}.json").read_text()) for t in TABLE_WEIGHTS}
    cases = [
        make_table_case(fuzz_base, tmp_path / f"table-{k}", tables, m)
        for k, m in enumerate(table_cases(tables, rng))
    ]
    cases += [
        make_pcd_case(fuzz_base, tmp_path / f"pcd-{k}", PCD_DAMAGE[k % len(PCD_DAMAGE)], rng)
        for k in range(PCD_CASES)
    ]
    assert len(cases) == TABLE_CASES + PCD_CASES >= 50 + PCD_CASES
    worker = Worker((str(fuzz_base), str(tmp_path / "warm-up")))
    problems: list[str] = []
    outcomes: dict[str, list[str]] = {policy: [] for policy in POLICIES}
    try:
        for k, case in enumerate(cases):
            for policy in policies_of(k):
                outcome = worker.run(case.root, policy, str(tmp_path / f"cache-{k}-{policy}"))
                problems += problems_of(case, policy, outcome)
                outcomes[policy].append("converted" if outcome.get("converted") else "failed")
    finally:
        worker.close()
    assert not problems, "\n".join(problems)
    # The harness is not vacuous: under "raise" most cases fail (the bad record stops the run),
    # under "skip" most convert (the bad record is left out).
    raised, skipped = outcomes["raise"], outcomes["skip"]
    assert raised.count("failed") > len(raised) // 2 and skipped.count("converted") > len(skipped) // 2, (
        outcomes
    )
