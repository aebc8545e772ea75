"""Benchmark scripts print their tables and leave BENCHMARKS.md alone unless asked (``--update``)."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import _report  # noqa: E402

SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))


def _report_file(tmp_path: Path) -> Path:
    path = tmp_path / "BENCHMARKS.md"
    path.write_text("# Benchmarks\n\n<!-- section:demo -->\nold figures\n<!-- /section:demo -->\n\ntail\n")
    return path


def test_write_without_update_leaves_the_tracked_file_and_saves_the_section(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(_report, "SCRATCH_DIR", tmp_path / "out")
    path = _report_file(tmp_path)
    before = path.read_bytes()
    report = _report.Report("demo", "Demo", header="- Machine: test")
    report.table("Figures", ["a", "b"], [[1, 2.5]])
    written = report.write(update=False, path=path)
    assert path.read_bytes() == before
    assert written == tmp_path / "out" / "demo.md"
    assert re.search(r"\|\s*1\s*\|\s*2\.5\s*\|", written.read_text())
    assert "pass --update" in capsys.readouterr().out


def test_write_with_update_replaces_only_its_section(tmp_path, monkeypatch):
    monkeypatch.setattr(_report, "SCRATCH_DIR", tmp_path / "out")
    path = _report_file(tmp_path)
    report = _report.Report("demo", "Demo", header="- Machine: test")
    report.text("new figures")
    assert report.write(update=True, path=path) == path
    text = path.read_text()
    assert "old figures" not in text and "new figures" in text
    assert text.endswith("tail\n") and text.count("<!-- section:demo -->") == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_every_benchmark_script_writes_only_with_update(script: Path):
    """Each script that builds a Report gives itself ``--update`` and passes it to every write."""
    tree = ast.parse(script.read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    names = {n.func.id for n in calls if isinstance(n.func, ast.Name)}
    if "Report" not in names:
        pytest.skip(f"{script.name} writes no BENCHMARKS.md section")
    assert "add_update_flag" in names, f"{script.name} has no --update flag"
    writes = [
        n
        for n in calls
        if isinstance(n.func, ast.Attribute)
        and n.func.attr == "write"
        and isinstance(n.func.value, ast.Name)
        and n.func.value.id in {"report", "rep", "stage"}
    ]
    assert writes, f"{script.name} never writes its section"
    for call in writes:
        where = f"{script.name}:{call.lineno}"
        assert any(k.arg == "update" for k in call.keywords), f"{where} writes without update="


def test_a_real_benchmark_run_without_update_leaves_benchmarks_md_byte_identical(tmp_path, monkeypatch):
    import rangeview

    monkeypatch.setattr(_report, "SCRATCH_DIR", tmp_path)
    before = _report.BENCHMARKS_MD.read_bytes()
    rangeview.main(["--repeats", "1"])
    assert _report.BENCHMARKS_MD.read_bytes() == before
    section = (tmp_path / "rangeview.md").read_text()
    assert section.startswith("## Range views: speed and size") and "Milliseconds per frame" in section


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_every_benchmark_script_finds_its_helpers_as_a_script_and_as_a_module(script: Path):
    """``python benchmarks/X.py`` and ``python -m benchmarks.X`` both work: each script puts its own
    folder on the path before importing ``_report`` (or a sibling script)."""
    text = script.read_text()
    if "_report import" not in text:
        pytest.skip(f"{script.name} imports no helper")
    assert "from benchmarks._report" not in text
    insert = text.find("sys.path.insert(0, str(Path(__file__).resolve().parent))")
    assert 0 <= insert < text.find("from _report import"), script.name


@pytest.mark.parametrize("form", ["script", "module"])
@pytest.mark.parametrize("name", ["depth", "stage2_variants"])
def test_a_benchmark_runs_both_ways(name: str, form: str):
    import subprocess

    argv = [f"benchmarks/{name}.py"] if form == "script" else ["-m", f"benchmarks.{name}"]
    done = subprocess.run(
        [sys.executable, *argv, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "--update" in done.stdout
