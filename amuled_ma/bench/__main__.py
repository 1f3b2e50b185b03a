"""``python -m amuled_ma.bench NAME`` is ``amuled bench NAME``."""

import sys

from amuled_ma.cli import main

sys.exit(main(["bench", *sys.argv[1:]]))
