"""Case I: the generalized forces are known, so they fix the Lagrangian's scale."""

from __future__ import annotations

import numpy as np

from . import Problem, Solution


def fit_forces(problem: Problem) -> Solution:
    """Sparse fit of tau (the column after the features) by every identifiable column."""
    free = np.flatnonzero(problem.identifiable)
    coef, result = problem.solver.solve(
        problem.balanced,
        free,
        problem.n_features,
        1.0,
        problem.penalty,
        0.0,
        problem.solver.verbose,
        start=problem.start,
    )
    return Solution(coef, result)
