"""Range checks of the config keys before anything is built (``assemble_scene`` calls
``validate_config`` first, ``validate_measure`` once the scene is built, both before the first
step).  Every error is an ``InputError`` naming the key, its value and the allowed range.

One place per key: the keys the model, guides, physics and control layers read and check
themselves are not checked again here (scene.n_strands/n_vertices/length/spread/root_radius/
seed/direction/root_center/gravity and the collider shapes in hairexp/model/builders.py,
scene.hair.* ``build_material``, keyframed motions in hairexp/model/rigid.py, scene.body.*
hairexp/model/dynamic_body.py, scene.settle/settle_dt hairexp/physics/settle.py, solver.dt,
fps and frames hairexp/physics/schedule.py, guides.count/n_vertices/keyframes/edits/file in
hairexp/guides/, tracking.points_per_guide and tracking.variance.* in hairexp/control/tracking/,
controller.attract_stiffness hairexp/control/attract.py).  The rest are checked here, and so are
the ranges of controller.attract_stiffness and scene.body.* whether or not their layer reads
them (``_unused``: a free run never builds the attract controller, a keyframed body no block).
The tracking layer's own checks of tracking.* (hairexp/control/tracking/controller.py
``check_tracking_config``, which the controller runs when built) are called here too: an
experiment checks every variant's config before the first runs, and a free variant never builds
the tracking controller (probe of issue 12, round 9).
``solver.integrator`` is checked by hairexp/physics/integrators.py ``make_integrator`` (and
``solver.kernels`` / ``solver.threads`` by hairexp/physics/strand_kernels.py ``check_options``), called
here too so that a bad name fails before the settle phase and the guides are simulated.
"""

from __future__ import annotations

import logging
import math

from omegaconf import OmegaConf

from hairexp.app.config import ColliderConfig, MeasureConfig, changed_keys
from hairexp.errors import MAX_SPEED, InputError, choice_name, enum_value, integer, number
from hairexp.control.tracking.controller import MAX_POINTS_PER_GUIDE, check_tracking_config  # noqa: F401
from hairexp.control.tracking.kkt import MAX_SCHUR_BYTES, schur_bytes
from hairexp.evaluation.judges import JUDGE_MEASURES, missing_controllers
from hairexp.guides.authoring import check_edits
from hairexp.model.builders import check_spin
from hairexp.evaluation.measures import MEASURE_KEYS, collider_named
from hairexp.physics.integrators import DEFAULT_INTEGRATOR, make_integrator
from hairexp.physics.simulator import MAX_ATOL, MAX_ITERATION_BUDGET, MAX_LAST_ATTEMPT, MAX_SUBSTEP_LEVELS, check_collision_config, check_solver_config  # noqa: F401
from hairexp.physics.strand_kernels import check_options


#: guides.scale_factors at most this (a guide 1,000 times its length)
MAX_SCALE_FACTOR = 1e3


log = logging.getLogger("hairexp")


def keyframes(times, key_times: str, values: dict) -> None:
    """``times`` finite and strictly increasing, each list of ``values`` (key -> list) as long."""
    t = [number(x, f"{key_times}[{i}]") for i, x in enumerate(times)]
    if not t:
        raise InputError("needs at least one keyframe", key_times)
    if any(b <= a for a, b in zip(t, t[1:])):
        raise InputError(f"keyframe times must increase strictly, got {t}", key_times)
    for key, vals in values.items():
        if len(vals) != len(t):
            raise InputError(f"has {len(vals)} values but {key_times} has {len(t)}: one per time", key)
        for i, x in enumerate(vals):
            number(x, f"{key}[{i}]")


def _solver(s) -> None:
    check_solver_config(s)   # hairexp/physics/simulator.py: the Simulator checks the same when built directly


#: guides.count x tracking.points_per_guide at most, for the guides the config makes (a guide file's or
#: a stage's are counted once read): 3 constraints per cluster, and the Schur complement of a tracked
#: step is a dense (3 x clusters)^2 matrix factored at every SQP iteration (500 guides x 6 points:
#: 9,000 constraints, 648 MB and minutes per iteration; Celia has 24 clusters)
MAX_CLUSTERS = 1024


