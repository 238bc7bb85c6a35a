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
        if not g.requires_grad:  # the energy is linear in x: the Hessian is zero
            return g.detach(), torch.zeros(n, 3 * k, 3 * k, dtype=xs.dtype)
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
    """Base class.  Subclasses set ``name``, ``stencil`` ((n, k) vertex indices) and either
    ``energy_fn`` (a pure function ``(xs, *energy_args()) -> (n,)``) or override ``energy``."""

    name: str = "term"
    stencil: np.ndarray
    energy_fn = None
    #: Optional closed form as a *pure* function ``kernel(xs, *kernel_args(), need_hessian)
    #: -> (grad (n, 3k), PSD Hessian (n, 3k, 3k) or None)``; pure so that ``torch.compile``
    #: sees every input (tensors read from attributes would be baked in as constants).
    kernel = None

    def energy_args(self) -> tuple:
        return ()

    def kernel_args(self) -> tuple:
        return ()

    def energy(self, xs: torch.Tensor) -> torch.Tensor:  # (n, k, 3) -> (n,)
        return type(self).energy_fn(xs, *self.energy_args())

    def total(self, x: torch.Tensor) -> torch.Tensor:
        """Summed energy for full positions x (V, 3)."""
        if "_compiled_total" in self.__dict__:
            return self._guarded("_compiled_total", x, self.stencil_t, *self.energy_args())
        return self.energy(x[self.stencil_t]).sum()

    def closed_form(self, xs: torch.Tensor, need_hessian: bool):
        """Fast (gradient, PSD Hessian) from ``kernel``; None if the term has no closed form."""
        if self.kernel is None:
            return None
        if "_compiled_kernel" in self.__dict__:
            return self._guarded("_compiled_kernel", xs, *self.kernel_args(), need_hessian)
        return type(self).kernel(xs, *self.kernel_args(), need_hessian)

    def compile(self) -> None:
        """Use ``torch.compile`` for the kernel and the summed energy (fused; same numbers to
        round-off).  They are built at the first call, which falls back to eager on failure."""
        if type(self).kernel is not None:
            self._compiled_kernel = torch.compile(type(self).kernel, dynamic=False)
        if type(self).energy_fn is not None:
            efn = type(self).energy_fn

            def summed(x, stencil, *args):
                return efn(x[stencil], *args).sum()

            self._compiled_total = torch.compile(summed, dynamic=False)

    def _guarded(self, attr: str, *args):
        try:
            return self.__dict__[attr](*args)
        except Exception as exc:  # the compiled build failed (no compiler, ...): use eager from now on
            import logging

            logging.getLogger(__name__).warning("torch.compile failed for %s (%s); using eager", self.name, exc)
            del self.__dict__[attr]
            if attr == "_compiled_total":
                return self.total(args[0])
            return self.closed_form(args[0], args[-1])

    def grad_hess(self, xs: torch.Tensor, need_hessian: bool = True, mode: str = "closed_form"):
        """Element gradients (n, 3k) and PSD element Hessians (n, 3k, 3k) or None."""
        if mode == "closed_form":
            out = self.closed_form(xs, need_hessian)
            if out is not None:
                return out
        g, H = autograd_grad_hess(self.energy, xs, need_hessian)
        return g, (project_psd(H) if need_hessian else None)

    @property
    def stencil_t(self) -> torch.Tensor:
        st = getattr(self, "_stencil_t", None)
        if st is None:
            st = torch.tensor(np.asarray(self.stencil), dtype=torch.long)
            self._stencil_t = st
        return st
