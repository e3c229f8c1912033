r"""Euler-Lagrange regression tensors by torch automatic differentiation.

For a library of candidate functions :math:`\phi_k(q, \dot q)` the Euler-Lagrange
operator applied to each candidate is, per sample (paper eqs. 5-8),

.. math::

    \Theta_{:, k} = M_k \ddot q + N_k \dot q - O_k, \quad
    M_k = \nabla_{\dot q}^\top \nabla_{\dot q} \phi_k, \;
    N_k = \nabla_q^\top \nabla_{\dot q} \phi_k, \;
    O_k = \nabla_q \phi_k,

so that a Lagrangian :math:`L = \sum_k c_k \phi_k` has generalized forces
:math:`\tau = \Theta c`. Derivatives come from ``torch.func`` (forward mode, vmapped
over samples); :math:`M_k \ddot q + N_k \dot q` is computed as one Jacobian-vector
product of :math:`\nabla_{\dot q}\phi_k` along :math:`(\dot q, \ddot q)`, which avoids
forming the Hessians when only :math:`\Theta` is needed.

Non-conservative force columns (Rayleigh dissipation, Coulomb friction, ...) enter
the same tensor as ``-Q_j(q, qdot)`` so that ``Theta @ c = tau`` still holds.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Sequence

import sympy as sp
import torch
from torch.func import jacfwd, jvp, vmap

from ._expr import compile_torch, symbols_for

DEFAULT_CHUNK_SIZE = 32_768

TermFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@contextlib.contextmanager
def _quiet_forward_ad():
    """Silence torch's own deprecation notice raised when forward AD first loads."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*is deprecated")
        yield


def _chunks(n: int, size: int):
    size = max(1, int(size))
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def _columns_one(fn: TermFunction):
    grad_qd = jacfwd(fn, argnums=1)  # (p, dof)

    def one(q, qd, qdd):
        _, total = jvp(grad_qd, (q, qd), (qd, qdd))  # M qdd + N qd, (p, dof)
        o = jacfwd(fn, argnums=0)(q, qd)  # (p, dof)
        return (total - o).transpose(0, 1)  # (dof, p)

    return one


