"""The SQP's secant correction of its Hessian model along the last step (hairexp/control/
tracking/sqp.py ``secant_correction``): the band product (hairexp/physics/assembly.py), the rank-one term's curvature and
definiteness, the signed Woodbury solve, and what it does to a solve whose model overestimates
the curvature (a buckling wisp: stylization's block falling off its rail)."""

from __future__ import annotations

import numpy as np
import pytest

from hairexp.control.tracking import sqp as S
from hairexp.physics.assembly import band_product


def _band(rng, n, bw):
    """A random SPD matrix with half-bandwidth bw and its LAPACK lower band."""
    B = np.zeros((n, n))
    for d in range(bw + 1):
        v = rng.normal(size=n - d)
        B[np.arange(d, n), np.arange(n - d)] = v
    B = B @ B.T
    B[np.abs(np.subtract.outer(np.arange(n), np.arange(n))) > bw] = 0.0
    B += n * np.eye(n)
    ab = np.zeros((bw + 1, n))
    for d in range(bw + 1):
        ab[d, : n - d] = np.diagonal(B, -d)
    return B, ab


def test_band_product_equals_the_dense_product(monkeypatch):
    from hairexp.physics import assembly, bandchol
    calls = []
    compiled = bandchol.band_product_lt
    monkeypatch.setattr(bandchol, "band_product_lt", lambda *a: (calls.append(1), compiled(*a)))
    rng = np.random.default_rng(0)
    for n, bw in ((1, 0), (7, 2), (30, 8)):
        B, ab = _band(rng, n, min(bw, n - 1))
        v = rng.normal(size=n)
        np.testing.assert_allclose(band_product(ab, v), B @ v, rtol=1e-13, atol=1e-13)
        # the compiled kernels' layout: ab as the transposed view of a C-order (N, bw + 1) array
        abT = np.ascontiguousarray(ab.T)
        assert abT.T.T.flags.c_contiguous
        calls.clear()
        np.testing.assert_allclose(band_product(abT.T, v), B @ v, rtol=1e-13, atol=1e-13)
        assert len(calls) == (1 if assembly.HAVE_NUMBA else 0)   # the transposed view took the compiled product


def test_band_product_by_runs_of_blocks_is_the_whole_band_product(monkeypatch):
    """A block-diagonal band (zeros across the blocks' ends, as the assembly writes it) by runs of
    blocks on two threads (``bandchol.band_product_parallel``, chosen from
    ``bandchol.PARALLEL_MIN_BLOCKS`` blocks on when the objective's kernels run 2 threads): the
    whole band's product bit for bit, and the dense product; fewer blocks, or 1 thread, take the
    whole-band product."""
    from types import SimpleNamespace

    from hairexp.physics import assembly, bandchol
    if not assembly.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(3)
    sizes = rng.integers(3, 30, size=40)
    blk_dof = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n, bw = int(blk_dof[-1]), 8
    B = np.zeros((n, n))
    for b in range(len(sizes)):
        d0, d1 = blk_dof[b], blk_dof[b + 1]
        Bb, _ = _band(rng, d1 - d0, min(bw, d1 - d0 - 1))
        B[d0:d1, d0:d1] = Bb
    abT = np.zeros((n, bw + 1))
    for d in range(bw + 1):
        abT[: n - d, d] = np.diagonal(B, -d)
    v = rng.normal(size=n)
    whole = np.empty(n)
    bandchol.band_product_lt(abT, v, whole)
    for threads in (1, 2):
        bandchol.set_threads(threads)
        out = np.empty(n)
        bandchol.band_product_parallel(abT, v, out, blk_dof)
        assert np.array_equal(out, whole)
    np.testing.assert_allclose(whole, B @ v, rtol=1e-13, atol=1e-12)
    calls = []
    par = bandchol.band_product_parallel
    monkeypatch.setattr(bandchol, "band_product_parallel", lambda *a: (calls.append(1), par(*a)))
    monkeypatch.setattr(bandchol, "PARALLEL_MIN_BLOCKS", 40)
    for threads, blocks, want in ((2, 40, 1), (1, 40, 0), (2, 41, 0)):
        monkeypatch.setattr(bandchol, "PARALLEL_MIN_BLOCKS", blocks)
        calls.clear()
        kernels = SimpleNamespace(parallel=threads > 1, threads=threads, blk_dof=blk_dof)
        assert np.array_equal(band_product(abT.T, v, kernels), whole)
        assert len(calls) == want


