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

``tracking.schur=krylov`` does not build S at every SQP iteration: A is constant, so a product
S v = A H^-1 A^T v costs one solve with the current factor, and the reduced system above is
solved by GMRES right-preconditioned with the exact solve of the same system with the last S
built (an earlier iteration's or step's Hessian).  The products' solves run over all strands at
once, strand-interleaved (``solve_interleaved``: one strand's banded substitution is a chain of
dependent operations, 301 of them side by side vectorise), and dx comes from the products'
solves (no further solve).  A solve stops at |b - M z| <= krylov_tol |b| (checked again with the
true residual) and an error estimate |P^-1 (b - M z)| within krylov_tol of each block of z (lam,
dt); one that would need more than ``krylov_max`` iterations builds S for the current factor and
solves directly: the exact path, which is also the whole of ``tracking.schur=exact``.  The SQP
then solves for the multiplier's change (hairexp/control/tracking/sqp.py), so that the relative
tolerance applies to the step.  With krylov_tol = 1e-12 the KKT residual of a solve is that of
the direct solves (round-off; tests/test_tracking_solver.py); the default, 1e-6 (``KRYLOV_TOL``),
makes each SQP step an inexact Newton step, whose error the next iteration corrects.
"""

from __future__ import annotations

import math

import numpy as np

from hairexp.errors import InputError
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from hairexp.physics import bandchol
from hairexp.physics.assembly import BandedAssembler
from hairexp.physics.kernels import HAVE_NUMBA, njit, prange

#: ``tracking.schur``: how the Schur complement enters each solve (``SchurKKT``)
SCHUR_MODES = ("exact", "krylov")
#: Krylov mode: the relative residual |b - M z| / |b| of the reduced system each solve reaches
#: (``tracking.krylov_tol``).  An inexact Newton step (the SQP's own convergence test is on the true
#: residuals): on the Celia benchmark 1e-6 took the same SQP iterations as 1e-12 (7.87 a step, max
#: 11), 7.8 GMRES iterations a solve against 9.3 and 17 builds of S against 31, residual 8.7e-12 of
#: the hair length against 2.3e-13; 0.86-0.90 x the step time (2026-12-06, steps interleaved).
#: 1e-12 gives the direct solves' KKT residual (round-off; the tests that compare paths use it).
KRYLOV_TOL = 1e-6
#: Krylov mode: iterations (solves with H) before S is built again for the current factor (at
#: Celia's size an iteration costs about a twentieth of building S)
KRYLOV_MAX = 16


#: The strand-interleaved kernels (band, factor, the Krylov products, the solve) on 2 threads split the
#: strands into this many contiguous chunks (``prange``), one a thread; the products' A x is summed by
#: the same chunks on one thread too, so the numbers do not depend on the thread count.  They run on 2
#: threads from ``bandchol.PARALLEL_MIN_BLOCKS`` strands on (``SchurKKT._threaded``).  More chunks cost
#: more than they balance: 8 took 1.8 x the time of one pass for the solve at Celia's size, 2 took 1.15.
IL_CHUNKS = 2


@njit(cache=True, error_model="numpy")
def il_chunk(S, c):
    """(s0, s1): the strands of chunk ``c`` of ``IL_CHUNKS`` (contiguous, sizes within 1)."""
    return (S * c) // IL_CHUNKS, (S * (c + 1)) // IL_CHUNKS


#: bytes the per-strand Schur blocks may take (``SchurKKT``): Celia's 301 strands x 54 columns
#: take about 20 MB
MAX_SCHUR_BYTES = 4 << 30


def schur_bytes(strands: int, columns: int, dofs: int) -> int:
    """Bytes of ``SchurKKT``'s per-strand blocks: A^T's (strands, dofs, columns), the (columns,
    columns) products and their scatter indices, for ``columns`` right-hand sides a strand."""
    return int(strands) * int(columns) * (2 * int(columns) + 3 * int(dofs)) * 8


class SchurKKT:
    def __init__(self, strands, cons, bandwidth: int, kernels=None, schur: str = "exact",
                 krylov_tol: float = KRYLOV_TOL, krylov_max: int = KRYLOV_MAX):
        """``kernels``: the objective's ``StrandKernels`` (None: the LAPACK + torch path); used
        only when each strand's DOFs are whole blocks of it.  ``schur``: "exact" builds S for
        every factorisation; "krylov" keeps the last S built and solves with it as the
        preconditioner (``solve``), building S again only when the Krylov solve needs more than
        ``krylov_max`` iterations to reach the relative residual ``krylov_tol``."""
        if schur not in SCHUR_MODES:
            raise ValueError(f"unknown schur mode {schur!r} ({'|'.join(SCHUR_MODES)})")
        self.mode, self.krylov_tol, self.krylov_max = schur, float(krylov_tol), int(krylov_max)
        self.Smat = None          # the last S built (exact for the current factor when ``fresh``)
        self.fresh = False
        self.stats = {"factors": 0, "builds": 0, "direct_solves": 0, "krylov_solves": 0, "krylov_iterations": 0,
                      "krylov_fallbacks": 0}
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
        need = schur_bytes(S, self.R, nmax)
        if need > MAX_SCHUR_BYTES:
            # 4 guides x 256 points: 13.8 GB of indices for 200 strands, then the machine's memory ran
            # out with the run unable to stop (probe of issue 12, round 11)
            raise InputError(f"the tracked step's per-strand Schur blocks would take {need / 2 ** 30:.1f} GiB "
                             f"({S} strands, each sharing {self.R // 3} tracking points of {nr} guides; "
                             f"at most {MAX_SCHUR_BYTES / 2 ** 30:g} GiB): use fewer tracking.points_per_guide "
                             "or guides, or tracking.assignment=hard", "tracking.points_per_guide")
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
        # the Krylov mode's products with H^-1 run strand-interleaved (``solve_interleaved``): DOF
        # j of strand s at position j S + s of an (nmax, S) array; A's columns permuted to match
        pos = np.arange(nmax)[:, None] * S + np.arange(S)[None, :]                  # (nmax, S)
        il_dof = np.where(np.arange(nmax)[:, None] < n[None, :], self.dof_off[:-1][None, :] + np.arange(nmax)[:, None],
                          self.N)
        self._il_of_dof = np.empty(self.N, dtype=np.int64)                          # global DOF -> position
        real = il_dof < self.N
        self._il_of_dof[il_dof[real]] = pos[real]
        A_pad = sp.hstack([cons.A, sp.csr_matrix((3 * K, 1))], format="csr")
        self._A_il = A_pad[:, il_dof.ravel()].tocsr()
        self._AT_il = self._A_il.T.tocsr()
        self._L_il = None                     # the factor interleaved, built on the first product
        self._il_buf = None                   # its buffers, kept from factor to factor (``_il_buffers``)
        self._LT = self._cb = None            # the factor in bandchol's / LAPACK's layout (``LT``, ``cb``)
        # A^T's rows in the interleaved order as (position, membership) lists, padded with weight 0
        # (``_products``: A^T v, the solve and A x in one pass)
        ATc = self._AT_il.tocsr()
        cnt = np.diff(ATc.indptr)
        cmax = max(int(cnt.max(initial=0)), 1)
        # int32 as the per-vertex lists: one type, so each compiled product kernel has one signature
        # (numba's on-disk cache pairs an index and data files per function; two processes compiling
        # two signatures of one function at once can pair one's index with the other's code)
        self._m_rows = np.zeros((nmax * S, cmax), dtype=np.int32)
        self._m_wts = np.zeros((nmax * S, cmax))
        slot = np.arange(ATc.nnz) - np.repeat(ATc.indptr[:-1], cnt)
        pos_of = np.repeat(np.arange(nmax * S), cnt)
        self._m_rows[pos_of, slot] = ATc.indices
        self._m_wts[pos_of, slot] = ATc.data
        self._m_rows = self._m_rows.reshape(nmax, S, cmax)
        self._m_wts = self._m_wts.reshape(nmax, S, cmax)
        # the same lists per vertex (``_products``, ``per_vertex``): a DOF's rows are its vertex's clusters'
        # rows at the DOF's coordinate, with the vertex's weights (A = W (x) I3), so (nmax / 3, S, cmax)
        # cluster indices (int32) and weights: a sixth of the bytes the product streams per call
        # (at 10,000 strands 33 MB -> 9 MB), the same sums in the same order
        self._v_rows = self._v_wts = None
        if nmax % 3 == 0:
            r3 = self._m_rows.reshape(nmax // 3, 3, S, cmax)
            w3 = self._m_wts.reshape(nmax // 3, 3, S, cmax)
            k0 = r3[:, 0] // 3
            pad = w3[:, 0] == 0.0
            same = all(np.array_equal(w3[:, c], w3[:, 0]) and np.array_equal(np.where(pad, 0, r3[:, c]),
                                                                               np.where(pad, 0, 3 * k0 + c))
                       for c in range(3))
            if same and 3 * K < np.iinfo(np.int32).max:
                self._v_rows = np.ascontiguousarray(np.where(pad, 0, k0), dtype=np.int32)
                self._v_wts = np.ascontiguousarray(w3[:, 0])
        # the Krylov products' lists of A^T's rows (per vertex where A = W (x) I3, else per DOF) and
        # A's rows as lists per chunk of strands (``scatter_lists``), for their A x
        per_vertex = self._v_rows is not None
        self._lists = (self._v_rows, self._v_wts, True) if per_vertex else (self._m_rows, self._m_wts, False)
        self._scatter = scatter_lists(self._lists[0], self._lists[1], K if per_vertex else 3 * K, per_vertex)
        self._uniform = bool(np.all(n == nmax))
        self._W_buf = None                    # the Krylov products' rows (``_krylov``), kept between solves
        jj, aa = np.meshgrid(np.arange(nmax), np.arange(bandwidth + 1), indexing="ij")
        self._il_cut = (jj + aa >= nmax) & (aa > 0)                                   # (nmax, bw + 1)
        self.kernels = None
        self._dof_off = np.ascontiguousarray(self.dof_off, dtype=np.int64)
        if kernels is not None and np.isin(self.dof_off, kernels.blk_dof).all():
            self.kernels = kernels
            # ``_factor_interleaved``: each DOF's block end, and each strand's pivots' outcome
            self._blk_end = np.repeat(kernels.blk_dof[1:], np.diff(kernels.blk_dof)).astype(np.int64)
            self._ok_il = np.empty(S, dtype=np.bool_)
            self._Bt, self._first, self._base, self._scale = distinct_columns(AT)
            # strands with the same constraint rows, summed together before the scatter into S
            g_rows, g_of = np.unique(self._rows, axis=0, return_inverse=True)
            order = np.argsort(g_of.ravel(), kind="stable")
            self._g_rows = np.ascontiguousarray(g_rows, dtype=np.int64)
            self._g_strands = order.astype(np.int64)
            self._g_ptr = np.searchsorted(g_of.ravel()[order], np.arange(len(g_rows) + 1)).astype(np.int64)

    def factor(self, ab: np.ndarray, fallback: np.ndarray | None = None) -> None:
        """Factor H (lower band ``ab``) and, in the exact mode (or when there is no S yet),
        build S = A H^-1 A^T.  ``fallback``: a band H is taken from on the strands (blocks; the
        whole band on the LAPACK path) where ``ab`` is not positive definite."""
        self.stats["factors"] += 1
        self.fresh = False
        self._L_il = None
        self._LT = None
        self._solves = 0          # solves on this factor
        if self.kernels is not None:
            # the factor strand-interleaved, bandchol's layout (``LT``) made only when asked for; a
            # band not positive definite on some strand: the per-block factor with its fallback or shift
            if not self._factor_interleaved(ab):
                self._LT = self.kernels.factor(ab, fallback)
        else:
            for band in (ab,) if fallback is None else (ab, fallback):
                try:
                    self._cb = scipy.linalg.cholesky_banded(band, lower=True, check_finite=False)
                    break
                except np.linalg.LinAlgError:
                    continue
            else:   # round-off made the last band indefinite: a small diagonal shift
                band = band.copy()
                band[0] += 1e-8 * np.abs(band[0]).max()
                self._cb = scipy.linalg.cholesky_banded(band, lower=True, check_finite=False)
        if self.mode == "exact" or self.Smat is None:
            self.build_schur()

    def _factor_interleaved(self, ab: np.ndarray) -> bool:
        """The factor of ``ab`` strand-interleaved (``interleave_band``, ``factor_interleaved``),
        straight into the buffers the Krylov products read; False (nothing kept) when a strand's
        band is not positive definite: ``kernels.factor`` then takes its fallback band or shift."""
        buf = self._il_buffers(ab.shape[0])
        AT = ab.T if ab.T.flags.c_contiguous else np.ascontiguousarray(ab.T)
        par = self._threaded()
        (interleave_band_parallel if par else interleave_band)(AT, self._dof_off, self._blk_end, self.nmax, buf[0])
        (factor_interleaved_parallel if par else factor_interleaved)(buf[0], buf[1], self._ok_il)
        if not self._ok_il.all():
            return False
        self._L_il, self._inv_il = buf
        return True

    def _threaded(self) -> bool:
        """Whether the interleaved kernels run their chunks on the objective kernels' threads
        (``StrandKernels.threads``, ``solver.threads``: 2 where the machine has a core free), which
        it then sets; the results are the same either way (``IL_CHUNKS``)."""
        k = self.kernels
        if k is None or not k.parallel or self.S < bandchol.PARALLEL_MIN_BLOCKS:
            return False
        bandchol.set_threads(k.threads)
        return True

    def _il_buffers(self, bw1: int) -> tuple:
        """(L, inv): the interleaved factor's buffers, (nmax, bw1, S) and (nmax, S), kept from factor to
        factor (at 10,000 strands 49 MB, above malloc's mmap threshold: fresh zeroed pages every time
        otherwise)."""
        buf = self._il_buf
        if buf is None or buf[0].shape != (self.nmax, bw1, self.S):
            buf = self._il_buf = (np.empty((self.nmax, bw1, self.S)), np.empty((self.nmax, self.S)))
        return buf

    @property
    def LT(self) -> np.ndarray:
        """The current factor in bandchol's layout (N, bw + 1) (the compiled path)."""
        if self._LT is None:
            self._LT = np.zeros((self.N, self._L_il.shape[1]))
            deinterleave_factor(self._L_il, self._dof_off, self._LT)
        return self._LT

    @property
    def cb(self) -> np.ndarray:
        """The current factor in ``scipy.linalg.cholesky_banded(lower=True)``'s layout."""
        return self.LT.T if self.kernels is not None else self._cb

    def build_schur(self) -> None:
        """S = A H^-1 A^T for the current factor."""
        self.stats["builds"] += 1
        if self.kernels is not None:
            self._schur_kernels()
        else:
            self._schur_torch()
        self.fresh = True

    def _schur_torch(self) -> None:
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

    def _schur_kernels(self) -> None:
        k = self.kernels
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

    def _hinv_il(self, r_il: np.ndarray) -> np.ndarray:
        """H^-1 r for r strand-interleaved ((nmax S,), see ``__init__``), with the factor
        interleaved once per factorisation; without numba, through ``hinv``."""
        if not HAVE_NUMBA:
            r = np.zeros(self.N)
            r[:] = r_il[self._il_of_dof]
            out = np.zeros_like(r_il)
            out[self._il_of_dof] = self.hinv(r)
            return out
        self._interleave()
        x = np.array(r_il, dtype=np.float64).reshape(self.nmax, self.S)
        (solve_interleaved_parallel if self._threaded() else solve_interleaved)(self._L_il, self._inv_il, x)
        return x.reshape(-1)

    def _interleave(self) -> None:
        """The current factor strand-interleaved (``interleave_factor``), once per factorisation."""
        if self._L_il is None:
            LT = self.LT if self.kernels is not None else np.ascontiguousarray(self.cb.T)
            bw1 = LT.shape[1]
            # one strand-by-strand pass (``interleave_factor``) for equal and unequal strands alike: a plain
            # transpose reads each strand's rows with a stride of nmax (bw + 1) doubles, one TLB miss an
            # element from about 2,000 strands (10,000 strands: 38 ms a factor, 5 times the per-strand cost
            # at 1,000; the strand-by-strand pass 12 ms, 2026-12-06), into buffers kept between factors
            self._L_il, self._inv_il = self._il_buffers(bw1)
            if HAVE_NUMBA:
                interleave_factor(LT, self._dof_off, self.nmax, self._L_il, self._inv_il)
            elif self._uniform and bw1 == self._il_cut.shape[1]:    # every strand nmax DOFs: a transpose, and the band cut at each strand's end
                self._L_il[...] = LT.reshape(self.S, self.nmax, bw1).transpose(1, 2, 0)
                self._L_il[self._il_cut] = 0.0
                self._inv_il[...] = 1.0 / self._L_il[:, 0, :]
            else:
                interleave_factor(LT, self._dof_off, self.nmax, self._L_il, self._inv_il)

    def hinv(self, r: np.ndarray) -> np.ndarray:
        if self.kernels is not None:
            return self.kernels.cho_solve(self.LT, r)
        return scipy.linalg.cho_solve_banded((self.cb, True), r, check_finite=False)

    def solve(self, r_x: np.ndarray, C: np.ndarray, Bmat: np.ndarray | None = None, D: np.ndarray | None = None,
              r_t: np.ndarray | None = None, reg: np.ndarray | None = None):
        """(dx, dt or None, lam) for the system above; C: (3K,), Bmat: (3K, K) or None (static);
        ``reg`` (3K,): -diag(reg) in the (lam, lam) block (the SQP's elastic rows, reg = 1/rho).

        With S exact for the current factor (``fresh``: the exact mode, or S just built) the
        reduced system is solved directly.  Otherwise (the krylov mode) by GMRES on the reduced
        system, right-preconditioned by its exact solve with the last S built (``_krylov``); a
        product with S costs one solve with H (A is constant).  If it does not reach the relative
        residual ``krylov_tol`` in ``krylov_max`` iterations, S is built for this factor and the
        system solved directly: the result is always that of the direct solve to ``krylov_tol``.
        A second solve on the same factor (the Woodbury columns of the variance penalty) builds S:
        one build then serves every further solve directly."""
        m = 3 * self.K
        self._solves += 1
        if not self.fresh and self._solves > 1:
            # several solves on one factor (the SQP's Woodbury update of the variance penalty):
            # S built once serves them all directly, where each Krylov solve costs several solves with H
            self.build_schur()
        if not self.fresh:
            r_il = np.zeros(self._A_il.shape[1])
            r_il[self._il_of_dof] = r_x
            u_il = self._hinv_il(r_il)
            rhs_l = C - self._A_il @ u_il
            b = rhs_l if Bmat is None else np.concatenate([rhs_l, -r_t])
            got = self._krylov(b, m, Bmat, D, reg)
            if got is not None:
                sol, W, y = got
                lam = sol[:m]
                dt = None if Bmat is None else sol[m:]
                dx = -(u_il + y @ W)[self._il_of_dof]   # H^-1 (r_x + A^T lam), from the products' solves
                return dx, dt, lam
            self.stats["krylov_fallbacks"] += 1
            self.build_schur()
        u = self.hinv(r_x)
        rhs_l = C - self.A @ u
        b = rhs_l if Bmat is None else np.concatenate([rhs_l, -r_t])
        self.stats["direct_solves"] += 1
        sol = np.linalg.solve(self._reduced(self.Smat, Bmat, D, reg), b)
        lam = sol[:m]
        dt = None if Bmat is None else sol[m:]
        dx = -self.hinv(r_x + self.AT_sparse @ lam)
        return dx, dt, lam

    @staticmethod
    def _reduced(Smat, Bmat, D, reg):
        """[[S + diag(reg), -B], [B^T, diag(D)]] (static: S + diag(reg))."""
        M = Smat if reg is None else Smat + np.diag(reg)
        if Bmat is None:
            return M
        return np.block([[M, -Bmat], [Bmat.T, np.diag(D)]])

    def _small(self, P, r, z, tol, scales) -> bool:
        """The error estimate P^-1 r of z = (lam, dt) (r = b - M z, P the preconditioner's LU)
        within tol (|lam| + scale) and tol (|dt| + scale), block by block: their units differ, and
        lam (no constraint force) or dt (t at rest) may be 0.  ``scales``: |b| / max|S| and
        |b| / max|B|, the sizes the right-hand side gives each block."""
        e = scipy.linalg.lu_solve(P, r, check_finite=False)
        m = 3 * self.K
        return all(float(np.linalg.norm(e[sl])) <= tol * (float(np.linalg.norm(z[sl])) + sc)
                   for sl, sc in zip((slice(0, m), slice(m, None)), scales) if z[sl].size)

    def _krylov(self, b, m, Bmat, D, reg):
        """GMRES (right-preconditioned, no restart) on the reduced system M z = b, whose product
        is M z = reduced(0) z + [A H^-1 A^T z_lam; 0] (one solve with H), preconditioned by the
        LU of the reduced matrix with the last S built.  Returns (z, W, y) with z = Z y and
        W^T y = H^-1 A^T z_lam (strand-interleaved), or None when it does not reach |b - M z| <=
        krylov_tol |b| and |P^-1 (b - M z)| <= krylov_tol |z| (the error, estimated with the
        preconditioner P) in ``krylov_max`` iterations (given up early when the residual's rate so
        far would not)."""
        self.stats["krylov_solves"] += 1
        self.history = []         # the relative residual after each iteration
        P = scipy.linalg.lu_factor(self._reduced(self.Smat, Bmat, D, reg), check_finite=False)
        M0 = self._reduced(np.zeros((m, m)), Bmat, D, reg)   # the part without S
        bnorm = float(np.linalg.norm(b))
        n, kmax, tol = b.size, self.krylov_max, self.krylov_tol
        if bnorm == 0.0:
            return np.zeros(n), np.zeros((1, self._A_il.shape[1])), np.zeros(1)
        scales = (bnorm / max(float(np.abs(self.Smat).max()), 1e-300),
                  0.0 if Bmat is None else bnorm / max(float(np.abs(Bmat).max()), 1e-300))
        V = np.empty((kmax + 1, n))       # rows: the orthonormal basis
        Z = np.empty((kmax, n))           # rows: the preconditioned basis
        # rows: H^-1 A^T Z[j, :m], strand-interleaved; kept between solves (at 10,000 strands 92 MB: above
        # malloc's mmap threshold, a fresh allocation page-faults every row it writes)
        if self._W_buf is None or self._W_buf.shape != (kmax, self._A_il.shape[1]):
            self._W_buf = np.empty((kmax, self._A_il.shape[1]))
        W = self._W_buf
        Hh = np.zeros((kmax + 1, kmax))   # the Arnoldi relation M Z = V Hh
        R = np.zeros((kmax + 1, kmax))    # Hh rotated to upper triangular (Givens)
        g = np.zeros(kmax + 1)            # Q^T |b| e1
        g[0] = bnorm
        V[0] = b / bnorm
        cs, sn = np.zeros(kmax), np.zeros(kmax)   # the Givens rotations
        hist = np.zeros(kmax)
        if HAVE_NUMBA:    # the whole Arnoldi loop compiled (``gmres_arnoldi``): at Celia's size its Python
            self._interleave()   # form spent about 1.4 ms a solve outside the products
            M0c = np.ascontiguousarray(M0)
        j0 = 0
        while True:   # Arnoldi iterations up to one whose residual estimate reaches tol, then the checks
            if HAVE_NUMBA:
                arnoldi = gmres_arnoldi_threaded if self._threaded() else gmres_arnoldi
                done, code = arnoldi(P[0], P[1], M0c, b, bnorm, tol, kmax, m, *self._lists, *self._scatter, self._L_il,
                                     self._inv_il, j0, V, Z, W, Hh, R, g, cs, sn, hist)
            else:
                done, code = self._arnoldi_python(P, M0, b, bnorm, tol, kmax, m, j0, V, Z, W, Hh, R, g, cs, sn, hist)
            self.stats["krylov_iterations"] += int(done) - j0
            self.history = hist[:done].tolist()
            if code != ARNOLDI_CANDIDATE:
                return None
            j = int(done) - 1
            hn = Hh[j + 1, j]
            y = scipy.linalg.solve_triangular(R[:j + 1, :j + 1], g[:j + 1], check_finite=False)
            zz = y @ Z[:j + 1]
            # and the error: its estimate P^-1 (b - M z) (with a small residual alone, lam's
            # relative error may be cond(S) x tol)
            r = -(Hh[:j + 2, :j + 1] @ y) @ V[:j + 2]
            r += b
            if self._small(P, r, zz, tol, scales) or hn <= 1e-300 * bnorm:
                # the true residual, without a further solve with H: S z = A W^T y
                r = b - M0 @ zz
                r[:m] -= self._A_il @ (y @ W[:j + 1])
                # (its error estimate is bounded below by the products' round-off, cond(M) eps |z|,
                # about what the direct solve's error is: a factor 100 of slack for it)
                if float(np.linalg.norm(r)) <= tol * bnorm and self._small(P, r, zz, 100.0 * tol, scales):
                    return zz, W[:j + 1], y
                return None
            if done >= kmax:   # the error estimate not yet small: iterate on, while there are iterations left
                return None
            j0 = int(done)

    def _arnoldi_python(self, P, M0, b, bnorm, tol, kmax, m, j0, V, Z, W, Hh, R, g, cs, sn, hist):
        """``gmres_arnoldi`` without numba (the products through ``_hinv_il``), from iteration j0."""
        for j in range(j0, kmax):
            z = scipy.linalg.lu_solve(P, V[j], check_finite=False)
            Z[j] = z
            w = M0 @ z
            W[j] = self._hinv_il(self._AT_il @ z[:m])
            w[:m] += self._A_il @ W[j]
            for _ in range(2):     # Gram-Schmidt, twice: the basis stays orthogonal to round-off
                h = V[:j + 1] @ w
                Hh[:j + 1, j] += h
                w -= h @ V[:j + 1]
            hn = float(np.linalg.norm(w))
            if not np.isfinite(hn):      # a non-finite system (a diverging iterate): the direct solve says so
                return j, ARNOLDI_GAVE_UP
            Hh[j + 1, j] = hn
            V[j + 1] = w / hn if hn > 1e-300 * bnorm else 0.0
            col = Hh[:j + 2, j].copy()
            for i in range(j):
                col[i], col[i + 1] = cs[i] * col[i] + sn[i] * col[i + 1], -sn[i] * col[i] + cs[i] * col[i + 1]
            rr = float(np.hypot(col[j], col[j + 1]))
            cs[j], sn[j] = (col[j] / rr, col[j + 1] / rr) if rr > 0 else (1.0, 0.0)
            col[j], col[j + 1] = rr, 0.0
            R[:j + 2, j] = col
            g[j], g[j + 1] = cs[j] * g[j], -sn[j] * g[j]
            rel = abs(float(g[j + 1])) / bnorm
            hist[j] = rel
            out = arnoldi_outcome(rel, hn, bnorm, tol, j, kmax)
            if out >= 0:
                return j + 1, out
        return kmax, ARNOLDI_GAVE_UP


