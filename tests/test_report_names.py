"""Every experiments/ script that writes a report takes ``--report NAME`` (reports/NAME.md and
.json; the default is the committed report), so that a run that should not replace the committed
report need not: a name with path parts is a usage error (exit 2, "is not a report name") before
anything runs or is written, checked on the command line (``python -m experiments.<name> --report
../x``, a subprocess per script); and ``--help`` shows the option, checked in this process (``main``
with ``--help``: one import of torch for all the scripts, where a subprocess costs 2-3 s of start-up
each).

The scripts are found by their text (a call of ``write_report(``, or a ``--report`` of type
``report_name`` for a script that writes its markdown itself), so a new report script is covered
without a change here.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXPERIMENTS = REPO / "experiments"


def report_scripts() -> list[str]:
    names = []
    for path in sorted(EXPERIMENTS.glob("*.py")):
        if path.stem in ("__init__", "common"):
            continue
        text = path.read_text(encoding="utf-8")
        if "write_report(" in text or "type=report_name" in text:
            names.append(path.stem)
    return names


SCRIPTS = report_scripts()


def run(module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"experiments.{module}", *args], cwd=REPO,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=120)


def test_the_report_scripts_are_found():
    assert {"bench_tracking", "paper_scenes", "ablations", "baselines", "fidelity"} <= set(SCRIPTS), SCRIPTS


@pytest.mark.parametrize("module", SCRIPTS)
def test_a_report_name_with_path_parts_is_a_usage_error(module):
    outside = [REPO / f"x{suffix}" for suffix in (".md", ".json", ".png")]   # where reports/../x would go
    before = {p: p.exists() for p in outside}
    proc = run(module, "--report", "../x")
    assert proc.returncode == 2, (proc.returncode, proc.stdout[-2000:], proc.stderr[-3000:])
    assert "is not a report name" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout == "", proc.stdout
    assert {p: p.exists() for p in outside} == before


@pytest.mark.parametrize("module", SCRIPTS)
def test_help_shows_the_report_option(module, monkeypatch, capsys):
    main = importlib.import_module(f"experiments.{module}").main
    monkeypatch.setattr(sys, "argv", [f"{module}.py", "--help"])   # every main parses sys.argv without argv
    with pytest.raises(SystemExit) as exc:
        main()
    out = capsys.readouterr().out
    assert exc.value.code == 0, out
    assert "--report" in out, out
