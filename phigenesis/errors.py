"""The errors the toolkit reports to its users, in one hierarchy.

Every error raised because of what a user gave the toolkit (a dataset file, a cache, a manifest,
a config, a checkpoint, a run folder, an argument) is a :class:`PhiGenesisError`. Its message is
complete on its own: it names the file, the record in it (byte offset, row, table + token) and the
field, and says what is wrong, so the command line prints it as is, without a class path or a
traceback. Anything else that escapes is a bug in the toolkit, and is reported as one.

Hierarchy::

    PhiGenesisError
      PrepError          a run that writes a cache (prep, render, generate, Stage 2 latents)
                         cannot start, or a scene failed
        SourceError      a dataset file is invalid (WaymoFormatError, NuScenesError, ...)
        CacheWriteError  a cache file cannot be written (a full disk; also an OSError; in shards.py)
      CacheError         a cache directory, manifest or shard is missing, malformed or corrupt
      CheckpointError    a checkpoint or a run folder cannot be used
      TrainingDivergedError  a run reached a non-finite loss, gradient or weight (it stops there)

The dataset and checkpoint errors are also ``ValueError`` s, as they were before this module.

A message that tells the caller what to pass names the argument with :func:`argument`: a Python
caller reads the library's keyword (``overwrite=True``), the command line prints the flag
(``--overwrite``, :meth:`PhiGenesisError.command_line_message`).
"""

from __future__ import annotations

import re

#: An argument named in a message: its Python spelling and its command-line spelling between
#: unit separators (a control character that file names practically never hold).
_ARGUMENT = re.compile("\x1f([^\x1f|]*)\\|([^\x1f]*)\x1f")


def argument(python: str, flag: str) -> str:
    """Names an argument inside a :class:`PhiGenesisError` message: ``python`` (the library
    function's keyword, e.g. ``overwrite=True``) where the error reaches Python code, ``flag``
    (``--overwrite``) where a command prints it."""
    return f"\x1f{python}|{flag}\x1f"


def _spelled(message: str, command_line: bool) -> str:
    return _ARGUMENT.sub(lambda m: m.group(2 if command_line else 1), message)


class PhiGenesisError(Exception):
    """An input the toolkit cannot use; the message names the file, the record and the field."""

    def __str__(self) -> str:
        return _spelled(super().__str__(), command_line=False)

    def command_line_message(self) -> str:
        """The message with the arguments it names spelled as command-line flags."""
        return _spelled(super().__str__(), command_line=True)


class PrepError(PhiGenesisError):
    """A run that writes a cache cannot start (its folder is locked by another run or holds
    something else) or a scene failed; the message says which file or scene and why."""


class SourceError(PrepError, ValueError):
    """A dataset file is invalid: the message names the file, the record and the field."""


class CacheError(PhiGenesisError):
    """A cache is missing, malformed or corrupt; the message names the file and the problem."""


class CheckpointError(PhiGenesisError, ValueError):
    """A checkpoint or run folder that cannot be read, or that does not match what was asked for."""


class TrainingDivergedError(PhiGenesisError):
    """A training run reached a non-finite loss term, gradient or weight and stopped there; the
    message names the run folder, the step, the term (or parameter) and the config value most
    likely at fault, and says which checkpoint is kept."""


def describe(error: BaseException) -> str:
    """The one-line message a user sees for ``error``: a :class:`PhiGenesisError`'s own message;
    for anything else (a bug, or an error of a library we call) the exception's type and message."""
    if isinstance(error, PhiGenesisError):
        return str(error)
    return f"{type(error).__name__}: {error}"
