"""The one assembly path: config -> scene, guides, controller, simulator and the settled
initial state.  The command line (``hairexp.app.run``), the USD export, every script under
experiments/ and the tests that build runs go through it, so a benchmark times exactly what
``python -m hairexp`` runs.

    from hairexp.app import assemble, compose_config

    run = assemble(compose_config(["experiment=goaling_smoke", "controller=tracking"]))
    state = run.initial_state()
    for step, frame, state, info in run.steps(state):
        ...                                  # state: hairexp.physics.state.State, info: StepInfo

Order (the same for every caller): the config's ranges (``validate.validate_config``), the
stage's timing (``frames``/``fps`` null: from ``scene.usd``), the step schedule, the resource
guard (``guard.guard_run``), the scene (``app.builders.build_scene``), the measure's references
into it (``validate.validate_measure``), the settle phase (``scene.settle``,
hairexp/physics/settle.py), the guide animation (``app.guides.build_guides``), the controller
(``controller.name`` in the registry, hairexp/control/__init__.py) and the Simulator
(hairexp/physics/simulator.py).  Every key is checked before the first step.
"""

from __future__ import annotations

import copy
import logging
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from omegaconf import OmegaConf

from hairexp.app.builders import build_scene
from hairexp.app.config import require_config
from hairexp.app.guard import guard_hair_hair, guard_run
from hairexp.app.guides import build_guides, check_simulated_guides, read_guide_file, source_guides
from hairexp.app.validate import late_keys, validate_config, validate_measure
from hairexp.control import build_controller
from hairexp.errors import InputError, choice_name
from hairexp.guides.animation import GuideAnimation
from hairexp.model.builders import check_counts
from hairexp.model.rigid import motion_poses
from hairexp.model.scene import Scene
from hairexp.physics.controller import Controller
from hairexp.physics.info import StepInfo
from hairexp.physics.schedule import step_schedule
from hairexp.physics.settle import settle_scene
from hairexp.physics.simulator import Simulator
from hairexp.physics.state import State

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Run:
    """An assembled run: everything that stays fixed while it is stepped."""

    cfg: object                  # the composed config (frames and fps filled in from a USD stage)
    scene: Scene                 # settled when scene.settle > 0
    guides: GuideAnimation
    controller: Controller
    simulator: Simulator
    steps_per_frame: int
    dt: float                    # s, the step (the frame interval / steps_per_frame)

    @property
    def frames(self) -> int:
        return int(self.cfg.frames)

    @property
    def controller_name(self) -> str:
        return choice_name(self.cfg.controller.name)

    def initial_state(self) -> State:
        return self.simulator.initial_state()

    def steps(self, state: State | None = None, frames: int | None = None) -> Iterator[tuple[int, int, State, StepInfo]]:
        """Step from ``state`` (default: the initial state) through ``frames`` frames (default:
        the config's): yields (step, frame, state, info) after every step, steps and frames
        counted from 1."""
        state = self.initial_state() if state is None else state
        frames = self.frames if frames is None else frames
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)):
            raise TypeError(f"Run.steps: frames must be a whole number >= 0, got {frames!r}")
        if frames < 0:   # a value error (an InputError), not a type error (probe of issue 12, round 13)
            raise InputError(f"must be a whole number >= 0, got {frames}", "Run.steps: frames")
        fps = float(self.cfg.fps)
        try:   # a state that is not a State, or a time that is not a number: Simulator.step names it
            t0 = float(state.time) if isinstance(state, State) else 0.0
        except (TypeError, ValueError):
            t0 = 0.0
        t0 = t0 if np.isfinite(t0) else 0.0
        end, last = t0 + int(frames) / fps, (self.guides.n_frames - 1) / self.guides.fps
        if self.controller_name != "free" and end > last + 0.5 / fps:
            # past the animation the guides froze at their last frame, and the run said converged (probe of issue 12)
            # an InputError (a ValueError) naming the argument, as the other entry points' (a probe)
            raise InputError(f"{int(frames)} frames from t = {t0:g} s end at {end:g} s, past the guide animation's "
                             f"end ({last:g} s, frames 0..{self.guides.n_frames - 1}); the {self.controller_name} "
                             "controller follows the guides: assemble the run with enough frames", "Run.steps: frames")
        step = 0
        for frame in range(1, int(frames) + 1):
            for _ in range(self.steps_per_frame):
                state, info = self.simulator.step(state, self.dt)
                step += 1
                yield step, frame, state, info