#: ``gmres_arnoldi``'s outcomes: the residual estimate reached the tolerance (or the basis broke
#: down: the solution is in it), or the iteration gave up (its rate, kmax or a non-finite value)
ARNOLDI_CANDIDATE, ARNOLDI_GAVE_UP = 0, 1


@njit(cache=True, error_model="numpy")
def arnoldi_outcome(rel, hn, bnorm, tol, j, kmax):
    """After Arnoldi iteration j with relative residual estimate ``rel`` and new basis norm
    ``hn``: ARNOLDI_CANDIDATE (the estimate reached tol, or the basis broke down), ARNOLDI_GAVE_UP
    (at this rate kmax iterations would not do), or -1 (iterate on)."""
    if rel <= tol or hn <= 1e-300 * bnorm:
        return ARNOLDI_CANDIDATE
    if j >= 2 and rel ** (kmax / (j + 1)) > tol:
        return ARNOLDI_GAVE_UP
    return -1


@njit(cache=True, error_model="numpy")
def lu_apply(lu, piv, b, out):
    """out = M^-1 b from ``scipy.linalg.lu_factor``'s (lu, piv) of M (LAPACK getrs: the row
    interchanges in order, then the unit lower and the upper triangle)."""
    n = b.shape[0]
    for i in range(n):
        out[i] = b[i]
    for i in range(n):
        p = piv[i]
        if p != i:
            t = out[i]
            out[i] = out[p]
            out[p] = t
    for i in range(n):
        s = out[i]
        for k in range(i):
            s -= lu[i, k] * out[k]
        out[i] = s
    for i in range(n - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, n):
            s -= lu[i, k] * out[k]
        out[i] = s / lu[i, i]


