"""The command line's jobs and exit codes.

A job (``job``: one Hydra job, a single run or one job of a ``-m`` sweep) never exits the
process: it runs the experiment, prints the one error line of a failure and returns its
outcome (status, exit code, run folder).  The exit code is decided in the main process after
Hydra returns (``exit_code``): for a run, the job's; for a sweep, every job has run, one line
per job is printed and the sweep exits with the first failing job's code (in job order).
A sweep job's outcome is written to ``<job folder>/.hydra/outcome.json`` (the main process
reads them back; a job that left no outcome is reported as not finished).

Exit codes: 0 completed; 1 an unexpected error (or Hydra's config errors); 2 bad input
(``InputError``: a bad value, a used run folder, a bad variant name); 3 the simulation failed
(``SimulationError``, including non-convergence: none of the steps converged, or some under
``on_unconverged=fail``); 4 the run folder could not be written (``OSError``: a full disk, a
blocked path); 130 / 143 interrupted by SIGINT / SIGTERM.
"""

from __future__ import annotations

import json
import logging
import sys
import traceback
from pathlib import Path

from hydra.experimental.callback import Callback

from hairexp.app.experiment import run_experiment
from hairexp.app.signals import exit_code as signal_exit_code
from hairexp.errors import InputError, Interrupted, SimulationError
from hairexp.outputs.files import write_json

log = logging.getLogger("hairexp")
OUTCOME = Path(".hydra") / "outcome.json"

#: the outcome of the last job run in this process (single runs: read by the main process)
LAST: dict | None = None
#: the sweep folder of a multirun started in this process (set by SweepOutcomes)
SWEEP_DIR: Path | None = None


def outcome(out, status: str, code: int, message: str | None = None, summary: dict | None = None) -> dict:
    return {"status": status, "code": code, "message": message, "out": str(out),
            "converged": None if summary is None else summary.get("converged")}


def job(cfg, out: str, sweep: bool = False) -> dict:
    """Run the experiment of ``cfg`` into ``out``; returns its outcome (never raises for a
    failing run, never exits)."""
    global LAST
    if sweep:
        _write_outcome(out, outcome(out, "running", 1, "the job did not finish"))
    try:
        summary = run_experiment(cfg, out)
        res = outcome(out, "completed", 0, None, summary)
        _log_completed(summary, out)
    except InputError as exc:
        print(f"hairexp: error: {exc}", file=sys.stderr)
        res = outcome(out, "failed", 2, str(exc))
    except SimulationError as exc:
        print(f"hairexp: simulation failed: {exc} (partial metrics in {out})", file=sys.stderr)
        _print_notes(exc)
        res = outcome(out, "failed", 3, str(exc))
    except OSError as exc:   # the run folder could not be written (a full disk, a blocked path)
        print(f"hairexp: cannot write the run folder {out}: {exc}", file=sys.stderr)
        _print_notes(exc)
        res = outcome(out, "failed", 4, str(exc))
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else 2
        msg = str(exc) if isinstance(exc, Interrupted) else "interrupted by SIGINT"
        print(f"hairexp: {msg} (partial results in {out})", file=sys.stderr)
        _print_notes(exc)
        res = outcome(out, "interrupted", signal_exit_code(signum), msg)
    except Exception as exc:   # noqa: BLE001  (a bug: the traceback, exit 1; the sweep's other jobs go on)
        traceback.print_exc()
        res = outcome(out, "failed", 1, f"{type(exc).__name__}: {exc}")
    LAST = res
    if sweep:
        _write_outcome(out, res)
    return res


def _print_notes(exc: BaseException) -> None:
    """The failures met while writing the ending of a failed run (the first error was printed)."""
    for note in getattr(exc, "__notes__", []):
        print(f"hairexp:   also: {note}", file=sys.stderr)


def _write_outcome(out, res: dict) -> None:
    try:
        p = Path(out) / OUTCOME
        p.parent.mkdir(parents=True, exist_ok=True)
        write_json(p, res)
    except OSError as exc:
        log.error("%s: cannot write the job's outcome: %s", out, exc)


def _log_completed(summary: dict, out) -> None:
    if "variants" in summary:
        for name, v in summary["variants"].items():
            log.info("%s: %s%s, %.2f iterations/step, median %.1f ms/step, measures %s", name, v["status"],
                     "" if v.get("converged") is not False else f" (not converged: {v['unconverged_steps']} steps)",
                     v["iterations_mean"], 1e3 * v["step_seconds_median"], v["measures"])
        log.info("%s: success=%s -> %s", summary["experiment"], summary["success"], out)
        return
    log.info("%s/%s: %d steps, %.2f iterations/step, median %.1f ms/step, max stretch %.2e -> %s",
             summary["scene"], summary["controller"], summary["steps"], summary["iterations_mean"],
             1e3 * summary["step_seconds_median"], summary["stretch_max"], out)


class SweepOutcomes(Callback):
    """Hydra callback (conf/config.yaml ``hydra.callbacks``): remembers the sweep folder of a
    multirun in the main process, so its jobs' outcomes can be read after Hydra returns."""

    def on_multirun_start(self, config, **kwargs) -> None:
        global SWEEP_DIR
        SWEEP_DIR = Path(str(config.hydra.sweep.dir))


def sweep_outcomes(sweep_dir: Path) -> list[tuple[str, str, dict]]:
    """(job folder name, its overrides, outcome) of every job folder of a sweep, in job order."""
    rows = []
    dirs = [d for d in Path(sweep_dir).iterdir() if d.is_dir() and (d / ".hydra").is_dir()]
    for d in sorted(dirs, key=lambda d: (not d.name.isdigit(), int(d.name) if d.name.isdigit() else 0, d.name)):
        try:
            res = json.loads((d / OUTCOME).read_text())
        except (OSError, ValueError):
            res = outcome(d, "failed", 1, "the job left no outcome (it did not finish)")
        try:
            import yaml

            overrides = " ".join(yaml.safe_load((d / ".hydra" / "overrides.yaml").read_text()) or [])
        except (OSError, ValueError, TypeError):
            overrides = ""
        rows.append((d.name, overrides, res))
    return rows


def exit_code() -> int:
    """The process's exit code after Hydra returned: a single run's, or a sweep's (one line per
    job printed; the first failing job's code)."""
    if SWEEP_DIR is not None:
        rows = sweep_outcomes(SWEEP_DIR) if SWEEP_DIR.is_dir() else []
        bad = [r for r in rows if r[2]["code"] != 0]
        stream = sys.stderr if bad else sys.stdout
        for name, overrides, res in rows:
            note = "" if res.get("converged") is not False else ", not converged"
            msg = f": {res['message']}" if res.get("message") and res["code"] != 0 else ""
            print(f"hairexp: job {name} [{overrides}]: {res['status']}{note} (exit {res['code']}){msg} -> {res['out']}",
                  file=stream)
        print(f"hairexp: sweep: {len(rows) - len(bad)} of {len(rows)} jobs completed -> {SWEEP_DIR}", file=stream)
        return bad[0][2]["code"] if bad else (0 if rows else 1)
    return 0 if LAST is None else int(LAST["code"])
