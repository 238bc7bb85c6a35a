"""The rerun recording of a run.  Only imported when ``logging.rerun=true``.

Entities: /world/hair (line strips), /world/body (rigid body transform and box), /world/rail
(a dynamic body's rail),
/world/roots (root vertices), /clusters/variance_ratio (one series per cluster, tracked runs),
/metrics/<name> (scalars on the ``frame``, ``sim_time`` and ``step`` timelines).  Each recording
has an explicit recording id, so parallel workers never share one.

Its layout (``blueprint(plan)``) is sent once, when the run ends (``close``): only then are the
bounds of every frame (grown frame by frame in ``log_frame``), the metrics with data and their
ranges and the key moment (from the measure, passed by the app) known; see
``hairexp.outputs.layout`` and the README's "Looking at a run".

The recording is written while the run goes to ``recording.partial.rrd`` (rerun's file sink).
rerun's file writer keeps one row of its footer's index per chunk until the file is closed
(about 1.3 kB each while the file is written, 3.2 kB at the close's peak, when the footer is
built; rerun 0.41, experiments/rrd_index_memory.py), so the sink keeps the number of
chunks few, whatever the number of frames:
- the metrics go to the recording when the run ends, read back column by column from the
  metrics table (``close(metrics=...)``; ``MetricColumns.numeric``, a row group at a time) and
  written every METRICS_FLUSH_BYTES: one chunk per metric, whatever the run's length (before,
  every send of the step's scalars was one chunk per metric, about 140 chunks);
- the per-cluster variance ratios are one entity (a series per cluster), not one per cluster;
- the frames are sent as columns (``FrameColumns``, held as contiguous arrays, no Python object
  per frame): a chunk of an entity every 1 MiB or 250 frames of its own rows, and of every
  entity at ``flush()``, which also
  waits for the writer (so a write failure such as a full disk raises there instead of passing
  silently) at most every FLUSH_SECONDS.
rerun's SDK allocates from its own mimalloc heap; ``MIMALLOC_PURGE_DELAY=0`` (set in
hairexp/__init__.py before rerun loads) makes it give freed pages back at once, so the encoded chunks'
pages do not pile up (reports/bench_memory.md).
``close(True)`` renames the file to ``recording.rrd`` once it is complete (its footer read back);
a failed or interrupted run keeps the ``.partial.rrd`` name (a valid recording of the steps done,
with the metrics of the steps done).
"""

from __future__ import annotations

import atexit
import errno
import logging
import os
import resource
import shutil
import sys
import time
import uuid
from typing import NamedTuple
from array import array

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from hairexp.guides import spline
from hairexp.memory import release
from hairexp.outputs import layout

#: ``flush()`` waits for the file writer (and so ends a chunk of every entity) at most this often (s)
FLUSH_SECONDS = 10.0
#: s, the longest a flush waits for rerun's file writer.  On a disk that filled up, the writer
#: thread sometimes stopped without waking the flush that waited for it, and the run hung in
#: ``flush`` (SIGTERM could not end it: the main thread waited in rerun's code; probe of issue 12,
#: round 9).  Past this, the recording is given up as unwritable (OSError), and the stream is
#: abandoned without ``disconnect`` or rerun's exit handler, which would wait for the same writer.
FLUSH_TIMEOUT_SECONDS = 60.0
#: recording streams given up on (their writer stuck): kept alive so that no finaliser waits for it
_ABANDONED: list = []


def abandoned(rec) -> bool:
    """``rec`` was given up by ``flush_recording`` (its file writer did not finish)."""
    return any(r is rec for r in _ABANDONED)


def flush_recording(rec, partial: str) -> None:
    """Wait (at most FLUSH_TIMEOUT_SECONDS) until rerun's file writer holds everything sent to
    ``rec``; OSError naming the file ``partial`` when it cannot: the writer stopped (a full disk)
    or did not finish in time.  On any failure the stream is given up (``abandoned``): neither
    ``disconnect`` nor rerun's exit handler (``rerun_shutdown``) runs for it, since both wait for
    the writer without a limit, and a writer that stopped on an error sometimes never answers
    (``disconnect`` hung for ever after ``File too large``; probe of issue 12, round 17).  Callers
    end a stream with ``finish_stream``."""
    if abandoned(rec):
        raise OSError(f"{partial}: the recording could not be written (rerun's file writer is stuck)")
    waited = 0.0
    while True:   # in slices: a full disk is told at once, not after the whole time-out
        wait = min(FLUSH_SLICE_SECONDS, FLUSH_TIMEOUT_SECONDS - waited)
        try:
            rec.flush(timeout_sec=wait)
            return
        except RuntimeError as exc:   # rerun's file writer stopped, or not done yet
            free = _free_bytes(partial)
            capped = _size_capped(partial)
            timed_out = "timed out" in str(exc).lower()
            full = free is not None and free < DISK_FULL_BYTES
            if timed_out and capped is None and not full and waited + wait < FLUSH_TIMEOUT_SECONDS:
                waited += wait
                continue
            _abandon(rec)
            cause = _disk_error(partial, capped, free, f"rerun: {exc}")
            if cause is not None:
                raise cause from exc
            if not timed_out:
                raise OSError(f"{partial}: the recording could not be written ({exc})") from exc
            raise OSError(f"{partial}: the recording could not be written (rerun's file writer did not finish "
                          f"within {FLUSH_TIMEOUT_SECONDS:g} s: {exc})") from exc


