"""Compiled (numba) banded Cholesky of the strand-block-diagonal Hessian, block by block.

The Hessian of eq. (5) over DOFs ordered strand by strand is block diagonal (one block per
strand's free vertices) and banded within a block (half-bandwidth bw = 8 for bending triples).
LAPACK's banded routines are bound by call overhead at bw = 8 (hairexp FACTS: numba assembly +
``dpbsv`` 1.9 ms vs 0.43 ms for a per-strand factorisation), so each block is factored here by a
left-looking band Cholesky A = L L^T, in parallel over blocks.

Storage: ``abT[j, d] = A[j + d, j]`` (C order, a column's entries contiguous); ``abT.T`` is
LAPACK's lower band, so a factor ``LT`` gives ``LT.T`` in the layout of
``scipy.linalg.cholesky_banded(lower=True)`` (used by ``cho_solve_banded`` and the SQP's Schur
complement).  ``blk_dof`` (B + 1,) are the blocks' DOF offsets.

Threads (``solver.threads``): numba runs the ``prange`` loops on its thread pool; ``pick_threads``
chooses 1 or 2 from what the machine has free (with both cores busy, 2-thread kernels were slower
than 1 thread: FACTS, "What a Newton step can cost").
"""

from __future__ import annotations

import math
import os

import numpy as np

from hairexp.errors import choice_name
from hairexp.physics.kernels import HAVE_NUMBA, njit, prange

#: ``solver.threads=auto`` starts 2 threads only while the 1-minute load average leaves about a core
#: idle besides this process (load <= cores - AUTO_IDLE_CORES), and goes back to 1 once the load
#: says another process is busy besides this one's 2 threads (load > cores + AUTO_IDLE_CORES).
AUTO_IDLE_CORES = 0.75
#: s between two re-decisions of ``auto`` (the load average itself moves over a minute).
AUTO_RECHECK_S = 2.0
THREAD_CHOICES = ("auto", "1", "2")
#: ``solver.threads=auto`` keeps 1 thread below this many free vertices: a parallel region's start
#: costs more than half a small scene's kernel.  Measured 2026-12-06, whole free steps, 2 threads over
#: 1 (interleaved in one process, idle machine): 800 vertices (goaling, spreading) 1.54 and 1.52 x the
#: time (tracked 1.09 and 1.12), 1,300: 1.07, 2,600: 0.95, 5,200: 0.82, 7,826 (Celia): 0.79.
AUTO_MIN_VERTICES = 2000


#: The tracked step's memory-bound kernels (the strand-interleaved band, factor, Krylov products and
#: solve, hairexp/control/tracking/kkt.py; the band product ``band_product_parallel``) run on 2 threads
#: from this many strands (blocks) on, where ``pick_threads`` gives 2.  Measured 2026-12-08, one
#: thread / two (idle machine; a parallel region's start costs about 0.1 ms): 301 strands, a Krylov
#: product 156 / 197 us, band + factor 406 / 520 us; 1,000: 510 / 385 and 1,237 / 1,034; 3,000:
#: 1,806 / 1,485 and 5,460 / 3,172 (the whole tracked step at 3,000 strands 0.42-0.44 s -> 0.32-0.33).
PARALLEL_MIN_BLOCKS = 1000


#: at most this many kernel threads in this process (``cap_threads``): an experiment's variant run
#: beside another in its own process takes one core (hairexp/app/variant_processes.py)
_CAP = 2


def cap_threads(n: int) -> None:
    """Every later ``pick_threads`` of this process gives at most ``n`` (>= 1) threads."""
    global _CAP
    _CAP = max(1, int(n))


def pick_threads(setting="auto", current: int | None = None, vertices: int | None = None) -> int:
    """Threads for the kernels: ``1`` or ``2`` as asked (at most the usable cores), ``auto``: 2
    when the process may use >= 2 cores, the load average says one is idle and the scene has at
    least ``AUTO_MIN_VERTICES`` free ``vertices`` (None: not known), else 1; ``current``: the
    threads ``auto`` runs with now (their own load is allowed for)."""
    setting = choice_name(setting)
    if setting == "auto" and vertices is not None and vertices < AUTO_MIN_VERTICES:
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    if setting == "auto":
        try:
            load = os.getloadavg()[0]
        except OSError:  # pragma: no cover
            load = float(cores)
        limit = cores + AUTO_IDLE_CORES if current == 2 else cores - AUTO_IDLE_CORES
        want = 2 if load <= limit else 1
    else:
        want = int(setting)
    return max(1, min(want, cores, 2, _CAP))


def set_threads(n: int) -> None:
    """numba's thread count for the calling thread's kernels."""
    if HAVE_NUMBA:
        import numba

        numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


#: The half-bandwidth the compiled factorisation is specialised for (bending triples: 3 * 2 + 2);
#: a compile-time constant so that the inner loops unroll.
BW = 8


