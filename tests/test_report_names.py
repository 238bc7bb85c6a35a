"""Every experiments/ script that writes a report takes ``--report NAME`` (reports/NAME.md and
.json; the default is the committed report), so that a run that should not replace the committed
report need not: a name with path parts is a usage error (exit 2, "is not a report name") before
anything runs or is written, checked in this process (each script's ``main`` with ``--report ../x``: one import of torch for all
the scripts, where a subprocess costs 2-3 s of start-up each) and for one script on the command
line; and ``--help`` shows the option.

The scripts are found by their text (a call of ``write_report(``, or a ``--report`` option,
``add_report_option(`` or of type ``report_name``, for a script that writes its markdown itself),
so a new report script is covered
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
        if "write_report(" in text or "add_report_option(" in text or "type=report_name" in text:
            names.append(path.stem)
    return names


SCRIPTS = report_scripts()


def run(module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"experiments.{module}", *args], cwd=REPO,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=120)


def test_the_report_scripts_are_found():
    assert {"bench_tracking", "paper_scenes", "ablations", "baselines", "fidelity"} <= set(SCRIPTS), SCRIPTS


@pytest.mark.parametrize("module", SCRIPTS)
def test_a_report_name_with_path_parts_is_a_usage_error(module, monkeypatch, capsys):
    outside = [REPO / f"x{suffix}" for suffix in (".md", ".json", ".png")]   # where reports/../x would go
    before = {p: p.exists() for p in outside}
    main = importlib.import_module(f"experiments.{module}").main
    monkeypatch.setattr(sys, "argv", [f"{module}.py", "--report", "../x"])
    with pytest.raises(SystemExit) as exc:
        main()
    captured = capsys.readouterr()
    assert exc.value.code == 2, (captured.out[-2000:], captured.err[-3000:])
    assert "is not a report name" in captured.err, captured.err
    assert captured.out == "", captured.out
    assert {p: p.exists() for p in outside} == before


def test_on_the_command_line_too():
    """One script as a user runs it (a subprocess): exit 2, the usage line, no traceback."""
    proc = run("bench_free", "--report", "../x")
    assert proc.returncode == 2, (proc.returncode, proc.stdout[-2000:], proc.stderr[-3000:])
    assert "is not a report name" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout == ""


@pytest.mark.parametrize("module", SCRIPTS)
def test_help_shows_the_report_option(module, monkeypatch, capsys):
    main = importlib.import_module(f"experiments.{module}").main
    monkeypatch.setattr(sys, "argv", [f"{module}.py", "--help"])   # every main parses sys.argv without argv
    with pytest.raises(SystemExit) as exc:
        main()
    out = capsys.readouterr().out
    assert exc.value.code == 0, out
    assert "--report" in out, out
