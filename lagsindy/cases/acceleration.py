"""Case II: passive data without a prior, fitted through the predicted accelerations.

The datafit compares measured accelerations with ``M(c)^+ (-h(c))`` of the learned
model, which is non-convex in ``c``; the scale is fixed by a unit norm and the sign
by a positive-definite mass matrix after the fit.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from .._torch import to_numpy
from ..formulation.operator import lagrangian_components
from ..solvers import AccelerationDatafit
from . import Problem, Solution
from .sparse import PATH_TIE

# Rows used by case II (each iteration costs O(rows * terms * n_dof^2)).
CASE_II_ROWS = 20_000
# Eigenvectors tried as the start of case II.
CASE_II_STARTS = 10
# Of those, the best few (by acceleration loss) are each run through the staged solve.
# 1 for now: each case II run costs minutes on the 20-trajectory degree-4 test, so
# more runs need a cheaper stage first (issue 12, item 5, left open).
CASE_II_RUNS = 1


def fit_acceleration(problem: Problem) -> Solution:
    """Case II: sparse fit of accelerations through the learned mass matrix."""
    p = problem
    Xt, balanced = p.Xt, p.balanced
    rows = p.solver.subsample_rows(Xt.shape[0], CASE_II_ROWS)
    Xs = Xt[torch.as_tensor(rows, device=Xt.device)]
    free = np.flatnonzero(p.identifiable)
    n_terms = len(p.terms)
    sub = p.feature_operator(free)
    d = p.n_dof
    q, qd, qdd = Xs[:, :d], Xs[:, d : 2 * d], Xs[:, 2 * d : 3 * d]
    mass, n_mat, o = lagrangian_components(sub._fn, q, qd)
    bias = torch.einsum("skij,sj->ski", n_mat, qd) - o
    n_forces = int((free >= n_terms).sum())
    if n_forces:  # force features: no inertia, left-hand side -Q
        mass = torch.cat([mass, mass.new_zeros((mass.shape[0], n_forces, d, d))], dim=1)
        bias = torch.cat([bias, -sub.force_values(q, qd).transpose(1, 2)], dim=1)
    # Spectral start (no prior knowledge): unit vectors that nearly satisfy the
    # homogeneous Euler-Lagrange equations are the eigenvectors of the scaled Gram
    # matrix with the smallest eigenvalues (dense estimates of the Lagrangian). In
    # a large library the very smallest can be a combination without kinetic
    # energy (its mass matrix singular, so it predicts no accelerations): start
    # from the one of the first few that best predicts the accelerations.
    g, scale = balanced.block(free)
    datafit = AccelerationDatafit(mass, bias, qdd, scale)
    # Which of the first eigenvectors predicts best can hinge on rounding (two of
    # them nearly tie), and different starts can end in different local optima
    # (a Taylor polynomial standing in for cos(theta)): the staged solve runs from
    # the CASE_II_RUNS best starts and the result that best predicts the
    # accelerations is kept, the sparsest (then the earliest start) of those
    # within PATH_TIE of the best, so a rounding-level change cannot flip it.
    vecs = torch.linalg.eigh(g)[1][:, :CASE_II_STARTS]
    losses = [datafit.value(vecs[:, k]) for k in range(vecs.shape[1])]
    ranked = np.argsort(np.asarray(losses), kind="stable")[:CASE_II_RUNS]
    weights = torch.as_tensor(p.penalty[free], dtype=Xt.dtype, device=Xt.device)
    runs, failure = [], None
    for k in ranked:
        w0 = vecs[:, int(k)]
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = p.solver.stages(datafit, free, weights, p.solver.verbose, w0=w0)
        except FloatingPointError as exc:
            failure = exc
            continue
        value = datafit.relative_residual(res.coef)
        if np.isfinite(value):
            runs.append((value, int((res.coef != 0).sum()), len(runs), res, caught))
    if not runs:
        exc = failure if failure is not None else "no start gave a finite fit"
        raise ValueError(
            f"case='acceleration' failed: {exc}. The model lost every term that "
            "gives it a mass matrix, so it predicts no accelerations. This happens "
            "when the data are driven by forces that were not given (pass them: "
            "fit(X, tau)) or when no velocity term of the library fits the data; "
            "try a lower threshold, or case III (fit(X) with a fixed_term)."
        ) from None
    best = min(r[0] for r in runs)
    near = [r for r in runs if r[0] <= (1 + PATH_TIE) * best + 1e-12]
    *_, result, caught = min(near, key=lambda r: (r[1], r[2]))
    for w_ in caught:
        warnings.warn_explicit(w_.message, w_.category, w_.filename, w_.lineno)
    w = result.coef / scale
    # Present the gauge-free answer with a positive-definite mass matrix and the
    # largest scaled term at unit size.
    mc = torch.einsum("skij,k->sij", mass, w)
    if float(torch.linalg.eigvalsh(mc).mean()) < 0:
        w = -w
    big = int(torch.argmax(result.coef.abs()))
    w = w / abs(float(w[big]))
    coef = np.zeros(balanced.n_features)
    coef[free] = to_numpy(w)
    for st in result.stages:
        full = np.zeros(len(coef))
        full[free] = st.coef / to_numpy(scale)
        st.coef = full
        st.support = free[st.support]
    return Solution(coef, result)