@pytest.mark.parametrize("ratio", [-0.8, 0.05, 0.3])
def test_correction_sets_the_curvature_along_the_step_and_stays_definite(ratio):
    """Where s^T y < SECANT_RATIO s^T B s: B' = B + U D U^T has s^T B' s = max(s^T y, floor),
    is positive definite, and acts as B on every vector B-orthogonal to s."""
    rng = np.random.default_rng(1)
    n = 20
    B, _ = _band(rng, n, 5)
    s = rng.normal(size=(n, 1))
    km = float(s[:, 0] @ B @ s[:, 0])
    y = B @ s * ratio                 # s^T y = ratio km
    U, signs = S.secant_correction(B @ s, s, y)
    Bc = B + U @ np.diag(signs) @ U.T
    np.testing.assert_allclose(s[:, 0] @ Bc @ s[:, 0], max(ratio, S.SECANT_FLOOR) * km, rtol=1e-10)
    assert np.linalg.eigvalsh(Bc).min() > 0
    v = rng.normal(size=n)
    v -= (v @ B @ s[:, 0]) / km * s[:, 0]          # B-orthogonal to s
    np.testing.assert_allclose(Bc @ v, B @ v, rtol=1e-10, atol=1e-10)


def test_correction_over_several_steps_sets_the_curvature_on_their_span():
    """With two steps: on their span the corrected model's curvature is the secant one where that
    is below SECANT_RATIO of the model's (clamped at the floor) and B's elsewhere; B-orthogonal
    vectors see B; nearly parallel steps are one direction."""
    rng = np.random.default_rng(4)
    n = 16
    B, _ = _band(rng, n, 4)
    Hm = rng.normal(size=(n, n))
    H = 0.5 * (Hm + Hm.T)                       # an indefinite "true" Hessian
    Sx = rng.normal(size=(n, 2))
    U, signs = S.secant_correction(B @ Sx, Sx, H @ Sx)
    Bc = B + U @ np.diag(signs) @ U.T
    assert np.linalg.eigvalsh(Bc).min() > 0
    G, M = Sx.T @ B @ Sx, Sx.T @ H @ Sx
    w, V = np.linalg.eigh(G)
    R = V / np.sqrt(w)
    lam, Q = np.linalg.eigh(R.T @ M @ R)
    Z = Sx @ R @ Q                              # B-orthonormal, M-diagonal directions of the span
    want = np.where(lam < S.SECANT_RATIO, np.maximum(lam, S.SECANT_FLOOR), 1.0)
    np.testing.assert_allclose(np.diag(Z.T @ Bc @ Z), want, rtol=1e-9, atol=1e-12)
    v = rng.normal(size=n)
    v -= Sx @ np.linalg.solve(G, Sx.T @ B @ v)   # B-orthogonal to the span
    np.testing.assert_allclose(Bc @ v, B @ v, rtol=1e-9, atol=1e-9)
    # a repeated step: its span is one direction, corrected as the single step is
    twice = np.column_stack([Sx[:, 0], Sx[:, 0]])
    U2, s2 = S.secant_correction(B @ twice, twice, -(B @ twice))
    assert U2.shape[1] == 1
    U1, s1 = S.secant_correction(B @ twice[:, :1], twice[:, :1], -(B @ twice[:, :1]))
    np.testing.assert_allclose(U2 @ np.diag(s2) @ U2.T, U1 @ np.diag(s1) @ U1.T, rtol=1e-8, atol=1e-10)


def test_no_correction_where_the_model_curvature_is_not_too_large():
    rng = np.random.default_rng(2)
    B, _ = _band(rng, 10, 3)
    s = rng.normal(size=(10, 1))
    for ratio in (1.001 * S.SECANT_RATIO, 1.0, 3.0):
        assert S.secant_correction(B @ s, s, ratio * (B @ s)) is None
    assert S.secant_correction(B @ s, s, np.full((10, 1), np.nan)) is None
    assert S.secant_correction(np.zeros((10, 1)), np.zeros((10, 1)), np.zeros((10, 1))) is None


