"""The ``labbench`` command line.

Each subcommand lives in its own module ``labbench/cmd_<name>.py`` exposing
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
taking the parsed namespace and returning an exit code. Errors a user can
cause (``UserError``) print one line on stderr and exit 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from labbench.errors import UserError

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
            module = importlib.import_module(f"labbench.cmd_{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"labbench.cmd_{name}":
                continue  # command not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"labbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"labbench {args.command}: interrupted", file=sys.stderr)
        return 130
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


def json_safe(obj):
    """numpy arrays/scalars -> lists/floats, non-finite floats -> None (strict JSON)."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


if __name__ == "__main__":
    sys.exit(main())
