"""Guide animations: G guide polylines with one shape per frame, rooted on the rigid body.

``GuideAnimation.shape_at(t)`` interpolates linearly between frames when the time step is
smaller than the frame interval, and holds the first/last frame outside the animation.
Sources (``guides.source``): ``rigid`` (rest guides carried by the body), ``scaled`` (rest
guides scaled about their roots by keyframed factors, then carried by the body: the paper's
Fig. 2 shrinking guide), ``file`` (an npz with ``guide_positions`` (F, Vg, 3),
``guide_offsets`` (G + 1,) and ``fps``, such as a run's guides.npz), ``simulated`` (the rest
guides simulated as free strands with the scene's body motion, material and gravity: the
paper's "initial simulation on a coarse set of guide hairs using best-guess parameters"; with
``guides.collide`` they collide with the scene's colliders), ``usd`` (the guide prim of the
stage ``scene.usd``, hairexp/io/usd_read.py).

Guides are authored in the body frame.  On a dynamic body (``scene.body.dynamic``, paper 4
Stylization) the animation's world positions are those of the block held at its initial pose
(``DynamicBody.reference``: the pose is not known before the simulation), and ``shape_at`` carries
the body-frame guide with the live block: world = block pose at t x body-frame guide.  A
``simulated`` guide source on a dynamic body simulates the guides on the block held still.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hairexp.errors import InputError
from hairexp.scene.builders import disk_points
from hairexp.scene.dynamic_body import authoring_motion
from hairexp.scene.strands import validate_polylines
from hairexp.tracking.authoring import apply_edits, keyframed_positions


@dataclass
class GuideAnimation:
    positions: np.ndarray   # (F, Vg, 3) m
    offsets: np.ndarray     # (G + 1,)
    fps: float
    where: str = "guides"
    motion: object = None   # the body the guides are rooted on: interpolate in its frame


    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.offsets = np.asarray(self.offsets, dtype=np.int64)
        if self.positions.ndim != 3 or self.positions.shape[-1] != 3 or self.positions.shape[0] < 1:
            raise InputError(f"guide positions must have shape (frames, vertices, 3), got {self.positions.shape}",
                             self.where)
        counts = np.diff(self.offsets)
        if counts.size == 0 or self.offsets[0] != 0:
            raise InputError("guide offsets must start at 0 and name at least one guide", self.where)
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"fps must be > 0, got {self.fps}", self.where)
        for f in range(self.positions.shape[0]):
            validate_polylines(self.positions[f], counts, f"{self.where} frame {f}", min_vertices=2)
        self.attach(self.motion)

    def attach(self, motion) -> None:
        """Interpolate between frames in the body frame of ``motion`` and map back with its
        exact pose, so that the guide roots follow the body between frames as the detail
        hair roots do (a linear blend of world positions would cut corners when it turns).
        A dynamic body: the positions are in its ``reference`` pose (authoring), ``shape_at``
        maps them with the live block."""
        self.motion = motion
        if motion is not None:
            ref = authoring_motion(motion)
            self._body = np.stack([ref.to_body(P, f / self.fps) for f, P in enumerate(self.positions)])
    @property
    def n_guides(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def rest(self) -> np.ndarray:
        return self.positions[0]

    def guides(self, P: np.ndarray) -> list[np.ndarray]:
        return [P[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def shape_at(self, t: float) -> np.ndarray:
        """(Vg, 3) guide vertices at time t (linear in time between frames)."""
        u = float(np.clip(t * self.fps, 0.0, self.n_frames - 1))
        f = min(int(np.floor(u)), self.n_frames - 2) if self.n_frames > 1 else 0
        src = self.positions if self.motion is None else self._body
        if self.n_frames == 1:
            B = src[0]
        else:
            a = u - f
            B = (1 - a) * src[f] + a * src[f + 1]
        return B if self.motion is None else self.motion.transform(B, t)

    def save(self, path: Path) -> None:
        np.savez_compressed(path, guide_positions=self.positions, guide_offsets=self.offsets, fps=self.fps)


def rest_guides(scene_cfg, count: int, n_vertices: int, layout_radius: float) -> np.ndarray:
    """(count * n_vertices, 3) straight rest guides in the body frame, rooted on a circle of
    ``layout_radius`` x the root radius (the disk centre for a single guide)."""
    if count < 1:
        raise InputError(f"must be >= 1, got {count}", "guides.count")
    if n_vertices < 2:
        raise InputError(f"must be >= 2, got {n_vertices}", "guides.n_vertices")
    d = np.asarray(scene_cfg.direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    center = np.asarray(scene_cfg.root_center, dtype=np.float64)
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 0, 1.0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    if count == 1:
        roots = center[None]
    else:
        phi = 2 * np.pi * np.arange(count) / count
        r = layout_radius * scene_cfg.root_radius
        roots = center + r * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)
    s = np.linspace(0.0, scene_cfg.length, n_vertices)
    return np.concatenate([r0 + s[:, None] * d for r0 in roots])


def source_guides(cfg, scene, frames: int, fps: float) -> GuideAnimation:
    """Guide animation for frames 0..frames from ``cfg.guides`` (see module doc; ``keyframed``:
    ``authoring.keyframed_positions``), before the edits."""
    g = cfg.guides
    source = str(getattr(g.source, "value", g.source))
    motion = authoring_motion(scene.motion)   # a dynamic body: its initial pose held still
    if source == "file":
        path = Path(g.file)
        try:
            data = np.load(path)
            pos, off, gfps = data["guide_positions"], data["guide_offsets"], float(data["fps"])
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(f"cannot read guide animation: {exc}", f"guides.file={path}") from exc
        return GuideAnimation(pos, off, gfps, where=str(path), motion=scene.motion)
    if source == "usd":  # the guide prim of the stage scene.usd
        from hairexp.io.usd_read import read_guides

        return read_guides(cfg, scene, frames, fps)
    body = rest_guides(cfg.scene, g.count, g.n_vertices, g.layout_radius)
    offsets = np.arange(g.count + 1) * g.n_vertices
    times = np.arange(frames + 1) / fps
    if source == "simulated":
        return simulate_guides(cfg, scene, body, offsets, frames, fps)
    if source == "keyframed":
        pos, offsets = keyframed_positions(g, motion, frames, fps)
        return GuideAnimation(pos, offsets, fps, where="guides.keyframes", motion=scene.motion)
    frames_pos = []
    for t in times:
        X = body
        if source == "scaled":
            if len(g.scale_times) != len(g.scale_factors) or not g.scale_times:
                raise InputError("scale_times and scale_factors must be non-empty and of equal length", "guides")
            f = float(np.interp(t, g.scale_times, g.scale_factors))
            roots = np.repeat(body[offsets[:-1]], g.n_vertices, axis=0)
            X = roots + f * (body - roots)
        frames_pos.append(motion.transform(X, t))
    return GuideAnimation(np.stack(frames_pos), offsets, fps, motion=scene.motion)


def simulate_guides(cfg, scene, body: np.ndarray, offsets: np.ndarray, frames: int, fps: float) -> GuideAnimation:
    """Free simulation of the guide strands (eq. 5, same solver settings) at the scene's rate.
    With ``guides.collide`` the guides collide with the scene's colliders (the collision stage
    of ``collision.*``, without hair-hair), so that a coarse guide is dragged over an object as
    the hair is; otherwise they pass through it.  With ``scene.settle`` > 0 the guides first
    settle under gravity for that time, the body (and colliders) held at their t = 0 poses, and
    the animation starts from the settled guides at rest (frame 0).  The other guide sources
    (rigid, scaled, keyframed, file, usd) are not settled: they are used as given."""
    from hairexp.physics.integrator import Simulator
    from hairexp.physics.settle import settle_seconds, settle_state, settle_step, settled_scene
    from hairexp.run import step_schedule
    from hairexp.scene.scene import Scene
    from hairexp.scene.strands import Strands

    if cfg.guides.n_vertices < 3:
        raise InputError("simulated guides need >= 3 vertices (two are held by the body)", "guides.n_vertices")
    motion = authoring_motion(scene.motion)
    world = motion.transform(body, 0.0)
    strands = Strands.from_polylines(world, np.diff(offsets), scene.material.linear_density, where="guides")
    collide = bool(getattr(cfg.guides, "collide", False)) and bool(scene.colliders)
    gscene = Scene(scene.name + "_guides", strands, scene.material, motion, scene.gravity, body,
                   list(scene.colliders) if collide else [])
    ccfg = None
    if collide:
        ccfg = copy.deepcopy(cfg.collision)
        ccfg.hair_hair = False
    n_sub, dt = step_schedule(fps, cfg.solver.dt, frames)
    seconds = settle_seconds(cfg.scene)
    if seconds > 0:   # scene.settle: the guides settle as the detail hair does (hairexp/physics/settle.py)
        gscene = settled_scene(gscene, settle_state(gscene, cfg.solver, ccfg, seconds, settle_step(cfg.scene),
                                                             what="guides"))
    sim = Simulator(gscene, cfg.solver, collision_cfg=ccfg)
    state = sim.initial_state()
    out = [state.x.copy()]
    for _ in range(frames):
        for _ in range(n_sub):
            state, _ = sim.step(state, dt)
        out.append(state.x.copy())
    return GuideAnimation(np.stack(out), offsets, fps, motion=scene.motion)


def build_guides(cfg, scene, frames: int, fps: float) -> GuideAnimation:
    """The guide animation a run tracks and saves as guides.npz: the source's
    (``source_guides``) with the authored edits ``guides.edits`` applied in order
    (``authoring.apply_edits``; paper 4: the artist edits a coarse best-guess guide simulation by
    keyframing; ``source=keyframed`` keys the guides directly)."""
    anim = source_guides(cfg, scene, frames, fps)
    if not cfg.guides.edits:
        return anim
    pos = apply_edits(anim.positions, anim.offsets, anim.fps, authoring_motion(scene.motion), cfg.guides.edits)
    return GuideAnimation(pos, anim.offsets, anim.fps, where="guides.edits", motion=scene.motion)
