"""Arc-length parameterised Catmull-Rom splines (paper 3.2, "Dynamic Constraint Targets").

A curve through control points P_i at knots s_i (the guide's *rest* arc lengths, so the
parameter t is rest arc length) is the cubic Hermite interpolant with Catmull-Rom tangents
m_i = (P_{i+1} - P_{i-1}) / (s_{i+1} - s_{i-1}) (one-sided at the ends).  It interpolates the
P_i and is C1.  Beyond the ends it continues along the end tangent (C1, linear), so a sliding
target may leave a guide that shrank.  Written in torch; ``eval_with_derivatives`` gives value, first and second t-derivatives in
closed form, tested against ``autograd_derivatives``.
"""

from __future__ import annotations

import torch


def tangents(P: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Catmull-Rom tangents dP/dt at the knots.  P: (..., n, 3), s: (n,) -> (..., n, 3)."""
    m = torch.empty_like(P)
    ds = s[1:] - s[:-1]
    m[..., 0, :] = (P[..., 1, :] - P[..., 0, :]) / ds[0]
    m[..., -1, :] = (P[..., -1, :] - P[..., -2, :]) / ds[-1]
    if P.shape[-2] > 2:
        m[..., 1:-1, :] = (P[..., 2:, :] - P[..., :-2, :]) / (s[2:] - s[:-2]).unsqueeze(-1)
    return m


def evaluate(P: torch.Tensor, s: torch.Tensor, t: torch.Tensor, m: torch.Tensor | None = None) -> torch.Tensor:
    """Curve points at parameters t.

    P: (K, n, 3) control points of K curves sharing the knots s (n,); t: (K,) one parameter
    per curve.  Returns (K, 3)."""
    t = t.to(P.dtype)
    if m is None:
        m = tangents(P, s)
    n = s.shape[0]
    i = torch.clamp(torch.searchsorted(s.detach(), t.detach(), right=True) - 1, 0, n - 2)
    k = torch.arange(P.shape[0])
    s0, s1 = s[i], s[i + 1]
    h = s1 - s0
    u = ((t - s0) / h).unsqueeze(-1)
    p0, p1, m0, m1 = P[k, i], P[k, i + 1], m[k, i], m[k, i + 1]
    h = h.unsqueeze(-1)
    inner = ((2 * u ** 3 - 3 * u ** 2 + 1) * p0 + (u ** 3 - 2 * u ** 2 + u) * h * m0
             + (-2 * u ** 3 + 3 * u ** 2) * p1 + (u ** 3 - u ** 2) * h * m1)
    before = P[k, 0] + (t - s[0]).unsqueeze(-1) * m[k, 0]
    after = P[k, -1] + (t - s[-1]).unsqueeze(-1) * m[k, -1]
    tt = t.unsqueeze(-1)
    return torch.where(tt < s[0], before, torch.where(tt > s[-1], after, inner))


def eval_with_derivatives(P: torch.Tensor, s: torch.Tensor, t: torch.Tensor):
    """(value (K, 3), d/dt (K, 3), d2/dt2 (K, 3)) in closed form (derivatives of the Hermite
    basis; tests check them against ``autograd_derivatives``).  Beyond the ends the curve is
    linear: first derivative the end tangent, second derivative zero."""
    t = t.to(P.dtype)
    m = tangents(P, s)
    n = s.shape[0]
    i = torch.clamp(torch.searchsorted(s, t, right=True) - 1, 0, n - 2)
    k = torch.arange(P.shape[0])
    s0 = s[i]
    h = (s[i + 1] - s0).unsqueeze(-1)
    u = ((t - s0).unsqueeze(-1) / h)
    p0, p1, m0, m1 = P[k, i], P[k, i + 1], m[k, i], m[k, i + 1]
    c = ((2 * u ** 3 - 3 * u ** 2 + 1) * p0 + (u ** 3 - 2 * u ** 2 + u) * h * m0
         + (-2 * u ** 3 + 3 * u ** 2) * p1 + (u ** 3 - u ** 2) * h * m1)
    d1 = ((6 * u ** 2 - 6 * u) * (p0 - p1) / h + (3 * u ** 2 - 4 * u + 1) * m0 + (3 * u ** 2 - 2 * u) * m1)
    d2 = ((12 * u - 6) * (p0 - p1) / h ** 2 + (6 * u - 4) * m0 / h + (6 * u - 2) * m1 / h)
    tt = t.unsqueeze(-1)
    lo, hi = tt < s[0], tt > s[-1]
    c = torch.where(lo, P[k, 0] + (tt - s[0]) * m[k, 0], torch.where(hi, P[k, -1] + (tt - s[-1]) * m[k, -1], c))
    d1 = torch.where(lo, m[k, 0], torch.where(hi, m[k, -1], d1))
    d2 = torch.where(lo | hi, torch.zeros_like(d2), d2)
    return c, d1, d2


def autograd_derivatives(P: torch.Tensor, s: torch.Tensor, t: torch.Tensor):
    """The same three quantities from torch autograd of ``evaluate`` (the reference the closed
    form is tested against; batched over the K curves, which do not share parameters)."""
    t = t.detach().clone().to(P.dtype).requires_grad_(True)

    def dt(y, create_graph):
        out = []
        for j in range(3):
            g = None
            if y.requires_grad:
                (g,) = torch.autograd.grad(y[:, j].sum(), t, create_graph=create_graph, retain_graph=True,
                                           allow_unused=True)
            out.append(torch.zeros_like(t) if g is None else g)
        return torch.stack(out, -1)

    with torch.enable_grad():
        c = evaluate(P.detach(), s, t)
        d1 = dt(c, True)
        d2 = dt(d1, False)
    return c.detach(), d1.detach(), d2.detach()


def rest_arclength(points) -> torch.Tensor:
    """(n,) cumulative arc length of a polyline (n, 3)."""
    P = torch.as_tensor(points, dtype=torch.float64)
    seg = torch.linalg.vector_norm(P[1:] - P[:-1], dim=-1)
    return torch.cat([torch.zeros(1, dtype=P.dtype), torch.cumsum(seg, 0)])
