"""An experiment: one run, or one run per variant (e.g. free and tracked) judged together.

With ``variants`` empty, the run folder is that of ``hairexp.app.run.run``.  Otherwise each
variant runs in ``<out>/<variant name>/`` (a complete run folder) with its overrides applied
to the experiment's config, and ``<out>/summary.json`` gathers the variants' measures, their
per-step times and iteration counts, and the judge's verdict (``success``); with
``logging.rerun`` the variants' recordings are put side by side in ``<out>/comparison.rrd``
(``hairexp.outputs.comparison``).  A failing variant
stops the experiment: the top-level summary says ``failed`` (``interrupted`` on SIGINT/SIGTERM)
and the error propagates.  Variant names are folder names: safe identifiers (letters, digits,
``_ . -``, not ``.`` or ``..``), unique within the experiment.
"""

from __future__ import annotations

import copy
import json
import logging
import re
import signal
import time
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from hairexp.app.assemble import check_config, shared_settle
from hairexp.app.guard import planning
from hairexp.app.config import SAFE_NAME, check_bool, require_config, to_plain, unknown_key_hint
from hairexp.app.validate import validate_judge, validate_judge_controllers
from hairexp.app.signals import InterruptSignals, note_late, take_late
from hairexp.app.variant_processes import choose_width, run_side_by_side
from hairexp.errors import InputError, Interrupted, choice_name
from hairexp.evaluation.judges import JUDGES
from hairexp.evaluation.measures import experiment_key_moment
from hairexp.app.run import config_hash, inputs_inside, run, run_arguments, run_checked, to_log_files, warnings_once, write_ending
from hairexp.outputs.files import write_json
from hairexp.outputs.folder import SUMMARY, claim, free_reserve, inside_run_refusal, owner, reserve, unusable_folder

log = logging.getLogger("hairexp")

#: Figures of each variant copied into the experiment's summary.
VARIANT_FIELDS = ("status", "steps", "iterations_mean", "iterations_max", "converged_fraction", "converged",
                  "unconverged_steps", "step_seconds_median", "stretch_max", "residual_rel_max", "wall_seconds")
#: names a variant's folder may not have: the experiment folder's own entries
RESERVED_NAMES = {"stream", "summary", "metrics", "result", "recording", "guides", "comparison"}


#: a variant's name at most (bytes): a folder name, with room for the files a run writes beside it
MAX_NAME_BYTES = 100


def check_variant_names(variants) -> list[str]:
    """The variants' names, each a safe folder name and unique (InputError naming ``variants[i].name``)."""
    names: list[str] = []
    for i, v in enumerate(variants):
        name = "" if v.name is None else str(v.name)
        where = f"variants[{i}].name"
        if not SAFE_NAME.match(name):
            raise InputError(f"{name!r} is not a safe folder name (letters, digits, '_', '.' and '-', starting with "
                             "a letter or digit)", where)
        if len(name.encode()) > MAX_NAME_BYTES:   # the folder's creation failed late (exit 4, ENAMETOOLONG; probe of issue 12)
            raise InputError(f"is {len(name.encode())} bytes long; a variant's name is a folder name of at most "
                             f"{MAX_NAME_BYTES} bytes", where)
        if name.split(".")[0].lower() in RESERVED_NAMES:
            raise InputError(f"{name!r} is reserved (the experiment folder's own entries: "
                             f"{', '.join(sorted(RESERVED_NAMES))})", where)
        if name in names:
            raise InputError(f"{name!r} is also the name of variants[{names.index(name)}]", where)
        names.append(name)
    return names


class OverrideLoader(yaml.SafeLoader):
    """YAML for override values, with Hydra's booleans: only ``true`` / ``false`` (any case)
    are booleans; YAML 1.1's ``on``, ``off``, ``yes``, ``no``, ``y``, ``n`` stay strings (so
    ``solver.compile=off`` is the choice ``off``).  Numbers, null, lists and records as in
    ``yaml.safe_load``."""


OverrideLoader.yaml_implicit_resolvers = {
    ch: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:bool"]
    for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
OverrideLoader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?i:true|false)$"), list("tTfF"))


def parse_value(text: str):
    """An override's value as Hydra would read it (``OverrideLoader``)."""
    return yaml.load(text, Loader=OverrideLoader)  # noqa: S506  (a SafeLoader)


