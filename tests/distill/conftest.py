"""Fixtures of the distilled-feedback tests: their helpers import from this folder and tests/."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1]))  # tiny_cli
