"""Energy terms: autograd derivatives against finite differences (derivcheck), closed forms
against autograd, PSD Hessians, and the stretch tension linearisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from derivcheck import check_term
from helpers import as_t, bent_polyline, chain_stencils
from hairexp.physics.energies import AirDrag, Bending, EdgeDamping, Gravity, Stretch
from hairexp.physics.terms import Term, autograd_grad_hess, project_psd

N = 9            # vertices of the test chain
K_STRETCH = 20.0  # N
B_BEND = 2e-6     # N m^2
DT = 0.04         # s
GRAVITY = np.array([0.0, -9.81, 0.0])
LIN_DENSITY = 2e-4
#: closed forms and autograd are the same formulas in a different order: round-off only
CLOSED_RTOL = 1e-10


def straight_polyline(n: int, direction=(0.3, -0.8, 0.2), edge: float = 0.02) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    s = edge * np.cumsum(np.r_[0.0, np.linspace(0.7, 1.3, n - 1)])  # unequal edges
    return np.array([0.01, 0.02, -0.03]) + s[:, None] * d


def masses_of(x: np.ndarray) -> np.ndarray:
    l = np.linalg.norm(np.diff(x, axis=0), axis=1)
    m = np.zeros(len(x))
    m[:-1] += 0.5 * LIN_DENSITY * l
    m[1:] += 0.5 * LIN_DENSITY * l
    return m


def elements(term: Term, x: np.ndarray) -> torch.Tensor:
    return as_t(x)[torch.as_tensor(term.stencil)]


def make_term(name: str, rest: np.ndarray, x_n: np.ndarray | None = None) -> Term:
    edges, bends = chain_stencils(len(rest))
    l0 = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    if name == "stretch":
        return Stretch(edges, l0, K_STRETCH)
    if name == "bending":
        return Bending(bends, rest, B_BEND)
    if name == "gravity":
        return Gravity(masses_of(rest), GRAVITY)
    x_n = rest if x_n is None else x_n
    if name == "edge_damping":
        t = EdgeDamping(edges, l0, 0.3)
    elif name == "air_drag":
        t = AirDrag(masses_of(rest), 5.0, np.arange(len(rest)))
    else:
        raise ValueError(name)
    t.set_reference(as_t(x_n), DT)
    return t


def curved_rest() -> np.ndarray:
    return bent_polyline(N, seed=11, max_turn=0.6)


def current() -> np.ndarray:
    """A configuration away from every rest shape used here (different turning and lengths)."""
    return bent_polyline(N, seed=5, edge=0.021, max_turn=1.2)


# --------------------------------------------------------------------------------------------
# 1. derivatives of every term against finite differences
# --------------------------------------------------------------------------------------------

CASES = {
    "stretch": ("stretch", curved_rest, current),
    "bending_straight_rest": ("bending", lambda: straight_polyline(N), current),
    "bending_curved_rest": ("bending", curved_rest, current),
    "edge_damping": ("edge_damping", curved_rest, current),
    "air_drag": ("air_drag", curved_rest, current),
}


@pytest.mark.parametrize("case", list(CASES))
def test_derivatives_match_finite_differences(case):
    name, rest_fn, x_fn = CASES[case]
    rest, x = rest_fn(), x_fn()
    # the damping terms' reference is the start-of-step state: a third configuration
    term = make_term(name, rest, x_n=bent_polyline(N, seed=23, max_turn=0.8))
    rep = check_term(term, elements(term, x))
    assert rep.grad_scale > 0 and rep.hess_scale > 0  # the check compared something non-trivial


def test_gravity_gradient_matches_finite_differences():
    term = make_term("gravity", curved_rest())
    rep = check_term(term, elements(term, current()), hessian=False)
    assert rep.grad_scale > 0
    assert torch.allclose(rep.grad, -term.mg, rtol=1e-14, atol=0)


def test_gravity_autograd_hessian_is_zero():
    term = make_term("gravity", curved_rest())
    rep = check_term(term, elements(term, current()))
    assert float(rep.hess.abs().max()) == 0.0


@pytest.mark.parametrize("direction", [(1.0, 0.0, 0.0), (0.3, -0.8, 0.2)], ids=["axis", "oblique"])
def test_bending_exactly_straight_strand_has_nonzero_exact_hessian(direction):
    """The atan2 trap: at three collinear nodes an atan2-based energy gets a zero autograd
    Hessian.  The curvature-binormal form must give the true, non-zero one."""
    rest = straight_polyline(3, direction)
    if direction == (1.0, 0.0, 0.0):  # exactly collinear in floating point
        e0, e1 = rest[1] - rest[0], rest[2] - rest[1]
        assert np.all(np.cross(e0, e1) == 0.0)
    term = make_term("bending", rest)
    rep = check_term(term, elements(term, rest))
    assert float(rep.grad.abs().max()) <= 1e-12 * rep.hess_scale  # straight: no bending force
    assert rep.hess_scale > 0
    H = rep.hess[0]
    # it has transverse stiffness: bending the middle node sideways costs energy
    assert torch.linalg.eigvalsh(H).max() > 1e-3 * B_BEND / 0.02 ** 3


class Atan2Bending(Term):
    """The atan2 trap: theta = atan2(|e0 x e1|, e0 . e1), E = B theta^2."""

    name = "atan2_bending"

    def __init__(self, stencil):
        self.stencil = stencil

    def energy(self, xs):
        e0, e1 = xs[:, 1] - xs[:, 0], xs[:, 2] - xs[:, 1]
        th = torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(e0, e1), dim=-1), (e0 * e1).sum(-1))
        return B_BEND * th ** 2


def test_derivcheck_catches_the_atan2_trap():
    """The helper itself can fail: it rejects the zero autograd Hessian of the atan2 form at a
    straight strand, and accepts the same form where it is smooth."""
    _, bends = chain_stencils(3)
    term = Atan2Bending(bends)
    straight = straight_polyline(3, (1.0, 0.0, 0.0))
    g, H = autograd_grad_hess(term.energy, elements(term, straight))
    assert not bool(torch.isfinite(H).all()) or float(H.abs().max()) == 0.0  # zero (or NaN): wrong
    with pytest.raises(AssertionError, match="Hessian"):
        check_term(term, elements(term, straight))
    check_term(term, elements(term, bent_polyline(3, seed=1)))


# --------------------------------------------------------------------------------------------
# 2. closed forms against autograd
# --------------------------------------------------------------------------------------------

def assert_close(a: torch.Tensor, b: torch.Tensor, rtol: float = CLOSED_RTOL, what: str = ""):
    scale = float(b.abs().max())
    err = float((a - b).abs().max())
    assert err <= rtol * scale, f"{what}: max difference {err:.3e}, scale {scale:.3e}"


def min_eig(H: torch.Tensor) -> torch.Tensor:
    return torch.linalg.eigvalsh(0.5 * (H + H.transpose(-1, -2))).min(dim=-1).values


def assert_psd(H: torch.Tensor, what: str = "", scale: float | None = None):
    scale = float(H.abs().amax(dim=(-1, -2)).max()) if scale is None else scale
    lo = float(min_eig(H).min())
    assert lo >= -1e-12 * scale, f"{what}: min eigenvalue {lo:.3e} (scale {scale:.3e})"


@pytest.mark.parametrize("case", list(CASES) + ["gravity"])
def test_closed_form_gradient_equals_autograd(case):
    name, rest_fn, x_fn = CASES.get(case, ("gravity", curved_rest, current))
    term = make_term(name, rest_fn(), x_n=bent_polyline(N, seed=23, max_turn=0.8))
    xs = elements(term, x_fn())
    out = term.closed_form(xs, True)
    assert out is not None, f"{name} has no closed form"
    g_cf, H_cf = out
    g_ad, _ = autograd_grad_hess(term.energy, xs, need_hessian=False)
    assert g_cf.dtype == torch.float64
    assert_close(g_cf, g_ad, what=f"{case} gradient")
    assert H_cf.shape == (len(xs), g_ad.shape[1], g_ad.shape[1])
    assert_psd(H_cf, case)


@pytest.mark.parametrize("name", ["edge_damping", "air_drag"])
def test_quadratic_terms_closed_hessian_is_exact(name):
    term = make_term(name, curved_rest(), x_n=bent_polyline(N, seed=23, max_turn=0.8))
    xs = elements(term, current())
    _, H_cf = term.closed_form(xs, True)
    _, H_ad = autograd_grad_hess(term.energy, xs)
    assert_close(H_cf, H_ad, what=name)


def test_gravity_closed_hessian_is_zero():
    term = make_term("gravity", curved_rest())
    _, H = term.closed_form(elements(term, current()), True)
    assert float(H.abs().max()) == 0.0


def scaled_about_first(x: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """Chain with every edge scaled by ``factor`` (per edge), directions kept."""
    e = np.diff(x, axis=0) * np.asarray(factor)[:, None]
    return np.vstack([x[:1], x[0] + np.cumsum(e, axis=0)])


def test_stretch_hessian_exact_on_stretched_springs():
    rest = curved_rest()
    term = make_term("stretch", rest)
    x = scaled_about_first(current(), np.linspace(1.5, 2.5, N - 1))  # all longer than rest (<= 1.5 * 0.02 * 1.5)
    xs = elements(term, x)
    assert bool((term.tension_of(xs) > 0).all())
    _, H_cf = term.closed_form(xs, True)
    _, H_ad = autograd_grad_hess(term.energy, xs)
    assert_close(H_cf, H_ad, what="stretched springs")


def test_stretch_hessian_on_compressed_springs_is_projected_exact():
    rest = curved_rest()
    term = make_term("stretch", rest)
    x = scaled_about_first(rest, np.linspace(0.3, 0.9, N - 1))
    xs = elements(term, x)
    assert bool((term.tension_of(xs) < 0).all())
    _, H_cf = term.closed_form(xs, True)
    _, H_ad = autograd_grad_hess(term.energy, xs)
    assert float(min_eig(H_ad).min()) < 0  # the exact Hessian really is indefinite here
    assert_psd(H_cf, "compressed springs")
    assert_close(H_cf, project_psd(H_ad), rtol=1e-9, what="compressed springs vs projected exact")
    # and in the axial direction (x1 - x0 along u) it is the exact stiffness k / l0
    e = xs[:, 1] - xs[:, 0]
    u = e / torch.linalg.vector_norm(e, dim=-1, keepdim=True)
    a = torch.cat([-u, u], dim=1)
    axial_cf = torch.einsum("ni,nij,nj->n", a, H_cf, a)
    axial_ad = torch.einsum("ni,nij,nj->n", a, H_ad, a)
    assert_close(axial_cf, axial_ad, what="axial stiffness")


def test_stretch_primal_dual_hessian_uses_tension_and_keeps_gradient():
    """With a tension iterate set, the gradient is unchanged and the Hessian is
    (k/l0) u u^T + max(T, 0)/l (I - u u^T) with that tension (energies.Stretch)."""
    rest = curved_rest()
    term = make_term("stretch", rest)
    xs = elements(term, scaled_about_first(current(), np.linspace(0.8, 1.2, N - 1)))
    g0, _ = term.closed_form(xs, True)
    E = len(xs)
    e = xs[:, 1] - xs[:, 0]
    l = torch.linalg.vector_norm(e, dim=-1)
    # tensions between -0.5 and +0.5 of the stiffness bound k l / l0 (negatives are clamped)
    term.tension = torch.linspace(-0.5, 0.5, E, dtype=torch.float64) * term.k_l0 * l
    g1, H1 = term.closed_form(xs, True)
    assert torch.equal(g0, g1)
    u = e / l.unsqueeze(-1)
    uu = u.unsqueeze(-1) * u.unsqueeze(-2)
    K = term.k_l0.view(-1, 1, 1) * uu + (term.tension.clamp_min(0) / l).view(-1, 1, 1) * (torch.eye(3) - uu)
    expect = torch.cat([torch.cat([K, -K], 2), torch.cat([-K, K], 2)], 1)
    assert_close(H1, expect, what="primal-dual Hessian")


def test_stretch_linearized_tension_is_the_derivative_of_tension():
    rest = curved_rest()
    term = make_term("stretch", rest)
    xs = elements(term, current())
    dxs = as_t(np.random.default_rng(3).normal(size=xs.shape)) * 1e-3
    T0 = term.tension_of(xs)
    lin = term.linearized_tension(xs, dxs)
    h = 1e-4
    fd = (term.tension_of(xs + h * dxs) - term.tension_of(xs - h * dxs)) / (2 * h)
    assert_close(lin - T0, fd, rtol=1e-7, what="directional derivative of the tension")
    # first-order accurate: the error of the linearisation shrinks quadratically with the step
    err = [float((term.linearized_tension(xs, s * dxs) - term.tension_of(xs + s * dxs)).abs().max())
           for s in (1.0, 0.5)]
    assert 3.0 < err[0] / err[1] < 5.0


BENDING_CONFIGS = {
    "straight_rest_bent": (lambda: straight_polyline(N), current),
    "curved_rest_bent": (curved_rest, current),
    "curved_rest_straight": (curved_rest, lambda: straight_polyline(N, (1.0, 0.0, 0.0))),
    "curved_rest_nearly_straight": (curved_rest, lambda: bent_polyline(N, seed=2, max_turn=1e-4)),
    "straight_rest_straight": (lambda: straight_polyline(N), lambda: straight_polyline(N, (1.0, 0.0, 0.0))),
    "curved_rest_folded": (curved_rest, lambda: bent_polyline(N, seed=9, max_turn=2.8)),
}


@pytest.mark.parametrize("case", list(BENDING_CONFIGS))
def test_bending_gauss_newton_hessian_is_psd(case):
    rest_fn, x_fn = BENDING_CONFIGS[case]
    term = make_term("bending", rest_fn())
    xs = elements(term, x_fn())
    g, H = term.closed_form(xs, True)
    assert torch.isfinite(g).all() and torch.isfinite(H).all()
    assert_psd(H, case)


def test_bending_closed_hessian_exact_at_straight_with_straight_rest():
    term = make_term("bending", straight_polyline(N))
    for direction in [(1.0, 0.0, 0.0), (0.3, -0.8, 0.2)]:
        xs = elements(term, straight_polyline(N, direction, edge=0.023))
        g, H_cf = term.closed_form(xs, True)
        g_ad, H_ad = autograd_grad_hess(term.energy, xs)
        assert float(H_ad.abs().max()) > 0
        assert float(g.abs().max()) <= 1e-12 * float(H_ad.abs().max()) * 0.02
        assert_close(H_cf, H_ad, what=f"straight {direction}")


def test_bending_closed_hessian_exact_at_curved_rest_shape():
    """At the rest shape (residual |kb| - |kb_rest| = 0) Gauss-Newton is the exact Hessian,
    also after a rigid rotation of it (the energy is rotation invariant)."""
    rest = curved_rest()
    term = make_term("bending", rest)
    from scipy.spatial.transform import Rotation

    for x in (rest, rest @ Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix().T + 0.05):
        xs = elements(term, x)
        g, H_cf = term.closed_form(xs, True)
        _, H_ad = autograd_grad_hess(term.energy, xs)
        assert float(g.abs().max()) <= 1e-9 * float(H_ad.abs().max()) * 0.02
        assert_close(H_cf, H_ad, rtol=1e-8, what="at rest")


@pytest.mark.parametrize("case", ["stretch", "bending_straight_rest", "bending_curved_rest",
                                  "edge_damping", "air_drag", "stretch_compressed"])
def test_autograd_mode_hessians_are_psd(case):
    if case == "stretch_compressed":
        rest = curved_rest()
        term = make_term("stretch", rest)
        x = scaled_about_first(rest, np.full(N - 1, 0.5))
    else:
        name, rest_fn, x_fn = CASES[case]
        term = make_term(name, rest_fn(), x_n=bent_polyline(N, seed=23, max_turn=0.8))
        x = x_fn()
    xs = elements(term, x)
    g, H = term.grad_hess(xs, True, mode="autograd")
    g_ad, H_exact = autograd_grad_hess(term.energy, xs)
    assert torch.equal(g, g_ad)
    assert_psd(H, case)
    # the projection only removes the negative part: H - H_exact is PSD too
    assert_psd(H - H_exact, case + " (H - exact)", scale=float(H_exact.abs().max()))


def test_project_psd_clamps_only_negative_eigenvalues():
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    w = np.array([-3.0, -1e-3, 0.0, 0.5, 2.0, 7.0])
    H = as_t(Q @ np.diag(w) @ Q.T).unsqueeze(0)
    P = project_psd(H)[0]
    assert_close(P, as_t(Q @ np.diag(np.maximum(w, 0)) @ Q.T), what="projection")
    assert_close(torch.linalg.eigvalsh(P), as_t(np.sort(np.maximum(w, 0))), rtol=1e-12, what="eigenvalues")
