"""The `bitcomm` command line. Each subcommand lives in `bitcomm.commands.<name>` and exposes
`add_parser(subparsers)` and `run(args) -> int` and is found by name, so adding a command touches
no shared list; bad input ends with one line and exit status 2, a file the system would not write or read (a
full disk, a read-only folder) with one line and exit status 1."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import sys
from typing import Any, NoReturn

import bitcomm.commands
from bitcomm.commands.flags import HelpFormatter, check_omp_threads
from bitcomm.errors import ConfigError, os_error_line


def command_names() -> list[str]:
    """Every module of `bitcomm.commands` that defines a subcommand, in alphabetical order."""
    names = [m.name for m in pkgutil.iter_modules(bitcomm.commands.__path__)]
    return [n for n in sorted(names) if hasattr(importlib.import_module(f"bitcomm.commands.{n}"), "add_parser")]


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (no usage dump), exit status 2, and help shows defaults."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    from bitcomm import __version__

    description = __doc__.split(".")[0] if __doc__ else None
    parser = _Parser(prog="bitcomm", description=description, epilog="a command's flags: bitcomm help COMMAND")
    parser.add_argument("--version", action="version", version=f"bitcomm {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name in command_names():
        importlib.import_module(f"bitcomm.commands.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv:  # what there is to run, rather than argparse's one line that a command is required
        parser.print_help(sys.stderr)
        return 2
    if argv[0] == "help":  # `bitcomm help [COMMAND]`, as `git help` and `pip help`: the same as -h
        argv = [*argv[1:2], "--help"]
    try:
        args, unknown = parser.parse_known_args(argv)
    except SystemExit as exit_:  # a usage error (2, its line printed) or --help (0): a status, as run() returns
        return exit_.code if isinstance(exit_.code, int) else 2
    if unknown:  # named with its command, as every other error (argparse's own line names only `bitcomm`)
        print(f"bitcomm {args.command}: error: unrecognized arguments: {' '.join(unknown)}", file=sys.stderr)
        return 2
    try:
        check_omp_threads()  # before any command loads torch
        return int(args.run(args) or 0)
    except ConfigError as err:
        print(f"bitcomm {args.command}: error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `bitcomm ... --json | head`: the reader has what it wanted; say nothing, as cat does
        with contextlib.suppress(OSError, ValueError):  # nor at exit, when Python flushes what stdout still holds
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, the status a shell reports for a writer whose reader stopped early
    except OSError as err:  # the machine, not the input: a full disk, a quota, a folder made read-only meanwhile
        print(f"bitcomm {args.command}: error: {os_error_line(err)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as err:
        print(f"bitcomm {args.command}: interrupted", file=sys.stderr)
        return int(getattr(err, "exit_code", 130))  # a run stopped on SIGTERM (`Stopped`) ends as killed by it


if __name__ == "__main__":
    sys.exit(main())