@njit(cache=True, error_model="numpy")
def _arnoldi_extend(j, w, Av, m, V, Hh, R, g, cs, sn, hist, h, col, bnorm, tol, kmax):
    """Arnoldi iteration j of ``gmres_arnoldi`` after its product: w += [A x; 0], then
    Gram-Schmidt, the Givens rotations and the residual estimate.  Returns (iterations done,
    outcome), or (-1, -1) to iterate on."""
    n = w.shape[0]
    for i in range(m):
        w[i] += Av[i]
    for _ in range(2):     # classical Gram-Schmidt, twice
        for i in range(j + 1):
            s = 0.0
            for k in range(n):
                s += V[i, k] * w[k]
            h[i] = s
        for i in range(j + 1):
            Hh[i, j] += h[i]
            for k in range(n):
                w[k] -= h[i] * V[i, k]
    s = 0.0
    for k in range(n):
        s += w[k] * w[k]
    hn = math.sqrt(s)
    if not np.isfinite(hn):
        return j, ARNOLDI_GAVE_UP
    Hh[j + 1, j] = hn
    for k in range(n):
        V[j + 1, k] = w[k] / hn if hn > 1e-300 * bnorm else 0.0
    for i in range(j + 2):
        col[i] = Hh[i, j]
    for i in range(j):
        a = cs[i] * col[i] + sn[i] * col[i + 1]
        col[i + 1] = -sn[i] * col[i] + cs[i] * col[i + 1]
        col[i] = a
    rr = math.hypot(col[j], col[j + 1])
    if rr > 0:
        cs[j] = col[j] / rr
        sn[j] = col[j + 1] / rr
    else:
        cs[j] = 1.0
        sn[j] = 0.0
    col[j] = rr
    col[j + 1] = 0.0
    for i in range(j + 2):
        R[i, j] = col[i]
    gj = g[j]
    g[j] = cs[j] * gj
    g[j + 1] = -sn[j] * gj
    rel = abs(g[j + 1]) / bnorm
    hist[j] = rel
    out = arnoldi_outcome(rel, hn, bnorm, tol, j, kmax)
    if out >= 0:
        return j + 1, out
    return -1, -1


