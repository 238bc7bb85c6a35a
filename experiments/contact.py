"""Contact inside the optimisation (issue 14): the IPC barrier (``collision.contact=barrier``)
against the post-solve collision stage with its strain limiter (``collision.contact=stage``),
on the paper scenes with colliders and on the fast-collider stress cases.  Writes
reports/contact.{md,json}.

Per run (one controller variant of a scene, both contact modes, same config otherwise):

* contact frames: steps whose ``contacts`` column is > 0 (barrier: edges within d_hat of a
  collider at the end of the step; stage: vertices it corrected);
* strain max in contact frames (``stretch_max``: |edge length / rest - 1|), target <= 2 %;
* tracking residual max / L over all frames (``residual_rel_max``), target <= 1e-6;
* SQP (or Newton) iterations: mean over contact frames / mean over all frames, target <= 2;
* penetration: deepest point of the saved frames inside a collider's thickness shell, over the
  vertices and 16 samples per edge (result.npz positions against the colliders at the frames'
  times), target none;
* cost: median step seconds of contact frames / of non-contact frames, target <= 1.3.

Usage: python -m experiments.contact [--runs NAME ...] [--frames N] [--keep] [--extra ROWS.json ...]
                                     [--set KEY=VALUE ...]

``--keep`` keeps the rows of the existing report (reports/contact.json) ahead of the new ones and
the hand-written sections of reports/contact.md (from its first "## " heading on); ``--extra``
adds the rows of other result files (e.g. a before run written with ``--out``).  Each row
records the commit it was measured at (``code``; "+wip" when hairexp/ had uncommitted changes).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from experiments.common import ROOT, check_set, compose, fail, fmt, key_value, md_table, positive_int, writable_dir, writable_file

EDGE_SAMPLES = 16
#: stress cases: the stress matrix's scene (experiments/stress.py BASE) with a fast collider
STRESS_BASE = ["experiment=goaling", "variants=[]", "scene.n_strands=12", "scene.n_vertices=12", "frames=30",
               "measure.name=none", "measure.collider=", "solver.compile=off"]
BALL_10MS = ('scene.colliders=[{name: ball, shape: sphere, radius: 0.05, friction: 0.3, motion: {interpolation: linear, '
             'times: [0.0, 0.5], translations: [[0.01, -0.15, -2.5], [0.01, -0.15, 2.5]], '
             'rotations_deg: [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]}}]')
# a capsule (r 2 cm, 20 cm long, axis along world x) swept sideways (z) at 8 m/s through the hanging
# wisp at mid-length (t = 0.25 s)
CAPSULE_8MS = ('scene.colliders=[{name: bar, shape: capsule, radius: 0.02, half_length: 0.1, friction: 0.3, '
               'motion: {interpolation: linear, times: [0.0, 0.5], translations: [[0.0, -0.15, -2.0], [0.0, -0.15, 2.0]], '
               'rotations_deg: [[0.0, 0.0, 90.0], [0.0, 0.0, 90.0]]}}]')

#: name -> (hydra overrides, typed overrides, controller)
RUNS = {
    "goaling_tracked": (["experiment=goaling", "variants=[]"], [], "tracking"),
    "goaling_free": (["experiment=goaling", "variants=[]"], [], "free"),
    "splitting_tracked_2": (["experiment=splitting", "variants=[]", "guides.count=2",
                             "guides.edits=[{guide: 0, kind: displace, offset: [0.0, 0.0, 0.14], falloff: 2.0, "
                             "times: [0.75, 1.05], weights: [0.0, 1.0]}, {guide: 1, kind: displace, offset: "
                             "[0.0, 0.0, -0.14], falloff: 2.0, times: [0.75, 1.05], weights: [0.0, 1.0]}]"], [], "tracking"),
    "splitting_free": (["experiment=splitting", "variants=[]"], [], "free"),
    "celia_tracked": (["experiment=celia", "variants=[]"], [], "tracking"),
    "ball_10ms_free": (STRESS_BASE, [BALL_10MS], "free"),
    "ball_10ms_tracked": (STRESS_BASE, [BALL_10MS], "tracking"),
    "capsule_8ms_free": (STRESS_BASE + ["guides.source=rigid", "guides.edits=[]"], [CAPSULE_8MS], "free"),
    "capsule_8ms_tracked": (STRESS_BASE + ["guides.source=rigid", "guides.edits=[]"], [CAPSULE_8MS], "tracking"),
}
MODES = ("stage", "barrier")


def penetration(cfg, out: Path) -> tuple[float, float]:
    """Deepest penetration (m) into a collider's thickness shell over the saved frames, of the
    vertices and of EDGE_SAMPLES points per edge."""
    from hairexp.app.assemble import assemble_scene

    _, scene, _ = assemble_scene(cfg, settle=False)
    r = np.load(out / "result.npz")
    X, times = r["positions"], r["times"]
    free = ~scene.strands.kinematic
    E = scene.strands.edges
    E = E[free[E[:, 0]] | free[E[:, 1]]]   # an edge of two root vertices is prescribed (celia's roots sit in the head)
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES)
    pv = pe = 0.0
    for f in range(len(times)):
        x = X[f]
        for c in scene.colliders:
            pv = max(pv, float(np.maximum(-c.distance(x[free], times[f]), 0).max(initial=0)))
            pts = x[E[:, 0], None] * (1 - s)[None, :, None] + x[E[:, 1], None] * s[None, :, None]
            pe = max(pe, float(np.maximum(-c.distance(pts.reshape(-1, 3), times[f]), 0).max(initial=0)))
    return pv, pe


def measure(name: str, mode: str, frames: int | None, work: Path, extra: list | None = None) -> dict:
    import pandas as pd

    from hairexp.app.run import run

    hydra, typed, controller = RUNS[name]
    ov = list(hydra) + [f"controller.name={controller}", f"collision.contact={mode}", "logging.rerun=false",
                        "logging.progress=false"]
    if frames:
        ov.append(f"frames={frames}")
    ov += list(extra or [])
    cfg = compose(ov, typed, where=name)
    label = mode + (f" [{' '.join(extra)}]" if extra else "")
    out = work / (f"{name}_{mode}" + ("_" + "_".join(e.replace("/", "-") for e in extra) if extra else ""))
    t0 = time.perf_counter()
    row = {"run": name, "mode": label, "controller": controller}
    try:
        s = run(cfg, out)
        row["outcome"] = "completed"
        row["converged"] = s.get("converged")
    except Exception as exc:  # noqa: BLE001 - the table records failures
        row["outcome"] = f"failed: {type(exc).__name__}: {exc}"
    row["wall"] = time.perf_counter() - t0
    mp = out / "metrics.parquet"
    if not mp.is_file():
        return row
    df = pd.read_parquet(mp)
    df = df[df["frame"] > 0] if "frame" in df else df
    c = df["contacts"] > 0
    row.update(steps=len(df), contact_steps=int(c.sum()),
               strain_contact=float(df.loc[c, "stretch_max"].max()) if c.any() else None,
               strain_max=float(df["stretch_max"].max()),
               iterations_mean=float(df["iterations"].mean()),
               iterations_contact=float(df.loc[c, "iterations"].mean()) if c.any() else None,
               iterations_max=int(df["iterations"].max()),
               unconverged=int((~df["converged"]).sum()),
               recovered=int(df["recovered"].sum()) if "recovered" in df else None,
               sec_contact=float(df.loc[c, "step_seconds"].median()) if c.any() else None,
               sec_free=float(df.loc[~c, "step_seconds"].median()) if (~c).any() else None)
    if "residual_rel_max" in df and df["residual_rel_max"].notna().any():
        rr = df["residual_rel_max"].astype(float)
        row["residual_rel_max"] = float(rr.max())
        row["residual_frames_over_1e-6"] = int((rr > 1e-6).sum())
    if row["iterations_contact"] is not None:
        row["iter_ratio"] = row["iterations_contact"] / row["iterations_mean"]
    if row["sec_contact"] is not None and row["sec_free"]:
        row["cost_ratio"] = row["sec_contact"] / row["sec_free"]
    if (out / "result.npz").is_file():
        row["pen_vertex"], row["pen_edge"] = penetration(cfg, out)
    for k in ("relaxed_frames", "relaxed_clusters_max", "relaxed_slack_max"):
        if k in df:
            row[k] = float(df[k].max()) if k != "relaxed_frames" else int((df["relaxed_clusters"] > 0).sum())
    return row


def rows_of(path: Path) -> list:
    """The rows of a result file (a JSON list of row objects), or ValueError."""
    rows = json.loads(path.read_text())
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ValueError("not a list of rows (a contact result file: a JSON list of objects)")
    return rows


def code_version() -> str:
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "hairexp"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    except OSError:
        return "-"
    return head + ("+wip" if dirty else "")


COLUMNS = ["run", "mode", "outcome", "contact steps / steps", "strain max in contact", "residual max / L",
           "frames residual > 1e-6 L", "iterations contact / mean", "penetration vertex / edge (mm)",
           "s/step contact / non-contact", "unconverged", "wall s", "code"]


def table_row(r: dict) -> list[str]:
    out = r["outcome"] if r["outcome"] == "completed" else r["outcome"][:60]
    return [r["run"], r["mode"], out, f"{r.get('contact_steps', '-')} / {r.get('steps', '-')}",
            fmt(r.get("strain_contact"), ".3g"), fmt(r.get("residual_rel_max"), ".2g"),
            fmt(r.get("residual_frames_over_1e-6"), "d"),
            f"{fmt(r.get('iterations_contact'), '.2f')} / {fmt(r.get('iterations_mean'), '.2f')} "
            f"({fmt(r.get('iter_ratio'), '.2f')}x)",
            f"{fmt(1e3 * r['pen_vertex'] if r.get('pen_vertex') is not None else None, '.3g')} / "
            f"{fmt(1e3 * r['pen_edge'] if r.get('pen_edge') is not None else None, '.3g')}",
            f"{fmt(r.get('sec_contact'), '.3g')} / {fmt(r.get('sec_free'), '.3g')} ({fmt(r.get('cost_ratio'), '.2f')}x)",
            fmt(r.get("unconverged"), "d"), fmt(r.get("wall"), ".0f"), str(r.get("code", "-"))]


def report_stem(text: str) -> Path:
    """argparse ``type`` of ``--out``: the stem of the report's two files, <OUT>.md and <OUT>.json,
    both writable (``common.writable_file``), checked before any run."""
    if not text or not text.strip() or text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"{text!r}: not a file stem (the report is written to <OUT>.md and "
                                         "<OUT>.json)")
    for suffix in (".md", ".json"):
        writable_file(str(Path(text).with_suffix(suffix)))
    return Path(text)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", nargs="*", default=list(RUNS), choices=list(RUNS))
    ap.add_argument("--modes", nargs="*", default=list(MODES), choices=list(MODES))
    ap.add_argument("--frames", type=positive_int, default=None)
    ap.add_argument("--work", type=writable_dir, default=str(ROOT / "outputs" / "contact"), help="the runs' folders go here")
    ap.add_argument("--out", type=report_stem, default=str(ROOT / "reports" / "contact"),
                    help="the report: <OUT>.md and <OUT>.json (default reports/contact)")
    ap.add_argument("--keep", action="store_true", help="keep the existing report's rows and analysis")
    ap.add_argument("--extra", nargs="*", default=[], help="result files whose rows to add")
    ap.add_argument("--set", nargs="*", default=[], type=key_value, help="config overrides of every run (a variant; named in the mode column)")
    args = ap.parse_args(argv)
    check_set(ap, args.set)   # before any run (a bad key would fail every run and replace the report)
    work, out = Path(args.work), Path(args.out)
    rows, notes = [], ""
    try:   # the inputs read before any run: an unreadable one is a usage error, not a traceback
        if args.keep and out.with_suffix(".json").is_file():
            what = f"--keep: {out.with_suffix('.json')}"
            rows += rows_of(out.with_suffix(".json"))
            md_old = out.with_suffix(".md").read_text() if out.with_suffix(".md").is_file() else ""
            notes = md_old[md_old.index("\n## ") + 1:] if "\n## " in md_old else ""
        for f in args.extra:
            what = f"argument --extra: {f}"
            rows += rows_of(Path(f))
    except (OSError, ValueError) as exc:
        ap.error(f"{what}: cannot be read: {exc}")
    work.mkdir(parents=True, exist_ok=True)
    code = code_version()
    t0 = time.perf_counter()
    for name in args.runs:
        for mode in args.modes:
            r = measure(name, mode, args.frames, work, args.set)
            r["code"] = code
            rows.append(r)
            print(json.dumps(r, default=str), flush=True)
    new = rows[len(rows) - len(args.runs) * len(args.modes):]
    if new and not any(r.get("outcome") == "completed" for r in new):
        print(f"contact.py: error: no run completed ({new[0].get('outcome')}); {out}.md/.json left as they were",
              file=sys.stderr)
        return 3
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1, default=str))
    md = ["# Contact inside the optimisation: barrier vs post-solve stage", "",
          "Command: `python -m experiments.contact " + " ".join(argv if argv is not None else sys.argv[1:]) + "`", "",
          __doc__.split("Usage:")[0], "", md_table(COLUMNS, [table_row(r) for r in rows]), "",
          f"Total wall time {time.perf_counter() - t0:.0f} s.", "", notes]
    out.with_suffix(".md").write_text("\n".join(md))
    failed = [f"{r['run']} {r['mode']}" for r in new if r.get("outcome") != "completed"]
    if failed:
        return fail(f"{len(failed)} of {len(new)} runs failed: {', '.join(failed)} (recorded as failed in "
                    f"{out}.md/.json)")
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
