"""solver.integrator (hairexp/physics/integrators.py): implicit Euler unchanged, BDF2 and
generalized-alpha against their linear analysis, the hanging chain's period and decay, energy,
the first step and substep recovery, the collision-stage history, every controller, the dynamic
body and simulated guides with bdf2, and the config check."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from integrator_reference import SOLVER, reference_runs
from hairexp.errors import InputError
from hairexp.evaluation.fidelity_chain import chain_scene, first_mode, linear_prediction, measure_chain
from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Material, Scene
from hairexp.model.strands import Strands
from hairexp.physics import simulator as simulator_module
from hairexp.physics.collisions import CollisionInfo
from hairexp.physics.info import CONVERGED, MAX_ITERATIONS
from hairexp.physics.integrators import (INTEGRATORS, LMM2_ALPHA, LMM2_BETA, LMM2_CALM_STEPS, GeneralizedAlpha,
                                         bdf2_coefficients, make_integrator)
from hairexp.physics.simulator import Simulator

DATA = Path(__file__).resolve().parent / "data"
DT = 0.04


def solver(integrator: str, **kw):
    return SimpleNamespace(**{**SOLVER, "integrator": integrator, **kw})


# -- implicit Euler is unchanged -------------------------------------------------------------
def test_implicit_euler_is_bit_identical_to_the_code_before_solver_integrator():
    """tests/data/implicit_euler_reference.npz was made by the code before this key existed
    (tests/integrator_reference.py): damped, dragged strands on a swung root."""
    ref = np.load(DATA / "implicit_euler_reference.npz")
    # Bit-identical on the CPU kind that made the reference (AMD EPYC); another kind's BLAS/LAPACK
    # code paths round differently at the last place (measured on an Intel Xeon: 5.6e-17 m in x,
    # 1.4e-15 m/s in v).  1e-13 is ~1000 ulp of the 0.15 m / 0.28 m/s magnitudes; bdf2 differs by > 1e-6.
    run = reference_runs(integrator="implicit_euler")
    assert np.abs(run["x"] - ref["x"]).max() <= 1e-13 and np.abs(run["v"] - ref["v"]).max() <= 1e-13
    # a solver config without the key takes the default integrator (trbdf2, not implicit Euler)
    default = reference_runs()
    assert np.array_equal(default["x"], reference_runs(integrator="trbdf2")["x"])
    other = reference_runs(integrator="bdf2")
    assert not np.allclose(other["x"], ref["x"], atol=1e-6)    # the reference can tell schemes apart


# -- linear 1-DOF spring: the schemes' own recursions -----------------------------------------
W, L0, RHO = 12.5, 0.02, 2e-4   # rad/s, m, kg/m


def spring_scene(stretch: float = 0.002) -> Scene:
    """One free vertex on an axial spring below two kinematic root vertices, no gravity, no
    bending: motion along the spring is exactly linear, x'' = -W^2 x (x: stretch, m)."""
    pts = np.zeros((3, 3))
    pts[:, 1] = -L0 * np.arange(3)
    s = Strands.from_polylines(pts, np.array([3]), RHO, where="spring")
    m = s.masses[2]
    k = W * W * m * L0                              # EA with (EA / l0) = m W^2
    x0 = pts.copy()
    x0[2, 1] -= stretch
    return Scene("spring", s, Material(RHO, k, 0.0), RigidMotion.static(), np.zeros(3), x0, initial=x0)


def spring_run(integrator: str, n: int, dt: float = DT):
    sim = Simulator(spring_scene(), solver(integrator, rtol=1e-10, atol=1e-17))
    st = sim.initial_state()
    xs, vs = [-(st.x[2, 1] + 2 * L0)], [0.0]
    for _ in range(n):
        st, info = sim.step(st, dt)
        assert info.converged
        xs.append(-(st.x[2, 1] + 2 * L0))
        vs.append(-st.v[2, 1])
    return np.array(xs), np.array(vs)


def recursion(integrator: str, x0: float, n: int, dt: float = DT):
    """The scheme written as a scalar recursion on x'' = -W^2 x (independent of the objective)."""
    xs, vs = [x0], [0.0]
    w2 = W * W
    if integrator in ("implicit_euler", "bdf2"):
        x1 = xs[0] / (1 + w2 * dt * dt)               # implicit Euler (BDF2's first step)
        xs.append(x1)
        vs.append((x1 - xs[0]) / dt)
        b = 2 * dt / 3
        for _ in range(n - 1):
            xp, vp, xc, vc = xs[-2], vs[-2], xs[-1], vs[-1]
            if integrator == "implicit_euler":
                x1 = (xc + dt * vc) / (1 + w2 * dt * dt)
                v1 = (x1 - xc) / dt
            else:
                x1 = (4 / 3 * xc - 1 / 3 * xp + b * (4 / 3 * vc - 1 / 3 * vp)) / (1 + b * b * w2)
                v1 = (x1 - 4 / 3 * xc + 1 / 3 * xp) / b
            xs.append(x1)
            vs.append(v1)
    elif integrator == "trbdf2":
        # TR stage to gamma dt: x_g = x + g dt v + (g dt/2)^2 (a(x) + a(x_g)), v_g = 2 (x_g - x)/(g dt) - v;
        # BDF2 stage (Bank et al. 1985): x1 = [x_g - (1 - g)^2 x]/(g (2 - g)) + (1 - g) dt/(2 - g) v1
        g = 2 - np.sqrt(2)
        tau, beta = 0.5 * g * dt, (1 - g) * dt / (2 - g)
        c0, c1 = 1 / (g * (2 - g)), (1 - g) ** 2 / (g * (2 - g))
        x, v = x0, 0.0
        for _ in range(n):
            xg = (x + g * dt * v - tau * tau * w2 * x) / (1 + tau * tau * w2)
            vg = 2 * (xg - x) / (g * dt) - v
            # v1 = c0 v_g - c1 v + beta a(x1), x1 = c0 x_g - c1 x + beta v1
            x1 = (c0 * xg - c1 * x + beta * (c0 * vg - c1 * v)) / (1 + beta * beta * w2)
            v = c0 * vg - c1 * v - beta * w2 * x1
            x = x1
            xs.append(x)
            vs.append(v)
    elif integrator == "lmm2":
        # sum_j alpha_j x_{n+j} = dt sum_j beta_j v_{n+j}, sum_j alpha_j v_{n+j} = dt sum_j beta_j a_{n+j},
        # a = -W^2 x; the first step is implicit Euler, then LMM2_CALM_STEPS steps of BDF2
        (a0, a1, _), (b0, b1, b2) = LMM2_ALPHA, LMM2_BETA
        x1 = xs[0] / (1 + w2 * dt * dt)
        xs.append(x1)
        vs.append((x1 - xs[0]) / dt)
        b = 2 * dt / 3
        for k in range(n - 1):
            xp, vp, xc, vc = xs[-2], vs[-2], xs[-1], vs[-1]
            if k < LMM2_CALM_STEPS:   # BDF2 after the (re)start
                x2 = (4 / 3 * xc - 1 / 3 * xp + b * (4 / 3 * vc - 1 / 3 * vp)) / (1 + b * b * w2)
                xs.append(x2)
                vs.append((x2 - 4 / 3 * xc + 1 / 3 * xp) / b)
                continue
            # x2 - dt b2 v2 = rx, v2 + dt b2 W^2 x2 = rv
            rx = -a1 * xc - a0 * xp + dt * (b1 * vc + b0 * vp)
            rv = -a1 * vc - a0 * vp - dt * w2 * (b1 * xc + b0 * xp)
            x2 = (rx + dt * b2 * rv) / (1 + (dt * b2) ** 2 * w2)
            xs.append(x2)
            vs.append(rv - dt * b2 * w2 * x2)
    else:
        g = GeneralizedAlpha()
        am, af, gm, be = g.alpha_m, g.alpha_f, g.gamma, g.beta
        x, v, a = x0, 0.0, -w2 * x0
        for _ in range(n):
            xs_ = x + dt * v + dt * dt * (0.5 - be) * a
            x1 = ((1 - am) * xs_ / (be * dt * dt) - am * a - w2 * af * x) / ((1 - am) / (be * dt * dt) + w2 * (1 - af))
            a1 = (x1 - xs_) / (be * dt * dt)
            v = v + dt * ((1 - gm) * a + gm * a1)
            x, a = x1, a1
            xs.append(x)
            vs.append(v)
    return np.array(xs), np.array(vs)


@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_spring_follows_the_schemes_recursion(integrator):
    x, v = spring_run(integrator, 60)
    xr, vr = recursion(integrator, x[0], 60)
    assert np.allclose(x, xr, rtol=0, atol=1e-9 * abs(x[0])), np.abs(x - xr).max()
    assert np.allclose(v, vr, rtol=0, atol=1e-9 * abs(x[0]) * W)


def test_bdf2_spring_matches_the_analytic_amplification_factor():
    """x_n = Re(C lambda^n) once the spurious root has decayed: lambda is the principal root of
    (1 - i beta W dt... ) zeta^2 - 4/3 zeta + 1/3 = 0 with beta = 2 dt / 3 (BDF2 on x' = v,
    v' = -W^2 x).  The trajectory fixes 2 Re(lambda) and |lambda|^2 through
    x_{n+1} = 2 Re(lambda) x_n - |lambda|^2 x_{n-1}."""
    x, _ = spring_run("bdf2", 80)
    b = 2 * DT / 3
    roots = np.roots([1 - 1j * b * W, -4 / 3, 1 / 3])
    lam = roots[np.argmax(np.abs(roots))]
    t = x[40:]
    A = np.stack([t[1:-1], -t[:-2]], 1)
    (p, q), *_ = np.linalg.lstsq(A, t[2:], rcond=None)
    assert p == pytest.approx(2 * lam.real, abs=1e-7)
    assert q == pytest.approx(abs(lam) ** 2, abs=1e-7)
    assert abs(lam) < 1 and abs(lam) > 1 / (1 + W * DT)   # damped, less than implicit Euler


def spring_energy(x, v):
    m = 1.0
    return 0.5 * m * v ** 2 + 0.5 * m * W * W * x ** 2


@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_spring_energy_never_increases(integrator):
    """Implicit Euler: the energy.  BDF2 (a two-step scheme): its G-norm energy
    1/4 (E(y_n) + E(2 y_n - y_{n-1})) (Dahlquist's G-stability), from the first step that has
    history.  Generalized-alpha (state x, v, a): the energy at the end of each period (its
    energy oscillates within a period, by a few % at W dt = 0.5)."""
    x, v = spring_run(integrator, 120)
    E = spring_energy(x, v)
    if integrator in ("implicit_euler", "trbdf2"):   # TR-BDF2: one-step, its energy itself
        assert np.all(np.diff(E) <= 1e-12 * E[0])
    elif integrator == "bdf2":
        EG = 0.25 * (E[1:] + spring_energy(2 * x[1:] - x[:-1], 2 * v[1:] - v[:-1]))
        assert np.all(np.diff(EG) <= 1e-12 * E[0])
    else:
        per = int(round(2 * np.pi / (W * DT)))
        peaks = [E[k:k + per].max() for k in range(0, len(E) - per, per)]
        assert np.all(np.diff(peaks) <= 1e-9 * E[0]) and peaks[-1] < E[0]


def test_variable_step_bdf2_is_exact_for_quadratics():
    """x_{n+1} - a0 x_n + a1 x_{n-1} = beta x'(t_{n+1}) for x = c0 + c1 t + c2 t^2, any ratio w."""
    rng = np.random.default_rng(3)
    for w in (0.25, 0.5, 1.0, 2.0):
        a0, a1, b = bdf2_coefficients(w)
        h_prev, h = 0.04, 0.04 * w
        c = rng.normal(size=3)
        x = lambda t: c[0] + c[1] * t + c[2] * t * t    # noqa: E731
        dx = lambda t: c[1] + 2 * c[2] * t              # noqa: E731
        t0, t1, t2 = 0.3, 0.3 + h_prev, 0.3 + h_prev + h
        assert x(t2) - a0 * x(t1) + a1 * x(t0) == pytest.approx(b * h * dx(t2), abs=1e-14)
    assert bdf2_coefficients(1.0) == pytest.approx((4 / 3, 1 / 3, 2 / 3))


# -- the hanging chain ------------------------------------------------------------------------
#: (integrator, dt): measured amplitude per period and period error must match the linear
#: analysis at omega dt within these (the nonlinear chain, 1 cm swing, its first mode)
CHAIN_TOL_AMP, CHAIN_TOL_PERIOD = 0.005, 0.002


@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_hanging_chain_period_and_decay_match_the_linear_analysis(integrator):
    r = measure_chain(integrator, DT)
    amp, per = linear_prediction(integrator, r.omega_dt)
    assert r.amplitude_per_period == pytest.approx(amp, abs=CHAIN_TOL_AMP)
    assert r.period_error == pytest.approx(per, abs=CHAIN_TOL_PERIOD)
    # the linearised discrete chain is the continuum chain within 3 % (19 free masses)
    assert r.period_linear == pytest.approx(r.period_continuum, rel=0.03)
    if integrator == "implicit_euler":       # issue 13's numbers
        assert r.amplitude_per_period == pytest.approx(0.417, abs=0.005) and r.period_error > 0.02
    else:
        assert r.amplitude_per_period > 0.9


def test_linear_prediction_of_implicit_euler_is_its_closed_form():
    """|1/(1 - i W)|^(2 pi / arg) for implicit Euler (independent of the matrix in the module)."""
    Wdt = 0.28
    lam = 1 / (1 - 1j * Wdt)
    steps = 2 * np.pi / np.angle(lam)
    amp, per = linear_prediction("implicit_euler", Wdt)
    assert amp == pytest.approx(abs(lam) ** steps, rel=1e-12)
    assert per == pytest.approx(steps * Wdt / (2 * np.pi) - 1, rel=1e-12)


@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_chain_first_mode_energy_never_increases_after_release(integrator):
    """No input after the root stops (0.4 s).  The energy of the chain's first mode,
    E(q, q') = 1/2 (q'^2 + omega^2 q^2) with q the mass-weighted projection on the mode shape (the
    full energy of the nonlinear chain also swaps with the stiff stretch at twice the swing
    frequency).  Implicit Euler: E itself.  BDF2 (two-step): its G-norm energy
    1/4 (E(y_n) + E(2 y_n - y_{n-1})) (Dahlquist's G-stability).  Generalized-alpha (state x, v, a)
    and TR-BDF2 (whose E at a step moves by ~4e-4 of E as the mode trades energy with the others):
    E's maximum over each half period (E oscillates within a period; it keeps 99.99 % of the
    amplitude per period, and the peaks move by ~1e-4 of E through the coupling to the other
    modes, so the bound is 5e-4 of E)."""
    sc = chain_scene()
    omega, phi = first_mode(sc)
    free = np.flatnonzero(~sc.strands.kinematic)
    mphi = sc.strands.masses[free] * phi
    sim = Simulator(sc, solver(integrator, rtol=1e-9, atol=1e-14))
    st = sim.initial_state()
    q, dq = [], []
    for _ in range(60):
        st, info = sim.step(st, DT)
        assert info.converged
        if st.time >= 0.4 - 1e-9:
            q.append(float(mphi @ (st.x[free, 0] - st.x[0, 0])))
            dq.append(float(mphi @ st.v[free, 0]))
    q, dq = np.array(q), np.array(dq)
    E = 0.5 * (dq ** 2 + omega ** 2 * q ** 2)
    tol = 1e-6 * E.max()
    if integrator == "implicit_euler":
        assert np.all(np.diff(E) <= tol) and E[-1] < 0.5 * E[0]
    elif integrator == "bdf2":
        G = 0.25 * (E[1:] + 0.5 * ((2 * dq[1:] - dq[:-1]) ** 2 + omega ** 2 * (2 * q[1:] - q[:-1]) ** 2))
        assert np.all(np.diff(G) <= tol) and G[-1] < G[0]
    else:
        half = 11                                       # steps per half period at dt 0.04 s
        peaks = [E[k:k + half].max() for k in range(0, len(E) - half + 1, half)]
        assert np.all(np.diff(peaks) <= 5e-4 * E.max()) and peaks[-1] <= peaks[0] * (1 + 2e-4)


# -- first step, substep recovery, collision history ---------------------------------------------
@pytest.mark.parametrize("integrator", ["bdf2", "generalized_alpha"])
def test_first_step_has_no_history_and_a_documented_start(integrator):
    sc = chain_scene()
    st0 = Simulator(sc, solver("implicit_euler")).initial_state()
    assert st0.history is None
    sim = Simulator(sc, solver(integrator))
    assert sim.integrator.plan(sim, st0, DT).note == "start"
    st1, _ = sim.step(st0, DT)
    assert st1.history is not None and sim.integrator.plan(sim, st1, DT).note == ""
    if integrator == "bdf2":   # the start is one implicit Euler step
        ie1, _ = Simulator(sc, solver("implicit_euler")).step(st0, DT)
        assert np.array_equal(st1.x, ie1.x) and np.array_equal(st1.v, ie1.v)
        assert np.array_equal(st1.history.x, st0.x) and st1.history.dt == DT


def recovered_step(integrator: str, monkeypatch):
    """The swung chain under ``integrator``, 12 steps in; from there one step whose first full-dt
    attempt fails (the recovery redoes it as two halves).  Returns (sim, st: the state before that
    step, the recovered state, and the halves stepped by hand from st: mid, end)."""
    sim = Simulator(chain_scene(), solver(integrator))
    st = sim.initial_state()
    for _ in range(12):
        st, _ = sim.step(st, DT)
    orig = sim._attempt
    calls = []

    def failing(state, dt):
        new, info = orig(state, dt)
        calls.append(dt)
        if dt == DT and len(calls) == 1:
            info.status = MAX_ITERATIONS
        return new, info

    monkeypatch.setattr(sim, "_attempt", failing)
    rec, info = sim.step(st, DT)
    assert info.recovered and info.substeps == 2 and calls == [DT, DT / 2, DT / 2]
    monkeypatch.setattr(sim, "_attempt", orig)
    mid, _ = sim.step(st, DT / 2)
    end, _ = sim.step(mid, DT / 2)
    assert np.array_equal(rec.x, end.x) and np.array_equal(rec.v, end.v)
    return sim, st, rec, mid, end


def test_bdf2_substep_recovery_uses_the_step_ratio_and_leaves_the_right_history(monkeypatch):
    """A step that fails at dt is redone as two halves: the same as stepping dt/2 twice (first
    with w = 1/2, then w = 1), the history is the middle state and dt/2, and the next full step
    (w = 2) stays on the chain's motion."""
    sim, st, rec, mid, end = recovered_step("bdf2", monkeypatch)
    assert rec.history.dt == DT / 2 and np.array_equal(rec.history.x, mid.x) and np.array_equal(rec.history.v, mid.v)
    a0, a1, b = bdf2_coefficients(0.5)
    p = sim.integrator.plan(sim, st, DT / 2)
    assert p.h == pytest.approx(b * DT / 2) and np.allclose(p.x_ref, a0 * st.x - a1 * st.history.x)
    # the next full step (w = 2) and one without the recovery agree to the scheme's accuracy
    nxt, _ = sim.step(rec, DT)
    plain, _ = sim.step(sim.step(st, DT)[0], DT)
    swing = np.abs(st.x[:, 0]).max()
    assert np.abs(nxt.x - plain.x).max() < 0.05 * swing


def test_bdf2_history_follows_a_collision_impulse(monkeypatch):
    """A collision stage that stops a moving vertex (inelastic, no forces otherwise): with the
    history shifted by the stage's correction it stays stopped; BDF2's recursion on the raw
    history would bring back half the removed velocity (v -> 1.5 dv total change)."""
    pts = np.zeros((3, 3))
    pts[:, 1] = -L0 * np.arange(3)
    s = Strands.from_polylines(pts, np.array([3]), RHO, where="impulse")
    sc = Scene("impulse", s, Material(RHO, 1e-12, 0.0), RigidMotion.static(), np.zeros(3), pts.copy())
    sim = Simulator(sc, solver("bdf2"))
    st = sim.initial_state()
    st.v[2] = [0.1, 0.0, 0.0]                       # the free vertex moves sideways
    calls = []

    def stage(cfg, scene, hh, x0, x1, t0, t1, dt, limiter=None, volume_dt=None, dist_out=None, push=None, solved=None):
        calls.append(t1)
        v1 = (x1 - x0) / dt
        if len(calls) == 3:                         # the third step: stopped dead
            x1 = x1.copy()
            x1[2] = x0[2]
            v1[2] = 0.0
        return x1, v1, CollisionInfo()

    monkeypatch.setattr(simulator_module, "collision_stage", stage)
    sim.collide_objects = True
    sim.collision_cfg = SimpleNamespace()
    vs = []
    for _ in range(8):
        st, _ = sim.step(st, DT)
        vs.append(st.v[2, 0])
    assert vs[1] == pytest.approx(0.1, rel=1e-6) and vs[2] == 0.0
    assert np.allclose(vs[3:], 0.0, atol=1e-9), vs


@pytest.mark.parametrize("resolve,resting", [(False, 4), (True, 2)])
def test_bdf2_strand_lands_on_a_plane_and_rests_on_it(resolve, resting):
    """A real collision stage (tests/test_collisions.py's dropped strand, 50 steps): never inside
    the thickness shell, and the vertices that end on the plane stayed on it for the last 10
    steps with zero normal velocity (no bounce from the history).  The stage alone ends with the
    last three vertices of each strand flat on the plane; with the contact planes (the default)
    each strand's tip rests on it while the rest still swings above at 2 s (friction acts on the
    vertices in contact only, the stage's positional friction no longer holds the others).  The
    resting tips keep their planes in the next step's first solve (``Simulator._resting_planes``):
    no second solve once they rest (the landing's steps 2-5 and 12 solve twice), 248 Newton
    iterations in all against the stage alone's 273 (666 when every step of resting contact solved
    twice, 1,048 with the planes' earlier C^2 penalty)."""
    from omegaconf import OmegaConf
    from test_collisions import collider, deepest, make_scene

    from hairexp.app.config import CollisionConfig

    col = collider("plane", at=(0.0, -0.1, 0.0), thickness=0.002, friction=0.5)
    scene = make_scene([col], n_strands=2, n_vertices=12, length=0.3, direction=[1.0, 0.0, 0.0], spread=0.2)
    sim = Simulator(scene, solver("bdf2"), collision_cfg=OmegaConf.structured(CollisionConfig(resolve=resolve)))
    second = []   # the step start of every second solve with contact planes
    resolve_contacts = sim._resolve_contacts
    sim._resolve_contacts = lambda st_, *a, **k: (second.append(st_.time), resolve_contacts(st_, *a, **k))[1]
    st = sim.initial_state()
    states, contacts = [], 0
    for _ in range(50):
        st, info = sim.step(st, DT)
        assert info.converged
        contacts += info.object_contacts
        states.append(st)
    assert contacts > 0 and deepest(scene, [None] + states) <= 1e-9
    if resolve:   # second solves while landing only: the resting hair's planes hold it after that
        assert second and max(second) < 20 * DT, second
    shell = -0.1 + 0.002
    on = (~scene.strands.kinematic) & (np.abs(states[-1].x[:, 1] - shell) < 1e-6)
    assert on.sum() >= resting
    for s_ in states[-10:]:
        assert np.all(np.abs(s_.x[on, 1] - shell) < 1e-6) and np.all(s_.v[on, 1] == 0.0)


# -- controllers, dynamic body, guides with bdf2 ----------------------------------------------
def goaling_run(controller: str, integrator: str, frames: int = 4):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=goaling_smoke", f"controller.name={controller}", f"frames={frames}",
                          "logging.rerun=false", "logging.progress=false", "solver.compile=off",
                          "scene.hair.edge_damping=0.002", "scene.hair.air_drag=0.5",
                          f"solver.integrator={integrator}"])
    run = assemble(cfg)
    states, infos = [], []
    for _, _, st, info in run.steps():
        states.append(st)
        infos.append(info)
    return run, states, infos


