"""Findings of a probe of the Python API (2026-12-07), fixed: settings a dataclass config takes
without a word, a state with a NaN named only as "not finite", a sweep's comma list in
``compose_config``, and strands of impossible size."""

from __future__ import annotations

import dataclasses
from enum import Enum

import numpy as np
import pytest

from hairexp.errors import InputError


def _one_strand_scene():
    from hairexp.model import Material, RigidMotion, Scene, Strands

    line = np.stack([np.zeros(10), -np.linspace(0.0, 0.2, 10), np.zeros(10)], 1)
    strands = Strands.from_polylines(line, np.array([10]), 1e-4)
    still = RigidMotion(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))
    return Scene("one", strands, Material(1e-4, 10.0, 1e-7), still, np.array([0.0, -9.81, 0.0]), line)


@pytest.mark.parametrize("key, bad", [("derivatives", "bogus"), ("stretch_hessian", "exact"), ("compile", "maybe"),
                                      ("on_failure", "ignore"), ("on_failure", None), ("derivatives", 1)])
def test_the_simulator_refuses_a_solver_choice_the_config_does_not_have(key, bad):
    """``SolverConfig(on_failure="ignore")`` ran (and would not have substepped a failed step);
    ``derivatives="bogus"`` ran as the closed forms."""
    from hairexp.app.config import SolverConfig
    from hairexp.physics import Simulator

    with pytest.raises(InputError) as err:
        Simulator(_one_strand_scene(), dataclasses.replace(SolverConfig(), **{key: bad}))
    assert str(err.value).startswith(f"solver.{key}: must be one of ") and repr(bad) in str(err.value)


@pytest.mark.parametrize("key, bad", [("objects", "no"), ("hair_hair", "yes"), ("resolve", 1), ("friction", None),
                                      ("edge_response", "false"), ("plane_friction", 0.0)])
def test_the_simulator_refuses_a_collision_switch_that_is_not_a_bool(key, bad):
    """``CollisionConfig(objects="no")`` was true: the colliders stayed on; ``hair_hair="yes"``
    built the hair-hair stage from a string."""
    from hairexp.app.config import CollisionConfig, SolverConfig
    from hairexp.physics import Simulator

    with pytest.raises(InputError) as err:
        Simulator(_one_strand_scene(), SolverConfig(), collision_cfg=dataclasses.replace(CollisionConfig(), **{key: bad}))
    assert str(err.value).startswith(f"collision.{key}: must be true or false, got {type(bad).__name__}")


def test_the_simulator_takes_every_choice_the_config_offers():
    from hairexp.app.config import CollisionConfig, SolverConfig
    from hairexp.physics import Simulator

    Simulator(_one_strand_scene(), SolverConfig(derivatives="autograd", stretch_hessian="penalty", compile="off",
                                                on_failure="warn"),
              collision_cfg=CollisionConfig(objects=np.bool_(False), hair_hair=False))


@pytest.mark.parametrize("key, bad, said", [
    ("kkt", "bogus", "must be one of schur|reference, got str 'bogus'"),
    ("schur", "lu", "must be one of exact|krylov"),
    ("targets", "moving", "must be one of static|sliding"),
    ("elastic", "no", "must be true or false, got str 'no'"),
    ("secant", 0, "must be true or false, got int 0"),
    ("restore", "yes", "must be true or false"),
    ("exact_compression", None, "must be true or false"),
    ("krylov_tol", float("nan"), "got nan"),
    ("rtol", 2.0, "must be >= 0 and < 1, got 2"),
])
def test_the_tracking_controller_checks_its_settings_as_the_command_line_does(key, bad, said):
    """A TrackingConfig of the Python API took ``kkt="bogus"`` as the Schur solve and
    ``elastic="no"`` as true: the controller now checks its settings first (before it reads the
    scene or the guides), with the checks the config's validation runs."""
    from hairexp.app.config import TrackingConfig
    from hairexp.control.tracking.controller import TrackingController

    with pytest.raises(InputError) as err:
        TrackingController(None, None, dataclasses.replace(TrackingConfig(), **{key: bad}))
    assert str(err.value).startswith(f"tracking.{key}: ") and said in str(err.value)
    with pytest.raises(InputError, match=r"^tracking: must be a tracking config .* got dict"):
        TrackingController(None, None, {"rtol": 1e-5})


def _choices(enum: type[Enum]) -> tuple:
    return tuple(e.value for e in enum)


