"""What every command-line front end shares: the parser (help text without Sphinx markup), argument
types, logging, and how a command ends.

Exit status: 0 done, 1 an unexpected error (a bug: one line, ``-v`` shows the traceback), 2 an input
the toolkit cannot use (:data:`USER_ERRORS`: one line, the error's own message), 130 interrupted
(Ctrl-C: one line saying what was kept and how to resume, as a shell reports 128 + SIGINT).
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import sys
from collections.abc import Callable, Sequence
from typing import Any

from phigenesis.errors import PhiGenesisError, describe

#: Errors a command reports as ``PROG: error: ...`` on stderr with exit status 2 (bad input, not bugs):
#: the toolkit's own (PrepError, SourceError, CacheError, CheckpointError), and the ValueError and
#: OSError that argument checks and file access raise.
USER_ERRORS: tuple[type[BaseException], ...] = (PhiGenesisError, ValueError, OSError)

EXIT_BUG = 1
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130

#: A command: runs the parsed arguments, returns the exit status.
Command = Callable[[argparse.Namespace], int]
#: What a command says when Ctrl-C stops it (after ``PROG: ``), or None to say nothing (e.g. a
#: torchrun process other than rank 0).
Interrupted = Callable[[argparse.Namespace], str | None]

_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`([^`]+)`")
_LITERAL = re.compile(r"``(.+?)``", re.S)


def _role_text(match: re.Match[str]) -> str:
    """What Sphinx shows for a role: ``title <target>`` -> title, ``~a.b.C`` -> C, else the target."""
    content = match.group(1).strip()
    titled = re.fullmatch(r"(.+?)\s*<[^>]+>", content, re.S)
    if titled:
        return titled.group(1)
    if content.startswith("~"):
        return content[1:].rsplit(".", 1)[-1]
    return content


def plain_text(text: str) -> str:
    """``text`` (a docstring or help text) without reStructuredText inline markup, as a terminal
    should show it: double-backquoted literals and Sphinx roles (``:func:``, ``:class:``, ``:meth:``,
    ``:mod:``, ``:data:``, ...) become their plain text."""
    return _LITERAL.sub(r"\1", _ROLE.sub(_role_text, text))


class Parser(argparse.ArgumentParser):
    """The parser of every command: its description may be a module docstring, and no help or
    usage text shows Sphinx markup. Subcommand parsers (``add_subparsers``) are of this class too."""

    def __init__(self, *args: Any, **kwargs: Any):
        for key in ("description", "epilog"):
            if kwargs.get(key):
                kwargs[key] = plain_text(kwargs[key])
        super().__init__(*args, **kwargs)

    def format_help(self) -> str:
        return plain_text(super().format_help())

    def format_usage(self) -> str:
        return plain_text(super().format_usage())


def positive(value: str) -> int:
    """argparse type: an integer of at least 1."""
    n = int(value)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def positive_float(value: str) -> float:
    """argparse type: a finite number above 0."""
    x = float(value)
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {value}")
    return x


def time_after_frame_s(value: str) -> float:
    """argparse type: seconds after a frame, finite and within a day either way (a time further off
    overflows the microsecond clock or is a typo)."""
    x = float(value)
    if not (math.isfinite(x) and abs(x) <= 86_400):
        raise argparse.ArgumentTypeError(f"must be seconds within [-86400, 86400], got {value}")
    return x


def unit_interval(value: str) -> float:
    """argparse type: a float in [0, 1]."""
    x = float(value)
    if not 0.0 <= x <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return x


def add_anchor_options(parser: argparse.ArgumentParser) -> None:
    """Stage 2 sampling's render anchoring and pasting (``GenerateOptions.anchor``, ``anchor_until``
    and ``paste``), what a rollout trusts and keeps of its own output (``generated_trust``, ``spawn_max_u``,
    ``lift_frames``),
    the localization potential's mapping (``lp_trust``) and the history's geometry (``geometry``)."""
    # imported when the command runs: the library imports torch, which parsing arguments does not need
    from phigenesis.models.uncertainty import LP_TRUSTS
    from phigenesis.rollout.conditions import GEOMETRY_SOURCES
    from phigenesis.rollout.runner import GenerateOptions

    defaults = GenerateOptions()
    parser.add_argument(
        "--anchor",
        type=unit_interval,
        default=defaults.anchor,
        help="render anchoring: pull each latent cell anchor x u of the way to the render's latent "
        f"after every sampling step; 0 turns it off (default {defaults.anchor:g})",
    )
    parser.add_argument(
        "--anchor-until",
        type=unit_interval,
        default=defaults.anchor_until,
        help=f"the anchor acts while the flow time is at least this (default {defaults.anchor_until:g})",
    )
    parser.add_argument(
        "--paste",
        type=unit_interval,
        default=defaults.paste,
        help="render pasting: move each decoded pixel paste x u of the way to the render; 0 keeps the "
        f"VAE's decoding as it is (default {defaults.paste:g})",
    )
    parser.add_argument(
        "--generated-trust",
        type=unit_interval,
        default=defaults.generated_trust,
        help="multiply u by this where the render shows Gaussians of generated windows (the recorded "
        f"history's keep 1), so a rollout trusts its own output less (default {defaults.generated_trust:g})",
    )
    parser.add_argument(
        "--spawn-max-u",
        type=unit_interval,
        default=defaults.spawn_max_u,
        help="a generated window adds static Gaussians only at pixels whose u is at most this; where u "
        "trusted the render more, the buffer keeps the Gaussians the render came from (default "
        f"{defaults.spawn_max_u:g}: every pixel)",
    )
    parser.add_argument(
        "--lift-frames",
        type=positive,
        default=defaults.lift_frames,
        metavar="N",
        help="the newest N frames of each generated window whose Gaussians join the buffer (default: as "
        "many as the model's history frames, the frames the next window takes as its history); every "
        "frame lifted adds its own copy of each surface it shows, at its own depth error",
    )
    parser.add_argument(
        "--lp-trust",
        choices=LP_TRUSTS,
        help="the localization potential's u: stable (trust what a depth error barely moves) or "
        "localised (trust what the history localises well); default: the one the model was trained with",
    )
    parser.add_argument(
        "--geometry",
        choices=GEOMETRY_SOURCES,
        help="the first window's history Gaussians: stage1 (the Stage 1 model's), cache (the cache's "
        "dense depth lifted) or truth (the synthetic truth's); default: the one the model was trained on",
    )


def size_hw(value: str) -> tuple[int, int]:
    """argparse type: ``HxW`` in pixels (e.g. ``48x72``)."""
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW (e.g. 128x192), got {value!r}") from None
    return h, w


def setup_logging(verbose: bool) -> None:
    """INFO logging to stderr (DEBUG with ``-v``)."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )


