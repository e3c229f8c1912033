"""Case III: passive data; the scale is fixed by a known term or by the mass matrix.

Passive data determine the Lagrangian only up to a factor, so one linear condition
fixes it: a term's coefficient is 1 (the paper), or the data mean of the trace of the
learned mass matrix is 1. Without a ``fixed_term`` every candidate term and the mass
normalization are tried and the model that best predicts the measured accelerations
is kept.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from .._torch import to_numpy
from ..formulation.operator import EulerLagrangeOperator
from ..formulation.scaling import fixed_term_bounds
from ..solvers import GramQuadratic
from . import Problem, Solution
from .sparse import PATH_FLOOR

# Rows of the subsample on which the mean traces of the mass matrices are taken.
SELECTION_ROWS = 4000
# Rows of the subsample on which the shortlisted models' accelerations are scored
# (FittedLagrangian's own R^2 check uses as many). 2000 instead of the former 4000
# rows halved the scoring (6.4 -> about 3 ms of a 67 ms search, 20 cart-pendulum
# trajectories) and chose the same model, coefficients equal to the last bit, in
# all 73 searches compared: single, double and cart pendulums (noise 0 to 0.1,
# 3 seeds) and the real single, double and triple recordings (3388-17342 rows).
SCORING_ROWS = 2000
SELECTION_TOP = 12
# Candidate models within this factor of the best unexplained acceleration variance
# count as ties, resolved towards the sparsest.
SELECTION_TIE = 1.1
# The ranking first solves the candidates whose residual bound is within this
# factor of the SELECTION_TOP-th smallest bound (then any other that can still
# reach the shortlist).
RANK_FIRST = 1.5
# ... and every candidate at once when that is most of them anyway.
RANK_ALL = 2 / 3


def fit_fixed(problem: Problem) -> Solution:
    """Case III: fix the scale, by one known term or by the mass matrix, and fit.

    Returns the coefficients, the solver result, the index of the term whose
    coefficient is 1 in the returned scale and the normalization (``"term"`` or
    ``"mass"``).
    """
    p = problem
    terms, identifiable, penalty = p.terms, p.identifiable, p.penalty
    n_terms = len(terms)
    fixed_term, verbose = p.fixed_term, p.solver.verbose
    with_mass = fixed_term is None or (
        isinstance(fixed_term, str) and fixed_term == "mass"
    )
    if fixed_term is not None and not with_mass:
        candidates = [p.library.index(fixed_term)]
        if not identifiable[candidates[0]]:
            raise ValueError(
                f"the fixed term {fixed_term!r} has a zero Euler-Lagrange column "
                "on this data, so it cannot set the scale; choose another term"
            )
    elif fixed_term is None:
        candidates = [k for k in np.flatnonzero(identifiable) if k < n_terms]
    else:
        candidates = []
    fits = []
    single = len(candidates) + int(with_mass) == 1
    # A fixed term with a positive kinetic part fixes the sign of the scale, so
    # dissipation can be constrained non-negative; a potential term does not.
    traces = (
        mass_traces(p) if p.dissipation_terms and candidates else np.zeros(p.n_features)
    )
    if with_mass and single:
        coef, result, r = solve_mass(p, verbose)
        fits.append(("mass", r, coef, result))
    if single:
        for r in candidates:
            free = np.array([k for k in np.flatnonzero(identifiable) if k != r])
            coef, result = p.solver.solve(
                p.balanced,
                free,
                r,
                -1.0,
                penalty,
                1.0,
                verbose,
                constrain=bool(traces[r] > 0),
                start=p.start,
            )
            coef[r] = 1.0
            fits.append(("term", r, coef, result))
    else:
        # In the search over every term, one start ranks the candidates (their
        # solves batched, with the mass normalization's first start); the shortlist
        # is re-solved with every start below. Warnings of candidates that lose are
        # noise; the winner's are re-raised.
        mass = _pivot_problem(p, *_mass_start(p)) if with_mass else None
        ranked, mass_first = _rank(p, candidates, traces, mass)
        if with_mass:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                coef, result, r = solve_mass(p, 0, mass_first)
            fits.append(("mass", r, coef, result))
        fits.extend(ranked)
    if single:
        kind, r, coef, result = fits[0]
        return Solution(coef, result, r, kind)
    # Rank the term candidates by relative residual, then score the best few (and
    # the mass normalization) on accelerations.
    term_fits = sorted((f for f in fits if f[0] == "term"), key=lambda f: f[3].cost)
    # The ranking's one-start result is each solve's first start: only the later
    # starts are run, and only where the first stays above the bound.
    top = term_fits[:SELECTION_TOP]
    jobs = [
        (
            np.array([k for k in np.flatnonzero(identifiable) if k != r]),
            r,
            -1.0,
            bool(traces[r] > 0),
            ranked,
        )
        for _, r, _, ranked in top
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        solved = p.solver.solve_many(p.balanced, jobs, penalty, 1.0)
    resolved = []
    for (_, r, _, _), (coef, result) in zip(top, solved):
        coef[r] = 1.0
        resolved.append(("term", r, coef, result))
    shortlist = [f for f in fits if f[0] == "mass"] + resolved
    rows = p.solver.subsample_rows(p.Xt.shape[0], SCORING_ROWS)
    Xs = p.Xt[torch.as_tensor(rows, device=p.Xt.device)]
    scores = acceleration_r2s(p, [f[2] for f in shortlist], Xs)
    scored = []
    for (kind, r, coef, result), score in zip(shortlist, scores):
        if verbose:
            label = "mass normalization" if kind == "mass" else f"fixed term {terms[r]}"
            print(
                f"[lagsindy] {label}: {int((coef != 0).sum())} terms, relative "
                f"residual {result.cost:.3g}, acceleration R2 {score:.4f}"
            )
        scored.append((score if np.isfinite(score) else -np.inf, kind, r, coef, result))
    score, kind, r, coef, result = pick_scored(scored)
    return Solution(coef, result, r, kind, score=score)


def pick_scored(scored):
    """The model case III's search keeps among its scored shortlist.

    ``scored`` holds ``(r2, kind, r, coef, result)`` per model. Models whose
    unexplained acceleration variance ``1 - r2`` is within ``SELECTION_TIE`` of the
    best's are equally good (with noise, extra terms buy a little in-sample R^2):
    the sparsest of them is kept, then the mass normalization, then the earlier
    library term, so that rounding (e.g. the order of the rows) cannot pick
    between them.
    """
    top = max(s_[0] for s_ in scored)
    near = [s_ for s_ in scored if 1 - s_[0] <= SELECTION_TIE * (1 - top) + 1e-9]
    return min(
        near,
        key=lambda s_: (int((s_[3] != 0).sum()), -1 if s_[1] == "mass" else s_[2]),
    )


def _rank(p: Problem, candidates, traces, mass=None):
    """One-start solves of the fixed-term candidates that can reach the shortlist.

    Only the :data:`SELECTION_TOP` candidates of smallest relative residual go on
    to the shortlist. Each candidate's residual is bounded from below by the dense
    least-squares fit of its column (:func:`fixed_term_bounds`, all at once), so the
    candidates are solved in order of their bounds: first those whose bound is
    near the shortlist's smallest, then any other whose bound is below the
    :data:`SELECTION_TOP`-th residual found (with a margin above rounding). A
    candidate left out cannot be in the shortlist, so the shortlist is the one that
    solving every candidate gives; on data where the bounds say little (a noise
    correction that leaves the Gram matrix singular) every candidate is solved.

    ``mass``, the mass normalization's first problem (:func:`_pivot_problem`), is
    solved with one start in the first batch.

    Returns
    -------
    fits : list of ("term", r, coef, result)
        For the candidates solved, in the order of ``candidates``.
    mass_first : StagedResult or None
        The one-start result of ``mass``, in its variables.
    """
    free_all = np.flatnonzero(p.identifiable)
    jobs = {
        r: (free_all[free_all != r], r, -1.0, bool(traces[r] > 0), None)
        for r in candidates
    }
    solved = {}
    with_first = [] if mass is None else [mass[:3]]  # solved in the first batch

    def run(batch, extra=()):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = p.solver.solve_many(
                p.balanced, [jobs[r] for r in batch], p.penalty, 1.0, 1, extra
            )
        solved.update(zip(batch, out))
        return out[len(batch) :]

    if len(candidates) <= SELECTION_TOP:
        mass_first = run(list(candidates), with_first)
    else:
        g, _ = p.balanced.block(free_all)
        bound = dict(zip(free_all.tolist(), fixed_term_bounds(g).tolist()))
        ordered = sorted(candidates, key=lambda r: bound[r])
        near = bound[ordered[SELECTION_TOP - 1]] * RANK_FIRST + PATH_FLOOR
        first = [r for r in candidates if bound[r] <= near]
        # Bounds that leave out few candidates (e.g. zero after a noise correction)
        # are not worth a second batch.
        mass_first = run(
            first if len(first) <= RANK_ALL * len(candidates) else list(candidates),
            with_first,
        )
        costs = sorted(res.cost for _, res in solved.values())
        cut = np.inf  # fewer solved than the shortlist holds: every other may enter
        if len(costs) >= SELECTION_TOP:
            cut = costs[SELECTION_TOP - 1] * (1 + 1e-6) + PATH_FLOOR
        rest = [r for r in candidates if r not in solved and bound[r] <= cut]
        if rest:
            run(rest)
        if p.solver.verbose and len(solved) < len(candidates):
            print(
                f"[lagsindy] fixed-term ranking: {len(solved)} of {len(candidates)} "
                "candidates solved (the others' least-squares bounds exceed the "
                f"{SELECTION_TOP}th best residual, {cut:.3g})"
            )
    fits = []
    for r in candidates:
        if r in solved:
            coef, result = solved[r]
            coef[r] = 1.0
            fits.append(("term", r, coef, result))
    return fits, mass_first[0] if mass_first else None


def mass_traces(p: Problem) -> np.ndarray:
    """Mean over (a subsample of) the data of tr(M_k) for every feature.

    Computed once per subsample and kept in ``p.memo``: the traces depend on the
    data and the library only, so every window of a weak-form fit shares them.
    """
    rows = p.solver.subsample_rows(p.Xt.shape[0], SELECTION_ROWS)
    key = ("mass_traces", rows.tobytes())
    if key not in p.memo:
        p.memo[key] = _mass_traces(p, rows)
    return p.memo[key].copy()


def _mass_traces(p: Problem, rows) -> np.ndarray:
    """:func:`mass_traces` on the data rows ``rows``, computed afresh."""
    Xs = p.Xt[torch.as_tensor(rows, device=p.Xt.device)]
    d = p.n_dof
    op = EulerLagrangeOperator(
        p.coordinates, p.terms, dtype=p.Xt.dtype, device=p.Xt.device
    )
    # (terms, dof, dof, rows): the kernels' layout, without a copy
    mass = op.mass_matrices_t(Xs[:, :d], Xs[:, d : 2 * d])
    traces = np.zeros(p.n_features)
    # The mean over the rows first: a reduction over the diagonal's strided
    # entries of every row took most of this function's time.
    mean = mass.mean(-1)
    traces[: op.n_terms] = to_numpy(torch.diagonal(mean, dim1=1, dim2=2).sum(1))
    return traces


def solve_mass(p: Problem, verbose, first=None):
    r"""Case III with the scale fixed by the mass matrix: mean tr(M(c)) = 1.

    Passive data fix the Lagrangian only up to a factor. Fixing one coefficient
    to 1 lets a combination of other terms cancel it where the data lie (on a
    pendulum swinging by +-1 rad, ``theta_dot**2 * (1 - cos(theta) -
    sin(theta)**2 / 2)`` nearly vanishes), giving a Lagrangian that is almost zero
    on the data and fits the residual trivially. Fixing instead the data mean of
    the trace of the learned mass matrix, :math:`\sum_k c_k \overline{\mathrm{tr}
    M_k} = 1` (scaled units), rules such models out. The constraint is eliminated
    through a pivot term (the largest contributor to the trace, found in two
    passes), and the sparse problem is solved as in case III. ``first``: the
    one-start result of the first pivot's problem, already computed (see
    :meth:`~lagsindy.cases.sparse.SparseSolve.stages`).
    """
    traces = mass_traces(p)
    free, pivot, t_scaled = _mass_start(p)
    for k in range(3):
        coef, result = _solve_pivot(
            p, free, pivot, t_scaled, verbose, first if k == 0 else None
        )
        share = np.abs(traces * coef)
        new = int(np.argmax(share))
        if new == pivot:
            break
        pivot = new
    # Report in the scale where the largest kinetic contributor has coefficient 1.
    coef = coef / coef[pivot]
    for st in result.stages:
        if st.coef[pivot] != 0:
            st.coef = st.coef / st.coef[pivot]
    return coef, result, pivot


def _mass_start(p: Problem):
    """The identifiable features, the first pivot term and the scaled mean traces
    of the mass normalization."""
    traces = mass_traces(p)
    free = np.flatnonzero(p.identifiable)
    scale = to_numpy(p.balanced.col_scale)
    t_scaled = np.where(scale > 0, traces / np.where(scale > 0, scale, 1.0), 0.0)
    if not np.any(t_scaled[free] != 0):
        raise ValueError(
            "no candidate term has a kinetic (velocity-squared) part on this data, "
            "so the mass matrix cannot fix the scale; give a fixed_term"
        )
    return free, int(free[np.argmax(np.abs(t_scaled[free]))]), t_scaled


def _solve_pivot(p: Problem, free, pivot, t_scaled, verbose, first=None):
    """Minimise the EL residual subject to sum_k t_k w_k = 1, pivot eliminated."""
    datafit, features, weights, to_coef = _pivot_problem(p, free, pivot, t_scaled)
    result = p.solver.stages(
        datafit, features, weights, verbose, reference=1.0, first=first
    )
    coef = to_coef(result.coef)
    for st in result.stages:
        st.coef = to_coef(st.coef)
        st.support = np.concatenate([[pivot], features[st.support]])
    return coef, result


def _pivot_problem(p: Problem, free, pivot, t_scaled):
    """The sparse problem of :func:`_solve_pivot`, in its scaled variables.

    Returns
    -------
    datafit : GramQuadratic
    features : ndarray of int
        The library indices of its variables (``free`` but the pivot).
    weights : Tensor
        Their L1 weights.
    to_coef : callable
        Maps the variables to coefficients over all features.
    """
    balanced = p.balanced
    dtype, device = balanced.gram.dtype, balanced.gram.device
    f = np.asarray(free)
    j = int(np.flatnonzero(f == pivot)[0])
    others = np.delete(np.arange(len(f)), j)
    g, s = balanced.block(f)
    t = torch.as_tensor(t_scaled[f], dtype=dtype, device=device)
    # w = T u + y0 with u the other coefficients: the constraint holds for any u.
    T = torch.eye(len(f), dtype=dtype, device=device)[
        :, torch.as_tensor(others, device=device)
    ]
    T[j, :] = -t[torch.as_tensor(others, device=device)] / t[j]
    y0 = torch.zeros(len(f), dtype=dtype, device=device)
    y0[j] = 1.0 / t[j]
    gq = T.T @ g @ T
    bq = -(T.T @ g @ y0)
    c0 = float(y0 @ g @ y0)
    if c0 <= 0:
        raise ValueError("the pivot term's Euler-Lagrange column is zero on the data")
    dq = torch.sqrt(torch.clamp(torch.diagonal(gq), min=0))
    dq = torch.where(dq > 0, dq, torch.ones_like(dq))
    datafit = GramQuadratic(gq / (dq[:, None] * dq[None, :]), bq / (dq * c0**0.5), 1.0)
    weights = torch.as_tensor(p.penalty[f[others]], dtype=dtype, device=device)

    def to_coef(u_scaled):
        u = torch.as_tensor(u_scaled, dtype=dtype, device=device)
        w = T @ (u * c0**0.5 / dq) + y0
        full = np.zeros(balanced.n_features)
        full[f] = to_numpy(w / s)
        return full

    return datafit, f[others], weights, to_coef


def acceleration_r2s(p: Problem, coefs, Xt) -> list:
    """Variance-weighted R^2 of the accelerations each model in ``coefs`` predicts.

    The Euler-Lagrange columns and per-term mass matrices of the union of the models'
    supports are evaluated once on ``Xt`` (one operator, not one per model). All the
    models are then scored together: their mass matrices ``M(c)`` and
    Euler-Lagrange residuals are one stacked product over the union's features, the
    errors of the accelerations ``M(c)^+ (-h(c))`` one batched closed form
    (:func:`_error_squares`) and the scores one vectorized R^2 (as
    :func:`r2_scores`). The result equals the former one-model-at-a-time scoring
    (``accelerations_from`` and ``sklearn.metrics.r2_score`` per model) up to
    rounding.

    Parameters
    ----------
    p : Problem
    coefs : list of ndarray of shape (n_features,)
        The models' coefficients.
    Xt : Tensor of shape (n_samples, 3 * n_dof)
        The rows to score on.

    Returns
    -------
    list of float
        One score per model; ``-inf`` for a model without terms or whose predicted
        accelerations are not finite.
    """
    supports = [np.flatnonzero(c) for c in coefs]
    scored = [j for j, s_ in enumerate(supports) if s_.size]
    if not scored:
        return [-np.inf] * len(coefs)
    union = np.unique(np.concatenate([supports[j] for j in scored]))
    op = p.feature_operator(union, Xt.device, Xt.dtype)
    n = p.n_dof
    q, qd, qdd = Xt[:, :n], Xt[:, n : 2 * n], Xt[:, 2 * n : 3 * n]
    # Samples last (the kernels' own layout): the models' combinations are plain
    # matrix products, without copies.
    theta = op.columns_t(Xt)  # (n_dof, features of the union, rows)
    mass = op.mass_matrices_t(q, qd)  # (terms of the union, n_dof, n_dof, rows)
    # Each scored model's coefficients over the union (zero off its support).
    c = torch.as_tensor(
        np.stack([coefs[j] for j in scored])[:, union], dtype=Xt.dtype, device=Xt.device
    )
    m, k = len(scored), op.n_terms
    # (models, i, j, rows)
    mc = (c[:, :k] @ mass.reshape(k, n * n * Xt.shape[0])).reshape(m, n, n, -1)
    # Each model's Euler-Lagrange residual r = M(c) qdd + h(c), (n_dof, models, rows)
    residual = torch.matmul(c, theta)
    # Squared errors summed in torch; a prediction that is not finite leaves its
    # sum not finite, and the model scores -inf.
    numerator = to_numpy(_error_squares(mc, residual, qdd.T))  # (models, n_dof)
    values = _r2_from_sums(numerator, _total_squares(to_numpy(qdd)))
    scores = [-np.inf] * len(coefs)
    for i, j in enumerate(scored):
        if np.all(np.isfinite(numerator[i])):
            scores[j] = float(values[i])
    return scores


def _error_squares(mc, residual, qdd_t):
    r"""Summed squared errors of the predicted accelerations, per model and dof.

    The prediction is :math:`M^{+} (-h) = M^{+} (M \ddot q - r)` with ``r`` the
    model's Euler-Lagrange residual, so where ``M`` is invertible the error
    :math:`\ddot q - M^{+}(M \ddot q - r)` is :math:`M^{-1} r`: for two degrees of
    freedom, the well-conditioned matrices (those :func:`pinv_solve` solves by
    Cramer's rule) give it without forming the prediction; the others, and other
    sizes, go through :func:`pinv_solve`.

    Parameters
    ----------
    mc : Tensor of shape (models, n_dof, n_dof, rows)
    residual : Tensor of shape (n_dof, models, rows)
    qdd_t : Tensor of shape (n_dof, rows)

    Returns
    -------
    Tensor of shape (models, n_dof)
    """
    n = mc.shape[1]
    if n != 2:
        inertial = sum(mc[:, :, j] * qdd_t[j] for j in range(n))  # (models, i, rows)
        rhs = (inertial - residual.transpose(0, 1)).transpose(1, 2)  # (m, rows, n)
        pred = pinv_solve(mc.permute(0, 3, 1, 2), rhs)
        return ((qdd_t.T[None] - pred) ** 2).sum(1)
    a, b, c = mc[:, 0, 0], mc[:, 1, 0], mc[:, 1, 1]
    r0, r1 = residual[0], residual[1]
    easy, safe = _cramer_safe(a, b, c)
    e0 = (c * r0 - b * r1) / safe
    e1 = (a * r1 - b * r0) / safe
    if not bool(easy.all()):
        hard = (~easy).nonzero(as_tuple=True)
        q0, q1 = qdd_t[0][hard[1]], qdd_t[1][hard[1]]
        ah, bh, ch = a[hard], b[hard], c[hard]
        rhs0 = ah * q0 + mc[:, 0, 1][hard] * q1 - r0[hard]  # M qdd - r
        rhs1 = bh * q0 + ch * q1 - r1[hard]
        pred = _pinv_solve2(ah, bh, ch, rhs0, rhs1)
        e0[hard] = q0 - pred[:, 0]
        e1[hard] = q1 - pred[:, 1]
    return torch.stack([(e0 * e0).sum(1), (e1 * e1).sum(1)], dim=1)


def pinv_solve(mat, rhs):
    """``pinv(mat, hermitian=True) @ rhs`` for a batch of small symmetric matrices.

    The pseudo-inverse of :func:`torch.linalg.pinv` (``hermitian=True``, default
    tolerance: eigenvalues of magnitude at most ``n * eps`` times the largest are
    dropped; the lower triangle is used), applied to ``rhs``. For ``n = 1`` and
    ``n = 2`` the eigen-decomposition is in closed form (the 2 x 2 one as LAPACK's
    ``dlaev2``: the smaller eigenvalue from the determinant, without cancellation),
    element-wise over the batch instead of one LAPACK call per matrix; 2 x 2
    matrices whose condition number is certainly below 1e8 are solved by Cramer's
    rule. The result equals ``torch.linalg.pinv``'s up to rounding (within a small
    multiple of the condition number times the machine epsilon). Larger matrices use
    :func:`torch.linalg.pinv`.

    Parameters
    ----------
    mat : Tensor of shape (..., n, n)
        Symmetric matrices.
    rhs : Tensor of shape (..., n)

    Returns
    -------
    Tensor of shape (..., n)
    """
    n = mat.shape[-1]
    eps = torch.finfo(mat.dtype).eps
    if n == 1:
        a = mat[..., 0, 0]
        keep = a.abs() > eps * a.abs()
        inv = torch.where(keep, 1.0 / torch.where(keep, a, torch.ones_like(a)), 0.0)
        return rhs * inv.unsqueeze(-1)
    if n != 2:
        return (torch.linalg.pinv(mat, hermitian=True) @ rhs.unsqueeze(-1)).squeeze(-1)
    a, b, c = mat[..., 0, 0], mat[..., 1, 0], mat[..., 1, 1]
    r0, r1 = rhs[..., 0], rhs[..., 1]
    # Well-conditioned matrices (most, for a model with a mass matrix) by Cramer's
    # rule, which the pseudo-inverse equals there up to rounding: the smaller
    # eigenvalue is at least |det| / (|a| + |c| + 2|b|), so a condition number
    # below 1e8 is certain. The others by the eigen-decomposition below.
    easy, safe = _cramer_safe(a, b, c)
    out = torch.stack([c * r0 - b * r1, a * r1 - b * r0], dim=-1) / safe.unsqueeze(-1)
    if bool(easy.all()):
        return out
    hard = (~easy).nonzero(as_tuple=True)  # one search, five gathers
    out[hard] = _pinv_solve2(a[hard], b[hard], c[hard], r0[hard], r1[hard])
    return out


def _cramer_safe(a, b, c):
    """Which ``[[a, b], [b, c]]`` Cramer's rule solves (condition number certainly
    below 1e8, see :func:`pinv_solve`), and their determinants (1 elsewhere)."""
    det = a * c - b * b
    norm = a.abs() + c.abs() + 2 * b.abs()
    easy = det.abs() > 1e-8 * norm * norm
    return easy, torch.where(easy, det, 1.0)


def _pinv_solve2(a, b, c, r0, r1):
    """:func:`pinv_solve` of ``[[a, b], [b, c]]`` by the eigen-decomposition."""
    eps = torch.finfo(a.dtype).eps
    rt1, rt2, cs, sn = _eig2(a, b, c)
    big = rt1.abs()
    tol = 2 * eps * big
    inv1 = torch.where(big > tol, 1.0 / torch.where(big > tol, rt1, 1.0), 0.0)
    keep2 = rt2.abs() > tol
    inv2 = torch.where(keep2, 1.0 / torch.where(keep2, rt2, 1.0), 0.0)
    p1 = (cs * r0 + sn * r1) * inv1  # along (cs, sn), the eigenvalue rt1
    p2 = (cs * r1 - sn * r0) * inv2  # along (-sn, cs), the eigenvalue rt2
    return torch.stack([cs * p1 - sn * p2, sn * p1 + cs * p2], dim=-1)


def _eig2(a, b, c):
    """Eigen-decomposition of the symmetric 2 x 2 matrices ``[[a, b], [b, c]]``.

    LAPACK's ``dlaev2``, element-wise: ``rt1`` is the eigenvalue of larger
    magnitude, ``rt2`` the other, ``(cs, sn)`` the unit eigenvector of ``rt1``.
    """
    one = torch.ones_like(a)
    sm, df = a + c, a - c
    adf, tb = df.abs(), 2.0 * b
    ab = tb.abs()
    acmx = torch.where(a.abs() > c.abs(), a, c)
    acmn = torch.where(a.abs() > c.abs(), c, a)
    safe_adf = torch.where(adf > 0, adf, one)
    safe_ab = torch.where(ab > 0, ab, one)
    rt = torch.where(
        adf > ab,
        adf * torch.sqrt(1.0 + (ab / safe_adf) ** 2),
        torch.where(
            adf < ab, ab * torch.sqrt(1.0 + (adf / safe_ab) ** 2), ab * 2.0**0.5
        ),
    )
    rt1 = torch.where(sm < 0, 0.5 * (sm - rt), 0.5 * (sm + rt))
    safe_rt1 = torch.where(rt1 != 0, rt1, one)
    rt2 = torch.where(sm != 0, (acmx / safe_rt1) * acmn - (b / safe_rt1) * b, -0.5 * rt)
    sgn1 = torch.where(sm < 0, -one, one)
    cs = torch.where(df >= 0, df + rt, df - rt)
    sgn2 = torch.where(df >= 0, one, -one)
    acs = cs.abs()
    ct = -tb / torch.where(cs != 0, cs, one)
    sn_a = 1.0 / torch.sqrt(1.0 + ct * ct)
    cs_a = ct * sn_a
    tn = -cs / torch.where(tb != 0, tb, one)
    cs_b = torch.where(ab == 0, one, 1.0 / torch.sqrt(1.0 + tn * tn))
    sn_b = torch.where(ab == 0, torch.zeros_like(a), tn * cs_b)
    cs1 = torch.where(acs > ab, cs_a, cs_b)
    sn1 = torch.where(acs > ab, sn_a, sn_b)
    swap = sgn1 == sgn2
    cs1, sn1 = torch.where(swap, -sn1, cs1), torch.where(swap, cs1, sn1)
    return rt1, rt2, cs1, sn1


def r2_scores(true, pred):
    """``sklearn.metrics.r2_score(true, pred[m], multioutput="variance_weighted")``
    for every model ``m`` at once.

    Parameters
    ----------
    true : ndarray of shape (n_samples, n_outputs)
    pred : ndarray of shape (n_models, n_samples, n_outputs)

    Returns
    -------
    ndarray of shape (n_models,)
        As ``r2_score`` computes it (``force_finite=True``): an output with zero
        variance scores 1 when predicted exactly, else 0; when every output has
        zero variance, the outputs' scores are averaged with equal weights.
    """
    numerator = ((true[None] - pred) ** 2).sum(axis=1)  # (models, outputs)
    return _r2_from_sums(numerator, _total_squares(true))


def _total_squares(true):
    """Per output, the squared deviations of ``true`` from their mean, summed."""
    return ((true - np.average(true, axis=0)) ** 2).sum(axis=0)


def _r2_from_sums(numerator, denominator):
    """:func:`r2_scores` from the summed squared errors (models, outputs) and
    :func:`_total_squares` of the true values."""
    nonzero_den = denominator != 0
    nonzero_num = numerator != 0
    valid = nonzero_den[None] & nonzero_num
    out = np.ones_like(numerator)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = 1 - numerator / np.where(nonzero_den, denominator, 1.0)[None]
    out = np.where(valid, ratio, out)
    out = np.where(nonzero_num & ~nonzero_den[None], 0.0, out)
    if not np.any(nonzero_den):  # every output constant: uniform weights
        return out.mean(axis=1)
    return np.average(out, axis=1, weights=denominator)
