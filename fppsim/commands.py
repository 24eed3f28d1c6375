"""A neutral command-line framework: git-style subcommands, one line per error, exit codes.

Both command lines (``fppsim`` in :mod:`fppsim.cli`, ``uhrnet`` in :mod:`uhrnet.cli`) are built from
it: a :class:`Command` per subcommand declares its flags and runs the library, and
:func:`run_commands` turns how it ended into an exit status. The framework knows no package: the
caller passes its error classes (``errors``: one line, exit 1; ``usage_errors``: exit 2, like
argparse's own errors).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Callable

from fppsim.files import command_named, signals_raise

__all__ = ["parse_numbers", "Command", "ReportLines", "build_command_parser", "one_line", "run_commands"]


@dataclass(frozen=True)
class Command:
    """A subcommand: ``add(parser)`` declares its flags, ``run(args) -> exit code`` calls the library."""

    add: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str


class ReportLines(list):
    """The lines a library function reports (what its command prints), kept in order; :meth:`say` also
    hands each line to ``echo`` (the command line passes ``print``) as soon as it is known."""

    def __init__(self, echo: Callable[[str], None] | None = None):
        super().__init__()
        self.echo = echo

    def say(self, line: str) -> None:
        self.append(line)
        if self.echo is not None:
            self.echo(line)


def build_command_parser(prog: str, description: str, commands: dict[str, Command],
                         globals_: Callable[[argparse.ArgumentParser], None] | None = None,
                         load: str | None = None) -> argparse.ArgumentParser:
    """One sub-parser per command; with ``load`` only that command declares its flags (the others
    keep name and help: a CLI whose commands import heavy modules stays fast)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    if globals_ is not None:
        globals_(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, cmd in commands.items():
        p = sub.add_parser(name, help=cmd.help, description=cmd.help)
        if load is None or load == name:
            cmd.add(p)
    return parser


def one_line(exc: BaseException) -> str:
    """The one-line message of an error, also when a DataLoader worker re-raised it.

    A worker's error arrives as ``Caught DatasetError in DataLoader worker process 0.`` followed by the
    worker's traceback, whose last line (``fppsim.errors.DatasetError: <file>: ...``) names the culprit.
    """
    lines = [line for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    if len(lines) > 1 and lines[0].startswith("Caught ") and "worker" in lines[0]:
        last = lines[-1].strip()
        head, sep, rest = last.partition(": ")
        return rest if sep and "." in head and " " not in head else last
    return lines[0]


def parse_numbers(text: str, kind=float, sep: str | None = ",", skip_empty: bool = False) -> list | None:
    """The numbers of an option's ``text`` split at ``sep`` (None: one number), each made by ``kind`` (``int``,
    ``float`` or a parser such as ``psp_freq``), or None when one is not a number: the command lines' argument
    types turn None into their own one-line message, so no command line catches ValueError itself."""
    parts = [text] if sep is None else text.split(sep)
    try:
        return [kind(p) for p in parts if p.strip() or not skip_empty]
    except (ValueError, OverflowError):
        return None


def run_commands(parser: argparse.ArgumentParser, commands: dict[str, Command], argv: list[str] | None,
                 errors: tuple[type[BaseException], ...], setup: Callable[[argparse.Namespace], None] | None = None,
                 resume_hint: dict[str, str] | str = " (re-run the same command to resume)",
                 usage_errors: tuple[type[BaseException], ...] = ()) -> int:
    """Parse ``argv``, run the chosen command and report how it ended, one line on stderr:

    * ``errors`` and ``OSError`` -> ``prog command: error: <one line>`` (``file: strerror`` for I/O
      errors such as a full disk), exit 1; ``usage_errors`` (an option value wrong on its own) exit 2
      like argparse's own errors; no command is a usage error too;
    * SIGTERM (e.g. a Slurm timeout) and SIGINT -> ``prog command: terminated|interrupted<hint>``, exit
      ``128 + signum``; the library's clean-up ran on the way (pools terminated, temp files removed);
    * anything else is a bug: traceback.

    ``resume_hint``: text after the interruption line, or ``{command: text}``.
    """
    args = parser.parse_args(argv)
    if setup is not None:
        setup(args)
    if args.command is None:
        parser.print_usage(sys.stderr)
        print(f"{parser.prog}: error: choose a command: " + ", ".join(commands), file=sys.stderr)
        return 2
    where = f"{parser.prog} {args.command}"
    try:
        # SIGTERM stops like Ctrl-C: exit 128 + signum; a warning the library prints begins with `where` too
        with signals_raise(), command_named(where):
            return int(commands[args.command].run(args) or 0)
    except Exception as exc:
        if isinstance(exc, OSError) and exc.strerror:  # disk full, read-only file system, missing file ...
            msg = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
        elif isinstance(exc, errors + usage_errors + (OSError,)):
            msg = one_line(exc)
        else:
            raise
        print(f"{where}: error: {msg}", file=sys.stderr)
        return 2 if isinstance(exc, usage_errors) else 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        hint = resume_hint.get(args.command, "") if isinstance(resume_hint, dict) else resume_hint
        print(f"{where}: {'terminated' if signum == 15 else 'interrupted'}{hint}", file=sys.stderr)
        return 128 + signum