@pytest.mark.parametrize("integrator", ["bdf2", "trbdf2", "lmm2"])
@pytest.mark.parametrize("controller", ["free", "attract", "skinned", "tracking"])
def test_every_controller_runs_with_bdf2(controller, integrator):
    run, states, infos = goaling_run(controller, integrator)
    assert all(i.status == CONVERGED for i in infos)
    assert all(np.isfinite(s.x).all() and np.isfinite(s.v).all() for s in states)
    if integrator == "bdf2":
        assert states[-1].history is not None and states[-1].history.dt == run.dt
    elif integrator == "lmm2":   # the previous start and both accelerations, at the run's step (no restart)
        h = states[-1].history
        assert h.dt == run.dt and h.x is not None and h.a is not None and h.a_prev is not None
        assert all(i.substeps == 1 and not i.recovered for i in infos)
    else:                 # carries only the end acceleration (the next trapezoidal stage's a_0)
        h = states[-1].history
        assert h.x is None and h.a is not None and all(i.substeps == 1 and not i.recovered for i in infos)
    _, ie_states, _ = goaling_run(controller, "implicit_euler")
    d = np.abs(states[-1].x - ie_states[-1].x).max()
    assert 0 < d < 0.01                              # another scheme, the same motion
    if controller == "skinned":                      # positions are the guides'; the effort is bdf2's
        assert run.simulator.control_effort(states[-1]) is not None
    if controller == "tracking":
        assert infos[-1].constraint_norm <= run.controller.opts.ctol


