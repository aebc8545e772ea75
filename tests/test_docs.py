"""The README and the guide stay true: the README's test command is what CI runs, the README stays short
and its quick-start reading example runs, the guide's schema names every column and its plain-pyarrow
reading example runs against a real cache without importing phigenesis, and every relative link of the
README and the guide leads to a file of the repository."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

from phigenesis.data.schema import BoxColumns, CameraColumns, FrameColumns, LidarColumns

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
GUIDE = ROOT / "docs" / "guide"
CACHES = (GUIDE / "caches.md").read_text()
#: Files other parts of the docs work create (the generated reference and the design index): links to
#: them are allowed before they exist. Nothing else may be missing.
PLANNED_DOCS = {
    "docs/reference/cli.md",
    "docs/reference/schema.md",
    "docs/reference/configs.md",
    "docs/design/README.md",
}


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
    schema_doc = _between(CACHES, "<!-- schema -->", "<!-- /schema -->")
    for cls in (FrameColumns, CameraColumns, LidarColumns, BoxColumns):
        for f in dataclasses.fields(cls):
            assert f"`{f.name}`" in schema_doc or f.name in schema_doc, (
                f"{cls.__name__}.{f.name} undocumented"
            )


def test_readme_plain_pyarrow_example_runs_without_phigenesis(tiny_cache: Path):
    code = re.search(r"### Reading a cache without this package\n\n```python\n(.*?)```", CACHES, re.S).group(
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


def test_readme_quick_start_reads_a_cache_without_phigenesis(tiny_cache: Path):
    code = _between(README, "<!-- quickstart-read -->\n```python\n", "```\n<!-- /quickstart-read -->")
    assert 'pathlib.Path("cache")' in code
    code = code.replace('pathlib.Path("cache")', f"pathlib.Path({str(tiny_cache)!r})")
    code += "\nimport sys; assert 'phigenesis' not in sys.modules"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert result.returncode == 0, result.stderr
    rows, camera, width, height, *_ = result.stdout.split()
    assert (rows, camera) == ("3", "FRONT") and int(width) > 0 and int(height) > 0


def test_readme_has_at_most_200_lines():
    assert len(README.splitlines()) <= 200


def _relative_links(path: Path) -> list[str]:
    """The relative link targets of a markdown file, outside code blocks and code spans, without anchors."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t.split("#", 1)[0] for t in targets if not re.match(r"[a-z]+:|#", t)]


def test_every_relative_link_of_the_readme_and_the_guide_leads_to_a_file_of_the_repository():
    pages = [ROOT / "README.md", *sorted(GUIDE.glob("*.md"))]
    assert len(pages) > 9
    missing = []
    for page in pages:
        for target in _relative_links(page):
            resolved = (page.parent / target).resolve()
            assert resolved.is_relative_to(ROOT), f"{page.name}: {target} leads outside the repository"
            relative = resolved.relative_to(ROOT).as_posix()
            if not resolved.exists() and relative not in PLANNED_DOCS:
                missing.append(f"{page.relative_to(ROOT)}: {target}")
    assert not missing, missing
