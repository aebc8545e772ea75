"""What every command-line front end shares: argument types, logging, and turning errors into exit 2."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

from phigenesis.data.shards import CacheError
from phigenesis.train.checkpoint import CheckpointError

#: Errors a command reports as ``PROG: error: ...`` on stderr with exit status 2 (bad input, not bugs).
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, CacheError, CheckpointError, OSError)


def positive(value: str) -> int:
    """argparse type: an integer of at least 1."""
    n = int(value)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def size_hw(value: str) -> tuple[int, int]:
    """argparse type: ``HxW`` in pixels (e.g. ``48x72``)."""
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW (e.g. 128x192), got {value!r}") from None
    return h, w


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )


def dispatch(
    prog: str,
    args: argparse.Namespace,
    commands: dict[str, Callable[[argparse.Namespace], int]],
    errors: tuple[type[BaseException], ...] = USER_ERRORS,
) -> int:
    """Runs ``commands[args.command]``; an error of ``errors`` is printed as ``PROG: error: ...`` on
    stderr and gives exit status 2."""
    setup_logging(getattr(args, "verbose", False))
    try:
        return commands[args.command](args)
    except errors as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
