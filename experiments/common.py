"""What the scripts under experiments/ share: composing a config, the one timing loop of the
benchmarks, number formatting and markdown tables.

The scripts are modules of this package, run from the repository root as
``python -m experiments.<name>``; every run they make is assembled by
``hairexp.app.assemble.assemble`` (or run whole by ``hairexp.app.run.run`` /
``hairexp.app.experiment.run_experiment``), as ``python -m hairexp`` assembles it.
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

#: the repository root (conf/, reports/, outputs/)
ROOT = Path(__file__).resolve().parent.parent

#: the parts of a step's time (``StepInfo.seconds``, hairexp/physics/simulator.py) besides the total
TIME_KEYS = ("derivatives", "assembly", "solve", "collision", "other")


# -- command-line arguments --------------------------------------------------------------------
def _number(kind, low: float, inclusive: bool, what: str):
    """An argparse ``type``: ``kind`` (int or float), finite, above ``low`` (or at it when
    ``inclusive``); anything else is a usage error naming the value (exit 2)."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not math.isfinite(v) or v < low or (v == low and not inclusive):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return v

    parse.__name__ = what   # argparse names the type in its messages
    return parse


positive_int = _number(int, 1, True, "a positive integer")
nonnegative_int = _number(int, 0, True, "an integer >= 0")
positive_float = _number(float, 0.0, False, "a positive number")

#: the most strands (and vertices of one strand) a script's size argument takes: far above what fits
#: (reports/bench_scale.md: 10,000 strands x 26 vertices peak at about 3 GB), refused before anything runs
MAX_STRANDS = 1_000_000
MAX_STRAND_VERTICES = 10_000


def _bounded_int(low: int, high: int, what: str, too_many: str):
    """An argparse ``type``: an integer in [low, high]: below ``low`` or not an integer is ``what``'s
    usage error, above ``high`` says ``too_many`` (exit 2)."""
    base = _number(int, low, True, what)

    def parse(text: str) -> int:
        v = base(text)
        if v > high:
            raise argparse.ArgumentTypeError(f"{text!r} is more than {high:,} {too_many}")
        return v

    parse.__name__ = what
    return parse


strand_count = _bounded_int(1, MAX_STRANDS, "a positive integer",
                            "strands: a run that large cannot fit in memory (6 kB a vertex, hairexp/app/guard.py)")
strand_vertices = _bounded_int(3, MAX_STRAND_VERTICES, "an integer >= 3 (a strand's vertices: two clamped, one free)",
                               "vertices in a strand: its edges would be shorter than 0.1 mm on any hair up to "
                               "1 m long, too short for a step to converge (hairexp/model/builders.py MIN_REST_EDGE)")


