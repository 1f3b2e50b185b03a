"""``python -m amuled_ma`` runs the ``amuled`` command line."""

import sys

from amuled_ma.cli import main

sys.exit(main())