@pytest.mark.parametrize("integrator", ["bdf2", "trbdf2", "lmm2"])
def test_simulated_guides_use_the_run_integrator(integrator):
    """goaling_smoke's guides are simulated (hairexp/app/guides.py) with the run's integrator;
    the body starts moving at 0.2 s (frame 5)."""
    run_b, _, _ = goaling_run("skinned", integrator, frames=10)
    run_e, _, _ = goaling_run("skinned", "implicit_euler", frames=10)
    gb, ge = run_b.guides.positions, run_e.guides.positions
    assert np.isfinite(gb).all() and np.array_equal(gb[0], ge[0]) and not np.allclose(gb, ge, atol=1e-6)


@pytest.mark.parametrize("integrator", ["bdf2", "trbdf2", "lmm2"])
def test_dynamic_body_with_bdf2(integrator):
    """Hanging hair on a block on a frictionless rail stays at rest; a block sliding on a rail
    with friction decelerates at mu g with light hair on it (tests/test_dynamic_body.py)."""
    from test_dynamic_body import G, POSITION, VELOCITY, dyn_scene, hair_mass

    scene = dyn_scene(dict(mass=0.01, rail_height=0.0, rail_end=0.1, rail_friction=0.0), n_strands=3, n_vertices=8)
    sim = Simulator(scene, solver(integrator, rtol=1e-10))
    st = sim.initial_state()
    x0 = st.x.copy()
    for _ in range(30):
        st, info = sim.step(st, DT)
        assert info.converged
    # at rest to round-off (trbdf2: -9e-17 m from its two stages of gamma dt and (1 - gamma) dt)
    assert np.abs(st.body[POSITION]).max() <= 1e-12 and np.max(np.abs(st.x - x0)) < 1e-4
    mu = 0.3
    scene = dyn_scene(dict(mass=0.01, rail_end=10.0, rail_friction=mu, velocity=[0.5, 0.0, 0.0]),
                      n_strands=3, n_vertices=8)
    assert hair_mass(scene) / scene.motion.mass < 0.01
    sim = Simulator(scene, solver(integrator))
    st = sim.initial_state()
    v = [0.5]
    for _ in range(12):
        st, info = sim.step(st, 0.01)
        assert info.converged and st.history is not None
        v.append(st.body[VELOCITY][0])
    assert np.allclose(-np.diff(v) / 0.01, mu * G, rtol=0.03)