@njit(cache=True, error_model="numpy")
def _arnoldi_start(j, lu, piv, M0, V, Z, w, zl, m):
    """Arnoldi iteration j of ``gmres_arnoldi`` before its product: Z[j] = P^-1 V[j], w = M0 Z[j],
    zl = its multiplier part."""
    n = w.shape[0]
    z = Z[j]
    lu_apply(lu, piv, V[j], z)
    for i in range(n):
        s = 0.0
        for k in range(n):
            s += M0[i, k] * z[k]
        w[i] = s
    for i in range(m):
        zl[i] = z[i]


@njit(cache=True, error_model="numpy")
def gmres_arnoldi(lu, piv, M0, b, bnorm, tol, kmax, m, rows, wts, per_vertex, ptr, pos, wt, L, inv, j0, V, Z, W, Hh,
                  R, g, cs, sn, hist):
    """The Arnoldi loop of ``SchurKKT._krylov`` (GMRES, right-preconditioned, no restart, Givens
    rotations; Saad 2003, "Iterative methods for sparse linear systems", Alg. 9.5) on the reduced
    system M z = b, M z = M0 z + [A H^-1 A^T z[:m]; 0], preconditioner P = (lu, piv); A^T's rows
    (rows, wts): the per-vertex lists where ``per_vertex``, else the per-DOF ones (``_products``);
    A's rows (ptr, pos, wt): ``scatter_lists`` of them.  V[0] = b /
    bnorm and g[0] = bnorm on entry.  From iteration j0 (0, or the one after a candidate whose
    error estimate was not yet small: the earlier iterations' state in V, Z, W, Hh, R, g and the
    Givens rotations cs, sn) it fills V, Z, W (rows H^-1 A^T Z[j, :m], strand-interleaved), Hh, R,
    g, cs, sn and hist (the relative residual estimate after each iteration).  Returns (iterations done,
    ARNOLDI_CANDIDATE when the last one reached ``tol`` or broke down, else ARNOLDI_GAVE_UP: a
    non-finite value, ``kmax`` reached, or a rate at which kmax iterations would not do), the
    same decisions as ``SchurKKT._arnoldi_python``.  Its products on one thread
    (``gmres_arnoldi_threaded``: on the kernels' threads, the same numbers; a loop of its own, as
    no one-thread kernel may call a parallel one, ``_products_threaded``)."""
    nmax, S = inv.shape
    w, h, zl, Av, col = np.empty(b.shape[0]), np.empty(kmax + 1), np.empty(m), np.empty(m), np.empty(kmax + 1)
    Avc = np.empty((IL_CHUNKS, m))
    for j in range(j0, kmax):
        _arnoldi_start(j, lu, piv, M0, V, Z, w, zl, m)
        _products(rows, wts, ptr, pos, wt, zl, L, inv, W[j].reshape((nmax, S)), Av, Avc, per_vertex)
        done, out = _arnoldi_extend(j, w, Av, m, V, Hh, R, g, cs, sn, hist, h, col, bnorm, tol, kmax)
        if done >= 0:
            return done, out
    return kmax, ARNOLDI_GAVE_UP


