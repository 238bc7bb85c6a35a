"""The tracking controller: correspondence, constraints, variance control and the KKT
solver for one run, plus the per-step state it needs (targets at the end of the step)."""

from __future__ import annotations

import numpy as np

from hairexp.errors import InputError
from hairexp.tracking.constraints import TrackingConstraints
from hairexp.tracking.correspondence import build_correspondence
from hairexp.tracking.guides import GuideAnimation
from hairexp.tracking.kkt import SchurKKT
from hairexp.tracking.sqp import SQPOptions
from hairexp.tracking.variance import VarianceControl


def _v(x):
    return getattr(x, "value", x)


class TrackingController:
    def __init__(self, scene, guides: GuideAnimation, tcfg, bandwidth: int):
        s = scene.strands
        self.scene, self.guides = scene, guides
        free = ~s.kinematic
        self.corr = build_correspondence(scene.initial_positions(), s.offsets, free, guides.guides(guides.rest), tcfg.points_per_guide,
                                         tcfg.max_guide_distance)
        targets = str(_v(tcfg.targets))
        if targets not in ("static", "sliding"):
            raise InputError(f"unknown targets {targets!r} (static|sliding)", "tracking.targets")
        self.cons = TrackingConstraints(scene, self.corr, guides, sliding=targets == "sliding")
        self.kkt = SchurKKT(s, self.cons, bandwidth)
        self.hair_length = float(np.mean(s.strand_lengths()))
        rest_free = scene.initial_positions()[free].reshape(-1)
        self.variance = VarianceControl(tcfg.variance, self.cons, rest_free)
        self.use_variance = self.variance.active          # k_v = 0: no penalty term at all
        self.opts = SQPOptions(rtol=tcfg.rtol, atol=tcfg.atol, ctol=tcfg.ctol_rel * self.hair_length,
                               max_iterations=tcfg.max_iterations, kkt=str(_v(tcfg.kkt)))
        self.tg = None
        self.time = None
        self._kv = self._vbar = None
        self.m_g_norm = scene.free_weight_norm()

    def targets_at(self, t: float):
        """Target curves at time t; the step's own (built in ``begin``) when t is its time, so
        the metrics and the recording of a step do not rebuild the guide frames."""
        if self.tg is None or t != self.time:
            self.time, self.tg = t, self.cons.targets(t)
        return self.tg

    def begin(self, t: float) -> None:
        """Targets (and variance keys) at the end-of-step time t.  Always rebuilt: a step retried
        as substeps reaches the same t again, and on a dynamic body (scene.body) the guides ride
        with a block whose pose at t depends on the attempt."""
        self.time, self.tg = t, self.cons.targets(t)
        if self.use_variance:
            self._kv, self._vbar = self.variance.at(t)

    def penalty(self, xf: np.ndarray, need_grad: bool = False):
        if not self.use_variance:
            return 0.0, None
        return self.variance.value_grad(xf, self._kv, self._vbar, need_grad)

    def penalty_hessian(self, xf: np.ndarray):
        """(diagonal, U): the PSD model diag + U U^T of the variance penalty's Hessian, or None."""
        if not self.use_variance:
            return None
        return self.variance.hessian_parts(xf, self._kv, self._vbar)

    def initial_duals(self) -> dict:
        return {"t": self.cons.t_rest.copy(), "lambda": np.zeros(3 * self.cons.K)}

    def measure(self, xf: np.ndarray, t: float, duals: dict) -> dict:
        """Tracking metrics of a state (free DOF vector xf) at time t."""
        tg = self.targets_at(t)
        tk = duals.get("t", self.cons.t_rest)
        C = self.cons.residual(xf, tg, tk)
        r = np.linalg.norm(C, axis=1)
        V = self.variance.values(xf)
        if self.use_variance:
            _, vbar = self.variance.at(t)
        else:
            vbar = self.variance.rest
        ratio = np.where(vbar > 0, V / np.where(vbar > 0, vbar, 1.0), np.nan)
        lam = duals.get("lambda", np.zeros(3 * self.cons.K))
        force = float(np.linalg.norm(self.cons.AT @ lam))
        return {"residual_max": float(r.max()), "residual_rms": float(np.sqrt(np.mean(r ** 2))),
                "residual_rel_max": float(r.max() / self.hair_length),
                "variance_ratio_mean": float(np.nanmean(ratio)), "variance_ratios": ratio,
                "constraint_force": force, "constraint_force_rel": force / self.m_g_norm,
                "targets": self.cons.target_points(tg, tk), "com": self.cons.com(xf), "guides": tg.guide_shape}
