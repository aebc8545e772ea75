"""keep_freed_memory: a process that frees and re-allocates a frame's worth of memory stops
taking its pages from the kernel again."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

PROBE = """
import resource, sys
from phigenesis.malloc_tuning import keep_freed_memory
if sys.argv[1] == "1":
    assert keep_freed_memory()
def frame():
    # a frame's allocations: several blocks alive together, then all freed
    blocks = [bytearray(3 << 20) for _ in range(8)]
    for b in blocks:
        b[::4096] = b"x" * len(b[::4096])
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _probe(code: str, *args: str, env: dict[str, str] | None = None) -> list[str]:
    """What a fresh Python running ``code`` prints, split into words."""
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, check=True, env=env
    )
    return out.stdout.split()


def _page_faults(keep: bool) -> int:
    # Not inherited from this process, which may have run phigenesis-prep's main already.
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    return int(_probe(PROBE, "1" if keep else "0", env=env)[0])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the thresholds are glibc's")
def test_kept_memory_turns_ten_frames_of_page_faults_into_almost_none() -> None:
    pages_per_frame = 8 * (3 << 20) // 4096
    default = _page_faults(keep=False)
    kept = _page_faults(keep=True)
    assert default > 5 * pages_per_frame, default  # glibc hands the blocks back and takes them again
    assert kept < pages_per_frame // 10, kept


def test_the_settings_reach_processes_started_later(monkeypatch: pytest.MonkeyPatch) -> None:
    from phigenesis import malloc_tuning

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.setenv("PHIGENESIS_MALLOC", "0")
    assert not malloc_tuning.keep_freed_memory()
    assert "MALLOC_TRIM_THRESHOLD_" not in os.environ
    monkeypatch.delenv("PHIGENESIS_MALLOC")
    if platform.libc_ver()[0] == "glibc":
        assert malloc_tuning.keep_freed_memory()
        assert os.environ["MALLOC_TRIM_THRESHOLD_"] == str(malloc_tuning.TRIM_THRESHOLD_BYTES)
        assert os.environ["MALLOC_MMAP_THRESHOLD_"] == str(malloc_tuning.MMAP_THRESHOLD_BYTES)


# Each probe first turns huge pages back on for itself: it inherits the setting, and a test that ran
# phigenesis-prep's main in this process turned them off here.
RESET = "import ctypes; ctypes.CDLL(None).prctl(41, 0, 0, 0, 0)\n"

HUGE_PROBE = (
    RESET
    + """
import sys
import numpy as np
from phigenesis import malloc_tuning
if sys.argv[1] == "1":
    assert malloc_tuning.avoid_huge_page_faults()
a = np.ones(64 << 20, np.uint8)  # numpy advises huge pages for arrays of 4 MiB and more
huge_kib = 0
with open("/proc/self/smaps_rollup") as f:
    for line in f:
        if line.startswith("AnonHugePages:"):
            huge_kib = int(line.split()[1])
print(malloc_tuning.huge_pages_disabled(), huge_kib)
"""
)


def _huge_pages(disable: bool) -> tuple[bool, int]:
    disabled, kib = _probe(HUGE_PROBE, "1" if disable else "0")
    return disabled == "True", int(kib)


@pytest.mark.skipif(platform.system() != "Linux", reason="PR_SET_THP_DISABLE is Linux's")
def test_huge_pages_off_means_a_large_array_gets_none() -> None:
    control_disabled, control_kib = _huge_pages(disable=False)
    assert not control_disabled
    disabled, kib = _huge_pages(disable=True)
    assert disabled
    assert kib == 0, kib
    if control_kib == 0:
        pytest.skip("this machine gave the control no huge pages either (THP off or memory fragmented)")


@pytest.mark.skipif(platform.system() != "Linux", reason="PR_SET_THP_DISABLE is Linux's")
def test_huge_pages_setting_is_inherited_and_can_be_turned_off() -> None:
    code = RESET + (
        "import subprocess, sys\n"
        "from phigenesis import malloc_tuning\n"
        "print(malloc_tuning.avoid_huge_page_faults())\n"
        "child = 'from phigenesis import malloc_tuning; print(malloc_tuning.huge_pages_disabled())'\n"
        "out = subprocess.run([sys.executable, '-c', child], capture_output=True, text=True)\n"
        "print(out.stdout.strip())\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PHIGENESIS_MALLOC"}
    assert _probe(code, env=env) == ["True", "True"]
    assert _probe(code, env={**env, "PHIGENESIS_MALLOC": "0"}) == ["False", "False"]
