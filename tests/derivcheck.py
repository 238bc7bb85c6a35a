"""One derivative check for every energy term: autograd against central finite differences.

``check_term(term, xs)`` compares, element by element,

* the autograd gradient of ``term.energy`` (the gradient of the energy summed over the batch,
  which is every element's own gradient since elements do not share inputs) with central
  differences of ``term.energy``, relative to the larger of the gradient and the force an
  element-sized displacement produces (Hessian scale x element size: the gradient's own scale
  is round-off where it vanishes, e.g. at a straight strand);
* the exact Hessian from ``hairexp.physics.terms.autograd_grad_hess`` with central differences
  of that autograd gradient.

Elements are independent, so one perturbation of local coordinate ``c`` in *all* elements at
once gives column ``c`` of every element's derivative: 2 * 3k energy evaluations per check.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hairexp.physics.terms import autograd_grad_hess

#: Step of the central differences, relative to the element size (error O(h^2) + O(eps/h)).
FD_STEP = 1e-6
#: Agreement required, relative to the largest entry of the compared derivative.
GRAD_RTOL = 1e-6
HESS_RTOL = 1e-5


@dataclass
class DerivReport:
    grad_err: float      # max |autograd - FD| over all elements and coordinates
    grad_scale: float    # max |FD gradient|
    hess_err: float | None
    hess_scale: float | None
    grad: torch.Tensor   # (n, 3k) autograd gradient
    hess: torch.Tensor | None  # (n, 3k, 3k) autograd exact Hessian


def _step(xs: torch.Tensor) -> float:
    size = float((xs - xs.mean(dim=1, keepdim=True)).abs().max())
    return FD_STEP * max(size, 1e-3)


def fd_gradient(fn, xs: torch.Tensor, h: float | None = None) -> torch.Tensor:
    """Central differences of a per-element function ``fn: (n, k, 3) -> (n, ...)``, returned
    as (n, ..., 3k): derivative of each output entry with respect to each local coordinate."""
    n, k, _ = xs.shape
    h = _step(xs) if h is None else h
    cols = []
    for c in range(3 * k):
        d = torch.zeros(n, 3 * k, dtype=xs.dtype)
        d[:, c] = h
        d = d.reshape(n, k, 3)
        with torch.no_grad():
            cols.append((fn(xs + d) - fn(xs - d)) / (2.0 * h))
    return torch.stack(cols, dim=-1)


def check_term(term, xs: torch.Tensor, hessian: bool = True, grad_rtol: float = GRAD_RTOL,
               hess_rtol: float = HESS_RTOL) -> DerivReport:
    """Assert that ``term``'s autograd gradient and exact Hessian match finite differences at
    element positions ``xs`` (n, k, 3), float64.  Returns the measured errors."""
    assert xs.dtype == torch.float64
    n, k, _ = xs.shape
    g, H = autograd_grad_hess(term.energy, xs, need_hessian=hessian)
    assert g.shape == (n, 3 * k)
    assert torch.isfinite(g).all(), "non-finite autograd gradient"
    hess_err = hess_scale = None
    force_floor = 0.0
    if hessian:
        assert H.shape == (n, 3 * k, 3 * k)
        assert torch.isfinite(H).all(), f"{term.name}: non-finite autograd Hessian"

        def grad_fn(ys):
            return autograd_grad_hess(term.energy, ys, need_hessian=False)[0]

        H_fd = fd_gradient(grad_fn, xs)  # (n, 3k, 3k): [e, row, column]
        hess_scale = float(H_fd.abs().max())
        hess_err = float((H - H_fd).abs().max())
        assert hess_err <= hess_rtol * max(hess_scale, 1e-300), (
            f"{term.name}: Hessian differs from finite differences by {hess_err:.3e} (scale {hess_scale:.3e})")
        sym = float((H - H.transpose(1, 2)).abs().max())
        assert sym <= 1e-10 * max(hess_scale, 1e-300), f"{term.name}: autograd Hessian not symmetric ({sym:.3e})"
        # the force an element-sized displacement produces: the gradient's natural scale where
        # the gradient itself vanishes (e.g. a straight strand under bending)
        force_floor = hess_scale * float((xs - xs.mean(dim=1, keepdim=True)).abs().max())
    g_fd = fd_gradient(term.energy, xs)  # (n, 3k)
    grad_scale = float(g_fd.abs().max())
    grad_err = float((g - g_fd).abs().max())
    assert grad_err <= grad_rtol * max(grad_scale, force_floor, 1e-300), (
        f"{term.name}: gradient differs from finite differences by {grad_err:.3e} "
        f"(scale {grad_scale:.3e}, force floor {force_floor:.3e})")
    return DerivReport(grad_err, grad_scale, hess_err, hess_scale, g, H)