@njit(cache=True, error_model="numpy")
def _eliminate(L, j, m):
    """Right-looking step at column j: scale it, subtract its outer product from the next m columns."""
    piv = L[j, 0]
    if not piv > 0.0:
        return False
    r = math.sqrt(piv)
    L[j, 0] = r
    inv = 1.0 / r
    for a in range(1, m + 1):
        L[j, a] *= inv
    for a in range(1, m + 1):
        la = L[j, a]
        for b in range(a, m + 1):
            L[j + a, b - a] -= L[j, b] * la
    return True


@njit(cache=True, error_model="numpy")
def factor_block(blk, A, L, blk_dof):
    """L (in A's layout, half-bandwidth ``BW``) = Cholesky factor of block ``blk`` of A; False if
    a pivot is not > 0.  Right-looking: column j is scaled, then its outer product is taken from
    the next BW columns (contiguous rows of the (N, BW + 1) storage); the block's last BW columns
    with the bound of the block."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    for j in range(d0, d1):
        for d in range(BW + 1):
            L[j, d] = A[j, d]
    for j in range(d0, max(d0, d1 - BW)):
        if not _eliminate(L, j, BW):
            return False
    for j in range(max(d0, d1 - BW), d1):
        if not _eliminate(L, j, d1 - 1 - j):
            return False
    return True


@njit(cache=True, error_model="numpy")
def solve_block(blk, L, b, x, blk_dof):
    """x = (L L^T)^-1 b on block ``blk`` (forward then back substitution; x may be b).  The
    pivots' reciprocals do not depend on x, so they leave the substitutions' dependency chain
    (a division there costs its full latency per row)."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    for j in range(d0, d1):
        x[j] = b[j]
    for j in range(d0, d1):
        xj = x[j] * (1.0 / L[j, 0])
        x[j] = xj
        for a in range(1, min(BW, d1 - 1 - j) + 1):
            x[j + a] -= L[j, a] * xj
    for j in range(d1 - 1, d0 - 1, -1):
        s = x[j]
        for a in range(1, min(BW, d1 - 1 - j) + 1):
            s -= L[j, a] * x[j + a]
        x[j] = s * (1.0 / L[j, 0])


@njit(cache=True, parallel=True, error_model="numpy")
def factor_parallel(A, L, blk_dof, ok):
    """Factor every block (``ok[blk]``: its pivots were positive)."""
    for blk in prange(blk_dof.shape[0] - 1):
        ok[blk] = factor_block(blk, A, L, blk_dof)


@njit(cache=True, error_model="numpy")
def factor_serial(A, L, blk_dof, ok):
    for blk in range(blk_dof.shape[0] - 1):
        ok[blk] = factor_block(blk, A, L, blk_dof)


@njit(cache=True, parallel=True, error_model="numpy")
def solve1_parallel(L, b, x, blk_dof):
    """x = A^-1 b (vectors) with the factor L of every block."""
    for blk in prange(blk_dof.shape[0] - 1):
        solve_block(np.int64(blk), L, b, x, blk_dof)   # prange's index is unsigned: one build with the serial loop's


@njit(cache=True, error_model="numpy")
def solve1_serial(L, b, x, blk_dof):
    for blk in range(blk_dof.shape[0] - 1):
        solve_block(blk, L, b, x, blk_dof)


@njit(cache=True, parallel=True, error_model="numpy")
def solve_parallel(L, B, X, blk_dof):
    """X[:, r] = A^-1 B[:, r] for every column r (B, X: (N, R)) with the factor L of every block."""
    for blk in prange(blk_dof.shape[0] - 1):
        for r in range(B.shape[1]):
            solve_block(np.int64(blk), L, B[:, r], X[:, r], blk_dof)


@njit(cache=True, error_model="numpy")
def solve_serial(L, B, X, blk_dof):
    for blk in range(blk_dof.shape[0] - 1):
        for r in range(B.shape[1]):
            solve_block(blk, L, B[:, r], X[:, r], blk_dof)


@njit(cache=True, error_model="numpy")
def schur_block(s, L, Bt, first, dof_off, out):
    """out[s] = Y^T Y, Y = L_s^-1 B_s, for strand s (see ``schur_parallel``).  Y (rows, columns)
    is solved right-looking with the columns innermost (contiguous, independent: they vectorise);
    the columns are sorted by their first non-zero row, so at row j only the prefix of columns
    with first <= j is non-zero and updated.  Y^T Y by BLAS (one thread: hairexp.tune_runtime)."""
    Rb, nmax = Bt.shape[1], Bt.shape[2]
    d0 = dof_off[s]
    n = dof_off[s + 1] - d0
    Y = np.zeros((nmax, Rb))
    for r in range(Rb):
        if first[s, r] >= 0:
            for j in range(first[s, r], n):
                Y[j, r] = Bt[s, r, j]
    m = 0
    for j in range(n):
        while m < Rb and first[s, m] >= 0 and first[s, m] <= j:
            m += 1
        inv = 1.0 / L[d0 + j, 0]
        for r in range(m):
            Y[j, r] *= inv
        for a in range(1, min(BW, n - 1 - j) + 1):
            la = L[d0 + j, a]
            for r in range(m):
                Y[j + a, r] -= la * Y[j, r]
    out[s] = np.dot(Y.T, Y)   # BLAS: a third faster than the rank-one updates over the non-zero prefix


