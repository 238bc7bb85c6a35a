"""A picture of an experiment's variants at its key moment, rendered from the run folders with
matplotlib (a dev dependency): ``render_key_moment(folder, png)``.

``folder`` is an experiment's run folder (``summary.json`` with ``variants``, one sub-folder per
variant with ``result.npz`` and ``summary.json``) or a single run's.  The key moment is the one
the recording's time panel loops over (``hairexp.evaluation.measures.experiment_key_moment``:
the tracked run's first hit, the apex, the clump time, the block leaving the rail).  One panel
per variant, side by side with the same axes: the hair at the key frame (one line per strand),
the guides (red), the colliders at their pose then (grey: the hull of their inside, sampled
through their signed distance), a dynamic block's rail.  The view is a side projection on the
vertical (y) and the horizontal axis along which the hair spreads most at the key moment.
Reads one frame of each variant's ``positions`` (``frame_of``: the npz member is decompressed
as a stream up to that frame, never held whole).

    python -m experiments.scene_pictures <folder> <out.png>
"""

from __future__ import annotations

import argparse
import json
import zipfile
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy.spatial import ConvexHull

from hairexp.evaluation.measures import experiment_key_moment, key_moment
from hairexp.model.builders import build_collider

from experiments.common import writable_file

HAIR = "#b8732e"
GUIDE = "#d62728"


def frame_of(npz: Path, key: str, f: int) -> np.ndarray:
    """Frame ``f`` of the array ``key`` (frames first, C order) of an npz: its member is read as
    a stream (decompressed up to the frame), so the other frames are never held in memory."""
    with zipfile.ZipFile(npz) as z, z.open(f"{key}.npy") as fh:
        major, _ = np.lib.format.read_magic(fh)
        read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read(fh)
        if fortran:
            raise ValueError(f"{npz}: {key} is stored in Fortran order")
        per = int(np.prod(shape[1:])) * dtype.itemsize
        fh.seek(fh.tell() + f * per)
        return np.frombuffer(fh.read(per), dtype=dtype).reshape(shape[1:]).copy()


def collider_hulls(colliders_cfg, t: float, ax_h: int, n: int = 40) -> list[np.ndarray]:
    """Each bounded collider's projected outline at time ``t`` (the convex hull of grid points
    inside it, in the plane of axes (ax_h, y))."""
    out = []
    for i, c in enumerate(colliders_cfg or []):
        col = build_collider(OmegaConf.create(c), i)
        r = float(col.bounding_radius())
        if not np.isfinite(r):
            continue
        g = np.linspace(-r, r, n)
        X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        X = X[col.sdf_body(X) <= 0]
        if len(X) < 4:
            continue
        R, T = col.motion.pose(t)
        P = (X @ np.asarray(R).T + T)[:, [ax_h, 1]]
        out.append(P[ConvexHull(P).vertices])
    return out


def describe(measure: str, m: dict) -> str:
    """A short line of a variant's measure for its panel's title."""
    if measure == "collider_contact":
        return (f"hits ({m['contacts']} contacts)" if m.get("hit")
                else f"misses by {100 * m['min_distance']:.1f} cm")
    if measure == "clumps":
        return f"{m['clumps']} clump{'s' if m['clumps'] != 1 else ''}"
    if measure == "tip_variance":
        r = m.get("cluster_variance_ratio")
        return f"tip cluster {r:.1f} v0" if r is not None else f"tip spread {m['tip_variance_ratio']:.1f} v0"
    if measure == "block_rail":
        return f"left the rail, travel {m['travel']:.2f} m" if m.get("left_rail") else "block stays on the rail"
    return ""


