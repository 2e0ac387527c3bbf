"""Helper modules of this folder (`instrument_process`) are importable by its tests: pytest
imports test files by path (``--import-mode=importlib``), not this folder."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
