"""The command line's jobs and exit codes.

A job (``job``: one Hydra job, a single run or one job of a ``-m`` sweep) never exits the
process: it runs the experiment, prints the one error line of a failure and returns its
outcome (status, exit code, run folder).  The exit code is decided in the main process after
Hydra returns (``exit_code``): for a run, the job's; for a sweep, every job has run, one line
per job is printed and the sweep exits with the first failing job's code (in job order).
A sweep job's outcome is written to ``<job folder>/.hydra/outcome.json`` (the main process
reads them back; a job that left no outcome is reported as not finished).  SIGTERM / SIGINT
in a sweep's main process first stops its running jobs (``stop_sweep_jobs``: the signal is
forwarded to the workers and the jobs are waited for, so each ends ``interrupted``).

Exit codes: 0 completed; 1 an unexpected error (or Hydra's config errors); 2 bad input
(``InputError``: a bad value, a key not in the schema added with ``+``, a used run folder, a bad
variant name); 3 the simulation failed
(``SimulationError``, including non-convergence: none of the steps converged, or some under
``on_unconverged=fail``); 4 the run folder could not be written (``OSError``: a full disk, a
blocked path; a ``hydra.run.dir`` / ``hydra.sweep.dir`` given on the command line that cannot be
a folder is refused before Hydra starts, ``run_dir_error``); 130 / 143 interrupted by SIGINT /
SIGTERM.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import re
import resource
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

import yaml
from hydra.experimental.callback import Callback

from hairexp.app.assemble import check_config
from hairexp.app.config import (CONF_DIR, check_bool_overrides, check_interpolations, check_keys, check_sections,
                                compose_config, unknown_key_hint)
from hairexp.app.experiment import apply_overrides, check_variant_names, run_experiment
from hairexp.app.run import INPUT_KEYS, end_dead_run, implausible, inputs_inside, to_log_files, write_refused
from hairexp.app.validate import unused_settings
from hairexp.app.signals import forward, read_stop_mark, take_late, watch_stop_file, worker_pids
from hairexp.app.streams import guard_streams
from hairexp.app.signals import exit_code as signal_exit_code
from hairexp.app.variant_processes import keep_sequential
from hairexp.errors import InputError, Interrupted, ScratchError, SimulationError, choice_name
from hairexp.outputs.files import atomic_write_bytes, write_json
from hairexp.outputs.folder import (LOCK, OUTCOME, RUN_DIRS, RUN_FILES, SUMMARY, inside_run_refusal,
                                    held_elsewhere, hold,
                                    hydra_link_refusal, note_job_logs, overwrite_refusal, owner, pinned,
                                    refused_summary, reserved_part, running_run, unusable_folder, used_entries,
                                    used_refusal)

log = logging.getLogger("hairexp")
#: in a sweep folder while its main process stops the sweep: the signal's name (SIGTERM, SIGINT)
STOP_MARK = ".hairexp-stopping"

#: the outcome of the last job run in this process (single runs: read by the main process)
LAST: dict | None = None
#: the sweep folder of a multirun started in this process (set by SweepOutcomes)
SWEEP_DIR: Path | None = None
#: the number of jobs the sweep was to run (``sweep_size``), None when not a sweep or not known
SWEEP_TOTAL: int | None = None


def one_line_warning(message, category, filename, lineno, line=None) -> str:
    """``warnings.formatwarning`` of the command lines: a library's warning (OmegaConf's on an
    interpolation such as ``${oc.env:X,}``) as one line naming its category and module, not two
    with a source line of the library (probe of issue 12)."""
    module = Path(filename).stem if filename else "?"
    return f"hairexp: {category.__name__} (from {module}): {message}\n"


def outcome(out, status: str, code: int, message: str | None = None, summary: dict | None = None) -> dict:
    return {"status": status, "code": code, "message": message, "out": str(out),
            "converged": None if summary is None else summary.get("converged")}


def absolute_inputs(cfg, cwd: str | None) -> None:
    """Make the relative input paths of ``cfg`` (``run.INPUT_KEYS``) absolute against ``cwd``, the
    directory hairexp was started in: with ``hydra.job.chdir=true`` a job runs inside its run
    folder, where ``scene.usd=scene.usda`` was not found (probe of issue 12, round 11)."""
    if not cwd:
        return
    from omegaconf import OmegaConf, open_dict

    for key in INPUT_KEYS:
        value = OmegaConf.select(cfg, key, default=None)
        if isinstance(value, str) and value and not os.path.isabs(value):
            with open_dict(cfg):
                OmegaConf.update(cfg, key, os.path.join(cwd, value), merge=False)
    for v in OmegaConf.select(cfg, "variants", default=None) or []:   # a variant's own ``guides.file=...``
        ovr = v.get("overrides") if hasattr(v, "get") else None
        for i, o in enumerate(ovr or []):
            key, eq, value = str(o).partition("=")
            if eq and key.strip() in INPUT_KEYS and value.strip() and not os.path.isabs(value.strip()):
                ovr[i] = f"{key.strip()}={os.path.join(cwd, value.strip())}"


def _job_label(out: str, sweep_dir: str | None) -> str:
    """``job <name>: `` of a sweep's job folder (its path under the sweep folder), as the sweep's
    closing lines name it."""
    try:
        return f"job {Path(out).resolve().relative_to(Path(sweep_dir).resolve()).as_posix()}: "
    except (TypeError, ValueError, OSError):
        return f"job {Path(out).name}: "


def job(cfg, out: str, sweep: bool = False, sweep_dir: str | None = None, overrides=(),
        cwd: str | None = None) -> dict:
    """``_job``, with the sweep's stop mark watched while it runs (``watch_stop_file``): a worker
    process runs the next job, or the main process goes on, with nothing watched."""
    try:
        return _job(cfg, out, sweep, sweep_dir, overrides, cwd)
    finally:
        watch_stop_file(None)


def _job(cfg, out: str, sweep: bool = False, sweep_dir: str | None = None, overrides=(),
         cwd: str | None = None) -> dict:
    """Run the experiment of ``cfg`` into ``out``; returns its outcome (never raises for a
    failing run, never exits).  A sweep job that starts after the sweep was stopped
    (``<sweep_dir>/STOP_MARK``, ``stop_sweep_jobs``) ends as interrupted without running.
    ``overrides``: the job's command-line overrides (a boolean key given anything but true or
    false is bad input: a sweep's jobs are composed by Hydra, which would read ``2`` as true).
    ``cwd``: the directory hairexp was started in, which relative input paths are read from
    (``absolute_inputs``)."""
    global LAST
    # a log file on a full disk is not worth a traceback per line, in a sweep's worker process too (the
    # main process sets it in __main__.entry; a worker printed "--- Logging error ---" with a traceback
    # for each line, ~300 lines; independent probe of issue 12, round 22)
    logging.raiseExceptions = False
    # a sweep's worker process: its standard streams as the main process's (a stderr to /dev/full or a
    # closed pipe failed every job of a joblib sweep on the progress bar's first write, ENOSPC / EPIPE,
    # where a single run and the basic launcher completed; independent probe of issue 12, round 33)
    guard_streams()
    note_job_logs(Path(out))   # what its logs hold now is a previous run's (overwrite=true drops it)
    # a sweep's jobs run their variants one after the other unless asked (the workers use the cores)
    keep_sequential("a sweep's job (the sweep's workers share the cores)" if sweep else None)
    if sweep:
        # the sweep's stop mark is read between steps too: a signal forwarded while the job was starting
        # could be lost (independent probe of issue 12, round 35)
        watch_stop_file(None if sweep_dir is None else Path(sweep_dir) / STOP_MARK)
        stopped = _stopped_by(sweep_dir)
        if stopped is not None:
            msg = f"interrupted by {stopped} before the job started"
            print(f"hairexp: {msg} ({out})", file=sys.stderr)
            LAST = outcome(out, "interrupted", signal_exit_code(_signum(stopped)), msg)
            _write_outcome(out, LAST)
            # the folder says it too (it held Hydra's record and an empty log; independent probe, round 26)
            write_refused(cfg, out, msg, "interrupted", "the sweep was stopped before this job started: no step ran")
            return LAST
        _write_outcome(out, {**outcome(out, "running", 1, "the job did not finish"), "pid": os.getpid()})
    summary = None
    try:
        check_sections(cfg)   # a section deleted with ``~section``
        check_keys(cfg)   # a ``+key`` Hydra added without asking the schema
        check_interpolations(cfg)   # a ${...} that cannot be resolved (a sweep job Hydra composed)
        check_bool_overrides(list(overrides))
        absolute_inputs(cfg, cwd)
        summary = run_experiment(cfg, out, on_checked=lambda: _say_unused(cfg, overrides))
        late = take_late()   # a signal after the run had written its completed ending
        wild = implausible(summary)
        if wild is not None and late is None:
            print(f"hairexp: {wild}", file=sys.stderr)
        res = (outcome(out, "completed", 0 if wild is None else 3, wild, summary) if late is None
               else _signalled_after(out, late, summary))
        _log_completed(summary, out)
    except InputError as exc:
        # a sweep's job says which it is: the line is said again in the sweep's closing lines, which
        # name the job (it read as the same error twice; probe of issue 12, round 18)
        print(f"hairexp: error: {_job_label(out, sweep_dir) if sweep else ''}{exc}", file=sys.stderr)
        res = outcome(out, "failed", 2, str(exc))
    except SimulationError as exc:
        print(f"hairexp: simulation failed: {exc} ({kept(out, 'partial metrics', exc)})", file=sys.stderr)
        _print_notes(exc)
        res = outcome(out, "failed", 3, str(exc))
    except OSError as exc:   # the run folder could not be written (a full disk, a blocked path)
        if not Path(out).is_dir():   # moved or deleted mid-run: one line, not an errno line per ending file (round 14)
            print(f"hairexp: the run folder {out} was moved or deleted while the run went on, so its ending could "
                  f"not be written (the folder's summary.json, wherever it is now, still says running): {exc}",
                  file=sys.stderr)
        elif isinstance(exc, ScratchError) and exc.reading:   # a temporary file that does not read back
            print(f"hairexp: cannot read a temporary file back: {exc} (a disk error, or the file was changed by "
                  f"another process; TMPDIR chooses the folder; the failed summary is in {out})", file=sys.stderr)
            _print_notes(exc)
        elif isinstance(exc, ScratchError):   # not the run folder: the system's temporary folder (TMPDIR)
            print(f"hairexp: cannot write a temporary file: {exc} (a full disk, or a file-size limit: ulimit -f; TMPDIR "
                  f"chooses the folder; the failed summary is in {out})", file=sys.stderr)
            _print_notes(exc)   # the failed ending's own write errors, as for the run folder's
        else:
            where = getattr(exc, "run_folder", None) or out   # a variant's folder (an experiment's own run)
            print(f"hairexp: cannot write the run folder {where}: {exc}{_limit_hint(exc)}", file=sys.stderr)
            _print_notes(exc)
        res = outcome(out, "failed", 4, str(exc))
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else 2
        msg = str(exc) if isinstance(exc, Interrupted) else "interrupted by SIGINT"
        if summary is not None and summary.get("status") == "completed":   # the run had ended: nothing partial
            res = _signalled_after(out, signum, summary)
        else:
            print(f"hairexp: {msg} ({kept(out, 'partial results', exc)})", file=sys.stderr)
            _print_notes(exc)
            res = outcome(out, "interrupted", signal_exit_code(signum), msg)
    except MemoryError as exc:   # numpy's ArrayMemoryError too: a size the checks did not foresee (probe, round 14)
        why = " ".join(str(exc).split()) or "an allocation failed"
        print(f"hairexp: out of memory: {why} ({kept(out, 'partial metrics', exc)}); make the run smaller "
              "(scene.n_strands, scene.n_vertices, guides.count, tracking.points_per_guide) or lower the setting that "
              "sized it",
              file=sys.stderr)
        res = outcome(out, "failed", 3, f"out of memory: {why}")
    except Exception as exc:   # noqa: BLE001  (a bug: the traceback, exit 1; the sweep's other jobs go on)
        traceback.print_exc()
        res = outcome(out, "failed", 1, f"{type(exc).__name__}: {exc}")
    if res["status"] != "completed":
        restore_previous_record(out)   # overwrite=true that ended before the run claimed the folder
    if res["status"] != "completed" and Path(out).is_dir() and (
            not (Path(out) / SUMMARY).exists() or refused_summary(Path(out) / SUMMARY)):
        # ended before the run claimed the folder Hydra made (refused by its settings; a signal, or a temporary
        # file that could not be written, while they were checked): the folder says how all the same
        why = {"interrupted": "interrupted while its settings were checked"}.get(
            res["status"], "refused by its settings" if res["code"] == 2 else "failed while its settings were checked")
        write_refused(cfg, out, res["message"], res["status"], f"{why}, before the run claimed its folder: no step ran")
    if res["status"] != "completed" or res["code"]:
        to_log_files(f"{res['status']} (exit {res['code']}): {res['message']}")
    LAST = res
    if sweep:
        _write_outcome(out, res)
        if res["status"] == "interrupted" and SWEEP_DIR is not None:
            # the launcher runs the jobs in this process (hydra/launcher=basic): the signal ended this
            # job only, and the launcher went on to start the next ones (probe of issue 12, round
            # 10); raised, it ends the sweep here, its later jobs said as not started
            signum = res["code"] - 128 if res["code"] > 128 else int(signal.SIGTERM)
            try:
                (SWEEP_DIR / STOP_MARK).write_text(signal.Signals(signum).name + "\n")
            except (OSError, ValueError):
                pass
            raise Interrupted(signum)
    return res


def _limit_hint(exc: OSError) -> str:
    """Where a bare ``[Errno 27] File too large`` came from (a numpy or parquet write names no
    file): the process's file-size limit."""
    if exc.errno == errno.EFBIG and "ulimit" not in str(exc):
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft != resource.RLIM_INFINITY:
            return f" (a file reached the process's file-size limit, ulimit -f: {soft} bytes)"
    if exc.errno == errno.EMFILE:   # not the folder's fault (own probe, 2026-12-05: ulimit -n 16)
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        return (f" (the process's open-file limit, ulimit -n {soft}: a run holds about 30 files open, its "
                "libraries' included; raise it)")
    return ""