def timed_config(cfg):
    """``cfg`` with ``frames``/``fps`` filled in from the USD stage where they are null."""
    if cfg.frames is None or cfg.fps is None:   # null: from the USD stage (experiment=from_usd)
        from hairexp.io.usd_read import stage_timing   # pxr is imported only for USD scenes

        return stage_timing(cfg)
    return cfg


def assemble_scene(cfg, settle: bool = True) -> tuple[object, Scene, GuideAnimation]:
    """(config with its timing, scene, guides): the first half of ``assemble``.  ``settle=False``
    keeps the built scene unsettled (the USD export writes the elastic rest shape); the guides are
    the same either way (simulated guides settle on their own, hairexp/app/guides.py)."""
    require_config(cfg, "assemble_scene")
    return _assemble_scene(cfg, settle)[:3]


def check_config(cfg, files: bool = True) -> None:
    """What ``assemble`` checks before the first step, short of settling and simulated guides:
    the config's ranges, the step schedule, a guide file, the resource guard, the scene as built
    (its keys read by the model layer: lengths, colliders, motions), the measure's references
    into it, a clear start, and the guides (simulated ones: their keys, and their edits applied
    to the rest guides carried rigidly; their simulation is a run of its own).  A run checks its
    config this way before it claims its folder, and an experiment every variant's before the
    first runs: a bad ``scene.length`` or a later variant's unknown ``measure.collider`` left a
    failed summary in the folder, or was found after the earlier variants had run (probe of
    issue 12, round 17).  The checks take 20-60 ms on the paper scenes.

    ``files=False`` (``--cfg job``, which prints the config): no file is read, so the timing and
    the scene of a USD stage and a guide file's guides are not checked; the rest is (``fps=0``,
    ``frames=0``, ``scene.n_strands=0`` and a measure's unknown collider were printed, exit 0;
    independent probe, 2026-12-07)."""
    validate_config(cfg)
    usd = choice_name(cfg.scene.builder) == "usd"
    if not files and (cfg.frames is None or cfg.fps is None):   # the stage's timing: a file
        if not usd:
            check_counts(int(cfg.scene.n_strands), int(cfg.scene.n_vertices), float(cfg.scene.length))
        return
    cfg = timed_config(cfg)
    n_sub, _ = step_schedule(cfg.fps, cfg.solver.dt, cfg.frames)
    from_file = choice_name(cfg.guides.source) == "file"
    if from_file and files:   # read now: a later variant's bad file failed after the others ran
        read_guide_file(cfg.guides, None, int(cfg.frames), float(cfg.fps))
    if not usd:
        check_counts(int(cfg.scene.n_strands), int(cfg.scene.n_vertices), float(cfg.scene.length))
        guard_run(cfg, int(cfg.scene.n_strands) * int(cfg.scene.n_vertices), n_sub)
    elif not files:
        return
    scene = build_scene(cfg.scene)
    if usd:
        guard_run(cfg, scene.strands.n_vertices, n_sub)
    guard_hair_hair(cfg, scene.strands.rest, scene.strands.edges)
    validate_measure(cfg, scene)
    check_clear_start(scene, choice_name(cfg.collision.contact))
    check_clear_roots(scene, int(cfg.frames), float(cfg.fps), n_sub)
    if from_file and not files:
        return
    if choice_name(cfg.guides.source) != "simulated":   # read or made in milliseconds
        guides = build_guides(cfg, scene, cfg.frames, cfg.fps)
    else:   # their simulation is a run of its own: their keys, and their edits on the rest guides carried rigidly
        check_simulated_guides(cfg)
        stand_in = copy.deepcopy(cfg)
        stand_in.guides.source = "rigid"
        with _no_warnings():   # the stand-in's warnings are not the run's (it says its own)
            guides = build_guides(stand_in, scene, cfg.frames, cfg.fps)
    # the controller on them: the tracking's correspondence (clusters within tracking.max_guide_distance,
    # a cluster for each tracking point) failed only when its variant was assembled, after the free one
    # had run (an outside probe, 2026-12-07); its warnings are the run's to say
    with _no_warnings():
        build_controller(choice_name(cfg.controller.name), cfg, scene, guides)