def test_signed_woodbury_matches_the_dense_kkt_solve():
    rng = np.random.default_rng(3)
    n, m = 12, 3
    B, _ = _band(rng, n, 4)
    A = rng.normal(size=(m, n))
    U = rng.normal(size=(n, 2))
    signs = np.array([1.0, -0.01])

    def kkt(Hx):
        return np.block([[Hx, A.T], [A, np.zeros((m, m))]])

    def solve(r_x, c):
        sol = -np.linalg.solve(kkt(B), np.concatenate([r_x, c]))
        return sol[:n], None, sol[n:]

    g, C = rng.normal(size=n), rng.normal(size=m)
    dx, _, lam = S.woodbury(solve, U, solve(g, C), np.zeros(m), signs)
    want = -np.linalg.solve(kkt(B + U @ np.diag(signs) @ U.T), np.concatenate([g, C]))
    np.testing.assert_allclose(dx, want[:n], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(lam, want[n:], rtol=1e-10, atol=1e-12)


def _tracked(exp: str, secant: bool, *overrides, converged: bool = True):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    cfg = compose_config([f"experiment={exp}", "variants=[]", "controller.name=tracking", "logging.rerun=false",
                          f"tracking.secant={str(secant).lower()}", *overrides])
    run = assemble(cfg)
    updates = [0]
    solve = run.controller.solve

    def counted(*a, **k):
        out = solve(*a, **k)
        updates[0] += out[2].secant_updates
        return out

    run.controller.solve = counted
    its, state = [], None
    for *_, state, info in run.steps(run.initial_state(), int(cfg.frames)):
        assert info.converged or not converged
        its.append(info.iterations)
    return state, its, updates[0], run


def test_corrected_and_plain_models_converge_to_the_same_steps():
    """The correction changes the SQP's path, not its solutions: goaling_smoke, where it acts in a
    few iterations after the wisp hits the wheel, ends where the plain model's run ends (both
    converge to rtol 1e-5, both stages of every step: solver.stage_rtol_factor=1, since a first
    stage solved to 100 x rtol leaves each run's intermediate points that far from the solution,
    1.5e-6 L apart at the end)."""
    a, its_a, upd_a, run = _tracked("goaling_smoke", True, "solver.stage_rtol_factor=1")
    b, its_b, upd_b, _ = _tracked("goaling_smoke", False, "solver.stage_rtol_factor=1")
    assert upd_a > 0 and upd_b == 0
    L = float(np.mean(run.scene.strands.strand_lengths()))
    assert np.abs(a.x - b.x).max() < 1e-6 * L


@pytest.mark.slow
def test_correction_cuts_the_iterations_of_a_buckling_wisp():
    """The shrinking guide with static targets (paper Fig. 2's ablation) forces the wisp to
    compress: it buckles in its third step.  Measured 2026-12-06: 100.4 / 1600 SQP iterations a step
    without the correction, 44.1 / 548 with it (17.6 against 7.1 s)."""
    _, its_on, upd, _ = _tracked("shrinking_guide", True, "tracking.targets=static", converged=False)
    _, its_off, _, _ = _tracked("shrinking_guide", False, "tracking.targets=static", converged=False)
    assert upd > 0
    assert sum(its_on) < 0.6 * sum(its_off)


def test_prediction_rule_needs_a_full_step_and_quadratic_decrease():
    assert not S._likely_converged([(100.0, 0.0)], 1.0)                 # one iterate: no rate yet
    assert S._likely_converged([(100.0, 5.0), (0.5, 0.01)], 1.0)      # both already within
    assert S._likely_converged([(100.0, 0.0), (5.0, 0.0)], 1.0)       # 5 (5/100)^2 = 0.0125
    assert not S._likely_converged([(100.0, 0.0), (5.0, 0.0)], 0.5)   # a cut step
    assert not S._likely_converged([(10.0, 0.0), (5.0, 0.0)], 1.0)    # 5 (1/2)^2 > 1: linear rate
    assert not S._likely_converged([(100.0, 40.0), (5.0, 20.0)], 1.0)  # the constraints lag


@pytest.mark.parametrize("integrator", ["implicit_euler", "trbdf2"])
def test_gradient_only_evaluation_at_a_predicted_solution_changes_nothing(monkeypatch, integrator):
    """The SQP assembles no band at an iterate predicted to converge (``_likely_converged``): the
    same iterates, multipliers and counts bit for bit as with the band at every iterate, and fewer
    banded evaluations."""
    from hairexp.physics import objective as O
    from tracking_helpers import GOALING_MOTION, build_tracked, run_steps, tracked_cfg

    def run(predict: bool):
        if not predict:
            monkeypatch.setattr(S, "_likely_converged", lambda *a: False)
        calls = []
        orig = O.ImplicitEulerObjective.evaluate
        monkeypatch.setattr(O.ImplicitEulerObjective, "evaluate",
                            lambda self, x, need_hessian=True: (calls.append(need_hessian), orig(self, x, need_hessian))[1])
        _, _, sim = build_tracked(tracked_cfg({"solver.integrator": integrator, **GOALING_MOTION}))
        states, infos = run_steps(sim, 20)
        monkeypatch.undo()
        return states, infos, calls

    s1, i1, c1 = run(True)
    s0, i0, c0 = run(False)
    assert [i.iterations for i in i1] == [i.iterations for i in i0]
    assert all(i.converged for i in i1)
    for a, b in zip(s1, s0):
        assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)
    assert sum(c1) < sum(c0)   # bands not assembled
    assert len(c1) - sum(c1) > len(c0) - sum(c0)


def test_prediction_ratios_with_a_zero_tolerance():
    """tracking.atol = 0 and a hair at rest (no force): the tolerance is 0, met by a zero residual only."""
    assert S._ratio(0.0, 0.0) == 0.0 and S._ratio(1e-300, 0.0) == float("inf") and S._ratio(2.0, 4.0) == 0.5
    assert not S._likely_converged([(float("inf"), 0.0), (float("inf"), 0.0)], 1.0)


def test_a_hair_at_rest_with_a_zero_absolute_tolerance_steps():
    """No gravity, the guide still, tracking.atol = 0: every residual and tolerance is 0 and the
    solves converge at once (the prediction's ratios divided 0 by 0 there)."""
    from tracking_helpers import NO_GRAVITY, build_tracked, run_steps, tracked_cfg

    _, _, sim = build_tracked(tracked_cfg({"scene.gravity": NO_GRAVITY, "tracking.atol": 0.0, "frames": 3}))
    _, infos = run_steps(sim, 3)
    assert all(i.converged for i in infos)