def user_message(error: BaseException) -> str:
    """The one-line message of an error a user caused: the error's own message (a file error as
    ``PATH: reason``; the arguments it names as flags), never a class path."""
    if isinstance(error, OSError) and error.filename and error.strerror:
        return f"{error.filename}: {error.strerror}"
    if isinstance(error, PhiGenesisError):
        return error.command_line_message() or describe(error)
    if isinstance(error, ValueError | OSError):
        return str(error) or describe(error)
    return describe(error)


def _say(prog: str, message: str) -> None:
    print(f"{prog}: {message}", file=sys.stderr, flush=True)


def _interrupted_message(interrupted: Interrupted | None, args: argparse.Namespace | None) -> str | None:
    """What to print on Ctrl-C; plain ``interrupted`` when the command's own account fails (it
    reads run folders and manifests that a killed run may have left in any state)."""
    if interrupted is None or args is None:
        return "interrupted"
    # The account reads what a stopped writer left (a checkpoint pointer one step behind, say): the
    # library's warnings about that are for the next run, and the answer to Ctrl-C stays one line.
    logging.disable(logging.WARNING)
    try:
        return interrupted(args)
    except Exception:  # the account must never turn Ctrl-C into a traceback
        return "interrupted"
    finally:
        logging.disable(logging.NOTSET)


def dispatch(
    prog: str,
    args: argparse.Namespace,
    commands: dict[str, Command],
    errors: tuple[type[BaseException], ...] = USER_ERRORS,
    interrupted: Interrupted | None = None,
) -> int:
    """Runs ``commands[args.command]`` and turns how it ends into an exit status (see the module
    docstring): an error of ``errors`` is printed as ``PROG: error: MESSAGE``; Ctrl-C prints
    ``PROG: `` and what the interrupt itself says (a library that stops cleanly may raise a
    KeyboardInterrupt whose message says what it kept), else ``interrupted(args)``; any other
    exception is a bug, printed as one line unless ``args.verbose`` (then re-raised with its
    traceback)."""
    verbose = bool(getattr(args, "verbose", False))
    setup_logging(verbose)
    try:
        return commands[args.command](args)
    except KeyboardInterrupt as e:
        message = _interrupted_message(interrupted, args)
        if message:
            if sys.stderr.isatty():  # off the line the terminal's "^C" and any progress bar are on
                print(file=sys.stderr)
            _say(prog, str(e) or message)
        return EXIT_INTERRUPTED
    except errors as e:
        _say(prog, f"error: {user_message(e)}")
        return EXIT_USER_ERROR
    except Exception as e:
        if verbose:
            raise
        _say(prog, f"error: {describe(e)} (unexpected: a bug in phigenesis? rerun with -v for the traceback)")
        return EXIT_BUG


def run(
    prog: str,
    build_parser: Callable[[], argparse.ArgumentParser],
    argv: Sequence[str] | None,
    commands: dict[str, Command],
    interrupted: Interrupted | None = None,
) -> int:
    """The whole of a command's ``main``: builds the parser, parses ``argv`` and runs the command
    with :func:`dispatch`; Ctrl-C while the parser is built (it may import torch) also ends with one
    line and status 130."""
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        _say(prog, "interrupted")
        return EXIT_INTERRUPTED
    return dispatch(prog, args, commands, interrupted=interrupted)
