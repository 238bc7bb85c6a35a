"""The tracking controller (paper 3): correspondence (3.1), constraints with sliding targets
(3.2), variance control (3.3) and the SQP on the KKT system (3.4, eqs. 6-8) for one run, plus
the per-step state it needs (targets at the end of the step).  Its iterates, the sliding
parameters t and the multipliers lambda, travel in ``State.control`` (``TrackingIterates``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg

from hairexp.errors import InputError, check_switches, choice_name, integer, number
from hairexp.control.tracking.constraints import TrackingConstraints
from hairexp.control.tracking.correspondence import build_correspondence, check_correspondence_options
from hairexp.control.tracking.kkt import KRYLOV_TOL, SCHUR_MODES, SchurKKT
from hairexp.control.tracking.sqp import SQPOptions, sqp_solve
from hairexp.control.tracking.variance import VarianceControl, check_variance_config
from hairexp.guides.animation import GuideAnimation
from hairexp.physics.controller import Controller, scaled_iterations
from hairexp.physics.simulator import MAX_ATOL, MAX_ITERATION_BUDGET


#: relative to the hair length: the constraints are restored after the collision stage where a
#: cluster is off its target by more than this (``restore``); 1e-8 L is 3 nm on a 30 cm wisp.  At
#: the SQP's own ctol (1e-9 L) the rounds chased what the strain limiter and the contacts undo:
#: goaling's restores took a third of its stepping time, 40 ms each
RESTORE_TOL = 1e-8
#: ``restore``: a cluster moves only its unpinned vertices while they carry at least this share of
#: its centre's mass weight (else all of its vertices move)
RESTORE_MIN_SHARE = 0.25
#: ``restore_unmet``: a cluster still this far off target (a fraction of the hair length) after the
#: restore's last round is reported relaxed (issue 14's residual bound)
RESTORE_REPORT_TOL = 1e-6


#: ``tracking.krylov_max`` at most this: a KKT solve's GMRES keeps krylov_max basis rows as long
#: as the hair's vertex coordinates (Celia: 188 kB a row); the default is 16
MAX_KRYLOV = 1000
#: tracking.points_per_guide at most: beyond, most clusters are empty (a warning each) and the
#: correspondence's (vertices, points) distance table grows without bound (1e7 points: 14 GB for 60 vertices)
MAX_POINTS_PER_GUIDE = 256
#: the tracking settings' choices (hairexp/app/config.py's Enums, which a test compares) and switches
TRACKING_CHOICES = {"targets": ("static", "sliding"), "kkt": ("schur", "reference"), "schur": SCHUR_MODES}
TRACKING_FLAGS = ("exact_compression", "secant", "elastic", "restore")


def check_tracking_config(t) -> None:
    """The tracking settings (``tracking.*``: hairexp/app/config.py TrackingConfig, or any object
    with its attributes) an SQP can run with, or an InputError naming the key: checked by the
    config's validation and by ``TrackingController`` itself, so that the Python API refuses what
    the command line does (a dataclass config took ``kkt="bogus"`` as the Schur solve and
    ``elastic="no"`` as true; probe of issue 16).  Optional attributes the object lacks are left
    out (their defaults apply)."""
    if isinstance(t, (dict, str, bytes)) or not hasattr(t, "rtol"):
        raise InputError(f"must be a tracking config (hairexp.app.config.TrackingConfig, or an object with its "
                         f"attributes: targets, assignment, points_per_guide, rtol, ...), got {type(t).__name__}",
                         "tracking")
    check_switches(t, "tracking", TRACKING_CHOICES, TRACKING_FLAGS)
    rtol = number(t.rtol, "tracking.rtol", lo=0, hi=1, hi_open=True)   # >= 1 accepts the first iterate (round 14)
    atol = number(t.atol, "tracking.atol", lo=0, hi=MAX_ATOL)
    if rtol == 0 and atol == 0:
        raise InputError("tracking.rtol and tracking.atol are both 0: no step can converge; give one > 0",
                         "tracking.rtol")
    number(t.ctol_rel, "tracking.ctol_rel", lo=0, hi=0.1, lo_open=True)   # of the hair length: 1e300 met nothing
    if integer(t.max_iterations, "tracking.max_iterations", 1) > MAX_ITERATION_BUDGET:
        raise InputError(f"must be at most {MAX_ITERATION_BUDGET} (an SQP solve takes 2-60 iterations; one that has "
                         f"not converged in {MAX_ITERATION_BUDGET} will not), got {t.max_iterations}",
                         "tracking.max_iterations")
    if integer(getattr(t, "nonmonotone", 1), "tracking.nonmonotone", 1) > MAX_ITERATION_BUDGET:   # a window of past merits
        raise InputError(f"must be <= {MAX_ITERATION_BUDGET}, got {t.nonmonotone}", "tracking.nonmonotone")
    number(getattr(t, "krylov_tol", KRYLOV_TOL), "tracking.krylov_tol", lo=0, hi=1e-2, lo_open=True)   # relative residual of each KKT solve
    if integer(getattr(t, "krylov_max", 1), "tracking.krylov_max", 1) > MAX_KRYLOV:   # 1e9: a 536 GiB basis (probe, round 14)
        raise InputError(f"must be <= {MAX_KRYLOV} (GMRES iterations of one KKT solve before the Schur complement is "
                         f"rebuilt; each keeps a basis row of every hair vertex), got {t.krylov_max}", "tracking.krylov_max")
    number(t.max_guide_distance, "tracking.max_guide_distance", lo=0)
    number(getattr(t, "elastic_stiffness", 1e3), "tracking.elastic_stiffness", lo=0, hi=1e9, lo_open=True)
    number(t.blend_width, "tracking.blend_width", lo=0, hi=10.0, lo_open=True)   # m; 1e300 overflowed (round 14)
    n = t.points_per_guide   # >= 1: hairexp/control/tracking/correspondence.py, checked here too
    check_correspondence_options(n, choice_name(t.point_placement), choice_name(t.assignment))
    check_variance_config(t.variance)   # hairexp/control/tracking/variance.py
    if isinstance(n, int) and n > MAX_POINTS_PER_GUIDE:
        raise InputError(f"must be <= {MAX_POINTS_PER_GUIDE} (the paper uses 8; each point is a cluster with 3 "
                         "constraints per guide, and the correspondence holds a vertices x points distance table), "
                         f"got {n}", "tracking.points_per_guide")
    for i, p in enumerate(t.variance.points):
        if integer(p, f"tracking.variance.points[{i}]", 0) >= max(int(n), 1):
            raise InputError(f"is {p}, but tracking points are numbered 0..{int(n) - 1} along each guide "
                             f"(tracking.points_per_guide={n})", f"tracking.variance.points[{i}]")
        if p in list(t.variance.points)[:i]:   # accepted without a word (probe of issue 12, round 13)
            raise InputError(f"is {p}, given twice (at [{list(t.variance.points).index(p)}] too): list each tracking "
                             "point once", f"tracking.variance.points[{i}]")


@dataclass
class TrackingIterates:
    """The SQP's iterates carried from step to step (warm start): t (K,) the targets' spline
    parameters (paper 3.2; fixed at rest for static targets) and lam (3K,) the multipliers."""

    t: np.ndarray
    lam: np.ndarray
    # (K,) bool: clusters relaxed in this step: by the elastic mode (barrier contact), or left off
    # target by the post-solve stage's restore (``restore_unmet``)
    relaxed: np.ndarray | None = None


def check_independent(cons, corr) -> None:
    """InputError unless the clusters' centre-of-mass constraints are linearly independent: with
    fewer hairs than clusters need (one strand under three guides' clusters, say) two clusters'
    centres are the same combination of the same vertices, the KKT matrix is singular and no step
    can converge (it failed every step as "singular"; probe of issue 12).  A = W (x) I3, so W W^T
    (K x K) is tested."""
    K = cons.K
    if K < 2:
        return
    W = cons.A[0::3]                                   # (K, N) rows of the x coordinate: W with every 3rd column
    G = (W @ W.T).toarray()
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    C = G / d[:, None] / d[None, :]                    # cosines between the clusters' weight vectors
    ev = np.linalg.eigvalsh(C)
    if ev[0] > 1e-9 * ev[-1]:
        return
    iu = np.triu_indices(K, 1)
    j = int(np.argmax(C[iu]))
    a, b = int(iu[0][j]), int(iu[1][j])
    P = int(corr.cluster_point.max()) + 1
    name = lambda k: f"guide {int(corr.cluster_guide[k])} point {int(corr.cluster_point[k])}"   # noqa: E731
    raise InputError(f"the clusters' centres of mass are not independent (clusters {name(a)} and {name(b)} are made "
                     f"of the same hair, cosine {C[a, b]:.6f}): with {int(np.unique(cons.scene.strands.strand_of_vertex).size)} "
                     f"strand(s) for {K} clusters ({P} points per guide) no step can meet them all; use more strands "
                     "(scene.n_strands), fewer guides or tracking points (tracking.points_per_guide), or "
                     "tracking.assignment=hard", "tracking")


class TrackingController(Controller):
    name = "tracking"

    def __init__(self, scene, guides: GuideAnimation, tcfg):
        check_tracking_config(tcfg)
        s = scene.strands
        self.scene, self.guides, self.tcfg = scene, guides, tcfg
        free = ~s.kinematic
        self.assignment = choice_name(tcfg.assignment)
        self.corr = build_correspondence(scene.initial_positions(), s.offsets, free, guides.guides(guides.rest), tcfg.points_per_guide,
                                         tcfg.max_guide_distance, self.assignment,
                                         float(tcfg.blend_width), choice_name(tcfg.point_placement), s.masses)
        targets = choice_name(tcfg.targets)
        self.cons = TrackingConstraints(scene, self.corr, guides, sliding=targets == "sliding")
        check_independent(self.cons, self.corr)
        self.kkt = None   # bound to the objective's band (``bind``)
        self.hair_length = float(np.mean(s.strand_lengths()))
        rest_free = scene.initial_positions()[free].reshape(-1)
        self.variance = VarianceControl(tcfg.variance, self.cons, rest_free)
        self.use_variance = self.variance.active          # k_v = 0: no penalty term at all
        self.opts = SQPOptions(rtol=tcfg.rtol, atol=tcfg.atol, ctol=tcfg.ctol_rel * self.hair_length,
                               max_iterations=tcfg.max_iterations, kkt=choice_name(tcfg.kkt),
                               nonmonotone=int(getattr(tcfg, "nonmonotone", 5)),
                               exact_compression=bool(getattr(tcfg, "exact_compression", False)),
                               secant=bool(getattr(tcfg, "secant", True)))
        # elastic mode (paper 3.4 has none): when a step's SQP fails against an obstacle, the
        # clusters it could not reach are relaxed to penalties rho/2 |C_k|^2 and the step is solved
        # again; rho_k = elastic_stiffness x cluster mass / dt^2 (N/m)
        self.elastic = bool(getattr(tcfg, "elastic", True))
        self.elastic_stiffness = float(getattr(tcfg, "elastic_stiffness", 1e3))
        free_mass = float(s.masses[free].sum())
        self.cluster_mass = free_mass / max(self.cons.K, 1)
        self.tg = None
        self.time = None
        # tracking.restore: the constraints restored after the post-solve collision stage (``restore``)
        self.restore_constraints = bool(getattr(tcfg, "restore", True))
        # (M^-1 of the free DOFs, Cholesky of A M^-1 A^T or None, |A|'s row sums): A is constant
        self._restore_factor = None
        self._kv = self._vbar = None
        self.m_g_norm = scene.free_weight_norm()

    # -- Controller -------------------------------------------------------------------------
    def bind(self, sim) -> None:
        t = self.tcfg
        self.kkt = SchurKKT(self.scene.strands, self.cons, sim.objective.assembler.bandwidth, sim.objective.kernels,
                            schur=choice_name(getattr(t, "schur", "krylov")), krylov_tol=float(getattr(t, "krylov_tol", KRYLOV_TOL)),
                            krylov_max=int(getattr(t, "krylov_max", 16)))

    def initial_control(self) -> TrackingIterates:
        return TrackingIterates(self.cons.t_rest.copy(), np.zeros(3 * self.cons.K))

    def begin(self, t: float, motion=None) -> None:
        """Targets (and variance keys) at the end-of-step time t.  Always rebuilt: a step retried
        as substeps reaches the same t again, and on a dynamic body (scene.body) the guides ride
        with a block whose pose at t depends on the attempt."""
        self.guides.check_time(t, "Simulator.step: state.time")
        self.time, self.tg = t, self.cons.targets(t, motion)
        if self.use_variance:
            self._kv, self._vbar = self.variance.at(t)

    def check_control(self, control, where: str) -> None:
        """The SQP's warm start: TrackingIterates with t (K,) and lam (3K,) of these clusters (a free
        run's state, control None, was an AttributeError in the SQP; another run's a matmul
        mismatch; probe of issue 16)."""
        K = self.cons.K
        if not isinstance(control, TrackingIterates):
            raise InputError(f"must be the tracking controller's iterates (TrackingIterates: a tracked run's state, or "
                             f"Simulator.initial_state()), got {type(control).__name__}", where)
        for name, n in (("t", K), ("lam", 3 * K)):
            a = getattr(control, name)
            try:
                finite = np.shape(a) == (n,) and bool(np.isfinite(np.asarray(a, dtype=np.float64)).all())
            except (TypeError, ValueError):
                finite = False
            if not finite:
                raise InputError(f"{name} must be {n} finite numbers for this run's {K} clusters, got shape "
                                 f"{np.shape(a)}: iterates of another run?", where)

    def solve(self, sim, state, dt, t_next, motion):
        obj = sim.objective
        it = state.control
        x0 = obj.initial_guess()
        opts = scaled_iterations(self.opts, sim)
        xf, tk, lam, info = sqp_solve(obj, self, x0, it.t, it.lam, opts)
        relaxed = None
        if not info.converged and self.elastic and getattr(sim, "contact", None) is not None and np.isfinite(xf).all():
            relaxed = self.unreachable(xf, tk, lam)
            rho = np.repeat(np.where(relaxed, self.elastic_stiffness * self.cluster_mass / dt ** 2, 0.0), 3)
            xe, te, le, ie = sqp_solve(obj, self, x0, it.t, it.lam, opts, rho=rho)
            if ie.converged:
                first = info.iterations
                xf, tk, lam, info = xe, te, le, ie
                info.iterations += first   # both attempts count
            else:
                relaxed = None
        return obj.positions(xf).numpy(), TrackingIterates(tk, lam, relaxed), info

    def restore(self, sim, x: np.ndarray, control, pinned: np.ndarray | None = None) -> np.ndarray | None:
        """Post-stabilisation of the constraints (Cline and Pai 2003) after the post-solve
        collision stage moved vertices: the smallest mass-weighted move back onto C = 0 (eq. 3;
        C = A x_f - c_hat is linear in x with the constant COM Jacobian A, so one projection
        dx_f = -W A^T (A W A^T)^-1 C restores it exactly, W = M^-1), the targets' parameters t kept
        at the solve's.  ``pinned``: (V,) bool, vertices the move leaves in place (W's rows zero:
        the ones a collider or the strain limiter placed, which the move would push back into
        them); a cluster keeping less than RESTORE_MIN_SHARE of its mass weight free of pins
        moves all its vertices (no large move of a few).  Clusters the elastic mode relaxed keep
        their centres of mass.  None when every constraint holds within RESTORE_TOL of the hair
        length (or A W A^T is singular)."""
        if not self.restore_constraints or control is None or self.tg is None:
            return None
        free = sim.objective.free_vertices
        C = self.cons.residual(x[free].reshape(-1), self.tg, control.t)
        if control.relaxed is not None:
            C[control.relaxed] = 0.0
        if np.abs(C).max(initial=0.0) <= RESTORE_TOL * self.hair_length:
            return None
        A = self.cons.A
        if self._restore_factor is None:
            minv = np.repeat(1.0 / self.scene.strands.masses[free], 3)
            self._restore_factor = (minv, self._restore_cholesky(minv), np.asarray(abs(A).sum(axis=1)).ravel())
        minv, fac, row_weight = self._restore_factor
        if pinned is not None and pinned[free].any():
            held = np.repeat(pinned[free], 3)
            share = A @ (~held).astype(np.float64)   # (3K,) each row's weight on unpinned DOFs
            low = np.abs(share) < RESTORE_MIN_SHARE * row_weight
            if low.any():   # those clusters' DOFs move after all
                held &= np.asarray(abs(A[low]).sum(axis=0)).ravel() == 0
            w = np.where(held, 0.0, minv)
            fac_w = self._restore_cholesky(w)
            if fac_w is not None:   # else the unpinned move
                minv, fac = w, fac_w
        if fac is None:
            return None
        y = scipy.linalg.cho_solve(fac, C.reshape(-1))
        out = x.copy()
        out[free] -= (minv * (self.cons.AT @ y)).reshape(-1, 3)
        return out

    def _restore_cholesky(self, w: np.ndarray):
        """cho_factor of A W A^T (W = diag(w), inverse masses of the DOFs that may move), or None
        where it is singular."""
        try:
            S = (self.cons.A.multiply(w[None, :]).tocsr() @ self.cons.AT).toarray()
            return scipy.linalg.cho_factor(np.asarray(S))
        except np.linalg.LinAlgError:
            return None

    def restore_unmet(self, sim, x: np.ndarray, control):
        """After the restore's last round (``Simulator._restore``): the iterates with the clusters
        still more than RESTORE_REPORT_TOL of the hair length off target marked relaxed, where the
        colliders and the strain limiter won against the constraints (a target the hair cannot
        reach without entering a collider or stretching past the limit).  The metrics then report
        them (``relaxed_clusters``, ``relaxed_slack_rel_max``) instead of counting them in the
        residual of the constraints that hold."""
        if control is None or self.tg is None:
            return control
        free = sim.objective.free_vertices
        C = self.cons.residual(x[free].reshape(-1), self.tg, control.t)
        off = np.linalg.norm(C, axis=1) > RESTORE_REPORT_TOL * self.hair_length
        if not off.any():
            return control
        return replace(control, relaxed=off if control.relaxed is None else control.relaxed | off)

    def unreachable(self, xf: np.ndarray, tk: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(K,) bool: the clusters a failed SQP left off target (|C_k| > ctol), or if none, the
        one pulling hardest (largest |lam_k|): the ones the elastic mode relaxes."""
        C = self.cons.residual(xf, self.tg, tk)
        off = np.linalg.norm(C, axis=1) > self.opts.ctol
        if not off.any():
            off[int(np.argmax(np.linalg.norm(lam.reshape(-1, 3), axis=1)))] = True
        return off

    def observe(self, sim, state, motion) -> dict:
        return self.measure(sim.free_dofs(state.x), state.time, state.control, motion)

    def cluster_of_vertex(self) -> np.ndarray:
        return self.corr.cluster_of_vertex

    def cluster_weights(self) -> np.ndarray | None:
        """Soft assignment: (V, K) each vertex's share in each cluster (rows of clustered free
        vertices sum to one; root vertices are all zero); hard: None (``cluster_of_vertex`` says it)."""
        if self.assignment == "hard":
            return None
        c = self.corr
        W = np.zeros((len(c.cluster_of_vertex), c.n_clusters))
        np.add.at(W, (c.member_vertex, c.member_cluster), c.member_weight)
        return W

    # -- used by the SQP ------------------------------------------------------------------
    def targets_at(self, t: float, motion=None):
        """Target curves at time t; the step's own (built in ``begin``) when t is its time, so
        the metrics and the recording of a step do not rebuild the guide frames."""
        if self.tg is None or t != self.time:
            self.time, self.tg = t, self.cons.targets(t, motion)
        return self.tg

    def penalty(self, xf: np.ndarray, need_grad: bool = False):
        if not self.use_variance:
            return 0.0, None
        return self.variance.value_grad(xf, self._kv, self._vbar, need_grad)

    def penalty_hessian(self, xf: np.ndarray):
        """(diagonal, U): the PSD model diag + U U^T of the variance penalty's Hessian, or None."""
        if not self.use_variance:
            return None
        return self.variance.hessian_parts(xf, self._kv, self._vbar)

    def measure(self, xf: np.ndarray, t: float, it: TrackingIterates | None = None, motion=None) -> dict:
        """Tracking metrics of a state (free DOF vector xf, iterates ``it``) at time t."""
        tg = self.targets_at(t, motion)
        tk = self.cons.t_rest if it is None else it.t
        C = self.cons.residual(xf, tg, tk)
        r = np.linalg.norm(C, axis=1)
        V = self.variance.values(xf)
        if self.use_variance:
            _, vbar = self.variance.at(t)
        else:
            vbar = self.variance.rest
        ratio = np.where(vbar > 0, V / np.where(vbar > 0, vbar, 1.0), np.nan)
        lam = np.zeros(3 * self.cons.K) if it is None else it.lam
        force = float(np.linalg.norm(self.cons.AT @ lam))
        rel = None if it is None else it.relaxed
        hard = np.ones(len(r), bool) if rel is None else ~rel
        slack = 0.0 if rel is None or not rel.any() else float(r[rel].max() / self.hair_length)
        return {"residual_max": float(r[hard].max(initial=0.0)), "residual_rms": float(np.sqrt(np.mean(r[hard] ** 2))),
                "residual_rel_max": float(r[hard].max(initial=0.0) / self.hair_length),
                "relaxed_clusters": int(0 if rel is None else rel.sum()), "relaxed_slack_rel_max": slack,
                # NaN when no cluster has a target spread (target_scale 0): without numpy's empty-slice warning
                "variance_ratio_mean": float(np.nanmean(ratio)) if np.isfinite(ratio).any() else float("nan"),
                "variance_ratios": ratio,
                "constraint_force": force, "constraint_force_rel": force / self.m_g_norm,
                "targets": self.cons.target_points(tg, tk), "com": self.cons.com(xf), "guides": tg.guide_shape}