def _clusters(cfg) -> None:
    if choice_name(cfg.controller.name) != "tracking" or choice_name(cfg.guides.source) in ("file", "usd"):
        return
    g, n = cfg.guides.count, cfg.tracking.points_per_guide
    if isinstance(g, int) and isinstance(n, int) and g >= 1 and n >= 1 and g * n > MAX_CLUSTERS:
        raise InputError(f"x tracking.points_per_guide = {g} x {n} = {g * n} clusters, more than {MAX_CLUSTERS}: "
                         "each is 3 tracking constraints in a dense Schur complement factored at every SQP "
                         "iteration (the paper's Celia has 24)", "guides.count")
    builder = choice_name(cfg.scene.builder)
    if builder != "usd" and isinstance(g, int) and isinstance(n, int) and g >= 1 and n >= 1:
        # the per-strand Schur blocks, at most (soft assignment: a strand may share every guide's
        # points), checked here before any variant runs; SchurKKT checks the real size
        shared = 1 if choice_name(cfg.tracking.assignment) == "hard" else g
        need = schur_bytes(int(cfg.scene.n_strands), 3 * n * shared, 3 * int(cfg.scene.n_vertices))
        if need > MAX_SCHUR_BYTES:
            raise InputError(f"with guides.count={g}, {cfg.scene.n_strands} strands of {cfg.scene.n_vertices} "
                             f"vertices and tracking.assignment={enum_value(cfg.tracking.assignment)}, the tracked step's "
                             f"per-strand Schur blocks could take {need / 2 ** 30:.1f} GiB (at most "
                             f"{MAX_SCHUR_BYTES / 2 ** 30:g} GiB): use fewer points, guides or strands, or "
                             "tracking.assignment=hard", "tracking.points_per_guide")


def _tracking(t) -> None:
    check_tracking_config(t)   # hairexp/control/tracking/controller.py: the controller checks the same when built directly


def _collision(c) -> None:
    check_collision_config(c)   # the Simulator checks the same (hairexp/physics/simulator.py)


def _guides(cfg) -> None:
    g = cfg.guides
    source = choice_name(g.source)
    number(g.layout_radius, "guides.layout_radius", lo=0, hi=10.0)   # of the root radius; 1e300 diverged (round 14)
    keyframes(g.scale_times, "guides.scale_times", {"guides.scale_factors": g.scale_factors})
    for i, f in enumerate(g.scale_factors):   # 1e9 was blamed on scene.length and the body (probe, round 12)
        number(f, f"guides.scale_factors[{i}]", lo=0, hi=MAX_SCALE_FACTOR, lo_open=True)
    if source == "file" and not str(g.file):
        raise InputError("guides.source=file needs the path of a guide npz", "guides.file")
    if source != "simulated" and bool(g.collide):   # accepted, then did nothing (probe of issue 12)
        raise InputError(f"is true but guides.source={source} does not simulate the guides (only simulated guides "
                         "collide with scene.colliders): set guides.source=simulated or guides.collide=false",
                         "guides.collide")
    count = int(g.count) if source in ("rigid", "scaled", "simulated", "keyframed") else None
    if count is not None:   # before the edits, whose index check would name them instead (probe of issue 12)
        integer(g.count, "guides.count", 1)
    check_edits(g.edits, count)
    if source != "file" and str(g.file):
        raise InputError(f"is set ({g.file}) but guides.source={source} does not read it: set guides.source=file "
                         "or leave guides.file empty", "guides.file")
    if source != "keyframed" and len(g.keyframes):   # ignored without a word, and unchecked (probe, round 13)
        raise InputError(f"holds {len(g.keyframes)} keyframe(s) but guides.source={source} does not read them: set "
                         "guides.source=keyframed or leave guides.keyframes empty", "guides.keyframes")


def _c(cfg, key: str) -> str:
    return choice_name(OmegaConf.select(cfg, key))


