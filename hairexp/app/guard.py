"""The resource guard: before a run builds anything big, estimate its memory, its disk and its
step count from the config alone, refuse what cannot fit in the machine's available memory or in
the free space of the run folder's disk (an InputError naming the keys that size the run, unless
``guard.allow_large=true``) and log a warning with the estimated steps and time of a long run.

The estimate (``estimate``, a pure function) is

    memory = (V + Vg) x BYTES_PER_VERTEX                  (state, banded Hessian, energies' stencils,
                                                           torch buffers of the closed forms, ...)
           + (frames + 1) x BYTES_PER_FRAME               (what still grows with the frames: the USD
                                                           crate layer's index of its time samples)
    disk   = (frames + 1) x (V + Vg) x DISK_BYTES_PER_VERTEX_FRAME + steps x DISK_BYTES_PER_STEP
           + with the recording on: RECORDING_BYTES + (frames + 1) x (V + Vg) x RECORDING_BYTES_PER_VERTEX_FRAME
             + steps x RECORDING_BYTES_PER_STEP (+ (frames + 1) x RECORDING_BYTES_PER_TRACKED_FRAME tracked)
    time   = (steps + settle steps) x (SECONDS_PER_STEP + V x SECONDS_PER_VERTEX_STEP)

(V hair vertices, Vg vertices of a simulated guide animation).  Frames and metrics rows are
streamed to the run folder while the run goes (hairexp/app/run.py), so memory is flat in the
frames (reports/bench_memory.md: +2 to +3 MB from 200 to 3,000 frames, about 1 kB a frame of which
the crate index is 0.2-0.5 kB) and a long run's cost is disk: the streamed positions (float64, 24 B
a vertex a frame) while it runs, result.npz (at most as much again) and result.usdc (float32, 12 B,
plus the crate's saves), about 70 B a vertex a frame in all, and ~110 B of metrics.parquet a step.

Constants measured on this project's goaling_smoke scene (controller free, ``logging.rerun=false``,
peak RSS from ``/usr/bin/time -v``, 2 cores): 20 000 vertices peaked at 683 MB and 50 000 at
819 MB (2 frames; 4.5 kB per vertex, rounded up to 6 kB for hair-hair lists and the tracking's KKT
blocks: 20 000 tracked vertices peaked at 694 MB).  A step took 4 ms at 10 vertices and 0.18 s at
20 000 (9 us per vertex).
"""

from __future__ import annotations

from contextlib import contextmanager

import logging
import math
import os
from dataclasses import dataclass, replace

import numpy as np

from hairexp.errors import InputError, choice_name
from hairexp.physics.collisions import bounding_spheres, edge_boxes
from hairexp.physics.settle import settle_seconds, settle_step

log = logging.getLogger(__name__)

BYTES_PER_VERTEX = 6_000
BYTES_PER_FRAME = 1_000
DISK_BYTES_PER_VERTEX_FRAME = 72
DISK_BYTES_PER_STEP = 200
#: recording.rrd (logging.rerun=true): goaling_smoke's free run (90 vertices with the guides) wrote
#: 767 kB at 200 frames and 4.83 MB at 3,000, 16 B a vertex a frame over about 480 kB of metrics,
#: layout and static entities; celia_smoke's (360 + 78 vertices, 30 frames) 649 kB.  It was left out,
#: and an experiment's second variant was refused for want of disk after the first had run (round 24)
RECORDING_BYTES = 650_000
RECORDING_BYTES_PER_VERTEX_FRAME = 16
#: the recording's per-step plots (the metrics' scalars): goaling_smoke at 40 frames wrote 536 / 759 /
#: 1,486 kB at dt 0.04 / 0.004 / 0.001 free (617 B a step), 756 / 1,012 kB at dt 0.04 / 0.004 tracked
#: (709 B); a 4,000-step run's recording passed the estimate by 1.4 MB and filled the disk after
#: every step had run (independent probe of issue 12, round 26).  Rounded up; then 760 since the two
#: contact-plane columns (2026-12-07): goaling_smoke tracked at dt 0.001 wrote 1,138,143 B against an
#: estimate of 1,138,120 with 720, the timings' compression varying by some bytes from run to run
RECORDING_BYTES_PER_STEP = 760
#: a tracked run's per-frame targets, clusters and constraint plots: goaling_smoke tracked wrote 3.5 kB
#: a frame, free 1.5 kB (80 against 40 frames at dt 0.04); its base was 614 kB against free's 477 kB
RECORDING_BYTES_PER_TRACKED_FRAME = 3_000
SECONDS_PER_STEP = 4e-3
SECONDS_PER_VERTEX_STEP = 1e-5
#: runs with more steps (settle phases included), or estimated to take longer (s), are announced
#: with a warning (a run of 1M vertices and 4,000 steps, about 5.6 h, was not: probe of issue 12)
LONG_RUN_STEPS = 100_000
LONG_RUN_SECONDS = 600.0
#: a run estimated to take more than this share of the available memory is announced as large
LARGE_RUN_SHARE = 0.25


