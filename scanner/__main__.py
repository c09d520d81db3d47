"""``python -m scanner``: the same command line as the ``scanner`` console script."""

import sys

from scanner.app.cli import main

sys.exit(main())
