"""The rerun recording of a run.  Only imported when ``logging.rerun=true``.

Entities: /world/hair (line strips), /world/body (rigid body transform and box), /world/rail
(a dynamic body's rail),
/world/roots (root vertices), /metrics/<name> (scalars on the ``frame``, ``sim_time`` and
``step`` timelines).  Each recording has an explicit recording id, so parallel workers never
share one.

Its layout (``blueprint(plan)``) is sent once, when the run ends (``close``): only then are the
bounds of every frame (grown frame by frame in ``log_frame``), the metrics with data and their
ranges (``on_step``) and the key moment (from the measure, passed by the app) known; see
``hairexp.outputs.layout`` and the README's "Looking at a run".

The recording is written while the run goes to ``recording.partial.rrd`` (rerun's file sink);
``flush()`` sends the metric scalars gathered since the last flush and waits for the writer,
so a write failure (a full disk) raises there instead of passing silently.  ``close(True)``
renames the file to ``recording.rrd`` once it is complete (its footer read back); a failed or
interrupted run keeps the ``.partial.rrd`` name (a valid recording of the steps done).
"""

from __future__ import annotations

import os
import time
import uuid

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from hairexp.guides import spline
from hairexp.outputs import layout

#: the metric scalars go to the recording at most this often (s), or every this many steps
METRICS_SECONDS = 10.0
METRICS_STEPS = 1000

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


