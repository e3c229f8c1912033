"""Case II: passive data without a prior, fitted through the predicted accelerations.

The datafit compares measured accelerations with ``M(c)^+ (-h(c))`` of the learned
model, which is non-convex in ``c``; the scale is fixed by a unit norm and the sign
by a positive-definite mass matrix after the fit.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import torch

from .._stacklevel import outside_stacklevel
from .._torch import to_numpy
from ..solvers import AccelerationDatafit
from . import Problem, Solution

# Rows used by case II (each iteration costs O(rows * terms * n_dof^2)).
CASE_II_ROWS = 20_000
# Scaled coefficients within this relative distance of the largest tie for the unit.
GAUGE_TIE = 1e-6
# Eigenvectors tried as the start of case II when the case III start fails.
CASE_II_STARTS = 10


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
    mass, bias = sub.parts(q, qd)  # bias: N qd - O, then -Q of the forces
    n_forces = int((free >= n_terms).sum())
    if n_forces:  # force features: no inertia
        mass = torch.cat([mass, mass.new_zeros((mass.shape[0], n_forces, d, d))], dim=1)
    g, scale = balanced.block(free)
    datafit = AccelerationDatafit(mass, bias, qdd, scale)
    weights = torch.as_tensor(p.penalty[free], dtype=Xt.dtype, device=Xt.device)
    w0 = _start(p, free, g, scale, datafit)
    try:
        result = p.solver.stages(datafit, free, weights, p.solver.verbose, w0=w0)
        finite = np.isfinite(datafit.relative_residual(result.coef))
        failure = None if finite else "the fit is not finite"
    except FloatingPointError as exc:
        failure = exc
    if failure is not None:
        raise ValueError(
            f"case='acceleration' failed: {failure}. The model lost every term that "
            "gives it a mass matrix, so it predicts no accelerations. This happens "
            "when the data are driven by forces that were not given (pass them: "
            "fit(X, tau)) or when no velocity term of the library fits the data; "
            "try a lower threshold, or case III (fit(X) with a fixed_term)."
        ) from None
    w = result.coef / scale
    # Present the gauge-free answer with a positive-definite mass matrix and the
    # largest scaled term at unit size.
    mc = torch.einsum("skij,k->sij", mass, w)
    if float(torch.linalg.eigvalsh(mc).mean()) < 0:
        w = -w
    # The first (in library order) of the terms within GAUGE_TIE of the largest, so
    # that two nearly equal scaled terms cannot swap the unit with the rounding.
    size = result.coef.abs()
    big = int(torch.nonzero(size >= (1 - GAUGE_TIE) * size.max())[0, 0])
    w = w / abs(float(w[big]))
    coef = np.zeros(balanced.n_features)
    coef[free] = to_numpy(w)
    for st in result.stages:
        full = np.zeros(len(coef))
        full[free] = st.coef / to_numpy(scale)
        st.coef = full
        st.support = free[st.support]
    return Solution(coef, result)


def _start(p: Problem, free, g, scale, datafit):
    """Where case II's non-convex solve starts: the case III search's model.

    The homogeneous Euler-Lagrange equations are nearly satisfied by every vector of
    the Gram matrix's near-null space; in a large library (degree 4 in one angle:
    Taylor polynomials of ``cos``) that space has several dimensions, and its
    eigenvectors are an arbitrary, rounding-dependent basis of it (measured: four of
    the first seven predict the accelerations with a loss below 1e-15, and the best
    of them rotates within that space when the data are scaled by 1 + 1e-12, so that
    it starts another local optimum: a wrong four-term model or the right one). A
    start chosen among them made the answer depend on the machine. Case III's search
    (every term and the mass matrix as the scale, ranked and tie-broken on
    well-conditioned quantities) gives one sparse, reproducible model of that space;
    its unit-norm scaled coefficients start the solve. Only when it fails (or
    predicts nothing) do the eigenvectors serve, the one of the first few that best
    predicts the accelerations, with a warning that says so.
    """
    from .fixed import fit_fixed

    quiet = replace(p, solver=replace(p.solver, verbose=0), fixed_term=None)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the start's warnings are not the fit's
            coef = fit_fixed(quiet).coef
        w0 = torch.as_tensor(coef[free], dtype=scale.dtype, device=scale.device) * scale
        w0 = w0 / torch.linalg.vector_norm(w0)
        if np.isfinite(datafit.value(w0)):
            return w0
        reason = "its model predicts no accelerations"
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        reason = " ".join(str(exc).split())[:200]
    warnings.warn(
        f"case='acceleration' could not start from case III's search ({reason}); it "
        "starts from the eigenvector of the Gram matrix that best predicts the "
        "accelerations, which can depend on rounding when several nearly tie: "
        "compare with case III (fit(X) without case=)",
        UserWarning,
        stacklevel=outside_stacklevel(),
    )
    vecs = torch.linalg.eigh(g)[1][:, :CASE_II_STARTS]
    losses = [datafit.value(vecs[:, k]) for k in range(vecs.shape[1])]
    return vecs[:, int(np.argmin(losses))]