def lagrangian_columns(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    qdd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Euler-Lagrange columns of candidate functions at each sample.

    Parameters
    ----------
    fn : callable
        ``fn(q, qd) -> Tensor (n_terms,)`` for one sample (see
        :func:`lagsindy._expr.compile_torch`).
    q, qd, qdd : Tensor of shape (n_samples, n_dof)
        Positions, velocities and accelerations.
    chunk_size : int, default=32768
        Samples processed at once (bounds memory).

    Returns
    -------
    Tensor of shape (n_samples, n_dof, n_terms)
        ``Theta[s, i, k] = (M_k qdd + N_k qd - O_k)_i`` at sample ``s``.
    """
    batched = vmap(_columns_one(fn))
    with _quiet_forward_ad():
        parts = [batched(q[sl], qd[sl], qdd[sl]) for sl in _chunks(q.shape[0], chunk_size)]
    return torch.cat(parts, dim=0)


def lagrangian_components(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The paper's ``M_k``, ``N_k`` and ``O_k`` for every candidate at each sample.

    Returns
    -------
    M : Tensor of shape (n_samples, n_terms, n_dof, n_dof)
        ``d2 phi_k / dqd_i dqd_j``.
    N : Tensor of shape (n_samples, n_terms, n_dof, n_dof)
        ``d2 phi_k / dqd_i dq_j``.
    O : Tensor of shape (n_samples, n_terms, n_dof)
        ``d phi_k / dq_i``.
    """
    grad_qd = jacfwd(fn, argnums=1)

    def one(q1, qd1):
        n_mat, m_mat = jacfwd(grad_qd, argnums=(0, 1))(q1, qd1)
        o = jacfwd(fn, argnums=0)(q1, qd1)
        return m_mat, n_mat, o

    batched = vmap(one)
    ms, ns, os_ = [], [], []
    for sl in _chunks(q.shape[0], chunk_size):
        with _quiet_forward_ad():
            m_mat, n_mat, o = batched(q[sl], qd[sl])
        ms.append(m_mat)
        ns.append(n_mat)
        os_.append(o)
    return torch.cat(ms), torch.cat(ns), torch.cat(os_)


class EulerLagrangeOperator:
    """Regression tensor of a Lagrangian library and optional force terms.

    Parameters
    ----------
    coordinates : sequence of str
        Coordinate names (their order is the dof order).
    terms : sequence of sympy.Expr
        Lagrangian candidate functions of the coordinates and velocities.
    forces : sequence of sequence of sympy.Expr, optional
        Generalized force vectors ``Q_j(q, qd)`` (one entry per coordinate) of
        non-conservative candidates; their columns are ``-Q_j``.
    dtype : torch.dtype, default=torch.float64
    device : str or torch.device, default="cpu"
    chunk_size : int, default=32768

    Notes
    -----
    Columns are ordered: Lagrangian terms first, then force terms.
    """

    def __init__(
        self,
        coordinates: Sequence[str],
        terms: Sequence[sp.Expr],
        forces: Sequence[Sequence[sp.Expr]] | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        device="cpu",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ):
        self.coordinates = list(coordinates)
        self.terms = list(terms)
        self.forces = [list(f) for f in (forces or [])]
        self.dtype = dtype
        self.device = torch.device(device)
        self.chunk_size = chunk_size
        q, qd, _ = symbols_for(self.coordinates)
        self._symbols = (q, qd)
        self._fn = compile_torch(self.terms, (q, qd)) if self.terms else None
        flat = [e for f in self.forces for e in f]
        self._force_fn = compile_torch(flat, (q, qd)) if flat else None

    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    @property
    def n_terms(self) -> int:
        return len(self.terms)

    @property
    def n_columns(self) -> int:
        return len(self.terms) + len(self.forces)

    def _split(self, X: torch.Tensor):
        n = self.n_dof
        return X[:, :n], X[:, n : 2 * n], X[:, 2 * n : 3 * n]

    def columns(self, X: torch.Tensor) -> torch.Tensor:
        """Regression tensor of shape (n_samples, n_dof, n_columns) at ``X``.

        ``X`` has columns ``[q..., qd..., qdd...]``.
        """
        q, qd, qdd = self._split(X)
        parts = []
        if self._fn is not None:
            parts.append(lagrangian_columns(self._fn, q, qd, qdd, chunk_size=self.chunk_size))
        if self._force_fn is not None:
            parts.append(-self.force_values(q, qd))
        if not parts:
            return X.new_zeros((X.shape[0], self.n_dof, 0))
        return torch.cat(parts, dim=2)

    def force_values(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Generalized forces ``Q_j`` of the force terms, shape (n_samples, n_dof, n_forces)."""
        if self._force_fn is None:
            return q.new_zeros((q.shape[0], self.n_dof, 0))
        values = vmap(self._force_fn)(q, qd)  # (n, n_forces * n_dof)
        return values.reshape(q.shape[0], len(self.forces), self.n_dof).transpose(1, 2)

    def mass_matrices(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``M_k`` of every Lagrangian term, shape (n_samples, n_terms, n_dof, n_dof)."""
        if self._fn is None:
            return q.new_zeros((q.shape[0], 0, self.n_dof, self.n_dof))
        m_mat, _, _ = lagrangian_components(self._fn, q, qd, chunk_size=self.chunk_size)
        return m_mat

    def gram(self, X: torch.Tensor, y: torch.Tensor | None = None):
        """Per-dof Gram statistics of ``A = [Theta | y]``, accumulated in chunks.

        Parameters
        ----------
        X : Tensor of shape (n_samples, 3 * n_dof)
        y : Tensor of shape (n_samples, n_dof), optional
            Target generalized forces, appended as the last column of ``A``.

        Returns
        -------
        Tensor of shape (n_dof, n_columns (+1), n_columns (+1))
            ``G[i] = A[:, i, :].T @ A[:, i, :]``, so Theta is never held in memory
            whole.
        """
        width = self.n_columns + (0 if y is None else 1)
        out = X.new_zeros((self.n_dof, width, width))
        for sl in _chunks(X.shape[0], self.chunk_size):
            theta = self.columns(X[sl])
            if y is not None:
                theta = torch.cat([theta, y[sl].unsqueeze(2)], dim=2)
            out += torch.einsum("sip,siq->ipq", theta, theta)
        return out


def forward_accelerations(
    operator: EulerLagrangeOperator,
    coef: torch.Tensor,
    X: torch.Tensor,
    tau: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""Accelerations of the model ``sum_k c_k phi_k`` (paper eq. 10).

    :math:`\ddot q = M(c)^{+} (\tau - h(c))` with :math:`M(c) = \sum_k c_k M_k`
    (Moore-Penrose pseudo-inverse, as in the paper) and the velocity/position part
    :math:`h(c) = \Theta c - M(c) \ddot q` read off the regression tensor, so that
    force columns (dissipation) enter too. The ``qdd`` columns of ``X`` only serve to
    form :math:`h`; they cancel out.

    Returns
    -------
    Tensor of shape (n_samples, n_dof)
    """
    n = operator.n_dof
    q, qd, qdd = X[:, :n], X[:, n : 2 * n], X[:, 2 * n : 3 * n]
    theta = operator.columns(X)
    mass = operator.mass_matrices(q, qd)
    mc = torch.einsum("skij,k->sij", mass, coef[: operator.n_terms])
    bias = theta @ coef - torch.einsum("sij,sj->si", mc, qdd)
    rhs = -bias if tau is None else tau - bias
    return (torch.linalg.pinv(mc, hermitian=True) @ rhs.unsqueeze(-1)).squeeze(-1)