def _tracked(c) -> bool:
    return _c(c, "controller.name") == "tracking"


def _simulates(c) -> bool:
    return _c(c, "controller.name") != "skinned"


def _barrier(c) -> bool:
    return bool(c.collision.objects) and _c(c, "collision.contact") == "barrier"


def _stage_objects(c) -> bool:
    """The post-solve stage handles object contact (its contact planes read ``collision.resolve``)."""
    return _simulates(c) and bool(c.collision.objects) and _c(c, "collision.contact") != "barrier"


def _plane_friction(c) -> bool:
    return _stage_objects(c) and bool(c.collision.resolve) and bool(c.collision.plane_friction)


#: (key, or a prefix ending in '.' or '_', whether a run's config reads it, the setting that makes it read);
#: the first that matches a key decides.  ``unused_settings`` says a key given for a launch that no
#: run of it reads (probe of issue 12, round 15: ``tracking.rtol`` with the free controller, the
#: volume keys without hair-hair, ``scene.body.mass`` without a dynamic body, ... were taken silently)
KEY_USES = (
    ("tracking.variance.stiffness", _tracked, "controller.name=tracking"),
    ("tracking.variance.", lambda c: _tracked(c) and float(c.tracking.variance.stiffness) > 0,
     "controller.name=tracking with tracking.variance.stiffness > 0"),
    ("tracking.blend_width", lambda c: _tracked(c) and _c(c, "tracking.assignment") == "soft",
     "controller.name=tracking with tracking.assignment=soft"),
    # the KKT solver's settings (accepted without a word; independent probe of issue 12, round 35)
    ("tracking.krylov_", lambda c: _tracked(c) and _c(c, "tracking.kkt") != "reference" and _c(c, "tracking.schur") == "krylov",
     "controller.name=tracking with tracking.schur=krylov and tracking.kkt=schur"),
    ("tracking.schur", lambda c: _tracked(c) and _c(c, "tracking.kkt") != "reference",
     "controller.name=tracking with tracking.kkt=schur"),
    ("tracking.", _tracked, "controller.name=tracking"),
    ("controller.attract_stiffness", lambda c: _c(c, "controller.name") == "attract", "controller.name=attract"),
    ("collision.volume_", lambda c: bool(c.collision.hair_hair) and _c(c, "collision.hair_hair_model") == "volume"
     and _c(c, "controller.name") != "skinned", "collision.hair_hair=true with collision.hair_hair_model=volume"),
    ("collision.hair_hair_model", lambda c: bool(c.collision.hair_hair), "collision.hair_hair=true"),
    ("collision.skin", lambda c: bool(c.collision.hair_hair), "collision.hair_hair=true"),   # round 16
    ("collision.hair_hair", lambda c: _c(c, "controller.name") != "skinned",
     "a controller that simulates the hair (not skinned)"),
    ("collision.barrier_", _barrier, "collision.contact=barrier with collision.objects=true"),
    ("collision.friction_epsilon", lambda c: _barrier(c) or _plane_friction(c),
     "collision.contact=barrier with collision.objects=true, or collision.plane_friction=true with "
     "collision.resolve=true"),
    ("collision.plane_friction", lambda c: _stage_objects(c) and bool(c.collision.resolve),
     "collision.objects=true with collision.contact=stage and collision.resolve=true"),
    ("collision.resolve", _stage_objects, "collision.objects=true with collision.contact=stage"),
    ("collision.contact", lambda c: bool(c.collision.objects), "collision.objects=true"),
    # accepted without a word (independent probe of issue 12, round 36)
    ("collision.hair_thickness", lambda c: _simulates(c) and (
        (bool(c.collision.hair_hair) and _c(c, "collision.hair_hair_model") == "edges") or _barrier(c)),
     "collision.hair_hair=true with collision.hair_hair_model=edges, or collision.contact=barrier with "
     "collision.objects=true"),
    ("collision.friction", _barrier, "collision.contact=barrier with collision.objects=true (the stage always "
     "applies each collider's friction)"),
    ("collision.max_travel", lambda c: _simulates(c) and bool(c.collision.objects), "collision.objects=true"),
    ("scene.settle_dt", lambda c: float(c.scene.settle) > 0, "scene.settle > 0"),
    ("scene.usd_", lambda c: _c(c, "scene.builder") == "usd" or _c(c, "guides.source") == "usd",
     "scene.builder=usd or guides.source=usd"),
    ("solver.compile", lambda c: _c(c, "solver.derivatives") == "closed_form", "solver.derivatives=closed_form"),
    ("solver.threads", lambda c: _c(c, "solver.kernels") == "numba" and _c(c, "solver.derivatives") == "closed_form",
     "solver.kernels=numba with solver.derivatives=closed_form"),
    # the post-solve stage's strain limiter (round 35): built for the object stage or hair-hair contact
    ("collision.strain_limit", lambda c: _simulates(c) and (
        (bool(c.collision.objects) and _c(c, "collision.contact") != "barrier") or bool(c.collision.hair_hair)),
     "collision.objects=true with collision.contact=stage, or collision.hair_hair=true"),
    ("collision.max_travel_substeps", lambda c: _simulates(c) and bool(c.collision.objects)
     and float(c.collision.max_travel) > 0, "collision.objects=true with collision.max_travel > 0"),
    ("solver.restart_at_jumps", lambda c: _c(c, "solver.integrator") != "implicit_euler" and not bool(c.scene.body.dynamic),
     "a solver.integrator other than implicit_euler, without a dynamic body"),
    ("solver.max_substep_levels", lambda c: _c(c, "solver.on_failure") == "substep", "solver.on_failure=substep"),
    ("judge_tolerance", lambda c: _c(c, "judge") == "variance_follows_targets",
     "judge=variance_follows_targets, the one judge with a tolerance"),
    # accepted without a word (independent probe of issue 12, round 27)
    ("guides.scale_", lambda c: _c(c, "guides.source") == "scaled", "guides.source=scaled"),
    ("guides.keyframes", lambda c: _c(c, "guides.source") == "keyframed", "guides.source=keyframed"),
    ("guides.layout_radius", lambda c: _c(c, "guides.source") not in ("file", "usd"),
     "a guide source that lays the guides out (not file or usd)"),
    ("solver.last_attempt_iterations", lambda c: _c(c, "solver.on_failure") == "substep", "solver.on_failure=substep"),
    ("logging.strict", lambda c: bool(c.logging.rerun), "logging.rerun=true"),
    ("scene.body.dynamic", lambda c: True, ""),
    ("scene.body.", lambda c: bool(c.scene.body.dynamic), "scene.body.dynamic=true"),
)


