"""Reduction of candidate terms: the trivial and the linearly dependent ones.

A term is *trivial* when its Euler-Lagrange expression vanishes identically (a total
time derivative such as ``q*qdot``); it is *dependent* when its Euler-Lagrange
column, sampled at random states, is a linear combination of earlier terms' columns
(``sin(q)**2`` once ``cos(q)**2`` is in). :class:`~lagsindy.library.CandidateLibrary`
removes both when it builds, and reports each with the reason.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import sympy as sp

from ._expr import symbols_for

__all__ = [
    "DEPENDENCE_TOL",
    "TRIVIAL_REASON",
    "euler_lagrange_expressions",
    "reduce_terms",
    "sample_columns",
]

TRIVIAL_REASON = "trivial: its Euler-Lagrange expression is identically zero"
#: Residual norm (of a unit column) below which a column counts as dependent.
DEPENDENCE_TOL = 1e-7


def euler_lagrange_expressions(term: sp.Expr, coordinates: Sequence[str]) -> list:
    """Symbolic Euler-Lagrange expression of one term, one entry per coordinate.

    ``d/dt (d term / d qdot_i) - d term / d q_i`` with the time derivative expanded by
    the chain rule (it contains the ``*_ddot`` symbols).
    """
    q, qd, qdd = symbols_for(coordinates)
    out = []
    for i in range(len(q)):
        p_i = sp.diff(term, qd[i])
        dt = sum(
            sp.diff(p_i, q[j]) * qd[j] + sp.diff(p_i, qd[j]) * qdd[j]
            for j in range(len(q))
        )
        out.append(sp.expand(dt - sp.diff(term, q[i])))
    return out


def sample_columns(terms, coordinates, rng, n_points=None, expressions=None):
    """Euler-Lagrange columns of ``terms`` at random states drawn from ``rng``.

    Returns an array of shape ``(n_points * n_dof, n_terms)``; ``n_points`` defaults
    to enough rows for the terms (``ceil(3 n_terms / n_dof) + 24``).
    """
    q, qd, qdd = symbols_for(coordinates)
    n_dof = len(coordinates)
    if n_points is None:
        n_points = int(math.ceil(3 * len(terms) / n_dof)) + 24
    values = np.concatenate(
        [
            rng.uniform(-math.pi, math.pi, (n_points, n_dof)),
            rng.uniform(-2.0, 2.0, (n_points, n_dof)),
            rng.uniform(-2.0, 2.0, (n_points, n_dof)),
        ],
        axis=1,
    ).T
    if expressions is None:
        expressions = [euler_lagrange_expressions(t, coordinates) for t in terms]
    flat = [e for exprs in expressions for e in exprs]
    f = sp.lambdify(list(q) + list(qd) + list(qdd), flat, modules="numpy")
    with np.errstate(all="ignore"):
        out = f(*values)
    cols = np.stack(
        [np.broadcast_to(np.asarray(v, dtype=float), (n_points,)) for v in out], axis=1
    )  # (n_points, n_terms * n_dof)
    return (
        cols.reshape(n_points, len(terms), n_dof)
        .transpose(0, 2, 1)
        .reshape(-1, len(terms))
    )


def reduce_terms(candidates, coordinates, remove_trivial, remove_dependent):
    """Remove trivial and linearly dependent candidates (in order).

    Returns
    -------
    kept : list of sympy.Expr
    removed : list of (str, str)
        Each removed term and why (trivial, or the combination of earlier terms its
        Euler-Lagrange column equals).
    """
    return _reduce_cached(
        tuple(candidates),
        tuple(coordinates),
        bool(remove_trivial),
        bool(remove_dependent),
    )


@functools.lru_cache(maxsize=64)
def _reduce_cached(candidates, coordinates, remove_trivial, remove_dependent):
    candidates = list(candidates)
    if not (remove_trivial or remove_dependent):
        return list(candidates), []
    expressions = [euler_lagrange_expressions(t, coordinates) for t in candidates]
    symbolic_zero = [all(e == 0 for e in exprs) for exprs in expressions]
    a = sample_columns(
        candidates, coordinates, np.random.default_rng(0), expressions=expressions
    )
    a = a[np.all(np.isfinite(a), axis=1)]
    norms = np.linalg.norm(a, axis=0)
    zero_tol = 1e-12 * max(norms.max(initial=0.0), 1e-300)
    kept_idx, removed = [], []
    basis = np.zeros((a.shape[0], 0))
    # The kept columns in the basis, unit-scaled, are basis @ triangle (Gram-Schmidt's
    # QR): a dependent column's combination is one triangular solve, not a least
    # squares problem per removed term (a 2-angle poly4 library: 61 lstsq calls of
    # 676 x 128, 7 s on a busy 2-core machine).
    in_basis, triangle = [], np.zeros((0, 0))
    for k, term in enumerate(candidates):
        col, norm = a[:, k], norms[k]
        if symbolic_zero[k] or norm <= zero_tol:
            if remove_trivial:
                removed.append((str(term), TRIVIAL_REASON))
                continue
            kept_idx.append(k)
            continue
        unit = col / norm
        h1 = basis.T @ unit
        r = unit - basis @ h1
        h2 = basis.T @ r
        r = r - basis @ h2
        rn = np.linalg.norm(r)
        if remove_dependent and rn < DEPENDENCE_TOL:
            unit_coef = np.linalg.solve(triangle, h1 + h2)
            coef = unit_coef * norm / norms[in_basis]
            big = max(1.0, np.abs(coef).max(initial=0.0))
            parts = [
                f"{c:+.6g}*[{candidates[j]}]"
                for c, j in zip(coef, in_basis)
                if abs(c) > 1e-8 * big
            ]
            removed.append(
                (
                    str(term),
                    "dependent: its Euler-Lagrange column equals " + " ".join(parts),
                )
            )
            continue
        if rn > 1e-12:
            basis = np.concatenate([basis, (r / rn)[:, None]], axis=1)
            m = len(in_basis)
            triangle = np.pad(triangle, ((0, 1), (0, 1)))
            triangle[:m, m] = h1 + h2
            triangle[m, m] = rn
            in_basis.append(k)
        kept_idx.append(k)
    return [candidates[k] for k in kept_idx], removed
