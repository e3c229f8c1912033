"""The paper's staged schedule: FISTA stages, hard thresholds, lower penalty, refit."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from sklearn.exceptions import ConvergenceWarning

from .datafits import GramQuadratic
from .fista import fista, proximal_gradient
from .penalties import L1


# --------------------------------------------------------------------------- stages
@dataclass
class Stage:
    """Record of one stage of :func:`staged_fista` (indices refer to all features)."""

    lam: float
    step: float
    n_iter: int
    converged: bool
    stop_crit: float
    coef: np.ndarray
    support: np.ndarray
    cost: float


@dataclass
class StagedResult:
    """Outcome of :func:`staged_fista`."""

    coef: torch.Tensor
    support: np.ndarray
    stages: list
    n_iter: int
    converged: bool
    cost: float
    step_reductions: int = 0
    # The first stage's FISTA solution before thresholding (problem variables over
    # every feature): a warm start for a path from a smaller lam (continuation).
    first_stage: torch.Tensor | None = None


def staged_fista(
    datafit: GramQuadratic,
    *,
    lam: float,
    penalty_weights: torch.Tensor | None = None,
    threshold: float | torch.Tensor = 0.05,
    reference: float = 0.0,
    lam_decay: float = 10.0,
    step_growth: float = 2.0,
    alpha: float | None = None,
    max_stages: int = 5,
    max_iter: int = 10_000,
    tol: float = 1e-3,
    solver_tol: float = 1e-8,
    debias: bool = True,
    verbose: int = 0,
    w0: torch.Tensor | None = None,
    nonneg: torch.Tensor | None = None,
) -> StagedResult:
    r"""The xL-SINDy schedule: FISTA stages with hard thresholding between them.

    Each stage solves the L1-penalised problem on the current support, then removes
    the penalised coefficients whose magnitude is below
    ``threshold * max(reference, max_k |w_k|)``; the next stage divides ``lam`` by
    ``lam_decay`` and, when ``alpha`` is given, multiplies the step by
    ``step_growth`` (with ``alpha=None`` the step is ``1/L`` of the current,
    smaller problem, which rises by itself as terms leave). The schedule stops when
    the relative residual of the stage's thresholded solution is at most ``tol``,
    or after ``max_stages``. With ``debias=True`` the final support is refitted
    without penalty.

    A stage whose solution is all zero (``lam`` above the largest useful value)
    removes nothing; the schedule then simply lowers ``lam``.

    Parameters
    ----------
    datafit : GramQuadratic
    lam : float
        Penalty of the first stage.
    penalty_weights : Tensor, optional
        0 for unpenalised (known) terms, 1 otherwise.
    threshold : float or Tensor of shape (p,), default=0.05
        Relative hard threshold (one value, or one per feature).
    reference : float, default=0.0
        Magnitude of a fixed term in the same units as ``w`` (1 for case III).
    lam_decay, step_growth : float
    alpha : float, optional
        Initial step; ``None`` means ``1/L`` at every stage.
    max_stages, max_iter : int
    tol : float
        Stage-level tolerance on the relative residual.
    solver_tol : float
        KKT tolerance of each FISTA run.
    debias : bool
    verbose : int
    w0 : Tensor, optional
        Starting point of the first stage (zeros by default).
    nonneg : Tensor of bool, shape (p,), optional
        Coefficients constrained to be non-negative (dissipation), enforced by
        projection in FISTA's proximal step and in the unpenalised refit.

    Returns
    -------
    StagedResult
    """
    p = datafit.n_features
    template = datafit.zeros()
    device = template.device
    weights = torch.ones_like(template) if penalty_weights is None else penalty_weights
    support = np.arange(p)
    thresholds = (
        torch.as_tensor(threshold, dtype=template.dtype, device=device)
        .expand(p)
        .clone()
    )
    w_full = template.clone() if w0 is None else w0.clone()
    if nonneg is not None:
        nonneg = torch.as_tensor(nonneg, dtype=torch.bool, device=device)
        w_full = torch.where(nonneg, torch.clamp(w_full, min=0.0), w_full)
    stages, total_iter, reductions = [], 0, 0
    converged = True
    cur_lam = float(lam)
    cost = datafit.relative_residual(w_full)
    first_stage = None
    for s in range(max_stages):
        sub = datafit.restrict(support)
        sup_idx = torch.as_tensor(support, device=device)
        pen = L1(cur_lam, weights[sup_idx], None if nonneg is None else nonneg[sup_idx])
        step = None if alpha is None else float(alpha) * step_growth**s
        solver = fista if sub.lipschitz() is not None else proximal_gradient
        res = solver(
            sub,
            pen,
            w_full[torch.as_tensor(support, device=device)],
            step=step,
            max_iter=max_iter,
            tol=solver_tol,
        )
        total_iter += res.n_iter
        reductions += res.step_reductions
        converged = converged and res.converged
        w_sub = res.coef
        if s == 0:
            first_stage = template.clone()
            first_stage[torch.as_tensor(support, device=device)] = w_sub
        mags = w_sub.abs()
        largest = float(mags.max()) if mags.numel() else 0.0
        if largest > 0:  # an all-zero stage (lam too high) removes nothing
            sup_t = torch.as_tensor(support, device=device)
            penalised = weights[sup_t] > 0
            keep = ~((mags < thresholds[sup_t] * max(largest, reference)) & penalised)
        else:
            keep = torch.ones_like(mags, dtype=torch.bool)
        w_sub = torch.where(keep, w_sub, torch.zeros_like(w_sub))
        w_full = template.clone()
        w_full[torch.as_tensor(support, device=device)] = w_sub
        cost = datafit.relative_residual(w_full)
        new_support = support[keep.cpu().numpy()]
        stages.append(
            Stage(
                cur_lam,
                res.step,
                res.n_iter,
                res.converged,
                res.stop_crit,
                w_full.detach().cpu().numpy().copy(),
                new_support.copy(),
                cost,
            )
        )
        if verbose:
            print(
                f"[lagsindy] stage {s + 1}: lam={cur_lam:.3g} step={res.step:.3g} "
                f"iterations={res.n_iter}{'' if res.converged else ' (max_iter)'} "
                f"terms={len(new_support)} relative residual={cost:.3g}"
            )
        support = new_support
        if cost <= tol and float(w_sub.abs().max() if w_sub.numel() else 0.0) > 0:
            break
        cur_lam /= lam_decay
    if debias and len(support):
        w_full, support = _debias(
            datafit, support, weights, thresholds, reference, w_full, nonneg
        )
        cost = datafit.relative_residual(w_full)
    return StagedResult(
        w_full, support, stages, total_iter, converged, cost, reductions, first_stage
    )


def _debias(datafit, support, weights, thresholds, reference, w_start, nonneg=None):
    """Unpenalised refit of the support, thresholding the refit until it is stable.

    The L1 stages shrink coefficients, so a term that the penalty kept alive only
    to stand in for a shrunk one can look large before the refit and negligible
    after it; it is removed and the rest refitted (at most ``len(support)`` times).
    Coefficients in ``nonneg`` stay non-negative: where the unconstrained refit
    makes one negative, the refit is the non-negative least-squares solution
    (projected FISTA with no penalty).
    """
    device = datafit.zeros().device
    while True:
        idx = torch.as_tensor(support, device=device)
        sub = datafit.restrict(support)
        w_ls = sub.least_squares(w0=w_start[idx])
        if nonneg is not None and bool((nonneg[idx] & (w_ls < 0)).any()):
            start = torch.where(nonneg[idx], torch.clamp(w_ls, min=0.0), w_ls)
            w_ls = fista(
                sub, L1(0.0, None, nonneg[idx]), start, max_iter=50_000, tol=1e-12
            ).coef
        mags = w_ls.abs()
        peak = max(float(mags.max()), reference) if mags.numel() else 0.0
        drop = (mags < thresholds[idx] * peak) & (weights[idx] > 0)
        if not bool(drop.any()) or bool(drop.all()):
            break
        support = support[~drop.cpu().numpy()]
    w_full = datafit.zeros()
    w_full[idx] = w_ls
    return w_full, support


def fista_path(datafit, lams, *, penalty_weights=None, max_iter=10_000, tol=1e-8):
    """Solutions of the L1 problem along decreasing ``lams``, warm-started.

    Returns
    -------
    coefs : ndarray of shape (len(lams), p)
    n_iters : list of int
    """
    w = datafit.zeros()
    coefs, n_iters = [], []
    for lam in lams:
        res = fista(datafit, L1(lam, penalty_weights), w, max_iter=max_iter, tol=tol)
        w = res.coef
        coefs.append(w.detach().cpu().numpy().copy())
        n_iters.append(res.n_iter)
    return np.array(coefs), n_iters


def warn_not_converged(stages, max_iter):
    """Emit one ConvergenceWarning listing the stages that hit ``max_iter``."""
    bad = [i + 1 for i, st in enumerate(stages) if not st.converged]
    if bad:
        warnings.warn(
            f"FISTA reached max_iter={max_iter} before its KKT tolerance in stage(s) "
            f"{bad}; the support may be wrong. Increase max_iter, or raise "
            "solver_tol if the residual cost is already small.",
            ConvergenceWarning,
            stacklevel=3,
        )


def staged_fista_batch(
    datafits,
    *,
    lam: float,
    penalty_weights,
    threshold,
    reference: float = 0.0,
    lam_decay: float = 10.0,
    step_growth: float = 2.0,
    alpha: float | None = None,
    max_stages: int = 5,
    max_iter: int = 10_000,
    tol: float = 1e-3,
    solver_tol: float = 1e-8,
    debias: bool = True,
    nonneg=None,
    shared=None,
    w0=None,
) -> list:
    """:func:`staged_fista` of several problems, their FISTA runs batched.

    Every problem goes through the schedule of :func:`staged_fista` (same stages,
    thresholds, stopping rule and unpenalised refit); the FISTA runs of one stage
    are one :func:`~lagsindy.solvers.fista.fista_batch` call over the problems
    still in the schedule, so that the interpreter overhead of an iteration is paid
    once per stage rather than once per problem. The results are those of
    :func:`staged_fista` on each problem, up to rounding.

    Parameters
    ----------
    datafits : list of GramQuadratic
        CPU problems; without ``shared``, all with the same number of features.
    lam, reference, lam_decay, step_growth, alpha, max_stages, max_iter, tol, \