def unused_settings(cfgs: list, keys) -> list[str]:
    """The ``keys`` (config keys a launch set: its command line's, or a variant's) that none of
    ``cfgs`` (the configs of its runs) reads, each as ``key (read with <setting>)`` (``KEY_USES``)."""
    out = []
    for key in dict.fromkeys(k.lstrip("+~") for k in keys):
        for pattern, used, needs in KEY_USES:
            if key == pattern or (pattern.endswith((".", "_")) and key.startswith(pattern)):
                try:
                    if not any(used(c) for c in cfgs):
                        out.append(f"{key} (read with {needs})")
                except Exception:  # noqa: BLE001  (a value the checks refuse with their own error)
                    pass
                break
    return out


def late_keys(cfg) -> None:
    """A warning for ``guides.edits`` keyed after the run's end (``cfg`` timed: frames and fps
    known, also a stage's) where those keys cannot change the run: an edit keyed only there is held
    at its first weight for the whole run (it was silent; probe of issue 12, round 13), and keys
    from the third after the end on are never reached.  The first two keys after the end do shape
    the weight before it (``KeyedWeight``: the segment that crosses the end runs to the first, and
    its slope there is the Fritsch-Carlson mean of the secants to the second), so they are not
    named: goaling_smoke's 30 frames end in the ease back of goaling's edit."""
    if not (_positive(cfg.frames) and _positive(cfg.fps)):
        return
    end = int(cfg.frames) / float(cfg.fps)
    for i, e in enumerate(cfg.guides.edits or ()):
        times = [float(t) for t in e.times]
        late = [t for t in times if t > end + 1e-9]
        if late and len(late) == len(times):
            unused, held = late, " (every key is: the edit is held at its first weight, the whole run)"
        else:
            unused, held = late[2:], ""
        if unused:
            log.warning("guides.edits[%d].times: the key%s at %s s lie%s after the run's end at %.6g s (frames / fps) "
                        "and %s never reached%s", i, "s" if len(unused) > 1 else "", ", ".join(f"{t:g}" for t in unused),
                        "" if len(unused) > 1 else "s", end, "are" if len(unused) > 1 else "is", held)


