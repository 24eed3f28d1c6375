"""`uhrnet` command line: git-style subcommands.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``;
modules are imported lazily so ``uhrnet --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help)
COMMANDS = {
    "train": ("uhrnet.train", "train a model on real (figshare) and/or synthetic (fppsim) data"),
    "evaluate": ("uhrnet.evaluate", "evaluate checkpoints on the test split like the paper (Table 3, figures)"),
    "evaluate-phase": ("uhrnet.evaluate_phase", "evaluate checkpoints on real phase-shifting data without height "
                       "labels (PSin/PCos/Fringe/iPattern folders): calibration-free phase residual"),
    "predict": ("uhrnet.predict", "predict height maps and point clouds from fringe images"),
    "bench": ("uhrnet.bench", "parameters, forward/training-step time and peak memory per model"),
    "export": ("uhrnet.export", "export a checkpoint as ONNX or TorchScript (batch norms folded), with --check"),
}


from uhrnet.errors import ConfigError as CLIError, UsageError  # noqa: E402,F401  (names the subcommands use)


def build_parser(load=None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uhrnet",
        description="UHRNet and baselines for single-shot fringe projection profilometry. "
        "Heights are in label units on disk and reported in millimetres.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if load is None or load == name:
            importlib.import_module(module).add_arguments(p)
    return parser


def one_line(exc: BaseException) -> str:
    """The one-line message of a user error, also when a DataLoader worker re-raised it.

    A worker's error arrives as ``Caught DataError in DataLoader worker process 0.`` followed by the
    worker's traceback, whose last line (``uhrnet.data.DataError: <file>: ...``) names the culprit.
    """
    lines = [line for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    if len(lines) > 1 and lines[0].startswith("Caught ") and "worker" in lines[0]:
        last = lines[-1].strip()
        prefix = f"{type(exc).__module__}.{type(exc).__qualname__}: "
        return last[len(prefix):] if last.startswith(prefix) else last
    return lines[0]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Load only the chosen subcommand's module (argparse exits 2 on usage errors).
    chosen = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(load=chosen if chosen in COMMANDS else "__none__")
    if chosen not in COMMANDS and not any(a in ("-h", "--help") for a in argv):
        parser.print_usage(sys.stderr)
        print(f"uhrnet: error: choose a command from: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    module = importlib.import_module(COMMANDS[args.command][0])
    from fppsim._fs import signals_raise

    try:
        with signals_raise():  # SIGTERM stops like Ctrl-C: exit 128 + signum, temp files removed
            return int(module.run(args) or 0)
    except Exception as exc:  # user-facing errors become one line; anything else is a bug: traceback
        from uhrnet.errors import CheckpointError, ConfigError, DataError, FolderBusy, UhrnetError

        if isinstance(exc, OSError) and exc.strerror:  # disk full, read-only file system, ...
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"uhrnet {args.command}: error: {where}{exc.strerror}", file=sys.stderr)
            return 1
        if not isinstance(exc, (ConfigError, DataError, CheckpointError, UhrnetError, FolderBusy)):
            raise
        print(f"uhrnet {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", 2)
        print(f"uhrnet {args.command}: {'terminated' if signum == 15 else 'interrupted'}"
              + (" (resume with --resume)" if args.command == "train" else ""), file=sys.stderr)
        return 128 + signum


if __name__ == "__main__":
    sys.exit(main())
