"""The paper scenes' verdicts per integrator and time step (issue: physical fidelity, "scene verdicts
that do not depend on dt"): one table from several ``experiments.paper_scenes`` reports.

Each input is the JSON report that ``python -m experiments.paper_scenes --set solver.integrator=<i>
solver.dt=<dt> logging.rerun=false`` writes (reports/paper_scenes.json; copied aside per run, e.g. under
reports/verdicts/).  The integrator and dt of a column are read from the command recorded in the
report, never from the file name.  Several reports of one integrator and dt are parts of one column
(e.g. one scene re-run after it was re-authored: ``paper_scenes goaling --set ...``): a scene of the
later report replaces the earlier one's.  Writes reports/integrator_verdicts.{md,json}.

Usage: python -m experiments.integrator_verdicts [--report NAME] reports/verdicts/*.json
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from hairexp.app.report import header, write_report
from hairexp.physics.integrators import DEFAULT_INTEGRATOR

from experiments.common import add_report_option, check_reports, fmt, md_row, md_table

#: scene -> the variant figures shown beside the verdict (variant, measure key)
KEY_FIGURES = {
    "goaling": [("free", "min_distance"), ("tracked", "first_hit_time")],
    "celia": [("free", "min_distance"), ("tracked", "first_hit_time")],
    "splitting": [("free", "clumps"), ("tracked_2", "clumps"), ("tracked_3", "clumps")],
    "spreading": [("target_10v0", "cluster_variance_ratio"), ("target_10v0", "apex_time")],
    "stylization": [("free", "travel"), ("tracked", "left_rail_time")],
}


def column_of(report: dict, path: Path) -> tuple[str, float]:
    """(integrator, dt) from the command the report records (without them: the default integrator,
    ``DEFAULT_INTEGRATOR``, and 0.04; the reports under reports/verdicts/ all name both)."""
    cmd = report.get("command", "")
    cmd = cmd if isinstance(cmd, str) else ""
    integ = re.search(r"solver\.integrator=(\w+)", cmd)
    dt = re.search(r"solver\.dt=([0-9.eE+-]+)", cmd)
    if not cmd:
        raise SystemExit(f"integrator_verdicts: {path}: no command recorded in the report")
    return (integ.group(1) if integ else DEFAULT_INTEGRATOR, float(dt.group(1)) if dt else 0.04)


def load(paths: list[Path]) -> dict:
    """{(integrator, dt): column}.  Several reports of the same integrator and dt are the parts of
    one column: their scenes are merged, a scene in a later report (its recorded date) replacing
    the same scene of an earlier one (e.g. a scene re-run after it was re-authored), and the
    column lists every part's command."""
    parts = []
    for p in paths:
        try:
            rep = json.loads(p.read_text())
        except (OSError, ValueError) as exc:
            raise SystemExit(f"integrator_verdicts: {p}: cannot read the report: {exc}")
        if not isinstance(rep, dict) or not isinstance(rep.get("scenes"), dict):
            raise SystemExit(f"integrator_verdicts: {p}: not a paper_scenes report (no 'scenes')")
        for name, scene in rep["scenes"].items():   # a hand-made or truncated report: a KeyError (probe, round 21)
            if not isinstance(scene, dict) or (scene.get("status") != "failed"
                                               and not isinstance(scene.get("variants"), dict)):
                raise SystemExit(f"integrator_verdicts: {p}: scene {name!r} is not a paper_scenes scene record "
                                 "(no 'variants', and not failed)")
        machine = rep.get("machine") if isinstance(rep.get("machine"), dict) else {}
        rep = {**rep, "machine": machine}
        parts.append((str(machine.get("date") or ""), str(p), column_of(rep, p), rep))
    cols = {}
    for date, path, key, rep in sorted(parts, key=lambda q: (q[0], q[1])):
        c = cols.setdefault(key, {"paths": [], "commands": [], "dates": [], "scenes": {}})
        c["paths"].append(path)
        c["commands"].append(rep["command"])
        c["dates"].append(rep["machine"].get("date"))
        c["scenes"].update(rep["scenes"])
    for c in cols.values():   # the one-report form the tables and the JSON read
        c.update(path=", ".join(c["paths"]), command=" ; ".join(c["commands"]),
                 date=", ".join(str(d) for d in c["dates"]))
    return dict(sorted(cols.items(), key=lambda kv: (kv[0][0], -kv[0][1])))


def markdown(cols: dict) -> str:
    md = header("Paper scene verdicts per integrator and time step")
    md += ("Every column is the paper scenes run in full (every variant) by the command or commands given below "
           "it (several when a column was run in parts); the verdict is the scene's judge (README, \"Paper scenes\").  Beside each "
           "verdict: the figures its judge rests on (free: smallest distance to the target object in m; tracked: "
           "first hit time in s; splitting: clumps free and with 2 and 3 guides; spreading: the 10 v0 cluster variance "
           "ratio and the apex time (s) it is measured at; "
           "stylization: the free block's travel in m and the tracked block's time off the rail in s), then the "
           "tracked run's SQP iterations mean / max.\n\n")
    scenes = sorted({s for c in cols.values() for s in c["scenes"]},
                    key=lambda s: list(KEY_FIGURES).index(s) if s in KEY_FIGURES else 99)
    heads = [f"{i} dt {dt:g}" for i, dt in cols]
    md += md_table(["scene", *heads])
    for scene in scenes:
        cells = []
        for c in cols.values():
            s = c["scenes"].get(scene)
            if s is None:
                cells.append("not run")
                continue
            if s.get("status") == "failed":
                cells.append(f"**failed**: {s.get('error', '')}")
                continue
            figs = []
            for var, key in KEY_FIGURES.get(scene, []):
                v = s["variants"].get(var)
                figs.append(f"{var} {key} {fmt(v['measures'].get(key), '.3g') if v else '-'}")
            tracked = [v for n, v in s["variants"].items() if n != "free"]
            it = (f"; it {max(v['iterations_mean'] for v in tracked):.1f} / {max(v['iterations_max'] for v in tracked)}"
                  if tracked else "")
            cells.append(f"**{s['success']}** ({', '.join(figs)}{it})")
        md += md_row([scene, *cells])
    md += "\nCommands (each column's report, its date):\n\n"
    for (i, dt), c in cols.items():
        md += f"- {i} dt {dt:g}: " + "; then ".join(
            f"`{cmd}` ({date}; {Path(p).name})" for cmd, date, p in zip(c["commands"], c["dates"], c["paths"])) + "\n"
    return md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", type=Path, help="paper_scenes JSON reports, one per integrator and dt")
    add_report_option(ap, "integrator_verdicts")
    a = ap.parse_args(argv)
    try:
        cols = load(a.reports)
    except SystemExit as exc:   # an unreadable or foreign report: a usage error (exit 2), before anything is written
        ap.error(str(exc).removeprefix("integrator_verdicts: "))
    check_reports(ap, a.report)
    md = markdown(cols)
    path = write_report(a.report, md, {"columns": [
        {"integrator": i, "dt": dt, "report": c["path"], "command": c["command"],
         "success": {n: s.get("success") for n, s in c["scenes"].items()}} for (i, dt), c in cols.items()]})
    print(md)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