def _scene(cfg) -> None:
    s = cfg.scene
    if not str(s.name or "").strip():   # named as the API's Scene.name (probe of issue 12, round 14)
        raise InputError(f"must be a non-empty name, got {s.name!r}", "scene.name")
    builder = choice_name(s.builder)
    if str(s.usd) and builder != "usd" and choice_name(cfg.guides.source) != "usd":
        # an error, not a warning: the run would simulate another scene than the stage named, with exit 0
        raise InputError(f"is set ({s.usd}) but scene.builder={builder} and guides.source="
                         f"{enum_value(cfg.guides.source)} do not read it: set scene.builder=usd (or guides.source=usd) "
                         "or leave scene.usd empty", "scene.usd")


#: m, the largest measure.tolerance: a hit is within the hair's thickness plus this
MAX_CONTACT_TOLERANCE = 0.1
#: m, the largest measure.cohesion_threshold (single-linkage distance of a clump)
MAX_COHESION = 1.0


def _measure(cfg) -> None:
    m = cfg.measure
    tol = number(m.tolerance, "measure.tolerance", lo=0)
    if tol > MAX_CONTACT_TOLERANCE:   # 5 (m) made a run 0.7 m from the wheel "hit" from frame 0 (probe, round 19)
        raise InputError(f"is {tol:g} m beyond the hair's thickness: a strand that far from the collider would count as "
                         f"touching it; at most {MAX_CONTACT_TOLERANCE:g} m (the default is 0.002)", "measure.tolerance")
    number(m.time, "measure.time")
    number(m.threshold, "measure.threshold", lo=0, lo_open=True)
    number(m.strand_fraction, "measure.strand_fraction", lo=0, hi=1, hi_open=True)
    number(m.min_share, "measure.min_share", lo=0, hi=1)
    if number(m.cohesion_threshold, "measure.cohesion_threshold", lo=0, lo_open=True) > MAX_COHESION:
        # 1e300 made every strand one clump (independent probe of issue 12, round 35)
        raise InputError(f"must be at most {MAX_COHESION:g} m (strands this close link into one clump; at a metre every "
                         f"strand of a head of hair does; the default is 0.03), got {m.cohesion_threshold:g}",
                         "measure.cohesion_threshold")
    number(m.cohesion_fraction, "measure.cohesion_fraction", lo=0, hi=1, hi_open=True)
    axis = [number(x, f"measure.axis[{i}]") for i, x in enumerate(m.axis)]
    if len(axis) != 3 or not any(axis):
        raise InputError(f"must be 3 numbers, not all 0, got {axis}", "measure.axis")
    a0, a1 = number(m.apex_from, "measure.apex_from", lo=0), number(m.apex_until, "measure.apex_until")
    if 0 <= a1 < a0:
        raise InputError(f"must be < 0 (the last frame) or >= measure.apex_from ({a0}), got {a1}", "measure.apex_until")
    frames, fps = getattr(cfg, "frames", None), getattr(cfg, "fps", None)
    # (a USD scene's come from its stage; a bad frames or fps is named by hairexp/physics/schedule.py)
    if _positive(frames) and _positive(fps) and a0 > frames / fps + 1e-9:
        raise InputError(f"is after the run's last frame ({frames / fps:g} s), got {a0}", "measure.apex_from")
    number(m.rail_height, "measure.rail_height")
    number(m.rail_end, "measure.rail_end")
    if number(cfg.judge_tolerance, "judge_tolerance", lo=0, lo_open=True) >= 1:
        # a relative miss of the variance target: at 1 a variance of zero passes (1e9 passed an 80 % miss;
        # independent probe of issue 12, round 35)
        raise InputError(f"must be < 1 (the largest relative miss of a variance target the judge accepts: at 1 a "
                         f"variance of zero would pass; the default is 0.35), got {cfg.judge_tolerance:g}",
                         "judge_tolerance")
    if choice_name(m.name) == "collider_contact" and not str(m.collider):
        raise InputError("measure.name=collider_contact needs the name of a collider", "measure.collider")


