"""SQP on the tracking problem (paper 3.4, eqs. 6-8).

    min_{x, t}  H(x) + P(x)   s.t.  C(x, t) = c(x) - c_hat(t) = 0

H is the implicit Euler objective (eq. 5), P the variance penalty (3.3).  Each iteration
solves the KKT system (8) for (dx, dt, lam+) with the PSD Hessian of H plus a PSD model of
the variance penalty's Hessian (Gauss-Newton rank one per cluster by a Woodbury update, and
the positive diagonal curvature; the paper leaves it out), then backtracks on the l1 merit function
phi = H + P + mu |C|_1 (Nocedal & Wright 2006, eq. 18.27), whose directional derivative along
a step that satisfies the linearised constraints is grad(H+P).dx - mu |C|_1 (Theorem 18.2);
mu is kept above |lam+|_inf (eq. 18.32).  The search is non-monotone (Grippo, Lampariello and
Lucidi 1986, "A nonmonotone line search technique for Newton's method"; for the l1 merit of SQP,
Panier and Tits 1991): the sufficient decrease is measured from the largest merit of the last
``nonmonotone`` iterates (all evaluated with the current mu), not from the current one alone
(``nonmonotone`` = 1: the monotone Armijo search).  After a contact the tips of some strands are
folded by 60-120 degrees and their stiff tip edges swing fast; the monotone search then
alternated full steps with steps of 1/8-1/16 for 25-30 iterations while the gradient stayed on
those edges (goaling tracked: 11.55 SQP iterations a step, max 76).  With the last 5 iterates:
7.61, max 18, the same convergence test (README "Tracking performance").
Convergence needs both residuals small:
|grad_x L| <= atol + rtol (force scale + |A^T lam|), |grad_t L| <= rtol |lam| |c_hat'| and
max |C_k| <= ctol.  t and lam are warm-started from the previous step.

With ``tracking.schur=krylov`` (hairexp/control/tracking/kkt.py) the KKT system is solved to a
relative tolerance, so it is posed for the multiplier's change lam+ - lam, whose right-hand side
is the Lagrangian's residual at (x, t, lam), small near a solution, instead of for lam+ itself,
whose right-hand side holds the whole constraint force (|grad H| ~ |A^T lam| >> |grad_x L|).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from hairexp.physics.assembly import band_product
from hairexp.physics.newton import likely_converged
from hairexp.physics.info import CONVERGED, DIVERGED, LINE_SEARCH_FAILED, MAX_ITERATIONS, SINGULAR, SolveInfo
from hairexp.control.tracking.kkt import reference_solve

#: Sufficient-decrease constant of the merit line search (N&W eq. 18.28, eta).
MERIT_ETA = 1e-4
#: mu = MU_FACTOR * |lam|_inf + MU_MARGIN (N&W eq. 18.32 asks mu > |lam|_inf).
MU_FACTOR, MU_MARGIN = 1.5, 1e-12
#: Backtracking factor.
BACKTRACK = 0.5
#: ``secant_correction``: the model's curvature along the last step is corrected where the true
#: one is below this fraction of it, and kept at least SECANT_FLOOR of it (positive definite)
SECANT_RATIO, SECANT_FLOOR = 0.5, 0.1
#: ``secant_correction``: how many last steps (their span), and the smallest eigenvalue of their
#: Gram matrix in B's metric, relative to its largest, kept as a direction of that span
SECANT_MEMORY, SECANT_COND = 1, 1e-8    # stylization: m = 1, 2, 3, 5 took 12.03, 12.80, 12.59, 13.61 SQP it/step


@dataclass
class SQPOptions:
    rtol: float = 1e-5
    atol: float = 1e-10
    ctol: float = 1e-10          # m, on max_k |C_k|
    max_iterations: int = 50
    max_backtracks: int = 30
    kkt: str = "schur"           # or "reference"
    #: the merit line search's reference is the largest merit of this many last iterates
    #: (non-monotone, see the module doc; 1: monotone)
    nonmonotone: int = 5
    #: the compressed edges' negative transverse stiffness in the Hessian (the PSD stretch
    #: Hessian clamps it to 0), per strand where the band stays positive definite, from the
    #: iteration after one that met the constraints (max |C| <= ctol) with a full step on
    #: (``exact_when="tail"``), or from the start ("always").  TR-BDF2's trapezoidal stage ends
    #: with most edges compressed on tracked runs, and with the clamp the SQP converged linearly
    #: there.  Celia tracked (trbdf2, 48 steps, interleaved): 24.2 -> 18.5 SQP iterations a step
    #: (max 83 -> 44), median step 0.29 -> 0.25 s, the same substeps; "always" took 33.5 (erratic
    #: steps far from the solution), as did switching on by the gradient residual's fall alone.
    #: Off by default (``tracking.exact_compression``): on the default Celia scene it led, at two
    #: tolerances, to a step where the post-solve collision stage left 0.56-0.58 edge strain
    #: (0.10-0.11 off), the solves' own strain 2e-4 (README "Tracking performance")
    exact_compression: bool = False
    exact_when: str = "tail"
    #: the secant correction of the Hessian model along the last step (``secant_correction``):
    #: where the true curvature s^T y of the objective along the last step s is below
    #: SECANT_RATIO x the model's s^T B s, the model's curvature along s is lowered to
    #: max(s^T y, SECANT_FLOOR s^T B s) by a rank-one term (``tracking.secant``); stylization
    #: 13.57 / 170 -> 12.03 / 118 SQP iterations a step (README "The secant correction")
    secant: bool = True
    #: a list to record the iterations in (experiments/sqp_trace.py): each solve appends a list,
    #: and each iteration a dict of its step length, residuals and tolerances; None: no record
    trace: list | None = None


def woodbury(solve, U: np.ndarray, step: tuple, zero_c: np.ndarray, signs: np.ndarray | None = None) -> tuple:
    """The KKT step with U diag(signs) U^T (signs: default all 1) added to the Hessian block,
    from solves without it.

    ``solve(r_x, C)`` is linear: (dx, dt, lam) = s(b) = -K^-1 b for the right-hand side
    b = (r_x, C, 0).  With K + U~ D U~^T (U~ = U padded with zeros outside the x block, D =
    diag(signs)), the Sherman-Morrison-Woodbury identity gives
    s'(b) = s(b) + S_U (D^-1 - U^T S_U)^-1 U^T s(b)_x, S_U the solves of U's columns."""
    cols = [solve(U[:, j], zero_c) for j in range(U.shape[1])]
    SU = np.stack([c[0] for c in cols], 1)
    dx, dt, lam = step
    Dinv = np.eye(U.shape[1]) if signs is None else np.diag(1.0 / np.asarray(signs, dtype=np.float64))
    coef = np.linalg.solve(Dinv - U.T @ SU, U.T @ dx)
    dx = dx + SU @ coef
    lam = lam + np.stack([c[2] for c in cols], 1) @ coef
    if dt is not None:
        dt = dt + np.stack([c[1] for c in cols], 1) @ coef
    return dx, dt, lam


def secant_correction(BS: np.ndarray, S: np.ndarray, Y: np.ndarray):
    """(columns U, signs) of a term U diag(signs) U^T that lowers the model's curvature where the
    last steps show it too large, or None.  S, Y (N, m): the last m steps and the changes of the
    objective's gradient over them; BS = B S.

    On span(S), B's and the objective's curvatures are G = S^T B S and M = sym(S^T Y) (the
    secant estimate: y = H s on each step, and its cross terms).  In B-orthonormal directions z_i
    of that span diagonalising M (G^-1/2 M G^-1/2 = Q diag(lam) Q^T), lam_i is the true curvature
    over the model's; where lam_i < SECANT_RATIO the model's curvature along z_i is set to
    max(lam_i, SECANT_FLOOR) of its own by the column u_i = B z_i with sign max(lam_i, floor) - 1:
    z_j^T (B + U D U^T) z_j = 1 + (lam_j' - 1) since u_i^T z_j = delta_ij, and B is unchanged on
    every direction B-orthogonal to the span; B + U D U^T stays positive definite (its curvature is
    lam' > 0 on the corrected directions).  With one step this is B - (1 - lam') (B s)(B s)^T /
    (s^T B s), the first half of a BFGS update (Nocedal & Wright 2006, 6.1; 18.3 for the
    Lagrangian's Hessian, here its x block: the constraints are linear in x).

    Why: the SQP's Hessian model B is positive definite by construction (the compressed springs'
    negative transverse stiffness clamped, bending by Gauss-Newton); where the hair buckles the
    step's objective curves far less, or negatively.  Measured in stylization's slow solves (the
    block's fall at 4.8 s, 2026-12-06): along an SQP step 99.998 % out of the wisp's plane, model
    5.8e-9 against true -1.3e-9 (bending's Gauss-Newton 5.2e-9 against -0.7e-9, stretch 3.7e-10
    against -9.3e-10): the iterates crept from the saddle by 1 + |true| / model = 1.23 an
    iteration for 30 and more iterations, and where the true curvature was a fifth of the
    model's the gradient fell by only 0.8 an iteration."""
    G = S.T @ BS
    G = 0.5 * (G + G.T)
    M = S.T @ Y
    M = 0.5 * (M + M.T)
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(M))):
        return None
    w, V = np.linalg.eigh(G)
    if w[-1] <= 0.0:
        return None
    keep = w > SECANT_COND * w[-1]        # steps nearly parallel in B's metric: their span's basis
    R = V[:, keep] / np.sqrt(w[keep])      # R^T G R = I
    lam, Q = np.linalg.eigh(R.T @ M @ R)
    low = lam < SECANT_RATIO
    if not low.any():
        return None
    return BS @ (R @ Q[:, low]), np.maximum(lam[low], SECANT_FLOOR) - 1.0


