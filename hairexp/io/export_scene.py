"""Command-line entry point ``python -m hairexp.io.export_scene`` (README "USD scenes"); the
export itself is ``hairexp.app.export_scene``.  This module is an entry point, in the app layer
like ``hairexp/__main__.py``: nothing imports it (tests/test_layers.py)."""

from __future__ import annotations

import sys
import warnings

from hairexp.app.cli import one_line_warning
from hairexp.app.export_scene import main

if __name__ == "__main__":
    warnings.formatwarning = one_line_warning
    sys.exit(main())
