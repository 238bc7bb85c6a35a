"""Sparse assembly straight into LAPACK lower banded storage, pattern computed once.

DOFs are the free vertices, ordered strand by strand (3 per vertex), so a stencil of
consecutive vertices couples DOFs at most ``3 * (k - 1) + 2`` apart: half-bandwidth 8 for
bending triples.  ``ab[i - j, j] = A[i, j]`` for ``i >= j`` (``scipy.linalg.solveh_banded``
with ``lower=True``).  Each term's element entries are scattered with one ``np.bincount``
over precomputed flat destinations; entries touching kinematic vertices are dropped (their
positions are prescribed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from hairexp.physics import bandchol
from hairexp.physics.kernels import HAVE_NUMBA


def add_pair_blocks(grad: np.ndarray, ab: np.ndarray | None, slot: np.ndarray, g: np.ndarray,
                    H: np.ndarray | None = None) -> np.ndarray:
    """Add two-vertex elements' gradients g (n, 6) and Hessians H (n, 6, 6) to the free DOFs'
    gradient ``grad`` (N,) and lower band ``ab`` (bw + 1, N) (None: the gradient only), in place;
    ``slot`` (n, 2): the elements' vertices' free slots, -1 for a kinematic one (nothing added for
    it).  The two vertices may be one (an element (v, v) whose second half is zero).  Returns the
    gradient's contribution (N,).  The contact terms' assembly (hairexp/physics/barrier.py,
    contact_planes.py): their elements change every evaluation, so no precomputed pattern."""
    dof = (3 * slot[:, :, None] + np.arange(3)).reshape(-1, 6)          # negative for kinematic vertices
    ok = np.repeat(slot >= 0, 3, axis=1)
    contrib = np.bincount(np.where(ok, dof, 0)[ok], weights=g[ok], minlength=len(grad))
    grad += contrib
    if ab is not None:
        N = ab.shape[1]
        ii = np.broadcast_to(dof[:, :, None], H.shape)
        jj = np.broadcast_to(dof[:, None, :], H.shape)
        m = np.broadcast_to(ok[:, :, None] & ok[:, None, :], H.shape) & (ii >= jj)
        flat = (ii[m] - jj[m]) * N + jj[m]
        ab += np.bincount(flat, weights=H[m], minlength=ab.size).reshape(ab.shape)
    return contrib


@dataclass
class _Scatter:
    hess_src: np.ndarray   # (n_sel,) flat index into the (n, 3k * 3k) element Hessians
    hess_dst: np.ndarray   # (n_sel,) flat index into ab (bw + 1, N)
    grad_src: np.ndarray   # flat index into (n, 3k) element gradients
    grad_dst: np.ndarray   # DOF index


class BandedAssembler:
    def __init__(self, free_slot: np.ndarray, stencils: list[np.ndarray]):
        self.free_slot = np.asarray(free_slot)
        self.n_dofs = 3 * int((self.free_slot >= 0).sum())
        bw = 0
        for st in stencils:
            f = self.free_slot[st]
            big = np.iinfo(np.int64).max
            hi = np.where(f >= 0, f, -1).max(axis=1)
            lo = np.where(f >= 0, f, big).min(axis=1)
            has = hi >= 0
            if has.any():
                bw = max(bw, int(3 * (hi[has] - lo[has]).max() + 2))
        self.bandwidth = max(bw, 2)  # a vertex's own 3x3 block needs 2
        self.scatters = [self._pattern(st) for st in stencils]
        self._grad_dst = np.concatenate([s.grad_dst for s in self.scatters])
        self._hess_dst = np.concatenate([s.hess_dst for s in self.scatters])

    def _pattern(self, stencil: np.ndarray) -> _Scatter:
        n, k = stencil.shape
        m = 3 * k
        dof = (3 * self.free_slot[stencil][:, :, None] + np.arange(3)).reshape(n, m)  # (n, 3k), negative if kinematic
        free = (self.free_slot[stencil] >= 0).repeat(3, axis=1)
        # Hessian: lower triangle of the global matrix
        a, b = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")  # local row a, column b
        gi, gj = dof[:, a.ravel()], dof[:, b.ravel()]
        ok = free[:, a.ravel()] & free[:, b.ravel()] & (gi >= gj)
        e_idx, loc = np.nonzero(ok)
        hess_src = e_idx * (m * m) + loc
        N = self.n_dofs
        hess_dst = (gi[e_idx, loc] - gj[e_idx, loc]) * N + gj[e_idx, loc]
        if np.any(gi[e_idx, loc] - gj[e_idx, loc] > self.bandwidth):
            raise AssertionError("stencil exceeds the band; DOFs are not ordered strand by strand")
        ge, gl = np.nonzero(free)
        return _Scatter(hess_src, hess_dst, ge * m + gl, dof[ge, gl])

    def gradient(self, grads: list[np.ndarray]) -> np.ndarray:
        """Sum element gradients (one (n, 3k) array per stencil) into a DOF vector (N,)."""
        val = np.concatenate([g.reshape(-1)[s.grad_src] for s, g in zip(self.scatters, grads)])
        return np.bincount(self._grad_dst, weights=val, minlength=self.n_dofs)

    def banded(self, hessians: list[np.ndarray], diagonal: np.ndarray | None = None) -> np.ndarray:
        """Lower banded storage (bw + 1, N) of the summed element Hessians (one (n, 3k, 3k)
        array per stencil) plus ``diagonal``."""
        val = np.concatenate([H.reshape(-1)[s.hess_src] for s, H in zip(self.scatters, hessians)])
        N = self.n_dofs
        ab = np.bincount(self._hess_dst, weights=val, minlength=(self.bandwidth + 1) * N)
        ab = ab.reshape(self.bandwidth + 1, N)
        if diagonal is not None:
            ab[0] += diagonal
        return ab

    @staticmethod
    def to_sparse(ab: np.ndarray) -> sp.csc_matrix:
        """Full symmetric CSC matrix from lower banded storage (for reference solves and tests)."""
        bw1, N = ab.shape
        diags = [ab[d, : N - d] for d in range(bw1)]
        L = sp.diags(diags, offsets=[-d for d in range(bw1)], shape=(N, N), format="csc")
        return (L + sp.triu(L.T, k=1)).tocsc()


def band_product(ab: np.ndarray, v: np.ndarray, kernels=None) -> np.ndarray:
    """B v for the symmetric band B in LAPACK's lower storage (ab[d, j] = B[j + d, j]).  When
    ``ab`` is the transposed view of a C-order (N, bw + 1) array (the compiled kernels' band,
    ``bandchol``'s layout) the product is compiled (``bandchol.band_product_lt``); with the objective's
    ``kernels`` (hairexp/physics/strand_kernels.py) on 2 threads and at least
    ``bandchol.PARALLEL_MIN_BLOCKS`` strands, by runs of strands on both (the same sums)."""
    if HAVE_NUMBA and ab.T.flags.c_contiguous and ab.dtype == np.float64 and v.ndim == 1:
        out = np.empty(ab.shape[1])
        vv = np.ascontiguousarray(v, dtype=np.float64)
        if (kernels is not None and kernels.parallel and len(kernels.blk_dof) - 1 >= bandchol.PARALLEL_MIN_BLOCKS
                and kernels.blk_dof[-1] == ab.shape[1]):
            bandchol.set_threads(kernels.threads)
            bandchol.band_product_parallel(ab.T, vv, out, kernels.blk_dof)
        else:
            bandchol.band_product_lt(ab.T, vv, out)
        return out
    out = ab[0] * v
    for d in range(1, ab.shape[0]):
        n = v.size - d
        out[d:] += ab[d, :n] * v[:n]
        out[:-d] += ab[d, :n] * v[d:]
    return out


def banded_solve(ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve with the lower banded SPD matrix ``ab``; if Cholesky fails (round-off made the
    matrix indefinite), retry with a small diagonal shift."""
    try:
        return scipy.linalg.solveh_banded(ab.copy(), rhs, lower=True, check_finite=False, overwrite_ab=True)
    except np.linalg.LinAlgError:
        ab = ab.copy()
        ab[0] += 1e-8 * np.abs(ab[0]).max()
        return scipy.linalg.solveh_banded(ab, rhs, lower=True, check_finite=False, overwrite_ab=True)
