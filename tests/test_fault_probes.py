"""benchmarks/fault_probes.py (issue 53's probes) through its own functions, so that the script
cannot rot unnoticed: its child runner (exit, peak memory, time limit, memory cap), a config probe,
a cache probe and the summary figures."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import fault_probes as fp  # noqa: E402

#: The verdicts a refusal probe may give, before and after issue 53's fixes.
VERDICTS = {"clear error", "vague error", "bug", "accepted", "hang", "memory", "crash"}


@pytest.fixture
def work(tmp_path: Path) -> fp.Work:
    return fp.Work(tmp_path / "work", timeout_s=60.0, mem_cap_mb=4096.0)


def test_the_probes_cover_every_item_of_the_issue() -> None:
    assert {p.item for p in fp.PROBES} == {str(i) for i in range(1, 10)}
    names = [p.name for p in fp.PROBES]
    assert len(names) == len(set(names))
    assert [p.name for p in fp.selected(["ply-*"])] == [n for n in names if n.startswith("ply-")]
    assert {p.item for p in fp.selected(["7"])} == {"7"}


def test_a_child_reports_its_exit_peak_memory_time_limit_and_memory_cap(work: fp.Work) -> None:
    python = sys.executable
    big = work.run("big", [python, "-c", "b = bytearray(200 * 2**20); print('done')"])
    assert big.status == 0 and big.message == "done" and big.peak_mb > 200
    capped = fp.Work(work.root, timeout_s=60.0, mem_cap_mb=200.0)
    oom = capped.run("oom", [python, "-c", "b = bytearray(400 * 2**20)"])
    assert oom.hit_memory and fp.refusal_verdict(oom) == "memory"
    slow = work.run("slow", [python, "-c", "import time; time.sleep(60)"], timeout_s=1.0)
    assert slow.timed_out and fp.refusal_verdict(slow) == "hang" and slow.seconds < 10
    says = "import sys; sys.exit('phigenesis-x: error: boom (unexpected: a bug')"
    bug = work.run("bug", [python, "-c", says])
    assert bug.message.startswith("phigenesis-x: error") and fp.refusal_verdict(bug) == "bug"


def test_a_config_probe_runs_the_real_command_and_gives_a_verdict(work: fp.Work) -> None:
    work.__dict__["cache"] = work.root / "no-cache"  # the config is refused before the cache is read
    row = fp._yaml_list(work)
    assert row.verdict in VERDICTS - {"accepted", "hang"} and row.exit in {"1", "2"}
    assert row.message.startswith("phigenesis-train: error") and row.peak_mb and row.peak_mb > 50


def test_a_cache_probe_copies_the_cache_and_runs_verify(work: fp.Work, tiny_cache: Path) -> None:
    work.__dict__["cache"] = tiny_cache
    row = fp._manifest_symlink(work)
    assert row.verdict in {"accepted", "clear error"}
    assert "manifest-symlink-outside/cache" in row.message
    manifest = tiny_cache / "manifest.json"
    assert manifest.is_file() and not manifest.is_symlink()  # the probe changed its own copy
    figures = fp.summary([row])
    assert len(figures) == 7 and all(line.startswith("- ") for line in figures)