def apply_overrides(cfg, overrides: list[str], where: str):
    """A copy of ``cfg`` with ``key=value`` overrides (values parsed as YAML with only
    true/false as booleans, ``parse_value``), validated by
    the schema (unknown keys and wrong types are errors naming the variant).  A list value
    replaces the list, and a list of records (``guides.edits``, ``scene.colliders``) is typed
    by the schema (a plain assignment of dicts to a list of structured records fails)."""
    out = copy.deepcopy(cfg)
    for o in overrides:
        if "=" not in o:
            raise InputError(f"override {o!r} is not key=value", where)
        key, val = o.split("=", 1)
        if key.lstrip("+~").split(".")[0] == "hydra":   # called an unknown key (probe of issue 12, round 14)
            raise InputError(f"{o}: a variant cannot set Hydra's keys ({key}): the launch's settings, given on the "
                             "command line (a variant's run folder is <the run folder>/<variant name>)", where)
        node = OmegaConf.select(out, key, default="__missing__")
        if isinstance(node, str) and node == "__missing__":   # with the command line's hint (probe, round 16)
            hint = unknown_key_hint(key)
            raise InputError(f"unknown key {key!r}" + (f"; {hint}" if hint else ""), where)
        if key in ("judge", "judge_tolerance"):   # the experiment's verdict over all variants (probe, round 14)
            raise InputError(f"{o}: a variant cannot set {key!r}: it belongs to the experiment, which judges all its "
                             "variants together (set it on the command line)", where)
        if key in ("experiment", "variants"):   # it ran the parent's scene under the other's name (probe of issue 12)
            raise InputError(f"{o}: a variant cannot set {key!r}: it belongs to the experiment (run the other "
                             "experiment on its own)", where)
        if key == "variants_mode":   # how the experiment runs its variants, not a variant's setting
            raise InputError(f"{o}: a variant cannot set 'variants_mode': it belongs to the experiment (set it on "
                             "the command line)", where)
        if key == "overwrite":   # taken silently, and meaningless: the experiment's folder is claimed once (probe, round 12)
            raise InputError(f"{o}: a variant cannot set 'overwrite': it belongs to the launch (the experiment's "
                             "run folder is replaced or not as a whole; set overwrite=true on the command line)", where)
        value = parse_value(val)
        if OmegaConf.is_config(node) and not isinstance(value, (dict, list)):
            raise InputError(f"{o}: {key!r} is a config group; a variant sets keys inside it ({key}.<key>=<value>), "
                             "not a group choice", where)
        try:
            check_bool(key, value, val)
        except InputError as exc:
            raise InputError(f"{o}: {exc}", where) from exc
        try:
            # OmegaConf merges lists by replacement and validates their elements against the
            # schema; dicts keep ``merge=False`` (replace, not merge into the node).
            OmegaConf.update(out, key, value, merge=isinstance(value, list))
        except Exception as exc:  # omegaconf validation errors: their first line (then full_key, types)
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise InputError(f"{o}: {first}", where) from exc
    return out


def _variant_facts(cfg) -> dict:
    p = to_plain(cfg)
    return {"controller": p["controller"]["name"], "guides": p["guides"]["count"],
            "target_scale": max(p["tracking"]["variance"]["target_scale"] or [1.0]),
            "assignment": p["tracking"]["assignment"]}


def _every_variants(cfg, exc: InputError) -> bool:
    """``exc`` (a variant's refusal) is the experiment's config's own, without any variant's
    overrides: a bad command-line key was said to be "variants[0] free"'s."""
    base = copy.deepcopy(cfg)
    base.variants = []
    try:
        check_config(base)
        validate_judge(cfg, base.measure)
    except InputError as own:
        return str(own) == str(exc)
    return False


def _checked_variants(cfg, sizes: list | None = None) -> tuple[list[str], list]:
    """The variants' names and configs, every one checked (``check_config``, the judge) before
    the first runs; InputError naming the variant.  ``sizes``: gets each variant's (estimated
    seconds, estimated memory) from the resource guard, in order."""
    names = check_variant_names(cfg.variants)
    with planning() as planned:   # the variants share the folder's disk: checked together against it
        return _checked_each(cfg, names, planned, sizes)


