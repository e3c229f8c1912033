"""Case I: the generalized forces are known, so they fix the Lagrangian's scale."""

from __future__ import annotations

import numpy as np
import torch

from .._torch import to_numpy
from . import Problem, Solution


def fit_forces(problem: Problem) -> Solution:
    """Sparse fit of tau (the column after the features) by the identifiable columns."""
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
# A solution with more terms (the per-equation threshold's, see
# lagsindy.pipeline.judge_each_equation) replaces the fit's only for a tenfold gain
# in an equation the fit misses by at least 1e-4 of its energy (1 % in rms), none
# worse. Measured on a double pendulum driven at the first joint, second link 2 %
# of the first (separated degree-2 library): the fit dropped the
# theta1_dot*theta2_dot*sin(theta1)*sin(theta2) half of the coupling and left the
# second link's equation at 3.2e-2 of its energy (link parameters 40 % off, no
# warning); with the term, 3.6e-6.
MORE_TERMS_GAIN = 0.1
MORE_TERMS_MATERIAL = 1e-4


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
        if fits_better(gram, best, candidate):
            best = candidate
    return best


def fits_better(gram, current: Solution, candidate: Solution, *, more_terms=False):
    """The equations ``candidate`` meets clearly better than ``current`` on
    ``gram``'s statistics, as ``[(i, before, after)]`` (residuals relative to the
    equation's energy), or ``[]`` when it meets any equation worse (beyond
    ``SUPPORT_TIE``) or none clearly better.

    Clearly better: a residual at most ``SUPPORT_GAIN`` of the current one's, or,
    when the candidate has more terms (``more_terms``), at most ``MORE_TERMS_GAIN``
    of a residual that is at least ``MORE_TERMS_MATERIAL`` of the equation's energy
    (a term is added only for a tenfold gain in an equation the current model
    misses by 1 % in rms or more)."""
    r0, energy = equation_residuals(gram, current.coef)
    r1, _ = equation_residuals(gram, candidate.coef)
    if not np.all(r1 <= r0 + SUPPORT_TIE * np.abs(r0)):
        return []
    if more_terms:
        clear = (r0 >= MORE_TERMS_MATERIAL * energy) & (r1 <= MORE_TERMS_GAIN * r0)
    else:
        clear = (r0 > SUPPORT_FLOOR * energy) & (r1 <= SUPPORT_GAIN * r0)
    safe = np.where(energy > 0, energy, 1.0)
    return [(int(i), r0[i] / safe[i], r1[i] / safe[i]) for i in np.flatnonzero(clear)]


def misses_an_equation(gram, coef) -> bool:
    """Whether ``coef`` leaves some equation of ``gram``'s statistics at least
    ``MORE_TERMS_MATERIAL`` of its energy unexplained: where a solution with more
    terms could be kept (:func:`fits_better`); a fit that meets every equation
    closer needs no second solve."""
    r, energy = equation_residuals(gram, coef)
    return bool(np.any(r >= MORE_TERMS_MATERIAL * energy))


def known_columns(library) -> dict:
    """``{column: value}`` of the library's known terms (``known_terms_``, by name:
    e.g. a robot's URDF Lagrangian at coefficient 1 with
    ``RobotLibrary(inertia="urdf")``); empty for other libraries."""
    known = getattr(library, "known_terms_", None) or {}
    return {list(library.terms_).index(name): float(v) for name, v in known.items()}


def hold_known(gram, known: dict, case: str = "forces"):
    """Gram statistics with the ``known`` columns (``{column: value}``) moved to the
    target: the target becomes ``tau - sum_k value_k A_k`` and the known columns
    zero (so no solve can use them; their coefficients are set afterwards).

    ``gram`` is (..., P + 1, P + 1), the features then the target (a tensor or an
    array): the result is ``S^T gram S`` with ``S`` the identity except
    ``S[k, k] = 0`` and ``S[k, target] = -value_k``. Linear in ``gram``, so sums
    over folds, trajectories and resamples commute with it.
    """
    if case != "forces":
        raise ValueError(
            "this library holds known terms (a robot library with inertia='urdf'), "
            "which needs the forces: fit(X, tau) (case I)"
        )
    width = gram.shape[-1]
    s = np.eye(width)
    for k, v in known.items():
        s[k, k] = 0.0
        s[k, width - 1] = -v
    if isinstance(gram, np.ndarray):
        return s.T @ gram @ s
    t = torch.as_tensor(s, dtype=gram.dtype, device=gram.device)
    return t.T @ gram @ t
