"""Compiled (numba) per-strand kernels of the free objective, paper eq. (5):

    G(x) = 1/(2 h^2) |x - x_pred|^2_M + (E_stretch(y) + E_bend(y) + E_grav(y)) / (1 - alpha_f),

y = (1 - alpha_f) x + alpha_f x_n (hairexp/physics/integrators.py; alpha_f = 0 but for
generalized-alpha).  The element formulas are those of hairexp/physics/energies.py, term for
term (torch autograd of those energies is the reference they are tested against,
tests/test_kernels.py):

* stretch (``Stretch``): E = 1/2 (k/l0)(l - l0)^2, gradient (k/l0)(l - l0) u on the second
  vertex; PSD Hessian block K = c I + (k/l0 - c) u u^T with c = max(T, 0)/l, T the tension
  iterate of the primal-dual Hessian (or (k/l0)(l - l0) without one);
* bending (``Bending``): E = w (|kb| - s)^2, kb = 2 e0 x e1 / (|e0||e1| + e0.e1) (Bergou et al.
  2008), gradient 2w J^T kb (1 - s/|kb|), Gauss-Newton Hessian 2w [c J^T J + (1 - c) q q^T],
  c = max(0, 1 - s/|kb|), q = J^T kb/|kb| (``bending_kernel``);
* inertia M/h^2 on the diagonal and the constant external gradient (gravity).

Work is split by *blocks*: runs of free vertices that no element couples to the next run
(a strand's free vertices).  Every element is assigned to the block of its free vertices, and
each block's rows of the band and of the gradient are written by one thread only, so the blocks
run in parallel (``prange``) without atomics.  The band is LAPACK's lower banded storage
transposed, ``abT[j, d] = A[j + d, j]`` (``abT.T`` is what ``scipy.linalg.solveh_banded`` takes),
so that one column's entries are contiguous.

Everything is ``@njit(cache=True, error_model="numpy")``: the first run in a checkout compiles and
stores the machine code next to this file; later processes load it.  Compiling is not cheap (a fresh
clone, 2026-12-06, ``experiment=goaling_smoke frames=2``: the free step's kernels 48 s with
``solver.threads=1`` and 45 s more for the 2-thread variants, the tracked SQP's 23 s and 28 s more;
cached, the same runs start in 4-5 s).  The per-block and per-element
helpers are ``inline="always"`` (numba inlines them into the loops over blocks before LLVM sees
them): a call passes every array argument as its unpacked struct (data, shape, strides, ...), about
a microsecond per block for ``strand_derivatives``' twenty arrays, and views made per block (a
reshape, slices) cost a call each.  Inlined, the fused pass at Celia scale took 1.52 ms instead of
1.82 ms and the gradient alone 0.38 instead of 0.51 (2026-12-03, interleaved, one thread), with the
same operations in the same order: bit-identical results.  The price is compile time on a cold
cache (the inlined loops are compiled once per kernel that contains them).
"""

from __future__ import annotations

import logging
import math

import numpy as np

try:  # numba is a dependency, but a missing or broken install must not stop the torch path
    from numba import njit as _numba_njit
    from numba import prange
    from numba.core import caching as _caching
    HAVE_NUMBA = True

    _numba_save_overload = _caching.Cache.save_overload
    _CACHE_WARNED: list[str] = []

    def _save_or_warn(self, sig, data):
        """numba's ``Cache.save_overload``, with a write error of the on-disk compile cache said
        once and not raised: the function is compiled and in memory; only the next process
        compiles it again.  numba raised it into the run, which then failed as if its run folder
        could not be written (``[Errno 27] File too large``, naming no file, under ``ulimit -f``
        with a cold cache; independent probe of issue 12, round 22)."""
        try:
            _numba_save_overload(self, sig, data)
        except OSError as exc:
            if not _CACHE_WARNED:
                where = getattr(self, "_cache_path", "numba's cache folder")
                _CACHE_WARNED.append(str(exc))
                logging.getLogger("hairexp").warning(
                    "numba's compile cache could not be written in %s (%s): the run goes on; the kernels "
                    "compile again in the next process (NUMBA_CACHE_DIR chooses the folder)", where, exc)

    _caching.Cache.save_overload = _save_or_warn

    from numba.core import event as _event

    class _FirstCompile(_event.Listener):
        """Says once per process when numba compiles one of hairexp's kernels: a kernel found in the
        on-disk cache fires no compile event, so the line comes only when compiling takes the time
        (the first run in a checkout, or the first that takes another path, such as two threads:
        ``solver.threads=2`` on goaling_smoke ran 130 s instead of 5 without a word; independent
        probe, 2026-12-07)."""

        said = False

        def on_start(self, event):
            if self.said:
                return
            data = event.data if isinstance(event.data, dict) else {}
            func = getattr(data.get("dispatcher"), "py_func", None)
            if func is None or not str(getattr(func, "__module__", "")).startswith("hairexp."):
                return
            self.said = True
            logging.getLogger("hairexp").info(
                "numba is compiling hairexp's kernels (%s first): once per checkout and code path, up to a few "
                "minutes on 2 cores; later runs load them from the compile cache", func.__name__)

        def on_end(self, event):
            pass

    COMPILE_NOTICE = _FirstCompile()
    _event.register("numba:compile", COMPILE_NOTICE)

    def njit(*args, **kwargs):
        """numba's ``njit``; where its cache cannot be written (the checkout is read-only to this
        user and so is the user's cache folder: numba raises "no locator available" when the
        function is defined), the function is compiled without the on-disk cache instead of the
        import failing (it then compiles in every process, a few seconds)."""
        def deco(f):
            try:
                return _numba_njit(**kwargs)(f)
            except RuntimeError as exc:
                if not kwargs.get("cache") or "cannot cache" not in str(exc):
                    raise
                logging.getLogger(__name__).debug("numba cache unavailable for %s (%s)", f.__name__, exc)
                return _numba_njit(**dict(kwargs, cache=False))(f)

        if args and callable(args[0]):
            return deco(args[0])
        return deco
