"""The stylization scene's measure (paper 4, Fig. 7): "a wisp of hair attached to a rigid block
resting on a rail ... a keyframe animation of a single guide hair that pulls itself off the rail by
building up the necessary momentum".

``block_rail_measure`` reads the block's position per frame (``result.npz`` ``body_positions``:
the pose translation, i.e. the block's rail contact point, hairexp/model/dynamic_body.py) and
reports how far it travelled along the rail (x) and whether and when it left the rail: past the
rail's end in x, or below the rail's height, by more than ``tolerance``.

    python -m hairexp.evaluation.stylization <run or experiment folder> [...]

prints, per run, the measure with the rail of the run's config (``scene.body``) and the run's
figures (steps, SQP/Newton iterations, tracking residual, cluster variance range).  An
experiment's folder (``python -m hairexp experiment=stylization``: its variants ``free`` and
``tracked`` in subfolders) stands for its variants' run folders, in the experiment's order.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from hairexp.errors import InputError

#: Default tolerance (m): a block counts as off the rail beyond this distance past its end or below it.
TOLERANCE = 1e-3


def block_rail_measure(times, body_positions, rail_height: float, rail_end: float,
                       tolerance: float = TOLERANCE) -> dict:
    """``times`` (F,) s and ``body_positions`` (F, 3) m of the block's rail contact point.

    ``travel``: the largest |x - x_0| along the rail (m); ``travel_end``: x at the last frame
    minus x_0; ``left_rail``: whether in some frame x > rail_end + tolerance or
    y < rail_height - tolerance; ``left_rail_time``: the first such frame's time (s, None if it
    stayed); ``lift_max``: the highest the block rose above the rail (m); ``drop``: how far below
    the rail it ended (m, >= 0)."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    P = np.asarray(body_positions, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] != t.size or t.size == 0:
        raise InputError(f"need body positions (F, 3) for F = {t.size} times, got shape {P.shape}", "body_positions")
    if not (np.isfinite(P).all() and np.isfinite(t).all()):
        raise InputError("body positions and times must be finite", "body_positions")
    for key, v in (("rail_height", rail_height), ("rail_end", rail_end), ("tolerance", tolerance)):
        if not math.isfinite(float(v)):
            raise InputError(f"must be finite, got {v}", key)
    if not tolerance >= 0:
        raise InputError(f"must be >= 0, got {tolerance}", "tolerance")
    x, y = P[:, 0], P[:, 1]
    off = (x > rail_end + tolerance) | (y < rail_height - tolerance)
    first = int(np.argmax(off)) if off.any() else None
    return {
        "travel": float(np.max(np.abs(x - x[0]))),
        "travel_end": float(x[-1] - x[0]),
        "left_rail": bool(off.any()),
        "left_rail_time": None if first is None else float(t[first]),
        "lift_max": float(max(0.0, np.max(y - rail_height))),
        "drop": float(max(0.0, rail_height - y[-1])),
        "rail_height": float(rail_height), "rail_end": float(rail_end), "tolerance": float(tolerance),
    }


def run_report(run_dir) -> dict:
    """The measure and the run's figures from a run folder (result.npz, metrics.parquet,
    summary.json)."""
    import pandas as pd

    d = Path(run_dir)
    try:   # a missing or foreign folder: named, not a traceback (probe of issue 12, round 15)
        summary = json.loads((d / "summary.json").read_text())
        body = summary["config"]["scene"]["body"]
        res = np.load(d / "result.npz")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not a finished run folder (summary.json with its config, result.npz): "
                         f"{type(exc).__name__}: {exc}", str(d)) from exc
    if not body.get("dynamic"):   # a keyframed body has no rail: its "rail" figures were the defaults' (round 15)
        raise InputError("its body is keyframed (scene.body.dynamic=false): it has no rail to measure; give a "
                         "stylization run's folder", str(d))
    if "body_positions" not in res:
        raise InputError("result.npz has no body_positions (a run from before they were recorded)", str(d))
    out = block_rail_measure(res["times"], res["body_positions"], body["rail_height"], body["rail_end"])
    m = pd.read_parquet(d / "metrics.parquet")
    out.update({
        "controller": summary["controller"], "dynamic": bool(body["dynamic"]), "mass": body["mass"],
        "rail_friction": body["rail_friction"], "steps": int(len(m)),
        "iterations_mean": float(m["iterations"].mean()), "iterations_max": int(m["iterations"].max()),
        "converged_fraction": float(m["converged"].mean()), "stretch_max": float(m["stretch_max"].max()),
        "wall_seconds": summary.get("wall_seconds"),
    })
    if m["residual_rel_max"].notna().any():
        v = m["variance_ratio_mean"]
        out.update({"residual_rel_max": float(m["residual_rel_max"].max()),
                    "residual_max": float(m["residual_max"].max()),
                    "variance_ratio_min": float(v.min()), "variance_ratio_max": float(v.max()),
                    "variance_ratio_std": float(v.std())})
    return out


def run_folders(path) -> list[Path]:
    """The run folders ``path`` stands for: itself when it holds a run's result (or is no
    experiment's folder: ``run_report`` then says what is missing), else, for an experiment's
    folder (its summary.json lists ``variants``), each variant's subfolder in the experiment's
    order (the README's stylization commands ran an experiment of two variants into one folder,
    which was refused as "not a finished run folder")."""
    d = Path(path)
    if (d / "result.npz").is_file():
        return [d]
    try:
        variants = json.loads((d / "summary.json").read_text()).get("variants")
    except (OSError, ValueError, AttributeError):
        return [d]
    if not isinstance(variants, dict) or not variants:
        return [d]
    return [d / str(name) for name in variants]


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    usage = "usage: " + next(line.strip() for line in __doc__.splitlines() if "python -m hairexp.evaluation" in line)
    if any(a in ("-h", "--help") for a in args):
        print(usage)
        return 0
    if not args or any(a.startswith("-") for a in args):   # a usage error: exit 2, as the other commands
        bad = next((a for a in args if a.startswith("-")), None)
        print(f"hairexp: error: {'unknown option ' + bad if bad else 'a run folder is required'} ({usage})",
              file=sys.stderr)
        return 2
    for a in args:
        for d in run_folders(a):
            try:
                print(json.dumps({"run": str(d), **run_report(d)}, indent=1))
            except InputError as exc:
                print(f"hairexp: error: {exc}", file=sys.stderr)
                return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