def _disk_error(path: str, capped: int | None, free: int | None, said: str) -> OSError | None:
    """The recording ``path`` could not be written because of its disk: the file-size limit
    reached (``capped``, ``_size_capped``: EFBIG; probe of issue 12, round 14) or the disk full
    (``free`` below DISK_FULL_BYTES: ENOSPC; round 12), with ``said`` (what rerun or the check said),
    or None.  rerun's writer only logs these: the disk is what the run's error names."""
    if capped is not None:
        return OSError(errno.EFBIG, f"{path}: the recording could not be written: it reached the process's "
                                    f"file-size limit ({capped} bytes, ulimit -f; {said})")
    if free is not None and free < DISK_FULL_BYTES:
        return OSError(errno.ENOSPC, f"{path}: the recording could not be written: no space left on the device "
                                     f"({free} bytes free; {said})")
    return None


def _abandon(rec) -> None:
    """Give ``rec`` up: kept alive (no finaliser waits for its writer), rerun's exit handler off.
    In a sweep's worker process, which ends through the interpreter's own exit (the command line
    ends with ``os._exit``), the stream's finaliser then waited for the stuck writer when the
    module was torn down: the sweep had said its closing line and hung for ever (independent
    probe of issue 12, round 24); the worker ends at its exit handlers instead (``_exit_at_exit``)."""
    global _EXIT_REGISTERED
    if not abandoned(rec):
        _ABANDONED.append(rec)
    rr.unregister_shutdown()
    mp = sys.modules.get("multiprocessing")
    if not _EXIT_REGISTERED and mp is not None and mp.parent_process() is not None:
        _EXIT_REGISTERED = True
        atexit.register(_exit_at_exit)


_EXIT_REGISTERED = False


def _exit_at_exit() -> None:
    """The last exit handler of a worker process with an abandoned stream (registered last, run
    first): the log files closed and the streams flushed, then ``os._exit`` before the
    interpreter's teardown, whose finalisers would wait for the stuck writer."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(0)


def finish_stream(rec, partial: str) -> None:
    """End the recording stream ``rec`` (file ``partial``): ``disconnect`` only after a bounded
    flush that succeeded (``flush_recording``); a stream whose writer failed or is stuck is
    abandoned instead, and the file stays incomplete (its footer is missing; ``_check_complete``)."""
    if abandoned(rec):
        return
    try:
        flush_recording(rec, partial)
    except OSError:   # abandoned by flush_recording; the caller's own error (or _check_complete) tells it
        return
    rec.disconnect()


#: ``flush_recording`` waits in slices this long, looking at the disk between them (s)
FLUSH_SLICE_SECONDS = 2.0
#: fewer free bytes than this on the recording's disk while its writer is not done: the disk is full
DISK_FULL_BYTES = 64 << 10


def _size_capped(path: str) -> int | None:
    """The file-size limit (RLIMIT_FSIZE, bytes) when the file ``path`` has reached it, else None."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft == resource.RLIM_INFINITY or soft <= 0:
            return None
        return int(soft) if os.path.getsize(path) >= soft - (64 << 10) else None
    except (OSError, ValueError):
        return None


def _free_bytes(path: str) -> int | None:
    """Bytes free to this process on the disk holding ``path`` (None if it cannot be told)."""
    try:
        return shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free
    except OSError:
        return None
#: metric rows per chunk when the metrics are sent at the end (a chunk per metric per this many steps)
METRICS_CHUNK_ROWS = 1 << 18
#: ``send_metrics`` waits for the writer after this many bytes of sent columns, so that what rerun
#: holds until written stays small whatever the run's length (before: every 16 columns, about
#: 1.5 MB at 3,000 steps)
METRICS_FLUSH_BYTES = 256 << 10

#: the entities a tracked run draws over the hair: shown in a 3D view of their own ("tracking")
OVERLAYS = ("/world/clusters", "/world/com", "/world/targets", "/world/target_curves")
#: the time panel's timeline (a duration: plays in real time)
TIMELINE = "sim_time"


def framing(plan: dict | None, aspect: float):
    """The eye framed on ``plan['bounds']`` (``layout.frame_camera``) and a floor grid at the
    bottom of the bounds with a spacing at the scene's scale; rerun's defaults without a plan."""
    if not plan or plan.get("bounds") is None:
        return {}
    b = layout.Bounds.from_json(plan["bounds"])
    if b.empty:
        return {}
    eye, target, up = layout.frame_camera(b, aspect=aspect)
    return {"eye_controls": rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye, look_target=target,
                                               eye_up=up),
            "line_grid": rrb.LineGrid3D(visible=True, spacing=layout.grid_spacing(b),
                                        plane=rr.components.Plane3D((0.0, 1.0, 0.0), float(b.lo[1])),
                                        color=[128, 128, 128, 90])}