def _checked_each(cfg, names: list[str], planned: list, sizes: list | None) -> tuple[list[str], list]:
    vcfgs = []
    for i, (name, v) in enumerate(zip(names, cfg.variants)):   # every variant's config, before the first runs
        vcfg = apply_overrides(cfg, list(v.overrides), f"variants[{i}] ({name})")
        vcfg.variants = []
        vcfgs.append(vcfg)
        before = len(planned)
        try:
            check_config(vcfg)
            if sizes is not None:
                own = planned[before:]
                sizes.append((sum(e.seconds for e in own), sum(e.memory for e in own)))
            validate_judge(cfg, vcfg.measure)
        except InputError as exc:   # the key's own message, said to be the variant's
            if _every_variants(cfg, exc):   # the experiment's own setting (scene.n_strands=-5): not one variant's
                raise
            raise InputError(f"{exc} (variants[{i}] {name}, checked before any variant runs)") from exc
    validate_judge_controllers(cfg, names, [_variant_facts(v)["controller"] for v in vcfgs])
    spans = {name: (v.frames, v.fps) for name, v in zip(names, vcfgs)}
    if len(set(spans.values())) > 1:   # taken without a word (independent probe of issue 12, round 28)
        log.warning("the variants run different spans (%s): their measures, the judge and comparison.rrd compare "
                    "them as if they ran the same; set frames and fps for the experiment, not in a variant",
                    ", ".join(f"{n}: {f} frames at {_rate(r)} fps" for n, (f, r) in spans.items()))
    return names, vcfgs


def _rate(fps) -> str:
    """A variant's ``fps`` as said: null is the stage's rate (a USD scene)."""
    return "the stage's" if fps is None else str(fps)


def run_experiment(cfg, out_dir, on_checked=None) -> dict:
    """Run the experiment of ``cfg`` into ``out_dir``.  Every run's config is checked before the
    folder is claimed; ``on_checked()``, if given, is called then (the command line's warnings
    about unused keys: said above a refused run's error line, they hid it)."""
    out = run_arguments(cfg, out_dir, "run_folder")
    why = unusable_folder(str(out))   # as the command line refuses it before Hydra starts (it raised mkdir's
    if why is not None:               # bare FileNotFoundError; probe of issue 12, round 34)
        raise InputError(f"cannot be the run folder: {why}", str(out))
    why = inside_run_refusal(out)   # as the command line (an overwrite of that run then deleted this one; a probe)
    if why is not None:
        raise InputError(why, str(out))
    if not cfg.variants:
        return run(cfg, out, on_checked)
    with warnings_once():   # the variants' checks and runs say each warning once
        return _experiment(cfg, out, on_checked)