@njit(cache=True, error_model="numpy")
def gmres_arnoldi_threaded(lu, piv, M0, b, bnorm, tol, kmax, m, rows, wts, per_vertex, ptr, pos, wt, L, inv, j0, V, Z,
                           W, Hh, R, g, cs, sn, hist):
    """``gmres_arnoldi`` with its products on the kernels' threads (``_products_threaded``)."""
    nmax, S = inv.shape
    w, h, zl, Av, col = np.empty(b.shape[0]), np.empty(kmax + 1), np.empty(m), np.empty(m), np.empty(kmax + 1)
    Avc = np.empty((IL_CHUNKS, m))
    for j in range(j0, kmax):
        _arnoldi_start(j, lu, piv, M0, V, Z, w, zl, m)
        _products_threaded(rows, wts, ptr, pos, wt, zl, L, inv, W[j].reshape((nmax, S)), Av, Avc, per_vertex)
        done, out = _arnoldi_extend(j, w, Av, m, V, Hh, R, g, cs, sn, hist, h, col, bnorm, tol, kmax)
        if done >= 0:
            return done, out
    return kmax, ARNOLDI_GAVE_UP


@njit(cache=True, error_model="numpy")
def _interleave_rows(AT, dof_off, blk_end, nmax, out, inv, factor, s0, s1):
    """Rows of the band storage ``AT`` (N, bw + 1) (bandchol's layout: AT[j, a] = A[j + a, j])
    strand-interleaved: out[j, a, s] = AT[dof_off[s] + j, a], a strand a column of a (nmax, S)
    array (``solve_interleaved``, ``factor_interleaved``).  ``factor``: AT is a factor
    (``interleave_factor``): entries past the strand's end are 0, inv[j, s] = 1 / L[j, j] (1 on the
    padding rows j >= the strand's DOFs), out[j, 0, s] = 0 (not read); else a band
    (``interleave_band``): entries past the end of DOF j's block (``blk_end``: (N,)) are 0 and the
    padding rows are the identity (pivot 1); ``inv`` is not touched.  Strand by strand: each
    strand's rows of AT are read once, contiguously, and its writes (a stride of S doubles) stay
    within the cache lines the neighbouring strands fill next (at Celia's size 0.22 ms against 0.39
    for a row-major pass over blocks of 64 strands, whose inner loop gathered AT with a stride of a
    strand, 2026-12-06); strands s0 to s1 (a chunk of ``IL_CHUNKS``, or all)."""
    bw1 = AT.shape[1]
    for s in range(s0, s1):
        d0 = dof_off[s]
        n = dof_off[s + 1] - d0
        for j in range(nmax):
            if j < n:
                if factor:
                    e = n
                    inv[j, s] = 1.0 / AT[d0 + j, 0]
                    out[j, 0, s] = 0.0
                else:
                    e = blk_end[d0 + j] - d0
                    out[j, 0, s] = AT[d0 + j, 0]
                for a in range(1, bw1):
                    out[j, a, s] = AT[d0 + j, a] if j + a < e else 0.0
            else:
                if factor:
                    inv[j, s] = 1.0
                out[j, 0, s] = 0.0 if factor else 1.0
                for a in range(1, bw1):
                    out[j, a, s] = 0.0


