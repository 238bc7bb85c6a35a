"""Compare two trees of run folders bit for bit: every ``result.npz`` array (``np.array_equal``)
and every ``metrics.parquet`` column (``Series.equals``), timing columns (``step_seconds``,
``t_*``) aside.  For refactors that must not change behaviour: run the same cases with the old
and the new code into two folders (``python -m hairexp <case> hydra.run.dir=<tree>/<name>``),
then

    python -m experiments.compare_runs <before tree> <after tree>

Prints one line per file and ``N files compared, K differ``; a file in only one of the trees
differs.  Exits 1 if any differ, 2 if none were found."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def timing(column: str) -> bool:
    return column == "step_seconds" or column.startswith("t_")


def _differences(fa: Path, fb: Path) -> list[str]:
    """The arrays or columns in which the two files differ."""
    if fa.suffix == ".npz":
        with np.load(fa) as A, np.load(fb) as B:
            diff = [k for k in A.files if k not in B.files or A[k].shape != B[k].shape
                    or not np.array_equal(A[k], B[k])]
            return diff + [k for k in B.files if k not in A.files]
    A, B = pd.read_parquet(fa), pd.read_parquet(fb)
    A = A[[c for c in A.columns if not timing(c)]]
    B = B[[c for c in B.columns if not timing(c)]]
    diff = sorted(set(A.columns) ^ set(B.columns))
    return diff + [c for c in A.columns if c in B.columns and not A[c].equals(B[c])]


def compare(a: Path, b: Path) -> tuple[int, int]:
    """(files compared, files that differ) over the run files of either tree: a file only one tree
    holds is a difference (``MISSING in <tree>``; a run only the after tree held was not seen)."""
    bad = n = 0
    rels = sorted({f.relative_to(t) for t in (a, b) for name in ("result.npz", "metrics.parquet")
                   for f in t.rglob(name)}, key=lambda r: (r.name != "result.npz", str(r)))
    for rel in rels:
        fa, fb = a / rel, b / rel
        n += 1
        missing = [t for t, f in ((a, fa), (b, fb)) if not f.exists()]
        if missing:
            print(f"MISSING in {missing[0]}:", rel)
            bad += 1
            continue
        try:
            diff = _differences(fa, fb)
        except Exception as exc:   # a corrupt or truncated file: a difference, named
            why = _unreadable(fa, fb, exc)
            print(f"UNREADABLE {rel}: {why}")
            print(f"compare_runs: {rel}: cannot be read ({why})", file=sys.stderr)
            bad += 1
            continue
        print(("DIFF " if diff else "same ") + str(rel) + (f" {diff}" if diff else ""))
        bad += bool(diff)
    return n, bad


#: the first bytes of the files compared (numpy's message for a file that is not an npz said it held
#: "pickled (object) data"; independent probe of issue 12, round 21)
_MAGIC = {".npz": (b"PK\x03\x04", "an .npz (zip) archive"), ".parquet": (b"PAR1", "a Parquet file"),
          ".json": (None, "JSON")}


def _unreadable(fa: Path, fb: Path, exc: Exception) -> str:
    """Why a pair of files could not be compared: the file that is not of its kind, or the error."""
    magic, kind = _MAGIC.get(fa.suffix, (None, None))
    if magic is not None:
        for f in (fa, fb):
            try:
                with open(f, "rb") as fh:
                    head = fh.read(len(magic))
            except OSError as e:
                return f"{f}: {e}"
            if head != magic:
                return f"{f} is not {kind} (it does not begin as one: {'empty' if not head else 'other bytes'})"
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    for p in (args.before, args.after):
        if not p.is_dir():
            print(f"compare_runs: error: {p}: not a folder", file=sys.stderr)
            return 2
    n, bad = compare(args.before, args.after)
    if n == 0:
        print(f"compare_runs: error: no run files to compare in {args.before} and {args.after}", file=sys.stderr)
        return 2
    print(f"{n} files compared, {bad} differ")
    return 1 if bad or n == 0 else 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