#: The SDK's chunk batcher flushes every 2 s (its default is 0.2 s) or at 2 MiB, whichever first.
#: The file sink keeps one index entry per chunk until it writes the footer, so fewer, larger chunks
#: keep a long run's memory flatter: 6 x 10 goaling_smoke, 200 -> 3,000 frames, recording on:
#: +12.1 MB at 0.2 s against +7.0 MB at 2 s, where the same runs with the recording off (untouched by
#: this) grew +4.1 and +5.2 MB; one machine, one hour (experiments/bench_memory.py).
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
        self.metrics_sent = time.monotonic()
        self.scene = scene
        self.offsets = scene.strands.offsets
        self.scalars: dict[str, list] = {}   # since the last flush
        self.named: set[str] = set()           # metric series given their name
        self.steps, self.frames, self.times = [], [], []
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
        self.guide_offsets = guides.offsets
        if tracker is not None:
            K = tracker.cons.K
            rng = np.random.default_rng(7)
            self.cluster_colors = (60 + 195 * rng.random((K, 3))).astype(np.uint8)
            self.cluster_share = tracker.cluster_weights()

    def log_frame(self, frame: int, state, obs: dict | None = None, motion=None) -> None:
        """One frame; ``motion``: the body's poses at ``state.time`` (``Simulator.motion_of``),
        default the scene's motion."""
        obs = obs or {}
        rec = self.rec
        rec.set_time("frame", sequence=frame)
        rec.set_time("sim_time", duration=state.time)
        strips = np.split(state.x.astype(np.float32), self.offsets[1:-1])
        rec.log("/world/hair", rr.LineStrips3D(strips, radii=self.radius, colors=[[200, 150, 90]]))
        roots = state.x[self.scene.strands.kinematic]
        rec.log("/world/roots", rr.Points3D(roots.astype(np.float32), radii=1.5 * self.radius, colors=[[60, 60, 200]]))
        R, T = (motion or self.scene.motion).pose(state.time)
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
        rec.log("/world/body", rr.Transform3D(translation=T, quaternion=q))
        self.t_end = max(self.t_end, float(state.time))
        self.bounds.add(state.x)
        self.bounds.add_sphere(T, np.sqrt(3) * self.body_half)
        for c in self.scene.colliders:
            Rc, Tc = c.motion.pose(state.time)
            if np.isfinite(c.bounding_radius()):   # a plane is unbounded: it does not frame the view
                self.bounds.add_sphere(Tc, c.bounding_radius())
            rec.log(f"/world/colliders/{c.name}", rr.Transform3D(translation=Tc, quaternion=Rotation.from_matrix(Rc).as_quat()))
        if obs.get("guides") is not None:
            g = np.split(obs["guides"].astype(np.float32), self.guide_offsets[1:-1])
            self.bounds.add(obs["guides"])
            rec.log("/world/guides", rr.LineStrips3D(g, radii=1.5 * self.radius, colors=[[230, 60, 60]]))
        if getattr(self, "tracker", None) is not None and obs.get("com") is not None:
            tr = self.tracker
            # the overlays have a 3D view of their own ("tracking"): cluster colours as points on
            # the vertices, centres of mass as solid points inside their targets' wire boxes
            if self.cluster_share is None:
                cov = tr.corr.cluster_of_vertex
                cols = np.where(cov[:, None] >= 0, self.cluster_colors[np.maximum(cov, 0)], 150).astype(np.uint8)
            else:   # soft assignment: the clusters' colours mixed by the vertex's shares
                W = self.cluster_share
                cols = np.where(W.sum(1)[:, None] > 0, W @ self.cluster_colors, 150).astype(np.uint8)
            rec.log("/world/clusters", rr.Points3D(state.x.astype(np.float32), radii=self.radius, colors=cols))
            rec.log("/world/com", rr.Points3D(obs["com"].astype(np.float32), radii=1.5 * self.radius,
                                              colors=self.cluster_colors))
            tg_pts = obs["targets"].astype(np.float32)
            rec.log("/world/targets", rr.Boxes3D(centers=tg_pts, half_sizes=np.full_like(tg_pts, 3 * self.radius),
                                                 radii=0.3 * self.radius, colors=[[255, 255, 255]]))
            for k, v in enumerate(obs.get("variance_ratios", [])):
                if np.isfinite(v):
                    rec.log(f"/clusters/variance_ratio/{k}", rr.Scalars(float(v)))
            tg = tr.targets_at(state.time, motion)
            if tr.cons.soft:   # soft assignment: each cluster's curve is a blend over the guides
                L = max(float(s[-1]) for s in tg.knots)
                pts = np.stack([tr.cons.target_points(tg, np.full(tr.cons.K, u)) for u in np.linspace(0.0, L, 24)], 1)
                rec.log("/world/target_curves", rr.LineStrips3D(list(pts.astype(np.float32)), radii=0.5 * self.radius,
                                                                colors=self.cluster_colors))
                return
            curves = []
            for Q, s, ks in zip(tg.control, tg.knots, tg.clusters):
                tt = torch.linspace(float(s[0]), float(s[-1]), 24, dtype=torch.float64)
                for j in range(len(ks)):
                    curves.append(spline.evaluate(Q[j:j + 1].expand(len(tt), -1, -1), s, tt).numpy().astype(np.float32))
            rec.log("/world/target_curves", rr.LineStrips3D(curves, radii=0.6 * self.radius,
                                                            colors=self.cluster_colors[np.concatenate(tg.clusters)]))

    def on_step(self, row: dict, state) -> None:
        self.steps.append(row["step"])
        self.frames.append(row["frame"])
        self.times.append(row["time"])
        for k, v in row.items():
            if isinstance(v, (bool, np.bool_)):
                v = float(v)
            if isinstance(v, (int, float, np.integer, np.floating)) and k not in ("step", "frame", "time"):
                v = float(v)
                self.scalars.setdefault(k, []).append(v)
                if np.isfinite(v):
                    lo, hi = self.ranges.get(k, (v, v))
                    self.ranges[k] = (min(lo, v), max(hi, v))

    def _send_metrics(self) -> None:
        """The scalars since the last call as columns on the step, frame and sim_time timelines."""
        rec = self.rec
        if self.steps:
            idx = [rr.TimeColumn("step", sequence=self.steps), rr.TimeColumn("frame", sequence=self.frames),
                   rr.TimeColumn("sim_time", duration=self.times)]
            for k, vals in self.scalars.items():
                rec.send_columns(f"/metrics/{k}", indexes=idx, columns=rr.Scalars.columns(scalars=np.asarray(vals)))
                if k not in self.named:
                    rec.log(f"/metrics/{k}", rr.SeriesLines(names=k), static=True)
                    self.named.add(k)
        self.steps, self.frames, self.times, self.scalars = [], [], [], {}

    def flush(self, final: bool = False) -> None:
        """Wait until the file holds everything logged (a write failure raises OSError); the
        pending metrics are sent at most every METRICS_SECONDS or METRICS_STEPS steps, and when
        ``final``: each send is one chunk per metric, and the SDK keeps an index entry per chunk
        until it writes the file's footer (memory that grew with the run's length)."""
        if final or len(self.steps) >= METRICS_STEPS or time.monotonic() - self.metrics_sent >= METRICS_SECONDS:
            self._send_metrics()
            self.metrics_sent = time.monotonic()
        try:
            self.rec.flush()
        except RuntimeError as exc:   # rerun's file writer stopped (e.g. no space left on the device)
            raise OSError(f"{self.partial}: the recording could not be written ({exc})") from exc

    def plan(self, key: tuple[float, str] | None = None) -> dict:
        """What the finished run's layout shows (``blueprint(plan)``): the bounds of every frame
        drawn, the plots with data and their ranges, whether the run is tracked, the key moment
        ``(time s, what)`` (from the scene's measure, ``evaluation.measures.key_moment``)."""
        with_data = set(self.ranges)
        return {"bounds": None if self.bounds.empty else self.bounds.to_json(),
                "plots": layout.choose_plots(with_data), "with_data": sorted(with_data), "ranges": dict(self.ranges),
                "tracked": self.tracker is not None, "t_end": self.t_end,
                "key": None if key is None else {"time": float(key[0]), "what": key[1]}}

    def close(self, success: bool, key: tuple[float, str] | None = None) -> dict | None:
        """Flush, finish the file and, when ``success``, send the final layout (``plan(key)``,
        made the recording's default and active blueprint) and give the file its final name
        (after reading its footer back: a recording that did not finish stays ``.partial.rrd``).
        Returns the layout's facts for the summary (``view``: bounds, key moment), or None."""
        facts = None
        try:
            if success:
                self.flush(final=True)
                plan = self.plan(key)
                self.rec.send_blueprint(blueprint(plan), make_active=True, make_default=True)
                facts = {"bounds": plan["bounds"], "key": plan["key"], "t_end": plan["t_end"]}
                self.flush(final=True)
            else:   # a partial recording: the layout without the key moment
                self._send_metrics()
                self.rec.send_blueprint(blueprint(self.plan()), make_active=True, make_default=True)
        finally:
            self.rec.disconnect()
        if success:
            _check_complete(self.partial)
            os.replace(self.partial, self.path)
        return facts


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
        raise OSError(f"{path}: the recording is incomplete (no rerun stream footer at its end)")
