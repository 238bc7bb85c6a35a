"""Helpers that turn measurements into committed reports under reports/: every report
states the machine, the package versions and the command that produced it."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path

from hairexp.outputs.files import atomic_write_bytes

REPORTS = Path(__file__).resolve().parents[2] / "reports"


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numpy
    import scipy
    import torch

    return {"cores": os.cpu_count(), "cpu": cpu, "python": platform.python_version(), "numpy": numpy.__version__,
            "scipy": scipy.__version__, "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


def command() -> str:
    """The command line that made a report, as a user types it: ``python -m experiments.<name>``
    for a script run as a module of the experiments package."""
    py = os.path.relpath(sys.executable) if ".venv" in sys.executable else "python"
    args = list(sys.argv)
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name and args:
        args = ["-m", spec.name, *args[1:]]
    return " ".join(shlex.quote(a) for a in [py, *args])


def header(title: str) -> str:
    m = machine()
    return (f"# {title}\n\n"
            f"Command: `{command()}`  \n"
            f"Machine: {m['cores']} cores, {m['cpu']}; Python {m['python']}, numpy {m['numpy']}, "
            f"scipy {m['scipy']}, torch {m['torch']} ({m['torch_threads']} threads); {m['date']}\n\n")


def write_report(name: str, markdown: str, data: dict) -> Path:
    REPORTS.mkdir(exist_ok=True)
    # whole or not at all: a full disk left a half-written report under its final name (the committed
    # one lost), and the pair of files is written only once both are encoded
    body = json.dumps({"machine": machine(), "command": command(), **data}, indent=2, default=float).encode()
    atomic_write_bytes(REPORTS / f"{name}.json", lambda f: f.write(body))
    atomic_write_bytes(REPORTS / f"{name}.md", lambda f: f.write(markdown.encode()))
    return REPORTS / f"{name}.md"
