"""Argument parsing shared by the ``rve``, ``obu`` and ``captures`` commands.

A bad flag must give one line and a non-zero exit, not argparse's usage block, so
:class:`Parser` raises :class:`UsageError` and :func:`dispatch` prints it (one line to
stderr).  So must a bad input file, or a read or write that failed, that a command did
not catch itself: :func:`dispatch` prints :class:`hil.errors.InputError` (exit status 2)
and any :class:`OSError` (``FILE: reason``, exit status 1) in one line too.  It lives in
``hil``, the I/O shell under the three commands, because it writes: nothing in
:mod:`catc` does.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

from hil.errors import InputError, describe


class UsageError(Exception):
    """A bad command line; ``str()`` is the one-line message."""


class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def make_parser(prog: str, description: str) -> tuple[Parser, argparse._SubParsersAction]:
    """A top-level parser with required subcommands that share :class:`Parser`."""
    parser = Parser(prog=prog, description=description,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=Parser)
    return parser, sub


#: Exit statuses as a shell reports a process ended by SIGINT and by SIGPIPE.
INTERRUPTED, BROKEN_PIPE = 130, 141


def dispatch(parser: Parser, argv: list[str] | None) -> int:
    """Parse ``argv`` and run the chosen subcommand's ``func``; exit status 2 on bad usage.

    Ctrl-C before a daemon has set up its own handling (or in any other command) is one
    line and status 130; a reader that closed the pipe (``captures score | head``) ends
    the command quietly with status 141, stdout pointed at /dev/null so that the flush
    at exit raises nothing either.  Last, a bad input file (:class:`InputError`) or a
    file that cannot be read or written (:class:`OSError`) that the command left
    uncaught is one line too, with status 2 and 1; other exceptions are bugs and keep
    their traceback."""
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        print(err, file=sys.stderr)
        return 2
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return BROKEN_PIPE
    except InputError as err:
        print(f"{_prog(parser, args)}: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"{_prog(parser, args)}: {describe(err)}", file=sys.stderr)
        return 1


def _prog(parser: Parser, args: argparse.Namespace) -> str:
    """The command as the user typed it (``rve encode``)."""
    command = getattr(args, "command", None)
    return f"{parser.prog} {command}" if command else parser.prog
