"""An experiment: one run, or one run per variant (e.g. free and tracked) judged together.

With ``variants`` empty, the run folder is that of ``hairexp.app.run.run``.  Otherwise each
variant runs in ``<out>/<variant name>/`` (a complete run folder) with its overrides applied
to the experiment's config, and ``<out>/summary.json`` gathers the variants' measures, their
per-step times and iteration counts, and the judge's verdict (``success``).  A failing variant
stops the experiment: the top-level summary says ``failed`` and the error propagates.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from hairexp.app.config import to_plain
from hairexp.errors import InputError
from hairexp.evaluation.judges import JUDGES
from hairexp.app.run import config_hash, run
from hairexp.outputs.files import write_json

#: Figures of each variant copied into the experiment's summary.
VARIANT_FIELDS = ("status", "steps", "iterations_mean", "iterations_max", "converged_fraction", "step_seconds_median",
                  "stretch_max", "residual_rel_max", "wall_seconds")


def apply_overrides(cfg, overrides: list[str], where: str):
    """A copy of ``cfg`` with ``key=value`` overrides (values parsed as YAML), validated by
    the schema (unknown keys and wrong types are errors naming the variant).  A list value
    replaces the list, and a list of records (``guides.edits``, ``scene.colliders``) is typed
    by the schema (a plain assignment of dicts to a list of structured records fails)."""
    out = copy.deepcopy(cfg)
    for o in overrides:
        if "=" not in o:
            raise InputError(f"override {o!r} is not key=value", where)
        key, val = o.split("=", 1)
        if OmegaConf.select(out, key, default="__missing__") == "__missing__":
            raise InputError(f"unknown key {key!r}", where)
        value = yaml.safe_load(val)
        try:
            # OmegaConf merges lists by replacement and validates their elements against the
            # schema; dicts keep ``merge=False`` (replace, not merge into the node).
            OmegaConf.update(out, key, value, merge=isinstance(value, list))
        except Exception as exc:  # omegaconf validation errors
            raise InputError(f"{o}: {exc}", where) from exc
    return out


def _variant_facts(cfg) -> dict:
    p = to_plain(cfg)
    return {"controller": p["controller"]["name"], "guides": p["guides"]["count"],
            "target_scale": max(p["tracking"]["variance"]["target_scale"] or [1.0])}


def run_experiment(cfg, out_dir) -> dict:
    out = Path(out_dir)
    if not cfg.variants:
        return run(cfg, out)
    plain = to_plain(cfg)
    t0 = time.perf_counter()
    summary = {"experiment": plain.get("experiment"), "status": "running", "success": None, "judge": plain["judge"],
               "variants": {}, "config_hash": config_hash(plain), "config": plain}
    measures, facts = {}, {}
    for i, v in enumerate(cfg.variants):
        name = str(v.name)
        vcfg = apply_overrides(cfg, list(v.overrides), f"variants[{i}] ({name})")
        vcfg.variants = []
        facts[name] = _variant_facts(vcfg)
        try:
            s = run(vcfg, out / name)
        except Exception as exc:
            summary["variants"][name] = {"status": "failed", "error": str(exc)}
            summary.update(status="failed", error=f"variant {name}: {exc}", wall_seconds=time.perf_counter() - t0)
            write_json(out / "summary.json", summary)
            raise
        measures[name] = s["measures"]
        summary["variants"][name] = {**{k: s.get(k) for k in VARIANT_FIELDS}, **facts[name], "measures": s["measures"]}
    judge = plain["judge"]
    if judge != "none":
        ok, details = JUDGES[judge](measures, facts, float(cfg.judge_tolerance))
        summary.update(success=ok, verdict=details)
    summary.update(status="completed", wall_seconds=time.perf_counter() - t0)
    write_json(out / "summary.json", summary)
    return summary
