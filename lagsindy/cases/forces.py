"""Case I: the generalized forces are known, so they fix the Lagrangian's scale."""

from __future__ import annotations

import numpy as np

from .._torch import to_numpy
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


# A support the fit met on another test window replaces its own only when, solved
# on the same statistics, it has no more terms, meets every coordinate's equation
# within SUPPORT_TIE of the fit's own residual, and at most halves (SUPPORT_GAIN)
# some equation's residual that is above rounding (SUPPORT_FLOOR of the energy of
# its terms): a clear gain, never a rounding-level one. The weighted sum the solve
# minimizes is not the judge: a light link's equation weighs little in it.
# Measured on a 20 g pole on a 2 kg cart (degree-3 library, 161-sample window):
# the fit swapped theta_dot**2 for theta_dot**2*cos(theta) + sin(theta)**2 (6
# terms); the 81-sample window's support (5 terms, the true ones) solved on the same
# statistics left the cart's equation 1.17e-5 instead of 1.20e-5 and the pole's
# 6e-7 instead of 2.0e-3 (relative to the energy of their terms); on another record
# 4.383e-4 instead of 4.396e-4 and 1.7e-8 instead of 5.8e-6.
SUPPORT_TIE = 0.01
SUPPORT_GAIN = 0.5
SUPPORT_FLOOR = 1e-10


def equation_residuals(gram, coef) -> tuple:
    """Squared residual ``|tau_i - A_i coef|^2`` of each coordinate's equation, from
    its Gram statistics ``gram`` (n_dof, P, P: the features, then tau), and the
    energy of the equation's terms and target (``sum_k coef_k^2 |A_ik|^2 +
    |tau_i|^2``)."""
    g = to_numpy(gram)
    v = np.concatenate([np.asarray(coef, dtype=float), [-1.0]])
    g = g[:, : v.size, : v.size]
    residual = np.einsum("p,dpq,q->d", v, g, v)
    energy = np.einsum("p,dpp->d", v**2, g)
    return residual, energy


def better_support(gram, current: Solution, others, resolve) -> Solution:
    """Case I: ``current`` or the solution on another window's support that fits
    every equation at least as well and one clearly better (see ``SUPPORT_TIE``,
    ``SUPPORT_GAIN``).

    ``others`` are solutions of the same fit on other statistics (the weak form's
    other test windows); ``resolve(mask)`` solves on ``gram``'s statistics with the
    candidates outside ``mask`` left out. The staged solve judges terms by a
    weighted sum over the equations, so a light link's equation, small in that
    sum, can lose its terms to a swap that barely helps the heavy link's: the
    per-equation residuals show it.
    """
    own = np.asarray(current.coef) != 0
    best = current
    r_best, energy = equation_residuals(gram, current.coef)
    seen = {own.tobytes()}
    for other in others:
        mask = np.asarray(other.coef) != 0
        if mask.tobytes() in seen or mask.sum() > own.sum() or not mask.any():
            continue
        seen.add(mask.tobytes())
        candidate = resolve(mask)
        coef = np.asarray(candidate.coef)
        if not np.all(np.isfinite(coef)) or np.count_nonzero(coef) > own.sum():
            continue
        r, _ = equation_residuals(gram, coef)
        no_worse = np.all(r <= r_best + SUPPORT_TIE * np.abs(r_best))
        above_rounding = r_best > SUPPORT_FLOOR * energy
        if no_worse and np.any(above_rounding & (r <= SUPPORT_GAIN * r_best)):
            best, r_best = candidate, r
    return best