def test_the_layers_choices_are_the_configs():
    """The physics and tracking layers list the choices they accept (they cannot import the app's
    config); they must be the config's Enums, and their switches its bool fields."""
    from hairexp.app import config as C
    from hairexp.control.tracking.controller import TRACKING_CHOICES, TRACKING_FLAGS
    from hairexp.physics.simulator import COLLISION_CHOICES, COLLISION_FLAGS, SOLVER_CHOICES

    fields = {f.name: f for f in dataclasses.fields(C.SolverConfig)}
    for key, choices in SOLVER_CHOICES.items():
        assert set(choices) == set(_choices(fields[key].type if isinstance(fields[key].type, type)
                                            else getattr(C, fields[key].type))), key
    enum_fields = {cls: {f.name: getattr(C, f.type) if isinstance(f.type, str) else f.type for f in dataclasses.fields(cls)
                         if isinstance(getattr(C, f.type, None) if isinstance(f.type, str) else f.type, type)
                         and issubclass(getattr(C, f.type) if isinstance(f.type, str) else f.type, Enum)}
                   for cls in (C.SolverConfig, C.CollisionConfig, C.TrackingConfig)}
    assert set(enum_fields[C.SolverConfig]) == set(SOLVER_CHOICES)
    assert set(enum_fields[C.CollisionConfig]) == set(COLLISION_CHOICES)
    for key, enum in enum_fields[C.CollisionConfig].items():
        assert set(COLLISION_CHOICES[key]) == set(_choices(enum)), key
    checked_elsewhere = {"assignment", "point_placement"}   # correspondence.check_correspondence_options
    assert set(enum_fields[C.TrackingConfig]) == set(TRACKING_CHOICES) | checked_elsewhere
    for key, enum in enum_fields[C.TrackingConfig].items():
        if key not in checked_elsewhere:
            assert set(TRACKING_CHOICES[key]) == set(_choices(enum)), key

    def bools(cls):
        return {f.name for f in dataclasses.fields(cls) if f.type in (bool, "bool")}

    assert bools(C.CollisionConfig) == set(COLLISION_FLAGS)
    assert bools(C.TrackingConfig) == set(TRACKING_FLAGS)


@pytest.mark.parametrize("field, what", [("x", "positions"), ("v", "velocities")])
def test_a_state_that_is_not_finite_is_named_by_field_vertex_and_strand(field, what):
    """It said "the state's positions or velocities are not finite" (a ValueError)."""
    from hairexp.app.config import SolverConfig
    from hairexp.physics import Simulator

    sim = Simulator(_one_strand_scene(), SolverConfig())
    state = sim.initial_state()
    values = getattr(state, field).copy()
    values[7, 1] = np.nan
    with pytest.raises(InputError) as err:
        sim.step(dataclasses.replace(state, **{field: values}), 0.01)
    assert str(err.value).startswith(f"Simulator.step: state.{field}: the state's {what} are not finite: vertex 7 "
                                     "(strand 0, vertex 7 along it)")


def test_compose_config_names_a_sweeps_comma_list():
    """Hydra's four-line "Ambiguous value for argument" came through the Python API."""
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as err:
        compose_config(["solver.rtol=1e-4,1e-6"])
    msg = str(err.value)
    assert msg.startswith("solver.rtol: '1e-4,1e-6' is several values") and "\n" not in msg
    assert "python -m hairexp -m solver.rtol=1e-4,1e-6" in msg


def test_strands_of_impossible_size_are_named():
    """A curve at 1e300 m got an infinite length and one 120 m long was built."""
    from hairexp.errors import ExtentError
    from hairexp.model import Strands

    line = np.stack([np.zeros(10), -np.linspace(0.0, 0.2, 10), np.zeros(10)], 1)
    with pytest.raises(ExtentError, match=r"^hair: curve 1 vertex 1 is at .* more than 10000 m from the origin"):
        Strands.from_polylines(np.concatenate([line, 1e300 * line]), np.array([10, 10]), 1e-4, where="hair")
    with pytest.raises(InputError, match=r"^hair: curve 2 is 120 m long, more than 100 m: .*check the units"):
        Strands.from_polylines(np.concatenate([line, 3 * line, 600 * line]), np.array([10, 10, 10]), 1e-4, where="hair")
    s = Strands.from_polylines(np.concatenate([line, 3 * line, 400 * line]), np.array([10, 10, 10]), 1e-4)
    assert np.allclose(s.strand_lengths(), [0.2, 0.6, 80.0])


def test_guide_animation_names_a_motion_or_a_file_of_the_wrong_kind(tmp_path):
    """``GuideAnimation(..., motion="x")`` was taken (and failed at the first shape_at), and
    ``save(None)`` said "'NoneType' object has no attribute 'write'"."""
    import io

    from hairexp.guides.animation import GuideAnimation
    from hairexp.model import RigidMotion

    P = np.zeros((2, 4, 3))
    P[:, :, 1] = -np.linspace(0.0, 0.3, 4)
    for wrong in ("x", 5, {"times": [0.0]}):
        with pytest.raises(InputError, match=r"^guides: the body motion must be a rigid motion .* got " + type(wrong).__name__):
            GuideAnimation(P, np.array([0, 4]), 25.0, motion=wrong)
    still = RigidMotion(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))
    g = GuideAnimation(P, np.array([0, 4]), 25.0, motion=still)
    assert np.allclose(g.shape_at(0.02), P[0])
    for wrong in (None, 3):
        with pytest.raises(InputError, match=r"^guides: save needs a path or a binary file open for writing"):
            g.save(wrong)
    buf = io.BytesIO()
    g.save(buf)
    g.save(tmp_path / "g.npz")
    buf.seek(0)
    for src in (buf, tmp_path / "g.npz"):
        with np.load(src) as z:
            assert np.array_equal(z["guide_positions"], P) and list(z["guide_offsets"]) == [0, 4]