def _say_unused(cfg, overrides) -> None:
    """A warning for the command line's keys (and each variant's own) that no run of the launch
    reads (``validate.unused_settings``): said, not refused, since a key shared by an
    experiment's variants is read by some of them."""
    keys = [o.split("=", 1)[0] for o in overrides if "=" in o and not o.lstrip("+~").startswith("hydra.")]
    runs = [cfg]
    if cfg.get("variants"):
        try:
            runs = [apply_overrides(cfg, list(v.overrides), f"variants[{i}] ({v.name})") for i, v in enumerate(cfg.variants)]
        except InputError:   # said by the run's own checks
            return
        for v, vcfg in zip(cfg.variants, runs):
            own = unused_settings([vcfg], [o.split("=", 1)[0] for o in v.overrides if "=" in o])
            if own:
                log.warning("variant %s: %s not used by it", v.name, ", ".join(own))
    unused = unused_settings(runs, keys)
    if not cfg.get("variants"):   # a judge compares an experiment's variants (silent; independent probe, round 22)
        judged = [k for k in dict.fromkeys(k.lstrip("+~") for k in keys) if k in ("judge", "judge_tolerance")
                  and not any(u.startswith(f"{k} (") for u in unused)]
        if judged:
            unused.append(f"{', '.join(judged)} (read with variants: a judge compares an experiment's variants; "
                          "variants=[] runs the base config alone)")
    if unused:
        log.warning("%s not used by %s", ", ".join(unused), "any variant" if len(runs) > 1 else "this run")


def kept(out, what: str, exc: BaseException | None = None) -> str:
    """Where a failed or interrupted run's data are: ``what`` in the folder when a step's metrics
    were kept (metrics.parquet, here or in a variant's folder), else that no step ran (it said
    "partial results" when nothing but the summary was there; probe of issue 12).  ``exc``: the
    error, whose ``run_folder`` is the failing variant's folder (an experiment's): its own steps
    (it said "partial metrics" of the variants before it; independent probe, round 26)."""
    variant = getattr(exc, "run_folder", None)
    if variant is not None and Path(variant) != Path(out) and _this_runs(Path(out)):
        if (Path(variant) / "metrics.parquet").is_file():
            return f"{what} in {variant}"
        before = sorted(p.parent.name for p in Path(out).glob("*/metrics.parquet"))
        name = Path(variant).name
        # a signal between two variants: the next one had no folder yet (round 27: its summary.json was named)
        said = (f"its summary.json in {variant} says so" if (Path(variant) / SUMMARY).is_file()
                else f"it had not begun (the experiment's summary.json in {out} says so)")
        return (f"no step of the hair of variant {name} ran: {said}"
                + (f"; the variants before it ({', '.join(before)}) are in {out}" if before else ""))
    if not _this_runs(Path(out)):   # ended before the run claimed the folder: what is there is not its
        summary = Path(out) / SUMMARY   # (round 23: "partial results" of the old run)
        if summary.is_file() and not refused_summary(summary):   # overwrite=true that never began (round 24)
            return f"no step of the hair ran; {out} still holds the previous run, as it was"
        return f"no step of the hair ran; summary.json in {out} says so"
    if any(Path(out).rglob("metrics.parquet")):
        return f"{what} in {out}"
    return f"no step of the hair ran; summary.json in {out} says so"


