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
import multiprocessing
import os
import signal
import sys

try:   # before torch loads: in a deleted working folder it failed with "Intel oneMKL FATAL ERROR" (round 21)
    os.getcwd()
except FileNotFoundError:
    sys.stderr.write("hairexp: error: the working folder no longer exists (deleted while the shell was in it); cd to "
                     "a folder that exists and launch again\n")
    raise SystemExit(2) from None


def _address_space_error() -> str | None:
    """The error line when the process's address-space limit (``ulimit -v``) is below what a run
    reserves, or None.  A run reserves about 5.2-5.5 GB of virtual memory (VmPeak of goaling_smoke
    and celia_smoke; resident about 0.6 GB: the reservations of torch, numba's LLVM, USD and the
    threads' heaps and stacks).  Under 2-4.5 GB USD crashed with SIGSEGV while writing the result
    (exit 139, no word, summary.json left "running"); under 800 MB the import failed with a
    traceback (independent probe of issue 12, round 23)."""
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or soft >= MIN_ADDRESS_SPACE:
        return None
    return (f"hairexp: error: the process's address-space limit (ulimit -v) is {soft / 2**30:.2f} GiB; a run reserves "
            f"about 5.5 GiB of virtual memory (it uses about 0.6 GiB of it: torch's, LLVM's and USD's reservations "
            f"and the threads' heaps), and USD crashes when a reservation fails; raise it to at least "
            f"{MIN_ADDRESS_SPACE / 2**30:.0f} GiB (ulimit -v {MIN_ADDRESS_SPACE >> 10}) or lift it (ulimit -v unlimited)")


#: the smallest address-space limit (RLIMIT_AS) a run starts under (_address_space_error)
MIN_ADDRESS_SPACE = 6 << 30
#: the smallest open-file limit (RLIMIT_NOFILE) a run starts under: celia_smoke's experiment and a
#: two-job sweep ran under 64; under 16-20 a run failed on its stream's files, said as the run
#: folder's fault (exit 4; independent probe of issue 12, round 24)
MIN_OPEN_FILES = 64


def _open_files_error() -> str | None:
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= MIN_OPEN_FILES:
        return None
    return (f"hairexp: error: the process's open-file limit (ulimit -n) is {soft}; a run holds up to about 40 files "
            f"open (its libraries', its stream's and its logs'): raise it to at least {MIN_OPEN_FILES} "
            f"(ulimit -n {MIN_OPEN_FILES})")


if (_why := _address_space_error() or _open_files_error()) is not None:   # before torch, numba and USD load
    sys.stderr.write(_why + "\n")
    raise SystemExit(2)
import warnings
from concurrent.futures.process import BrokenProcessPool

import hydra
import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException, SearchPathException
from omegaconf import DictConfig
from omegaconf.errors import InterpolationResolutionError

import hairexp.app.config  # noqa: F401  (registers the schema in the ConfigStore)
from hairexp.app import cli
from hairexp.app.signals import InterruptSignals, exit_code, start_resource_tracker
from hairexp.app.streams import guard_streams, stdout_checked
from hairexp.app.startup import begun, ended, exit_now
from hairexp.errors import Interrupted
from hairexp.outputs.folder import unhold_unused


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    hc = HydraConfig.get()
    sweep = str(getattr(hc.mode, "name", hc.mode)) == "MULTIRUN"
    res = cli.job(cfg, hc.runtime.output_dir, sweep=sweep, sweep_dir=str(hc.sweep.dir) if sweep else None,
                  overrides=list(hc.overrides.task), cwd=str(hc.runtime.cwd))
    return res["code"]