def _experiment(cfg, out: Path, on_checked) -> dict:
    sizes: list = []
    names, vcfgs = _checked_variants(cfg, sizes)
    if on_checked is not None:
        on_checked()
    plain = to_plain(cfg)
    if bool(cfg.overwrite):
        inside = inputs_inside(cfg, out)
        if inside is not None:
            raise InputError(inside, str(out))
    t0 = time.perf_counter()
    summary = {"experiment": plain.get("experiment"), "status": "running", **owner(), "success": None,
               "judge": plain["judge"],
               "variants": {}, "config_hash": config_hash(plain), "config": plain}
    measures, facts = {}, {}
    with InterruptSignals() as signals:
        with signals.deferred():
            # a signal while overwrite=true removes the previous run's files, or before the running
            # summary is written, is kept for the try below: the folder is never left without a summary
            # beside half of the old run (independent probe of issue 12, round 22)
            claim(out, overwrite=bool(cfg.overwrite))
            write_json(out / SUMMARY, summary)
            # room for the experiment's ending on a disk that fills meanwhile (its summary stayed "running":
            # independent probe of issue 12, round 22), as a run holds for its own
            reserve(out)
        try:
            if signals.pending is not None:
                raise Interrupted(signals.pending)
            width, why = choose_width(cfg.variants_mode, len(names), [z[0] for z in sizes], [z[1] for z in sizes])
            summary["variants_at_once"] = {"mode": choice_name(cfg.variants_mode), "at_once": width, "why": why}
            if width > 1:   # one process each; each settles on its own core
                log.info("%s: the %d variants run %d at once (%s)", out, len(names), width, why)
                _run_parallel(out, names, vcfgs, width, summary, measures, facts, t0, signals)
            else:
                with shared_settle():   # variants that differ in their controller settle once
                    _run_variants(out, names, vcfgs, summary, measures, facts, t0)
            judge = plain["judge"]
            if judge != "none":
                ok, details = JUDGES[judge](measures, facts, float(cfg.judge_tolerance))
                why = unjudgeable(summary["variants"])
                if why is not None:   # the measures of a run that did not solve its steps say nothing
                    log.warning("%s: no verdict (success: null): %s", out, why)
                    ok, details = None, {**details, "not_judged": why}
                summary.update(success=ok, verdict=details)
            recorded = {n: (out / n / "recording.rrd").is_file() for n in names}
            if any(recorded.values()) and not all(recorded.values()):   # skipped without a word (round 25)
                log.warning("%s: no comparison.rrd (the variants side by side): %s ran without a recording "
                            "(logging.rerun=false)", out, ", ".join(n for n, r in recorded.items() if not r))
            if cfg.logging.rerun:   # the variants side by side, from their folders (rerun is imported only here)
                from hairexp.outputs.comparison import write_comparison

                key = experiment_key_moment(str(plain["measure"]["name"]), measures)
                if write_comparison(out, names, key) is not None:
                    summary["comparison"] = {"file": "comparison.rrd",
                                             "key": None if key is None else {"time": key[0], "what": key[1]}}
            with signals.deferred():   # the completed ending is written whole; a signal meanwhile comes after it
                converged = [v.get("converged") for v in summary["variants"].values()]
                summary.update(status="completed", converged=all(c is not False for c in converged),
                               wall_seconds=time.perf_counter() - t0)
                free_reserve(out)
                write_json(out / SUMMARY, summary)
        except BaseException as exc:
            status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
            with signals.deferred():
                if summary["status"] in ("running", "completed"):   # not yet told by a variant
                    # a verdict given before the ending (an interrupted comparison recording) is kept under
                    # "verdict", but an experiment that did not complete is no success (round 22: it said true)
                    summary.update(status=status, error=str(exc) or type(exc).__name__, success=None,
                                   wall_seconds=time.perf_counter() - t0)
                try:
                    free_reserve(out)   # its room is the summary's
                    write_ending(out / SUMMARY, summary)   # in place when the disk has no room for a new file
                except Exception as e2:   # noqa: BLE001  (never hide the first error)
                    note = f"while writing the experiment's {status} summary: {type(e2).__name__}: {e2}"
                    to_log_files(f"{out}: {note}")   # the console gets it under the error's line ("also:")
                    exc.add_note(note)
            raise
        if signals.pending is not None:   # after the completed ending: the experiment stays completed
            note_late(signals.pending)
    return summary


def _run_parallel(out: Path, names: list[str], vcfgs: list, width: int, summary: dict, measures: dict, facts: dict,
                  t0: float, signals) -> None:
    """Run the variants ``width`` at a time, one process each (``variant_processes``); the summary's
    entries in the experiment's order, and the first failure raised as ``_run_variants`` raises it."""
    for name, vcfg in zip(names, vcfgs):
        facts[name] = _variant_facts(vcfg)
    entries: dict[int, dict] = {}
    errors: dict[int, BaseException] = {}

    def done(i: int, s: dict) -> None:
        entries[i] = _done_entry(names[i], facts, s, measures)

    def failed(i: int, exc: BaseException) -> None:
        entries[i] = _failed_entry(out, names[i], facts, exc)
        errors[i] = exc

    def gather() -> None:
        summary["variants"] = {names[i]: entries[i] for i in sorted(entries)}

    try:
        index, exc = run_side_by_side(out, names, vcfgs, width, signals, done, failed)
    except BaseException as exc:   # a signal to the experiment: every running variant was stopped by it
        gather()
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        stopped = [names[i] for i in sorted(errors)]
        summary.update(status=status, wall_seconds=time.perf_counter() - t0,
                       error=(f"variant{'s' if len(stopped) > 1 else ''} {', '.join(stopped)}: " if stopped else "")
                       + (str(exc) or type(exc).__name__))
        if stopped and not hasattr(exc, "run_folder"):
            exc.run_folder = str(out / stopped[0])
        raise
    gather()
    if exc is None:
        return
    name = names[index]
    status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
    if index not in errors:   # completed, then a signal came (a late one): "after variant" as _run_variants says
        summary.update(status=status, error=f"interrupted by {signal.Signals(exc.signum).name} after variant {name}",
                       wall_seconds=time.perf_counter() - t0)
        raise exc
    summary.update(status=status, error=f"variant {name}: {exc}", wall_seconds=time.perf_counter() - t0)
    raised = _variant_error(exc, out, name)
    if raised is not exc:
        raise raised from exc
    raise exc


