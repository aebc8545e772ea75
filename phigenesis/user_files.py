"""Files a user names, read with a size limit, and the checks their JSON or YAML values share.

:func:`read_regular_file` reads only a regular file, and only up to a limit: ``/dev/zero`` or a
multi-gigabyte file is refused before anything is read, and a FIFO is refused without blocking (it is
opened with ``O_NONBLOCK`` and checked with ``fstat``, so a path swapped for a FIFO after the first
check does not hang either). :func:`read_small_file` is the same for the small text files of the
command line (rig, path and trajectory files, 1 MiB); :func:`read_config_file` reads a YAML config
file with it. Refusals are the caller's own error class, naming the file.
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from phigenesis.errors import PhiGenesisError
from phigenesis.options import ConfigError

#: Largest file :func:`read_small_file` reads by default, bytes (rig, path and trajectory files).
MAX_SMALL_FILE_BYTES = 1 << 20


def read_regular_file(
    path: str | os.PathLike[str], what: str, error: type[PhiGenesisError], max_bytes: int | None = None
) -> bytes:
    """The bytes of the regular file ``path``, of at most ``max_bytes`` bytes (None: any size).

    Args:
        path: the file.
        what: what the file is, for messages ("trajectory file").
        error: the error class raised, with a message that starts with the path.
        max_bytes: the largest size read.

    Raises:
        ``error``: for a missing or unreadable file, anything but a regular file (a folder, a FIFO,
            a device) or a file larger than ``max_bytes``.
    """
    path = Path(path)
    limit = max_bytes if max_bytes is not None else -1
    try:
        _check_regular(path, os.stat(path), what, error, max_bytes)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        with os.fdopen(fd, "rb") as f:
            _check_regular(path, os.fstat(f.fileno()), what, error, max_bytes)
            data = f.read(limit + 1 if limit >= 0 else -1)
    except OSError as e:
        raise error(f"{path}: cannot read the {what} ({e.strerror or e})") from None
    if max_bytes is not None and len(data) > max_bytes:  # it grew after the check
        raise error(f"{path}: larger than {max_bytes} bytes, the most a {what} may hold")
    return data


def read_small_file(
    path: str | os.PathLike[str],
    what: str,
    error: type[PhiGenesisError],
    max_bytes: int = MAX_SMALL_FILE_BYTES,
) -> str:
    """The UTF-8 text of the regular file ``path`` of at most ``max_bytes`` bytes
    (:func:`read_regular_file`); ``error`` also for text that is not UTF-8."""
    data = read_regular_file(path, what, error, max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text (byte {e.start}); a {what} is a text file") from None


def _check_regular(
    path: Path, st: os.stat_result, what: str, error: type[PhiGenesisError], max_bytes: int | None
) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file"
        raise error(f"{path}: {kind}; a {what} must be a regular file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes, the most a {what} may hold")


def check_keys(
    value: Any, allowed: Sequence[str], where: str, error: type[PhiGenesisError], noun: str = "key"
) -> Mapping[str, Any]:
    """``value`` if it is a mapping whose keys are all in ``allowed``; otherwise ``error`` naming
    ``where`` and the first unknown key (called a ``noun``) beside the allowed ones."""
    if not isinstance(value, Mapping):
        raise error(f"{where}: must be a mapping, got {type(value).__name__}")
    unknown = sorted(str(k) for k in value if k not in allowed)
    if unknown:
        raise error(f"{where}: unknown {noun} {unknown[0]!r}; the {noun}s are {', '.join(allowed)}")
    return value


def is_number(value: Any) -> bool:
    """Whether a parsed JSON/YAML value is a real number that is finite as a float (an int or a
    float; not a bool, not a numeric string, not an integer beyond the float range)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def matrix_problem(value: Any, rows: int, cols: int) -> str | None:
    """What keeps a parsed JSON/YAML value from being ``rows`` lists of ``cols`` finite numbers
    (:func:`is_number`), e.g. ``"[0][3] is '1.5', not a finite number"``; None if nothing does."""
    if not (isinstance(value, list) and len(value) == rows and all(isinstance(r, list) for r in value)):
        return f"is not {rows} rows of {cols} numbers"
    for i, row in enumerate(value):
        if len(row) != cols:
            return f"row {i} has {len(row)} values, not {cols}"
        for j, x in enumerate(row):
            if not is_number(x):
                return f"[{i}][{j}] is {x!r}, not a finite number"
    return None


def read_config_file(path: Path) -> dict[str, Any]:
    """The mapping of options in a YAML config file (an empty file: none). A missing file, one that
    is not a regular file or is over 1 MiB (:func:`~phigenesis.user_files.read_small_file`), invalid
    YAML and a YAML value other than a mapping raise :class:`~phigenesis.options.ConfigError`
    naming the file."""
    text = read_small_file(path, "config", ConfigError)
    try:
        values = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: cannot read the config ({' '.join(str(e).split())})") from None
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ConfigError(
            f"{path}: a config is a mapping of options (key: value), not a YAML {type(values).__name__}"
        )
    return values
