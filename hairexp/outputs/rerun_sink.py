"""The rerun recording of a run.  Only imported when ``logging.rerun=true``.

Entities: /world/hair (line strips), /world/body (rigid body transform and box), /world/rail
(a dynamic body's rail),
/world/roots (root vertices), /metrics/<name> (scalars on the ``frame``, ``sim_time`` and
``step`` timelines).  A default blueprint puts the 3D view beside the metric plots.  Each
recording has an explicit recording id, so parallel workers never share one.

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

#: the metric scalars go to the recording at most this often (s), or every this many steps
METRICS_SECONDS = 10.0
METRICS_STEPS = 1000

#: Metrics plotted (a subset of the row; all numeric row entries are logged).
PLOTTED = ("iterations", "stretch_max", "residual_rel_max", "variance_ratio_mean", "constraint_force_rel",
           "step_seconds")


def blueprint() -> rrb.Blueprint:
    plots = [rrb.TimeSeriesView(origin=f"/metrics/{m}", name=m) for m in PLOTTED]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/world", name="hair"),
            rrb.Vertical(*plots),
            column_shares=[2, 1],
        ),
        rrb.TimePanel(state="collapsed"),
        collapse_panels=False,
    )


def partial_name(path: str) -> str:
    """``recording.rrd`` -> ``recording.partial.rrd`` (the name while it is written)."""
    root, ext = os.path.splitext(path)
    return f"{root}.partial{ext}"


class RerunSink:
    def __init__(self, path: str, scene, application_id: str = "hairexp", recording_id: str | None = None,
                 strict: bool = False):
        if strict:
            rr.set_strict_mode(True)
        self.path = path
        self.partial = partial_name(path)
        self.recording_id = recording_id or str(uuid.uuid4())
        self.rec = rr.RecordingStream(application_id, recording_id=self.recording_id)
        self.rec.save(self.partial, default_blueprint=blueprint())
        self.metrics_sent = time.monotonic()
        self.scene = scene
        self.offsets = scene.strands.offsets
        self.scalars: dict[str, list] = {}   # since the last flush
        self.named: set[str] = set()           # metric series given their name
        self.steps, self.frames, self.times = [], [], []
        rec = self.rec
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        L = float(np.median(scene.strands.strand_lengths()))
        self.radius = 0.004 * L
        rec.log("/world/body/box", rr.Boxes3D(half_sizes=[[0.5 * L * 0.1] * 3], colors=[[180, 180, 190]]), static=True)
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
        for c in self.scene.colliders:
            Rc, Tc = c.motion.pose(state.time)
            rec.log(f"/world/colliders/{c.name}", rr.Transform3D(translation=Tc, quaternion=Rotation.from_matrix(Rc).as_quat()))
        if obs.get("guides") is not None:
            g = np.split(obs["guides"].astype(np.float32), self.guide_offsets[1:-1])
            rec.log("/world/guides", rr.LineStrips3D(g, radii=2.5 * self.radius, colors=[[230, 60, 60]]))
        if getattr(self, "tracker", None) is not None and obs.get("com") is not None:
            tr = self.tracker
            if self.cluster_share is None:
                cov = tr.corr.cluster_of_vertex
                cols = np.where(cov[:, None] >= 0, self.cluster_colors[np.maximum(cov, 0)], 150).astype(np.uint8)
            else:   # soft assignment: the clusters' colours mixed by the vertex's shares
                W = self.cluster_share
                cols = np.where(W.sum(1)[:, None] > 0, W @ self.cluster_colors, 150).astype(np.uint8)
            rec.log("/world/clusters", rr.Points3D(state.x.astype(np.float32), radii=self.radius, colors=cols))
            rec.log("/world/com", rr.Points3D(obs["com"].astype(np.float32), radii=3 * self.radius,
                                              colors=self.cluster_colors))
            rec.log("/world/targets", rr.Points3D(obs["targets"].astype(np.float32), radii=2 * self.radius,
                                                  colors=[[255, 255, 255]]))
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
            rec.log("/world/target_curves", rr.LineStrips3D(curves, radii=0.5 * self.radius,
                                                            colors=self.cluster_colors[np.concatenate(tg.clusters)]))

    def on_step(self, row: dict, state) -> None:
        self.steps.append(row["step"])
        self.frames.append(row["frame"])
        self.times.append(row["time"])
        for k, v in row.items():
            if isinstance(v, (bool, np.bool_)):
                v = float(v)
            if isinstance(v, (int, float, np.integer, np.floating)) and k not in ("step", "frame", "time"):
                self.scalars.setdefault(k, []).append(float(v))

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

    def close(self, success: bool) -> None:
        """Flush, finish the file and, when ``success``, give it its final name (after reading
        its footer back: a recording that did not finish stays ``.partial.rrd``)."""
        try:
            if success:
                self.flush(final=True)
            else:
                self._send_metrics()
        finally:
            self.rec.disconnect()
        if success:
            _check_complete(self.partial)
            os.replace(self.partial, self.path)


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
