"""The ``labbench`` command line: one module per subcommand (see ``main``)."""
from labbench.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
