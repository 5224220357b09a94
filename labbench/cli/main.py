"""The ``labbench`` command line.

Each subcommand lives in its own module ``labbench/cli/<name>.py`` exposing
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
taking the parsed namespace and returning an exit code. Errors a user can
cause (``UserError``, a missing optional package) print one line on stderr and
exit 2; a device that fails (``DeviceError``: dead bus, no answer, a fault)
prints one line and exits 1.

``-v``/``-q`` (before the command) set the level of Python's logging: default
warnings, ``-v`` info, ``-vv`` debug, ``-q`` errors only; the libraries under
labbench (canopen's SDO/NMT messages, python-can) speak from ``-v`` on.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import sys
import threading

from labbench import __version__
from labbench.errors import Cancelled, DeviceError, LabbenchError, UserError, missing_extra
from labbench.readout.escape import one_line
from labbench.loop.interrupts import raising
from labbench.readout.units import SI, DisplayUnits

# Order is the order shown in --help.
COMMANDS = ("theory", "design", "analyze", "run", "sweep", "campaign", "replay", "export", "report", "devices", "gui")
# Optional packages -> the extra that installs them (pyproject.toml).
OPTIONAL = {"cvxpy": "cvxpy", "PySide6": "gui", "pyqtgraph": "gui", "pandas": "pandas"}
# Libraries whose log lines are shown from -v on only: their errors (an SDO abort, a bus
# timeout) reach the user as our own one-line error already.
LIBRARY_LOGGERS = ("canopen", "can", "distributed")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line (exit 2), no usage dump."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    # no abbreviations: "--ve" of a subcommand must not read as --version or --verbose
    parser = _Parser(prog="labbench", description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--version", action="version", version=f"labbench {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output: -v info (canopen's SDO/NMT too), -vv debug")
    parser.add_argument("-q", "--quiet", action="count", default=0, help="errors only")
    parser.add_argument("--units", type=_display_units, default=SI, metavar="LIST",
                        help="display units for printed tables, e.g. mm,deg,Hz (files stay SI)")
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
    argv = sys.argv[1:] if argv is None else argv
    if list(argv) == ["--version"]:  # answered before the subcommands import numpy and scipy
        print(f"labbench {__version__}")
        return 0
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose - args.quiet)
    # SIGINT/SIGTERM/SIGHUP raise Interrupted whatever was inherited (labbench.loop.interrupts);
    # `run` narrows that to stopping the run. The GUI's Qt loop keeps its own.
    own = getattr(args, "own_signals", False) or threading.current_thread() is not threading.main_thread()
    with contextlib.nullcontext() if own else raising():
        try:
            return int(args.func(args) or 0)
        except Cancelled as exc:  # an analysis asked to stop: as an interrupt
            print(f"labbench {args.command}: {exc}", file=sys.stderr)
            return 130
        except LabbenchError as exc:  # one line, its controls escaped (names, paths in it)
            print(f"labbench {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return 1 if isinstance(exc, DeviceError) else 2
        except ModuleNotFoundError as exc:
            top = (exc.name or "").split(".")[0]
            if top not in OPTIONAL:
                raise
            print(f"labbench {args.command}: error: "
                  f"{missing_extra(top, OPTIONAL[top], f'labbench {args.command}')}",
                  file=sys.stderr)
            return 2
        except KeyboardInterrupt as exc:  # Interrupted (a signal) or a bare Ctrl-C
            print(f"labbench {args.command}: {str(exc) or 'interrupted'}", file=sys.stderr)
            return getattr(exc, "exit_code", 130)
        except BrokenPipeError:
            # The reader (e.g. `| head`) went away: not an error of ours; silence the
            # second failure Python would report when flushing stdout at exit.
            import os

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 0


_HANDLER_NAME = "labbench-cli"


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is now (tests and redirections replace it)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


class _OneLine(logging.Formatter):
    """A log line on one line, its controls escaped (``labbench.readout.escape.one_line``); a
    traceback, when one is logged, follows as it is."""

    def formatMessage(self, record) -> str:
        return one_line(super().formatMessage(record))


def setup_logging(verbosity: int) -> None:
    """One stderr handler on the root logger; ``verbosity`` 0 = warnings, 1 = info,
    2 = debug, -1 = errors only; the libraries' loggers speak from 1 on."""
    level = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO}.get(
        max(-1, min(verbosity, 2)), logging.DEBUG)
    root = logging.getLogger()
    if not any(h.get_name() == _HANDLER_NAME for h in root.handlers):
        handler = _StderrHandler()
        handler.set_name(_HANDLER_NAME)
        handler.setFormatter(_OneLine("%(name)s: %(levelname)s: %(message)s"))
        root.addHandler(handler)
    root.setLevel(level)
    for name in LIBRARY_LOGGERS:
        logging.getLogger(name).setLevel(level if verbosity > 0 else logging.CRITICAL + 1)


def _display_units(text: str):
    try:
        return DisplayUnits.parse(text)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def float_list(text: str) -> list[float]:
    """Parse ``1,10,100`` into floats (argparse ``type=``), with a one-line error."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
    if not values:
        raise argparse.ArgumentTypeError("expected at least one number")
    return values