@contextmanager
def _no_warnings():
    """Within it, no log record at WARNING or below is emitted (a check's build whose warnings the
    run itself will say)."""
    quiet = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(quiet)


def _assemble_scene(cfg, settle: bool):
    """``assemble_scene``'s (config, scene, guides) and the step schedule (steps per frame, dt)."""
    validate_config(cfg)                                # the config's ranges (hairexp/app/validate.py)
    cfg = timed_config(cfg)
    n_sub, dt = step_schedule(cfg.fps, cfg.solver.dt, cfg.frames)   # validated before anything is built
    usd = choice_name(cfg.scene.builder) == "usd"
    if not usd:   # the resource guard (hairexp/app/guard.py) before the hair is built
        check_counts(int(cfg.scene.n_strands), int(cfg.scene.n_vertices), float(cfg.scene.length))
        guard_run(cfg, int(cfg.scene.n_strands) * int(cfg.scene.n_vertices), n_sub, run=settle)
    scene = build_scene(cfg.scene)
    if usd:       # a stage's size is known once it is read
        guard_run(cfg, scene.strands.n_vertices, n_sub, run=settle)
    validate_measure(cfg, scene)
    check_clear_start(scene, choice_name(cfg.collision.contact))
    check_clear_roots(scene, int(cfg.frames), float(cfg.fps), n_sub)
    if settle:
        scene = _settled(scene, cfg)   # scene.settle > 0: start from the hair at rest under gravity
    guides = build_guides(cfg, scene, cfg.frames, cfg.fps, source_of=_shared_source)
    # the config's warnings once everything was built from it: a refused run printed them above its
    # error line (the error is what to mend)
    late_keys(cfg)
    frame = 1.0 / float(cfg.fps)
    if float(cfg.solver.dt) > frame * (1 + 1e-9):   # not the step: dt 0.04 at 24 fps is 2 steps of 1/48 s
        log.warning("solver.dt=%g s is longer than a frame (1/fps = %.4g s): each step is one frame, %.4g s",
                    float(cfg.solver.dt), frame, dt)
    return cfg, scene, guides, n_sub, dt


#: While ``shared_settle`` is on: per kind ("settle", "guides") the last one made and the settings
#: it was made from, (key, value) (``_shared``); None: off
_SHARED: dict | None = None


@contextmanager
def shared_settle():
    """Within it (an experiment's variants, ``run_experiment``), ``assemble`` settles a scene and
    simulates its guides once for runs with the same settings (``_settled``, ``_shared_source``)."""
    global _SHARED
    before, _SHARED = _SHARED, {} if _SHARED is None else _SHARED
    try:
        yield
    finally:
        _SHARED = before


def _shared(kind: str, groups: dict, make):
    """(value, reused): the last ``kind`` made within ``shared_settle`` when it was made from the
    same ``groups`` (config groups and values, compared as YAML), else ``make()``, kept as the last."""
    key = OmegaConf.to_yaml(OmegaConf.create(groups))
    held = _SHARED.get(kind)
    if held is not None and held[0] == key:
        return held[1], True
    value = make()
    _SHARED[kind] = (key, value)
    return value, False


