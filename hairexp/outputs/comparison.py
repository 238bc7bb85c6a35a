"""``comparison.rrd``: an experiment's variants side by side in one recording.  Only imported
when ``logging.rerun=true`` (it imports rerun).

Built after every variant ran, from their folders on disk: each variant's ``recording.rrd`` is
streamed chunk by chunk into the comparison (``rerun.chunk.RrdReader``: one chunk in memory at a
time), its entities moved under ``/runs/<variant>/`` (``/world/hair`` -> ``/runs/free/world/hair``)
and its metric series under ``/metrics/<column>/<variant>``; the layout is framed on the union of
the variants' bounds (``view.bounds`` of their ``summary.json``) and the plots are those with data
in some variant's ``metrics.parquet`` (read one column at a time).

Layout: one 3D view per variant (same camera, one shared timeline; a first tab shows every variant
fixed at the key moment, a second follows the time cursor), below them the shared plots
(kinetic energy, contacts, iterations, and for tracked variants the residual and the control
force) with one series per variant, one colour per variant (the legend on the first plot); the
time panel loops over the experiment's key moment (``rerun_sink.time_panel``).  The tracking
overlays are left out (each variant's own recording has them).
"""

from __future__ import annotations

import errno
import json
import os
import uuid
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from hairexp.errors import errno_in_text
from hairexp.outputs import layout
from hairexp.outputs.rerun_sink import (OVERLAYS, _check_complete, finish_stream, flush_recording, framing, key_view,
                                        partial_name, plot_views, time_panel)

NAME = "comparison.rrd"
#: the shared plots, one series per variant
COMPARISON_PLOTS = (
    layout.Plot("kinetic energy (J)", ("kinetic_energy",)),
    layout.Plot("contacts", ("contacts",)),
    layout.Plot("iterations", ("iterations",)),
    layout.Plot("tracking residual / hair length", ("residual_rel_max",)),
    layout.Plot("control force / hair weight", ("constraint_force_rel",)),
)
#: one colour per variant (matplotlib's tab10)
PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def run_path(variant: str, path: str) -> str:
    """Where a variant's entity goes in the comparison."""
    if path.startswith("/metrics/"):
        return f"{path}/{variant}"
    return f"/runs/{variant}{path}"


def metric_ranges(parquet: Path, columns) -> dict[str, tuple[float, float]]:
    """``{column: (min, max)}`` of the finite values of ``columns`` in a metrics table, read one
    column at a time; columns absent or without a finite value are left out."""
    out = {}
    names = set(pq.read_schema(parquet).names)
    for c in columns:
        if c not in names:
            continue
        v = pq.read_table(parquet, columns=[c]).column(c).to_numpy(zero_copy_only=False)
        try:
            v = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            continue
        v = v[np.isfinite(v)]
        if len(v):
            out[c] = (float(v.min()), float(v.max()))
    return out


def _chunks(variant: str, rrd: Path):
    """The variant's recording's chunks, moved under its paths; its static series names are
    dropped (the comparison names each series by its variant), and so are the tracking overlays
    (the comparison's views show the hair, guides and colliders; the overlays are as large as the
    hair: the variant's own recording has them)."""
    def move(c):
        path = c.entity_path
        if (path.startswith("/__properties") or (path.startswith("/metrics/") and c.is_static)
                or any(path == e or path.startswith(e + "/") for e in OVERLAYS)):
            return []
        return [c.with_entity_path(run_path(variant, path))]
    return RrdReader(rrd).stream().flat_map(move)


def _written(path: Path, call):
    """``call()``, a rerun call that writes ``path``; rerun's RuntimeError of a failed write ("Failed
    to encode LogMsg: Failed to write: No space left on device") as an OSError naming ``path``: it
    ended the experiment with a traceback, exit 1 (independent probe of issue 12, round 22)."""
    try:
        return call()
    except RuntimeError as exc:
        text = str(exc)
        if "Failed to write" not in text and "No space" not in text:
            raise
        code = errno_in_text(text)
        if code is None:
            raise OSError(errno.EIO, f"the recording could not be written: {text}", str(path)) from None
        raise OSError(code, os.strerror(code), str(path)) from None


