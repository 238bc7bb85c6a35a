"""experiments/sqp_curvature.py's measurement: the curvature d^T H d per term of the SQP's PSD
model against the true one (central differences of each term's gradient)."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import solver_cfg
from tracking_helpers import polyline_scene, straight

from experiments.sqp_curvature import curvature
from hairexp.outputs.metrics import stretch
from hairexp.physics.simulator import Simulator


def objective_at(scale: float, stretch_hessian: str = "penalty", kernels: str = "numba"):
    """The objective of one step of a straight 10-vertex strand (no gravity), its free vertices
    moved along the strand by ``scale`` (< 1: every edge compressed), that DOF vector, and the
    edges' strain l / l0 - 1 there."""
    scene = polyline_scene([straight([0, 0, 0], [1, 0, 0], 0.2, 10)])
    sim = Simulator(scene, solver_cfg(stretch_hessian=stretch_hessian, integrator="implicit_euler", kernels=kernels))
    state = sim.initial_state()
    obj = sim.objective
    obj.begin_step(state.x, state.v, scene.root_positions(0.04, scene.motion), 0.04, None, None)
    x = state.x.copy()
    x[obj.free_vertices] = x[obj.free_vertices] * np.array([scale, 1.0, 1.0])
    return obj, sim.free_dofs(x), stretch(scene, x)


@pytest.mark.parametrize("kernels", ["numba", "torch"])
def test_model_is_the_true_curvature_on_a_stretched_straight_strand(kernels):
    obj, xf, strain = objective_at(1.001, kernels=kernels)
    assert (obj.kernels is None) == (kernels == "torch")
    assert (strain[1:] > 0).all()
    d = np.random.default_rng(0).normal(size=xf.shape) * 1e-3
    cur = curvature(obj, xf, d)
    assert set(cur) == {"inertia", "Stretch", "Bending"}
    for name, (model, true) in cur.items():
        assert model > 0
        assert true == pytest.approx(model, rel=1e-5), name   # PSD model exact: stretched, straight, s = 0


def test_compressed_edges_have_negative_true_stretch_curvature_the_model_clamps():
    obj, xf, strain = objective_at(0.999)
    assert (strain[1:] < 0).all() and np.median(strain) == pytest.approx(-1e-3, rel=0.05)
    d = np.zeros_like(xf).reshape(-1, 3)
    d[:, 1] = np.sin(np.arange(len(d)))   # transverse: along the clamped stiffness only
    d = d.reshape(-1) * 1e-3
    cur = curvature(obj, xf, d)
    model, true = cur["Stretch"]
    assert model == pytest.approx(0.0, abs=1e-12 * abs(true))   # clamped: max(T, 0) = 0
    assert true < 0
    # the true value: the compressed edges' transverse stiffness T/l (I - uu^T), T = k/l0 (l - l0),
    # summed over the edges (d is perpendicular to every edge)
    st = next(t for t in obj.terms if type(t).__name__ == "Stretch")
    D = np.zeros((len(obj.x_full), 3))
    D[obj.free_vertices] = d.reshape(-1, 3)
    i, j = st.stencil[:, 0], st.stencil[:, 1]
    l0 = st.l0.numpy()
    T = st.k_l0.numpy() * strain * l0
    assert true == pytest.approx(float(np.sum(T / ((1 + strain) * l0) * (D[j, 1] - D[i, 1]) ** 2)), rel=1e-4)