def _shared_source(cfg, scene, frames, fps):
    """``source_guides(cfg, scene, frames, fps)``; within ``shared_settle``, simulated guides
    (``guides.source=simulated``, which read ``cfg.guides``, the scene built from ``cfg.scene``,
    ``cfg.solver``, ``cfg.collision``, frames and fps) made once for runs whose settings are equal
    (Celia: 1.3-1.5 s a variant), each run getting a copy; other sources are read or built anew."""
    source = choice_name(cfg.guides.source)
    if _SHARED is None or source != "simulated" or choice_name(cfg.scene.builder) == "usd":
        return source_guides(cfg, scene, frames, fps)
    hit, reused = _shared("guides", {"guides": cfg.guides, "scene": cfg.scene, "solver": cfg.solver,
                                     "collision": cfg.collision, "frames": int(frames), "fps": float(fps)},
                          lambda: source_guides(cfg, scene, frames, fps))
    if reused:
        log.info("guides (%s): the simulated guides of the last run with the same settings", scene.name)
    # a copy attached to this run's body motion (a dynamic body's is the run's own, live object)
    out = copy.deepcopy(hit, None if hit.motion is None else {id(hit.motion): scene.motion})
    if out.motion is not None:
        out.attach(scene.motion)
    return out


def _settled(scene, cfg):
    """``settle_scene(scene, cfg)``, which reads the scene (built from ``cfg.scene``), ``cfg.solver``
    and ``cfg.collision``: within ``shared_settle``, a run whose three groups are those of the last
    run settled there (an experiment's variants that differ in their controller) gets a copy of
    its settled scene instead of settling again (Celia: 1.3-1.9 s a variant).  A USD stage is read
    from a file that may change between runs: always settled."""
    if _SHARED is None or choice_name(cfg.scene.builder) == "usd":
        return settle_scene(scene, cfg)
    hit, reused = _shared("settle", {"scene": cfg.scene, "solver": cfg.solver, "collision": cfg.collision},
                          lambda: settle_scene(scene, cfg))
    if reused and float(cfg.scene.settle) > 0:
        log.info("settle hair (%s): the settled state of the last run with the same scene, solver and collision "
                 "settings", scene.name)
    return copy.deepcopy(hit)


#: m: without the barrier, a vertex that starts this little inside a collider is on its surface (a
#: plane at the tips' height, written as float32, was refused "by 2.98e-06 mm"; a probe); the
#: collision stage puts it on the surface
START_DEPTH = 1e-6


def check_clear_start(scene, contact: str) -> None:
    """InputError naming the collider when a free hair vertex starts inside it at t = 0 (with the
    contact barrier: within its thickness shell, where the barrier is infinite).  Such a start
    diverged in the first step ("try a smaller solver.dt", exit 3: a plane across the hanging hair,
    any collider with the barrier; probe of issue 12).  The paper scenes start 1.4-70 cm clear.
    Without the barrier a vertex within ``START_DEPTH`` of the surface (round-off) is not refused."""
    if not scene.colliders:
        return
    x = scene.initial_positions()
    free = np.flatnonzero(~scene.strands.kinematic)
    shell = contact == "barrier"
    for i, c in enumerate(scene.colliders):
        R, T = c.motion.pose(0.0)
        d = c.sdf_body((x[free] - T) @ R) - (float(c.thickness) if shell else 0.0)
        bad = np.flatnonzero(d < (0.0 if shell else -START_DEPTH))
        if bad.size:
            k = int(bad[np.argmin(d[bad])])
            v = int(free[k])
            s_ = int(scene.strands.strand_of_vertex[v])
            # with the barrier, a vertex inside the shape itself is said to be inside it (it said "within its
            # thickness shell by 52 mm" of hair 5 cm inside a plane; probe of issue 12, round 14)
            in_shape = not shell or d[k] + float(c.thickness) < 0
            inside = "inside it" if in_shape else "within its thickness shell"
            depth = -float(d[k]) - (float(c.thickness) if shell and in_shape else 0.0)   # into the shape, or the shell
            raise InputError(f"collider {c.name!r}: the hair starts {inside} (strand {s_} vertex "
                             f"{v - int(scene.strands.offsets[s_])} by {1e3 * depth:.3g} mm at t = 0; {bad.size} "
                             f"vertices in all): place the collider clear of the hair at rest"
                             + (" (the contact barrier needs a start free of contact)" if shell else ""),
                             getattr(c, "where", None) or f"scene.colliders[{i}]")


