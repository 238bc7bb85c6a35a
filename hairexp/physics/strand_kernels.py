"""The compiled path of the implicit Euler objective (``solver.kernels=numba``).

``StrandKernels`` takes over the objective's ``Stretch`` and ``Bending`` terms, the inertia
M/h^2 (x - x_pred) and the gravity gradient (paper eq. 5 and its ``StepPlan`` generalisation,
hairexp/physics/integrators.py) and evaluates them per strand with the numba kernels of
hairexp/physics/kernels.py, straight into the lower band; it factors and solves that band
block by block (hairexp/physics/bandchol.py).  Every other term (edge damping, air drag, a
controller's springs, any new term) still goes through its torch path and is added to the same
band by ``ImplicitEulerObjective``: the generic autograd path stays for any term.

``build`` returns None (and the objective keeps the torch path) when numba is missing or the
terms do not fit: several Stretch or Bending terms, subclasses, or stencils whose free vertices
are not numbered in stencil order (the DOFs are numbered strand by strand, so they are).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from hairexp.errors import InputError, choice_name
from hairexp.physics import bandchol, kernels
from hairexp.physics.bandchol import AUTO_RECHECK_S, THREAD_CHOICES, pick_threads, set_threads
from hairexp.physics.energies import Bending, Gravity, Stretch

#: solver.kernels choices: compiled per-strand kernels, or the torch closed forms + bincount assembly.
KERNEL_CHOICES = ("numba", "torch")
#: Diagonal shift (relative to the largest diagonal entry) when round-off makes a block indefinite,
#: as hairexp/physics/assembly.py ``banded_solve``.
SHIFT = 1e-8

log = logging.getLogger(__name__)


def check_options(kernels_opt, threads) -> tuple[str, str]:
    """(kernels, threads) as strings; InputError naming ``solver.kernels`` / ``solver.threads``."""
    k = choice_name(kernels_opt)
    if k not in KERNEL_CHOICES:
        raise InputError(f"unknown kernels {k!r} (one of {', '.join(KERNEL_CHOICES)})", "solver.kernels")
    t = choice_name(threads)
    if t not in THREAD_CHOICES:
        raise InputError(f"must be one of {', '.join(THREAD_CHOICES)}, got {t!r}", "solver.threads")
    return k, t


def _blocks(free_slot: np.ndarray, stencils: list[np.ndarray], n_free: int) -> np.ndarray:
    """(B + 1,) free-vertex offsets of the runs of free vertices that no stencil couples to the
    next run (a strand's free vertices)."""
    cover = np.zeros(n_free + 1, dtype=np.int64)
    for st in stencils:
        f = free_slot[np.asarray(st)]
        hi = np.where(f >= 0, f, -1).max(axis=1)
        lo = np.where(f >= 0, f, n_free).min(axis=1)
        has = hi > lo
        np.add.at(cover, lo[has], 1)
        np.add.at(cover, hi[has], -1)
    linked = np.cumsum(cover)[: max(n_free - 1, 0)] > 0           # free vertex i coupled to i + 1
    return np.concatenate([[0], np.flatnonzero(~linked) + 1, [n_free]]).astype(np.int64)


def _group(stencil: np.ndarray, free_slot: np.ndarray, blk_vert: np.ndarray):
    """Elements with a free vertex sorted by block: (index, block pointers (B + 1,)), the others,
    and whether the free vertices of every element are numbered in stencil order."""
    f = free_slot[stencil]
    has = (f >= 0).any(axis=1)
    ordered = True
    for a in range(f.shape[1]):
        for b in range(a + 1, f.shape[1]):
            both = (f[:, a] >= 0) & (f[:, b] >= 0)
            ordered &= bool(np.all(f[both, a] < f[both, b]))
    blk = np.searchsorted(blk_vert, f.max(axis=1), side="right") - 1
    idx = np.flatnonzero(has)
    idx = idx[np.argsort(blk[idx], kind="stable")]
    ptr = np.searchsorted(blk[idx], np.arange(len(blk_vert)), side="left").astype(np.int64)
    return idx.astype(np.int64), ptr, np.flatnonzero(~has).astype(np.int64), ordered


def _frozen(a) -> np.ndarray:
    """``a`` as a contiguous int64 array, read-only (``kernels.read_only``): a cold goaling
    experiment built assemble, energies, direction and tensions (serial and parallel) twice, for
    the scene's read-only topology and a deep copy's writable one."""
    return kernels.read_only(np.ascontiguousarray(a, dtype=np.int64))


def _np(t) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy() if isinstance(t, torch.Tensor) else t, dtype=np.float64)


