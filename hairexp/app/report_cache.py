"""A result cache for slow report runs (validation issue, part 6), keyed by the config hash.

``cached(kind, key, compute, use_cache)`` stores ``compute()``'s JSON result under
``reports/cache/<kind>/<hash>.json``.  The hash covers

* ``key``: what the caller says defines the result, normally ``{"config": <the fully composed,
  resolved run config as a plain dict>}`` (its ``config_hash`` is the one ``hairexp.app.run`` records)
  plus any other input the result depends on;
* the solver source: the content of every ``hairexp/**/*.py`` and ``conf/**/*.yaml`` file, so any
  code or config change invalidates every entry;
* the torch, numpy, scipy (and Python) versions.

The file stores these key parts, the date the result was computed and the result.  Top-level
numpy arrays in the result are stored beside it as ``<hash>.npz`` and loaded back as arrays.

``use_cache=False`` (the default in the scripts: fresh runs) always computes and then refreshes
the entry; ``use_cache=True`` returns the stored result when the whole key matches.  A corrupt or
unreadable entry gives a warning and is recomputed.  Writes are atomic (a temporary file, then
``os.replace``), and nothing is written when ``compute`` raises.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import tempfile
import warnings
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from hairexp.app.run import config_hash

ROOT = Path(__file__).resolve().parents[2]
CACHE = ROOT / "reports" / "cache"
SOURCE_GLOBS = ("hairexp/**/*.py", "conf/**/*.yaml")

_source_hashes: dict[str, str] = {}


class CacheWarning(UserWarning):
    """A cache entry could not be used (it is recomputed)."""


def source_hash(root: str | Path = ROOT, globs: tuple[str, ...] = SOURCE_GLOBS, refresh: bool = False) -> str:
    """sha256 over the relative path and content of every solver source file under ``root``
    (computed once per process and root unless ``refresh``)."""
    root = Path(root)
    k = f"{root.resolve()}|{'|'.join(globs)}"
    if refresh or k not in _source_hashes:
        h = hashlib.sha256()
        files = sorted({p for g in globs for p in root.glob(g) if p.is_file()})
        for p in files:
            h.update(p.relative_to(root).as_posix().encode() + b"\0")
            h.update(hashlib.sha256(p.read_bytes()).digest())
        _source_hashes[k] = h.hexdigest()[:16]
    return _source_hashes[k]


def versions() -> dict:
    import scipy
    import torch

    return {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "torch": torch.__version__}


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _dumps(o) -> str:
    return json.dumps(o, sort_keys=True, default=_jsonable)


def full_key(key: dict, source: str | None = None) -> dict:
    """The key parts hashed: the caller's key (and its config hash), the source hash, versions."""
    parts = {"key": json.loads(_dumps(key)), "source_hash": source or source_hash(), "versions": versions()}
    if "config" in key:
        parts["config_hash"] = config_hash(key["config"])
    return parts


def key_hash(parts: dict) -> str:
    return hashlib.sha256(_dumps(parts).encode()).hexdigest()[:16]


def _atomic_write(path: Path, write: Callable[[object], None], mode: str = "w") -> None:
    """Write through a temporary file in ``path``'s folder, then rename it over ``path``."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _load(path: Path, parts: dict) -> tuple[dict, dict]:
    """The stored result and the entry's date; raises on anything unexpected."""
    entry = json.loads(path.read_text())
    if not isinstance(entry, dict) or not {"key", "date", "result"} <= entry.keys():
        raise ValueError("not a cache entry (missing key, date or result)")
    if entry["key"] != json.loads(_dumps(parts)):
        raise ValueError("stored key differs from the requested key")
    result = entry["result"]
    if not isinstance(result, dict):
        raise ValueError("result is not an object")
    arrays = entry.get("arrays") or []
    if arrays:
        with np.load(path.with_suffix(".npz"), allow_pickle=False) as z:
            for name in arrays:
                result[name] = z[name]
    return result, entry


def cached(kind: str, key: dict, compute: Callable[[], dict], use_cache: bool, *,
           cache_dir: str | Path | None = None, source: str | None = None,
           store: Callable[[dict], bool] | None = None) -> tuple[dict, dict]:
    """``(result, info)``: the stored result of ``compute()`` for ``key`` when ``use_cache`` and a
    complete, readable entry exists, else ``compute()`` (stored, unless ``store(result)`` is false).

    ``info``: ``hit`` (bool), ``hash`` (the entry's), ``config_hash`` (when ``key`` has a
    ``config``), ``source_hash``, ``date`` (when the result was computed, UTC) and ``path``.
    ``source`` replaces the source hash (tests); ``cache_dir`` replaces ``reports/cache``.
    """
    parts = full_key(key, source)
    h = key_hash(parts)
    folder = Path(cache_dir or CACHE) / kind
    path = folder / f"{h}.json"
    info = {"hit": False, "hash": h, "config_hash": parts.get("config_hash"), "source_hash": parts["source_hash"],
            "path": str(path)}
    if use_cache and path.exists():
        try:
            result, entry = _load(path, parts)
            return result, {**info, "hit": True, "date": entry["date"]}
        except Exception as exc:  # noqa: BLE001 - any unreadable entry is recomputed
            warnings.warn(f"report cache: ignoring unreadable entry {path} ({type(exc).__name__}: {exc}); "
                          "recomputing", CacheWarning, stacklevel=2)
    result = compute()
    if not isinstance(result, dict):
        raise TypeError(f"compute() must return a dict, got {type(result).__name__}")
    date = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    info["date"] = date
    if store is not None and not store(result):
        return result, {**info, "stored": False}
    arrays = {k: v for k, v in result.items() if isinstance(v, np.ndarray)}
    plain = {k: v for k, v in result.items() if k not in arrays}
    text = json.dumps({"key": parts, "hash": h, "date": date, "arrays": sorted(arrays), "result": plain},
                      indent=1, sort_keys=True, default=_jsonable)
    folder.mkdir(parents=True, exist_ok=True)
    if arrays:  # the arrays first: the JSON is the entry's commit marker
        _atomic_write(path.with_suffix(".npz"), lambda f: np.savez_compressed(f, **arrays), "wb")
    _atomic_write(path, lambda f: f.write(text))
    return {**json.loads(_dumps(plain)), **arrays}, {**info, "stored": True}


def describe(info: dict) -> str:
    """For a report: where a row's figures come from."""
    if info.get("hit"):
        return f"cached {info['date']} (entry `{info['hash']}`)"
    return "fresh"