def plot_views(plots, ranges: dict, origin=lambda col: f"/metrics/{col}", legend_once: bool = False):
    """One TimeSeriesView per ``layout.Plot``: its columns' series (``origin(col)`` and below),
    a y range from the data (``ranges[col] = (min, max)``), and a legend only where a plot has
    more than one series (``legend_once``: on the first plot only, the comparison's variants)."""
    views = []
    for i, p in enumerate(plots):
        lo = min((ranges[c][0] for c in p.columns if c in ranges), default=None)
        hi = max((ranges[c][1] for c in p.columns if c in ranges), default=None)
        several = (i == 0) if legend_once else len(p.columns) > 1
        views.append(rrb.TimeSeriesView(
            origin="/", contents=[f"+ {origin(c)}/**" for c in p.columns], name=p.title,
            axis_y=rrb.ScalarAxis(range=layout.axis_range(lo, hi)) if lo is not None else None,
            plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True) if several else rrb.PlotLegend(visible=False)))
    return views


#: half-width (s) of the time range a key-moment view shows: the one frame logged at the key time
KEY_FRAME_EPS = 1e-6


def key_view(origin: str, name: str, plan: dict, aspect: float, exclude=()):
    """A 3D view of ``origin`` fixed at the key moment (``plan['key']``), whatever the time
    cursor: its visible time range on ``TIMELINE`` is the key frame's time +- KEY_FRAME_EPS (the
    key times of the measures are frame times).  The body is left out: rerun resolves transforms
    at the cursor, not at the view's time range (hair, guides and roots are logged in world
    coordinates; the paper scenes' colliders that matter do not move)."""
    t = float(plan["key"]["time"])
    rng = rr.VisibleTimeRange(TIMELINE, start=rr.TimeRangeBoundary.absolute(seconds=t - KEY_FRAME_EPS),
                              end=rr.TimeRangeBoundary.absolute(seconds=t + KEY_FRAME_EPS))
    return rrb.Spatial3DView(origin=origin, name=name, time_ranges=[rng],
                             contents=["+ $origin/**", "- $origin/body/**", *(f"- {e}" for e in exclude)],
                             **framing(plan, aspect=aspect))


def time_panel(plan: dict | None):
    """The time panel on ``TIMELINE``.  rerun 0.41 has no blueprint property for the time cursor
    (the TimePanel sets the timeline, play state, loop mode, speed and a time selection only),
    so the key moment is the time selection and the panel plays, looping over it: the cursor
    runs from the start to the key moment and then stays around it until paused."""
    key = (plan or {}).get("key")
    if not key:
        return rrb.TimePanel(state="collapsed", timeline=TIMELINE)
    lo, hi = layout.key_window(key["time"], plan["t_end"])
    return rrb.TimePanel(state="expanded", timeline=TIMELINE, play_state="playing", loop_mode="selection",
                         time_selection=rrb.components.AbsoluteTimeRange(min=rr.encodings.TimeInt(seconds=lo),
                                                                            max=rr.encodings.TimeInt(seconds=hi)))


def blueprint(plan: dict | None = None) -> rrb.Blueprint:
    """The recording's layout.  Without ``plan`` (while the run goes): the 3D view beside the
    step's basic plots.  With ``plan`` (the finished run: ``bounds``, ``plots`` (layout.Plot),
    ``ranges``, ``tracked``, ``key``, ``t_end``): the 3D view framed on the whole run's bounds
    with a floor grid, for a tracked run a second 3D view of the tracking overlays (clusters,
    centres of mass, targets, target curves), the plots that have data, and a second tab with
    every metric that has data; the selection and blueprint panels closed; the time panel
    looping over the key moment (``time_panel``)."""
    plan = plan or {}
    tracked = bool(plan.get("tracked"))
    plots = plan.get("plots") or layout.choose_plots({"kinetic_energy", "potential_energy", "contacts", "iterations"})
    ranges = plan.get("ranges", {})
    hair = rrb.Spatial3DView(origin="/world", name="hair", contents=["+ $origin/**", *(f"- {e}" for e in OVERLAYS)],
                             **framing(plan, aspect=1.2 if tracked else 2.6))
    views = [hair]
    if tracked:
        views.append(rrb.Spatial3DView(origin="/world", name="tracking: clusters, centres of mass, targets",
                                       contents=["+ /world/colliders/**", "+ /world/body/**",
                                                 *(f"+ {e}" for e in OVERLAYS)], **framing(plan, aspect=1.2)))
    if (plan or {}).get("key"):   # the run at its key moment, whatever the time cursor
        k = plan["key"]
        views.append(key_view("/world", f"key moment: {k['what']} at {k['time']:.2f} s", plan,
                              aspect=1.2 if tracked else 1.3, exclude=OVERLAYS))
        if not tracked:
            views[0] = rrb.Spatial3DView(origin="/world", name="hair",
                                         contents=["+ $origin/**", *(f"- {e}" for e in OVERLAYS)],
                                         **framing(plan, aspect=1.3))
    # the 3D views on top, the plots side by side below them (each about 300 px tall in a 1000 px window)
    review = rrb.Vertical(rrb.Horizontal(*views), rrb.Horizontal(*plot_views(plots, ranges)), row_shares=[3, 2],
                          name="review")
    parts = [review]
    every = sorted(plan.get("with_data", ()))
    if every:
        singles = [layout.Plot(c, (c,)) for c in every]
        parts.append(rrb.Grid(*plot_views(singles, ranges), grid_columns=4, name="all metrics"))
        if tracked:
            parts[-1] = rrb.Grid(*plot_views(singles, ranges),
                                 rrb.TimeSeriesView(origin="/clusters", name="cluster variance / target",
                                                    plot_legend=rrb.PlotLegend(visible=False)),
                                 grid_columns=4, name="all metrics")
    root = rrb.Tabs(*parts, active_tab=0) if len(parts) > 1 else review
    return rrb.Blueprint(root, rrb.SelectionPanel(state="collapsed"), rrb.BlueprintPanel(state="collapsed"),
                         time_panel(plan), collapse_panels=False)