class StrandKernels:
    def __init__(self, stretch: Stretch, bending: Bending, gravity: bool, free_slot, free_vertices,
                 bandwidth: int, blk_vert: np.ndarray, threads: int):
        self.stretch, self.bending, self.handles_gravity = stretch, bending, gravity
        self.free_slot = _frozen(free_slot)
        self.free_vertices = np.ascontiguousarray(free_vertices, dtype=np.int64)
        #: the vertices that are not free (their rows of the evaluation point come from x_full)
        self.fixed_vertices = np.setdiff1d(np.arange(len(self.free_slot)), self.free_vertices).astype(np.int64)
        self.blk_dof = 3 * blk_vert
        self.n_dofs = int(self.blk_dof[-1])
        self.bw = int(bandwidth)
        self.threads = threads   # 1: the serial kernels; 2: the prange ones
        self.thread_setting = "auto"
        self._checked = time.monotonic()
        self.edges = _frozen(stretch.stencil)
        self.bends = _frozen(bending.stencil)
        self.e_idx, self.e_ptr, self.e_rest, _ = _group(self.edges, self.free_slot, blk_vert)
        self.b_idx, self.b_ptr, self.b_rest, _ = _group(self.bends, self.free_slot, blk_vert)
        self.k_l0, self.l0 = _np(stretch.k_l0), _np(stretch.l0)
        self.w, self.s_rest = _np(bending.w), _np(bending.s_rest)
        self._Y = np.zeros((len(self.free_slot), 3))
        self._ok = np.ones(len(self.blk_dof) - 1, dtype=np.bool_)
        self._zero_t = np.zeros(len(self.edges))
        self._zero_dofs = np.zeros(self.n_dofs)
        self._sums = np.empty((len(self.blk_dof) - 1, 2))
        self.seconds_compile = 0.0

    @classmethod
    def build(cls, terms, external, free_slot, free_vertices, bandwidth: int, threads: str = "auto"):
        """The kernels for ``terms`` (or None: numba missing, or no single Stretch and Bending
        pair the kernels can take, see the module doc)."""
        if not kernels.HAVE_NUMBA:
            log.warning("solver.kernels=numba but numba is not importable; using the torch path")
            return None
        st = [t for t in terms if type(t) is Stretch]
        be = [t for t in terms if type(t) is Bending]
        if len(st) != 1 or len(be) != 1 or bandwidth != bandchol.BW:
            return None
        free_slot = np.asarray(free_slot)
        n_free = int((free_slot >= 0).sum())
        blk_vert = _blocks(free_slot, [t.stencil for t in terms], n_free)
        for t in (st[0], be[0]):
            if not _group(np.asarray(t.stencil), free_slot, blk_vert)[3]:
                return None
        gravity = len(external) == 1 and type(external[0]) is Gravity
        k = cls(st[0], be[0], gravity, free_slot, free_vertices, bandwidth, blk_vert,
                pick_threads(threads, vertices=n_free))
        k.thread_setting = choice_name(threads)
        return k

    def retune(self) -> None:
        """``solver.threads=auto``: re-decide the threads from the load (at most every
        ``AUTO_RECHECK_S``); called at the start of each step.  The kernels sum each strand in the
        same order on any thread count, so the results do not change."""
        now = time.monotonic()
        if self.thread_setting == "auto" and now - self._checked >= AUTO_RECHECK_S:
            self._checked = now
            self.threads = pick_threads("auto", self.threads, vertices=len(self.free_vertices))

    @property
    def parallel(self) -> bool:
        return self.threads > 1

    def handles(self, term) -> bool:
        return term is self.stretch or term is self.bending

    def _points(self, obj, xf: np.ndarray) -> np.ndarray:
        if self.parallel:
            set_threads(self.threads)
        kernels.eval_points(np.ascontiguousarray(xf, dtype=np.float64), obj.x_full,
                            np.ascontiguousarray(obj.x_n, dtype=np.float64), self.free_vertices, self.fixed_vertices,
                            obj.alpha_f, self._Y)
        return self._Y

    def evaluate(self, obj, xf: np.ndarray, need_hessian: bool):
        """(g_int (N,), abT (N, bw + 1) or None): the gradient of stretch and bending at y and the
        band of M/h^2 + (1 - alpha_f)(their Hessians), ``abT.T`` in LAPACK lower storage."""
        Y = self._points(obj, xf)
        T = self.stretch.tension
        use_t = T is not None
        tension = _np(T) if use_t else self._zero_t
        g_int = np.empty(self.n_dofs)
        abT = np.empty((self.n_dofs, self.bw + 1) if need_hessian else (1, 1))
        run = kernels.assemble_parallel if self.parallel else kernels.assemble_serial
        run(Y, self.free_slot, self.blk_dof, self.e_ptr, self.e_idx, self.edges, self.k_l0, self.l0,
            tension, use_t, self.b_ptr, self.b_idx, self.bends, self.w, self.s_rest,
            1.0 - obj.alpha_f, obj.mass_diag, abT, g_int, need_hessian, 4 * self.threads)
        return g_int, (abT if need_hessian else None)

    def value_parts(self, obj, xf: np.ndarray) -> tuple[float, float, float, float]:
        """(inertia, stretch, bending, gravity g_ext . y) at xf: the line search's energies."""
        Y = self._points(obj, xf)
        out = np.empty((len(self.blk_dof) - 1, 4))
        run = kernels.energies_parallel if self.parallel else kernels.energies_serial
        run(Y, np.ascontiguousarray(xf, dtype=np.float64), obj.x_pred, obj.mass_diag, obj.g_ext, self.free_vertices,
            self.blk_dof, self.e_ptr, self.e_idx, self.edges, self.k_l0, self.l0, self.b_ptr, self.b_idx, self.bends,
            self.w, self.s_rest, self.e_rest, self.b_rest, out)
        s = out.sum(axis=0)
        return float(s[0]), float(s[1]), float(s[2]), float(s[3])

    def elastic_energies(self, x: np.ndarray) -> tuple[float, float]:
        """(stretch, bending) energies in J of the full positions x (V, 3): the terms' ``total``
        (the metrics' potential energy, hairexp/outputs/metrics.py), by the line search's kernel."""
        Y = np.ascontiguousarray(x, dtype=np.float64)
        if Y.shape != self._Y.shape:
            raise ValueError(f"elastic_energies: positions of shape {Y.shape}, the kernels have {self._Y.shape}")
        out = np.empty((len(self.blk_dof) - 1, 4))
        zero = self._zero_dofs
        kernels.energies_serial(Y, zero, zero, zero, zero, self.free_vertices, self.blk_dof, self.e_ptr, self.e_idx,
                                self.edges, self.k_l0, self.l0, self.b_ptr, self.b_idx, self.bends, self.w,
                                self.s_rest, self.e_rest, self.b_rest, out)
        return float(out[:, 1].sum()), float(out[:, 2].sum())

    def tensions(self, obj, xf: np.ndarray, step: np.ndarray | None) -> np.ndarray:
        """(E,) tensions at y(xf), linearised along ``step`` (None: exact), as ``Stretch``."""
        Y = self._points(obj, xf)
        out = np.empty(len(self.edges))
        if step is None:
            kernels.tensions_along(Y, self._zero_dofs, 0.0, self.free_slot, self.edges, self.k_l0, self.l0, out)
        else:
            kernels.tensions_along(Y, np.ascontiguousarray(step, dtype=np.float64), 1.0 - obj.alpha_f, self.free_slot,
                                   self.edges, self.k_l0, self.l0, out)
        return out

    def direction(self, obj, xf: np.ndarray):
        """The fused Newton pass of the free objective (``kernels.direction_serial``): (grad (N,),
        p = -A^-1 grad (N,), |inertial force|, |internal force|), or None where a block's pivot
        was not positive (the caller then factors the band with a shift)."""
        Y = self._points(obj, xf)
        T = self.stretch.tension
        use_t = T is not None
        tension = _np(T) if use_t else self._zero_t
        grad = np.empty(self.n_dofs)
        p = np.empty(self.n_dofs)
        sums = self._sums
        run = kernels.direction_parallel if self.parallel else kernels.direction_serial
        run(Y, np.ascontiguousarray(xf, dtype=np.float64), obj.x_pred, obj.g_ext, self.free_slot, self.blk_dof,
            self.e_ptr, self.e_idx, self.edges, self.k_l0, self.l0, tension, use_t, self.b_ptr, self.b_idx, self.bends,
            self.w, self.s_rest, 1.0 - obj.alpha_f, obj.mass_diag, grad, p, sums, self._ok, 4 * self.threads)
        if not self._ok.all():
            return None
        s = sums.sum(axis=0)
        return grad, p, float(np.sqrt(s[0])), float(np.sqrt(s[1]))

    # -- the band ------------------------------------------------------------------------
    def factor(self, ab: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
        """Cholesky factor LT (N, bw + 1) of the lower band ``ab`` ((bw + 1, N), e.g. ``abT.T``),
        with a small diagonal shift where round-off made a block indefinite; ``LT.T`` is in
        ``scipy.linalg.cholesky_banded(lower=True)`` layout.  ``fallback`` (a band as ``ab``): the
        blocks of ``ab`` that are not positive definite are factored from it instead (their
        count: ``self.fell_back``)."""
        if self.parallel:
            set_threads(self.threads)
        run = bandchol.factor_parallel if self.parallel else bandchol.factor_serial
        A = np.ascontiguousarray(ab.T)
        L = np.empty_like(A)
        run(A, L, self.blk_dof, self._ok)
        self.fell_back = 0
        if fallback is not None and not self._ok.all():
            self.fell_back = int((~self._ok).sum())
            rows = np.repeat(~self._ok, np.diff(self.blk_dof))
            A = A.copy() if np.shares_memory(A, ab) else A
            A[rows] = fallback.T[rows]
            run(A, L, self.blk_dof, self._ok)
        if not self._ok.all():
            A = A.copy()
            A[:, 0] += SHIFT * np.abs(A[:, 0]).max()
            run(A, L, self.blk_dof, self._ok)
            if not self._ok.all():
                raise np.linalg.LinAlgError("the Hessian band is not positive definite")
        return L

    def add_compression(self, obj, xf: np.ndarray, abT: np.ndarray) -> int:
        """Adds the compressed edges' negative transverse stiffness to the band abT (N, bw + 1)
        in place (``kernels.add_compression``, scaled as the band by 1 - alpha_f); the number of
        compressed edges."""
        Y = self._points(obj, xf)
        T = self.stretch.tension
        use_t = T is not None
        tension = _np(T) if use_t else self._zero_t
        return int(kernels.add_compression(Y, self.free_slot, self.edges, self.k_l0, self.l0, tension, use_t,
                                           1.0 - obj.alpha_f, abT))

    def cho_solve(self, L: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs from the factor of ``factor``; rhs (N,) or (N, R)."""
        if self.parallel:
            set_threads(self.threads)
        b = np.ascontiguousarray(rhs, dtype=np.float64)
        x = np.empty_like(b)
        if b.ndim == 1:
            run = bandchol.solve1_parallel if self.parallel else bandchol.solve1_serial
            run(L, b, x, self.blk_dof)
        else:
            run = bandchol.solve_parallel if self.parallel else bandchol.solve_serial
            run(L, b, x, self.blk_dof)
        return x

    def solve(self, ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs for the lower band ``ab`` (as assembly.banded_solve)."""
        return self.cho_solve(self.factor(ab), rhs)
