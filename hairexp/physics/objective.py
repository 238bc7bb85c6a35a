"""The variational implicit Euler objective, paper eq. (5):

    H(x) = 1/2 dv^T M dv + E(x),   dv = (x - x_n)/dt - v_n,

minimised over the free vertex positions (kinematic root vertices are prescribed).  Its
gradient is M dv / dt + grad E (the backward Euler residual) and its Hessian
M / dt^2 + hess E.  The same objective serves the free step (Newton) and the tracked step
(SQP, 3.4); it is the single source of truth for both.

Other integrators (``solver.integrator``, hairexp/physics/integrators.py) give ``begin_step`` a
``StepPlan``: the objective is then |x - x_pred|^2_M / (2 h^2) + E(y)/(1 - alpha_f) with
y = (1 - alpha_f) x + alpha_f x_n the point where the energies are evaluated (alpha_f = 0 but for
generalized-alpha), and the dissipation terms get the plan's velocity reference.

``kernels="numba"`` (``solver.kernels``): stretch, bending, inertia and gravity are evaluated by
the compiled per-strand kernels (hairexp/physics/strand_kernels.py), the band is factored block
by block there; the other terms keep their torch path and are added to the same band.
``kernels="torch"``: every term through torch and ``BandedAssembler`` (the reference).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

import scipy.linalg

from hairexp.physics import bandchol
from hairexp.physics.assembly import BandedAssembler, banded_solve
from hairexp.physics.energies import Stretch, pair_hessian
from hairexp.physics.strand_kernels import StrandKernels
from hairexp.physics.terms import DTYPE, Term

#: How many ulps of the summed term magnitudes a value of H is trusted to.
ROUNDOFF_ULPS = 64


@dataclass
class Evaluation:
    """Objective pieces at one iterate (N = number of free DOFs)."""

    grad: np.ndarray                 # (N,)
    banded: np.ndarray | None        # (bw + 1, N) lower band of the PSD Hessian, or None
    force_scale: float               # |inertial| + |internal| + |external| force norms
    seconds: dict = field(default_factory=dict)


class ImplicitEulerObjective:
    """Eq. (5) for one time step.  Built once per run; ``begin_step`` sets x_n, v_n, dt."""

    def __init__(self, terms: list[Term], masses: np.ndarray, kinematic: np.ndarray, free_slot: np.ndarray,
                 derivatives: str = "closed_form", external: list[Term] = (), primal_dual: bool = True,
                 kernels: str = "numba", threads: str = "auto"):
        """``terms``: energies with Hessians (assembled each iteration); ``external``: linear
        potentials (gravity) whose gradient is constant and is computed once here.
        ``kernels``: "numba" (compiled per-strand kernels where the terms allow, with ``threads``
        "auto" | "1" | "2") or "torch"; the compiled path needs closed-form derivatives."""
        self.terms = list(terms)
        self.external = list(external)
        self.free_vertices = np.flatnonzero(~np.asarray(kinematic))
        self.m_free = np.asarray(masses)[self.free_vertices]
        self.m_dof = np.repeat(self.m_free, 3)
        self.assembler = BandedAssembler(free_slot, [t.stencil for t in self.terms])
        self.derivatives = derivatives
        self.primal_dual = primal_dual and derivatives == "closed_form"
        self.n_dofs = self.assembler.n_dofs
        self.g_ext = np.zeros(self.n_dofs)
        if self.external:
            ext_asm = BandedAssembler(free_slot, [t.stencil for t in self.external])
            x0 = torch.zeros(len(free_slot), 3, dtype=DTYPE)
            with torch.no_grad():
                self.g_ext = ext_asm.gradient([t.grad_hess(x0[t.stencil_t], False)[0].numpy() for t in self.external])
        self.ext_norm = float(np.linalg.norm(self.g_ext))
        self.kernels = None
        #: the free step's fused Newton pass (``evaluate_step``); False: evaluate, then solve
        self.fused = True
        if kernels == "numba" and derivatives == "closed_form":
            self.kernels = StrandKernels.build(self.terms, self.external, free_slot, self.free_vertices,
                                               self.assembler.bandwidth, threads)
        #: the terms evaluated through torch (all of them without kernels)
        self.torch_terms = [t for t in self.terms if self.kernels is None or not self.kernels.handles(t)]
        if self.kernels is not None and self.torch_terms:
            self.torch_assembler = BandedAssembler(free_slot, [t.stencil for t in self.torch_terms])
        else:
            self.torch_assembler = self.assembler
        # contact inside the objective (hairexp/physics/barrier.py ObjectContact), set by the
        # Simulator when collision.contact=barrier; None: no contact code runs
        self.contact = None
        self.x_start = None   # the contact's feasible start of this step (DOF vector), or None
        self._stretch_assembler = None   # the stretch term's alone (``compression_band``), built on first use

    # -- per step -------------------------------------------------------------------------
    def begin_step(self, x_n: np.ndarray, v_n: np.ndarray, x_kinematic_next: np.ndarray, dt: float,
                   tensions: dict | None = None, plan=None) -> None:
        """x_n, v_n: (V, 3) start-of-step state; x_kinematic_next: (V, 3) whose kinematic rows
        hold the prescribed end-of-step root positions; ``tensions``: warm start of the dual
        iterates (spring tensions, ``State.tensions``) from the previous step, or None;
        ``plan``: the integrator's ``StepPlan`` (None: implicit Euler, eq. 5)."""
        self.dt = float(dt)
        if self.kernels is not None:
            self.kernels.retune()
        self.x_n = np.asarray(x_n)
        self.x_full = np.array(x_kinematic_next, dtype=np.float64)
        self.alpha_f = 0.0
        if plan is None:
            ref, h_v, h = self.x_n, self.dt, self.dt
            x_pred = self.x_n + self.dt * np.asarray(v_n)   # x_n + dt v_n
        else:
            ref = plan.x_ref if plan.y_ref is None else plan.y_ref
            h_v, h, x_pred, self.alpha_f = float(plan.h_v), float(plan.h), plan.x_pred, float(plan.alpha_f)
        ref_t = torch.as_tensor(np.asarray(ref), dtype=DTYPE)
        for t in self.terms:
            if hasattr(t, "set_reference"):
                t.set_reference(ref_t, h_v)
        self.x_pred = np.asarray(x_pred)[self.free_vertices].reshape(-1)
        self.mass_diag = self.m_dof / h ** 2
        for t in self._dual_terms:
            t.tension = None if not tensions or tensions.get(t.name) is None else torch.as_tensor(tensions[t.name])

    def vertex_inertia(self) -> np.ndarray:
        """(V,) each vertex's inertia m / h^2 of the step (``begin_step``; 0 for the kinematic ones):
        the contacts' mass scale (the barrier's curvature bound, the contact planes' stiffness)."""
        out = np.zeros(len(self.x_full))
        out[self.free_vertices] = np.asarray(self.mass_diag, dtype=np.float64).reshape(-1, 3).min(axis=1)
        return out

    # -- dual iterates (primal-dual stretch Hessian, see energies.Stretch) ----------------
    @property
    def _dual_terms(self):
        return [t for t in self.terms if hasattr(t, "linearized_tension")] if self.primal_dual else []

    def _kernel_dual(self) -> bool:
        return self.kernels is not None and self.primal_dual

    def update_tensions(self, xf: np.ndarray, step: np.ndarray) -> None:
        """Advance the tension iterates by their linearisation along the accepted step."""
        terms = self._dual_terms
        if self._kernel_dual():
            self.kernels.stretch.tension = torch.from_numpy(self.kernels.tensions(self, xf, step))
            terms = [t for t in terms if not self.kernels.handles(t)]
        if not terms:
            return
        x = self.eval_positions(xf)
        d = torch.zeros_like(x)
        d[self.free_vertices] = torch.from_numpy(step.reshape(-1, 3))
        if self.alpha_f != 0.0:
            d = (1.0 - self.alpha_f) * d
        with torch.no_grad():
            for t in terms:
                t.tension = t.linearized_tension(x[t.stencil_t], d[t.stencil_t])

    def final_tensions(self, xf: np.ndarray) -> dict:
        """Tensions of the final state (the warm start of the next step)."""
        x = None   # the torch positions, built only for a term without kernels
        out = {}
        with torch.no_grad():
            for t in self._dual_terms:
                if self._kernel_dual() and self.kernels.handles(t):
                    t.tension = torch.from_numpy(self.kernels.tensions(self, xf, None))
                    out[t.name] = t.tension.numpy().copy()
                    continue
                if x is None:
                    x = self.eval_positions(xf)
                t.tension = t.tension_of(x[t.stencil_t])
                out[t.name] = t.tension.numpy().copy()
        return out

    # -- the compressed edges' transverse stiffness (tracked SQP) --------------------------
    def compression_band(self, xf: np.ndarray) -> np.ndarray | None:
        """Lower band (bw + 1, N) of what the PSD stretch Hessian leaves out: the negative
        transverse stiffness T/l (I - u u^T) of every compressed edge (T < 0, T the tension the
        model uses: the dual iterate where there is one, else the current stretch), scaled as the
        band's Hessians by (1 - alpha_f); None when no edge is compressed.  The band plus it is the
        exact stretch Hessian (energies.stretch_kernel clamps max(T, 0))."""
        st = [t for t in self.terms if isinstance(t, Stretch)]
        if not st:
            return None
        t = st[0]
        x = self.eval_positions(xf)
        with torch.no_grad():
            xs = x[t.stencil_t]
            e = xs[:, 1] - xs[:, 0]
            l = torch.linalg.vector_norm(e, dim=-1)
            T = t.k_l0 * (l - t.l0) if t.tension is None else t.tension
            c = T.clamp_max(0.0) / l
            if not bool((c < 0).any()):
                return None
            u = e / l.unsqueeze(-1)
            K = c.view(-1, 1, 1) * (torch.eye(3, dtype=u.dtype) - u.unsqueeze(-1) * u.unsqueeze(-2))
            H = (1.0 - self.alpha_f) * pair_hessian(K)
        if self._stretch_assembler is None:
            self._stretch_assembler = BandedAssembler(self.assembler.free_slot, [t.stencil])
        ab = self._stretch_assembler.banded([H.numpy()])
        out = np.zeros((self.assembler.bandwidth + 1, self.n_dofs))
        out[: ab.shape[0]] = ab
        return out

    def with_compression(self, xf: np.ndarray, ab: np.ndarray) -> np.ndarray | None:
        """A new band: ``ab`` plus ``compression_band`` (the kernels' pass where there are
        kernels, ``StrandKernels.add_compression``), or None when no edge is compressed."""
        if self.kernels is not None:
            abT = ab.T.copy()
            return abT.T if self.kernels.add_compression(self, xf, abT) else None
        extra = self.compression_band(xf)
        return None if extra is None else ab + extra

    def exact_where_definite(self, ab: np.ndarray, extra: np.ndarray) -> tuple[np.ndarray, int]:
        """(band, blocks): ``ab + extra`` on every strand block (a run of free DOFs no element
        couples to the next, ``StrandKernels.blk_dof``; the whole band on the torch path) where
        that sum is positive definite, ``ab`` on the others; ``blocks``: how many kept ``ab``."""
        full = ab + extra
        if self.kernels is None:
            try:
                scipy.linalg.cholesky_banded(full, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                return ab, 1
            return full, 0
        blk = self.kernels.blk_dof
        A = np.ascontiguousarray(full.T)
        ok = np.ones(len(blk) - 1, dtype=np.bool_)
        bandchol.factor_serial(A, np.empty_like(A), blk, ok)
        if ok.all():
            return full, 0
        rows = np.repeat(~ok, np.diff(blk))
        full[:, rows] = ab[:, rows]
        return full, int((~ok).sum())

    def initial_guess(self) -> np.ndarray:
        return (self.x_pred if self.x_start is None else self.x_start).copy()

    # -- contact hooks (barrier.ObjectContact; all no-ops without contact) -----------------
    def full_positions(self, xf: np.ndarray) -> np.ndarray:
        """(V, 3) numpy: prescribed kinematic rows, free rows from xf."""
        x = self.x_full.copy()
        x[self.free_vertices] = xf.reshape(-1, 3)
        return x

    def max_step(self, xf: np.ndarray, p: np.ndarray) -> float:
        """Largest step <= 1 along p that no contact barrier forbids (CCD line-search filter)."""
        if self.contact is None:
            return 1.0
        P = np.zeros_like(self.x_full)
        P[self.free_vertices] = p.reshape(-1, 3)
        return self.contact.max_step(self.full_positions(xf), P)

    def positions(self, xf: np.ndarray) -> torch.Tensor:
        """(V, 3) tensor: prescribed kinematic rows, free rows from the DOF vector xf."""
        x = self.x_full.copy()
        x[self.free_vertices] = xf.reshape(-1, 3)
        return torch.from_numpy(x)

    def eval_positions(self, xf: np.ndarray) -> torch.Tensor:
        """(V, 3) tensor: where the energies are evaluated, y = (1 - alpha_f) x + alpha_f x_n
        (x itself unless the integrator is generalized-alpha)."""
        x = self.positions(xf)
        if self.alpha_f == 0.0:
            return x
        return (1.0 - self.alpha_f) * x + self.alpha_f * torch.from_numpy(np.ascontiguousarray(self.x_n, dtype=np.float64))

    # -- evaluation -----------------------------------------------------------------------
    def value(self, xf: np.ndarray) -> float:
        """H(xf).  Also sets ``value_noise``: the round-off of that sum (a few ulps of the sum of
        the terms' magnitudes), below which two values cannot be told apart."""
        if self.kernels is not None:
            inertia, e_st, e_bend, e_ext = self.kernels.value_parts(self, xf)
            parts = [e_st, e_bend]
            rest = self.torch_terms + ([] if self.kernels.handles_gravity else self.external)
            if self.kernels.handles_gravity:
                parts.append(e_ext)
            if rest:
                x = self.eval_positions(xf)
                with torch.no_grad():
                    parts += [float(t.total(x)) for t in rest]
        else:
            d = xf - self.x_pred
            inertia = 0.5 * float(np.dot(self.mass_diag * d, d))  # 1/2 dv^T M dv
            x = self.eval_positions(xf)
            with torch.no_grad():
                parts = [float(t.total(x)) for t in self.terms + self.external]
        if self.alpha_f != 0.0:
            parts = [p / (1.0 - self.alpha_f) for p in parts]
        if self.contact is not None:
            parts.append(self.contact.energy(self.full_positions(xf)))
        self.value_noise = ROUNDOFF_ULPS * np.finfo(float).eps * (abs(inertia) + sum(abs(p) for p in parts))
        return inertia + sum(parts)

    def evaluate(self, xf: np.ndarray, need_hessian: bool = True) -> Evaluation:
        if self.kernels is not None:
            return self._evaluate_kernels(xf, need_hessian)
        t0 = time.perf_counter()
        grads, hessians = self._torch_derivatives(self.terms, xf, need_hessian)
        t1 = time.perf_counter()
        g_int = self.assembler.gradient(grads)
        ab = self.assembler.banded(hessians, self.mass_diag) if need_hessian else None
        grad, scale = self._total_gradient(xf, g_int, ab)
        t2 = time.perf_counter()
        return Evaluation(grad, ab, scale, {"derivatives": t1 - t0, "assembly": t2 - t1})

    @property
    def fuses(self) -> bool:
        """Whether ``evaluate_step`` takes the fused pass: the compiled kernels take every term, no
        contact, ``fused`` on."""
        return self.fused and self.kernels is not None and not self.torch_terms and self.contact is None

    def evaluate_step(self, xf: np.ndarray) -> tuple[Evaluation, np.ndarray | None]:
        """(evaluation, Newton step p = -A^-1 grad or None).  With the compiled kernels taking
        every term and no contact (and ``fused``), one pass per strand computes the gradient,
        the band in a strand-sized buffer (it stays in cache; ``banded`` is then None), its
        factor and p: the gradient and step of ``evaluate`` + ``solve`` bit for bit (the force
        scale to round-off: its norms are summed per strand), timed together as "assembly".
        Otherwise ``evaluate`` and p None (the caller solves)."""
        if not self.fuses:
            return self.evaluate(xf, need_hessian=True), None
        t0 = time.perf_counter()
        out = self.kernels.direction(self, xf)
        if out is None:   # a block is not positive definite (round-off): the shifted factorisation
            return self.evaluate(xf, need_hessian=True), None
        grad, p, n_inertia, n_int = out
        t1 = time.perf_counter()
        return Evaluation(grad, None, n_inertia + n_int + self.ext_norm, {"derivatives": 0.0, "assembly": t1 - t0}), p

    def _evaluate_kernels(self, xf: np.ndarray, need_hessian: bool) -> Evaluation:
        """The compiled path: stretch, bending and inertia fused per strand into the band (timed
        as "assembly"); the other terms through torch (their derivatives timed as "derivatives")
        added to it."""
        t0 = time.perf_counter()
        g_int, abT = self.kernels.evaluate(self, xf, need_hessian)
        t1 = time.perf_counter()
        t_deriv = 0.0
        if self.torch_terms:
            grads, hessians = self._torch_derivatives(self.torch_terms, xf, need_hessian)
            t_deriv = time.perf_counter() - t1
            g_int += self.torch_assembler.gradient(grads)
            if need_hessian:
                ab_o = self.torch_assembler.banded(hessians)
                abT[:, : ab_o.shape[0]] += ab_o.T
        ab = abT.T if need_hessian else None   # a view of abT: what the contact adds lands in it
        grad, scale = self._total_gradient(xf, g_int, ab)
        t2 = time.perf_counter()
        return Evaluation(grad, ab, scale, {"derivatives": t_deriv, "assembly": t2 - t0 - t_deriv})

    def _torch_derivatives(self, terms, xf: np.ndarray, need_hessian: bool):
        """Element gradients and PSD Hessians (numpy) of ``terms`` at the evaluation point y; the
        Hessians scaled by (1 - alpha_f), d^2/dx^2 E(y)/(1 - alpha_f)."""
        x = self.eval_positions(xf)
        grads, hessians = [], []
        with torch.no_grad():
            for term in terms:
                g, H = term.grad_hess(x[term.stencil_t], need_hessian, self.derivatives)
                grads.append(g.numpy())
                if need_hessian:
                    hessians.append(H.numpy())
        if need_hessian and self.alpha_f != 0.0:
            hessians = [(1.0 - self.alpha_f) * H for H in hessians]
        return grads, hessians

    def _total_gradient(self, xf: np.ndarray, g_int: np.ndarray, ab: np.ndarray | None):
        """(gradient of the objective, force scale) from the internal gradient ``g_int``: plus the
        inertial and external forces and, with contact, the barrier's gradient (its Hessian added to
        ``ab`` in place; the friction lag is refreshed here: callers re-take H's value after)."""
        f_inertia = self.mass_diag * (xf - self.x_pred)
        grad = f_inertia + g_int + self.g_ext
        scale = float(np.linalg.norm(f_inertia) + np.linalg.norm(g_int) + self.ext_norm)
        if self.contact is not None:
            xc = self.full_positions(xf)
            self.contact.update_lag(xc)
            scale += self.contact.add_to(xc, grad, ab)
        return grad, scale

    def solve(self, ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs for the lower band ``ab`` of ``evaluate``: the compiled block Cholesky, or
        LAPACK's banded one (``assembly.banded_solve``) on the torch path."""
        if self.kernels is not None:
            return self.kernels.solve(ab, rhs)
        return banded_solve(ab, rhs)