def partial_name(path: str) -> str:
    """``recording.rrd`` -> ``recording.partial.rrd`` (the name while it is written)."""
    root, ext = os.path.splitext(path)
    return f"{root}.partial{ext}"


#: the frames are sent as columns: an entity's pending rows go as one chunk once they hold this
#: many bytes or frames (or at a flush).  rerun's file writer keeps an index row of about 1.3 kB per
#: chunk until it writes the footer (3.2 kB at that peak; experiments/rrd_index_memory.py), so the
#: number of chunks is what grows with the run's length, and the pending rows are what the sink
#: holds (at most about this much per entity, whatever the length).  Each entity counts its own rows: a small entity
#: (the body, the roots) is not sent each time the hair fills its chunk.  Larger chunks cost more
#: than their index saves: at 2 MiB or 1,000 frames the peak of 40 x 20 hair rose 1.7 MB at 200
#: frames and 2.3 MB at 3,000 (README, "Benchmarks", memory against run length)
FRAME_CHUNK_BYTES = 1 << 20
FRAME_CHUNK_FRAMES = 250


class _Rows:
    """Rows appended to one contiguous numpy array (doubling as it fills): a frame's field costs
    its bytes, not a numpy object of its own.  ``take()`` hands the filled rows over and starts a
    new array: rerun may still read a sent column's buffer (it wraps numpy memory without
    copying, and writes the file on its own thread), so a buffer is never written again once sent."""

    __slots__ = ("a", "n")

    def __init__(self):
        self.a, self.n = None, 0

    def append(self, v: np.ndarray) -> None:
        if self.a is None:
            self.a = np.empty((max(16, 4 * len(v)),) + v.shape[1:], v.dtype)
        elif v.shape[1:] != self.a.shape[1:]:
            raise ValueError(f"rows of shape {v.shape[1:]} after rows of shape {self.a.shape[1:]}")
        end = self.n + len(v)
        if end > len(self.a):
            grown = np.empty((max(end, 2 * len(self.a)),) + self.a.shape[1:], self.a.dtype)
            grown[:self.n] = self.a[:self.n]
            self.a = grown
        self.a[self.n:end] = v
        self.n = end

    def take(self) -> np.ndarray:
        out = self.a[:self.n] if self.a is not None else np.empty((0,))
        self.a, self.n = None, 0
        return out


class Strips(NamedTuple):
    """Line strips given as one (P, 3) array of their points, one strip after another, and each
    strip's point count: ``FrameColumns.add``'s ``strips`` field without the list of arrays (the
    hair's 301 strips were split from one array a frame only to be joined again: 0.37 s of Celia's
    run, 2026-12-06)."""
    points: np.ndarray
    lengths: np.ndarray


