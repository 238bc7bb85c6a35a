"""The implicit Euler objective (paper eq. 5), H(x) = 1/2 dv^T M dv + E(x): its assembled
gradient and banded Hessian against finite differences and a dense reference assembly; and
Newton's answer against the objective."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers import scene_cfg, solver_cfg
from hairexp.app.config import OnFailure
from hairexp.errors import SimulationError
from hairexp.physics.assembly import BandedAssembler
from hairexp.physics.simulator import Simulator
from hairexp.app.builders import build_scene

DT = 0.02
MOTION = dict(interpolation="cubic", times=[0.0, 0.3], translations=[[0, 0, 0], [0.05, 0.03, -0.02]],
              rotations_deg=[[0, 0, 0], [15, -10, 5]])
ALL_TERMS = {"edge_damping": 0.05, "air_drag": 2.0}


def setup_step(derivatives="closed_form", **kw):
    """A simulator of 3 bent-ish strands with every term, advanced two steps, and its objective
    set up for the third step from that state.  Returns (sim, state, free DOF vector xf)."""
    scene = build_scene(scene_cfg(n_strands=3, n_vertices=7, direction=[1.0, -0.3, 0.2], spread=0.4,
                                  hair=ALL_TERMS, motion=MOTION, **kw))
    # eq. (5), the objective these tests check by hand: implicit Euler (the default is trbdf2)
    sim = Simulator(scene, solver_cfg(derivatives=derivatives, integrator="implicit_euler"))
    state = sim.initial_state()
    for _ in range(2):
        state, _ = sim.step(state, DT)
    obj = sim.objective
    obj.begin_step(state.x, state.v, scene.root_positions(state.time + DT), DT)
    rng = np.random.default_rng(4)
    xf = obj.initial_guess() + 1e-3 * rng.normal(size=obj.n_dofs)
    return sim, state, xf


def test_objective_value_is_eq5():
    """At the prediction x_n + dt v_n the inertia term vanishes; elsewhere it is
    1/2 (x - x_pred)^T M (x - x_pred) / dt^2 on top of the energies."""
    sim, state, xf = setup_step()
    obj = sim.objective
    s = sim.scene.strands
    x_pred = obj.initial_guess()
    free = ~s.kinematic
    np.testing.assert_allclose(x_pred, (state.x + DT * state.v)[free].reshape(-1), rtol=0, atol=1e-15)
    energies = lambda y: sum(float(t.total(obj.positions(y))) for t in sim.terms + sim.external)  # noqa: E731
    assert obj.value(x_pred) == pytest.approx(energies(x_pred), rel=1e-12, abs=1e-18)
    m = np.repeat(s.masses[free], 3)
    dv = (xf - x_pred) / DT
    assert obj.value(xf) == pytest.approx(0.5 * np.dot(m * dv, dv) + energies(xf), rel=1e-12)


@pytest.mark.parametrize("derivatives", ["closed_form", "autograd"])
def test_objective_gradient_matches_finite_differences(derivatives):
    sim, _, xf = setup_step(derivatives)
    obj = sim.objective
    ev = obj.evaluate(xf, need_hessian=False)
    h = 1e-7
    fd = np.empty_like(xf)
    for i in range(len(xf)):
        e = np.zeros_like(xf)
        e[i] = h
        fd[i] = (obj.value(xf + e) - obj.value(xf - e)) / (2 * h)
    err = np.abs(ev.grad - fd).max()
    assert err <= 1e-6 * np.abs(fd).max(), err
    assert ev.force_scale >= np.linalg.norm(ev.grad) * 0.5  # the scale is of the forces' size


def dense_reference(sim, xf) -> np.ndarray:
    """M/dt^2 + sum of element Hessians scattered with a plain double loop (free DOFs only)."""
    obj = sim.objective
    s = sim.scene.strands
    N = obj.n_dofs
    A = np.diag(obj.mass_diag.copy())
    x = obj.positions(xf)
    with torch.no_grad():
        for term in sim.terms:
            _, H = term.grad_hess(x[term.stencil_t], True, obj.derivatives)
            H = H.numpy()
            for e, verts in enumerate(term.stencil):
                dofs = [3 * s.free_slot[v] + c if s.free_slot[v] >= 0 else -1 for v in verts for c in range(3)]
                for a, da in enumerate(dofs):
                    for b, db in enumerate(dofs):
                        if da >= 0 and db >= 0:
                            A[da, db] += H[e, a, b]
    assert A.shape == (N, N)
    return A


@pytest.mark.parametrize("derivatives", ["closed_form", "autograd"])
def test_banded_hessian_equals_dense_assembly_and_is_spd(derivatives):
    sim, _, xf = setup_step(derivatives)
    ev = sim.objective.evaluate(xf, need_hessian=True)
    A = BandedAssembler.to_sparse(ev.banded).toarray()
    ref = dense_reference(sim, xf)
    np.testing.assert_allclose(A, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.linalg.eigvalsh(A).min() > 0  # PSD energies + M/dt^2


def test_banded_hessian_is_exact_where_the_models_are():
    """On straight strands stretched along themselves every element Hessian model is exact
    (stretched springs, bending at straight with straight rest, quadratic damping), so the
    assembled Hessian is the derivative of the assembled gradient."""
    scene = build_scene(scene_cfg(n_strands=2, n_vertices=6, direction=[0.2, -1.0, 0.1], hair=ALL_TERMS))
    sim = Simulator(scene, solver_cfg())
    obj = sim.objective
    s = scene.strands
    x = np.array(s.rest)
    for a, b in zip(s.offsets[:-1], s.offsets[1:]):
        x[a:b] = x[a] + 1.01 * (x[a:b] - x[a])  # 1 % stretch, straight
    obj.begin_step(np.array(s.rest), np.zeros_like(x), np.array(s.rest), DT)
    xf = x[~s.kinematic].reshape(-1)
    A = BandedAssembler.to_sparse(obj.evaluate(xf).banded).toarray()
    h = 1e-7
    fd = np.empty_like(A)
    for i in range(len(xf)):
        e = np.zeros_like(xf)
        e[i] = h
        fd[:, i] = (obj.evaluate(xf + e, False).grad - obj.evaluate(xf - e, False).grad) / (2 * h)
    np.testing.assert_allclose(A, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_newton_step_meets_its_tolerance():
    sim, state, _ = setup_step()
    new, info = sim.step(state, DT)
    assert info.converged and info.substeps == 1
    obj = sim.objective  # still set up for this step
    xf = new.x[~sim.scene.strands.kinematic].reshape(-1)
    ev = obj.evaluate(xf, need_hessian=False)
    cfg = sim.cfg
    assert np.linalg.norm(ev.grad) <= cfg.atol + cfg.rtol * ev.force_scale
    np.testing.assert_allclose(new.v, (new.x - state.x) / DT, rtol=0, atol=1e-12)
    s = sim.scene.strands
    np.testing.assert_allclose(new.x[s.kinematic], sim.scene.root_positions(new.time)[s.kinematic], rtol=0, atol=0)


MODELS = [("closed_form", "primal_dual"), ("closed_form", "penalty"), ("autograd", "primal_dual")]


def test_converged_states_do_not_depend_on_the_hessian_model():
    """The Hessian models (closed forms with the primal-dual or the penalty stretch Hessian,
    autograd with eigenvalue clamping) differ; the gradient, and so the solution, does not.
    Each converged step is within |grad| / lambda_min(H) <= (atol + rtol * force scale) dt^2 / m_min
    of the exact minimiser; the two runs may differ by the sum of those bounds."""
    scene = build_scene(scene_cfg(n_strands=3, n_vertices=8, direction=[1.0, 0.0, 0.0], spread=0.3,
                                  hair=ALL_TERMS))
    m_min = scene.strands.masses[~scene.strands.kinematic].min()
    dt = 0.04
    out, bound = {}, 0.0
    for d, sh in MODELS:
        sim = Simulator(scene, solver_cfg(derivatives=d, stretch_hessian=sh, rtol=1e-8))
        st = sim.initial_state()
        for _ in range(10):
            st, info = sim.step(st, dt)
            assert info.converged and info.substeps == 1
            bound += (sim.cfg.atol + sim.cfg.rtol * info.force_scale) * dt ** 2 / m_min
        out[d, sh] = st.x
    ref = out[MODELS[0]]
    moved = np.abs(ref - scene.strands.rest).max()
    assert moved > 0.01 and bound < 1e-4 * moved
    for m in MODELS[1:]:
        np.testing.assert_allclose(out[m], ref, rtol=0, atol=bound, err_msg=str(m))


#: The on_failure choice that stops the run (neither substep nor warn).
STOP = next(m for m in OnFailure if m not in (OnFailure.substep, OnFailure.warn))


def swinging(on_failure, max_iterations):
    scene = build_scene(scene_cfg(n_strands=2, n_vertices=8, direction=[1.0, 0.0, 0.0]))
    return Simulator(scene, solver_cfg(max_iterations=max_iterations, on_failure=on_failure))


def test_failed_step_is_recovered_by_substeps():
    sim = swinging(OnFailure.substep, 2)
    st = sim.initial_state()
    recovered = 0
    for _ in range(5):
        st, info = sim.step(st, 0.04)
        assert np.isfinite(st.x).all()
        assert info.converged
        recovered += info.recovered
        assert info.substeps >= 1 and (info.substeps > 1) == info.recovered
    assert recovered > 0


def test_on_failure_stop_and_warn():
    sim = swinging(STOP, 1)
    with pytest.raises(SimulationError, match="did not converge"):
        st = sim.initial_state()
        for _ in range(5):
            st, _ = sim.step(st, 0.04)
    sim = swinging(OnFailure.warn, 1)
    st = sim.initial_state()
    statuses = []
    for _ in range(5):
        st, info = sim.step(st, 0.04)
        statuses.append(info.status)
        assert np.isfinite(st.x).all() and info.substeps == 1
    assert "max_iterations" in statuses


@pytest.mark.slow
def test_compiled_kernels_match_eager(caplog):
    """solver.compile=on (torch.compile of the closed forms; cold compile costs 10-20 s) gives
    the same trajectory as eager to round-off."""
    scene = build_scene(scene_cfg(n_strands=3, n_vertices=8, direction=[1.0, 0.0, 0.0], spread=0.3,
                                  motion=MOTION, hair=ALL_TERMS))
    out = {}
    for mode in ("off", "on"):
        sim = Simulator(scene, solver_cfg(compile=mode))
        st = sim.initial_state()
        for _ in range(5):
            st, info = sim.step(st, DT)
            assert info.converged
        out[mode] = st.x
    assert np.abs(out["off"] - scene.strands.rest).max() > 1e-3
    np.testing.assert_allclose(out["on"], out["off"], rtol=0, atol=1e-12)
    # and the compiled path really ran: no fallback to eager was logged
    assert not [r for r in caplog.records if "torch.compile failed" in r.getMessage()]