# -- settle and validation ------------------------------------------------------------------------
def test_settle_phase_uses_implicit_euler_whatever_the_integrator():
    from hairexp.physics.settle import settle_state

    sc = chain_scene(swing=0.0)
    a = settle_state(sc, solver("bdf2"), None, 0.2, DT)
    b = settle_state(sc, solver("implicit_euler"), None, 0.2, DT)
    assert np.array_equal(a, b)


def test_unknown_integrator_is_an_input_error_naming_the_key():
    with pytest.raises(InputError) as info:
        make_integrator("rk4")
    assert info.value.where == "solver.integrator" and "bdf2" in str(info.value)
    with pytest.raises(InputError):
        Simulator(chain_scene(), solver("bogus"))


def test_unknown_integrator_exits_2(tmp_path):
    import subprocess
    import sys

    from helpers import REPO

    proc = subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling_smoke", "solver.integrator=rk4",
                           f"hydra.run.dir={tmp_path / 'run'}", "logging.rerun=false"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "solver.integrator" in proc.stderr and "rk4" in proc.stderr


# -- TR-BDF2 ------------------------------------------------------------------------------------
def test_trbdf2_carries_the_equation_of_motions_acceleration():
    """The acceleration TR-BDF2 carries, (x - x_pred)/h^2 of its BDF2 stage, is M^-1 F at the
    step's end (the free chain: no constraint forces), to the solver's tolerance."""
    sc = chain_scene()
    sim = Simulator(sc, solver("trbdf2", rtol=1e-9, atol=1e-14))
    st = sim.initial_state()
    for _ in range(12):
        st, info = sim.step(st, DT)
        assert info.converged
    free = ~sc.strands.kinematic
    a_eval = sim.accelerations(st)
    assert np.abs(st.history.a[free] - a_eval[free]).max() <= 1e-6 * np.abs(a_eval[free]).max()