class FrameColumns:
    """The frames' entities as columns (``RecordingStream.send_columns``): per entity, its rows
    since the last send on the ``frame`` and ``sim_time`` timelines, sent as one chunk each.

    ``add(path, archetype, constant, **fields)``: one row of ``path`` at the current ``frame``;
    ``fields`` are the archetype's fields of that row as arrays (first axis: its instances; a
    ``strips`` field is a list of strips), ``constant`` the fields that never change (radii,
    colours: logged once, static).  The rows are copied into one growing array per field
    (``_Rows``) and the indexes into typed arrays: the pending frames hold their bytes and no
    Python object per frame (a list of small arrays held about 4 kB a frame of 6 x 10 hair, the
    data 1.3 kB).  rerun's own per-call logging batches rows too, but holds about a kilobyte per
    row and call until its batch is sent, and ends a chunk at every flush."""

    def __init__(self, rec, max_bytes: int = FRAME_CHUNK_BYTES, max_frames: int = FRAME_CHUNK_FRAMES):
        self.rec = rec
        self.max_bytes, self.max_frames = max_bytes, max_frames
        self.entities: dict[str, dict] = {}
        self.static: set[str] = set()
        self.current = (0, 0.0)

    def frame(self, frame: int, t: float) -> None:
        self.current = (int(frame), float(t))

    def add(self, path: str, archetype, constant: dict | None, **fields) -> None:
        if constant and path not in self.static:
            self.rec.log(path, archetype.from_fields(**constant), static=True)
            self.static.add(path)
        e = self.entities.get(path)
        if e is None:
            e = self.entities[path] = {"archetype": archetype, "frame": array("q"), "time": array("d"),
                                       "length": array("q"), "strip_length": array("q"),
                                       "fields": {k: _Rows() for k in fields}, "bytes": 0}
        if set(e["fields"]) != set(fields):
            raise ValueError(f"{path}: fields {sorted(fields)} differ from this entity's {sorted(e['fields'])}")
        n = None
        for k, v in fields.items():
            if k == "strips" and isinstance(v, Strips):   # already one array: no split and re-join
                e["strip_length"].extend(v.lengths)
                m, v = len(v.lengths), np.asarray(v.points)
            elif k == "strips":
                e["strip_length"].extend(len(s) for s in v)
                m, v = len(v), (np.concatenate(v) if len(v) else np.empty((0, 3), np.float32))
            else:
                v = np.asarray(v)
                m = len(v)
            if n is not None and m != n:
                raise ValueError(f"{path}: field {k} has {m} instances, {n} expected")
            n = m
            e["fields"][k].append(v)
            e["bytes"] += v.nbytes
        e["frame"].append(self.current[0])
        e["time"].append(self.current[1])
        e["length"].append(n)
        e["bytes"] += 24

    @property
    def bytes(self) -> int:
        """The bytes pending over all entities."""
        return sum(e["bytes"] for e in self.entities.values())

    def send_if_due(self) -> None:
        """Send each entity whose pending rows reached ``max_bytes`` or ``max_frames``."""
        for path, e in self.entities.items():
            if e["bytes"] >= self.max_bytes or len(e["frame"]) >= self.max_frames:
                self._send(path, e)

    def send(self) -> None:
        """Every entity's pending rows as one chunk each."""
        for path, e in self.entities.items():
            self._send(path, e)

    def _send(self, path: str, e: dict) -> None:
        if len(e["frame"]):
            data = {}
            for k, rows in e["fields"].items():
                v = rows.take()
                if k == "strips":
                    lengths = np.frombuffer(e["strip_length"], np.int64)
                    if lengths.size and lengths[0] > 0 and (lengths == lengths[0]).all():
                        # strips of one length as one (strips, points, 3) array: the SDK's numpy path
                        # gives the same arrow array as a list of strips, which it converted strip by
                        # strip (Celia's 301 x 26 hair: 0.1 s a chunk, 3.3 s of the experiment)
                        v = v.reshape(-1, int(lengths[0]), 3)
                    else:
                        v = np.split(v, np.cumsum(lengths)[:-1])
                data[k] = v
            self.rec.send_columns(path, indexes=[rr.TimeColumn("frame", sequence=np.frombuffer(e["frame"], np.int64)),
                                                 rr.TimeColumn("sim_time", duration=np.frombuffer(e["time"], np.float64))],
                                  columns=e["archetype"].columns(**data).partition(np.frombuffer(e["length"], np.int64)))
            for k in ("frame", "time", "length", "strip_length"):
                e[k] = array(e[k].typecode)
            e["bytes"] = 0


#: The SDK's chunk batcher (only the static entities and the layout go through it now) flushes
#: every FLUSH_TICK_SECONDS (its default is 0.2 s) or at 2 MiB, whichever first.
FLUSH_TICK_SECONDS = 2.0