# -- output paths: checked before a script runs anything (a bad one failed only at the end) ------
def _probe(folder: Path) -> str | None:
    """None when a file can be created (and removed) in the existing ``folder``, else why not.  Not
    ``os.access`` alone: root may "write" anywhere by the permission bits, yet /proc, /sys or a
    read-only mount refuse a new file."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"{folder} is not writable (permission denied)"
    try:
        fd, name = tempfile.mkstemp(prefix=".write_probe_", dir=folder)
    except OSError as exc:
        why = "no files can be created there" if exc.errno == errno.ENOENT else (exc.strerror or str(exc)).lower()
        return f"{folder} is not writable ({why})"
    os.close(fd)
    try:
        os.unlink(name)
    except OSError:
        pass
    return None


def folder_problem(folder, probe: bool = True) -> str | None:
    """None when ``folder`` is a writable directory or can be created as one (its nearest existing
    ancestor is a writable directory), else a short reason.  ``probe``: also create and remove a
    file there (see ``_probe``); without it, ``os.access`` only."""
    p = Path(os.path.abspath(folder))
    anc = p
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        return f"{anc} is a file, not a folder"
    if not probe:
        return None if os.access(anc, os.W_OK | os.X_OK) else f"{anc} is not writable (permission denied)"
    return _probe(anc)


def _path_error(text: str, msg: str):
    return argparse.ArgumentTypeError(f"{text!r}: {msg}")


def writable_dir(text: str) -> Path:
    """An argparse ``type``: a folder to write into, existing or not yet (then its nearest existing
    ancestor must be a writable directory: the script creates it); else a usage error naming why."""
    if not text or not text.strip():
        raise _path_error(text, "an empty path")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise _path_error(text, "exists and is not a directory")
    problem = folder_problem(p)
    if problem is not None:
        raise _path_error(text, f"cannot be written: {problem}")
    return p


def writable_file(text: str) -> Path:
    """An argparse ``type``: a file to write, new or to replace: not a directory, and its folder
    exists or can be created and can be written; else a usage error naming why."""
    if not text or not text.strip():
        raise _path_error(text, "an empty path")
    p = Path(text)
    if text.endswith(("/", os.sep)) or p.is_dir() or p.name in ("", ".", ".."):
        raise _path_error(text, "is a directory, not a file")
    if p.exists() and not os.access(p, os.W_OK):
        raise _path_error(text, "exists and cannot be written (permission denied)")
    problem = folder_problem(p.parent)
    if problem is not None:
        raise _path_error(text, f"cannot be written: {problem}")
    return p


def report_name(text: str) -> str:
    """An argparse ``type``: a report's name, the stem of reports/<name>.{md,json}: not empty, no
    path parts ('/', '\\\\', '..'), no leading '.', no control characters, short enough for a file
    name; else a usage error.  (A name with path parts wrote the report outside reports/.)"""
    why = None
    if not text or not text.strip():
        why = "an empty name"
    elif "/" in text or "\\" in text or ".." in text:
        why = "has path parts ('/', '\\', '..'): give a plain name, the report goes to reports/<name>.md"
    elif text.startswith("."):
        why = "starts with '.'"
    elif any(ord(c) < 32 or c == "\x7f" for c in text):
        why = "has control characters"
    elif len(text.encode()) > 200:
        why = "is longer than 200 bytes"
    if why is not None:
        raise argparse.ArgumentTypeError(f"{text!r} is not a report name: {why}")
    return text


def add_report_option(ap, default: str | None, files: str = "md,json", default_text: str | None = None) -> None:
    """``--report NAME`` on the parser ``ap``: the report's name (``report_name``), written as
    reports/NAME.{``files``}; ``default`` the committed report's (``default_text`` says it where
    it depends on other options)."""
    ap.add_argument("--report", type=report_name, default=default,
                    help=f"the report's name: reports/<NAME>.{{{files}}} (default {default_text or default}; another name "
                         "leaves the committed one as it is)")


def check_reports(ap, *names: str) -> None:
    """reports/ (where ``hairexp.app.report.write_report`` and the scripts' pictures go) and the
    reports ``names`` (stems) can be written, else a usage error (``ap.error``: exit 2) before the
    script runs anything, not a traceback after its runs."""
    reports = ROOT / "reports"
    problem = folder_problem(reports, probe=False)
    if problem is None:
        for name in names:
            for suffix in (".md", ".json"):
                f = reports / f"{name}{suffix}"
                if f.is_dir() or (f.exists() and not os.access(f, os.W_OK)):
                    problem = f"{f} is {'a directory' if f.is_dir() else 'not writable'}"
                    break
    if problem is not None:
        ap.error(f"the reports cannot be written to {reports}: {problem}")


def fail(message: str, code: int = 1) -> int:
    """Say ``message`` as one line ``<script>: error: <message>`` on stderr (its whitespace and line
    breaks folded) and return ``code`` for ``run_script`` (1: runs failed; 2 is a usage error)."""
    print(f"{Path(sys.argv[0]).name}: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
    return code


def key_value(word: str) -> str:
    """argparse ``type`` of ``--set``'s words: a ``KEY=VALUE`` override.  A name after ``--set``
    (``--set solver.dt=-1 goaling_smoke``) was taken as an override and failed in Hydra's parser
    ("missing EQUAL at '<EOF>'"; probe of issue 12, round 12)."""
    if "=" not in word:
        raise argparse.ArgumentTypeError(f"{word!r} is not KEY=VALUE; --set takes every word after it, so give the "
                                         "names (scenes, cases) before --set")
    return word


def check_set(ap, overrides, base=("experiment=goaling_smoke", "variants=[]")) -> None:
    """``--set KEY=VALUE ...`` overrides that compose and pass the config's checks on ``base``
    (``hairexp.app.assemble.check_config``: keys, types, ranges, the step schedule), else a usage
    error naming them (``ap.error``: exit 2), before a script runs anything or rewrites its report."""
    if not overrides:
        return
    from hairexp.app.assemble import check_config
    from hairexp.app.cli import compose_error

    msg = compose_error([*base, *overrides])   # the command line's one-line message (nearest key, why)
    if msg is not None:
        ap.error(f"--set {' '.join(overrides)}: {msg}")
    try:
        check_config(compose([*base, *overrides]))
    except Exception as exc:   # noqa: BLE001  (Hydra's composition errors, the schema's, InputError)
        ap.error(f"--set {' '.join(overrides)}: {' '.join(str(exc).split())}")


# -- configs -----------------------------------------------------------------------------------
def compose(overrides=(), typed=(), where: str = "script"):
    """The composed config (``hairexp.app.config.compose_config``) with the Hydra ``overrides``,
    then the ``typed`` ``key=value`` overrides applied as YAML values
    (``hairexp.app.experiment.apply_overrides``: lists of records such as ``scene.colliders``
    are typed by the schema; ``where`` names them in an error)."""
    from hairexp.app.config import compose_config

    # the report scripts write their runs into fixed folders of their own (outputs/paper_scenes/<name>,
    # ...) and re-run them: they replace the previous run there (``overwrite``, README "Run folder")
    cfg = compose_config(["overwrite=true", *overrides])
    if typed:
        from hairexp.app.experiment import apply_overrides

        cfg = apply_overrides(cfg, list(typed), where)
    return cfg


def _rows(rows) -> str:
    return "[" + ",".join("[" + ",".join(f"{float(v)}" for v in r) + "]" for r in rows) + "]"


def motion_overrides(times, translations, key: str = "scene.motion", interpolation: str = "linear") -> list[str]:
    """Overrides of a keyframed translation (no rotation) at ``key`` (``scene.motion``)."""
    return [f"{key}.interpolation={interpolation}", f"{key}.times=[{','.join(str(float(t)) for t in times)}]",
            f"{key}.translations={_rows(translations)}", f"{key}.rotations_deg={_rows([[0, 0, 0]] * len(times))}"]


def motion_record(times, translations, interpolation: str = "linear") -> str:
    """The same motion as a YAML flow record (a collider's ``motion``)."""
    return (f"{{interpolation: {interpolation}, times: [{', '.join(str(float(t)) for t in times)}], "
            f"translations: {_rows(translations)}, rotations_deg: {_rows([[0, 0, 0]] * len(times))}}}")


# -- the timing loop ---------------------------------------------------------------------------
@dataclass
class Timing:
    """Per-step figures of the timed steps of a run (``time_steps``)."""

    rows: list[dict]                     # one per timed step: seconds by part, iterations, contacts, extras
    state: object = None                 # the state after the last timed step
    warmup: int = 0
    start_time: float = 0.0              # s, run time at the first timed step's start

    def column(self, key: str) -> np.ndarray:
        return np.array([r[key] for r in self.rows], dtype=float)

    @property
    def seconds(self) -> np.ndarray:
        """(steps,) s, each step's own time (``StepInfo.seconds['total']``)."""
        return self.column("total")

    def split(self) -> dict:
        """Share of the timed steps' total time spent in each part (TIME_KEYS)."""
        tot = self.seconds.sum()
        return {k: float(self.column(k).sum() / tot) if tot > 0 else 0.0 for k in TIME_KEYS}

    def summary(self) -> dict:
        """median/mean/p90 s per step, iterations mean/max, converged fraction, the time split."""
        s, its = self.seconds, self.column("iterations")
        return {"steps": len(self.rows), "warmup_steps": self.warmup, "start_time": self.start_time,
                "median_s": float(np.median(s)), "mean_s": float(s.mean()), "p90_s": float(np.percentile(s, 90)),
                "iterations_mean": float(its.mean()), "iterations_max": int(its.max()),
                "converged_fraction": float(self.column("converged").mean()), "split": self.split()}


def time_steps(run, steps: int, warmup: int = 0, state=None, observe=None) -> Timing:
    """Step ``run`` (``hairexp.app.assemble.Run``) as ``Run.steps`` steps a run: from ``state``
    (default: ``run.initial_state()``, the settled hair of ``scene.settle``), ``warmup`` untimed
    steps (torch.compile builds its kernels on the first one), then ``steps`` timed ones.  Per
    timed step: the step's seconds by part (``StepInfo.seconds``), iterations, convergence, the
    collision stage's contacts and penetration, and ``observe(run, state, info)`` (a dict of
    numbers, computed after the step, not timed)."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    state = run.initial_state() if state is None else state
    n = warmup + steps
    frames = math.ceil(n / run.steps_per_frame)
    rows, start = [], state.time
    for i, (_, _, state, info) in enumerate(islice(run.steps(state, frames), n)):
        if i < warmup:
            start = state.time
            continue
        row = {**{k: info.seconds.get(k, 0.0) for k in (*TIME_KEYS, "total")}, "iterations": info.iterations,
               "converged": info.converged, "substeps": info.substeps, "object_contacts": info.object_contacts,
               "hair_contacts": info.hair_contacts, "penetration_max": info.penetration_max}
        if observe is not None:
            row.update(observe(run, state, info))
        rows.append(row)
    if len(rows) != steps:
        raise RuntimeError(f"the run has {frames} frames of {run.steps_per_frame} steps: fewer than {n} steps")
    return Timing(rows, state, warmup, float(start))


def stretch_max(run, state, info=None) -> dict:
    """``observe`` for ``time_steps``: the largest edge strain |l / l0 - 1| of the state."""
    from hairexp.outputs.metrics import stretch

    return {"stretch": float(np.abs(stretch(run.scene, state.x)).max())}


def frames_for(steps: int, dt: float, fps: float, margin: int = 1) -> int:
    """Output frames covering ``steps`` steps of ``dt`` at ``fps`` (the guides must cover the
    timed steps): for a ``frames=`` override."""
    return int(math.ceil(steps * dt * fps - 1e-9)) + margin


# -- formatting --------------------------------------------------------------------------------
def fmt(v, spec: str = ".3g", none: str = "-") -> str:
    """A table cell: ``none`` for None, floats with ``spec``, anything else (bools, ints, lists)
    as ``str``."""
    if v is None:
        return none
    if isinstance(v, (float, np.floating)):
        return format(float(v), spec)
    return str(v)


def pct(v: float) -> str:
    """A share (0..1) as a whole percentage."""
    return f"{100 * v:.0f}%"


def md_table(columns, rows=()) -> str:
    """A markdown table: the header of ``columns`` and one line per row of cells (already
    formatted strings, or anything ``str`` turns into one)."""
    out = md_row(columns) + "|" + "---|" * len(columns) + "\n"
    return out + "".join(md_row(r) for r in rows)


def md_row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |\n"


# -- the benchmark scene at Celia scale (bench_free, bench_tracking, bench_collisions) ---------
#: untimed steps before the timed ones: torch.compile builds its kernels (the head is still)
WARMUP = 2


def jerk(t0: float) -> tuple[list[float], list[list[float]]]:
    """(times, translations) of the benchmarks' head: still until t0, then up 12 cm in 0.1 s, and
    sideways (+x) 10 cm in 0.1 s one second later."""
    times = [0.0, t0, t0 + 0.1, t0 + 1.0, t0 + 1.1, t0 + 10.0]
    tr = [[0, 0, 0], [0, 0, 0], [0, 0.12, 0], [0, 0.12, 0], [0.1, 0.12, 0], [0.1, 0.12, 0]]
    return times, tr


def head_collider(cfg=None) -> str:
    """``scene.colliders`` with Celia's head alone, moving with the body (the benchmarks' jerk)."""
    return ("scene.colliders=[{name: head, shape: sphere, radius: 0.085, thickness: 0.002, friction: 0.3, "
            f"motion: {motion_record(*jerk(jerk_start(cfg)))}}}]")


def celia_bench(controller: str = "free", steps: int = 50, overrides=(), typed=(), collision: str = "off"):
    """The benchmarks' run config: ``experiment=celia variants=[] controller=<controller>
    collision=<collision>`` (the Celia ponytail, its simulated guides and edit, its
    ``scene.settle``), the body's motion replaced by ``jerk`` starting after the WARMUP steps, the
    colliders by the head alone moving with it (``head_collider``; a ``typed`` ``scene.colliders``
    replaces it), and ``frames`` covering the warm-up and the timed steps (the guides are built for
    them).  The head moves with the body: with Celia's own head, which stays still, the jerked roots
    would pass through it, which a run refuses (``check_clear_roots``) whether or not the collision
    stage is on."""
    base = compose(["experiment=celia", "variants=[]"])
    frames = frames_for(WARMUP + steps, float(base.solver.dt), float(base.fps))
    if not any(str(t).startswith("scene.colliders=") for t in typed):
        typed = [head_collider(base), *typed]
    # a benchmark times the steps: no measure (Celia's names the goblet, which a benchmark may replace)
    return compose(["experiment=celia", "variants=[]", f"controller={controller}", f"collision={collision}",
                    "measure.name=none", "measure.collider=", "judge=none", f"frames={frames}", *motion_overrides(*jerk(jerk_start(base))), *overrides], typed, "benchmark")


def jerk_start(cfg=None) -> float:
    """s, when the benchmarks' jerk starts: after the WARMUP steps of Celia's dt."""
    cfg = compose(["experiment=celia"]) if cfg is None else cfg
    return WARMUP * float(cfg.solver.dt)


def describe_run(run) -> str:
    """What a benchmark times, from the assembled run: scene size, dt, settle, controller,
    constraints and collision stage."""
    s, cfg, sim = run.scene.strands, run.cfg, run.simulator
    cons = getattr(run.controller, "cons", None)
    settle = float(cfg.scene.settle)
    stage = [n for n, on in (("objects", sim.collide_objects), ("hair-hair", sim.hair_hair is not None)) if on]
    return (f"`{cfg.experiment}` scene: {s.n_strands} strands, {s.n_vertices} vertices, {sim.objective.n_dofs} DOFs, "
            f"dt = {run.dt:g} s; settled for scene.settle = {settle:g} s (steps of {float(cfg.scene.settle_dt):g} s) "
            f"before t = 0" + ("" if settle > 0 else " (off)") + f"; controller `{run.controller_name}`"
            + (f" ({cons.K} clusters, {3 * cons.K} constraints)" if cons is not None else "")
            + f"; collision stage: {' and '.join(stage) if stage else 'off'}")


def experiment_names(ap, names, default) -> list[str]:
    """The experiments a script runs: ``names`` (command line) checked against conf/experiment/
    (an unknown one is ``ap.error``, exit 2, naming the known ones), else those of ``default`` that
    exist."""
    available = {p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml")}
    unknown = sorted(set(names or ()) - available)
    if unknown:
        ap.error(f"unknown experiment(s) {', '.join(unknown)} (conf/experiment/ has {', '.join(sorted(available))})")
    return list(names) if names else [n for n in default if n in available]


def run_child(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float]:
    """(peak RSS in MB, wall seconds) of one child process (``os.wait4``: ``ru_maxrss``); SystemExit
    naming the command and the end of its stderr if it fails."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = p.stderr.read().decode(errors="replace")   # before waiting: a full pipe would block the child
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    p.stderr.close()
    if p.returncode:
        raise SystemExit(f"{Path(sys.argv[0]).stem}: {' '.join(cmd)} failed with exit {p.returncode}:\n{err[-2000:]}")
    return usage.ru_maxrss / 1024, time.perf_counter() - t0


def run_script(main) -> None:
    """A script's entry point: ``main()``'s return code, and an interrupted run (SIGINT, SIGTERM:
    hairexp's ``Interrupted``) as one line and exit 128 + signal instead of a traceback from deep
    inside the run (probe of issue 12).  What the script wrote before stays."""
    from hairexp.app.streams import guard_streams, stdout_checked
    from hairexp.errors import InputError

    guard_streams()   # a full or closed stdout (--help >/dev/full): one line and exit 4, not a traceback
    prog = Path(sys.argv[0]).stem
    try:
        code = main()
    except SystemExit as exc:   # argparse's --help (0) and usage errors (2)
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        sys.exit(stdout_checked(code, prog))
    except InputError as exc:   # a bad input met inside a run (accuracy --scenes from_usd: a traceback; round 27)
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt as exc:   # hairexp.errors.Interrupted is one
        import signal as _signal

        signum = int(getattr(exc, "signum", _signal.SIGINT))
        name = _signal.Signals(signum).name
        print(f"{Path(sys.argv[0]).stem}: interrupted by {name}; the runs finished before it are kept", file=sys.stderr)
        sys.exit(128 + signum)
    sys.exit(stdout_checked(code if isinstance(code, int) and not isinstance(code, bool) else 0, prog))