@njit(cache=True, error_model="numpy")
def interleave_factor(LT, dof_off, nmax, out, inv):
    """The factor ``LT`` (N, bw + 1) strand-interleaved (``_interleave_rows``): out[j, a, s] =
    LT[dof_off[s] + j, a] for the band inside strand s, 0 elsewhere, and inv[j, s] = 1 / L[j, j]
    (1 on the padding rows)."""
    _interleave_rows(LT, dof_off, dof_off, nmax, out, inv, np.bool_(True), np.int64(0), dof_off.shape[0] - 1)


@njit(cache=True, error_model="numpy")
def _interleave_band_chunk(AT, dof_off, blk_end, nmax, out, c):
    s0, s1 = il_chunk(dof_off.shape[0] - 1, c)
    _interleave_rows(AT, dof_off, blk_end, nmax, out, out[0], np.bool_(False), s0, s1)


@njit(cache=True, error_model="numpy")
def interleave_band(AT, dof_off, blk_end, nmax, out):
    """The band ``AT`` (N, bw + 1) strand-interleaved for ``factor_interleaved``
    (``_interleave_rows``): out[j, a, s] = AT[dof_off[s] + j, a] where DOF j + a lies in DOF j's
    block (``blk_end``: (N,) the end of each DOF's block, bandchol's blocks; the band's entries
    across a block's end are never written by the assembly), 0 elsewhere; the padding rows j >= the
    strand's DOFs are the identity (pivot 1)."""
    _interleave_rows(AT, dof_off, blk_end, nmax, out, out[0], np.bool_(False), np.int64(0), dof_off.shape[0] - 1)


@njit(cache=True, parallel=True, error_model="numpy")
def interleave_band_parallel(AT, dof_off, blk_end, nmax, out):
    """``interleave_band``, its chunks on the kernels' threads (the same values)."""
    for c in prange(IL_CHUNKS):
        _interleave_band_chunk(AT, dof_off, blk_end, nmax, out, np.int64(c))


@njit(cache=True, error_model="numpy")
def _factor_range(L, inv, ok, s0, s1):
    """``factor_interleaved`` on strands s0 to s1 (rows as slices, as in ``_solve_chunk``)."""
    n, bw1, S = L.shape
    w = s1 - s0
    okc = ok[s0:s1]
    for s in range(w):
        okc[s] = True
    for j in range(n):
        Lj0 = L[j, 0, s0:s1]
        ij = inv[j, s0:s1]
        for s in range(w):
            p = Lj0[s]
            if not p > 0.0:
                okc[s] = False
                p = 1.0
            r = math.sqrt(p)
            Lj0[s] = r
            ij[s] = 1.0 / r
        m = min(bw1 - 1, n - 1 - j)
        for a in range(1, m + 1):
            la = L[j, a, s0:s1]
            for s in range(w):
                la[s] *= ij[s]
        for a in range(1, m + 1):
            la = L[j, a, s0:s1]
            for b in range(a, m + 1):
                lb = L[j, b, s0:s1]
                t = L[j + a, b - a, s0:s1]
                for s in range(w):
                    t[s] -= lb[s] * la[s]


@njit(cache=True, error_model="numpy")
def factor_interleaved(L, inv, ok):
    """In place, the Cholesky factor of every strand's band at once (L from ``interleave_band``,
    (nmax, bw + 1, S)): bandchol.factor_block's right-looking elimination, the same operations on
    each entry in the same order (the factor is bit for bit bandchol's, interleaved as by
    ``interleave_factor``; here L[j, 0, s] keeps the pivot's root), with the strands as the
    innermost, vectorised loop: one strand's elimination is a chain of dependent square roots
    and divisions, 301 side by side overlap (at Celia's size, band and factor 0.47 ms against
    0.64 for bandchol.factor_serial and 0.21 for ``interleave_factor``, 2026-12-06).  ok[s]:
    strand s's pivots were all > 0 (a strand that fails goes on with pivot 1: its factor is
    not used)."""
    _factor_range(L, inv, ok, np.int64(0), L.shape[2])   # int64 0: one build with the chunks' bounds


@njit(cache=True, parallel=True, error_model="numpy")
def factor_interleaved_parallel(L, inv, ok):
    """``factor_interleaved``, its chunks on the kernels' threads (bit for bit the same factor)."""
    S = L.shape[2]
    for c in prange(IL_CHUNKS):
        s0, s1 = il_chunk(S, np.int64(c))
        _factor_range(L, inv, ok, s0, s1)


