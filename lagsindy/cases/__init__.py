"""The three cases of the paper, each a function of one :class:`Problem`.

* :mod:`~lagsindy.cases.forces`: case I, the generalized forces are known;
* :mod:`~lagsindy.cases.fixed`: case III, passive data with the scale fixed by a
  known term, by the mass matrix, or by a search over both;
* :mod:`~lagsindy.cases.acceleration`: case II, passive data fitted through the
  predicted accelerations (non-convex).

Each returns a :class:`Solution`; :class:`~lagsindy.LagrangianSINDy` picks the case
(``CASES[case](problem)``) and turns the solution into a
:class:`~lagsindy.model.FittedLagrangian`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..formulation import feature_operator
from .sparse import SparseSolve


@dataclass
class Problem:
    """What a case needs: the scaled statistics, the data and the library.

    Attributes
    ----------
    balanced : BalancedGram
        Scaled Gram statistics (candidate columns, then the target in case I).
    identifiable : ndarray of bool
        Columns that are not identically zero on the data.
    penalty : ndarray
        L1 weight per feature (0 for ``unpenalized`` features).
    Xt : Tensor of shape (n_samples, 3 * n_dof)
        The data (case III ranks its candidates on them, case II fits them).
    library : CandidateLibrary
        The built library; its terms are the first features.
    dissipation_terms : list of ForceTerm
        The dissipation features that follow.
    names : ndarray of str
        Feature names.
    solver : SparseSolve
    fixed_term : str, sympy.Expr, "mass" or None
    memo : dict
        Results that depend only on the data and the library (not on the window's
        statistics), shared by the problems of one fit (the estimator passes one
        dict to every window's problem): e.g. case III's mass-matrix traces.
    start : ndarray of shape (n_features,) or None
        A warm start of the first stage, in coefficient units (the bootstrap starts
        its resamples from the full fit's first stage); used by case I and by case
        III with one fixed term. The first stage is strictly convex where its Gram
        block is definite, so the start changes the iterations, not the answer.
    """

    balanced: object
    identifiable: np.ndarray
    penalty: np.ndarray
    Xt: object
    library: object
    dissipation_terms: list
    names: np.ndarray
    solver: SparseSolve
    fixed_term: object = None
    memo: dict = field(default_factory=dict, repr=False, compare=False)
    start: np.ndarray | None = None

    @property
    def coordinates(self) -> list:
        return list(self.library.coordinates_)

    @property
    def terms(self) -> list:
        return self.library.terms_

    @property
    def n_dof(self) -> int:
        return len(self.library.coordinates_)

    @property
    def n_features(self) -> int:
        return self.balanced.n_features

    def feature_operator(self, indices, device=None, dtype=None):
        return feature_operator(
            self.coordinates,
            self.terms,
            self.dissipation_terms,
            indices,
            self.Xt.device if device is None else device,
            self.Xt.dtype if dtype is None else dtype,
        )


@dataclass
class Solution:
    """Coefficients over all features, the staged result, and how the scale was set.

    ``fixed`` is the index of the term whose coefficient is 1 in the returned scale
    (case III), ``normalization`` ``"term"`` or ``"mass"`` (case III) or ``None``;
    ``row_scale`` the balanced problem's row scales (set by the estimator);
    ``score`` the acceleration R^2 that case III's search scored the model with.
    """

    coef: np.ndarray
    result: object
    fixed: int | None = None
    normalization: str | None = None
    row_scale: object = None
    score: float | None = None


def _cases():
    from .acceleration import fit_acceleration
    from .fixed import fit_fixed
    from .forces import fit_forces

    return {"forces": fit_forces, "fixed": fit_fixed, "acceleration": fit_acceleration}


def solve_case(case: str, problem: Problem) -> Solution:
    """Run case ``case`` (``"forces"``, ``"fixed"`` or ``"acceleration"``)."""
    return _cases()[case](problem)


__all__ = ["Problem", "Solution", "SparseSolve", "solve_case"]
