"""The README's Python API examples run as written."""

from __future__ import annotations

import re

from helpers import REPO


def api_blocks() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## Python API", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_has_the_api_examples():
    assert len(api_blocks()) == 2


def test_readme_api_examples_run(capsys):
    for code in api_blocks():
        exec(compile(code, "README.md (Python API)", "exec"), {})
    out = capsys.readouterr().out
    assert "strands," in out and "converged" in out