def test_trbdf2_restarts_with_implicit_euler_after_a_collision_stage_moved_vertices(monkeypatch):
    pts = np.zeros((3, 3))
    pts[:, 1] = -L0 * np.arange(3)
    s = Strands.from_polylines(pts, np.array([3]), RHO, where="impulse")
    sc = Scene("impulse", s, Material(RHO, 1e-3, 0.0), RigidMotion.static(), np.array([0.0, -9.81, 0.0]), pts.copy())
    sim = Simulator(sc, solver("trbdf2"))
    calls = []

    def stage(cfg, scene, hh, x0, x1, t0, t1, dt, limiter=None, volume_dt=None, dist_out=None, push=None, solved=None):
        calls.append(t1)
        x1 = x1.copy()
        if len(calls) == 4:                         # the second step's last stage: pushed up 1 mm
            x1[2, 1] += 1e-3
        return x1, (x1 - x0) / dt, CollisionInfo()

    monkeypatch.setattr(simulator_module, "collision_stage", stage)
    sim.collide_objects = True
    sim.collision_cfg = SimpleNamespace()
    st = sim.initial_state()
    firsts = []
    for _ in range(4):
        firsts.append(type(sim.integrator.stages(st, DT)[0][0]).__name__)
        st, info = sim.step(st, DT)
        assert info.converged
    assert firsts == ["Trapezoidal", "Trapezoidal", "_StageEuler", "Trapezoidal"]


