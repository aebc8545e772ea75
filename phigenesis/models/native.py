"""Builds and loads the native CPU rasterizer (``csrc/rasterize_cpu.cpp`` and the forward-only
projection ``csrc/project_cpu.cpp``, one extension) on first use.

Entry point: :func:`load_rasterizer`.

The extension is compiled from the package's own source with PyTorch's C++ extension tools (g++ with
OpenMP, and ninja) into a cache folder, once per machine, torch version and source:
``$PHIGENESIS_NATIVE_DIR`` if set, else ``$XDG_CACHE_HOME/phigenesis/native`` (``~/.cache/...``).
The folder's name hashes everything the binary depends on (the sources, the compiler flags, the
torch and Python versions and this CPU's instruction set, since it is built with ``-march=native``),
so a shared home never hands one machine another's build. When the build fails (no compiler, no
ninja, a read-only cache) the reason is one warning line and :func:`load_rasterizer` returns
``None``: the caller renders with the PyTorch path. ``PHIGENESIS_NATIVE=0`` skips the build.

Two things about PyTorch's builder this module works around. It compiles the sources where they are,
so a second checkout of the same sources (a clone, a worktree) rewrote the folder's ``build.ninja``
and compiled again: the sources are staged into the build folder first (its name hashes them), so
every checkout builds from the same paths and the first build serves them all. And it marks a build
in progress by the existence of a ``lock`` file, which a build killed midway leaves behind: every
later process then waited on it forever, silently. Builds and loads run under a ``flock``
(:func:`~phigenesis.native_cache.build_lock`), which dies with its holder, and under it any ``lock``
file is such a leftover: it is removed, with a warning.
"""

from __future__ import annotations

import hashlib
import logging
import platform
import sys
import threading
from pathlib import Path
from types import ModuleType

import torch

from phigenesis.native_cache import build_lock, cache_root, cpu_flags, native_enabled, write_source_copy

logger = logging.getLogger(__name__)

SOURCE = Path(__file__).parent / "csrc" / "rasterize_cpu.cpp"
#: Every source of the extension (``SOURCE`` holds its Python bindings).
SOURCES = (SOURCE, SOURCE.with_name("project_cpu.cpp"))
CFLAGS = ("-O3", "-march=native", "-fopenmp", "-fno-math-errno")
LDFLAGS = ("-fopenmp",)

_lock = threading.Lock()
_module: ModuleType | None = None
_failure: str | None = None


def build_directory() -> Path:
    """Where this machine's build of the current source lives."""
    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    for part in (repr((CFLAGS, LDFLAGS)).encode(), torch.__version__.encode()):
        digest.update(part)
    digest.update(f"{sys.version_info[:2]} {platform.machine()} {cpu_flags()}".encode())
    return cache_root() / f"rasterize_cpu-{digest.hexdigest()[:16]}"


def stage_sources(build_dir: Path) -> list[Path]:
    """Copies of :data:`SOURCES` in ``build_dir/src`` (written only where missing or different), the
    paths the build compiles: the same for every checkout of the same sources."""
    staged = build_dir / "src"
    staged.mkdir(parents=True, exist_ok=True)
    paths = []
    for source in SOURCES:
        data, copy = source.read_bytes(), staged / source.name
        if not copy.is_file() or copy.read_bytes() != data:
            write_source_copy(copy, data)  # a unique temporary name: without flock others may stage too
        paths.append(copy)
    return paths


def remove_stale_baton(build_dir: Path) -> None:
    """Removes PyTorch's build marker ``build_dir/lock``, which only a killed build leaves when the
    caller holds :func:`~phigenesis.native_cache.build_lock`."""
    baton = build_dir / "lock"
    if not baton.exists():
        return
    logger.warning(
        "removing %s, left by a build of the native rasterizer that was killed before it finished "
        "(PyTorch would wait on it forever); building again",
        baton,
    )
    baton.unlink(missing_ok=True)


def _summary(error: BaseException) -> str:
    """The line of a build failure worth showing: the first compiler error, else the first line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    for line in lines:
        if "error" in line.lower() and not line.lower().startswith("error building extension"):
            return line[:300]
    return (lines[0] if lines else type(error).__name__)[:300]


def load_rasterizer() -> ModuleType | None:
    """The compiled extension, built on first call (about a minute, once), or ``None`` if it cannot be
    built here; the reason is logged once and kept in :func:`failure_reason`."""
    global _module, _failure
    with _lock:
        if _module is not None or _failure is not None:
            return _module
        if not native_enabled():
            _failure = "disabled by PHIGENESIS_NATIVE=0"
            return None
        build_dir = build_directory()
        try:
            # PyTorch's extension builder loads only when the kernel is built
            from torch.utils import cpp_extension

            with build_lock(build_dir) as held:
                if held:
                    remove_stale_baton(build_dir)
                sources = stage_sources(build_dir)
                if not any(build_dir.glob("*.so")):
                    logger.info(
                        "building the native CPU rasterizer (once per machine, about a minute) in %s",
                        build_dir,
                    )
                _module = cpp_extension.load(
                    name=f"phigenesis_{build_dir.name.replace('-', '_')}",
                    sources=[str(source) for source in sources],
                    extra_cflags=list(CFLAGS),
                    extra_ldflags=list(LDFLAGS),
                    build_directory=str(build_dir),
                    verbose=False,
                )
        except Exception as error:  # any build or load failure means the fallback, never a crash
            _failure = _summary(error)
            log = build_dir / "build-error.log"
            try:
                log.write_text(f"{type(error).__name__}: {error}\n")
                where = f" (full log: {log})"
            except OSError:
                where = ""
            logger.warning(
                "native CPU rasterizer not available: %s; rendering with the PyTorch tiled path%s",
                _failure,
                where,
            )
        return _module


def failure_reason() -> str | None:
    """Why the extension is not available (after :func:`load_rasterizer` returned ``None``), else ``None``."""
    return _failure


__all__ = [
    "build_directory",
    "cache_root",
    "failure_reason",
    "load_rasterizer",
    "remove_stale_baton",
    "stage_sources",
]