#: root positions checked together by ``check_clear_roots`` (samples x roots)
ROOT_CHECK_POINTS = 1 << 16


def check_clear_roots(scene, frames: int, fps: float, steps_per_frame: int) -> None:
    """InputError naming the collider when the body carries a root vertex into it during the run.
    The roots are kinematic: a root driven into a collider pins its strand inside it, and neither
    the contact nor the controller can free it (a wheel of radius 0.5 m in goaling ran "completed"
    with the hair stretched by 518 %, and the tracked variant took 85 s for 21 steps; probe of
    issue 12, round 29).  A root that starts inside a collider moving with it is the scalp under a
    head sphere (celia: 7 mm inside) and is allowed: only a root that goes deeper than it started,
    by more than the collider's thickness or 1 mm (at most half its centre's depth: a thin plate), is
    refused.  The poses are sampled at every
    step (at most 2000 times), and between two samples wherever the root moved (in the collider's
    frame) far enough to have gone in and out again (``_passes_between``: a thin plate or a fast
    ball swept through the roots within a step).  A dynamic body (``scene.body.dynamic``) moves as
    the run computes it and is not checked."""
    if not scene.colliders or scene.body is not None:
        return
    k = np.flatnonzero(scene.strands.kinematic)
    if k.size == 0:
        return
    n = int(frames) * int(steps_per_frame)   # every step, or 2000 even samples of a longer run
    ts = np.linspace(0.0, int(frames) / float(fps), min(n, 2000) + 1)
    X = scene.root_body[k]
    block = max(1, ROOT_CHECK_POINTS // len(k))   # samples a block: the roots' positions of a block at once
    for i, c in enumerate(scene.colliders):
        where = getattr(c, "where", None) or f"scene.colliders[{i}]"
        gap = max(float(c.thickness), 1e-3)
        deep = -float(c.sdf_body(np.zeros((1, 3)))[0])   # its centre's depth: a plate's half-thickness
        if deep > 0:   # a collider thinner than the gap: a root gone halfway through it (else never refused)
            gap = min(gap, 0.5 * deep)
        level, prev, budget = None, None, [PASS_BUDGET]   # level: each root's refused signed distance
        for a in range(0, len(ts), block):
            tb = ts[a:a + block]
            P, D = _roots_in_collider(scene, c, X, tb)
            if level is None:
                level = np.minimum(D[0], 0.0) - gap
            below = D - level[None]
            hit = np.flatnonzero((below < 0).any(axis=1))
            if hit.size:   # the first sample where a root went deeper
                r = int(hit[0])
                j = int(np.argmin(below[r]))
                _roots_refusal(scene, c, where, k[j], float(tb[r]), float(D[r, j]))
            if prev is not None:   # the interval between the blocks too
                tb, P, D = np.concatenate([prev[0], tb]), np.concatenate([prev[1], P]), np.concatenate([prev[2], D])
            found = _passes_between(scene, c, X, tb, P, D, level, budget)
            if found is not None:
                _roots_refusal(scene, c, where, k[found[0]], found[1], found[2])
            prev = (tb[-1:], P[-1:], D[-1:])


def _roots_in_collider(scene, c, X: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, D): the body-held points ``X`` (R, 3) at the times ``ts`` (T,) in collider ``c``'s
    frame, (T, R, 3), and their signed distances to it (T, R)."""
    Rb, Tb = motion_poses(scene.motion, ts)   # the body's poses, then the collider's
    Rc, Tc = motion_poses(c.motion, ts)
    W = np.matmul(X[None], np.swapaxes(Rb, 1, 2)) + Tb[:, None, :]
    P = np.matmul(W - Tc[:, None, :], Rc)
    return P, c.sdf_body(P.reshape(-1, 3)).reshape(len(ts), len(X))


def _roots_refusal(scene, c, where: str, v: int, t: float, d: float):
    """The InputError of root vertex ``v`` at signed distance ``d`` inside collider ``c`` at time ``t``."""
    s_ = int(scene.strands.strand_of_vertex[int(v)])
    raise InputError(f"collider {c.name!r}: the hair's roots go into it (strand {s_} root by {1e3 * -d:.3g} mm at "
                     f"t = {t:.4g} s); a root is held by the body, so its strand would be pinned inside: keep the "
                     f"collider off the roots' path", where)


#: ``_passes_between``: a root's path between two samples is taken as at most this many times its
#: chord (in the collider's frame: a body turning 90 degrees between samples makes 1.11)
PATH_OVER_CHORD = 2.0
#: ... an interval is halved at most this many times (a plate crossing 1 m in a step found within
#: 1e-9 m), and at most this many halvings are made for one collider (a root gliding along the
#: refused depth)
PASS_DEPTH = 40
PASS_BUDGET = 4096


def _passes_between(scene, c, X, ts, P, D, level, budget: list, depth: int = 0):
    """(root index, time, signed distance) of a root that goes below its refused depth ``level``
    (R,) between two of the samples ``ts`` (T,), where none is below (P: the roots' positions in
    the collider's frame (T, R, 3), D: their signed distances (T, R)), or None.  The signed distance
    changes by at most the path's length: a root whose margins above ``level`` at an interval's
    ends sum to more than PATH_OVER_CHORD x its chord cannot have gone below between them; where
    they do not, the interval is halved and both halves checked in turn (PASS_DEPTH deep, PASS_BUDGET
    halvings at most, counted down in ``budget[0]``: a root that grazes the depth all along is not
    refused for it)."""
    if len(ts) < 2 or depth >= PASS_DEPTH:
        return None
    M = D - level[None]
    chord = np.linalg.norm(P[1:] - P[:-1], axis=2)                     # (T - 1, R)
    maybe = M[1:] + M[:-1] < PATH_OVER_CHORD * chord   # strict: a root that does not move cannot go in
    for a in np.flatnonzero(maybe.any(axis=1)):
        if budget[0] <= 0:
            return None
        budget[0] -= 1
        roots = np.flatnonzero(maybe[a])
        tm = 0.5 * (float(ts[a]) + float(ts[a + 1]))
        Pm, Dm = _roots_in_collider(scene, c, X[roots], np.array([tm]))
        below = Dm[0] - level[roots]
        if (below < 0).any():
            j = int(np.argmin(below))
            return int(roots[j]), tm, float(Dm[0, j])
        found = _passes_between(scene, c, X[roots], np.array([ts[a], tm, ts[a + 1]]),
                                np.stack([P[a, roots], Pm[0], P[a + 1, roots]]),
                                np.stack([D[a, roots], Dm[0], D[a + 1, roots]]), level[roots], budget, depth + 1)
        if found is not None:
            return int(roots[found[0]]), found[1], found[2]
    return None


def assemble(cfg) -> Run:
    """The run of a composed config (``compose_config`` or Hydra's), ready to step."""
    require_config(cfg, "assemble")
    if getattr(cfg, "variants", None):   # said: the variants are run_experiment's (probe of issue 12)
        log.warning("assemble: the config has %d variant(s); this builds the base config without them "
                    "(hairexp.app.experiment.run_experiment runs each variant; variants=[] silences this)",
                    len(cfg.variants))
    cfg, scene, guides, n_sub, dt = _assemble_scene(cfg, settle=True)
    controller = build_controller(choice_name(cfg.controller.name), cfg, scene, guides)
    sim = Simulator(scene, cfg.solver, controller, cfg.collision)
    return Run(cfg, scene, guides, controller, sim, n_sub, dt)
