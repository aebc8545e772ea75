"""Shared helpers of the benchmark scripts: markdown tables and named sections of BENCHMARKS.md.

A script builds a :class:`Report`, adds tables as it measures (each is printed at once), and
finally calls :meth:`Report.write`. With the script's ``--update`` flag (:func:`add_update_flag`)
that replaces the script's section of ``BENCHMARKS.md`` (or appends it) between the markers
``<!-- section:NAME -->`` and ``<!-- /section:NAME -->``; without it the tracked file is left
alone and the section goes to ``benchmarks/out/NAME.md`` (ignored by git), so reproducing a
figure never rewrites the published table.
Every section starts with a header naming the machine, the exact command, the date and the
versions of the main libraries, so numbers are never quoted without their context.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import platform
import re
import shlex
import statistics
import subprocess
import sys
from argparse import ArgumentParser
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS_MD = REPO_ROOT / "BENCHMARKS.md"
#: Where a run without ``--update`` leaves its section (one file per section, ignored by git).
SCRATCH_DIR = REPO_ROOT / "benchmarks" / "out"
#: The distributions whose versions every section header records.
VERSIONED_PACKAGES = ("torch", "open3d", "numpy", "pyarrow")
_TITLE = (
    "# Benchmarks\n\n"
    "Measured performance of phigenesis. Each section below is written by the script in `benchmarks/` "
    "that its header names; rerun that script with `--update` (on a quiet machine) to replace the "
    "section; without it the script prints its tables and saves the section under `benchmarks/out/`. "
    "Timings are medians over repeated runs unless a table says otherwise.\n"
)
_NUMBER = re.compile(r"^[-+]?[\d,]*\.?\d+(e[-+]?\d+)?\s*[%×x]?$", re.IGNORECASE)


def round_ratio(times: list[float], floor: list[float]) -> float:
    """Median over rounds of a run's time over the floor's time in the same round: on a VM whose
    speed drifts by tens of percent within minutes, steadier than the ratio of the medians."""
    return statistics.median(t / f for t, f in zip(times, floor, strict=True))


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub markdown table; columns whose cells are all numbers (or empty) are right-aligned."""
    cells = [[str(c) for c in row] for row in rows]
    for row in cells:
        if len(row) != len(headers):
            raise ValueError(f"row {row} has {len(row)} cells, the table has {len(headers)} columns")
    numeric = [
        bool(cells) and all(_NUMBER.match(row[j]) or row[j] in ("", "—") for row in cells)
        for j in range(len(headers))
    ]
    widths = [max(len(str(h)), *(len(row[j]) for row in cells), 3) for j, h in enumerate(headers)]

    def line(values: Sequence[str]) -> str:
        padded = [
            v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = (
        "|"
        + "|".join(
            "-" * (w + 1) + ":" if num else "-" * (w + 2) for w, num in zip(widths, numeric, strict=True)
        )
        + "|"
    )
    return "\n".join([line([str(h) for h in headers]), rule, *(line(row) for row in cells)])


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (``platform.processor()`` where that is missing)."""
    with contextlib.suppress(OSError):
        for text_line in Path("/proc/cpuinfo").read_text().splitlines():
            if text_line.lower().startswith("model name"):
                return text_line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def ram_gib() -> float | None:
    """Total RAM in GiB from /proc/meminfo, or None where that is unavailable."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        for text_line in Path("/proc/meminfo").read_text().splitlines():
            if text_line.startswith("MemTotal:"):
                return int(text_line.split()[1]) / 2**20
    return None


def machine_summary() -> str:
    """CPU model, core count (usable by this process / online), RAM and the load average now."""
    online = os.cpu_count() or 0
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else online
    cores = f"{usable} cores" if usable == online else f"{usable} of {online} cores"
    ram = ram_gib()
    parts = [cpu_model(), cores, f"{ram:.1f} GiB RAM" if ram is not None else "RAM unknown"]
    if hasattr(os, "getloadavg"):
        parts.append("load average {:.2f} / {:.2f} / {:.2f} at start".format(*os.getloadavg()))
    return ", ".join(parts)


def versions(packages: Sequence[str] = VERSIONED_PACKAGES) -> str:
    """``python X, torch Y, ...`` from the installed distributions' metadata (nothing is imported)."""
    out = [f"python {platform.python_version()}"]
    for name in packages:
        try:
            out.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name} (not installed)")
    return ", ".join(out)


