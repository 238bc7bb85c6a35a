"""Command line: ``python -m hairexp experiment=<name> [key=value ...]`` (``-m`` sweeps).

Configs live in ../conf (Hydra); the schema in hairexp/app/config.py rejects unknown keys and
wrong types at start.  Errors in the input end with one line naming the input and a
non-zero exit (2 for bad input, 3 for a simulation that could not continue).
"""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import hairexp.app.config  # noqa: F401  (registers the schema in the ConfigStore)
from hairexp.app.experiment import run_experiment
from hairexp.errors import InputError, SimulationError

log = logging.getLogger("hairexp")


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    out = HydraConfig.get().runtime.output_dir
    try:
        summary = run_experiment(cfg, out)
    except InputError as exc:
        print(f"hairexp: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except SimulationError as exc:
        print(f"hairexp: simulation failed: {exc} (partial metrics in {out})", file=sys.stderr)
        sys.exit(3)
    if "variants" in summary:
        for name, v in summary["variants"].items():
            log.info("%s: %s, %.2f iterations/step, median %.1f ms/step, measures %s", name, v["status"],
                     v["iterations_mean"], 1e3 * v["step_seconds_median"], v["measures"])
        log.info("%s: success=%s -> %s", summary["experiment"], summary["success"], out)
        return None
    log.info("%s/%s: %d steps, %.2f iterations/step, median %.1f ms/step, max stretch %.2e -> %s",
             summary["scene"], summary["controller"], summary["steps"], summary["iterations_mean"],
             1e3 * summary["step_seconds_median"], summary["stretch_max"], out)
    return summary["step_seconds_median"]


if __name__ == "__main__":
    main()
