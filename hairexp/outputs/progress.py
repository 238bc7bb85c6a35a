"""Progress bar for long runs: quiet in CI (the CI environment variable is set) and when
``logging.progress=false``."""

from __future__ import annotations

import os
import sys


def progress_enabled(requested: bool) -> bool:
    return bool(requested) and not os.environ.get("CI") and sys.stderr is not None


class Progress:
    def __init__(self, total: int, enabled: bool, desc: str):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, leave=False)

    def on_step(self, row: dict, state) -> None:
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(it=row["iterations"], ms=f"{1e3 * row['step_seconds']:.0f}", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