def test_trbdf2_substep_recovery_is_two_half_steps(monkeypatch):
    """A failed TR-BDF2 step is redone as two half steps (each with both stages), the same as
    stepping dt/2 twice; the carried acceleration is the second half step's."""
    _, _, rec, _, end = recovered_step("trbdf2", monkeypatch)
    assert np.array_equal(rec.history.a, end.history.a)


# -- the first stage's tolerance (solver.stage_rtol_factor) -----------------------------------
def _solve_rtols(monkeypatch, integrator: str, **kw) -> list[float]:
    """The rtol of every Newton solve of one step of the swung chain (``chain_scene``)."""
    from hairexp.physics import controller as controller_module

    seen = []
    real = controller_module.newton_solve

    def spy(obj, x0, opts):
        seen.append(opts.rtol)
        return real(obj, x0, opts)

    monkeypatch.setattr(controller_module, "newton_solve", spy)
    sim = Simulator(chain_scene(), solver(integrator, **kw))
    st, _ = sim.step(sim.initial_state(), DT)    # a first step: TR-BDF2's trapezoidal stage, then BDF2
    seen.clear()
    st, info = sim.step(st, DT)
    assert info.converged
    return seen


def test_first_stage_is_solved_to_the_stage_factor_times_rtol_and_the_step_end_to_rtol(monkeypatch):
    """TR-BDF2's trapezoidal stage (the intermediate point) takes solver.stage_rtol_factor x rtol,
    at most STAGE_RTOL_CAP, its BDF2 stage (the step's end) rtol; a one-stage scheme and a factor
    of 1 change nothing; a solver config without the key solves every stage to rtol."""
    from hairexp.physics.controller import STAGE_RTOL_CAP

    got = _solve_rtols(monkeypatch, "trbdf2", rtol=1e-6, stage_rtol_factor=100.0)
    assert np.allclose(got, [1e-4, 1e-6], rtol=1e-12, atol=0)
    assert _solve_rtols(monkeypatch, "trbdf2", rtol=1e-3, stage_rtol_factor=1e4) == [STAGE_RTOL_CAP, 1e-3]
    assert _solve_rtols(monkeypatch, "trbdf2", rtol=1e-6, stage_rtol_factor=1.0) == [1e-6, 1e-6]
    assert _solve_rtols(monkeypatch, "implicit_euler", rtol=1e-6, stage_rtol_factor=100.0) == [1e-6]
    assert _solve_rtols(monkeypatch, "trbdf2", rtol=1e-6) == [1e-6, 1e-6]


@pytest.mark.parametrize("bad", [0.5, -1.0, 1e9, float("nan"), "x"])
def test_stage_rtol_factor_out_of_range_is_an_input_error_naming_the_key(bad):
    with pytest.raises(InputError, match="solver.stage_rtol_factor"):
        Simulator(chain_scene(), solver("trbdf2", stage_rtol_factor=bad))