def _positive(x) -> bool:
    """``x`` is a finite number > 0 (frames and fps before the schedule checks them)."""
    try:
        return math.isfinite(float(x)) and float(x) > 0
    except (TypeError, ValueError):
        return False


def _unused(cfg) -> None:
    """Keys whose layer reads (and checks) them only when they are used: a free run never builds
    the attract controller (controller.attract_stiffness), a keyframed body never builds the
    dynamic block (scene.body.*).  A bad value there is refused all the same, so that a typo is
    not found only by the variant or the later run that uses it."""
    c, b = cfg.controller, cfg.scene.body
    # 1/s^2; at most 1e9 (omega 3e4 rad/s, k dt^2 = 1.6e6 at dt 0.04): 1e308 passed and the first step overflowed
    number(c.attract_stiffness, "controller.attract_stiffness", lo=0, hi=1e9, lo_open=True)
    number(b.mass, "scene.body.mass", lo=0, hi=1e6, lo_open=True)   # kg; 1e12 was taken (probe, round 15)
    number(b.rail_height, "scene.body.rail_height")                                   # m
    number(b.rail_end, "scene.body.rail_end")                                         # m
    number(b.rail_friction, "scene.body.rail_friction", lo=0, hi=100.0)   # as a collider's friction (round 15)
    vel = list(b.velocity)
    if len(vel) != 3:
        raise InputError(f"expected 3 finite numbers (m/s), got {vel}", "scene.body.velocity")
    for i, v in enumerate(vel):   # 1e9 m/s ran "completed", the hair 1.2e8 m away (probe of issue 12, round 12)
        number(v, f"scene.body.velocity[{i}]", lo=-MAX_SPEED, hi=MAX_SPEED)


#: the size keys each collider shape reads (hairexp/model/builders.py build_collider)
SHAPE_SIZES = {"sphere": ("radius",), "capsule": ("radius", "half_length"), "box": ("half_extents",),
               "cylinder": ("radius", "half_height"), "plane": ()}


def _collider_sizes(cfg) -> None:
    """A size key a collider's shape does not read, set to other than the schema's default, is
    an error (a sphere's ``half_height=0.3`` was ignored without a word while its ``spin`` was
    refused; probe of issue 12, round 12)."""
    for i, c in enumerate(cfg.scene.colliders):
        shape = choice_name(c.shape)
        check_spin(shape, c.spin, f"scene.colliders[{i}]")   # the builder's own check, first: the shape's other key
        unread = [k for k in ("radius", "half_length", "half_height", "half_extents") if k not in SHAPE_SIZES.get(shape, ())]
        for k, v in changed_keys(c, ColliderConfig(), unread).items():
            uses = ", ".join(SHAPE_SIZES.get(shape, ())) or "no size"
            raise InputError(f"is {v}, but a {shape} does not read it (it reads {uses})", f"scene.colliders[{i}].{k}")