def _this_runs(out: Path) -> bool:
    """Whether ``out``'s summary.json is this process's run's (its ``pid`` and ``host``)."""
    try:
        d = json.loads((out / SUMMARY).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and {k: d.get(k) for k in ("pid", "host")} == owner()


def _signalled_after(out, signum: int, summary: dict) -> dict:
    """The outcome of a run that completed before ``signum`` arrived: completed, exit 128 +
    signal, said on stderr."""
    name = signal.Signals(signum).name
    print(f"hairexp: {name} after the run had completed; its results are whole (summary.json: completed) ({out})",
          file=sys.stderr)
    return outcome(out, "completed", signal_exit_code(signum), f"{name} after the run had completed", summary)


def _stopped_by(sweep_dir) -> str | None:
    """The signal's name in ``<sweep_dir>/STOP_MARK``, or None."""
    signum = None if sweep_dir is None else read_stop_mark(Path(sweep_dir) / STOP_MARK)
    return None if signum is None else signal.Signals(signum).name


def _signum(name: str) -> int:
    return int(signal.Signals[name])


def clear_stop_mark() -> None:
    """Remove the stop mark of this process's sweep (its workers are gone)."""
    if SWEEP_DIR is not None:
        try:
            (SWEEP_DIR / STOP_MARK).unlink(missing_ok=True)
        except OSError:
            pass


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
        global SWEEP_DIR, SWEEP_TOTAL
        SWEEP_DIR = Path(str(config.hydra.sweep.dir))
        SWEEP_TOTAL = sweep_size(list(config.hydra.overrides.task))


def sweep_size(overrides: list[str]) -> int | None:
    """The number of jobs of a basic sweep over ``overrides`` (the product of the swept values'
    counts), None if it cannot be told (an override the parser cannot read)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        n = 1
        for o in OverridesParser.create().parse_overrides(overrides):
            if o.is_sweep_override():
                n *= len(list(o.sweep_string_iterator()))
        return n
    except Exception:  # noqa: BLE001  (a range or a sweep the basic count does not cover)
        return None


def _job_folders(root: Path) -> list[Path]:
    """The job folders of the sweep folder ``root`` (a ``.hydra/`` of their own), at any depth:
    hydra.sweep.subdir may nest (``a/${hydra.job.num}``; the report looked one level down only and
    called such jobs not started, probe of issue 12, round 9), in job order."""
    def order(d):
        return tuple((not p.isdigit(), int(p) if p.isdigit() else 0, p) for p in d.relative_to(root).parts)

    return sorted({h.parent for h in root.rglob(".hydra") if h.is_dir() and h.parent != root}, key=order)


#: marks an outcome made up by ``sweep_outcomes`` for a job folder that held none (``_end_killed_jobs``)
_NO_OUTCOME = "_no_outcome"


def sweep_outcomes(sweep_dir: Path) -> list[tuple[str, str, dict]]:
    """(job folder name, its overrides, outcome) of every job folder of a sweep, in job order."""
    rows = []
    root = Path(sweep_dir)
    for d in _job_folders(root):
        try:
            res = json.loads((d / OUTCOME).read_text())
        except (OSError, ValueError):
            res = outcome(d, "failed", 1, "the job left no outcome (it did not finish)")
            res[_NO_OUTCOME] = True
        try:
            # Hydra's sweeper writes a job's booleans as Python's True / False: shown as they are typed
            overrides = " ".join(re.sub(r"=(True|False)$", lambda m: "=" + m.group(1).lower(), str(o))
                                 for o in yaml.safe_load((d / ".hydra" / "overrides.yaml").read_text()) or [])
        except (OSError, ValueError, TypeError, yaml.YAMLError):
            overrides = ""
        rows.append((d.relative_to(root).as_posix(), overrides, res))
    return rows


def _wait_workers_gone(seconds: float = 10.0) -> None:
    """Wait until this process has no worker processes left (the launcher's teardown), at most ``seconds``."""
    end = time.monotonic() + seconds
    while worker_pids() and time.monotonic() < end:
        time.sleep(0.1)


def _end_killed_jobs(rows: list, signum: int | None, workers_gone: bool = False) -> None:
    """Jobs whose outcome still says running and whose process is gone (a sweep's teardown
    killed a worker before its job wrote its ending; probe of issue 12: the job's summary.json
    stayed "running" with its ``.ending.reserve``): their summary and outcome are ended here as
    ``interrupted`` (the sweep was signalled) or ``failed``, saying that the process ended."""
    for name, _, res in rows:
        d = SWEEP_DIR / name
        if res.get(_NO_OUTCOME) and signum is not None and not (d / SUMMARY).exists():
            # Hydra made the job's folder and the signal came before its run wrote anything: it said
            # "failed (exit 1): the job left no outcome" (independent probe of issue 12, round 31)
            sig = signal.Signals(signum).name
            why = f"the sweep was stopped by {sig} before the job's run began"
            write_refused(None, d, why, "interrupted", f"stopped by {sig} before the run claimed its folder: no step ran")
            res.pop(_NO_OUTCOME)
            res.update(status="interrupted", code=signal_exit_code(signum), message=why)
            _write_outcome(d, res)
            continue
        res.pop(_NO_OUTCOME, None)
        if res.get("status") != "running":
            continue
        found = running_run(d)
        if found is None and workers_gone and not (d / SUMMARY).exists():
            # ended by the launcher before its run claimed its folder: said in the folder as such (round 24)
            why = "the launcher ended the job's process (hydra.launcher.timeout) before its run began"
            write_refused(None, d, why, "failed", "ended by the sweep's launcher before the run claimed its folder: "
                          "no step ran")
            res.update(status="failed", code=3, message=why)
            _write_outcome(d, res)
            continue
        if found is None or (found[0] != "killed" and not (workers_gone and found[0] == "live")):
            continue
        summary = found[1]
        status = "interrupted" if signum is not None else "failed"
        # a healthy job's worker is torn down with the others when one worker is killed (loky): said so (round 14)
        why = (f"the job's process ended before it wrote its ending (pid {summary['pid']}"
               + (f", the sweep was stopped by {signal.Signals(signum).name})" if signum is not None
                  else ": ended by the launcher, hydra.launcher.timeout)" if workers_gone
                  else ": killed, or stopped with the sweep's other workers when one of them was killed)"))
        # the job's folder, and an experiment's variant folders in it (a variant's summary stayed
        # "running" under its failed experiment; independent probe of issue 12, round 24)
        for f, s in [(d, summary)] + [(v, r[1]) for v in sorted(p for p in d.iterdir() if p.is_dir())
                                       if (r := running_run(v)) is not None and r[0] in ("killed", "live")]:
            end_dead_run(f, s, status, why)
        # killed (the out-of-memory killer, a SIGKILL): a run that could not continue, exit 3 as an
        # allocation that failed; 1 is a bug's traceback (probe of issue 12, round 18)
        res.update(status=status, code=signal_exit_code(signum) if signum is not None else 3, message=why)
        _write_outcome(d, res)


def sweep_completed() -> bool:
    """True in a sweep whose every job has run and ended completed (its outcome in Hydra's record)."""
    if SWEEP_DIR is None or not SWEEP_DIR.is_dir():
        return False
    rows = sweep_outcomes(SWEEP_DIR)
    return bool(rows) and len(rows) >= (SWEEP_TOTAL or 0) and all(r[2].get("status") == "completed" for r in rows)


def exit_code(signum: int | None = None, workers_gone: bool = False) -> int:
    """The process's exit code after Hydra returned: a single run's, or a sweep's (one line per
    job printed; the first failing job's code).  ``signum``: the signal that stopped the sweep;
    ``workers_gone``: the launcher ended its worker processes (hydra.launcher.timeout)."""
    if SWEEP_DIR is not None:
        rows = sweep_outcomes(SWEEP_DIR) if SWEEP_DIR.is_dir() else []
        if workers_gone:
            _wait_workers_gone()
        _end_killed_jobs(rows, signum, workers_gone)
        bad = [r for r in rows if r[2]["code"] != 0]
        total = max(len(rows), SWEEP_TOTAL or 0)
        # the job lines and the closing line on one stream: stderr when a job failed or never ran (the job
        # lines went to stdout and the closing line to stderr in an interrupted sweep; round 24)
        stream = sys.stderr if bad or total > len(rows) else sys.stdout
        for name, overrides, res in rows:
            note = "" if res.get("converged") is not False else ", not converged"
            msg = f": {res['message']}" if res.get("message") and res["code"] != 0 else ""
            print(f"hairexp: job {name} [{overrides}]: {res['status']}{note} (exit {res['code']}){msg} -> {res['out']}",
                  file=stream)
        unstarted = f" ({total - len(rows)} not started)" if total > len(rows) else ""
        if unstarted:   # an interrupted sweep: its jobs that never ran are said, not left out (probe of issue 12)
            bad = bad or [("", "", {"code": 1})]
        print(f"hairexp: sweep: {len(rows) - sum(1 for r in rows if r[2]['code'] != 0)} of {total} jobs completed"
              f"{unstarted} -> {SWEEP_DIR}", file=stream)
        return bad[0][2]["code"] if bad else (0 if rows else 1)
    return 0 if LAST is None else int(LAST["code"])


#: the smallest file-size limit (RLIMIT_FSIZE, ``ulimit -f``) a run starts under: Hydra's own
#: .hydra/config.yaml (4-5 kB) and the run's summary.json (about 10 kB) must fit
MIN_FILE_SIZE_LIMIT = 64 << 10


def file_size_limit_error(argv: list[str]) -> str | None:
    """The error line when the process's file-size limit cannot hold a run's first files, or None.
    Under ``ulimit -f 1`` Hydra's write of .hydra/config.yaml failed with its traceback, exit 1,
    and no summary (probe of issue 12, round 18).  A larger limit that a run reaches later is the
    run's own failure (exit 4, its summary failed)."""
    if prints_only(argv):
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft == resource.RLIM_INFINITY or soft >= MIN_FILE_SIZE_LIMIT:
        return None
    return (f"hairexp: error: the process's file-size limit (ulimit -f) is {soft} bytes, less than the "
            f"{MIN_FILE_SIZE_LIMIT >> 10} kB a run needs to write its first files (Hydra's .hydra/config.yaml, "
            "summary.json); raise it (ulimit -f unlimited)")


def _default_dir(key: str) -> str | None:
    """The run folder conf/config.yaml gives ``key`` (``hydra.run.dir`` / ``hydra.sweep.dir``)."""
    import yaml

    try:
        node = yaml.safe_load((CONF_DIR / "config.yaml").read_text())
        for part in key.split("."):
            node = node[part]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return str(node) if isinstance(node, str) else None


#: ``${oc.env:NAME}`` / ``${oc.env:NAME,default}`` in a folder path (resolved before the checks)
_ENV_INTERPOLATION = re.compile(r"\$\{oc\.env:([A-Za-z_][A-Za-z0-9_]*)(?:,([^}]*))?\}")


def _resolve_env(path: str) -> str:
    """``path`` with its ``${oc.env:NAME[,default]}`` replaced from the environment (left as it
    is when NAME is unset and no default is given)."""
    return _ENV_INTERPOLATION.sub(lambda m: os.environ.get(m.group(1), m.group(0) if m.group(2) is None
                                                           else m.group(2).strip().strip("'\"")), path)


def _static_part(path: str) -> str | None:
    """The part of ``path`` before its first interpolation (``${...}``), up to its last ``/``;
    None when the path starts with one.  ``${oc.env:NAME}`` is resolved first, from the
    environment (a run folder given as an environment variable that names a file gave Hydra's
    traceback, exit 1; probe of issue 12)."""
    path = _resolve_env(path)
    if "${" not in path:
        return path
    static = path[:path.index("${")]
    if not static:
        return None
    return static[:static.rindex("/") + 1] if "/" in static else "."


#: Hydra's command-line flags that take the next argument as their value
_FLAGS_WITH_VALUE = ("--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                     "--config-dir", "-cd", "--info", "-i", "--experimental-rerun")


#: Hydra's command-line flags (hydra 1.3's argparse parser)
_FLAGS = frozenset(_FLAGS_WITH_VALUE + ("-h", "--help", "--hydra-help", "--version", "-r", "--run", "--resolve", "-m",
                                        "--multirun", "-sc", "--shell-completion"))
#: the flags with which Hydra prints something and runs nothing
_NO_RUN_FLAGS = frozenset({"-h", "--help", "--hydra-help", "--version", "-c", "--cfg", "-i", "--info", "-sc",
                           "--shell-completion"})


#: the values ``--info`` takes (argparse: an optional value among these choices)
_INFO_CHOICES = ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath")


def _is_value(argv: list[str], i: int) -> bool:
    """Whether ``argv[i]`` is the value of the flag before it (``--cfg job``; ``--info`` takes
    one only among its choices): the one reading of Hydra's flag grammar every check here uses."""
    if i < 1 or argv[i - 1] not in _FLAGS_WITH_VALUE:
        return False
    return argv[i - 1] not in ("-i", "--info") or argv[i] in _INFO_CHOICES


def _flag(arg: str) -> str:
    """The flag ``arg`` names (``--cfg=job`` is ``--cfg``)."""
    return arg.split("=", 1)[0] if arg.startswith("--") else arg


def version() -> str:
    """hairexp's version: the installed package's, else pyproject.toml's (a checkout run in place)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("hairexp")
    except PackageNotFoundError:
        pass
    try:
        text = (CONF_DIR.parent / "pyproject.toml").read_text()
    except OSError:
        return "unknown"
    found = re.search(r'^version\s*=\s*"([^"]+)"', text, re.M)
    return found.group(1) if found else "unknown"


#: the flags with which the config given is composed as for a run (``config_error`` checks it first:
#: ``--cfg job solver.dt=abc`` gave Hydra's multi-line message, exit 1; independent probe, round 22)
_COMPOSING_FLAGS = frozenset({"-m", "--multirun", "--cfg", "-c", "--resolve", "--package", "-p"})
#: Hydra's mutually exclusive modes (its ValueError "Only one of --run, --multirun, --cfg, --info and
#: --shell-completion can be specified" came as a traceback, exit 1; independent probe, round 22)
_MODES = {"--run": "--run", "-r": "--run", "--multirun": "--multirun", "-m": "--multirun", "--cfg": "--cfg",
          "-c": "--cfg", "--info": "--info", "-i": "--info", "--shell-completion": "--shell-completion",
          "-sc": "--shell-completion"}


def mode_error(argv: list[str]) -> str | None:
    """The error line for more than one of Hydra's modes on one command line (``-m --cfg job``)."""
    modes = []
    for i, a in enumerate(argv):
        m = _MODES.get(_flag(a))
        if m is not None and not _is_value(argv, i) and m not in modes:
            modes.append(m)
    if len(modes) > 1:
        return (f"hairexp: error: {' and '.join(modes)} given together; give one of --run, --multirun (-m), --cfg (-c), "
                "--info (-i), --shell-completion (-sc)")
    return None


def flag_error(argv: list[str]) -> str | None:
    """The error line for a command-line flag Hydra does not have (``--bogus-flag``), before any
    folder is made: Hydra's argparse refused it (exit 2) after hairexp had taken the run folder's
    launch lock, leaving an empty folder (probe of issue 12, round 13).  An abbreviation that
    argparse would take (``--multi``) is refused too, naming the flag: hairexp's own checks of
    the run or sweep folder read the flags written in full."""
    for i, arg in enumerate(argv):
        if arg.startswith("-") and _flag(arg) not in _FLAGS and not _is_value(argv, i):
            longer = sorted(f for f in _FLAGS if f.startswith("--") and f.startswith(_flag(arg)))
            if arg.startswith("--") and len(longer) == 1:
                return f"hairexp: error: {arg}: write the option in full: {longer[0]}"
            return (f"hairexp: error: unknown option {arg}; the options are Hydra's ({', '.join(sorted(_FLAGS))}), "
                    "the rest key=value overrides (python -m hairexp --help)")
    return None


def flag_values(argv: list[str], *names: str) -> list[str]:
    """The values given to the flag ``names`` (``-cn x`` and ``--config-name=x`` alike)."""
    out = []
    for i, arg in enumerate(argv):
        if _is_value(argv, i):
            continue
        if arg in names and i + 1 < len(argv):
            out.append(argv[i + 1])
        elif "=" in arg and arg.split("=", 1)[0] in names:
            out.append(arg.split("=", 1)[1])
    return out


def config_source_error(argv: list[str]) -> str | None:
    """The error line for ``--config-dir`` / ``-cd`` that is not a folder, ``--config-path`` /
    ``-cp`` that is not one (absolute, or relative to hairexp/, as Hydra reads it), or
    ``--config-name`` / ``-cn`` that none of them (nor the schema's registered configs) holds; before
    any folder is made.  Hydra found these after hairexp had locked the run folder: exit 1 with its
    multi-line message and a folder holding only ``.lock``, and in a ``-m`` sweep a traceback
    (probe of issue 12, round 19)."""
    from hydra.core.config_store import ConfigStore

    dirs = []
    for value in flag_values(argv, "--config-dir", "-cd"):
        path = Path(value).absolute()   # as Hydra reads it: a "~" the shell left is a folder named "~"
        if not path.is_dir():
            return (f"hairexp: error: --config-dir={value}: " + ("not a folder" if path.exists() else "no such folder")
                    + " (a folder of extra config files)")
        dirs.append(path)
    paths = flag_values(argv, "--config-path", "-cp")
    primary = [CONF_DIR]
    for value in paths:
        if "://" in value:   # pkg:// or file://: Hydra's to read
            return None
        path = Path(value)
        path = path if path.is_absolute() else Path(__file__).resolve().parents[1] / path
        if not path.is_dir():
            return (f"hairexp: error: --config-path={value}: no such folder ({path}; a relative config path is "
                    "read from hairexp/, where python -m hairexp's entry point is)")
        primary = [path]
    names = flag_values(argv, "--config-name", "-cn") or ["config"]
    name = names[-1]
    file = name if name.endswith(".yaml") else f"{name}.yaml"
    stored = ConfigStore.instance().repo
    if not any((d / file).is_file() for d in primary + dirs) and file not in stored:
        where = ", ".join(str(d) for d in primary + dirs)
        return (f"hairexp: error: --config-name={name}: no config {file} in {where}"
                + ("" if name != "config" else " (the primary config: give --config-name, or a --config-path "
                   "holding config.yaml)"))
    return None


def undecodable_config(argv: list[str]) -> str | None:
    """The first ``*.yaml`` under the command line's ``--config-dir`` folders that is not UTF-8, or None."""
    for value in flag_values(argv, "--config-dir", "-cd"):
        try:
            for p in sorted(Path(value).rglob("*.yaml")):
                try:
                    p.read_bytes().decode("utf-8")
                except UnicodeDecodeError:
                    return str(p)
        except OSError:
            continue
    return None


def shadowed_config_warning(argv: list[str]) -> str | None:
    """A warning line when a ``--config-dir`` holds files of the names hairexp's own config folder
    has (``config.yaml``, ``experiment/goaling.yaml``): Hydra reads the primary folder's first, and
    the user's file was ignored without a word, broken or not (independent probe of issue 12, round 24)."""
    primary = CONF_DIR
    for value in flag_values(argv, "--config-dir", "-cd"):
        user = Path(value).absolute()
        if not user.is_dir():
            continue
        try:
            same = sorted(str(p.relative_to(user)) for p in user.rglob("*.yaml") if (primary / p.relative_to(user)).is_file())
        except OSError:
            continue
        if same:
            return (f"hairexp: warning: --config-dir={value}: {', '.join(same[:5])}{', ...' if len(same) > 5 else ''} "
                    "not used: hairexp's own config folder has files of these names and Hydra reads them first; give "
                    "yours other names (--config-name=<name> for a primary config, experiment=<name> for an experiment)")
    return None


def duplicate_key_error(argv: list[str]) -> str | None:
    """The error line for a ``hydra.*`` key or ``overwrite`` given twice on the command line: Hydra
    took the last ``hydra.run.dir`` while hairexp had locked the first folder (probe of issue 12,
    round 15).  Other keys may repeat (the last wins, as in Hydra: a script appends its own)."""
    seen: dict[str, str] = {}
    for i, arg in enumerate(argv):
        if arg.startswith("-") or "=" not in arg or _is_value(argv, i):
            continue
        key = _key_of(arg)
        if not (key.startswith("hydra.") or key == "overwrite"):
            continue
        if key in seen:
            return f"hairexp: error: {key}: given twice on the command line ({seen[key]} and {arg}); give it once"
        seen[key] = arg
    return None


def flags_first(argv: list[str]) -> list[str]:
    """``argv`` with Hydra's flags (and their values) before the overrides: argparse refused
    ``key=value --cfg job key=value`` with its 8-line usage ("unrecognized arguments"; probe of
    issue 12, round 15).  An abbreviation or unknown flag is ``flag_error``'s."""
    flags, rest, last, i = [], [], [], 0
    while i < len(argv):
        a = argv[i]
        if a in ("-i", "--info") and not (i + 1 < len(argv) and _is_value(argv, i + 1)):
            last.append(a)   # without a value: last, or argparse takes the next override as its value
        elif a.startswith("-") and _flag(a) in _FLAGS:
            flags.append(a)
            if i + 1 < len(argv) and _is_value(argv, i + 1):
                flags.append(argv[i + 1])
                i += 1
        else:
            rest.append(a)
        i += 1
    return flags + rest + last


#: the shell function completing ``python -m hairexp ...`` from Hydra's answers (``shell_completion``).
#: The shell's word breaks are left as they are (with ``=`` among them the word completed is the part
#: after the last ``=``: the answers are cut to it); a line that is not ``python -m hairexp`` goes to
#: the completion ``python`` had before, which ``uninstall`` puts back
_COMPLETION = r"""_hairexp_completion()
{
    local words=($COMP_LINE)
    if [[ ${#words[@]} -ge 3 && "${words[0]}" == *python* && "${words[1]}" == "-m" &&
          "${words[2]}" == "hairexp" ]]; then
        local cur="${COMP_LINE:0:$COMP_POINT}" choices prefix
        [[ "$cur" =~ [[:space:]]$ ]] && cur="" || cur="${cur##*[[:space:]]}"
        choices=$(COMP_POINT=$COMP_POINT COMP_LINE=$COMP_LINE ${words[0]} -m hairexp -sc query=bash 2>/dev/null)
        COMPREPLY=($(compgen -W "$choices" -- "$cur"))
        if [[ "$COMP_WORDBREAKS" == *"="* && "$cur" == *"="* ]]; then
            prefix="${cur%"${cur##*=}"}"
            COMPREPLY=("${COMPREPLY[@]#"$prefix"}")
        fi
        compopt -o nospace 2> /dev/null
    elif [[ -n "$_HAIREXP_OLD_PYTHON_FN" ]] && declare -F "$_HAIREXP_OLD_PYTHON_FN" > /dev/null; then
        "$_HAIREXP_OLD_PYTHON_FN" "$@"
    fi
}
if [[ -z "${_HAIREXP_OLD_PYTHON+x}" ]]; then
    _HAIREXP_OLD_PYTHON="$(complete -p python 2> /dev/null)"
    _HAIREXP_OLD_PYTHON3="$(complete -p python3 2> /dev/null)"
    _HAIREXP_OLD_PYTHON_FN="$(sed -n 's/.*-F \([^ ]*\).*/\1/p' <<< "$_HAIREXP_OLD_PYTHON")"
fi
complete -o default -F _hairexp_completion python python3"""

#: what ``-sc uninstall=bash`` prints: the completions ``python`` and ``python3`` had back
_UNCOMPLETION = r"""complete -r python python3 2> /dev/null
[[ -n "$_HAIREXP_OLD_PYTHON" ]] && eval "$_HAIREXP_OLD_PYTHON"
[[ -n "$_HAIREXP_OLD_PYTHON3" ]] && eval "$_HAIREXP_OLD_PYTHON3"
unset -f _hairexp_completion
unset _HAIREXP_OLD_PYTHON _HAIREXP_OLD_PYTHON3 _HAIREXP_OLD_PYTHON_FN"""


def shell_completion(argv: list[str]) -> tuple[str | None, str | None]:
    """(what ``-sc install=bash`` / ``install=zsh`` / ``uninstall=...`` print for ``python -m
    hairexp``, or an error line; (None, None): left to Hydra).  Hydra's script completes ``python
    script.py`` and installed commands only: for ``python -m hairexp`` it never fired, and a
    query's ``COMP_LINE`` of ``python -m hairexp experiment=go`` failed with "Error parsing override
    'hairexp'" (independent probe of issue 12, round 26).  A query's line is rewritten here (in this
    process's environment) to the ``python <script> ...`` form Hydra reads.  Without a value, or
    with another shell (Hydra's fish script completes ``python script.py`` only): an error (an
    IndexError traceback, argparse's usage; round 27)."""
    flags = [a.split("=")[0] for a in argv if a in ("-sc", "--shell-completion") or a.startswith("--shell-completion=")]
    if not flags:
        return None, None
    flag, values = flags[-1], flag_values(argv, "-sc", "--shell-completion")
    value = values[-1] if values else ""
    shells = "install=bash, install=zsh, uninstall=bash, uninstall=zsh (or query=bash, which the shell asks)"
    if value.startswith("query="):
        line = os.environ.get("COMP_LINE")
        m = re.match(r"\s*\S*python[\d.]*\s+-m\s+hairexp(?=\s|$)", line or "")
        if m is not None:
            os.environ["COMP_LINE"] = "python hairexp" + line[m.end():]
        return None, None
    if value in ("install=bash", "install=zsh"):
        return ("autoload -Uz bashcompinit && bashcompinit\n" if value.endswith("zsh") else "") + _COMPLETION, None
    if value in ("uninstall=bash", "uninstall=zsh"):
        return _UNCOMPLETION, None
    if value.split("=")[0] in ("install", "uninstall"):
        return None, f"hairexp: error: {flag} {value}: python -m hairexp completes in bash and zsh: {shells}"
    return None, f"hairexp: error: {flag}: give one of {shells}" + (f"; got {value!r}" if value else "")


def hydra_help_argv(argv: list[str]) -> tuple[list[str], list[str]]:
    """(``argv`` without the overrides ``--hydra-help`` does not read, those overrides).  Hydra's
    own help composes Hydra's config alone, and refused ``experiment=goaling_smoke`` with "Could
    not override 'experiment'. No match in the defaults list" (a valid choice; independent probe
    of issue 12, round 26); ``hydra.*`` overrides are read."""
    if "--hydra-help" not in argv:
        return argv, []
    kept, dropped = [], []
    for i, a in enumerate(argv):
        override = not a.startswith("-") and not _is_value(argv, i)
        (dropped if override and not a.lstrip("+~").startswith("hydra.") else kept).append(a)
    return kept, dropped


def unused_folder_key(argv: list[str]) -> str | None:
    """A warning line for ``hydra.run.dir`` given to a ``-m`` sweep, or ``hydra.sweep.dir`` /
    ``hydra.sweep.subdir`` to a single run: the other mode's folder, not used (probe of issue 12,
    round 15)."""
    sweep = _multirun(argv)
    keys = ("hydra.run.dir",) if sweep else ("hydra.sweep.dir", "hydra.sweep.subdir")
    given = [k for k in keys if _given(argv, k) is not None]
    if not given:
        return None
    where = "its jobs go under hydra.sweep.dir" if sweep else "a single run writes into hydra.run.dir"
    return f"hairexp: warning: {', '.join(given)} not used by {'a -m sweep' if sweep else 'a single run'} ({where})"


def prints_only(argv: list[str]) -> bool:
    """Whether Hydra only prints something for ``argv`` (``--help``, ``--cfg``, ``--info``, ...):
    nothing runs, so no run folder is checked, locked or made (``--cfg job`` left an empty
    folder holding a ``.lock``; probe of issue 12, round 13)."""
    return any(_flag(a) in _NO_RUN_FLAGS for i, a in enumerate(argv) if not _is_value(argv, i))


def _made_on_the_way(path: str) -> str | None:
    """The first folder of ``path`` that does not exist and is followed by a '..' (``os.makedirs``
    makes it, then climbs out of it), or None."""
    parts = Path(path).parts
    for i, part in enumerate(parts[:-1]):
        if parts[i + 1] == ".." and part not in ("..", "/") and not Path(*parts[:i + 1]).exists():
            return str(Path(*parts[:i + 1]))
    return None


def override_syntax_error(argv: list[str]) -> str | None:
    """The error line for a ``key=value`` argument that Hydra's override grammar cannot parse (a
    value with non-ASCII characters or an unbalanced bracket, unquoted), or for an empty run folder
    (``hydra.run.dir=`` would write the run into the working folder), or None.  Every override is
    checked, Hydra's own keys and sweeps included: Hydra would print its multi-line message and
    exit 1 (for hydra.* keys and ``-m``), before any of hairexp's checks."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for i, arg in enumerate(argv):
        if arg.startswith("-") or _is_value(argv, i):
            continue
        try:
            o = parser.parse_override(arg)
        except Exception as exc:  # noqa: BLE001  (Hydra's grammar errors)
            why = " ".join(str(exc).split()).split(" See https://")[0]
            why = re.sub(r"^.*?Exception: \S.*?\^ ", "", why)
            if "=" not in arg:   # a word alone: after --info, Hydra printed its plugins first (round 31)
                why = re.sub(r"^Error parsing override '.*?' ", "", why)
                return f"hairexp: error: {arg}: not a valid override: {why} (an override is key=value)"
            key, value = arg.split("=", 1)
            dotted = re.sub(r"\[(\d+)\]", r".\1", key)
            if dotted != key:   # the key's syntax, not the value's: quoting the value did not help (probe, round 14)
                return f"hairexp: error: {arg}: a list item is named with dots in a key, not brackets: {dotted}={value}"
            if value.lstrip().startswith(("[", "{")) and "=" in value:
                # quoting the whole list would make it a string (probe of issue 12)
                return (f"hairexp: error: {arg}: not a valid override ({why}); inside a list or a dict, quote each "
                        "item that holds '=' or other special characters, e.g. overrides: ['controller.name=free'] "
                        "(in the shell, the whole argument in double quotes)")
            return (f"hairexp: error: {arg}: not a valid override ({why}); quote a value with spaces, "
                    f"non-ASCII characters or brackets: {key}='...' (in the shell: \"{key}='...'\")")
        empty = not o.is_sweep_override() and str(o.value() if o.value() is not None else "").strip() == ""
        if empty and o.key_or_group in ("hydra.run.dir", "hydra.sweep.dir"):
            return (f"hairexp: error: {o.key_or_group}: is empty; give the run folder's path "
                    "(an empty one would put the run's files in the working folder)")
        if empty and o.key_or_group == "hydra.sweep.subdir":
            # every job would write into the sweep folder itself (probe of issue 12, round 9: exit 1,
            # "the folder is not empty (multirun.yaml)")
            return ("hairexp: error: hydra.sweep.subdir: is empty; a job's folder lies inside the sweep folder: keep "
                    "the default (${hydra.job.num}) or give a relative path that differs per job")
    return None


def _multirun(argv: list[str]) -> bool:
    """A ``-m`` sweep: ``-m``/``--multirun`` or ``hydra.mode=MULTIRUN`` on the command line."""
    return any(a in ("-m", "--multirun") or a.lstrip("+") in ("hydra.mode=MULTIRUN", "hydra.mode=multirun")
               for a in argv)


def _overwrite_given(argv: list[str], parser) -> bool:
    """``overwrite=true`` on the command line (the run's own check decides in every other case)."""
    for arg in argv:
        if arg.lstrip("+~").startswith("overwrite="):
            try:
                v = parser.parse_override(arg).value()
            except Exception:  # noqa: BLE001  (a syntax error: the config check says so)
                return True
            return str(v).lower() == "true"
    return False


def used_dir_error(argv: list[str]) -> str | None:
    """The error line for a command line's ``hydra.run.dir`` (a single run, a fixed path) that
    holds another run, unless ``overwrite=true`` is given: refused before Hydra writes its
    ``.hydra/`` files into it (they were replaced by the refused run's; probe of issue 12).  The
    run's own ``claim`` checks it again (launches racing into one folder, a config's overwrite)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    if _multirun(argv):
        return _used_sweep_dir_error(argv, parser)
    folder = _fixed_folder(argv, "hydra.run.dir", parser)
    if folder is None:
        return None
    linked = hydra_link_refusal(folder)
    if linked is not None:
        return f"hairexp: error: {folder}: {linked}"
    inside = inside_run_error(folder, "hydra.run.dir")
    if inside is not None:
        return inside
    if _overwrite_given(argv, parser):   # a finished run is replaced; a live one is not, nor foreign files (nor its .hydra/)
        refused = overwrite_refusal(folder)
        if refused is not None:
            return f"hairexp: error: {folder}: {refused}"
        if not used_entries(folder):
            return None
        bad = _overwrite_config_error(argv)
        if bad is None:
            _keep_previous_record(folder)
        return bad
    refused = used_refusal(folder)
    return None if refused is None else f"hairexp: error: {folder}: {refused}"


#: (folder, {name: bytes}, {log file: bytes}) of the ``.hydra/`` record and the job logs' sizes of the
#: run that ``overwrite=true`` is to replace, read before Hydra writes this launch's over them
#: (``restore_previous_record``)
_PREVIOUS_RECORD: tuple[Path, dict[str, bytes], dict[Path, int]] | None = None


def _keep_previous_record(folder: Path) -> None:
    global _PREVIOUS_RECORD
    record = Path(folder) / ".hydra"
    try:
        files = {p.name: p.read_bytes() for p in record.iterdir() if p.is_file() and not p.is_symlink()}
        logs = {p.resolve(): p.stat().st_size for p in Path(folder).glob("*.log") if p.is_file() and not p.is_symlink()}
    except OSError:
        return
    _PREVIOUS_RECORD = (Path(folder).resolve(), files, logs)


def restore_previous_record(out) -> None:
    """A launch with ``overwrite=true`` that ended before its run claimed the folder (a signal, a
    refused setting): the previous run is still there, and Hydra had written this launch's
    ``.hydra/`` over that run's; its own record is put back, so that the folder is one run's
    (its completed summary beside the other launch's config; independent probe of issue 12, round 23)."""
    if _PREVIOUS_RECORD is None or _this_runs(Path(out)):
        return
    folder, files, logs = _PREVIOUS_RECORD
    try:
        if Path(out).resolve() != folder or not used_entries(folder):
            return
        for name, data in files.items():
            atomic_write_bytes(folder / ".hydra" / name, lambda f, data=data: f.write(data))
    except OSError as exc:
        to_log_files(f"{out}: cannot put the previous run's .hydra/ back: {exc}")
        return
    # and its log as it was: this launch's lines (its "interrupted" line under the previous run's
    # "completed" one; independent probe of issue 12, round 27) are cut, and it writes no more there
    root = logging.getLogger()
    for h in [h for h in root.handlers if isinstance(h, logging.FileHandler)]:
        if Path(h.baseFilename).resolve().parent == folder:
            root.removeHandler(h)
            h.close()
    for log_file, size in logs.items():
        try:
            if log_file.is_file() and log_file.stat().st_size > size:
                os.truncate(log_file, size)
        except OSError:
            pass


def inside_run_error(folder: Path, key: str) -> str | None:
    """The error line when ``folder`` lies inside another run's folder (a parent holds a run's
    ``summary.json``): that folder then mixed two runs (probe of issue 12, round 12), or None."""
    why = inside_run_refusal(folder, key)
    return None if why is None else f"hairexp: error: {folder}: {why}"


def live_folder_error(argv: list[str]) -> str | None:
    """The error line when the command line's fixed run (sweep) folder is, or lies inside, a
    folder another launch holds now (``held_elsewhere``), or None; nothing is taken or created.
    Checked before ``used_dir_error``: that launch is the reason to name, not the files it has
    written so far (probe of issue 12, round 12)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    key = "hydra.sweep.dir" if _multirun(argv) else "hydra.run.dir"
    folder = _fixed_folder(argv, key, OverridesParser.create())
    if folder is None:
        return None
    what = "sweep" if key == "hydra.sweep.dir" else "run"
    for parent in Path(os.path.abspath(folder)).parents:   # inside a live launch's folder (a sweep's job folder)
        if held_elsewhere(parent):
            return (f"hairexp: error: {folder}: lies inside {parent}, a folder another launch is using now; choose "
                    f"a {key} outside it")
    try:
        if held_elsewhere(Path(folder)):
            return (f"hairexp: error: {folder}: another launch is using this {what} folder now; a {what} folder "
                    f"belongs to one {what}: choose another {key}")
    except OSError:
        return None
    return None


def hold_folder_error(argv: list[str]) -> str | None:
    """Take the launch lock (``folder.hold``) of the command line's fixed ``hydra.run.dir`` (a
    ``-m`` sweep: ``hydra.sweep.dir``) before Hydra writes into it; the error line when another
    launch holds it.  Called after ``used_dir_error`` (``live_folder_error`` before it): two
    launches that both found the folder empty are told apart here, and the second never reaches
    Hydra (it rewrote the first one's ``.hydra/`` record; probe of issue 12, round 10).  A folder
    that cannot be created is left to ``run_dir_error`` and the run."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    key = "hydra.sweep.dir" if _multirun(argv) else "hydra.run.dir"
    folder = _fixed_folder(argv, key, OverridesParser.create())
    if folder is None:
        return None
    what = "sweep" if key == "hydra.sweep.dir" else "run"
    live = live_folder_error(argv)
    if live is not None:
        return live
    try:
        if hold(folder):
            return None
    except InputError as exc:
        return f"hairexp: error: {exc}"
    except OSError:
        return None
    return (f"hairexp: error: {folder}: another launch is using this {what} folder now; a {what} folder belongs "
            f"to one {what}: choose another {key}")


def _overwrite_config_error(argv: list[str]) -> str | None:
    """The error line of a single run's settings (``check_config``) when ``overwrite=true`` is to
    replace a finished run: checked before Hydra replaces that run's ``.hydra/`` record and before
    its files go (a bad value deleted the run it was to replace and then was refused; probe of
    issue 12).  Composition errors are ``config_error``'s; a run checks its config again."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = _plain_overrides(argv)
    try:
        cfg = compose_config(overrides)
        folder = _fixed_folder(argv, "hydra.run.dir", OverridesParser.create())
        inside = None if folder is None else inputs_inside(cfg, folder)
        if inside is not None:
            return f"hairexp: error: {folder}: {inside}"
        check_config(cfg)
    except InputError as exc:
        return f"hairexp: error: {exc}"
    except Exception:  # noqa: BLE001  (not composable: config_error's message, after this)
        return None
    return None


def _fixed_folder(argv: list[str], key: str, parser) -> Path | None:
    """The folder the command line's ``key`` (``hydra.run.dir``, ``hydra.sweep.dir``) names, when
    it is one fixed path (not a sweep, not an interpolation such as ``${now:...}``), or None."""
    for arg in argv:
        if not arg.lstrip("+~").startswith(key + "="):
            continue
        try:
            o = parser.parse_override(arg)
        except Exception:  # noqa: BLE001  (a syntax error: Hydra's own message)
            return None
        value = None if o.value() is None else _resolve_env(str(o.value()))
        if o.is_sweep_override() or value is None or _static_part(value) != value:
            return None
        return Path(value)
    return None


def _given(argv: list[str], key: str) -> str | None:
    """The text after ``key=`` of the command line's first ``key=...`` (with or without ``+``/``~``)."""
    return next((a.split("=", 1)[1] for a in argv if a.lstrip("+~").startswith(key + "=")), None)


def _used_sweep_dir_error(argv: list[str], parser) -> str | None:
    """The error line for a ``-m`` sweep into a fixed ``hydra.sweep.dir`` that holds another
    sweep (its ``multirun.yaml`` or job folders), with or without ``overwrite=true``: a sweep
    folder is one sweep's.  A second sweep into it replaced ``multirun.yaml`` and its report
    counted the first sweep's jobs as its own (probe of issue 12)."""
    subdir = _fixed_folder(argv, "hydra.sweep.subdir", parser)
    same = subdir is not None and (sweep_size(_plain_overrides(argv)) or 2) > 1
    sub = _given(argv, "hydra.sweep.subdir")
    if sub is not None and (sub.startswith(("/", "~")) or ".." in Path(sub.replace("${", "").replace("}", "")).parts):
        # the jobs ran outside the sweep folder, and the sweep's report counted them as not
        # started (probe of issue 12, round 9); both reasons at once when both hold (``../out`` named
        # only the shared folder, and its advice, ``../${hydra.job.num}``, was refused next; round 36)
        return (f"hairexp: error: hydra.sweep.subdir={sub}: a job's folder must lie inside the sweep folder "
                "(hydra.sweep.dir): a relative path without '..'; move the sweep with hydra.sweep.dir instead"
                + ("; and it must differ per job: include ${hydra.job.num} (the default) or "
                   "${hydra.job.override_dirname}" if same else ""))
    if same:
        # every job in one folder: the second was refused and the report named the wrong job (probe of issue 12)
        return (f"hairexp: error: hydra.sweep.subdir={subdir}: every job of the sweep would write into the same "
                "folder; a job's folder must differ per job: keep the default (${hydra.job.num}) or include "
                "${hydra.job.num} or ${hydra.job.override_dirname} in it")
    dup = _duplicate_sweep_value(argv, parser)   # the plainer case first: its message names the repeated value
    if dup is not None:
        return dup
    escape = _escaping_job_folder(argv, sub)
    if escape is not None:
        return escape
    folder = _fixed_folder(argv, "hydra.sweep.dir", parser)
    linked = None if folder is None else hydra_link_refusal(folder)
    if linked is not None:
        return f"hairexp: error: {folder}: {linked}"
    inside = None if folder is None else inside_run_error(folder, "hydra.sweep.dir")
    if inside is not None:
        return inside
    entries = [] if folder is None or not folder.is_dir() else [p for p in folder.iterdir() if p.name != LOCK]
    if entries:   # its .lock alone: a launch's, told by hold_folder_error
        shown = ", ".join(sorted(p.name for p in entries)[:6])
        return (f"hairexp: error: {folder}: the sweep folder is not empty ({shown}); a sweep folder belongs to one "
                "sweep: choose another hydra.sweep.dir (the default is a new dated folder) or remove this one")
    return None


_INTERPOLATION = re.compile(r"\$\{([^{}]*)\}")


def _escaping_job_folder(argv: list[str], sub: str | None) -> str | None:
    """The error line for a ``hydra.sweep.subdir`` template that, once a job's values are in it,
    puts the job's folder outside the sweep folder (``${hydra.job.override_dirname}`` with a value
    such as ``../../x``, ``${oc.env:X}`` set to one, ``${hydra:runtime.cwd}``, a config key whose
    value climbs out), or two jobs into one folder (``j${frames}`` with frames=3,03).  Such jobs ran
    outside the sweep folder, or into one another's, and the sweep's report called them not
    started (probes of issue 12, rounds 10 and 11).  Every job is tried when the sweep has at most
    SUBDIR_JOBS_CHECKED jobs, else every value of every swept key once (``_sweep_jobs``); an
    interpolation that cannot be resolved here is taken as one plain folder name."""
    if sub is not None and reserved_part(sub) is not None:
        return f"hairexp: error: hydra.sweep.subdir={sub}: cannot be a job folder: {reserved_part(sub)}"
    if sub is None or "${" not in sub:
        return None
    overrides = _plain_overrides(argv)
    jobs = _sweep_jobs(overrides, every=SUBDIR_JOBS_CHECKED) or _sweep_jobs(overrides) or [(overrides, [])]
    seen: dict[str, str] = {}
    for num, (job_overrides, swept) in enumerate(jobs):
        cfg = None

        def value(m):
            nonlocal cfg
            key = m.group(1).strip()
            if key == "hydra.job.override_dirname":
                return ",".join(sorted(job_overrides))
            if key in ("hydra.job.num", "hydra.job.id"):
                return str(num)
            if key.startswith("oc.env:"):
                name, _, default = key[len("oc.env:"):].partition(",")
                return os.environ.get(name.strip(), default.strip().strip("'\"") if default else "x")
            if key.replace(":", ".").startswith(("hydra.runtime.cwd", "hydra.runtime.output_dir")):
                return os.getcwd()   # absolute: outside the sweep folder
            if key.startswith("hydra") or ":" in key:
                return "x"
            if cfg is None:
                try:
                    cfg = compose_config(job_overrides)
                except Exception:  # noqa: BLE001  (config_error's to say)
                    cfg = False
            from omegaconf import OmegaConf

            try:
                v = OmegaConf.select(cfg, key, default=None) if cfg is not False else None
            except Exception:  # noqa: BLE001
                v = None
            return "x" if v is None else choice_name(v)

        path = _INTERPOLATION.sub(value, sub)
        norm = os.path.normpath(path)
        what = " ".join(swept) if swept else " ".join(job_overrides)
        if os.path.isabs(path) or norm == ".." or norm.startswith("../"):
            return (f"hairexp: error: hydra.sweep.subdir={sub}: the job [{what}] would write into {path}, outside "
                    "the sweep folder (hydra.sweep.dir): a value with '..' or a leading '/' climbs out through "
                    "the template; use the default subdir (${hydra.job.num}) or values without path parts")
        if reserved_part(norm) is not None:
            return (f"hairexp: error: hydra.sweep.subdir={sub}: the job [{what}] would write into {path}: "
                    f"{reserved_part(norm)}")
        if norm in seen and "hydra.job.num" not in sub:
            return (f"hairexp: error: hydra.sweep.subdir={sub}: the jobs [{seen[norm]}] and [{what}] would both write "
                    f"into {norm}; a job's folder must differ per job: include ${{hydra.job.num}} in the template")
        seen[norm] = what
    return None


#: a sweep of at most this many jobs has every job's subdir tried (``_escaping_job_folder``)
SUBDIR_JOBS_CHECKED = 64


def _duplicate_sweep_value(argv: list[str], parser) -> str | None:
    """The error line for a swept key given one value twice when ``hydra.sweep.subdir`` is a
    template without ``${hydra.job.num}`` (such as ``${hydra.job.override_dirname}``): the two
    jobs would share a folder.  The second was refused as a used folder, had no job line, and
    the sweep said "(1 not started)" and exited 1 (probe of issue 12).  With the default subdir
    (the job's number) a repeated value is two runs in two folders, which is allowed."""
    sub = _given(argv, "hydra.sweep.subdir")
    if sub is None or "hydra.job.num" in sub:
        return None
    for arg in argv:
        if arg.startswith("-") or _hydra_arg(arg) or "=" not in arg:
            continue
        try:
            o = parser.parse_override(arg)
            vals = list(o.sweep_string_iterator()) if o.is_sweep_override() else []
        except Exception:  # noqa: BLE001  (a syntax error or a sweep Hydra expands: Hydra's to handle)
            continue
        seen = set()
        for v in vals:
            if v in seen:
                return (f"hairexp: error: {arg}: the value {v} is swept twice, and with hydra.sweep.subdir={sub} "
                        "the two jobs would write into one folder; give each value once, or include "
                        "${hydra.job.num} in hydra.sweep.subdir")
            seen.add(v)
    return None


#: resolvers a run folder's path may use besides OmegaConf's registered ones (Hydra registers these
#: when it starts)
_HYDRA_RESOLVERS = ("now", "hydra", "python_version")
_RESOLVER = re.compile(r"\$\{([A-Za-z_][\w.]*):")


def run_dir_value_error(argv: list[str]) -> str | None:
    """The error line for a command line's ``hydra.run.dir`` / ``hydra.sweep.dir`` whose
    interpolation cannot be resolved, or None: ``${oc.env:NAME}`` with NAME unset and no default,
    or a resolver that does not exist (``${foo:bar}``).  Hydra would resolve it after it started
    and fail with its traceback (probe of issue 12); this is a bad value (exit 2)."""
    from omegaconf import OmegaConf

    for arg in argv:
        key, eq, value = arg.lstrip("+~").partition("=")
        if not eq or key not in ("hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir"):   # subdir: round 15
            continue
        for m in _ENV_INTERPOLATION.finditer(value):
            if m.group(2) is None and m.group(1) not in os.environ:
                return (f"hairexp: error: {key}={value}: the environment variable {m.group(1)} is not set (set it, "
                        f"or give a default: ${{oc.env:{m.group(1)},/some/folder}})")
        for name in _RESOLVER.findall(value):
            if name not in _HYDRA_RESOLVERS and not OmegaConf.has_resolver(name):
                return (f"hairexp: error: {key}={value}: unknown resolver '{name}' in the folder's path (it may use "
                        "${now:...}, ${oc.env:NAME} and the config's keys)")
        refs = [r for r in _NODE_REF.findall(value) if not r.startswith("hydra.")]
        if refs:
            try:   # a config that cannot be composed is config_error's to report
                from hydra.core.override_parser.overrides_parser import OverridesParser

                parser = OverridesParser.create()
                single = [a for a in _plain_overrides(argv) if not parser.parse_override(a).is_sweep_override()]
                cfg = compose_config(single)
            except Exception:  # noqa: BLE001
                return None
            for r in refs:
                if OmegaConf.select(cfg, r, default=_NO_KEY) is _NO_KEY:
                    return (f"hairexp: error: {key}={value}: the folder's path refers to ${{{r}}}, which is not a "
                            "key of the config")
    return None


#: ``${key.path}`` (a node of the config) in a folder's path
_NODE_REF = re.compile(r"\$\{([A-Za-z_][\w.]*)\}")
_NO_KEY = object()


def run_dir_error(argv: list[str]) -> str | None:
    """The error line for a run folder that cannot be written, or None: the command line's
    ``hydra.run.dir`` (with ``-m``: ``hydra.sweep.dir``), or when none is given the default of
    conf/config.yaml (``outputs/...``, ``multirun/...`` under the working folder).  Checked
    before Hydra starts, since Hydra creates the folder before the job runs (and would fail with
    its traceback, exit 1).  A value with an interpolation (``${now:...}``) is checked up to its
    last ``/`` before the interpolation; a sweep over several folders is left to Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    key = "hydra.sweep.dir" if _multirun(argv) else "hydra.run.dir"
    parser = OverridesParser.create()
    given = False
    for arg in argv:
        if not arg.lstrip("+~").startswith(key + "="):
            continue
        given = True
        try:
            o = parser.parse_override(arg)
        except Exception:  # noqa: BLE001  (a syntax error: Hydra's own message)
            return None
        if o.is_sweep_override() or o.key_or_group != key or o.value() is None:
            continue
        value = str(o.value())
        if "${" in value and ".." in Path(value[value.index("${"):]).parts:
            # mkdir made the interpolated folder on the way and left it empty (probe of issue 12, round 12)
            return (f"hairexp: error: {key}={value}: a '..' after an interpolation makes the interpolated folder "
                    "on the way and leaves it empty; write the path without '..'")
        missing = _made_on_the_way(value if "${" not in value else value[:value.index("${")])
        if missing is not None:   # 'b//../../z': b made and left empty (probe of issue 12, round 14)
            return (f"hairexp: error: {key}={value}: the '..' after {missing}, a folder that does not exist, would make "
                    f"{missing} on the way and leave it empty; write the path without '..' "
                    f"({os.path.normpath(value) if '${' not in value else 'normalised'})")
        path = _static_part(value)
        why = None if path is None else unusable_folder(path)
        if why is not None:
            return f"hairexp: error: {key}={o.value()}: cannot be the run folder: {why}"

    if not given and not any(a.startswith(("--help", "-h", "--cfg", "-c", "--info", "--hydra-help", "--version"))
                             for a in argv):
        default = _default_dir(key)
        path = None if default is None else _static_part(default)
        why = None if path is None else unusable_folder(path)
        if why is not None:
            return (f"hairexp: error: the default run folder {path.rstrip('/')}/... ({key}, under the working folder "
                    f"{os.getcwd()}) cannot be the run folder: {why}; run from a writable folder or set {key}")
    return None


#: s, how long the main process of a sweep waits for its jobs to end after SIGTERM / SIGINT
STOP_WAIT_SECONDS = 30.0
#: s, after SIGINT: how long the jobs get to react to a Ctrl-C of their own before it is forwarded
SIGINT_GRACE_SECONDS = 2.0


def _running_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders of a sweep whose outcome still says ``running``."""
    running = []
    try:
        dirs = _job_folders(Path(sweep_dir))
    except OSError:
        return []
    for d in dirs:
        try:
            if json.loads((d / OUTCOME).read_text()).get("status") == "running":
                running.append(d)
        except (OSError, ValueError, AttributeError):
            continue
    return running


def _wait_jobs(sweep_dir: Path, seconds: float) -> list[Path]:
    """Wait up to ``seconds`` until no job of the sweep is running; the jobs still running."""
    deadline = time.monotonic() + seconds
    while True:
        running = _running_jobs(sweep_dir)
        if not running or time.monotonic() >= deadline:
            return running
        time.sleep(0.1)


def stop_sweep_jobs(signum: int) -> None:
    """On SIGTERM / SIGINT in the main process of a sweep: the jobs that are running are told
    (SIGTERM is forwarded to the worker processes; SIGINT only if the jobs did not react to a
    Ctrl-C of their own within SIGINT_GRACE_SECONDS) and waited for up to STOP_WAIT_SECONDS, so
    that each writes its own ``interrupted`` ending before the launcher tears the workers down.
    A job a worker starts meanwhile sees ``STOP_MARK`` and ends as interrupted without running;
    the mark is written even while no job says "running" yet (under load, a job still starting up
    began after the signal and ran to its end; independent probe of issue 12, round 30).  Nothing
    happens outside a sweep; nothing more when no job is running."""
    sweep_dir = SWEEP_DIR
    if sweep_dir is None:
        return
    name = signal.Signals(signum).name
    try:   # jobs the launcher starts from now on end at once (cli.job); removed on exit (clear_stop_mark)
        (sweep_dir / STOP_MARK).write_text(name + "\n")
    except OSError:
        pass
    if not _running_jobs(sweep_dir):
        return
    if signum == signal.SIGINT:
        if not _wait_jobs(sweep_dir, SIGINT_GRACE_SECONDS):
            return
    sent = forward(signum, worker_pids())
    print(f"hairexp: {name}: waiting up to {STOP_WAIT_SECONDS:g} s for the sweep's running jobs to end "
          f"({len(sent)} child processes signalled)", file=sys.stderr)
    left = _wait_jobs(sweep_dir, STOP_WAIT_SECONDS)
    if left:
        print(f"hairexp: {name}: {len(left)} jobs did not end in {STOP_WAIT_SECONDS:g} s: "
              f"{', '.join(d.name for d in sorted(left))}", file=sys.stderr)


def _hydra_arg(a: str) -> bool:
    return a.lstrip("+~").startswith(("hydra.", "hydra/"))   # ++hydra.* too (round 32)


def _plain_overrides(argv: list[str]) -> list[str]:
    """The command line's config overrides: neither a flag, a flag's value, nor one of Hydra's own keys."""
    return [a for i, a in enumerate(argv) if not (a.startswith("-") or _is_value(argv, i) or _hydra_arg(a))]


def _record_in_variant_error(argv: list[str], overrides: list[str]) -> str | None:
    """Why ``hydra.output_subdir`` cannot be the name it gives: an experiment's variant folder (Hydra's
    record went into ``free/``, and the variant's run refused its folder as used; round 24), or None."""
    given = [a.split("=", 1)[1] for a in argv if a.startswith("hydra.output_subdir=")]
    if not given or given[-1] in ("null", ""):
        return None
    try:
        variants = compose_config(overrides).get("variants") or []
        names = {str(v.name) for v in variants}
    except Exception:  # noqa: BLE001  (compose_error's)
        return None
    first = given[-1].replace("\\", "/").split("/")[0]
    if first in names:
        return (f"hydra.output_subdir={given[-1]}: Hydra's record would go into the folder of the variant {first}; "
                "give another name (the variants are " + ", ".join(sorted(names)) + ")")
    return None


def _variant_overrides_error(overrides: list[str]) -> str | None:
    """Why a variant's own overrides cannot be applied (an unknown key, a wrong type), or None:
    ``--cfg job`` checks them as a run does before it claims its folder (it printed the config of
    a variant with ``foo=1`` or ``solver.dt=abc``, exit 0; independent probe of issue 12, round 28)."""
    try:
        cfg = compose_config(overrides)
        runs = [apply_overrides(cfg, list(v.overrides), f"variants[{i}] ({v.name})")
                for i, v in enumerate(cfg.get("variants") or [])]
        # and their values' ranges, as a run checks them first (``solver.dt=-1`` was printed, exit 0;
        # independent probe of issue 12, round 35), and what the run checks before it starts that reads
        # no file (the step schedule, the sizes, a procedural scene as built, the variants' names;
        # ``fps=0`` and two variants of one name were printed, exit 0; independent probe, 2026-12-07)
        check_variant_names(cfg.get("variants") or [])
        for run in runs or [cfg]:
            check_config(run, files=False)
    except InputError as exc:
        return str(exc)
    except Exception:  # noqa: BLE001  (compose_error's)
        return None
    return None


def compose_error(overrides: list[str], input_errors: bool = True) -> str | None:
    """The message (without the ``hairexp: error:`` prefix) of ``overrides`` whose config cannot
    be composed, or None; ``input_errors=False``: hairexp's own checks (``InputError``: a ``+key``
    not in the schema, a boolean given ``2``) are left to the jobs."""
    try:
        compose_config(overrides)
    except InputError as exc:   # a key not in the schema (or in a record of a value) is a composition
        composing = ("unknown key" in str(exc) or "Error merging override" in str(exc.__cause__ or "")
                     or "of the config group" in str(exc))
        return str(exc) if input_errors or composing else None   # error, in a sweep's jobs too (a wrong type too)
    except Exception as exc:   # Hydra's composition and override-parsing errors, OmegaConf's validation
        return _list_key_error(overrides, exc) or one_line(exc)
    return None


def _list_key_error(overrides: list[str], exc: Exception) -> str | None:
    """A key into a list without an index (``guides.edits.kind=twist``: OmegaConf's "invalid literal
    for int() with base 10: 'kind'", naming no key; independent probe of issue 12, round 24), or None."""
    m = re.search(r"invalid literal for int\(\) with base 10: '([^']*)'", str(exc))
    if m is None:
        return None
    for o in overrides:
        key = _key_of(o)
        parts = key.split(".")
        if m.group(1) in parts[1:]:
            at = parts.index(m.group(1), 1)
            lst = ".".join(parts[:at])
            return (f"{key}: {lst} is a list: give an item's index ({lst}.0.{'.'.join(parts[at:])}=...) or the whole "
                    f"list ({lst}=[...])")
    return None


def one_line(exc: BaseException) -> str:
    """A Hydra or OmegaConf error as one line: its message and its cause's first line ("Error
    merging override x=y" says why only there), without Hydra's list of its search path."""
    msg = " ".join(str(exc).split())
    cause = exc.__cause__ or exc.__context__
    said = " ".join(str(cause).strip().splitlines()[0].split()) if cause is not None and str(cause).strip() else ""
    if said and said not in msg:
        msg += ": " + said
    # OmegaConf's tail (a user's config file with a wrong key or value: --config-dir): the key, not the types
    msg = re.sub(r"\s*full_key: (\S+)\s+(?:reference_type=\S+\s+)?object_type=\S+", r" (key \1)",
                 msg.split(" Config search path:")[0])
    if "Cannot convert 'DictConfig' to string" in msg and "(key experiment)" in msg:
        # a user's experiment file without its package line: its keys landed under "experiment" (round 25)
        msg += (" (an experiment file sets the config's own keys: it begins with the line '# @package _global_', "
                "as conf/experiment/*.yaml do)")
    typo = re.search(r"Key '[^']+' not in '[^']+' \(key ([\w.\[\]]+)\)", msg)
    if typo:   # a typo in a user's own config file got no hint where the command line's gets one (round 30)
        hint = unknown_key_hint(typo.group(1))
        msg += f"; {hint}" if hint else ""
    return msg


def _sweep_jobs(overrides: list[str], every: int | None = None) -> list[tuple[list[str], list[str]]] | None:
    """For a ``-m`` command line: (the overrides of a job, its swept ``key=value``s) for the first
    job and, for each swept key, one job per other value (the other keys at their first value):
    every value of every sweep is composed once, in 1 + sum(values - 1) jobs.  None when a sweep
    cannot be listed here (``glob``, an interval): then Hydra composes it.  ``every``: all the
    sweep's jobs (the product of the swept values) instead, or None when there are more than that."""
    import itertools

    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
        values = [list(o.sweep_string_iterator()) if o.is_sweep_override() else None for o in parsed]
    except Exception:  # noqa: BLE001
        return None

    def job(choice: dict) -> tuple[list[str], list[str]]:
        args, swept = [], []
        for arg, o, vals in zip(overrides, parsed, values):
            if vals is None:
                args.append(arg)
                continue
            kv = f"{o.get_key_element()}={vals[choice.get(id(o), 0)]}"
            args.append(kv)
            swept.append(kv)
        return args, swept

    if every is not None:
        swept = [(o, vals) for o, vals in zip(parsed, values) if vals]
        if math.prod(len(vals) for _, vals in swept) > every:
            return None
        return [job({id(o): i for (o, _), i in zip(swept, combo)})
                for combo in itertools.product(*[range(len(vals)) for _, vals in swept])]
    jobs = [job({})]
    for o, vals in zip(parsed, values):
        for i in range(1, len(vals or [])):
            jobs.append(job({id(o): i}))
    return jobs


def _hydra_value_error(key: str, value) -> str | None:
    """Why a value of one of Hydra's own keys that its schema lets through cannot be used, or None:
    ``hydra.job.name`` and ``hydra.output_subdir`` that write outside the run folder (the job's log
    file is ``<run dir>/<job.name>.log``, Hydra's record ``<run dir>/<output_subdir>``;
    ``hydra.job.name=../../victim`` appended the run's log lines to a file two folders up), and
    ``hydra.launcher.n_jobs=0`` (joblib's ValueError traceback, a multirun.yaml left behind that
    refused the next launch; independent probe of issue 12, round 21)."""
    if key == "hydra.launcher.timeout" and isinstance(value, (int, float)) and not isinstance(value, bool) and \
            not value > 0:   # every job was stopped before it began, exit 3 (independent probe, round 26)
        return f"{key}={value}: the most seconds a job may run is a number > 0, or null for no limit"
    if key.lstrip("+~") == "hydra.sweeper.params" or key.lstrip("+~").startswith("hydra.sweeper.params."):
        # Hydra 1.3 cannot merge it from the command line: "'NoneType' object has no attribute 'get'",
        # "Unexpected type: None" (independent probe of issue 12, round 26)
        return (f"{key.lstrip('+~')}: Hydra takes the sweeper's params from a config file only (hydra: sweeper: "
                "params: in your own config, --config-dir / --config-name); on the command line sweep a key as "
                "key=a,b,c")
    if key == "hydra.launcher.n_jobs" and value == 0 and not isinstance(value, bool):
        return (f"{key}=0: the number of jobs run at once is a positive count (or -1 for one per core; joblib's "
                "-n is cores + 1 - n)")
    if key == "hydra.launcher.batch_size" and not (value == "auto" or (isinstance(value, int) and not
                                                                        isinstance(value, bool) and value > 0)):
        return f"{key}={value}: joblib's batch size is a positive count or auto"
    if key == "hydra.launcher.pre_dispatch" and isinstance(value, int) and not isinstance(value, bool) and value <= 0:
        # nothing ran and the sweep said "0 of 2 jobs completed (2 not started)", exit 1 (round 24)
        return f"{key}={value}: joblib's pre-dispatch is a positive count of jobs, or an expression such as 2*n_jobs"
    # Hydra's joblib launcher runs its jobs with loky processes whatever these say (its _core.py sets
    # backend=loky): another value was taken silently, recorded in multirun.yaml but not used, and
    # require=sharedmem failed after the sweep folder was made (independent probe, rounds 24 and 25)
    if (key == "hydra.launcher.backend" and value not in (None, "loky")) or (
            key == "hydra.launcher.prefer" and value not in (None, "processes")) or (
            key == "hydra.launcher.require" and value is not None):
        return (f"{key}={value}: Hydra's joblib launcher runs the jobs in loky worker processes whatever this says "
                "(backend loky, prefer processes, require null); leave it out")
    if key == "hydra.launcher.mmap_mode" and value not in JOBLIB_MMAP_MODES:
        return f"{key}={value}: joblib's mmap_mode is one of r, r+, w+, c or null"
    if not isinstance(value, str):
        return None
    parts = value.replace("\\", "/").split("/")
    if key == "hydra.job.name" and (len(parts) > 1 or value in ("", ".", "..") or len(value.encode()) > NAME_BYTES):
        return (f"{key}={value[:60]}{'...' if len(value) > 60 else ''}: the job's name is its log file's name in the "
                f"run folder (<name>.log); give a name without '/' or '..', of at most {NAME_BYTES} bytes")
    if key == "hydra.output_subdir" and (value.startswith("/") or ".." in parts or value in ("", ".")
                                         or parts[0] in RUN_FILES | RUN_DIRS | {LOCK}
                                         or any(len(q.encode()) > NAME_BYTES for q in parts)):
        return (f"{key}={value[:60]}{'...' if len(value) > 60 else ''}: Hydra's record of the run (.hydra) goes in a "
                "folder of its own inside the run folder; give a relative name without '..' that is not one of the "
                "run's files (or null for none)")
    return None


#: joblib's memory-map modes (hydra.launcher.mmap_mode)
JOBLIB_MMAP_MODES = (None, "r", "r+", "w+", "c")

#: bytes of a file name hairexp gives Hydra (NAME_MAX 255, less ".log" and room for Hydra's suffixes)
NAME_BYTES = 200


#: Hydra's own keys whose value is a folder given as text (``RunDir.dir``, ``SweepDir.dir``/``subdir``):
#: Hydra's config takes any text there
TEXT_FOLDER_KEYS = frozenset({"hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir"})


def hydra_key_error(hydra_args: list[str]) -> str | None:
    """The message of ``hydra.*`` overrides Hydra's own config refuses (a typo such as
    ``hydra.foo=1``, ``hydra.job.chdir=maybe``), or None: composed here with Hydra's config, so
    that the error is one line and exit 2 (Hydra: its multi-line message, exit 1; probe of
    issue 12).  Swept values and unparsable overrides are left to the other checks."""
    if not hydra_args:
        return None
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(hydra_args)
    except Exception:  # noqa: BLE001  (override_syntax_error's)
        return None
    plain = [a for a, o in zip(hydra_args, parsed) if not o.is_sweep_override()]
    if not plain:
        return None
    for o in parsed:
        bad = _hydra_value_error(o.get_key_element(), o.value()) if not o.is_sweep_override() else None
        if bad is not None:
            return bad
    if all(not o.is_sweep_override() and not (o.is_add() or o.is_force_add() or o.is_delete())
           and o.get_key_element() in TEXT_FOLDER_KEYS and isinstance(o.value(), str) for o in parsed):
        # the folders alone (the benchmarks' and many a command line's ``hydra.run.dir=<path>``): text
        # keys of Hydra's schema that take any text, their values checked by run_dir_value_error and
        # run_dir_error; composing Hydra's config to find nothing took 0.2-0.3 s of every such launch
        return None

    def composed(overrides):
        GlobalHydra.instance().clear()
        try:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                return compose(config_name="config", overrides=overrides, return_hydra_config=True)
        finally:
            GlobalHydra.instance().clear()

    try:
        composed(plain)
    except Exception as exc:  # noqa: BLE001  (Hydra's composition / validation error of its own keys)
        # a typo (hydra.foo=1, hydra.run.dri=x): Hydra said "To append to your config use +hydra.foo=1",
        # which then ran without a word (independent probe of issue 12, round 32)
        typo = re.match(r"Could not override '(hydra\.[\w.]+)'", str(exc))
        if typo:
            said = _unknown_hydra_key(typo.group(1), [a for a in plain if _key_of(a) != typo.group(1)], composed)
            if said is not None:
                return said
        return one_line(exc)
    # +hydra.<key> of a node of Hydra's schema that has no such key: Hydra adds it, and nothing reads it
    added = [a for a, o in zip(hydra_args, parsed) if not o.is_sweep_override() and (o.is_add() or o.is_force_add())]
    for a in added:
        said = _unknown_hydra_key(_key_of(a), [p for p in plain if p not in added], composed, added=True)
        if said is not None:
            return said
    return None


def _key_of(override: str) -> str:
    """The key an override names (``+hydra.foo=1``: ``hydra.foo``)."""
    return override.split("=", 1)[0].lstrip("+~")


def _unknown_hydra_key(key: str, others: list[str], composed, added: bool = False) -> str | None:
    """The error line for ``key``, a ``hydra.*`` key that Hydra's config (composed with the
    overrides ``others`` by ``composed``) does not have under a node of its schema (a dataclass:
    not a free dict such as ``hydra.job.env_set``), with its node's keys and the nearest; None when
    the key is there, its node is a free dict, or the config cannot be composed."""
    import difflib

    from omegaconf import DictConfig, OmegaConf

    try:
        cfg = composed(others)
    except Exception:  # noqa: BLE001  (another error of the command line: Hydra's own line)
        return None
    parent_key, _, leaf = key.rpartition(".")
    parent = OmegaConf.select(cfg, parent_key, default=None)
    if not isinstance(parent, DictConfig) or OmegaConf.get_type(parent) is dict or leaf in parent:
        return None
    keys = sorted(str(k) for k in parent.keys())
    near = difflib.get_close_matches(leaf, keys, n=1, cutoff=0.6)
    hint = f"; did you mean {parent_key}.{near[0]}?" if near else ""
    how = " (+ adds a key that nothing reads)" if added else ""
    return (f"{key}: not a key of Hydra's config{how}: {parent_key} has {', '.join(keys)}{hint}")


def config_error(argv: list[str]) -> str | None:
    """The one-line error of a command line whose config cannot be composed (a key not in the
    schema, a wrong type, an unknown choice), or None.  The config is composed here first, as
    ``compose_config`` does, so that such input exits 2 like any bad value instead of Hydra's
    multi-line message and exit 1.  A ``-m`` sweep: every value of every swept key is composed
    (``_sweep_jobs``; Hydra would stop the sweep at its start), the error names the job's swept
    values; the values hairexp checks (ranges, booleans, ``+key``) are left to each job, so that
    the other jobs run.  Hydra's own flags and keys are left to Hydra, except for an override its
    grammar cannot parse or an empty run folder (``override_syntax_error``: every command line)."""
    bad = override_syntax_error(argv)
    if bad is not None:
        return bad
    multirun = any(a in ("-m", "--multirun") for a in argv)
    if any(a.startswith("-") and _flag(a) not in _COMPOSING_FLAGS and not _is_value(argv, i) for i, a in enumerate(argv)):
        return None
    hydra_msg = hydra_key_error([a for a in argv if _hydra_arg(a)])
    if hydra_msg is not None:
        return f"hairexp: error: {hydra_msg}"
    overrides = _plain_overrides(argv)
    if not multirun:
        msg = compose_error(overrides) or _record_in_variant_error(argv, overrides)
        if msg is None and any(_flag(a) in ("--cfg", "-c") for a in argv):
            msg = _variant_overrides_error(overrides)
        return None if msg is None else f"hairexp: error: {msg}"
    for job_overrides, swept in _sweep_jobs(overrides) or []:
        msg = compose_error(job_overrides, input_errors=False)
        if msg is not None:
            return f"hairexp: error: sweep job [{' '.join(swept)}]: {msg}" if swept else f"hairexp: error: {msg}"
    return None
