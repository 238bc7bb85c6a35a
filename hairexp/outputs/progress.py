"""Progress bar for long runs: quiet in CI (the CI environment variable is set) and when
``logging.progress=false``."""

from __future__ import annotations

import os
import sys


def progress_enabled(requested: bool) -> bool:
    return bool(requested) and not os.environ.get("CI") and sys.stderr is not None


#: (line, label) of this process's bar: an experiment's variants run side by side each draw theirs on
#: a line of its own, named (hairexp/app/variant_processes.py); None: the first line, the scene's name
_SLOT: tuple[int, str] | None = None


def set_slot(line: int, label: str) -> None:
    """This process's bars go on terminal line ``line`` (0: the first), described as ``label``."""
    global _SLOT
    _SLOT = (int(line), str(label))


class Progress:
    def __init__(self, total: int, enabled: bool, desc: str):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            line, label = _SLOT if _SLOT is not None else (None, None)
            self.bar = tqdm(total=total, desc=desc if label is None else f"{desc} {label}", unit="step",
                            dynamic_ncols=True, leave=False, position=line)

    def on_step(self, row: dict, state) -> None:
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(it=row["iterations"], ms=f"{1e3 * row['step_seconds']:.0f}", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