@njit(cache=True, error_model="numpy")
def scatter_grouped(G, base, scale, g_ptr, g_strands, g_rows, out):
    """S[rows[a], rows[b]] += scale[s, a] scale[s, b] G[s, base[s, a], base[s, b]] over the strands'
    non-empty columns (base >= 0): the strands' blocks A_s H_s^-1 A_s^T summed into S.  By groups of
    strands with the same constraint rows (``g_rows`` (Gr, R); strands
    ``g_strands[g_ptr[g]:g_ptr[g + 1]]``): each group is summed in a dense R x R buffer (contiguous
    writes), then scattered into S once."""
    R = base.shape[1]
    acc = np.empty((R, R))
    for g in range(g_ptr.shape[0] - 1):
        acc[:, :] = 0.0
        for k in range(g_ptr[g], g_ptr[g + 1]):
            s = g_strands[k]
            for a in range(R):
                ba = base[s, a]
                if ba < 0:
                    continue
                sa = scale[s, a]
                for b in range(R):
                    bb = base[s, b]
                    if bb >= 0:
                        acc[a, b] += sa * scale[s, b] * G[s, ba, bb]
        for a in range(R):
            ra = g_rows[g, a]
            for b in range(R):
                out[ra, g_rows[g, b]] += acc[a, b]


@njit(cache=True, error_model="numpy")
def schur_serial(L, Bt, first, dof_off, out):
    for s in range(Bt.shape[0]):
        schur_block(s, L, Bt, first, dof_off, out)


@njit(cache=True, parallel=True, error_model="numpy")
def schur_parallel(L, Bt, first, dof_off, out):
    """Per strand s: Y = L_s^-1 B_s (forward substitution), out[s] = Y^T Y (Rb, Rb).

    ``Bt`` (S, Rb, nmax): the strand's distinct columns of the constraint Jacobian's transpose
    A_s^T up to scale (constant: a centre of mass is linear in the positions, paper 3.2; the
    columns of one tracking point's clusters of different guides are proportional, so Celia's 72
    columns per strand are 24); ``first`` (S, Rb): the first non-zero row of each, ascending
(-1: padding, last).
    ``scatter_grouped`` sums the blocks into the Schur complement S = A H^-1 A^T (paper eq. 8,
    hairexp/control/tracking/kkt.py)."""
    for s in prange(Bt.shape[0]):
        schur_block(np.int64(s), L, Bt, first, dof_off, out)   # as solve1_parallel


@njit(cache=True, error_model="numpy")
def _band_rows(A, v, out, j0, j1, e):
    """out[j] += the band's products of rows j0 to j1 (their entries up to column e, exclusive):
    below the diagonal into out[j + a], above it summed in a register into out[j]."""
    bw1 = A.shape[1]
    for j in range(j0, j1):
        vj = v[j]
        acc = 0.0
        for a in range(1, min(bw1, e - j)):
            l = A[j, a]
            out[j + a] += l * vj
            acc += l * v[j + a]
        out[j] += acc


@njit(cache=True, error_model="numpy")
def band_product_lt(A, v, out):
    """out = A v for the symmetric band in this module's storage (A[j, d] = A[j + d, j], (N, bw + 1),
    C order): each column's entries are read once, contiguously, for both triangles (numpy on
    LAPACK's (bw + 1, N) view reads them with a stride of bw + 1 doubles, 2 x each: 0.79 ms at
    Celia's size against 0.22 here, 2026-12-06)."""
    N = A.shape[0]
    for j in range(N):
        out[j] = A[j, 0] * v[j]
    _band_rows(A, v, out, np.int64(0), N, N)


@njit(cache=True, error_model="numpy")
def _band_product_blocks(A, v, out, blk_dof, b0, b1):
    """``band_product_lt`` on blocks b0 to b1 (their rows, and no entry across a block's end: those
    are 0 in every band the assembly writes, so the sums are ``band_product_lt``'s bit for bit)."""
    for j in range(blk_dof[b0], blk_dof[b1]):
        out[j] = A[j, 0] * v[j]
    for blk in range(b0, b1):
        _band_rows(A, v, out, blk_dof[blk], blk_dof[blk + 1], blk_dof[blk + 1])


@njit(cache=True, parallel=True, error_model="numpy")
def band_product_parallel(A, v, out, blk_dof):
    """``band_product_lt`` for a block-diagonal band (``blk_dof``), two runs of blocks on the
    kernels' threads."""
    nb = blk_dof.shape[0] - 1
    for c in prange(2):
        k = np.int64(c)   # prange's index is unsigned
        _band_product_blocks(A, v, out, blk_dof, (nb * k) // 2, (nb * (k + 1)) // 2)