@dataclass(frozen=True)
class Estimate:
    memory: float        # bytes beyond the interpreter's own
    disk: float          # bytes the run folder's files take (the stream while it runs, then the results)
    steps: int           # recorded steps of the run (frames x steps per frame)
    settle_steps: int    # steps of the settle phases and of a guide simulation
    seconds: float       # rough wall time of all steps

    @property
    def total_steps(self) -> int:
        return self.steps + self.settle_steps


def estimate(n_vertices: int, frames: int, steps_per_frame: int, settle_steps: int = 0,
             guide_vertices: int = 0, guide_steps: int = 0) -> Estimate:
    """The memory and time of a run of ``n_vertices`` hair vertices over ``frames`` frames of
    ``steps_per_frame`` steps, after ``settle_steps`` settle steps; ``guide_steps`` steps of a
    guide simulation of ``guide_vertices`` vertices (``guides.source=simulated``)."""
    steps = int(frames) * int(steps_per_frame)
    memory = float(n_vertices + guide_vertices) * BYTES_PER_VERTEX + (frames + 1.0) * BYTES_PER_FRAME
    disk = (frames + 1.0) * float(n_vertices + guide_vertices) * DISK_BYTES_PER_VERTEX_FRAME + float(steps) * DISK_BYTES_PER_STEP
    seconds = ((steps + settle_steps) * (SECONDS_PER_STEP + n_vertices * SECONDS_PER_VERTEX_STEP)
               + guide_steps * (SECONDS_PER_STEP + guide_vertices * SECONDS_PER_VERTEX_STEP))
    return Estimate(memory, disk, steps, int(settle_steps) + int(guide_steps), seconds)


def available_memory() -> float | None:
    """Bytes the machine can still give a process: MemAvailable of /proc/meminfo, else the free
    physical pages (os.sysconf); None when neither is known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def total_memory() -> float | None:
    """Bytes of memory and swap the process could ever have: MemTotal + SwapTotal of
    /proc/meminfo, at most a cgroup's memory limit (cgroup v2 memory.max, v1
    memory.limit_in_bytes); None when unknown."""
    total = None
    try:
        with open("/proc/meminfo") as f:
            fields = {line.split(":")[0]: float(line.split()[1]) * 1024.0 for line in f if ":" in line}
        if "MemTotal" in fields:
            total = fields["MemTotal"] + fields.get("SwapTotal", 0.0)
    except (OSError, ValueError, IndexError):
        pass
    for limit in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(limit) as f:
                value = f.read().strip()
            if value.isdigit() and int(value) < (1 << 60):
                total = float(value) if total is None else min(total, float(value))
                break
        except OSError:
            continue
    return total


def available_disk(folder) -> float | None:
    """Free bytes of the disk holding ``folder`` (its nearest existing ancestor), or None."""
    import shutil
    from pathlib import Path

    p = Path(folder).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return float(shutil.disk_usage(p).free)
    except OSError:
        return None


def run_folder() -> str | None:
    """The Hydra job's output folder (the run folder), or None outside a Hydra job."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return str(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else None
    except Exception:   # noqa: BLE001  (no Hydra, or no job: no folder to check)
        return None