def test_a_scenes_arrays_are_read_only_copies():
    """``scene.gravity[1] = -20`` after the Simulator was built changed the scene under its
    gravity term without a word; a scene with other values is ``dataclasses.replace``'s."""
    scene = _one_strand_scene()
    g = np.array([0.0, -9.81, 0.0])
    scene = dataclasses.replace(scene, gravity=g)
    g[1] = -20.0
    assert scene.gravity[1] == -9.81
    for key in ("gravity", "root_body"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(scene, key)[0] = 1.0
    moved = dataclasses.replace(scene, gravity=[0.0, -3.7, 0.0])
    assert moved.gravity.dtype == np.float64 and moved.gravity[1] == -3.7 and scene.gravity[1] == -9.81


def test_run_names_an_out_dir_or_config_of_the_wrong_kind():
    """``run(cfg, 5)`` said "expected str, bytes or os.PathLike object, not int"."""
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]"])
    for bad in (5, "", None):
        with pytest.raises(TypeError, match=r"^run: out_dir must be a folder path \(str or pathlib.Path\), got"):
            run(cfg, bad)
    with pytest.raises(TypeError, match=r"^run: cfg must be a composed config"):
        run({}, "/tmp/nowhere")


@pytest.fixture(scope="module")
def tracked_smoke():
    """A tracked goaling_smoke run of 6 strands and 4 frames, and one with 8 strands."""
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    base = ["experiment=goaling_smoke", "variants=[]", "controller.name=tracking", "frames=4", "logging.rerun=false"]
    return (assemble(compose_config([*base, "scene.n_strands=6"])),
            assemble(compose_config([*base, "scene.n_strands=8"])))


def test_simulator_step_refuses_states_a_tracked_run_cannot_take(tracked_smoke):
    """Each of these gave a raw traceback deep in the step, or ran: a free run's state (control
    None: an AttributeError in the SQP), another run's iterates or history (a matmul or broadcast
    error), a state at t = 1e6 (tracked still guides and said converged), integer positions
    ("diverged ... try a smaller solver.dt"), positions with a zero-length edge."""
    from hairexp.physics.state import State

    run, other = tracked_smoke
    sim, s = run.simulator, run.initial_state()
    step_state = sim.step(s, run.dt)[0]
    x0 = s.x.copy()
    other_state = other.simulator.step(other.initial_state(), other.dt)[0]
    cases = [
        (dataclasses.replace(s, control=None), "state.control: must be the tracking controller's iterates"),
        (dataclasses.replace(s, control="x"), "state.control: must be the tracking controller's iterates"),
        (dataclasses.replace(step_state, history=other_state.history), "has the shape (80, 3), not the scene's (60, 3)"),
        (dataclasses.replace(s, time=1e6), "state.time: the step reaches t = 1e+06 s, outside the guide animation"),
        (dataclasses.replace(s, time=-1.0), "outside the guide animation"),
        (dataclasses.replace(s, x=s.x.astype(int)), "state.x: the state's positions must be floating-point numbers, got dtype int64"),
        (dataclasses.replace(s, v=s.v.astype(complex)), "state.v: the state's velocities must be floating-point numbers"),
    ]
    zero = s.x.copy()
    zero[4] = zero[3]
    cases.append((dataclasses.replace(s, x=zero), "state.x: the state's positions put vertices 3 and 4 (strand 0, vertices 3 and 4"))
    for state, said in cases:
        with pytest.raises(InputError) as err:
            sim.step(state, run.dt)
        assert str(err.value).startswith("Simulator.step: ") and said in str(err.value), str(err.value)
    assert np.array_equal(s.x, x0)    # never modified
    # lists are numbers too: the same step as the arrays'
    as_lists = State(s.time, s.x.tolist(), s.v.tolist(), s.tensions, s.control, s.body, s.history)
    a, b = sim.step(s, run.dt)[0], sim.step(as_lists, run.dt)[0]
    assert np.array_equal(a.x, b.x)


def test_simulator_observe_checks_the_state_as_step_does(tracked_smoke):
    """``observe`` of an 8-strand state on a 6-strand run returned a residual of the wrong hair;
    ``observe(None)`` an AttributeError."""
    run, other = tracked_smoke
    with pytest.raises(InputError, match=r"^Simulator.observe: state.x, state.v: .* must have the scene's shape \(60, 3\)"):
        run.simulator.observe(other.initial_state())
    with pytest.raises(TypeError, match=r"^Simulator.observe: state must be a hairexp State"):
        run.simulator.observe(None)
    assert run.simulator.observe(run.initial_state())["residual_rel_max"] < 1e-9