solver_tol, debias
        As in :func:`staged_fista` (shared by the problems).
    penalty_weights : list of Tensor
        Each problem's L1 weights.
    threshold : list of Tensor
        Each problem's relative hard thresholds (one per feature).
    nonneg : list of (Tensor of bool or None), optional
        Each problem's non-negative features.
    shared : tuple (ndarray of shape (m, m), list of int ndarray), optional
        One matrix ``C`` and, per problem, the indices ``idx`` with
        ``datafits[r].gram == C[idx][:, idx]``: the problems' gradients are then
        one product with ``C``.
    w0 : list of Tensor, optional
        Each problem's starting point (default zeros).

    Returns
    -------
    list of StagedResult
        One per datafit, in order.
    """
    from .fista import fista_batch

    n_prob = len(datafits)
    if n_prob == 0:
        return []
    dtype = datafits[0].rhs.dtype

    def arr(t):
        return t.detach().cpu().numpy()

    if shared is None:
        gram = np.stack([arr(d.gram) for d in datafits])
        index = [np.arange(d.n_features) for d in datafits]
    else:
        gram, index = np.asarray(shared[0]), [np.asarray(i) for i in shared[1]]
    m = gram.shape[-1]
    # Every problem lives in the coordinates of ``gram`` (its features at
    # ``index[r]``, zeros elsewhere), so a stage's thresholds, supports and costs
    # are array operations over all the problems at once.
    rhs = np.zeros((n_prob, m))
    w_np = np.zeros((n_prob, m))
    thr = np.zeros((n_prob, m))
    on = np.zeros((n_prob, m), dtype=bool)  # the current supports
    w_all = np.zeros((n_prob, m))  # the current (thresholded) solutions
    nn_np = None
    weights = [torch.as_tensor(w, dtype=dtype) for w in penalty_weights]
    nonneg = [None] * n_prob if nonneg is None else list(nonneg)
    nn_t = [None if x is None else torch.as_tensor(x, dtype=torch.bool) for x in nonneg]
    thresholds = [
        torch.as_tensor(t, dtype=dtype).expand(d.n_features).clone()
        for t, d in zip(threshold, datafits)
    ]
    for r, (d, idx) in enumerate(zip(datafits, index)):
        rhs[r, idx] = arr(d.rhs)
        w_np[r, idx] = arr(weights[r])
        thr[r, idx] = arr(thresholds[r])
        on[r, idx] = True
        if w0 is not None:
            w_all[r, idx] = arr(torch.as_tensor(w0[r], dtype=dtype))
        if nn_t[r] is not None:
            if nn_np is None:
                nn_np = np.zeros((n_prob, m), dtype=bool)
            nn_np[r, idx] = arr(nn_t[r])
    penalised = w_np > 0
    const = np.array([d.const for d in datafits])
    stages = [[] for _ in range(n_prob)]
    total_iter = np.zeros(n_prob, dtype=np.int64)
    reductions = np.zeros(n_prob, dtype=np.int64)
    converged = np.ones(n_prob, dtype=bool)

    # Every problem's own coordinates, gathered at once when they are as many.
    stacked_index = np.stack(index) if len({idx.size for idx in index}) == 1 else None

    def own_coordinates(values, sel):
        """Rows of ``values`` (one per problem in ``sel``) on their own coordinates."""
        if stacked_index is not None:
            return np.take_along_axis(values, stacked_index[sel], axis=1)
        return [v[index[r]] for v, r in zip(values, sel)]

    def residuals(sel, w):
        """Relative residuals of the problems ``sel`` at ``w`` (one row each)."""
        g = gram if shared is not None else gram[sel]
        return _relative_residuals(g, rhs[sel], const[sel], w)

    costs = residuals(np.arange(n_prob), w_all)
    first_stage = [None] * n_prob
    rows = np.arange(n_prob)
    cur_lam = float(lam)
    for s in range(max_stages):
        if rows.size == 0:
            break
        step = None if alpha is None else float(alpha) * step_growth**s
        res = fista_batch(
            gram if shared is not None else gram[rows],
            rhs[rows],
            const[rows],
            cur_lam,
            w_np[rows],
            w_all[rows],
            on[rows],
            None if nn_np is None else nn_np[rows],
            step=None if step is None else np.full(rows.size, step),
            max_iter=max_iter,
            tol=solver_tol,
        )
        coef = np.where(on[rows], res.coef, 0.0)
        if s == 0:
            for r, own in zip(rows, own_coordinates(coef, rows)):
                first_stage[r] = torch.as_tensor(own, dtype=dtype)
        # The hard threshold of staged_fista, relative to the largest coefficient
        # (or ``reference``); an all-zero stage (lam too high) removes nothing.
        mags = np.abs(coef)
        largest = mags.max(1)
        small = mags < thr[rows] * np.maximum(largest, reference)[:, None]
        keep = on[rows] & ~(small & penalised[rows] & (largest > 0)[:, None])
        coef = np.where(keep, coef, 0.0)
        on[rows], w_all[rows] = keep, coef
        stage_costs = residuals(rows, coef)
        total_iter[rows] += res.n_iter
        reductions[rows] += res.step_reductions
        converged[rows] &= res.converged
        records = zip(
            rows,
            res.step.tolist(),
            res.n_iter.tolist(),
            res.converged.tolist(),
            res.stop_crit.tolist(),
            own_coordinates(coef, rows),
            own_coordinates(keep, rows),
            stage_costs,
        )
        for r, step_r, n_iter, conv, crit, coef_r, keep_r, cost in records:
            costs[r] = cost
            stages[r].append(
                Stage(
                    cur_lam,
                    step_r,
                    n_iter,
                    conv,
                    crit,
                    coef_r,
                    keep_r.nonzero()[0],
                    cost,
                )
            )
        done = (np.array(stage_costs) <= tol) & np.any(coef != 0, axis=1)
        rows = rows[~done]
        cur_lam /= lam_decay
    everyone = np.arange(n_prob)
    supports = [k.nonzero()[0] for k in own_coordinates(on, everyone)]
    w_full = [torch.as_tensor(w, dtype=dtype) for w in own_coordinates(w_all, everyone)]
    total_iter, reductions = total_iter.tolist(), reductions.tolist()
    converged = converged.tolist()
    if debias:
        # The refit of the problems without sign constraints, all at once; those
        # with non-negative features go through _debias one by one (below).
        plain = np.array([x is None or not bool(x.any()) for x in nn_t])
        plain &= on.any(1)
        sel = np.flatnonzero(plain)
        if sel.size:
            w_ls, on[sel] = _debias_batch(
                gram if shared is not None else gram[sel],
                on[sel],
                rhs[sel],
                penalised[sel],
                thr[sel],
                reference,
            )
            fitted = residuals(sel, w_ls)
            refits = zip(
                sel, own_coordinates(on[sel], sel), own_coordinates(w_ls, sel), fitted
            )
            for r, on_r, w_r, cost in refits:
                supports[r] = on_r.nonzero()[0]
                w_full[r] = torch.as_tensor(w_r, dtype=dtype)
                costs[r] = cost
    results = []
    for r in range(n_prob):
        w, support, cost = w_full[r], supports[r], costs[r]
        if debias and len(support) and not plain[r]:
            w, support = _debias(
                datafits[r], support, weights[r], thresholds[r], reference, w, nn_t[r]
            )
            cost = datafits[r].relative_residual(w)
        results.append(
            StagedResult(
                w,
                support,
                stages[r],
                total_iter[r],
                converged[r],
                cost,
                reductions[r],
                first_stage[r],
            )
        )
    return results


def _debias_batch(gram, on, rhs, penalised, thr, reference, rtol=1e-13):
    """:func:`_debias` of several problems without sign constraints, at once.

    Each row's support ``on`` is refitted by the minimum-norm least squares of
    ``GramQuadratic.least_squares`` (eigenvalues up to ``rtol`` times the largest
    dropped) on its block of ``gram`` (shared, or one per row), padded with zeros
    to the batch's coordinates: the padding adds zero eigenvalues, which are
    dropped, so the kept eigenvectors lie on the support. Penalised coefficients
    below ``thr`` times the largest (or ``reference``) are removed and the rest
    refitted, until nothing is removed or everything would be.

    Returns
    -------
    w : ndarray of shape (R, m)
    on : ndarray of bool, shape (R, m)
        The refitted supports.
    """
    on = on.copy()
    w = np.zeros(on.shape)
    rows = np.arange(on.shape[0])
    while rows.size:
        both = on[rows][:, :, None] & on[rows][:, None, :]
        g = gram if gram.ndim == 2 else gram[rows]
        evals, evecs = np.linalg.eigh(np.where(both, g, 0.0))
        keep = evals > rtol * np.maximum(evals[:, -1:], 1e-300)
        inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
        proj = np.einsum("rji,rj->ri", evecs, np.where(on[rows], rhs[rows], 0.0))
        fit = np.einsum("rij,rj->ri", evecs, inv * proj)
        fit = np.where(on[rows], fit, 0.0)
        w[rows] = fit
        mags = np.abs(fit)
        peak = np.maximum(mags.max(1), reference)[:, None]
        drop = on[rows] & (mags < thr[rows] * peak) & penalised[rows]
        n_drop, n_on = drop.sum(1), on[rows].sum(1)
        again = (n_drop > 0) & (n_drop < n_on)
        on[rows[again]] &= ~drop[again]
        rows = rows[again]
    return w, on


def _relative_residuals(gram, rhs, const, w):
    """``GramQuadratic.relative_residual`` of every row of ``w`` (batch coordinates).

    ``gram`` is one matrix shared by the rows, shape (m, m), or one per row,
    (R, m, m); ``w`` and ``rhs`` are zero off each row's coordinates.
    """
    gw = w @ gram if gram.ndim == 2 else np.matmul(gram, w[:, :, None])[:, :, 0]
    value = 0.5 * np.einsum("ri,ri->r", w, gw) - np.einsum("ri,ri->r", rhs, w)
    value = value + 0.5 * const
    out = np.where(const > 0, 2.0 * value / np.where(const > 0, const, 1.0), 0.0)
    return [max(0.0, float(c)) for c in out]