@njit(cache=True, error_model="numpy")
def deinterleave_factor(L, dof_off, LT):
    """bandchol's factor layout LT (N, bw + 1) from the interleaved factor of
    ``factor_interleaved`` (entries across a block's end: 0, never read)."""
    S = dof_off.shape[0] - 1
    bw1 = LT.shape[1]
    for s in range(S):
        d0 = dof_off[s]
        n = dof_off[s + 1] - d0
        for j in range(n):
            LT[d0 + j, 0] = L[j, 0, s]
            for a in range(1, bw1):
                LT[d0 + j, a] = L[j, a, s] if j + a < n else 0.0


@njit(cache=True, error_model="numpy", fastmath=True)
def _solve_chunk(L, inv, x, s0, s1):
    """x <- (L L^T)^-1 x on strands s0 to s1 (``solve_interleaved``).  The rows are taken as slices
    [s0, s1) (the loops then run from 0: with run-time bounds on the whole rows LLVM vectorised
    them about 3 times slower, 2026-12-08)."""
    n, bw1, S = L.shape
    m = s1 - s0
    for j in range(n):
        xj = x[j, s0:s1]
        ij = inv[j, s0:s1]
        for s in range(m):
            xj[s] *= ij[s]
        for a in range(1, min(bw1 - 1, n - 1 - j) + 1):
            xa = x[j + a, s0:s1]
            la = L[j, a, s0:s1]
            for s in range(m):
                xa[s] -= la[s] * xj[s]
    for j in range(n - 1, -1, -1):
        xj = x[j, s0:s1]
        for a in range(1, min(bw1 - 1, n - 1 - j) + 1):
            xa = x[j + a, s0:s1]
            la = L[j, a, s0:s1]
            for s in range(m):
                xj[s] -= la[s] * xa[s]
        ij = inv[j, s0:s1]
        for s in range(m):
            xj[s] *= ij[s]


@njit(cache=True, error_model="numpy", fastmath=True)
def solve_interleaved(L, inv, x):
    """x <- (L L^T)^-1 x for every strand at once; x (nmax, S) strand-interleaved, L and inv from
    ``interleave_factor``.  The strands' substitutions are independent: the innermost loop runs
    over strands (contiguous, vectorised), where one strand's substitution alone is a dependency
    chain (bandchol.solve_block: about 2.5 times slower at Celia's size)."""
    _solve_chunk(L, inv, x, np.int64(0), L.shape[2])


@njit(cache=True, parallel=True, error_model="numpy", fastmath=True)
def solve_interleaved_parallel(L, inv, x):
    """``solve_interleaved``, its chunks of strands (``IL_CHUNKS``) on the kernels' threads (the
    same numbers: each strand's substitution is the same)."""
    S = L.shape[2]
    for c in prange(IL_CHUNKS):
        s0, s1 = il_chunk(S, np.int64(c))
        _solve_chunk(L, inv, x, s0, s1)


@njit(cache=True, error_model="numpy", fastmath=True)
def _gather_chunk(rows, wts, v, x, s0, s1):
    """x[j, s] = (A^T v) at interleaved position (j, s) for the strands s0 to s1: A^T's row there
    is sum_q wts[j, s, q] e_{rows[j, s, q]} (padding: weight 0)."""
    n, S, q = rows.shape
    for j in range(n):
        for s in range(s0, s1):
            acc = 0.0
            for k in range(q):
                acc += wts[j, s, k] * v[rows[j, s, k]]
            x[j, s] = acc


@njit(cache=True, error_model="numpy", fastmath=True)
def _gather_vertex_chunk(rows, wts, v, x, s0, s1):
    """``_gather_chunk`` with A^T's rows per vertex (``_products``, ``per_vertex``)."""
    nv, S, q = rows.shape
    for i in range(nv):
        x0 = x[3 * i]
        x1 = x[3 * i + 1]
        x2 = x[3 * i + 2]
        for s in range(s0, s1):
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            for k in range(q):
                w = wts[i, s, k]
                r = 3 * rows[i, s, k]
                a0 += w * v[r]
                a1 += w * v[r + 1]
                a2 += w * v[r + 2]
            x0[s] = a0
            x1[s] = a1
            x2[s] = a2


@njit(cache=True, error_model="numpy", fastmath=True)
def _scatter_chunk(xf, S, ptr, pos, wt, out, c):
    """out = chunk c's part of A x (x flat, strand-interleaved), row by row from the chunk's lists
    (``scatter_lists``): each row's sum in a register (a scatter into out, entry by entry, waited
    on its own stores: at Celia's size it took three times the solve).  Rows per cluster (``ptr``
    (IL_CHUNKS, K + 1), ``pos`` the vertex's x position, its 3 DOFs S apart) when out has 3 K
    entries per list row, else per DOF."""
    nr = ptr.shape[1] - 1
    if out.shape[0] == 3 * nr:
        for r in range(nr):
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            for e in range(ptr[c, r], ptr[c, r + 1]):
                p = pos[e]
                w = wt[e]
                a0 += w * xf[p]
                a1 += w * xf[p + S]
                a2 += w * xf[p + 2 * S]
            out[3 * r] = a0
            out[3 * r + 1] = a1
            out[3 * r + 2] = a2
    else:
        for r in range(nr):
            a = 0.0
            for e in range(ptr[c, r], ptr[c, r + 1]):
                a += wt[e] * xf[pos[e]]
            out[r] = a


@njit(cache=True, error_model="numpy", fastmath=True)
def _gather_solve(rows, wts, v, L, inv, x, s0, s1, per_vertex):
    """x's columns s0 to s1: H^-1 A^T v on those strands."""
    if per_vertex:
        _gather_vertex_chunk(rows, wts, v, x, s0, s1)
    else:
        _gather_chunk(rows, wts, v, x, s0, s1)
    _solve_chunk(L, inv, x, s0, s1)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=True)
def _products_parallel(rows, wts, ptr, pos, wt, v, L, inv, x, Avc, per_vertex):
    S = L.shape[2]
    xf = x.reshape(-1)
    for c in prange(IL_CHUNKS):
        s0, s1 = il_chunk(S, np.int64(c))
        _gather_solve(rows, wts, v, L, inv, x, s0, s1, per_vertex)
        _scatter_chunk(xf, S, ptr, pos, wt, Avc[c], np.int64(c))


@njit(cache=True, error_model="numpy", fastmath=True)
def _sum_chunks(Avc, Av):
    """Av = the chunks' parts of A x summed in chunk order."""
    for i in range(Av.shape[0]):
        a = 0.0
        for c in range(IL_CHUNKS):
            a += Avc[c, i]
        Av[i] = a