def render_key_moment(folder: str | Path, png: str | Path, dpi: int = 110) -> dict:
    """Render the variants of ``folder`` at the key moment into ``png``; returns what it drew
    (``key``: (time, what), ``frame``, ``variants``, ``axis``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    folder = Path(folder)
    top = json.loads((folder / "summary.json").read_text())
    measure = str(top["config"]["measure"]["name"])
    if top.get("variants"):
        names = list(top["variants"])
        runs = [folder / v for v in names]
        key = experiment_key_moment(measure, {v: top["variants"][v]["measures"] for v in names})
    else:
        names, runs = [folder.name], [folder]
        key = key_moment(measure, top.get("measures") or {})
    summaries = [json.loads((r / "summary.json").read_text()) for r in runs]
    times = np.load(runs[0] / "result.npz")["times"]
    t = float(key[0]) if key else float(times[-1])
    f = int(np.argmin(np.abs(times - t)))
    hair = [frame_of(r / "result.npz", "positions", f) for r in runs]
    guides = [frame_of(r / "result.npz", "guide_positions", f) for r in runs]
    allx = np.concatenate(hair)
    ax_h = 0 if np.ptp(allx[:, 0]) >= np.ptp(allx[:, 2]) else 2
    panels = []
    for name, r, s, x, g in zip(names, runs, summaries, hair, guides):
        npz = np.load(r / "result.npz")
        offs, goffs = npz["strand_offsets"], npz["guide_offsets"]
        hulls = collider_hulls(s["config"]["scene"].get("colliders"), float(times[f]), ax_h)
        panels.append((name, s, x, offs, g, goffs, hulls))
    pts = [allx[:, [ax_h, 1]]] + [h for p in panels for h in p[6]] + [p[4][:, [ax_h, 1]] for p in panels]
    P = np.concatenate(pts)
    lo, hi = P.min(0), P.max(0)
    pad = 0.08 * max(hi - lo)
    lo, hi = lo - pad, hi + pad
    n = len(panels)
    width = (hi[0] - lo[0]) / (hi[1] - lo[1])
    fig, axes = plt.subplots(1, n, figsize=(max(min(3.2 * width, 5.0) * n, 6.0) + 0.4, 4.1), squeeze=False)
    for ax, (name, s, x, offs, g, goffs, hulls) in zip(axes[0], panels):
        for h in hulls:
            ax.fill(h[:, 0], h[:, 1], color="0.6", alpha=0.45, ec="0.35", lw=0.8, zorder=1)
        rail = s.get("measures", {})
        if "rail_height" in rail:
            ax.plot([lo[0], rail["rail_end"]], [rail["rail_height"]] * 2, color="0.3", lw=2.5, zorder=1)
        strips = [x[a:b][:, [ax_h, 1]] for a, b in zip(offs[:-1], offs[1:])]
        ax.add_collection(LineCollection(strips, colors=HAIR, linewidths=0.7, alpha=0.85, zorder=2))
        if s.get("controller") == "tracking":
            gs = [g[a:b][:, [ax_h, 1]] for a, b in zip(goffs[:-1], goffs[1:])]
            ax.add_collection(LineCollection(gs, colors=GUIDE, linewidths=1.6, zorder=3))
        roots = x[offs[:-1]][:, [ax_h, 1]]
        ax.plot(roots[:, 0], roots[:, 1], "s", color="0.2", ms=3, zorder=4)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {describe(measure, s.get('measures') or {})}", fontsize=9)
        ax.set_xlabel(f"{'xyz'[ax_h]} (m); seen along {'xyz'[2 - ax_h]}", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("y (m)", fontsize=8)
    what = f"{key[1]} at t = {times[f]:.2f} s" if key else f"last frame, t = {times[f]:.2f} s"
    fig.suptitle(f"{top.get('experiment') or folder.name}: {what}\n(hair brown, guides red, colliders grey; "
                 "a projection: a collider may lie in front of or behind the hair)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=dpi)
    plt.close(fig)
    return {"key": key, "frame": f, "time": float(times[f]), "variants": names, "axis": "xyz"[ax_h]}


def _status(folder: Path) -> str:
    try:
        return str(json.loads((folder / "summary.json").read_text()).get("status"))
    except (OSError, ValueError, AttributeError):
        return "unreadable"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder")
    ap.add_argument("png", type=writable_file, help="the picture to write (its format from the suffix: .png, .pdf, .svg, ...)")
    args = ap.parse_args(argv)
    folder = Path(args.folder)
    if not folder.is_dir():   # a run's summary.json given: it said "not a run folder (no summary.json)" (round 30)
        ap.error(f"{args.folder}: " + ("is a file, not a folder: give the run folder that holds summary.json"
                                      if folder.exists() else "does not exist"))
    if not (folder / "summary.json").is_file():
        ap.error(f"{args.folder}: not a run folder (no summary.json)")
    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:
        ap.error("matplotlib is not installed (a dev dependency: pip install -e .[dev]): no pictures")
    suffix = args.png.suffix.lower().lstrip(".")
    if suffix:
        formats = FigureCanvasBase.get_supported_filetypes()
        if suffix not in formats:
            ap.error(f"argument png: {str(args.png)!r}: matplotlib cannot write .{suffix} (it writes "
                     f"{', '.join('.' + f for f in sorted(formats))})")
    status = _status(Path(args.folder))
    if status != "completed":   # no result.npz: a FileNotFoundError traceback (probe of issue 12)
        ap.error(f"{args.folder}: the run is {status} (summary.json), not completed: it has no results to draw")
    args.png.parent.mkdir(parents=True, exist_ok=True)
    info = render_key_moment(args.folder, args.png)
    print(f"wrote {args.png}: {info}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
