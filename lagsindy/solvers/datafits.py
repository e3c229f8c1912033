"""Datafits of the sparse solvers: quadratic forms on Gram statistics (cases I and
III) and the acceleration loss of case II."""

from __future__ import annotations

import math

import torch


# --------------------------------------------------------------------------- datafits
class GramQuadratic:
    r"""Least squares :math:`\frac{1}{2n}\|y - A w\|^2` from its Gram statistics.

    Parameters
    ----------
    gram : Tensor of shape (p, p)
        :math:`A^\top A / n`.
    rhs : Tensor of shape (p,)
        :math:`A^\top y / n`.
    const : float
        :math:`y^\top y / n`, so that :meth:`value` is the true objective.
    equation_shares : Tensor of shape (n_eq, p), optional
        Where the rows of :math:`A` are several equations stacked (one per
        coordinate), the share of each column's norm that each equation holds
        (:math:`\|A_{ik}\| / \|A_k\|`); the staged solve's threshold then judges
        each term within the equations it acts in. ``None``: one equation.
    target_shares : Tensor of shape (n_eq,), optional
        The same shares of the target :math:`y` (with ``equation_shares``).
    """

    def __init__(
        self,
        gram: torch.Tensor,
        rhs: torch.Tensor,
        const: float,
        equation_shares: torch.Tensor | None = None,
        target_shares: torch.Tensor | None = None,
    ):
        self.gram = gram
        self.rhs = rhs
        self.const = float(const)
        self.equation_shares = equation_shares
        self.target_shares = target_shares
        self._lipschitz = None

    @property
    def n_features(self) -> int:
        return self.rhs.shape[0]

    def zeros(self) -> torch.Tensor:
        return torch.zeros_like(self.rhs)

    def value(self, w: torch.Tensor) -> float:
        return float(0.5 * w @ (self.gram @ w) - self.rhs @ w + 0.5 * self.const)

    def gradient(self, w: torch.Tensor) -> torch.Tensor:
        return self.gram @ w - self.rhs

    def lipschitz(self) -> float:
        """Largest eigenvalue of the Gram matrix."""
        if self._lipschitz is None:
            if self.n_features == 0:
                self._lipschitz = 0.0
            else:
                self._lipschitz = float(
                    torch.linalg.eigvalsh(self.gram)[-1].clamp(min=0)
                )
        return self._lipschitz

    def relative_residual(self, w: torch.Tensor) -> float:
        """:math:`\\|y - A w\\|^2 / \\|y\\|^2` (1 for ``w = 0``)."""
        if self.const <= 0:
            return 0.0
        return max(0.0, 2.0 * self.value(w) / self.const)

    def restrict(self, idx) -> GramQuadratic:
        idx = torch.as_tensor(idx, dtype=torch.long, device=self.rhs.device)
        shares = self.equation_shares
        return GramQuadratic(
            self.gram[idx][:, idx],
            self.rhs[idx],
            self.const,
            None if shares is None else shares[:, idx],
            self.target_shares,
        )

    def least_squares(self, w0=None, rtol: float = 1e-13) -> torch.Tensor:
        """Minimum-norm unpenalised minimiser (eigen-decomposition of the Gram).

        ``w0`` is accepted for symmetry with non-convex datafits and ignored.
        """
        if self.n_features == 0:
            return self.rhs.clone()
        evals, evecs = torch.linalg.eigh(self.gram)
        keep = evals > rtol * evals[-1].clamp(min=1e-300)
        inv = torch.where(
            keep, 1.0 / torch.where(keep, evals, torch.ones_like(evals)), 0.0
        )
        return evecs @ (inv * (evecs.T @ self.rhs))