@njit(cache=True, error_model="numpy", fastmath=True)
def _products(rows, wts, ptr, pos, wt, v, L, inv, x, Av, Avc, per_vertex):
    """x = H^-1 A^T v (strand-interleaved, (nmax, S)) and Av = A x: a product with the Schur
    complement, S v = A H^-1 A^T v, in one pass.  A^T's rows (rows, wts): per DOF, the row at
    interleaved position (j, s) is sum_q wts[j, s, q] e_{rows[j, s, q]}; ``per_vertex``: per vertex,
    DOF 3 i + c of every strand has the rows 3 rows[i, s, q] + c with weights wts[i, s, q] (A = W (x)
    I3; a sixth of the bytes: at 10,000 strands 9 MB instead of 33 MB streamed twice a product);
    padding: weight 0.  Both give every entry of x and Av the same operations in the same order.
    A's rows: the lists (ptr, pos, wt) of ``scatter_lists``.  On one thread, on all strands at once (each strand's solve is
    ``_products_threaded``'s); A x summed by the chunks as there (``_scatter_chunk``), the chunks'
    parts then in chunk order: the same sums on any thread count."""
    S = L.shape[2]
    _gather_solve(rows, wts, v, L, inv, x, np.int64(0), S, per_vertex)
    xf = x.reshape(-1)
    for c in range(IL_CHUNKS):
        _scatter_chunk(xf, S, ptr, pos, wt, Avc[c], c)
    _sum_chunks(Avc, Av)


@njit(cache=True, error_model="numpy", fastmath=True)
def _products_threaded(rows, wts, ptr, pos, wt, v, L, inv, x, Av, Avc, per_vertex):
    """``_products`` chunk by chunk (``IL_CHUNKS``) on the kernels' threads.  A kernel of its own,
    not a flag of ``_products``: a compiled function that calls a parallel one starts numba's
    OpenMP threads wherever it is loaded, and in a variant's forked process (one thread,
    hairexp/app/variant_processes.py) that set libgomp's thread count under torch, whose next
    parallel region then waited forever on the team the fork had left behind (Celia's variants
    side by side hung in the tracked variant's observation, 2026-12-08)."""
    _products_parallel(rows, wts, ptr, pos, wt, v, L, inv, x, Avc, per_vertex)
    _sum_chunks(Avc, Av)


def scatter_lists(rows: np.ndarray, wts: np.ndarray, n_rows: int, per_vertex: bool):
    """A's rows as lists for ``_scatter_chunk``, from A^T's interleaved lists (rows, wts) (n, S, q):
    (ptr (IL_CHUNKS, n_rows + 1), pos (E,), wt (E,)), chunk c's row r the entries
    ptr[c, r]:ptr[c, r + 1], each the x position pos (per vertex: of its first DOF, j = 3 i) and
    weight, in the order (vertex or DOF, strand); ``n_rows``: K clusters (per vertex) or 3 K."""
    n, S, q = rows.shape
    j, s, _ = np.nonzero(wts != 0.0)
    r = rows[wts != 0.0].astype(np.int64)
    w = wts[wts != 0.0]
    chunk = np.searchsorted(np.array([(S * (c + 1)) // IL_CHUNKS for c in range(IL_CHUNKS)]), s, side="right")
    order = np.lexsort((s, j, r, chunk))
    key = chunk[order] * n_rows + r[order]
    ptr = np.zeros(IL_CHUNKS * n_rows + 1, dtype=np.int64)
    np.add.at(ptr, key + 1, 1)
    ptr = np.cumsum(ptr)
    # chunk c's row r spans ptr[c n_rows + r] to ptr[c n_rows + r + 1]: as (IL_CHUNKS, n_rows + 1)
    ptr2 = np.empty((IL_CHUNKS, n_rows + 1), dtype=np.int64)
    for c in range(IL_CHUNKS):
        ptr2[c] = ptr[c * n_rows:(c + 1) * n_rows + 1]
    jj = 3 * j if per_vertex else j
    pos = (jj * S + s)[order]
    return ptr2, np.ascontiguousarray(pos, dtype=np.int64), np.ascontiguousarray(w[order])


def distinct_columns(AT: np.ndarray):
    """Each strand's columns of A^T (AT: (S, n, R)) up to scale: (Bt (S, Rb, n) the distinct
    columns sorted by first (S, Rb), their first non-zero row (-1: padding, last), base (S, R) and scale (S, R)
    with AT[s, :, r] = scale[s, r] Bt[s, base[s, r]] (base -1: an empty column).  Two columns are
    the same when they have the same non-zero pattern and their entries over their first non-zero
    one agree to 1e-13 (relative); each column is matched against the distinct ones found before it,
    in order (``_distinct_kernel``: compiled, 0.54 s of Celia's tracked run's set-up in its numpy
    form, whose loop over each strand's columns called numpy for every pair)."""
    AT = np.ascontiguousarray(AT, dtype=np.float64)
    S, n, R = AT.shape
    base = np.full((S, R), -1, dtype=np.int64)
    scale = np.zeros((S, R))
    rep = np.full((S, max(R, 1)), -1, dtype=np.int64)
    nrep = np.zeros(S, dtype=np.int64)
    _distinct_kernel(AT, base, scale, rep, nrep)
    Rb = max(1, int(nrep.max(initial=0)))
    rep = rep[:, :Rb]
    real = np.arange(Rb)[None, :] < nrep[:, None]                     # (S, Rb)
    cols = np.where(real, rep, 0)
    U = np.take_along_axis(AT, cols[:, None, :], axis=2).transpose(0, 2, 1)             # (S, Rb, n)
    lead = np.take_along_axis(scale, cols, axis=1)
    U = np.where(real[:, :, None], U / np.where(real, lead, 1.0)[:, :, None], 0.0)
    f = np.where(real, (U != 0).argmax(axis=2), n)                   # padding last
    order = np.argsort(f, axis=1, kind="stable")                      # by first non-zero row (bandchol.schur_block)
    Bt = np.ascontiguousarray(np.take_along_axis(U, order[:, :, None], axis=1))
    first = np.take_along_axis(f, order, axis=1)
    first = np.where(first == n, -1, first).astype(np.int64)
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(Rb), order.shape), axis=1)
    has = base >= 0
    base = np.where(has, np.take_along_axis(rank, np.where(has, base, 0), axis=1), -1).astype(np.int64)
    return Bt, first, base, scale


@njit(cache=True, error_model="numpy")
def _distinct_kernel(AT, base, scale, rep, nrep):
    """``distinct_columns``' matching: per strand s, each non-empty column r gets scale[s, r] (its
    first non-zero entry) and base[s, r], the index (in order of discovery) of the first distinct
    column before it with the same non-zero pattern and |u_r - u_q| <= 1e-13 |u_q| entrywise (u: a
    column over its first non-zero entry), or a new index; rep[s, :nrep[s]] are the distinct
    columns' indices r."""
    S, n, R = AT.shape
    for s in range(S):
        k = 0
        for r in range(R):
            lead = 0.0
            for i in range(n):
                if AT[s, i, r] != 0.0:
                    lead = AT[s, i, r]
                    break
            if lead == 0.0:
                continue
            hit = -1
            for b in range(k):
                q = rep[s, b]
                lq = scale[s, q]
                same = True
                for i in range(n):
                    a = AT[s, i, r]
                    c = AT[s, i, q]
                    if (a != 0.0) != (c != 0.0):
                        same = False
                        break
                    uq = c / lq
                    if abs(a / lead - uq) > 1e-13 * abs(uq):
                        same = False
                        break
                if same:
                    hit = b
                    break
            scale[s, r] = lead
            if hit < 0:
                rep[s, k] = r
                hit = k
                k += 1
            base[s, r] = hit
        nrep[s] = k


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