#: a variant with fewer of its steps converged than this, or stretched more than MAX_JUDGED_STRETCH,
#: gets no verdict: with tracking.max_iterations=1 the tracked goaling wisp "hit" the wheel by
#: stretching 581 % with 26 of 30 steps unconverged, and the experiment said success (probe of
#: issue 12, round 12).  The paper scenes converge in at least 99 % of their steps.
MIN_JUDGED_CONVERGED = 0.8
MAX_JUDGED_STRETCH = 1.0


def unjudgeable(variants: dict) -> str | None:
    """Why the judge's verdict on these variants' measures is not given, or None."""
    bad = []
    for name, v in variants.items():
        frac, stretch = v.get("converged_fraction"), v.get("stretch_max")
        if frac is not None and frac < MIN_JUDGED_CONVERGED:
            bad.append(f"{name}: {v.get('unconverged_steps')} of {v.get('steps')} steps did not converge")
        if stretch is not None and stretch > MAX_JUDGED_STRETCH:
            bad.append(f"{name}: its hair stretched by {100 * stretch:.0f} %")
    if not bad:
        return None
    return ("; ".join(bad) + f" (a verdict needs >= {100 * MIN_JUDGED_CONVERGED:.0f} % of the steps converged and "
            f"<= {100 * MAX_JUDGED_STRETCH:.0f} % stretch)")


def _failed_entry(out: Path, name: str, facts: dict, exc: BaseException) -> dict:
    """The summary's entry of a variant that failed or was interrupted: the figures of the steps it
    ran, from its own ending summary, as for the other variants (it had only status and error;
    probe of issue 12, round 10)."""
    status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
    try:
        own = json.loads((out / name / SUMMARY).read_text())
    except (OSError, ValueError):
        own = {}
    own = own if isinstance(own, dict) else {}
    return {**{k: own.get(k) for k in VARIANT_FIELDS}, **facts.get(name, {}),
            "status": status, "error": str(exc) or type(exc).__name__}


def _done_entry(name: str, facts: dict, s: dict, measures: dict) -> dict:
    """The summary's entry of a completed variant (its summary ``s``); its measures go to ``measures``."""
    measures[name] = s["measures"]
    coh = s.get("cohesion") or {}
    return {**{k: s.get(k) for k in VARIANT_FIELDS}, **facts[name], "measures": s["measures"], "cohesion": coh}


def _variant_error(exc: BaseException, out: Path, name: str) -> BaseException:
    """The variant's error as the experiment raises it: a key checked once the variant's scene is
    built is said to be the variant's (probe of issue 12, round 14), and the command line names the
    variant's folder (round 18) and looks there for its partial metrics (round 26)."""
    if type(exc) is InputError:
        new = InputError(f"{exc} (variant {name}: {out / name})")
        new.__cause__ = exc
        return new
    if not hasattr(exc, "run_folder"):
        exc.run_folder = str(out / name)
    return exc


def _run_variants(out: Path, names: list[str], vcfgs: list, summary: dict, measures: dict, facts: dict,
                  t0: float) -> None:
    """Run each variant's config (``vcfgs``, built and checked by ``run_experiment``) in order."""
    for name, vcfg in zip(names, vcfgs):
        try:
            facts[name] = _variant_facts(vcfg)
            s = run_checked(vcfg, out / name)   # checked with the others (_checked_variants)
        except BaseException as exc:
            status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
            summary["variants"][name] = _failed_entry(out, name, facts, exc)
            summary.update(status=status, error=f"variant {name}: {exc}", wall_seconds=time.perf_counter() - t0)
            raised = _variant_error(exc, out, name)
            if raised is not exc:
                raise raised from exc
            raise
        summary["variants"][name] = _done_entry(name, facts, s, measures)
        late = take_late()   # a signal after this variant had completed: it stays so, the next ones do not run
        if late is not None:
            summary.update(status="interrupted", error=f"interrupted by {signal.Signals(late).name} after variant {name}",
                           wall_seconds=time.perf_counter() - t0)
            raise Interrupted(late)
