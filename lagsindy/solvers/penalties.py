"""Penalties of the sparse solvers: the weighted (optionally non-negative) L1."""

from __future__ import annotations

import torch


# --------------------------------------------------------------------------- penalty
class L1:
    r"""Weighted L1 penalty :math:`\lambda \sum_k \omega_k |w_k|`.

    Parameters
    ----------
    lam : float
        Penalty strength (the paper's :math:`\lambda`).
    weights : Tensor of shape (p,), optional
        Per-coefficient weights; 0 leaves a coefficient unpenalised (known terms).
    """

    def __init__(
        self,
        lam: float,
        weights: torch.Tensor | None = None,
        nonneg: torch.Tensor | None = None,
    ):
        self.lam = float(lam)
        self.weights = weights
        self.nonneg = nonneg

    def _w(self, like):
        return torch.ones_like(like) if self.weights is None else self.weights

    def value(self, w):
        return float(self.lam * (self._w(w) * w.abs()).sum())

    def prox(self, w, step):
        thresh = step * self.lam * self._w(w)
        out = torch.sign(w) * torch.clamp(w.abs() - thresh, min=0.0)
        if self.nonneg is not None:
            # Projection onto w_k >= 0 (prox of the L1 term plus the indicator).
            out = torch.where(self.nonneg, torch.clamp(out, min=0.0), out)
        return out

    def subdiff_distance(self, w, grad):
        """Largest distance of ``-grad`` to the subdifferential (the KKT violation)."""
        lw = self.lam * self._w(w)
        nonzero = w != 0
        at_zero = torch.clamp(grad.abs() - lw, min=0.0)
        if self.nonneg is not None:
            # at w_k = 0 with w_k >= 0 imposed, any grad_k >= -lw_k is optimal
            at_zero = torch.where(
                self.nonneg, torch.clamp(-grad - lw, min=0.0), at_zero
            )
        dist = torch.where(nonzero, (grad + lw * torch.sign(w)).abs(), at_zero)
        return float(dist.max()) if dist.numel() else 0.0

    def restrict(self, idx):
        if self.weights is None and self.nonneg is None:
            return L1(self.lam)
        like = self.weights if self.weights is not None else self.nonneg
        idx = torch.as_tensor(idx, dtype=torch.long, device=like.device)
        return L1(
            self.lam,
            None if self.weights is None else self.weights[idx],
            None if self.nonneg is None else self.nonneg[idx],
        )
