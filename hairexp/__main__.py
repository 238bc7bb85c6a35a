"""Command line: ``python -m hairexp experiment=<name> [key=value ...]`` (``-m`` sweeps).

Configs live in ../conf (Hydra); the schema in hairexp/app/config.py rejects unknown keys and
wrong types at start.  Errors in the input end with one line naming the input and a
non-zero exit; the codes are decided after Hydra returns (hairexp/app/cli.py): 2 bad input,
3 a simulation that could not continue, 4 a run folder that cannot be written (a
``hydra.run.dir`` / ``hydra.sweep.dir`` of the command line is checked before Hydra starts),
130/143 interrupted; a sweep runs every job and exits with its first failing job's code.
"""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import hairexp.app.config  # noqa: F401  (registers the schema in the ConfigStore)
from hairexp.app import cli
from hairexp.app.signals import InterruptSignals, exit_code
from hairexp.errors import Interrupted


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    hc = HydraConfig.get()
    sweep = str(getattr(hc.mode, "name", hc.mode)) == "MULTIRUN"
    res = cli.job(cfg, hc.runtime.output_dir, sweep=sweep, sweep_dir=str(hc.sweep.dir) if sweep else None,
                  overrides=list(hc.overrides.task))
    return res["code"]


def entry() -> int:
    logging.raiseExceptions = False   # a log file on a full disk is not worth a traceback per line
    bad_dir = cli.run_dir_error(sys.argv[1:])   # before Hydra creates it (its traceback, exit 1)
    if bad_dir is not None:
        print(bad_dir, file=sys.stderr)
        return 4
    bad_config = cli.config_error(sys.argv[1:])   # a typo, a wrong type, an unknown choice: bad input
    if bad_config is not None:
        print(bad_config, file=sys.stderr)
        return 2
    try:
        # outside a run (composing, between sweep jobs) too; a sweep's running jobs are stopped first
        with InterruptSignals(on_signal=cli.stop_sweep_jobs):
            main()
    except KeyboardInterrupt as exc:
        code = exit_code(exc.signum) if isinstance(exc, Interrupted) else 130
        # outside a run (a run prints its own line): while the config was composed, or between sweep jobs
        what = str(exc) if isinstance(exc, Interrupted) and str(exc) else "interrupted by SIGINT"
        print(f"hairexp: {what}", file=sys.stderr)
        cli.clear_stop_mark()   # the launcher has torn its workers down
        cli.exit_code()   # a sweep's jobs so far
        return code
    return cli.exit_code()


if __name__ == "__main__":
    sys.exit(entry())