def entry() -> int:
    logging.raiseExceptions = False   # a log file on a full disk is not worth a traceback per line
    # a sweep's interrupted or timed-out workers leave their semaphores to joblib's resource tracker,
    # which warned "resource_tracker: There appear to be N leaked semaphore objects" after the sweep's
    # closing line (it cleans them up all the same; round 24): its process takes the interpreter's -W
    # options from these
    sys.warnoptions.append("ignore:resource_tracker:UserWarning")
    warnings.formatwarning = cli.one_line_warning
    if "--version" in sys.argv[1:]:   # Hydra's said only "Hydra 1.3.8" (probe of issue 12, round 19)
        print(f"hairexp {cli.version()} (Hydra {hydra.__version__})")   # a lost stdout: _main says it, exit 4
        return 0
    bad_flag = (cli.flag_error(sys.argv[1:]) or cli.mode_error(sys.argv[1:])   # before any folder is made
                or cli.duplicate_key_error(sys.argv[1:]) or cli.config_source_error(sys.argv[1:]))
    if bad_flag is not None:
        print(bad_flag, file=sys.stderr)
        return 2
    shadowed = cli.shadowed_config_warning(sys.argv[1:])
    if shadowed is not None:
        print(shadowed, file=sys.stderr)
    sys.argv[1:] = cli.flags_first(sys.argv[1:])   # argparse takes no flag after the overrides
    script, bad_completion = cli.shell_completion(sys.argv[1:])   # python -m hairexp's own (Hydra's: python x.py)
    if bad_completion is not None:
        print(bad_completion, file=sys.stderr)
        return 2
    if script is not None:
        print(script)
        return 0
    sys.argv[1:], unread = cli.hydra_help_argv(sys.argv[1:])
    if unread:
        print(f"hairexp: warning: {' '.join(unread)} not used: --hydra-help prints Hydra's own help, which reads "
              "no override but hydra.*", file=sys.stderr)
    other_mode = cli.unused_folder_key(sys.argv[1:])
    if other_mode is not None:
        print(other_mode, file=sys.stderr)
    bad_value = cli.run_dir_value_error(sys.argv[1:])   # an interpolation Hydra could not resolve
    if bad_value is not None:
        print(bad_value, file=sys.stderr)
        return 2
    bad_dir = cli.run_dir_error(sys.argv[1:]) or cli.file_size_limit_error(sys.argv[1:])   # before Hydra writes
    if bad_dir is not None:   # (its traceback, exit 1)
        print(bad_dir, file=sys.stderr)
        return 4
    bad_config = cli.config_error(sys.argv[1:])   # a typo, a wrong type, an unknown choice: bad input
    if bad_config is not None:
        print(bad_config, file=sys.stderr)
        return 2
    # a launch into (or inside) the folder of one that has not ended first: that is the reason to
    # name, not the folder's files (probe of issue 12, round 12); then another run's folder, before
    # Hydra writes .hydra/ into it; then the launch lock (two launches that both found it empty)
    # (none of this when Hydra only prints: --cfg, --info, --help run nothing and make no folder)
    argv = sys.argv[1:]
    used = None if cli.prints_only(argv) else (
        cli.live_folder_error(argv) or cli.used_dir_error(argv) or cli.hold_folder_error(argv))
    if used is not None:
        print(used, file=sys.stderr)
        return 2
    # Hydra lets its exceptions through instead of printing them and exiting 1 itself: a config it
    # cannot compose is said below in one line (exit 2), and so is a sweep worker that was killed
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    if any(a in ("-m", "--multirun") for a in argv):   # a sweep: its launcher's helper must outlive a hangup
        start_resource_tracker()
    begun()   # from here a signal is the run's (its handlers), then one while the command ends
    try:
        # outside a run (composing, between sweep jobs) too; a sweep's running jobs are stopped first
        with InterruptSignals(on_signal=cli.stop_sweep_jobs) as signals:
            main()
            if signals.lost() is not None and cli.SWEEP_DIR is not None:   # a sweep's main process runs no job
                raise Interrupted(signals.lost())
    except BrokenProcessPool as exc:
        # a sweep worker killed (SIGKILL, the out-of-memory killer): joblib's traceback, exit 1, and its
        # job's summary left "running" (probe of issue 12, round 12); its job is ended as failed below
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        print(f"hairexp: a sweep worker process ended abruptly (killed: out of memory, or a SIGKILL); the jobs it "
              f"ran are failed ({type(exc).__name__}: {first})", file=sys.stderr)
        code = cli.exit_code()
        return code if code else 3   # as a killed job's (cli._end_killed_jobs)
    except multiprocessing.TimeoutError:
        # hydra.launcher.timeout: joblib gave up waiting and ended its workers (a traceback, exit 1, no job
        # lines; independent probe of issue 12, round 23); the jobs it ended are failed below
        limit = next((a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("hydra.launcher.timeout=")), "?")
        print(f"hairexp: the sweep was stopped: a job ran longer than hydra.launcher.timeout={limit} s", file=sys.stderr)
        # joblib has ended its workers (loky's abort): the jobs that were running are ended here as failed,
        # those not begun said as not started (their summaries said "running", or there were none)
        code = cli.exit_code(workers_gone=True)
        return code if code not in (0, 1) else 3   # a job's own bad ending, or 3: the sweep could not finish
    except (ConfigCompositionException, MissingConfigException, SearchPathException, OverrideParseException,
            yaml.YAMLError) as exc:
        # what Hydra could not compose and hairexp's checks did not foresee: in a -m sweep (Hydra lets
        # its exceptions through, above) a traceback, exit 1 (probe of issue 12, round 19); a user's
        # own config file (--config-dir) that is not YAML, or whose key or value the schema refuses:
        # a traceback, or only Hydra's first line "ConfigKeyError raised while composing config:" (the
        # reason is its cause's; independent probe of issue 12, round 22)
        first = (f"{' '.join(str(exc).split())}" if isinstance(exc, yaml.YAMLError) else cli.one_line(exc)) \
            or type(exc).__name__
        if isinstance(exc, yaml.YAMLError):
            first = f"a config file is not valid YAML: {first}"
        names = cli.flag_values(sys.argv[1:], "--config-name", "-cn")
        where = f"--config-name={names[-1]}: " if names else ""
        print(f"hairexp: error: {where}{first}", file=sys.stderr)
        unhold_unused()   # the run folder Hydra never wrote: not left holding only .lock
        return 2
    except InterpolationResolutionError as exc:
        # a run folder's interpolation that fails as Hydra makes the folder: the default folder's
        # experiment name that is no folder's name (a user's experiment file; a traceback; round 27)
        print(f"hairexp: error: {cli.one_line(exc)}", file=sys.stderr)
        unhold_unused()
        return 2
    except OSError as exc:
        # outside a run (a run's own write errors end it, hairexp/app/cli.py; the standard streams keep
        # theirs, hairexp/app/streams.py): Hydra's own files, such as .hydra/config.yaml on a full disk
        print(f"hairexp: error: cannot write {exc.filename or 'a file of Hydra'}: {exc}", file=sys.stderr)
        unhold_unused()
        return 4
    except Exception as exc:  # noqa: BLE001  (re-raised unless Hydra's own)
        if not _raised_by_hydra(exc):
            raise
        # Hydra's own flags given a value it refuses (--experimental-rerun of a missing file or of
        # one that is not a pickle, --shell-completion without install/uninstall/query or without
        # COMP_LINE): a traceback, exit 1 (independent probes, rounds 21 and 24).  A job's own errors
        # never get here (cli.job ends them)
        flags = [a.split("=")[0] for a in sys.argv[1:] if a.startswith("--")]
        why = (cli.one_line(exc) if isinstance(exc, ValueError)
               else f"{type(exc).__name__} {' '.join(str(exc).split())} (in Hydra's own code)")
        if isinstance(exc, KeyError) and str(exc).strip("'") in ("COMP_LINE", "COMP_POINT"):
            why = f"{str(exc)} is not set: the shell sets it when it asks for completions (install=bash sets that up)"
        elif isinstance(exc, RecursionError):   # a user's config whose defaults list includes itself (round 25)
            why = "the defaults lists of the configs include one another in a loop (a file among its own defaults?)"
        elif isinstance(exc, UnicodeDecodeError):   # a user's config file of binary bytes: name it (round 25)
            bad = cli.undecodable_config(sys.argv[1:])
            why = f"{bad}: not UTF-8 text (a config file is YAML)" if bad else why
        print(f"hairexp: error: {', '.join(flags) + ': ' if flags else ''}{why}", file=sys.stderr)
        unhold_unused()
        return 2
    except KeyboardInterrupt as exc:
        code = exit_code(exc.signum) if isinstance(exc, Interrupted) else 130
        if cli.sweep_completed():
            # the signal came as the last jobs ended: their lines said "2 of 2 jobs completed" on stdout
            # and this one "interrupted" on stderr (independent probe of issue 12, round 34); exit 128 + n
            # as a single run that had completed before its signal (cli._signalled_after)
            name = signal.Signals(exc.signum if isinstance(exc, Interrupted) else signal.SIGINT).name
            cli.clear_stop_mark()
            cli.exit_code()
            # worded for either order: the signal may have come before the jobs' last steps, which then
            # completed (it said "after every job had completed"; independent probe, round 35)
            print(f"hairexp: {name}: every job of the sweep completed before it could be stopped; nothing was "
                  f"interrupted, their results are whole", file=sys.stderr)
            return code
        # outside a run (a run prints its own line): while the config was composed, or between sweep jobs
        what = str(exc) if isinstance(exc, Interrupted) and str(exc) else "interrupted by SIGINT"
        where = _say_in_run_folder(what)
        if where is None and cli.SWEEP_DIR is None and cli.LAST is None and unhold_unused():
            # while Hydra started, before it wrote anything: a bare "interrupted by SIGTERM", and the run
            # folder left holding only the launch's .lock (independent probe of issue 12, round 35)
            where = "while starting; nothing was run or written"
        print(f"hairexp: {what}{f' ({where})' if where else ''}", file=sys.stderr)
        cli.clear_stop_mark()   # the launcher has torn its workers down
        cli.exit_code(exc.signum if isinstance(exc, Interrupted) else 2)   # a sweep's jobs so far
        return code
    return cli.exit_code()


