r"""Euler-Lagrange regression tensors of a library and force terms.

For a library of candidate functions :math:`\phi_k(q, \dot q)` the Euler-Lagrange
operator applied to each candidate is, per sample (paper eqs. 5-8),

.. math::

    \Theta_{:, k} = M_k \ddot q + N_k \dot q - O_k, \quad
    M_k = \nabla_{\dot q}^\top \nabla_{\dot q} \phi_k, \;
    N_k = \nabla_q^\top \nabla_{\dot q} \phi_k, \;
    O_k = \nabla_q \phi_k,

so that a Lagrangian :math:`L = \sum_k c_k \phi_k` has generalized forces
:math:`\tau = \Theta c`. Non-conservative force columns (Rayleigh dissipation,
Coulomb friction, ...) enter the same tensor as ``-Q_j(q, qdot)`` so that
``Theta @ c = tau`` still holds.

:class:`EulerLagrangeOperator` takes its rows ``X = [q, qd, qdd]``; the per-term
parts come from one :class:`~lagsindy.evaluator.TermEvaluator` (batched kernels and
``torch.func``), its strong-form statistics from :mod:`.strong`, its weak-form
statistics from :mod:`.weak_integrals`.
"""

from __future__ import annotations

from collections.abc import Sequence

import sympy as sp
import torch

from ..evaluator import (  # noqa: F401  (their 0.2 home)
    DEFAULT_CHUNK_SIZE,
    TermEvaluator,
    TermFunction,
    lagrangian_columns,
    lagrangian_components,
    lagrangian_gradients,
    lagrangian_hessians,
)
from . import weak_integrals
from .strong import strong_gram
from .weak_integrals import NOISE_ROWS, reuse_weak_columns  # noqa: F401


class EulerLagrangeOperator:
    """Regression tensor of a Lagrangian library and optional force terms.

    Parameters
    ----------
    coordinates : sequence of str
        Coordinate names (their order is the dof order).
    terms : sequence of sympy.Expr, or a torch term function
        Lagrangian candidate functions of the coordinates and velocities (see
        :mod:`lagsindy.evaluator` for the torch term function's contract).
    forces : sequence of sequence of sympy.Expr, optional
        Generalized force vectors ``Q_j(q, qd)`` (one entry per coordinate) of
        non-conservative candidates; their columns are ``-Q_j``.
    dtype : torch.dtype, default=torch.float64
    device : str or torch.device, default="cpu"
    chunk_size : int, default=32768

    Attributes
    ----------
    evaluator : TermEvaluator
        The per-term parts of the terms and forces.

    Notes
    -----
    Columns are ordered: Lagrangian terms first, then force terms.
    """

    def __init__(
        self,
        coordinates: Sequence[str],
        terms,
        forces: Sequence[Sequence[sp.Expr]] | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        device="cpu",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ):
        self.evaluator = TermEvaluator(
            coordinates, terms, forces, chunk_size=chunk_size
        )
        self.coordinates = self.evaluator.coordinates
        self.terms = terms if self.evaluator.terms is None else self.evaluator.terms
        self.forces = self.evaluator.forces
        self.dtype = dtype
        self.device = torch.device(device)
        self.chunk_size = chunk_size

    @property
    def n_dof(self) -> int:
        return self.evaluator.n_dof

    @property
    def n_terms(self) -> int:
        return self.evaluator.n_terms

    @property
    def n_columns(self) -> int:
        return self.evaluator.n_columns

    def _split(self, X: torch.Tensor):
        n = self.n_dof
        return X[:, :n], X[:, n : 2 * n], X[:, 2 * n : 3 * n]

    def columns(self, X: torch.Tensor) -> torch.Tensor:
        """Regression tensor of shape (n_samples, n_dof, n_columns) at ``X``.

        ``X`` has columns ``[q..., qd..., qdd...]``.
        """
        return self.evaluator.columns(*self._split(X))

    def columns_t(self, X: torch.Tensor) -> torch.Tensor:
        """:meth:`columns` in the layout (n_dof, n_columns, n_samples)."""
        return self.evaluator.columns_t(*self._split(X))

    def force_values(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Generalized forces ``Q_j``, shape (n_samples, n_dof, n_forces)."""
        return self.evaluator.force_values(q, qd)

    def force_jacobians(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``d Q_ji / d x_b`` over ``x = [q, qd]``, (n, n_forces, n_dof, 2 n_dof)."""
        return self.evaluator.force_jacobians(q, qd)

    def mass_matrices(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``M_k`` of every term, shape (n_samples, n_terms, n_dof, n_dof)."""
        return self.evaluator.mass_matrices(q, qd)

    def mass_matrices_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`mass_matrices` in the layout (n_terms, n_dof, n_dof, n_samples)."""
        return self.evaluator.mass_matrices_t(q, qd)

    def parts(self, q: torch.Tensor, qd: torch.Tensor):
        """``M_k`` of the terms (n, n_terms, d, d) and the bias ``h`` of every
        column (n, n_columns, d): see :meth:`lagsindy.evaluator.TermEvaluator.parts`."""
        return self.evaluator.parts(q, qd)

    def gram(self, X: torch.Tensor, y: torch.Tensor | None = None, extra=None):
        """Per-dof Gram statistics of ``A = [Theta | extra | y]``, in chunks.

        See :func:`lagsindy.formulation.strong.strong_gram`.

        Parameters
        ----------
        X : Tensor of shape (n_samples, 3 * n_dof)
        y : Tensor of shape (n_samples, n_dof), optional
        extra : Tensor of shape (n_samples, n_dof, n_extra), optional

        Returns
        -------
        Tensor of shape (n_dof, n_columns (+ n_extra) (+1), same)
        """
        return strong_gram(self.evaluator, X, y, extra)

    def weak_gram(self, X: torch.Tensor, y: torch.Tensor | None, segments, **kwargs):
        """Weak-form Gram statistics of one window: see
        :func:`lagsindy.formulation.weak_integrals.weak_gram` (same arguments after
        ``segments``: ``window=``, ``stride=``, ``dt=``, ``noise_cov=``, ...)."""
        return weak_integrals.weak_gram(self.evaluator, X, y, segments, **kwargs)

    def weak_grams(
        self, X: torch.Tensor, y: torch.Tensor | None, segments_by_window, **kwargs
    ) -> dict:
        """Weak-form Gram statistics of several windows at once: see
        :func:`lagsindy.formulation.weak_integrals.weak_grams`."""
        return weak_integrals.weak_grams(
            self.evaluator, X, y, segments_by_window, **kwargs
        )


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
    return accelerations_from(theta, mass, coef, qdd, tau)


def accelerations_from(theta, mass, coef, qdd, tau=None) -> torch.Tensor:
    """:func:`forward_accelerations` from precomputed columns and mass matrices.

    ``theta`` (n_samples, n_dof, n_features) holds the model's columns (Lagrangian
    terms, then force terms), ``mass`` (n_samples, n_terms, n_dof, n_dof) the
    per-term mass matrices of its Lagrangian terms.
    """
    mc = torch.einsum("skij,k->sij", mass, coef[: mass.shape[1]])
    bias = theta @ coef - torch.einsum("sij,sj->si", mc, qdd)
    rhs = -bias if tau is None else tau - bias
    return (torch.linalg.pinv(mc, hermitian=True) @ rhs.unsqueeze(-1)).squeeze(-1)