class RerunSink:
    def __init__(self, path: str, scene, application_id: str = "hairexp", recording_id: str | None = None,
                 strict: bool = False):
        if strict:
            rr.set_strict_mode(True)
        self.path = path
        self.partial = partial_name(path)
        self.recording_id = recording_id or str(uuid.uuid4())
        batcher = None   # RERUN_FLUSH_TICK_SECS set: the SDK's own reading of it
        if "RERUN_FLUSH_TICK_SECS" not in os.environ:
            batcher = rr.ChunkBatcherConfig.DEFAULT()
            batcher.flush_tick = FLUSH_TICK_SECONDS
        self.rec = rr.RecordingStream(application_id, recording_id=self.recording_id, batcher_config=batcher)
        # the layout is sent at the end (``close``): one blueprint per file, framed on the whole run
        self.rec.save(self.partial)
        self.flushed = time.monotonic()
        self.columns = FrameColumns(self.rec)
        self.scene = scene
        self.strip_lengths = scene.strands.counts     # the hair's strips (``Strips``)
        self._quats: dict = {}                         # key -> (rotation matrix bytes, quaternion) (``_quaternion``)
        self.bounds = layout.Bounds()          # of everything drawn, over the whole run
        self.ranges: dict[str, tuple[float, float]] = {}   # metric -> (min, max) of its finite values
        self.t_end = 0.0
        self.tracker = None
        rec = self.rec
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        L = float(np.median(scene.strands.strand_lengths()))
        self.radius = 0.004 * L
        self.body_half = 0.5 * L * 0.1
        rec.log("/world/body/box", rr.Boxes3D(half_sizes=[[self.body_half] * 3], colors=[[180, 180, 190]]), static=True)
        body = scene.motion
        if hasattr(body, "rail_end"):  # a dynamic block (scene.body): its rail, ending at rail_end
            h, e = body.rail_height, body.rail_end
            rec.log("/world/rail", rr.LineStrips3D([[[min(body.p0[0], e) - 2 * L, h, 0.0], [e, h, 0.0]]],
                                                   radii=2 * self.radius, colors=[[90, 90, 90]]), static=True)

    def log_static(self, guides, controller=None) -> None:
        """Collider shapes (in their body frames) and, for a controller with clusters (tracking),
        cluster colours (vertices coloured by cluster, grey when in none; soft assignment: the
        colours of a vertex's clusters mixed by its shares)."""
        from scipy.spatial.transform import Rotation

        z_to_y = Rotation.from_rotvec([-np.pi / 2, 0, 0]).as_quat()    # rerun's capsule/cylinder axis is +z
        grey = [[120, 160, 200, 160]]
        for c in self.scene.colliders:
            kind = type(c).__name__.lower()
            path = f"/world/colliders/{c.name}"
            if kind == "sphere":
                arch = rr.Ellipsoids3D(half_sizes=[[c.radius] * 3], colors=grey)
            elif kind == "capsule":
                arch = rr.Capsules3D(lengths=[2 * c.half_length], radii=[c.radius],
                                     translations=[[0, -c.half_length, 0]], quaternions=[z_to_y], colors=grey)
            elif kind == "cylinder":
                arch = rr.Cylinders3D(lengths=[2 * c.half_height], radii=[c.radius], centers=[[0, 0, 0]],
                                      quaternions=[z_to_y], colors=grey)
            elif kind == "box":
                arch = rr.Boxes3D(half_sizes=[list(c.half_extents)], colors=grey)
            else:  # plane: a large thin slab below body y = 0
                arch = rr.Boxes3D(half_sizes=[[1.0, 0.0005, 1.0]], centers=[[0, -0.0005, 0]], colors=grey)
            self.rec.log(path, arch, static=True)
        tracker = controller if controller is not None and controller.cluster_of_vertex() is not None else None
        self.tracker = tracker
        self.guide_lengths = np.diff(guides.offsets)
        if tracker is not None:
            K = tracker.cons.K
            rng = np.random.default_rng(7)
            self.cluster_colors = (60 + 195 * rng.random((K, 3))).astype(np.uint8)
            self.cluster_share = tracker.cluster_weights()
            if self.cluster_share is None:
                cov = tracker.corr.cluster_of_vertex
                vc = np.where(cov[:, None] >= 0, self.cluster_colors[np.maximum(cov, 0)], 150)
            else:   # soft assignment: the clusters' colours mixed by the vertex's shares
                W = self.cluster_share
                vc = np.where(W.sum(1)[:, None] > 0, W @ self.cluster_colors, 150)
            self.vertex_colors = vc.astype(np.uint8)
            self.rec.log("/clusters/variance_ratio", rr.SeriesLines(names=[f"cluster {k}" for k in range(K)],
                                                                    colors=self.cluster_colors), static=True)

    def _quaternion(self, key: str, R: np.ndarray) -> np.ndarray:
        """Rotation matrix R as a quaternion (x, y, z, w), the last one of ``key`` again while R
        is the same (a still collider's or body's pose: scipy's from_matrix took 0.31 s of Celia's run)."""
        from scipy.spatial.transform import Rotation

        b = np.ascontiguousarray(R, dtype=np.float64).tobytes()
        hit = self._quats.get(key)
        if hit is None or hit[0] != b:
            hit = self._quats[key] = (b, Rotation.from_matrix(R).as_quat())
        return hit[1]

    def log_frame(self, frame: int, state, obs: dict | None = None, motion=None) -> None:
        """One frame; ``motion``: the body's poses at ``state.time`` (``Simulator.motion_of``),
        default the scene's motion.  The frame goes to the entities' columns (``FrameColumns``),
        sent as one chunk per entity every FRAME_CHUNK_BYTES, FRAME_CHUNK_FRAMES or FLUSH_SECONDS."""
        obs = obs or {}
        cols = self.columns
        cols.frame(frame, float(state.time))
        x = state.x.astype(np.float32)
        cols.add("/world/hair", rr.LineStrips3D, dict(radii=self.radius, colors=[[200, 150, 90]]),
                 strips=Strips(x, self.strip_lengths))
        cols.add("/world/roots", rr.Points3D, dict(radii=1.5 * self.radius, colors=[[60, 60, 200]]),
                 positions=x[self.scene.strands.kinematic])
        R, T = (motion or self.scene.motion).pose(state.time)
        cols.add("/world/body", rr.Transform3D, None, translation=np.asarray(T, np.float64)[None],
                 quaternion=self._quaternion("/world/body", R)[None])   # x, y, z, w
        self.t_end = max(self.t_end, float(state.time))
        self.bounds.add(state.x)
        self.bounds.add_sphere(T, np.sqrt(3) * self.body_half)
        for c in self.scene.colliders:
            Rc, Tc = c.motion.pose(state.time)
            if np.isfinite(c.bounding_radius()):   # a plane is unbounded: it does not frame the view
                self.bounds.add_sphere(Tc, c.bounding_radius())
            cols.add(f"/world/colliders/{c.name}", rr.Transform3D, None, translation=np.asarray(Tc, np.float64)[None],
                     quaternion=self._quaternion(f"/world/colliders/{c.name}", Rc)[None])
        if obs.get("guides") is not None:
            self.bounds.add(obs["guides"])
            cols.add("/world/guides", rr.LineStrips3D, dict(radii=1.5 * self.radius, colors=[[230, 60, 60]]),
                     strips=Strips(obs["guides"].astype(np.float32), self.guide_lengths))
        if getattr(self, "tracker", None) is not None and obs.get("com") is not None:
            tr = self.tracker
            # the overlays have a 3D view of their own ("tracking"): cluster colours as points on
            # the vertices (``log_static``), centres of mass as solid points inside their targets' wire boxes
            cols.add("/world/clusters", rr.Points3D, dict(radii=self.radius, colors=self.vertex_colors), positions=x)
            cols.add("/world/com", rr.Points3D, dict(radii=1.5 * self.radius, colors=self.cluster_colors),
                     positions=obs["com"].astype(np.float32))
            tg_pts = obs["targets"].astype(np.float32)
            cols.add("/world/targets", rr.Boxes3D, dict(radii=0.3 * self.radius, colors=[[255, 255, 255]]),
                     centers=tg_pts, half_sizes=np.full_like(tg_pts, 3 * self.radius))
            ratios = obs.get("variance_ratios")
            if ratios is not None and len(ratios):   # one entity, a series per cluster (NaN: a gap)
                cols.add("/clusters/variance_ratio", rr.Scalars, None, scalars=np.asarray(ratios, dtype=np.float64))
            tg = tr.targets_at(state.time, motion)
            if tr.cons.soft:   # soft assignment: each cluster's curve is a blend over the guides
                L = max(float(s[-1]) for s in tg.knots)
                pts = np.stack([tr.cons.target_points(tg, np.full(tr.cons.K, u)) for u in np.linspace(0.0, L, 24)], 1)
                cols.add("/world/target_curves", rr.LineStrips3D, dict(radii=0.5 * self.radius),
                         strips=list(pts.astype(np.float32)), colors=self.cluster_colors)
            else:
                curves = []
                for Q, s, ks in zip(tg.control, tg.knots, tg.clusters):
                    tt = torch.linspace(float(s[0]), float(s[-1]), 24, dtype=torch.float64)
                    for j in range(len(ks)):
                        curves.append(spline.evaluate(Q[j:j + 1].expand(len(tt), -1, -1), s, tt).numpy().astype(np.float32))
                cols.add("/world/target_curves", rr.LineStrips3D, dict(radii=0.6 * self.radius),
                         strips=curves, colors=self.cluster_colors[np.concatenate(tg.clusters)])
        cols.send_if_due()

    def send_metrics(self, metrics) -> None:
        """The metrics table's numeric and boolean columns as scalars on the step, frame and
        sim_time timelines, one column at a time (``metrics``: ``columns`` and ``[name]``, a
        ``MetricColumns`` or a pandas DataFrame); each metric's finite range is kept for the layout."""
        if metrics is None or len(metrics) == 0 or not all(c in metrics.columns for c in ("step", "frame", "time")):
            return
        steps = np.asarray(metrics["step"], dtype=np.int64)
        frames = np.asarray(metrics["frame"], dtype=np.int64)
        times = np.asarray(metrics["time"], dtype=np.float64)
        rec = self.rec
        pending = 0
        for k in metrics.columns:
            if k in ("step", "frame", "time"):
                continue
            if pending >= METRICS_FLUSH_BYTES:   # the columns sent so far written, their memory back to the system
                self.flush(final=True)
                release()
                pending = 0
            vals = _numeric(metrics, k)
            if vals is None:
                continue   # text (controller, status)
            finite = vals[np.isfinite(vals)]
            if len(finite):
                self.ranges[k] = (float(finite.min()), float(finite.max()))
            rec.log(f"/metrics/{k}", rr.SeriesLines(names=k), static=True)
            for a in range(0, len(vals), METRICS_CHUNK_ROWS):
                b = a + METRICS_CHUNK_ROWS
                idx = [rr.TimeColumn("step", sequence=steps[a:b]), rr.TimeColumn("frame", sequence=frames[a:b]),
                       rr.TimeColumn("sim_time", duration=times[a:b])]
                rec.send_columns(f"/metrics/{k}", indexes=idx, columns=rr.Scalars.columns(scalars=vals[a:b]))
            pending += 32 * len(vals)   # the value and its three indexes, 8 bytes each
        self.flush(final=True)
        release()

    def flush(self, final: bool = False) -> None:
        """Wait until the file holds everything logged (a write failure raises OSError), at most
        every FLUSH_SECONDS or when ``final``: each wait ends a chunk of every entity, and the
        writer keeps an index entry per chunk until it writes the file's footer."""
        if not final and time.monotonic() - self.flushed < FLUSH_SECONDS:
            return
        self.columns.send()
        flush_recording(self.rec, self.partial)
        self.flushed = time.monotonic()

    @property
    def stuck(self) -> bool:
        """The file writer did not finish a flush in time: the stream was given up."""
        return abandoned(self.rec)

    def plan(self, key: tuple[float, str] | None = None) -> dict:
        """What the finished run's layout shows (``blueprint(plan)``): the bounds of every frame
        drawn, the plots with data and their ranges, whether the run is tracked, the key moment
        ``(time s, what)`` (from the scene's measure, ``evaluation.measures.key_moment``)."""
        with_data = set(self.ranges)
        return {"bounds": None if self.bounds.empty else self.bounds.to_json(),
                "plots": layout.choose_plots(with_data), "with_data": sorted(with_data), "ranges": dict(self.ranges),
                "tracked": self.tracker is not None, "t_end": self.t_end,
                "key": None if key is None else {"time": float(key[0]), "what": key[1]}}

    def close(self, success: bool, key: tuple[float, str] | None = None, metrics=None) -> dict | None:
        """Send the metrics (``send_metrics(metrics)``, the run's metrics table), flush, finish
        the file and, when ``success``, send the final layout (``plan(key)``, made the
        recording's default and active blueprint) and give the file its final name (after
        reading its footer back: a recording that did not finish stays ``.partial.rrd``).
        Returns the layout's facts for the summary (``view``: bounds, key moment), or None."""
        facts = None
        try:
            if success:
                self.send_metrics(metrics)
                self.flush(final=True)
                plan = self.plan(key)
                self.rec.send_blueprint(blueprint(plan), make_active=True, make_default=True)
                facts = {"bounds": plan["bounds"], "key": plan["key"], "t_end": plan["t_end"]}
                self.flush(final=True)
            else:   # a partial recording: the metrics of the steps done, the layout without the key moment
                self.columns.send()
                self.send_metrics(metrics)
                self.rec.send_blueprint(blueprint(self.plan()), make_active=True, make_default=True)
        finally:
            finish_stream(self.rec, self.partial)
        if success:
            _check_complete(self.partial)   # a full disk or the file-size limit named (round 25)
            os.replace(self.partial, self.path)
        elif os.path.isfile(self.partial):
            # a partial recording is kept as a valid recording of the steps done; one its writer could
            # not finish (a full disk) ends mid-message, and nothing said so (independent probe, round 23)
            try:
                _check_complete(self.partial)
            except OSError:
                raise OSError(f"{self.partial}: cut short where its writer failed (no rerun footer: a full disk?); "
                              "rerun shows the data before that point") from None
        return facts