def write_comparison(out: Path, variants: list[str], key: tuple[float, str] | None = None) -> Path | None:
    """Write ``out/comparison.rrd`` from the variant folders ``out/<variant>/`` (their
    recordings, summaries and metrics); None (nothing written) when a variant has no recording
    (``logging.rerun=false``)."""
    out = Path(out)
    folders = [out / v for v in variants]
    if not variants or not all((f / "recording.rrd").is_file() for f in folders):
        return None
    bounds, t_end = layout.Bounds(), 0.0
    for f in folders:
        view = json.loads((f / "summary.json").read_text()).get("view") or {}
        if view.get("bounds"):
            bounds = bounds.union(layout.Bounds.from_json(view["bounds"]))
        t_end = max(t_end, float(view.get("t_end") or 0.0))
    columns = {c for p in COMPARISON_PLOTS for c in p.columns}
    ranges: dict[str, tuple[float, float]] = {}
    for f in folders:
        for c, (lo, hi) in metric_ranges(f / "metrics.parquet", columns).items():
            a, b = ranges.get(c, (lo, hi))
            ranges[c] = (min(a, lo), max(b, hi))
    plots = layout.choose_plots(set(ranges), COMPARISON_PLOTS)
    path = out / NAME
    partial = Path(partial_name(str(path)))
    rec = rr.RecordingStream("hairexp", recording_id=str(uuid.uuid4()))
    _written(partial, lambda: rec.save(str(partial)))
    try:
        for i, (v, f) in enumerate(zip(variants, folders)):
            _written(partial, lambda v=v, f=f: rr.send_chunks(_chunks(v, f / "recording.rrd"), recording=rec))
            color = PALETTE[i % len(PALETTE)]
            for p in plots:
                for c in p.columns:
                    rec.log(f"/metrics/{c}/{v}", rr.SeriesLines(names=v, colors=[color]), static=True)
        plan = {"bounds": None if bounds.empty else bounds.to_json(), "t_end": t_end,
                "key": None if key is None else {"time": float(key[0]), "what": key[1]}}
        _written(partial, lambda: rec.send_blueprint(comparison_blueprint(variants, plots, ranges, plan),
                                                     make_active=True, make_default=True))
        flush_recording(rec, str(partial))
    finally:
        finish_stream(rec, str(partial))   # disconnect only after a flush that succeeded: a failed writer hangs it
    _check_complete(str(partial))
    os.replace(partial, path)
    return path


def comparison_blueprint(variants: list[str], plots, ranges: dict, plan: dict) -> rrb.Blueprint:
    """One 3D view per variant above the shared plots (``write_comparison``)."""
    n = len(variants)
    cols = n if n <= 4 else int(np.ceil(n / 2))
    aspect = 3.2 / cols if n <= 4 else 6.4 / cols   # a 3D view's width / height in a ~16:10 window
    views = [rrb.Spatial3DView(origin=f"/runs/{v}/world", name=v,
                               contents=["+ $origin/**", *(f"- /runs/{v}{e}" for e in OVERLAYS)],
                               **framing(plan, aspect=aspect)) for v in variants]
    top = rrb.Horizontal(*views, name="live") if n <= 4 else rrb.Grid(*views, grid_columns=cols, name="live")
    if plan.get("key"):   # the variants at the key moment (fixed, whatever the cursor), the tab shown first
        k = plan["key"]
        keys = [key_view(f"/runs/{v}/world", f"{v} at {k['time']:.2f} s ({k['what']})", plan, aspect,
                         exclude=[f"/runs/{v}{e}" for e in OVERLAYS]) for v in variants]
        at_key = (rrb.Horizontal(*keys, name=f"key moment: {k['what']}") if n <= 4
                  else rrb.Grid(*keys, grid_columns=cols, name=f"key moment: {k['what']}"))
        top = rrb.Tabs(at_key, top, active_tab=0)
    series = plot_views(plots, ranges, origin=lambda c: f"/metrics/{c}", legend_once=True)
    root = rrb.Vertical(top, rrb.Horizontal(*series), row_shares=[3, 2])
    return rrb.Blueprint(root, rrb.SelectionPanel(state="collapsed"), rrb.BlueprintPanel(state="collapsed"),
                         time_panel(plan), collapse_panels=False)
