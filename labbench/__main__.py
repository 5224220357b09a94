"""``python -m labbench``: the command line."""
import sys

from labbench.cli.main import main

sys.exit(main())
