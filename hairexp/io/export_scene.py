"""Command-line entry point ``python -m hairexp.io.export_scene`` (README "USD scenes"); the
export itself is ``hairexp.app.export_scene``.  This module is an entry point, in the app layer
like ``hairexp/__main__.py``: nothing imports it (tests/test_layers.py)."""

from __future__ import annotations

import sys
import warnings

from hairexp.app.cli import one_line_warning
from hairexp.app.export_scene import main
from hairexp.app.startup import exit_now
from hairexp.app.streams import guard_streams, stdout_checked

if __name__ == "__main__":
    warnings.formatwarning = one_line_warning
    guard_streams()   # a full or closed stdout: one line, exit 4 (README "USD scenes")
    exit_now(stdout_checked(main(command=True), "hairexp"))   # without the interpreter's teardown