def _numeric(metrics, k: str):
    """Column ``k`` of a metrics table as float64, None if it is not numeric or boolean: read a
    row group at a time from a ``MetricColumns`` (``numeric``), or converted from a DataFrame."""
    if hasattr(metrics, "numeric"):
        return metrics.numeric(k)
    import pandas as pd

    col = metrics[k]
    if not (pd.api.types.is_bool_dtype(col) or pd.api.types.is_numeric_dtype(col)):
        return None
    return np.asarray(col.astype("float64"), dtype=np.float64)


#: how a complete .rrd file ends (rerun 0.41's stream footer: the magic, then a version word)
FOOTER_MAGIC = b"RRF2FOOT"


def _check_complete(path: str) -> None:
    """OSError unless ``path`` ends with rerun's stream footer (the writer finished the file).
    Only the file's last bytes are read: a long recording is checked without loading its index."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError as exc:
        raise OSError(f"{path}: the recording cannot be read back ({exc})") from exc
    if FOOTER_MAGIC not in tail[-16:]:
        # the writer stopped where the disk filled, without an error of its own: the cause named (round
        # 25, a run's recording; round 27, an experiment's comparison.rrd)
        said = f"{path}: the recording is incomplete (no rerun stream footer at its end)"
        raise _disk_error(path, _size_capped(path), _free_bytes(path), said) or OSError(said)
