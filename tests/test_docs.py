"""The README stays true: its test command is what CI runs, its schema names every column, and its
plain-pyarrow reading example runs against a real cache without importing phigenesis."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

from phigenesis.data.schema import BoxColumns, CameraColumns, FrameColumns, LidarColumns

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _between(text: str, start: str, end: str) -> str:
    return text.split(start, 1)[1].split(end, 1)[0]


def test_ci_runs_the_readme_test_command():
    block = _between(README, "<!-- test-command -->", "<!-- /test-command -->")
    command = [line for line in block.splitlines() if line and not line.startswith("```")]
    assert len(command) == 1 and "pytest" in command[0]
    ci = (ROOT / ".ci" / "run").read_text()
    assert "<!-- test-command -->" in ci and 'eval "$test_command"' in ci


def test_readme_gives_exactly_two_setup_commands_that_install_pinned_torch():
    setup = _between(README, "## Set-up on a fresh machine", "\n## ")
    commands = re.findall(r"```bash\n(.*?)\n```", setup, flags=re.S)
    assert len(commands) == 2
    assert "phigenesis-prep synthetic" in commands[0] and "pytest" in commands[1]
    assert all("torch==2.13.0" in c for c in commands)


def test_readme_schema_documents_every_cache_column():
    schema_doc = _between(README, "<!-- schema -->", "<!-- /schema -->")
    for cls in (FrameColumns, CameraColumns, LidarColumns, BoxColumns):
        for f in dataclasses.fields(cls):
            assert f"`{f.name}`" in schema_doc or f.name in schema_doc, (
                f"{cls.__name__}.{f.name} undocumented"
            )


def test_readme_plain_pyarrow_example_runs_without_phigenesis(tiny_cache: Path):
    code = re.search(r"### Reading a cache without this package\n\n```python\n(.*?)```", README, re.S).group(
        1
    )
    assert "pandas" not in code and "pd." not in code  # the set-up command does not install pandas
    code = code.replace('pathlib.Path("cache")', f"pathlib.Path({str(tiny_cache)!r})")
    code += (
        "\nassert rgb.shape[2] == 3 and depth_m.shape == rgb.shape[:2] and points_ego.shape[1] == 3"
        "\nassert len(boxes) > 0 and 'center_world' in boxes[0] and len(frames) == table.num_rows"
        "\nimport sys; assert 'phigenesis' not in sys.modules"
        "\nprint('ok', table.num_rows)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "ok 3"