def git_revision() -> str:
    """The repository's short commit, marked ``+dirty`` with uncommitted changes; "unknown" without git."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


def command_line() -> str:
    """The command that started this process, exactly as it was given (interpreter included)."""
    return shlex.join(getattr(sys, "orig_argv", [sys.executable, *sys.argv]))


def run_header() -> str:
    """Markdown lines naming the machine, command, date, library versions and commit of this run."""
    now = datetime.datetime.now().astimezone()
    return "\n".join(
        [
            f"- Machine: {machine_summary()}",
            f"- Command: `{command_line()}` (in `{os.getcwd()}`)",
            f"- Date: {now:%Y-%m-%d %H:%M %Z}; commit {git_revision()}",
            f"- Versions: {versions()}",
        ]
    )


def update_section(name: str, body: str, path: Path = BENCHMARKS_MD) -> Path:
    """Replaces section ``name`` of the markdown file at ``path`` with ``body`` (appends it if absent).

    The file is created with a short title paragraph if missing, and rewritten atomically.
    """
    begin, end = f"<!-- section:{name} -->", f"<!-- /section:{name} -->"
    block = f"{begin}\n{body.strip()}\n{end}"
    text = path.read_text() if path.exists() else _TITLE
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text, count=1)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


class Report:
    """One benchmark script's section: a header, then tables printed as they are added."""

    def __init__(self, name: str, title: str, intro: str = "", header: str | None = None):
        """``header`` replaces :func:`run_header`'s lines (figures measured on another machine)."""
        self.name = name
        self.parts = [f"## {title}", run_header() if header is None else header]
        if intro:
            self.parts.append(intro.strip())
        print("\n\n".join(self.parts), end="\n\n", flush=True)

    def table(
        self, heading: str, headers: Sequence[str], rows: Sequence[Sequence[object]], note: str = ""
    ) -> None:
        """Adds (and prints) a table under a ``###`` heading, with an optional note below it."""
        part = f"### {heading}\n\n{markdown_table(headers, rows)}"
        if note:
            part += f"\n\n{note.strip()}"
        self.parts.append(part)
        print(part, end="\n\n", flush=True)

    def text(self, paragraph: str) -> None:
        """Adds (and prints) a paragraph of markdown."""
        self.parts.append(paragraph.strip())
        print(paragraph.strip(), end="\n\n", flush=True)

    def write(self, update: bool, path: Path = BENCHMARKS_MD) -> Path:
        """Writes the section into ``path`` (see :func:`update_section`) when ``update``, else into
        its own file under :data:`SCRATCH_DIR` (``path`` untouched); prints where it went."""
        body = "\n\n".join(self.parts)
        if update:
            written = update_section(self.name, body, path)
            print(f"wrote section '{self.name}' of {written}", flush=True)
            return written
        SCRATCH_DIR.mkdir(parents=True, exist_ok=True)
        written = SCRATCH_DIR / f"{self.name}.md"
        tmp = written.with_name(f".{written.name}.{os.getpid()}.tmp")
        tmp.write_text(body.strip() + "\n")
        os.replace(tmp, written)
        print(
            f"wrote section '{self.name}' to {written}; {path.name} is unchanged "
            "(pass --update to replace its section)",
            flush=True,
        )
        return written


def output_path(repo_relative: str | Path, update: bool) -> Path:
    """Where a benchmark writes a tracked artefact (a figure under ``docs/images``): the tracked
    path itself with ``--update``, else a file of the same name under :data:`SCRATCH_DIR`."""
    if update:
        return REPO_ROOT / repo_relative
    SCRATCH_DIR.mkdir(parents=True, exist_ok=True)
    return SCRATCH_DIR / Path(repo_relative).name


def add_update_flag(parser: ArgumentParser) -> None:
    """Gives a benchmark script the ``--update`` flag :meth:`Report.write` obeys."""
    parser.add_argument(
        "--update",
        action="store_true",
        help="replace this script's section of BENCHMARKS.md (default: write benchmarks/out/SECTION.md)",
    )
