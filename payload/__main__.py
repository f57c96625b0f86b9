"""``python -m payload``: the same command line as the ``payload`` console script."""

import sys

from payload.cli import main

if __name__ == "__main__":
    sys.exit(main())