def _say_in_run_folder(what: str) -> str | None:
    """A signal outside the job (in Hydra's code, after it wrote ``.hydra/`` into the run folder and
    before the job began): the folder says how the launch ended, as for a run refused before it
    claimed its folder (it held only Hydra's files, no summary.json; independent probe of issue 12,
    round 22).  A folder with a summary (the job's own ending) is left as it is.  Returns what the
    folder holds now, for the interruption's line (it said a bare "interrupted by SIGTERM" in this
    window, where the other windows say what was kept; round 26), or None outside a run folder."""
    if any(a in ("-m", "--multirun") for a in sys.argv[1:]):   # a sweep's jobs say their own
        return None
    # Hydra has reset its HydraConfig by now; the job's log file (Hydra's, <run folder>/<job name>.log,
    # made before its record) names the folder
    logs = [h.baseFilename for h in logging.getLogger().handlers if isinstance(h, logging.FileHandler)]
    out = os.path.dirname(logs[0]) if len(logs) == 1 else None
    if out:
        cli.restore_previous_record(out)
        cli.write_refused(None, out, what, "interrupted", "interrupted while Hydra started the run, before the run "
                          "claimed its folder: no step ran")
        return f"while starting: {cli.kept(out, 'partial results')}"
    return None


def _raised_by_hydra(exc: BaseException) -> bool:
    """Whether ``exc`` was raised under Hydra's or joblib's own code and not under hairexp's (the
    frames below ``entry``: a KeyError of ``os.environ`` that Hydra's shell completion asked for
    has its innermost frame in ``os``)."""
    tb, ours, theirs = exc.__traceback__, False, False
    here = os.path.dirname(os.path.abspath(__file__)).replace(os.sep, "/") + "/"
    while tb is not None:
        path = tb.tb_frame.f_code.co_filename.replace(os.sep, "/")
        if path.startswith(here) and not path.endswith("/__main__.py"):
            ours = True
        elif "/hydra/" in path or "/joblib/" in path:
            theirs = True
        tb = tb.tb_next
    return theirs and not ours


def _main() -> None:
    guard_streams()
    try:
        code = entry()
    except SystemExit as exc:   # Hydra's --help / --hydra-help end with sys.exit(0) after printing
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    code = stdout_checked(code, "hairexp")
    ended(code)   # a signal while the process exits keeps this code (hairexp/app/startup.py)
    exit_now(code)


if __name__ == "__main__":
    _main()
