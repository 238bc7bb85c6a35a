"""One small interface for every energy term, with derivatives from torch autograd.

A term is a sum of element energies over a stencil of ``k`` vertices:
``E(x) = sum_e  energy(x[stencil[e]])``.  ``energy`` is the single source of truth; the
gradient and Hessian come from autograd, batched over elements (batched reverse-over-reverse:
the gradient of the summed energy with ``create_graph=True`` gives every element's gradient
at once because elements do not share inputs, then one backward pass per local coordinate
gives the element Hessians row by row).  A term may add a closed form for speed
(``closed_form``); tests check every closed form against this autograd path.

The Hessian handed to Newton must be positive semi-definite.  The autograd path projects each
element Hessian onto the PSD cone by clamping its eigenvalues (``torch.linalg.eigh``); closed
forms use cheaper exact clamps (springs) or Gauss-Newton forms (bending).
"""

from __future__ import annotations

import numpy as np
import torch

DTYPE = torch.float64


def autograd_grad_hess(energy_fn, xs: torch.Tensor, need_hessian: bool = True):
    """Batched element gradients (n, 3k) and exact Hessians (n, 3k, 3k) of ``energy_fn``.

    ``xs``: (n, k, 3) element vertex positions.  ``energy_fn(xs) -> (n,)``.
    """
    n, k, _ = xs.shape
    x = xs.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        e = energy_fn(x)
        (g,) = torch.autograd.grad(e.sum(), x, create_graph=need_hessian)
        g = g.reshape(n, 3 * k)
        if not need_hessian:
            return g.detach(), None
        rows = []
        for c in range(3 * k):
            (hc,) = torch.autograd.grad(g[:, c].sum(), x, retain_graph=c < 3 * k - 1, allow_unused=True)
            rows.append(torch.zeros(n, 3 * k, dtype=xs.dtype) if hc is None else hc.reshape(n, 3 * k))
    return g.detach(), torch.stack(rows, dim=1).detach()


def project_psd(H: torch.Tensor, floor: float = 0.0) -> torch.Tensor:
    """Clamp the eigenvalues of a batch of symmetric matrices at ``floor``."""
    Hs = 0.5 * (H + H.transpose(-1, -2))
    w, Q = torch.linalg.eigh(Hs)
    return (Q * w.clamp_min(floor).unsqueeze(-2)) @ Q.transpose(-1, -2)


class Term:
    """Base class.  Subclasses set ``name``, ``stencil`` ((n, k) vertex indices) and ``energy``."""

    name: str = "term"
    stencil: np.ndarray

    def energy(self, xs: torch.Tensor) -> torch.Tensor:  # (n, k, 3) -> (n,)
        raise NotImplementedError

    def closed_form(self, xs: torch.Tensor, need_hessian: bool):
        """Optional fast (gradient, PSD Hessian); return None to fall back to autograd."""
        return None

    def grad_hess(self, xs: torch.Tensor, need_hessian: bool = True, mode: str = "closed_form"):
        """Element gradients (n, 3k) and PSD element Hessians (n, 3k, 3k) or None."""
        if mode == "closed_form":
            out = self.closed_form(xs, need_hessian)
            if out is not None:
                return out
        g, H = autograd_grad_hess(self.energy, xs, need_hessian)
        return g, (project_psd(H) if need_hessian else None)

    def total(self, x: torch.Tensor) -> torch.Tensor:
        """Summed energy for full positions x (V, 3)."""
        return self.energy(x[self.stencil_t]).sum()

    @property
    def stencil_t(self) -> torch.Tensor:
        st = getattr(self, "_stencil_t", None)
        if st is None:
            st = torch.as_tensor(self.stencil, dtype=torch.long)
            self._stencil_t = st
        return st
