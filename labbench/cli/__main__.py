import sys

from labbench.cli.main import main

sys.exit(main())
