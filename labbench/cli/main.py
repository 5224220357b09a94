"""The ``labbench`` command line.

Each subcommand lives in its own module ``labbench/cli/<name>.py`` exposing
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
taking the parsed namespace and returning an exit code. Errors a user can
cause (``UserError``) print one line on stderr and exit 2; a device that
fails (``DeviceError``: dead bus, no answer, a fault) prints one line and exits 1.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import sys
import threading

from labbench.errors import DeviceError, LabbenchError, UserError
from labbench.interrupts import raising

# Order is the order shown in --help.
COMMANDS = ("theory", "analyze", "run", "replay", "export", "report", "devices", "gui")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line (exit 2), no usage dump."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="labbench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"labbench.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"labbench.cli.{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # SIGINT/SIGTERM/SIGHUP raise Interrupted whatever was inherited (labbench.interrupts);
    # `run` narrows that to stopping the run. The GUI's Qt loop keeps its own.
    own = getattr(args, "own_signals", False) or threading.current_thread() is not threading.main_thread()
    with contextlib.nullcontext() if own else raising():
        try:
            return int(args.func(args) or 0)
        except LabbenchError as exc:
            print(f"labbench {args.command}: error: {exc}", file=sys.stderr)
            return 1 if isinstance(exc, DeviceError) else 2
        except KeyboardInterrupt as exc:  # Interrupted (a signal) or a bare Ctrl-C
            print(f"labbench {args.command}: {str(exc) or 'interrupted'}", file=sys.stderr)
            return getattr(exc, "exit_code", 130)
        except BrokenPipeError:
            # The reader (e.g. `| head`) went away: not an error of ours; silence the
            # second failure Python would report when flushing stdout at exit.
            import os

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0


def float_list(text: str) -> list[float]:
    """Parse ``1,10,100`` into floats (argparse ``type=``), with a one-line error."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
    if not values:
        raise argparse.ArgumentTypeError("expected at least one number")
    return values