def _size(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def _duration(s: float) -> str:
    if s >= 86400:
        return f"{s / 86400:.3g} days"
    if s >= 3600:
        return f"{s / 3600:.3g} h"
    if s >= 60:
        return f"{s / 60:.3g} min"
    return f"{s:.3g} s"


#: a run estimated to take longer than this (s) is refused unless guard.allow_large
MAX_RUN_SECONDS = 7 * 86400.0


def check(est: Estimate, keys: str, allow_large: bool, available: float | None, disk_free: float | None = None,
          folder: str | None = None, total: float | None = None, planned: float = 0.0) -> None:
    """Refuse ``est`` when it needs more than ``available`` bytes of memory or ``disk_free`` bytes
    of the disk of ``folder`` (an InputError naming ``keys``, the config keys that size the run),
    unless ``allow_large``; warn about a long run.  More than ``total`` bytes (the machine's memory
    and swap, ``total_memory``) is refused even with ``allow_large``: such a run can only end
    killed by the out-of-memory killer, its summary left running (probe of issue 12, round 13)."""
    def refuse(msg: str, kind: str) -> None:
        _refuse(msg, keys, kind, allow_large, folder)

    if allow_large and total is not None and est.memory > total:
        raise InputError(f"the run would need about {_size(est.memory)} of memory, more than the machine has "
                         f"({_size(total)} of memory and swap): guard.allow_large=true cannot make it fit; make it smaller",
                         keys)

    if available is not None and est.memory > available:
        refuse(f"the run would need about {_size(est.memory)} of memory ({est.steps:.3g} steps, "
               f"{est.total_steps:.3g} with settle and guide-simulation steps) but {_size(available)} is available; make it smaller "
               "or set guard.allow_large=true to run anyway", "memory")
    if disk_free is not None and est.disk + planned > disk_free:
        shared = (f", {_size(planned)} of it for the experiment's variants checked before this one" if planned > 0
                  else "")
        refuse(f"the run's files would take about {_size(est.disk)} of disk ({est.steps:.3g} steps; "
               f"{DISK_BYTES_PER_VERTEX_FRAME} B a vertex a frame) but {_size(disk_free)} is free"
               f"{f' where {folder} is' if folder else ''}{shared}; make it smaller or shorter, or set "
               "guard.allow_large=true to run anyway", "disk")
    if est.seconds > MAX_RUN_SECONDS:
        refuse(f"the run would take roughly {_duration(est.seconds)} (about {est.total_steps:.3g} steps, "
               f"{est.settle_steps:.3g} of them settle and guide steps), more than {_duration(MAX_RUN_SECONDS)}; "
               "make it shorter or set guard.allow_large=true to run anyway", "time")
    # a run that fits but takes a large share of the memory is said too: 200,000 strands (about 12 GB of
    # 22 GB available, 4 minutes for 20 steps) started without a word (independent probe of issue 12, round 30)
    large = available is not None and est.memory > LARGE_RUN_SHARE * available
    if est.total_steps > LONG_RUN_STEPS or est.seconds > LONG_RUN_SECONDS or large:
        said = (f"{'large' if large else 'long'} run: about {est.total_steps:.3g} steps ({est.steps:.3g} recorded, "
                f"{est.settle_steps:.3g} settle and guide steps), roughly {_duration(est.seconds)} ({keys}: "
                f"{_size(est.memory)} of memory")
        # once per process: an experiment checks each variant before any runs, then runs it; the memory
        # available is not part of what was said (it changed between a run's check and its run, and a
        # large run was announced twice; independent probe of issue 12, round 32)
        if said not in _ANNOUNCED:
            _ANNOUNCED.add(said)
            log.warning("%s", said + (f", of {_size(available)} available)" if large else ")"))


def _refuse(msg: str, keys: str, kind: str, allow_large: bool, folder: str | None = None) -> None:
    """An InputError naming ``keys``, or with ``allow_large`` a warning, said once a run (its
    checks and its run both estimate it)."""
    if not allow_large:
        raise InputError(msg, keys)
    if (keys, kind, folder) not in _ANNOUNCED:
        _ANNOUNCED.add((keys, kind, folder))
        log.warning("%s: %s (guard.allow_large=true: running anyway)", keys, msg)


#: the long-run warnings (their text) and allow_large warnings already logged by this process
_ANNOUNCED: set = set()   # allow_large warnings: (keys, kind, the run folder)


#: the disk (bytes) of the runs checked before this one in the same launch while ``planning()`` is
#: on: an experiment's variants share its folder's disk, and each was checked alone (the second of
#: two variants that fitted one at a time was refused after the first had run; independent probe
#: of issue 12, round 24)
_PLANNED: list | None = None


@contextmanager
def planning():
    """Runs checked inside this block are checked together against the disk: each run's estimate
    is added to the ones checked before it.  Yields the list of their estimates (``Estimate``), in
    the order they were checked."""
    global _PLANNED
    old, _PLANNED = _PLANNED, []
    try:
        yield _PLANNED
    finally:
        _PLANNED = old


def guard_run(cfg, n_vertices: int, steps_per_frame: int, run: bool = True) -> Estimate:
    """Estimate and check the run of ``cfg`` (frames and fps known, keys validated) with
    ``n_vertices`` hair vertices; ``run=False`` (the USD export): the scene and guides are built
    but neither settled nor stepped."""
    seconds, dt = settle_seconds(cfg.scene), settle_step(cfg.scene)
    hair_settle = max(1, int(math.ceil(seconds / dt - 1e-9))) if seconds > 0 else 0   # as settle_state counts
    g = cfg.guides
    simulated = choice_name(g.source) == "simulated"
    gv = int(g.count) * int(g.n_vertices) if simulated else 0
    gsteps = int(cfg.frames) * steps_per_frame + hair_settle if simulated else 0   # the guides settle too
    frames = int(cfg.frames) if run else 0
    est = estimate(n_vertices, frames, steps_per_frame, hair_settle if run else 0, gv, gsteps)
    if run and bool(getattr(getattr(cfg, "logging", None), "rerun", False)):
        vertices = float(n_vertices + int(g.count) * int(g.n_vertices))
        tracked = choice_name(cfg.controller.name) != "free"
        per_frame = vertices * RECORDING_BYTES_PER_VERTEX_FRAME + (RECORDING_BYTES_PER_TRACKED_FRAME if tracked else 0)
        est = replace(est, disk=est.disk + RECORDING_BYTES + (frames + 1.0) * per_frame
                      + est.steps * RECORDING_BYTES_PER_STEP)
    keys = "scene.usd" if choice_name(cfg.scene.builder) == "usd" else "scene.n_strands x scene.n_vertices"
    keys += ", frames, solver.dt" + (", scene.settle" if hair_settle else "")
    folder = run_folder() if run else None
    planned = sum(e.disk for e in _PLANNED) if _PLANNED is not None else 0.0
    check(est, keys, bool(getattr(getattr(cfg, "guard", None), "allow_large", False)), available_memory(),
          None if folder is None else available_disk(folder), folder, total_memory(), planned)
    if _PLANNED is not None and run:
        _PLANNED.append(est)
    return est


#: bytes a candidate edge pair of the exact hair-hair broad phase takes at its peak (scipy's pair
#: list, the index arrays, masks and closest-point parameters): measured 50-59 B on goaling's bundle
#: (1,000 strands: +0.50 GB for 8.5 M pairs; 3,000: +3.85 GB for 76 M pairs), rounded up.  The
#: compiled grid (physics/broad_phase.py, since 2026-12-06) holds at most 48 B a pair (its doubling
#: buffer of int64 pairs, up to twice the pairs, and the trimmed copy it returns): the bound stays
#: conservative
HAIR_HAIR_BYTES_PER_PAIR = 64
#: pairs within a sphere of radius d per pair of the same cell of side d (uniform density: 4.19 / 2),
#: calibrated against scipy's exact count_neighbors on goaling's bundle (1,000-30,000 strands: x 1.47)
_PAIRS_PER_CELL_PAIR = 3.1


def hair_hair_pairs(rest: np.ndarray, edges: np.ndarray, radius: float) -> float:
    """About how many edge pairs the exact hair-hair broad phase (physics/collisions.py,
    ``HairHair._pairs``) lists for the hair at ``rest``: boxes of the edges grown by
    ``radius`` (thickness + skin), whose bounding spheres' centres are binned into cells of their
    largest query distance; O(edges), where an exact count is quadratic in a dense bundle."""
    c, r = bounding_spheres(*edge_boxes(rest[edges[:, 0]], rest[edges[:, 1]], radius))
    if len(c) < 2:
        return 0.0
    _, counts = np.unique(np.floor(c / (2.0 * float(r.max()))).astype(np.int64), axis=0, return_counts=True)
    n = float(len(c))
    return min(_PAIRS_PER_CELL_PAIR * float(np.sum(counts.astype(np.float64) ** 2)), n * (n - 1) / 2)


def guard_hair_hair(cfg, rest: np.ndarray, edges: np.ndarray) -> None:
    """Refuse exact hair-hair contact (``collision.hair_hair=true``, ``hair_hair_model=edges``) whose
    broad phase cannot fit in memory, unless ``guard.allow_large`` (more than the machine's memory
    and swap: always).  30,000 strands in goaling's 2 cm bundle started without a word and reached
    12.4 GB before scipy's bad_alloc (about 7.6e9 pairs; independent probe of issue 12, round 33)."""
    cc = cfg.collision
    if not bool(cc.hair_hair) or choice_name(cc.hair_hair_model) != "edges" or \
            choice_name(cfg.controller.name) == "skinned":
        return
    pairs = hair_hair_pairs(rest, edges, float(cc.hair_thickness) + float(cc.skin))
    need = pairs * HAIR_HAIR_BYTES_PER_PAIR
    available, total = available_memory(), total_memory()
    allow = bool(getattr(getattr(cfg, "guard", None), "allow_large", False))
    keys = "collision.hair_hair"
    what = (f"exact hair-hair contact lists about {pairs:.3g} candidate edge pairs of this hair (edges whose boxes, "
            f"grown by collision.hair_thickness + collision.skin, overlap), about {_size(need)} of memory")
    fix = ("use collision.hair_hair_model=volume (the grid model, memory linear in the hair), fewer strands "
           "(scene.n_strands) or a wider bundle")
    if total is not None and need > total:
        raise InputError(f"{what}, more than the machine has ({_size(total)} of memory and swap): {fix}", keys)
    if available is not None and need > available:
        _refuse(f"{what} but {_size(available)} is available: {fix}, or set guard.allow_large=true to run anyway", keys,
                "hair-hair memory", allow)
