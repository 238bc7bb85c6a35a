"""KKT saddle-point solves of the SQP (paper eq. 8):

    [ H   0   A^T ] [dx ]   [ -r_x ]      H: banded PSD Hessian over free DOFs (N)
    [ 0   D   B^T ] [dt ] = [ -r_t ]      D: (K,) curvature of the sliding parameters
    [ A   B   0   ] [lam]   [ -C   ]      A: constant COM Jacobian (3K x N); B: dC/dt (3K x K)

``SchurKKT`` eliminates dx: with u = H^-1 r_x and S = A H^-1 A^T,

    [ S    -B ] [lam]   [ C - A u ]
    [ B^T   D ] [dt ] = [  -r_t   ],      dx = -H^-1 (r_x + A^T lam).

S is built from one banded Cholesky H = L L^T as S = Y^T Y, Y = L^-1 A^T.  H is block
diagonal over strands, so Y is computed strand by strand with batched dense triangular solves
(torch), and the columns of A^T for clusters of *different* guides (disjoint strands) share one
right-hand side "slot" (tracking point, coordinate): 3 x points-per-guide right-hand sides in
all, not 3K.  With soft assignment a strand belongs to clusters of several guides: the slot
of (strand, cluster) is (r P + p, coordinate), r the rank of the cluster's guide among the
guides the strand has weight on, so 3 x P x (most guides per strand) right-hand sides (hard:
r = 0, the layout above).  ``reference_solve`` is the plain sparse saddle-point solve (SuperLU) that tests
compare against.

With the objective's compiled kernels (``kernels``: hairexp/physics/strand_kernels.py,
``solver.kernels=numba``) the factorisation is the per-strand block Cholesky and Y^T Y is built
strand by strand in numba (hairexp/physics/bandchol.py ``schur_*``: each column's forward
substitution starts at its first non-zero row, the products skip the zero rows); otherwise
LAPACK's banded Cholesky and batched torch triangular solves.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from hairexp.physics import bandchol
from hairexp.physics.assembly import BandedAssembler


class SchurKKT:
    def __init__(self, strands, cons, bandwidth: int, kernels=None):
        """``kernels``: the objective's ``StrandKernels`` (None: the LAPACK + torch path); used
        only when each strand's DOFs are whole blocks of it."""
        s = strands
        free = np.flatnonzero(~s.kinematic)
        strand_of_free = s.strand_of_vertex[free]
        S = s.n_strands
        nf = np.bincount(strand_of_free, minlength=S)          # free vertices per strand
        self.dof_off = 3 * np.concatenate([[0], np.cumsum(nf)])
        n = 3 * nf
        nmax = int(n.max())
        self.S, self.nmax, self.bw, self.N = S, nmax, bandwidth, int(self.dof_off[-1])
        # band -> per-strand dense lower factor map
        src, dst = [], []
        for d in range(bandwidth + 1):
            j = np.arange(self.N)
            st = np.repeat(np.arange(S), n)
            loc = j - self.dof_off[st]
            ok = loc + d < n[st]
            src.append(d * self.N + j[ok])
            dst.append((st[ok] * nmax + loc[ok] + d) * nmax + loc[ok])
        self._src, self._dst = np.concatenate(src), np.concatenate(dst)
        pad = [(si * nmax + k) * nmax + k for si in range(S) for k in range(n[si], nmax)]
        self._pad = np.asarray(pad, dtype=np.int64)
        # right-hand-side slots: (guide rank r, tracking point p, coordinate c) -> slot 3 (r P + p) + c
        K = cons.K
        P = int(cons.corr.cluster_point.max()) + 1
        G = cons.guides.n_guides
        gw = cons.corr.guide_weights
        on = gw > 0 if gw is not None else np.eye(G, dtype=bool)[cons.corr.guide_of_strand]   # (S, G)
        rank = np.cumsum(on, axis=1) - 1                            # rank of guide g among the strand's guides
        nr = int(on.sum(1).max())
        self.R = 3 * P * nr
        AT = np.zeros((S, nmax, self.R))
        fv = cons.free_in_cluster                                  # free-vertex index per membership
        k = cons.member_cluster
        st = strand_of_free[fv]
        loc = 3 * fv - self.dof_off[st]
        slot = rank[st, cons.corr.cluster_guide[k]] * P + cons.corr.cluster_point[k]
        for c in range(3):
            AT[st, loc + c, 3 * slot + c] = cons.weights
        self.AT = torch.as_tensor(AT)
        # global constraint row of each (strand, slot); 3K is a dummy row for empty slots
        lookup = np.full((G, P), -1)
        lookup[cons.corr.cluster_guide, cons.corr.cluster_point] = np.arange(K)
        kk = np.full((S, P * nr), -1)                                # (S, R / 3): cluster of each slot
        for r in range(nr):
            g_r = np.argmax(on & (rank == r), axis=1)               # the strand's guide of rank r
            has = (on & (rank == r)).any(axis=1)
            kk[:, r * P:(r + 1) * P] = np.where(has[:, None], lookup[g_r], -1)
        kk = kk[:, np.arange(self.R) // 3]                          # (S, R)
        rows = np.where(kk >= 0, 3 * kk + np.arange(self.R) % 3, 3 * K)
        self._rows = np.ascontiguousarray(rows, dtype=np.int64)     # (S, R)
        self._srow = (rows[:, :, None] * (3 * K + 1) + rows[:, None, :]).ravel()
        self.K = K
        self.A, self.AT_sparse = cons.A, cons.AT
        self.kernels = None
        if kernels is not None and np.isin(self.dof_off, kernels.blk_dof).all():
            self.kernels = kernels
            self._Bt, self._first, self._base, self._scale = distinct_columns(AT)
            # strands with the same constraint rows, summed together before the scatter into S
            g_rows, g_of = np.unique(self._rows, axis=0, return_inverse=True)
            order = np.argsort(g_of.ravel(), kind="stable")
            self._g_rows = np.ascontiguousarray(g_rows, dtype=np.int64)
            self._g_strands = order.astype(np.int64)
            self._g_ptr = np.searchsorted(g_of.ravel()[order], np.arange(len(g_rows) + 1)).astype(np.int64)
            self._dof_off = np.ascontiguousarray(self.dof_off, dtype=np.int64)

    def factor(self, ab: np.ndarray) -> None:
        """Factor H (lower band ``ab``) and build S = A H^-1 A^T."""
        if self.kernels is not None:
            self._factor_kernels(ab)
            return
        try:
            self.cb = scipy.linalg.cholesky_banded(ab, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            ab = ab.copy()
            ab[0] += 1e-8 * np.abs(ab[0]).max()
            self.cb = scipy.linalg.cholesky_banded(ab, lower=True, check_finite=False)
        if not hasattr(self, "_Ld"):  # entries off the band pattern stay zero: allocate once
            self._Ld = np.zeros(self.S * self.nmax * self.nmax)
            self._Ld[self._pad] = 1.0
        self._Ld[self._dst] = self.cb.reshape(-1)[self._src]
        L = torch.from_numpy(self._Ld.reshape(self.S, self.nmax, self.nmax))
        Y = torch.linalg.solve_triangular(L, self.AT, upper=False)
        YtY = (Y.transpose(1, 2) @ Y).numpy()
        n = 3 * self.K + 1
        Sfull = np.bincount(self._srow, weights=YtY.ravel(), minlength=n * n).reshape(n, n)
        self.Smat = Sfull[:-1, :-1]

    def _factor_kernels(self, ab: np.ndarray) -> None:
        k = self.kernels
        self.LT = k.factor(ab)
        self.cb = self.LT.T        # scipy.linalg.cholesky_banded's layout
        G = np.empty((self.S, self._Bt.shape[1], self._Bt.shape[1]))
        if k.parallel:
            bandchol.set_threads(k.threads)
            bandchol.schur_parallel(self.LT, self._Bt, self._first, self._dof_off, G)
        else:
            bandchol.schur_serial(self.LT, self._Bt, self._first, self._dof_off, G)
        n = 3 * self.K + 1
        Sfull = np.zeros((n, n))
        bandchol.scatter_grouped(G, self._base, self._scale, self._g_ptr, self._g_strands, self._g_rows, Sfull)
        self.Smat = Sfull[:-1, :-1]

    def hinv(self, r: np.ndarray) -> np.ndarray:
        if self.kernels is not None:
            return self.kernels.cho_solve(self.LT, r)
        return scipy.linalg.cho_solve_banded((self.cb, True), r, check_finite=False)

    def solve(self, r_x: np.ndarray, C: np.ndarray, Bmat: np.ndarray | None = None, D: np.ndarray | None = None,
              r_t: np.ndarray | None = None, reg: np.ndarray | None = None):
        """(dx, dt or None, lam) for the system above; C: (3K,), Bmat: (3K, K) or None (static);
        ``reg`` (3K,): -diag(reg) in the (lam, lam) block (the SQP's elastic rows, reg = 1/rho)."""
        u = self.hinv(r_x)
        rhs_l = C - self.A @ u
        Smat = self.Smat if reg is None else self.Smat + np.diag(reg)
        if Bmat is None:
            lam = np.linalg.solve(Smat, rhs_l)
            dt = None
        else:
            K = Bmat.shape[1]
            M = np.block([[Smat, -Bmat], [Bmat.T, np.diag(D)]])
            sol = np.linalg.solve(M, np.concatenate([rhs_l, -r_t]))
            lam, dt = sol[:3 * self.K], sol[3 * self.K:]
        dx = -self.hinv(r_x + self.AT_sparse @ lam)
        return dx, dt, lam


def distinct_columns(AT: np.ndarray):
    """Each strand's columns of A^T (AT: (S, n, R)) up to scale: (Bt (S, Rb, n) the distinct
    columns sorted by first (S, Rb), their first non-zero row (-1: padding, last), base (S, R) and scale (S, R)
    with AT[s, :, r] = scale[s, r] Bt[s, base[s, r]] (base -1: an empty column)."""
    S, n, R = AT.shape
    base = np.full((S, R), -1, dtype=np.int64)
    scale = np.zeros((S, R))
    cols = []
    for s in range(S):
        c = AT[s].T                                                     # (R, n)
        nz = c != 0
        has = nz.any(axis=1)
        lead = np.where(has, c[np.arange(R), nz.argmax(axis=1)], 1.0)  # the first non-zero entry
        u = c / lead[:, None]
        mine = []
        for r in np.flatnonzero(has):
            for b, v in enumerate(mine):
                if np.array_equal(nz[r], v != 0) and np.allclose(u[r], v, rtol=1e-13, atol=0.0):
                    break
            else:
                b = len(mine)
                mine.append(u[r])
            base[s, r], scale[s, r] = b, lead[r]
        cols.append(mine)
    Rb = max(1, max(len(m) for m in cols))
    Bt = np.zeros((S, Rb, n))
    first = np.full((S, Rb), -1, dtype=np.int64)
    for s, mine in enumerate(cols):   # sorted by first non-zero row (bandchol.schur_block needs it)
        f = np.array([int(np.flatnonzero(v)[0]) for v in mine], dtype=np.int64)
        order = np.argsort(f, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        for b, o in enumerate(order):
            Bt[s, b] = mine[o]
            first[s, b] = f[o]
        has = base[s] >= 0
        base[s, has] = rank[base[s, has]]
    return Bt, first, base, scale


def reference_solve(ab: np.ndarray, A: sp.spmatrix, r_x: np.ndarray, C: np.ndarray, Bmat: np.ndarray | None = None,
                    D: np.ndarray | None = None, r_t: np.ndarray | None = None, reg: np.ndarray | None = None):
    """The plain sparse saddle-point solve of the same system (SuperLU); ``reg`` as in
    ``SchurKKT.solve``."""
    H = BandedAssembler.to_sparse(ab)
    m = A.shape[0]
    Z = None if reg is None else sp.diags(-np.asarray(reg))
    if Bmat is None:
        Kk = sp.bmat([[H, A.T], [A, Z]], format="csc")
        sol = spla.spsolve(Kk, -np.concatenate([r_x, C]))
        return sol[:H.shape[0]], None, sol[H.shape[0]:]
    Bs = sp.csr_matrix(Bmat)
    Kk = sp.bmat([[H, None, A.T], [None, sp.diags(D), Bs.T], [A, Bs, Z]], format="csc")
    sol = spla.spsolve(Kk, -np.concatenate([r_x, r_t, C]))
    N, K = H.shape[0], Bmat.shape[1]
    return sol[:N], sol[N:N + K], sol[N + K:]