class AccelerationDatafit:
    r"""Case II datafit: error of the accelerations predicted by the Lagrangian.

    .. math::

        f(w) = \frac{1}{2n} \sum_s \| D^{-1} (\ddot q_s -
        \ddot q_{pred,s}(c)) \|^2, \quad
        \ddot q_{pred} = -\Big(\sum_k c_k M_k\Big)^{+} \sum_k c_k (N_k \dot q - O_k),

    with :math:`c = w / s` (column scales ``s``) and :math:`D` the per-coordinate
    RMS of the measured accelerations (paper eqs. 10-11). The prediction does not
    change when :math:`c` is scaled, so the L1 penalty alone would shrink :math:`c`
    to zero; :meth:`project` fixes the gauge :math:`\|w\|_2 = 1`, on which the L1
    norm is smallest for sparse :math:`w`. No global Lipschitz constant exists
    (``lipschitz()`` is ``None``), so solvers use backtracking.

    Parameters
    ----------
    mass : Tensor of shape (n_samples, p, n_dof, n_dof)
        :math:`M_k` per sample.
    bias : Tensor of shape (n_samples, p, n_dof)
        :math:`N_k \dot q - O_k` per sample.
    qdd : Tensor of shape (n_samples, n_dof)
        Measured accelerations.
    scale : Tensor of shape (p,)
        Column scales ``s``.
    """

    def __init__(self, mass, bias, qdd, scale):
        self.mass, self.bias, self.qdd, self.scale = mass, bias, qdd, scale
        rms = torch.sqrt((qdd**2).mean(dim=0))
        self.acc_scale = torch.where(rms > 0, rms, torch.ones_like(rms))
        self.const = float(((qdd / self.acc_scale) ** 2).sum(dim=1).mean())
        # M(c), b(c) as matrix-vector products: (samples * d * d, p), (samples * d, p)
        s, p, d = mass.shape[0], mass.shape[1], mass.shape[2]
        self._m2 = mass.permute(0, 2, 3, 1).reshape(s * d * d, p)
        self._b2 = bias.permute(0, 2, 1).reshape(s * d, p)
        # The last solve: the proximal gradient evaluates the loss at a point, then
        # (once accepted) its gradient, which needs the same solve.
        self._last = None

    @property
    def n_features(self) -> int:
        return self.scale.shape[0]

    def zeros(self):
        return torch.zeros_like(self.scale)

    def lipschitz(self):
        return None

    def project(self, w):
        norm = torch.linalg.vector_norm(w)
        return w / norm if float(norm) > 0 else w

    def _solve(self, w):
        """``a = M(c)^{-1} b(c)`` per sample and ``M(c)``; ``a`` is None if singular."""
        if w.requires_grad:  # differentiated by autograd: no cached values
            return self._solve_at(w)
        if self._last is not None and torch.equal(self._last[0], w):
            return self._last[1]
        out = self._solve_at(w)
        self._last = (w.detach().clone(), out)
        return out

    def _solve_at(self, w):
        s, d = self.qdd.shape
        c = w / self.scale
        mc = (self._m2 @ c).view(s, d, d)
        bc = (self._b2 @ c).view(s, d)
        # A direct solve: a singular M(c) gives non-finite values, which the line
        # search rejects (cheaper than a pseudo-inverse and its SVD gradient).
        if d == 1:
            if bool((mc == 0).any()):
                return None, mc
            return bc / mc[:, :, 0], mc
        out, info = torch.linalg.solve_ex(mc, bc)
        if bool((info != 0).any()):
            return None, mc
        return out, mc

    def predict(self, w):
        a, _ = self._solve(w)
        if a is None:
            return torch.full_like(self.qdd, math.inf)
        return -a

    def _loss(self, w):
        r = (self.qdd - self.predict(w)) / self.acc_scale
        return 0.5 * (r**2).sum(dim=1).mean()

    def value(self, w) -> float:
        v = float(self._loss(w))
        return v if math.isfinite(v) else math.inf

    def gradient(self, w):
        r"""Analytic gradient (adjoint of the solve).

        With :math:`a_s = M_s(c)^{-1} b_s(c)` (the prediction is :math:`-a_s`),
        :math:`\partial a_s / \partial c_k = M_s^{-1} (b_{k,s} - M_{k,s} a_s)`, so
        :math:`\partial f / \partial c_k = \sum_s \lambda_s^\top (b_{k,s} - M_{k,s}
        a_s)` with :math:`\lambda_s = M_s^{-\top} D^{-2} (\ddot q_s + a_s) / n`: two
        matrix-vector products with the stacked term matrices.
        """
        a, mc = self._solve(w)
        if a is None:
            return torch.zeros_like(w)
        s, d = self.qdd.shape
        g_a = (self.qdd + a) / (self.acc_scale**2 * s)
        if d == 1:
            lam = g_a / mc[:, :, 0]
        else:
            lam = torch.linalg.solve_ex(mc.transpose(1, 2), g_a)[0]
        outer = (lam[:, :, None] * a[:, None, :]).reshape(-1)
        grad_c = self._b2.T @ lam.reshape(-1) - self._m2.T @ outer
        grad = grad_c / self.scale
        return torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)

    def relative_residual(self, w) -> float:
        if self.const <= 0:
            return 0.0
        return 2.0 * self.value(w) / self.const

    def restrict(self, idx):
        idx = torch.as_tensor(idx, dtype=torch.long, device=self.scale.device)
        return AccelerationDatafit(
            self.mass[:, idx], self.bias[:, idx], self.qdd, self.scale[idx]
        )

    def least_squares(self, w0=None, max_iter: int = 2000, tol: float = 1e-10):
        """Unpenalised minimiser from ``w0`` (local: the problem is not convex)."""
        from .fista import proximal_gradient
        from .penalties import L1

        res = proximal_gradient(self, L1(0.0), w0, max_iter=max_iter, tol=tol)
        return res.coef