def _ratio(value: float, tol: float) -> float:
    """value / tol, with a tolerance of 0 (atol = 0 and no force: a hair at rest) met only by 0."""
    if tol > 0.0:
        return value / tol
    return 0.0 if value == 0.0 else math.inf


def _likely_converged(norms: list, alpha: float) -> bool:
    """Whether the next iterate is predicted to meet the tolerances: after a full step, each of
    the last iterate's |grad L| / its tolerance and max |C| / ctol within 1 already, or predicted
    within 1 by quadratic convergence from the last two (``newton.likely_converged``).  Only
    chooses whether the band is assembled with the gradient; a wrong guess costs a second
    evaluation."""
    if alpha != 1.0 or len(norms) < 2:
        return False
    return all(now <= 1.0 or likely_converged([before, now], alpha, 1.0) for now, before in zip(norms[-1], norms[-2]))


def sqp_solve(obj, tracker, x0: np.ndarray, t0: np.ndarray, lam0: np.ndarray, opts: SQPOptions,
              rho: np.ndarray | None = None):
    """Returns (x, t, lam, SolveInfo).  ``tracker`` supplies the constraints at this step.

    Elastic mode (``rho``: (3K,) penalty stiffness per constraint row, 0 for rows kept hard): a
    relaxed row's constraint C_k = 0 becomes the quadratic penalty rho/2 |C_k|^2 (an elastic
    slack s_k = C_k, Nocedal & Wright 2006, 18.3 "elastic mode").  Eliminating s_k (lam_k =
    rho s_k) leaves the KKT system (8) with -I/rho in the relaxed rows' (lam, lam) block: the
    Schur matrix S becomes S + diag(1/rho).  The merit function takes rho/2 |C_k|^2 for those rows
    instead of mu |C_k|, and their convergence test is |C_k - lam_k / rho_k| <= ctol."""
    info = SolveInfo()
    sec = info.seconds
    x, t, lam = x0.copy(), t0.copy(), lam0.copy()
    cons, kkt = tracker.cons, tracker.kkt
    sliding = cons.sliding
    mu = MU_FACTOR * float(np.abs(lam).max(initial=0.0)) + MU_MARGIN
    relaxed = None if rho is None or not np.any(rho > 0) else rho > 0
    reg = None if relaxed is None else np.where(relaxed, 1.0 / np.where(relaxed, rho, 1.0), 0.0)

    def merit_parts(xf, tk):
        f = obj.value(xf) + tracker.penalty(xf)[0]
        C = cons.residual(xf, tracker.tg, tk).reshape(-1)
        return f, C

    def merit(f, C):
        if relaxed is None:
            return f + mu * float(np.abs(C).sum())
        return f + mu * float(np.abs(C[~relaxed]).sum()) + 0.5 * float(np.dot(rho[relaxed] * C[relaxed], C[relaxed]))

    f, C = merit_parts(x, t)
    record = None
    if opts.trace is not None:
        record = []
        opts.trace.append(record)
    recent: list[tuple[float, np.ndarray]] = []   # (f, C) of the last iterates: the non-monotone reference
    tail = opts.exact_compression and opts.exact_when == "always"
    alpha = 0.0
    last = None        # (x, gradient of H + P) at the previous iterate: the secant pair's ends
    pairs: list = []   # the last SECANT_MEMORY (step, gradient change) pairs
    lagged = obj.contact is not None and getattr(obj.contact, "lagged", True)
    done_norms: list[tuple[float, float]] = []   # (|grad L|, max |C|) of the iterates so far
    while True:
        # at an iterate predicted to meet the tolerances (``_likely_converged``) the gradient alone
        # first: the band is assembled only if it did not (the same gradient, bit for bit)
        hess_now = lagged or not _likely_converged(done_norms, alpha)
        ev = obj.evaluate(x, need_hessian=hess_now)
        if lagged:   # the contact's friction lag moved with the evaluation
            f, C = merit_parts(x, t)
            recent.clear()            # earlier merits were of another lag's objective: not comparable
        sec["derivatives"] += ev.seconds["derivatives"]
        sec["assembly"] += ev.seconds["assembly"]
        t0_ = time.perf_counter()
        _, gP = tracker.penalty(x, need_grad=True)
        g = ev.grad + gP if gP is not None else ev.grad
        ATlam = cons.AT @ lam
        r_x = g + ATlam
        if sliding:
            _, d1, d2 = cons.target_points(tracker.tg, t, derivatives=True)
            Bmat = np.zeros((3 * cons.K, cons.K))
            rows = np.arange(3 * cons.K)
            Bmat[rows, rows // 3] = -d1.reshape(-1)               # dC/dt = -c_hat'(t)
            lam3 = lam.reshape(-1, 3)
            r_t = -(lam3 * d1).sum(1)                              # grad_t L = lam . dC/dt
            D = np.maximum(-(lam3 * d2).sum(1), 0.0)                 # d2L/dt2 = -lam . c_hat'', clamped PSD
            t_scale = np.linalg.norm(lam3, axis=1) * np.linalg.norm(d1, axis=1)
        else:
            Bmat = D = r_t = None
        sec["solve"] += time.perf_counter() - t0_
        gnorm = float(np.linalg.norm(r_x))
        Ct = C if relaxed is None else np.where(relaxed, C - lam * reg, C)   # relaxed rows: lam = rho C
        cmax = float(np.abs(Ct).max(initial=0.0))
        info.grad_norm, info.force_scale, info.constraint_norm = gnorm, ev.force_scale + float(np.linalg.norm(ATlam)), cmax
        if not (np.isfinite(gnorm) and np.isfinite(f) and np.isfinite(cmax)):
            info.status = DIVERGED
            break
        t_ok = True if not sliding else bool(np.all(np.abs(r_t) <= opts.rtol * t_scale + opts.atol))
        gtol = opts.atol + opts.rtol * info.force_scale
        done_norms.append((_ratio(gnorm, gtol), _ratio(cmax, opts.ctol)))
        if gnorm <= gtol and cmax <= opts.ctol and t_ok:
            info.status = CONVERGED
            break
        if info.iterations >= opts.max_iterations:
            info.status = MAX_ITERATIONS
            break
        if not hess_now:   # predicted converged and was not: the band at this iterate
            ev_h = obj.evaluate(x, need_hessian=True)
            sec["derivatives"] += ev_h.seconds["derivatives"]
            sec["assembly"] += ev_h.seconds["assembly"]
            ev = ev_h
        t1 = time.perf_counter()
        if opts.exact_compression and not tail:
            tail = cmax <= opts.ctol and alpha == 1.0
        hp = tracker.penalty_hessian(x)
        if hp is not None:
            ev.banded[0] += hp[0]    # the variance penalty's positive curvature (diagonal)
        if last is not None:
            pairs.append((x - last[0], g - last[1]))
            del pairs[:-SECANT_MEMORY]
        last = (x, g)
        fallback = None
        if tail:
            if opts.kkt == "reference":   # its solve takes the band as it is: the sum only where definite
                extra = obj.compression_band(x)
                if extra is not None:
                    ev.banded, _ = obj.exact_where_definite(ev.banded, extra)
            else:   # the factorisation falls back to the clamped band where the sum is not definite
                exact = obj.with_compression(x, ev.banded)
                if exact is not None:
                    fallback, ev.banded = ev.banded, exact

        def solve(r_x, c, r_t=None):
            if sliding and r_t is None:
                r_t = np.zeros(cons.K)
            if opts.kkt == "reference":
                return reference_solve(ev.banded, cons.A, r_x, c, Bmat, D, r_t, reg)
            return kkt.solve(r_x, c, Bmat, D, r_t, reg)

        try:
            if opts.kkt != "reference":
                kkt.factor(ev.banded, fallback)
            if opts.kkt == "reference" or kkt.mode == "exact":
                dx, dt, lam_new = solve(g, C)     # for the new multiplier itself
                shift = None
            else:
                # an iterative KKT solve (tracking.schur=krylov) for the multiplier's change: its
                # right-hand side is the Lagrangian's residual at lam (small near a solution), so its
                # relative tolerance bounds the change's error, not lam's (|g| ~ |A^T lam| >> the residual)
                shift = lam
                dx, dt, lam_new = solve(r_x, C if reg is None else C - reg * lam, r_t if sliding else None)   # r_t = B^T lam
            U = hp[1] if hp is not None and hp[1].shape[1] else None
            signs = None
            curv = None
            if opts.secant and pairs and fallback is None and (obj.contact is None or not getattr(obj.contact, "lagged", True)):
                Sm = np.column_stack([p_[0] for p_ in pairs])
                Ym = np.column_stack([p_[1] for p_ in pairs])
                BS = np.column_stack([band_product(ev.banded, Sm[:, j], getattr(obj, "kernels", None)) for j in range(Sm.shape[1])])
                if U is not None:
                    BS += U @ (U.T @ Sm)
                corr = secant_correction(BS, Sm, Ym)
                curv = (float(Sm[:, -1] @ Ym[:, -1]), float(Sm[:, -1] @ BS[:, -1]))
                if corr is not None:
                    info.secant_updates += 1
                    n_u = 0 if U is None else U.shape[1]
                    signs = np.concatenate([np.ones(n_u), corr[1]])
                    U = corr[0] if U is None else np.column_stack([U, corr[0]])
            if U is not None:
                dx, dt, lam_new = woodbury(solve, U, (dx, dt, lam_new), np.zeros_like(C), signs)
        except np.linalg.LinAlgError:
            # a singular KKT matrix (e.g. two clusters' constraints that coincide): the step fails
            # as a solve, and the Simulator's recovery (substeps) or its failure policy takes over
            sec["solve"] += time.perf_counter() - t1
            info.status = SINGULAR
            break
        if shift is not None:
            lam_new = shift + lam_new
        sec["solve"] += time.perf_counter() - t1
        # l1 merit line search
        mu = max(mu, MU_FACTOR * float(np.abs(lam_new).max(initial=0.0)) + MU_MARGIN)
        phi0 = merit(f, C)
        recent.append((f, C))
        del recent[:-max(1, opts.nonmonotone)]
        phi_ref = max(merit(fi, Ci) for fi, Ci in recent)   # phi0 among them; the current mu for every iterate
        if relaxed is None:
            dphi = float(np.dot(g, dx)) - mu * float(np.abs(C).sum())
        else:   # hard rows: -mu |C|_1 (the step satisfies their linearisation); relaxed: rho C . dC
            dC = cons.A @ dx + (Bmat @ dt if sliding else 0.0)
            dphi = (float(np.dot(g, dx)) - mu * float(np.abs(C[~relaxed]).sum())
                    + float(np.dot(rho[relaxed] * C[relaxed], dC[relaxed])))
        # round-off of phi: that of H (value_noise) plus that of mu |C|_1, whose terms are
        # differences of centre-of-mass coordinates; without the second part a large mu made the
        # search reject steps at the solution and stall (tests: rigid translation, static targets)
        com_scale = float(np.abs(cons.com(x)).sum())
        noise = obj.value_noise + mu * 8.0 * np.finfo(float).eps * com_scale
        alpha, bt = obj.max_step(x, dx), 0   # <= 1: the contact barrier's collision-free bound (CCD)
        while True:
            xa = x + alpha * dx
            ta = t + alpha * dt if sliding else t
            fa, Ca = merit_parts(xa, ta)
            phia = merit(fa, Ca)
            if np.isfinite(phia) and phia <= phi_ref + MERIT_ETA * alpha * min(dphi, 0.0) + noise:
                break
            bt += 1
            if bt > opts.max_backtracks:
                alpha = 0.0
                break
            alpha *= BACKTRACK
        info.backtracks += bt
        info.iterations += 1
        if record is not None:
            record.append({"alpha": alpha, "grad": gnorm, "grad_tol": gtol,
                           "constraint": cmax, "constraint_tol": opts.ctol,
                           "t_residual": float(np.abs(r_t).max(initial=0.0)) if sliding else 0.0,
                           "backtracks": bt, "curvature": curv})
        if alpha == 0.0:
            info.status = LINE_SEARCH_FAILED
            break
        obj.update_tensions(x, alpha * dx)
        x, t = xa, ta
        lam = lam + alpha * (lam_new - lam)
        f, C = fa, Ca
    if info.status == CONVERGED:
        info.tensions = obj.final_tensions(x)
    return x, t, lam, info