def _unused_measure_keys(cfg) -> None:
    """A warning for the ``measure.*`` keys, set to other than the schema's default, that the
    chosen measure does not read (``measure.time`` with collider_contact was accepted without a
    word; probe of issue 12, round 13)."""
    name = choice_name(cfg.measure.name)
    reads = MEASURE_KEYS.get(name, ())
    unread = [k for keys in MEASURE_KEYS.values() for k in keys if k not in reads]
    unused = changed_keys(cfg.measure, MeasureConfig(), list(dict.fromkeys(unread)))
    if unused:
        log.warning("%s not used: measure.name=%s reads %s", ", ".join(f"measure.{k}={v}" for k, v in unused.items())
                    + (" is" if len(unused) == 1 else " are"), name,
                    ", ".join(f"measure.{k}" for k in reads) if reads else "no measure keys")


def validate_config(cfg) -> None:
    """Every config key the layers below do not check where they read it (see module doc)."""
    _scene(cfg)
    _collider_sizes(cfg)
    _unused(cfg)
    _guides(cfg)
    _solver(cfg.solver)
    _tracking(cfg.tracking)
    _clusters(cfg)
    _collision(cfg.collision)
    _measure(cfg)
    _unused_measure_keys(cfg)


def validate_judge(cfg, measure_cfg) -> None:
    """An experiment's ``judge`` reads the measure its variants record (``measure_cfg``: a
    variant's ``measure``); a single run (``variants=[]``) has no judge to check."""
    judge, name = choice_name(cfg.judge), choice_name(measure_cfg.name)
    if judge != "none" and JUDGE_MEASURES[judge] != name:
        raise InputError(f"judge {judge} reads the measure {JUDGE_MEASURES[judge]}, but measure.name is {name}; "
                         f"set measure.name={JUDGE_MEASURES[judge]} (and its keys) or judge=none", "judge")


def validate_judge_controllers(cfg, names: list[str], controllers: list[str]) -> None:
    """An experiment's ``judge`` compares runs of the controllers it needs (``JUDGE_NEEDS``): its
    variants (``names``, with their ``controllers``) must include each, else it has no verdict."""
    judge = choice_name(cfg.judge)
    missing = missing_controllers(judge, controllers)
    if missing:
        raise InputError(f"{judge} needs a variant with " + " and one with ".join(f"controller.name={c}" for c in missing)
                         + f", and the variants ({', '.join(names)}) have none; add one or set judge=none", "judge")


def validate_measure(cfg, scene) -> None:
    """The measure's references into the built scene (``measure.collider``, the dynamic block of
    ``block_rail``), before the first step rather than after the whole simulation."""
    if choice_name(cfg.measure.name) == "block_rail" and scene.body is None:
        # it read a keyframed body's motion as a block leaving its rail, exit 0 (probe of issue 12)
        raise InputError("block_rail measures a dynamic block on its rail (scene.body.dynamic=true, the stylization "
                         "scene); this scene's body is keyframed", "measure.name")
    if choice_name(cfg.measure.name) == "block_rail":
        # the measure judges the body's own rail: with scene.body.rail_end=1.0 and the measure's 0.1 it
        # said the block left its rail at 0.12 s while it was on it, exit 0 (probe of issue 12)
        for key in ("rail_height", "rail_end"):
            mine, body = float(cfg.measure[key]), float(cfg.scene.body[key])
            if abs(mine - body) > 1e-12:
                raise InputError(f"is {mine:g}, but the dynamic body's rail has scene.body.{key} = {body:g}: block_rail "
                                 f"measures the block against its own rail; set measure.{key}={body:g} too",
                                 f"measure.{key}")
    if choice_name(cfg.measure.name) == "collider_contact":
        collider_named(scene, str(cfg.measure.collider))
    if choice_name(cfg.measure.name) == "clumps":   # measured at measure.time; < 0: the last frame
        end = int(cfg.frames) / float(cfg.fps)
        if float(cfg.measure.time) > end + 1e-9:
            raise InputError(f"is {float(cfg.measure.time)} s, after the run's end at {end:.6g} s (frames / fps); "
                             "give a time within the run, or < 0 for its last frame", "measure.time")


__all__ = ["validate_config", "late_keys", "unused_settings", "validate_judge", "validate_judge_controllers", "validate_measure", "number", "integer",
           "keyframes"]