except ImportError:  # pragma: no cover - exercised by monkeypatching HAVE_NUMBA in the tests
    HAVE_NUMBA = False

    def njit(*args, **kwargs):
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

    prange = range


def read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (no copy; its layout kept).  numba types an array with its
    read-only flag: a kernel given a scene's topology read-only as built (``Strands``) and
    writable from a deep copy (an experiment's variants share a settled scene by copies) was
    compiled once for each; the kernels take such constant arrays through this, never writing them."""
    v = a.view()
    v.setflags(write=False)
    return v


#: Below this |kb| the bending direction is undefined (hairexp/physics/energies.py KB_EPS).
KB_EPS = 1e-14


@njit(cache=True, error_model="numpy")
def eval_points(xf, x_full, x_n, free_vertices, fixed_vertices, alpha_f, Y):
    """Y (V, 3): the evaluation point y = (1 - alpha_f) x + alpha_f x_n, x the prescribed
    ``x_full`` with the free rows from the DOF vector ``xf`` (as ``ImplicitEulerObjective.eval_positions``);
    ``fixed_vertices``: the other rows (the kinematic ones), the only ones copied from ``x_full``."""
    V = x_full.shape[0]
    for i in range(fixed_vertices.shape[0]):
        v = fixed_vertices[i]
        for c in range(3):
            Y[v, c] = x_full[v, c]
    for i in range(free_vertices.shape[0]):
        v = free_vertices[i]
        for c in range(3):
            Y[v, c] = xf[3 * i + c]
    if alpha_f != 0.0:
        for v in range(V):
            for c in range(3):
                Y[v, c] = (1.0 - alpha_f) * Y[v, c] + alpha_f * x_n[v, c]


@njit(cache=True, error_model="numpy", inline="always")
def bend_jacobian(Y, a, b, c, J, kb, e0, e1):
    """kb (3,) and its Jacobian J (3, 9) w.r.t. (x_a, x_b, x_c), as ``energies.kb_jacobian``:
    d kb/d e0 = (-2[e1]x - kb (l1 e0/l0 + e1)^T)/chi, d kb/d e1 = (2[e0]x - kb (l0 e1/l1 + e0)^T)/chi.
    In registers, J written once.  ``e0``, ``e1`` (3,): the edge vectors (set here)."""
    p0, p1, p2 = Y[b, 0] - Y[a, 0], Y[b, 1] - Y[a, 1], Y[b, 2] - Y[a, 2]   # e0
    q0, q1, q2 = Y[c, 0] - Y[b, 0], Y[c, 1] - Y[b, 1], Y[c, 2] - Y[b, 2]   # e1
    e0[0], e0[1], e0[2] = p0, p1, p2
    e1[0], e1[1], e1[2] = q0, q1, q2
    l0 = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    l1 = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    ic = 1.0 / (l0 * l1 + p0 * q0 + p1 * q1 + p2 * q2)    # 1 / chi
    k0 = 2.0 * ic * (p1 * q2 - p2 * q1)
    k1 = 2.0 * ic * (p2 * q0 - p0 * q2)
    k2 = 2.0 * ic * (p0 * q1 - p1 * q0)
    kb[0], kb[1], kb[2] = k0, k1, k2
    r01, r10 = l1 / l0, l0 / l1
    m0, m1, m2 = r01 * p0 + q0, r01 * p1 + q1, r01 * p2 + q2
    n0, n1, n2 = r10 * q0 + p0, r10 * q1 + p1, r10 * q2 + p2
    # d kb/d e0 = (-kb m^T - 2 [e1]x) / chi,  d kb/d e1 = (-kb n^T + 2 [e0]x) / chi,
    # [v]x = [[0, -v2, v1], [v2, 0, -v0], [-v1, v0, 0]]
    a00 = -k0 * m0 * ic
    a01 = (-k0 * m1 + 2.0 * q2) * ic
    a02 = (-k0 * m2 - 2.0 * q1) * ic
    a10 = (-k1 * m0 - 2.0 * q2) * ic
    a11 = -k1 * m1 * ic
    a12 = (-k1 * m2 + 2.0 * q0) * ic
    a20 = (-k2 * m0 + 2.0 * q1) * ic
    a21 = (-k2 * m1 - 2.0 * q0) * ic
    a22 = -k2 * m2 * ic
    b00 = -k0 * n0 * ic
    b01 = (-k0 * n1 - 2.0 * p2) * ic
    b02 = (-k0 * n2 + 2.0 * p1) * ic
    b10 = (-k1 * n0 + 2.0 * p2) * ic
    b11 = -k1 * n1 * ic
    b12 = (-k1 * n2 - 2.0 * p0) * ic
    b20 = (-k2 * n0 - 2.0 * p1) * ic
    b21 = (-k2 * n1 + 2.0 * p0) * ic
    b22 = -k2 * n2 * ic
    # J = (-d kb/d e0, d kb/d e0 - d kb/d e1, d kb/d e1)
    J[0, 0], J[0, 1], J[0, 2] = -a00, -a01, -a02
    J[1, 0], J[1, 1], J[1, 2] = -a10, -a11, -a12
    J[2, 0], J[2, 1], J[2, 2] = -a20, -a21, -a22
    J[0, 3], J[0, 4], J[0, 5] = a00 - b00, a01 - b01, a02 - b02
    J[1, 3], J[1, 4], J[1, 5] = a10 - b10, a11 - b11, a12 - b12
    J[2, 3], J[2, 4], J[2, 5] = a20 - b20, a21 - b21, a22 - b22
    J[0, 6], J[0, 7], J[0, 8] = b00, b01, b02
    J[1, 6], J[1, 7], J[1, 8] = b10, b11, b12
    J[2, 6], J[2, 7], J[2, 8] = b20, b21, b22


@njit(cache=True, error_model="numpy")
def _add_block(abT, rows, cols, H, p, q, scale):
    """Add scale * H[3p:3p+3, 3q:3q+3] at DOF rows ``rows`` > cols ``cols`` (p > q), or its lower
    triangle on the diagonal (p = q, rows = cols); rows and cols are rows of ``abT`` (a block's
    own band: the DOFs less the block's first one)."""
    if p == q:
        for r in range(3):
            for s in range(r + 1):
                abT[cols + s, r - s] += scale * H[3 * p + r, 3 * p + s]
    else:
        for r in range(3):
            for s in range(3):
                abT[cols + s, rows + r - cols - s] += scale * H[3 * p + r, 3 * q + s]


@njit(cache=True, error_model="numpy", inline="always")
def _add_diagonal_block(abT, C, K00, K10, K20, K11, K21, K22):
    """Adds the lower triangle of the symmetric 3x3 block K to the band's diagonal block whose
    first column is C (transposed band storage: abT[column, row - column])."""
    abT[C, 0] += K00
    abT[C, 1] += K10
    abT[C, 2] += K20
    abT[C + 1, 0] += K11
    abT[C + 1, 1] += K21
    abT[C + 2, 0] += K22


@njit(cache=True, error_model="numpy", inline="always")
def _sub_offdiagonal_block(abT, C, D, K00, K10, K20, K01, K11, K21, K02, K12, K22):
    """Subtracts the 3x3 block K (K[r, s] = K<r><s>) coupling the vertex whose first column is C
    to the one D columns further (transposed band storage: abT[C + s, D + r - s] -= K[r, s])."""
    abT[C, D] -= K00
    abT[C, D + 1] -= K10
    abT[C, D + 2] -= K20
    abT[C + 1, D - 1] -= K01
    abT[C + 1, D] -= K11
    abT[C + 1, D + 1] -= K21
    abT[C + 2, D - 2] -= K02
    abT[C + 2, D - 1] -= K12
    abT[C + 2, D] -= K22


@njit(cache=True, error_model="numpy", inline="always")
def strand_derivatives(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                       b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, off, need_hessian, W):
    """Gradient g_int (rows d0..d1 of the block's DOFs) of the energies and the lower band
    (M/h^2 on the diagonal plus (1 - alpha_f) x the element Hessians, ``h_scale``) of block
    ``blk``, the band's DOF j in row j - ``off`` of ``abT`` (``off`` = 0: the global band;
    ``off`` = the block's first DOF: a block-sized buffer that stays in cache).  ``W``
    (SCRATCH,): scratch, one per thread (an allocation per block costs as much as a strand's
    stretch)."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    bw = abT.shape[1] - 1
    for j in range(d0, d1):
        g_int[j] = 0.0
    if need_hessian:   # the block's rows zeroed (row by row: a reshape to one run costs a call per block), then the diagonal
        for i in range(d0 - off, d1 - off):
            for c in range(bw + 1):
                abT[i, c] = 0.0
        for j in range(d0, d1):
            abT[j - off, 0] = mass_diag[j]
    for k in range(e_ptr[blk], e_ptr[blk + 1]):
        e = e_idx[k]
        va, vb = edges[e, 0], edges[e, 1]
        u0 = Y[vb, 0] - Y[va, 0]
        u1 = Y[vb, 1] - Y[va, 1]
        u2 = Y[vb, 2] - Y[va, 2]
        ln = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        il = 1.0 / ln
        u0 *= il
        u1 *= il
        u2 *= il
        T_now = k_l0[e] * (ln - l0[e])
        sa, sb = free_slot[va], free_slot[vb]
        if sa >= 0:
            g_int[3 * sa] -= T_now * u0
            g_int[3 * sa + 1] -= T_now * u1
            g_int[3 * sa + 2] -= T_now * u2
        if sb >= 0:
            g_int[3 * sb] += T_now * u0
            g_int[3 * sb + 1] += T_now * u1
            g_int[3 * sb + 2] += T_now * u2
        if not need_hessian:
            continue
        T = tension[e] if use_tension else T_now
        cc = max(T, 0.0) * il
        kc = k_l0[e] - cc
        # h_scale x K, K = cc I + (k/l0 - cc) u u^T: the blocks (a, a), (b, b) = K, (b, a) = -K
        K00 = h_scale * (kc * u0 * u0 + cc)
        K11 = h_scale * (kc * u1 * u1 + cc)
        K22 = h_scale * (kc * u2 * u2 + cc)
        K10 = h_scale * (kc * u1 * u0)
        K20 = h_scale * (kc * u2 * u0)
        K21 = h_scale * (kc * u2 * u1)
        if sa >= 0:
            _add_diagonal_block(abT, 3 * sa - off, K00, K10, K20, K11, K21, K22)
        if sb >= 0:
            _add_diagonal_block(abT, 3 * sb - off, K00, K10, K20, K11, K21, K22)
            if sa >= 0:   # abT[C + s, R + r - C - s] -= K[r, s], R = the rows of b, C the columns of a
                K01 = h_scale * (kc * u0 * u1)
                K02 = h_scale * (kc * u0 * u2)
                K12 = h_scale * (kc * u1 * u2)
                C = 3 * sa - off
                _sub_offdiagonal_block(abT, C, 3 * sb - off - C, K00, K10, K20, K01, K11, K21, K02, K12, K22)
    J = W[84:111].reshape((3, 9))
    kb = W[111:114]
    q = W[114:123]
    e0 = W[123:126]
    e1 = W[126:129]
    for k in range(b_ptr[blk], b_ptr[blk + 1]):
        e = b_idx[k]
        bend_jacobian(Y, bends[e, 0], bends[e, 1], bends[e, 2], J, kb, e0, e1)
        nrm = math.sqrt(kb[0] * kb[0] + kb[1] * kb[1] + kb[2] * kb[2])
        s = s_rest[e]
        ratio = 0.0
        if s > 0.0:
            ratio = s / nrm if nrm > KB_EPS else 1.0   # at the kink: no pull
        f = 2.0 * w[e] * (1.0 - ratio)
        sl = (free_slot[bends[e, 0]], free_slot[bends[e, 1]], free_slot[bends[e, 2]])
        for p in range(3):
            if sl[p] >= 0:
                for r in range(3):
                    a = 3 * p + r
                    g_int[3 * sl[p] + r] += f * (J[0, a] * kb[0] + J[1, a] * kb[1] + J[2, a] * kb[2])
        if not need_hessian:
            continue
        c = max(1.0 - ratio, 0.0)
        wc = 2.0 * w[e] * c
        wq = 2.0 * w[e] * (1.0 - c)
        rank_one = wq != 0.0 and nrm > KB_EPS   # curved rest shape: the rank-one part along kb/|kb|
        if rank_one:
            inrm = 1.0 / nrm
            for a in range(9):
                q[a] = (J[0, a] * kb[0] + J[1, a] * kb[1] + J[2, a] * kb[2]) * inrm
        # the lower triangle of the 9 x 9 Gauss-Newton Hessian, entry by entry into the band
        if not rank_one and sl[1] == sl[0] + 1 and sl[2] == sl[0] + 2 and sl[0] >= 0:
            # a strand's interior bend (the common case): its 9 DOFs are the band's consecutive rows
            # B..B+8, H[a, bb] (a >= bb) at abT[B + bb, a - bb], one contiguous run per column bb
            B = 3 * sl[0] - off
            for bb in range(9):
                j0, j1, j2 = J[0, bb], J[1, bb], J[2, bb]
                for a in range(bb, 9):
                    abT[B + bb, a - bb] += h_scale * (wc * (J[0, a] * j0 + J[1, a] * j1 + J[2, a] * j2))
            continue
        # any bend: H[a, bb] at abT[C + s, R + r - C - s] (a = 3p + r, bb = 3qq + s, p >= qq)
        for p in range(3):
            if sl[p] < 0:
                continue
            R = 3 * sl[p] - off
            for qq in range(p + 1):
                if sl[qq] < 0:
                    continue
                C = 3 * sl[qq] - off
                for r in range(3):
                    a = 3 * p + r
                    for s3 in range(r + 1 if qq == p else 3):
                        bb = 3 * qq + s3
                        h = wc * (J[0, a] * J[0, bb] + J[1, a] * J[1, bb] + J[2, a] * J[2, bb])
                        if rank_one:
                            h += wq * q[a] * q[bb]
                        abT[C + s3, R + r - C - s3] += h_scale * h


@njit(cache=True, error_model="numpy", inline="always")
def assemble_block(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                   b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, need_hessian, W):
    """``strand_derivatives`` of block ``blk`` into the global band abT (N, bw + 1)."""
    strand_derivatives(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                       b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, 0, need_hessian, W)


#: Length of ``strand_derivatives``' scratch: H (9, 9), u (3), J (3, 9), kb (3), q (9), e0 (3), e1 (3).
SCRATCH = 129


@njit(cache=True, parallel=True, error_model="numpy")
def assemble_parallel(Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                      b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, need_hessian, n_chunks):
    """``assemble_block`` for every block, in parallel over ``n_chunks`` runs of blocks (one
    scratch each)."""
    nb = blk_dof.shape[0] - 1
    size = (nb + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        W = np.zeros(SCRATCH)
        for blk in range(c * size, min(nb, (c + 1) * size)):
            assemble_block(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                           b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, need_hessian, W)


@njit(cache=True, error_model="numpy")
def assemble_serial(Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                    b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, need_hessian, n_chunks):
    """``assemble_block`` for every block on the calling thread (a 1-thread ``prange`` region
    still pays the thread pool's launch)."""
    W = np.zeros(SCRATCH)
    for blk in range(blk_dof.shape[0] - 1):
        assemble_block(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                       b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, abT, g_int, need_hessian, W)


@njit(cache=True, error_model="numpy", inline="always")
def stretch_energy_of(Y, edges, e, k_l0, l0):
    va, vb = edges[e, 0], edges[e, 1]
    d = 0.0
    for i in range(3):
        t = Y[vb, i] - Y[va, i]
        d += t * t
    dl = math.sqrt(d) - l0[e]
    return 0.5 * k_l0[e] * dl * dl


@njit(cache=True, error_model="numpy", inline="always")
def bend_energy_of(Y, bends, e, w, s_rest):
    """w (|kb|^2 - 2 s |kb| + s^2), |kb| taken only where s > 0 (``energies.bending_energy``)."""
    a, b, c = bends[e, 0], bends[e, 1], bends[e, 2]
    p0, p1, p2 = Y[b, 0] - Y[a, 0], Y[b, 1] - Y[a, 1], Y[b, 2] - Y[a, 2]
    q0, q1, q2 = Y[c, 0] - Y[b, 0], Y[c, 1] - Y[b, 1], Y[c, 2] - Y[b, 2]
    l0 = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    l1 = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    chi = l0 * l1 + p0 * q0 + p1 * q1 + p2 * q2
    k0 = 2.0 * (p1 * q2 - p2 * q1) / chi
    k1 = 2.0 * (p2 * q0 - p0 * q2) / chi
    k2 = 2.0 * (p0 * q1 - p1 * q0) / chi
    sq = k0 * k0 + k1 * k1 + k2 * k2
    s = s_rest[e]
    mid = 2.0 * s * math.sqrt(max(sq, 1e-300)) if s > 0.0 else 0.0
    return w[e] * (sq - mid + s * s)


@njit(cache=True, error_model="numpy", inline="always")
def energies_block(blk, Y, xf, x_pred, mass_diag, g_ext, free_vertices, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                   b_ptr, b_idx, bends, w, s_rest, e_rest, b_rest, out):
    """out[blk] = (inertia 1/2 |x - x_pred|^2_M/h^2, stretch, bending, external g_ext . y) of
    block ``blk`` (the line search's value); ``e_rest``/``b_rest``: elements without a free
    vertex (their energy is constant over the step but part of the value), in block 0's sums."""
    ine, st, be, ext = 0.0, 0.0, 0.0, 0.0
    for i in range(blk_dof[blk] // 3, blk_dof[blk + 1] // 3):   # DOF j = 3 i + c of free vertex i, j ascending
        v = free_vertices[i]
        for c in range(3):
            j = 3 * i + c
            d = xf[j] - x_pred[j]
            ine += 0.5 * mass_diag[j] * d * d
            ext += g_ext[j] * Y[v, c]
    for k in range(e_ptr[blk], e_ptr[blk + 1]):
        st += stretch_energy_of(Y, edges, e_idx[k], k_l0, l0)
    for k in range(b_ptr[blk], b_ptr[blk + 1]):
        be += bend_energy_of(Y, bends, b_idx[k], w, s_rest)
    if blk == 0:
        for k in range(e_rest.shape[0]):
            st += stretch_energy_of(Y, edges, e_rest[k], k_l0, l0)
        for k in range(b_rest.shape[0]):
            be += bend_energy_of(Y, bends, b_rest[k], w, s_rest)
    out[blk, 0] = ine
    out[blk, 1] = st
    out[blk, 2] = be
    out[blk, 3] = ext


@njit(cache=True, parallel=True, error_model="numpy")
def energies_parallel(Y, xf, x_pred, mass_diag, g_ext, free_vertices, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                      b_ptr, b_idx, bends, w, s_rest, e_rest, b_rest, out):
    for blk in prange(blk_dof.shape[0] - 1):
        energies_block(blk, Y, xf, x_pred, mass_diag, g_ext, free_vertices, blk_dof, e_ptr, e_idx, edges, k_l0,
                       l0, b_ptr, b_idx, bends, w, s_rest, e_rest, b_rest, out)


@njit(cache=True, error_model="numpy")
def energies_serial(Y, xf, x_pred, mass_diag, g_ext, free_vertices, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                    b_ptr, b_idx, bends, w, s_rest, e_rest, b_rest, out):
    for blk in range(blk_dof.shape[0] - 1):
        energies_block(blk, Y, xf, x_pred, mass_diag, g_ext, free_vertices, blk_dof, e_ptr, e_idx, edges, k_l0,
                       l0, b_ptr, b_idx, bends, w, s_rest, e_rest, b_rest, out)


@njit(cache=True, error_model="numpy")
def tensions(Y, D, edges, k_l0, l0, out):
    """Spring tensions (N) of every edge at Y, linearised along the displacement D (V, 3):
    (k/l0)(l - l0 + u . (D_b - D_a)) (``Stretch.linearized_tension``; D = 0: ``tension_of``)."""
    for e in range(edges.shape[0]):
        va, vb = edges[e, 0], edges[e, 1]
        d2 = 0.0
        lin = 0.0
        for i in range(3):
            t = Y[vb, i] - Y[va, i]
            d2 += t * t
            lin += (D[vb, i] - D[va, i]) * t
        ln = math.sqrt(d2)
        out[e] = k_l0[e] * (ln - l0[e] + lin / ln)


@njit(cache=True, error_model="numpy")
def tensions_along(Y, step, scale, free_slot, edges, k_l0, l0, out):
    """``tensions`` with the displacement D = ``scale`` x the DOF vector ``step`` on the free
    vertices (0 on the prescribed ones), without building D: the same sums, bit for bit."""
    for e in range(edges.shape[0]):
        va, vb = edges[e, 0], edges[e, 1]
        sa, sb = free_slot[va], free_slot[vb]
        d2 = 0.0
        lin = 0.0
        for i in range(3):
            t = Y[vb, i] - Y[va, i]
            d2 += t * t
            da = scale * step[3 * sa + i] if sa >= 0 else 0.0
            db = scale * step[3 * sb + i] if sb >= 0 else 0.0
            lin += (db - da) * t
        ln = math.sqrt(d2)
        out[e] = k_l0[e] * (ln - l0[e] + lin / ln)


@njit(cache=True, error_model="numpy")
def add_compression(Y, free_slot, edges, k_l0, l0, tension, use_tension, h_scale, abT):
    """Adds to the band abT (N, bw + 1) what ``strand_derivatives``' PSD stretch Hessian leaves
    out: h_scale x the negative transverse stiffness (T/l)(I - u u^T) of every compressed edge
    (T < 0, the tension iterate when ``use_tension``); returns how many edges were compressed."""
    n = 0
    for e in range(edges.shape[0]):
        va, vb = edges[e, 0], edges[e, 1]
        u0 = Y[vb, 0] - Y[va, 0]
        u1 = Y[vb, 1] - Y[va, 1]
        u2 = Y[vb, 2] - Y[va, 2]
        ln = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        T = tension[e] if use_tension else k_l0[e] * (ln - l0[e])
        if T >= 0.0:
            continue
        n += 1
        il = 1.0 / ln
        u0 *= il
        u1 *= il
        u2 *= il
        cc = h_scale * T * il
        K00 = cc * (1.0 - u0 * u0)
        K11 = cc * (1.0 - u1 * u1)
        K22 = cc * (1.0 - u2 * u2)
        K10 = -cc * u1 * u0
        K20 = -cc * u2 * u0
        K21 = -cc * u2 * u1
        sa, sb = free_slot[va], free_slot[vb]
        if sa >= 0:
            _add_diagonal_block(abT, 3 * sa, K00, K10, K20, K11, K21, K22)
        if sb >= 0:
            _add_diagonal_block(abT, 3 * sb, K00, K10, K20, K11, K21, K22)
            if sa >= 0:
                C = 3 * sa
                _sub_offdiagonal_block(abT, C, 3 * sb - C, K00, K10, K20, K10, K11, K21, K20, K21, K22)
    return n


# -- the fused Newton direction of the free step -------------------------------------------
#: Half-bandwidth of the fused pass's band (bending triples: 3 * 2 + 2), as ``bandchol.BW``.  The
#: band Cholesky rows below repeat bandchol's factorisation (same operations, same order) rather
#: than calling it: numba's on-disk cache of a function does not notice edits to compiled
#: functions of another file that it calls.
BW = 8


@njit(cache=True, error_model="numpy", inline="always")
def _eliminate(L, j, m):
    """Right-looking step at column j: scale it, subtract its outer product from the next m
    columns (``bandchol._eliminate``)."""
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


@njit(cache=True, error_model="numpy", inline="always")
def factor_rows(L, n):
    """Cholesky factor, in place, of the band in rows 0..n-1 of L ((>= n, BW + 1), layout
    ``abT``); False if a pivot is not > 0 (``bandchol.factor_block`` on one block)."""
    for j in range(max(0, n - BW)):
        if not _eliminate(L, j, BW):
            return False
    for j in range(max(0, n - BW), n):
        if not _eliminate(L, j, n - 1 - j):
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def solve_rows(L, n, x):
    """x = (L L^T)^-1 x in place with the factor of ``factor_rows`` (``bandchol.solve_block``)."""
    for j in range(n):
        xj = x[j] * (1.0 / L[j, 0])
        x[j] = xj
        for a in range(1, min(BW, n - 1 - j) + 1):
            x[j + a] -= L[j, a] * xj
    for j in range(n - 1, -1, -1):
        s = x[j]
        for a in range(1, min(BW, n - 1 - j) + 1):
            s -= L[j, a] * x[j + a]
        x[j] = s * (1.0 / L[j, 0])


@njit(cache=True, error_model="numpy", inline="always")
def direction_gradient(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                       use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, W, band):
    """Block ``blk``'s derivatives into the block-sized ``band`` (it stays in cache), the total
    gradient into grad, p = -grad, and the block's squared force norms into ``sums``: the
    operations of ``assemble_block`` + ``objective._total_gradient`` in their order."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    strand_derivatives(blk, Y, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                       b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, band, grad, d0, True, W)
    s_in = 0.0
    s_int = 0.0
    for j in range(d0, d1):
        fi = mass_diag[j] * (xf[j] - x_pred[j])
        gi = grad[j]
        s_in += fi * fi
        s_int += gi * gi
        g = fi + gi + g_ext[j]
        grad[j] = g
        p[j] = -g
    sums[blk, 0] = s_in
    sums[blk, 1] = s_int


@njit(cache=True, error_model="numpy")
def direction_block(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                    use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, ok, W, band):
    """One block of ``direction_serial`` on its own (a called function, not inlined: the rare
    paths, so that the inlined pass holds one copy of the derivatives)."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    n = d1 - d0
    direction_gradient(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                       use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, W, band)
    ok[blk] = factor_rows(band, n)
    if ok[blk]:
        solve_rows(band, n, p[d0:d1])


#: Blocks of the same size whose factorisations and solves the fused pass runs side by side: each
#: column's pivot waits on the previous column's square root and division, and each row of the
#: back substitution on a chain of eight subtractions (latency chains the order of the operations,
#: kept for bit-identical results, fixes); GROUP independent chains interleaved keep the core busy.
#: Measured at Celia scale (2026-12-03, one thread, against the pass before the inlining in the same
#: process): 2 -> 1.25x, 4 -> 1.28x, 8 -> 1.33x (8 bands of 75 rows fill L1): a small gain; 2 was
#: the pairs of the pass before (``factor_rows2``).
GROUP = 4


@njit(cache=True, error_model="numpy", inline="always")
def factor_group(L, g, n):
    """``factor_rows`` of the first g blocks of L (GROUP, >= n, BW + 1), all of n rows, column by
    column across the blocks (each block's operations are those of ``factor_rows``; the columns
    with a full band first, their loops of constant length BW unrolled); False if a pivot of any
    is not > 0 (then which one is not known)."""
    for j in range(max(0, n - BW)):
        good = True
        for k in range(g):
            good &= _eliminate(L[k], j, BW)
        if not good:
            return False
    for j in range(max(0, n - BW), n):
        good = True
        for k in range(g):
            good &= _eliminate(L[k], j, n - 1 - j)
        if not good:
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _forward_in(L, k, j, m, x, c):
    xj = x[c] * (1.0 / L[k, j, 0])
    x[c] = xj
    for a in range(1, m + 1):
        x[c + a] -= L[k, j, a] * xj


@njit(cache=True, error_model="numpy", inline="always")
def _backward_in(L, k, j, m, x, c):
    s = x[c]
    for a in range(1, m + 1):
        s -= L[k, j, a] * x[c + a]
    x[c] = s * (1.0 / L[k, j, 0])


@njit(cache=True, error_model="numpy", inline="always")
def solve_group(L, g, n, x, o):
    """``solve_rows`` of g blocks of n rows at once: block k's factor L[k], its right-hand side
    and solution in x[o + k n : o + (k + 1) n] (in place); the rows with a full band apart (loops
    of constant length BW)."""
    full = max(0, n - BW)
    for j in range(full):
        for k in range(g):
            _forward_in(L, k, j, BW, x, o + k * n + j)
    for j in range(full, n):
        for k in range(g):
            _forward_in(L, k, j, n - 1 - j, x, o + k * n + j)
    for j in range(n - 1, full - 1, -1):
        for k in range(g):
            _backward_in(L, k, j, n - 1 - j, x, o + k * n + j)
    for j in range(full - 1, -1, -1):
        for k in range(g):
            _backward_in(L, k, j, BW, x, o + k * n + j)


@njit(cache=True, error_model="numpy", inline="always")
def direction_blocks(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                     use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, ok, W, bands,
                     nb):
    """Block ``blk`` and the next ones of the same size, up to GROUP of them and below ``nb``, of
    ``direction_serial``: their derivatives one after the other into ``bands`` (GROUP, nmax, BW + 1),
    then their factorisations and solves side by side (``factor_group``, ``solve_group``); returns
    how many blocks it did.  A lone block, and a group with a failed pivot, go block by block
    through ``direction_block`` (the same operations)."""
    d0, d1 = blk_dof[blk], blk_dof[blk + 1]
    n = d1 - d0
    g = 1
    while g < GROUP and blk + g < nb and blk_dof[blk + g + 1] - blk_dof[blk + g] == n:
        g += 1
    if g == 1:
        direction_block(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                        use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, ok, W,
                        bands[0])
        return 1
    for i in range(g):
        direction_gradient(blk + i, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                           tension, use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums,
                           W, bands[i])
    if factor_group(bands, g, n):
        solve_group(bands, g, n, p, d0)
        for i in range(g):
            ok[blk + i] = True
    else:   # which one failed: each on its own (the next pass shifts the failed one)
        for i in range(g):
            direction_block(blk + i, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                            tension, use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums,
                            ok, W, bands[0])
    return g


@njit(cache=True, error_model="numpy")
def direction_serial(Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension, use_tension,
                     b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, ok, n_chunks):
    """Newton direction of the free objective (stretch, bending, inertia, gravity), block by block
    in one pass: grad (N,) the objective's gradient, p (N,) = -A^-1 grad with A its banded
    Hessian (never stored whole), ``sums[blk]`` the block's squared norms of the inertial and
    internal forces (the force scale), ``ok[blk]``: its pivots were positive (else p is not set
    there and the caller factors the band with a shift).  The same operations in the same order,
    per block, as ``assemble_block`` + ``objective._total_gradient`` + ``bandchol.factor_block``
    + ``bandchol.solve_block``: bit-identical results."""
    nb = blk_dof.shape[0] - 1
    nmax = 0
    for blk in range(nb):
        nmax = max(nmax, blk_dof[blk + 1] - blk_dof[blk])
    W = np.zeros(SCRATCH)
    bands = np.empty((GROUP, nmax, BW + 1))
    blk = np.int64(0)   # not the literal 0: direction_block was built a second time for it
    while blk < nb:
        blk += direction_blocks(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                                tension, use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p,
                                sums, ok, W, bands, nb)


@njit(cache=True, parallel=True, error_model="numpy")
def direction_parallel(Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0, tension,
                       use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad, p, sums, ok, n_chunks):
    """``direction_serial`` in parallel over ``n_chunks`` runs of blocks (one scratch each)."""
    nb = blk_dof.shape[0] - 1
    nmax = 0
    for blk in range(nb):
        nmax = max(nmax, blk_dof[blk + 1] - blk_dof[blk])
    size = (nb + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        W = np.zeros(SCRATCH)
        bands = np.empty((GROUP, nmax, BW + 1))
        end = min(nb, (c + 1) * size)
        blk = c * size
        while blk < end:
            blk += direction_blocks(blk, Y, xf, x_pred, g_ext, free_slot, blk_dof, e_ptr, e_idx, edges, k_l0, l0,
                                    tension, use_tension, b_ptr, b_idx, bends, w, s_rest, h_scale, mass_diag, grad,
                                    p, sums, ok, W, bands, end)
