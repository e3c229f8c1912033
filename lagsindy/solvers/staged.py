"""The paper's staged schedule: FISTA stages, hard thresholds, lower penalty, refit.

The schedule is written once (:func:`_schedule`) over a batch of problems, one
problem being a batch of one: :func:`staged_fista` runs it on one datafit,
:func:`staged_fista_batch` on several, whose FISTA runs, residuals and refits are
batched where the problems allow it (see :mod:`~lagsindy.solvers._problems`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from sklearn.exceptions import ConvergenceWarning

from .._stacklevel import outside_stacklevel
from ._problems import Alone, Lockstep
from .datafits import GramQuadratic
from .fista import fista
from .penalties import L1
from .settings import EQUATION_THRESHOLD, MAX_ITER, SOLVER_TOL


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
    datafit,
    *,
    lam: float,
    penalty_weights: torch.Tensor | None = None,
    threshold: float | torch.Tensor = 0.05,
    w0: torch.Tensor | None = None,
    nonneg: torch.Tensor | None = None,
    **schedule,
) -> StagedResult:
    r"""The xL-SINDy schedule: FISTA stages with hard thresholding between them.

    Each stage solves the L1-penalised problem on the current support, then removes
    the penalised coefficients whose magnitude is below
    ``threshold * max(reference, max_k |w_k|)`` (except, for a datafit of several
    equations, a term that contributes at least ``equation_threshold`` of the
    largest term of some equation); the next stage divides ``lam`` by
    ``lam_decay`` and, when ``alpha`` is given, multiplies the step by
    ``step_growth`` (with ``alpha=None`` the step is ``1/L`` of the current,
    smaller problem, which rises by itself as terms leave). The schedule stops when
    the relative residual of the stage's thresholded solution is at most ``tol``,
    or after ``max_stages``. With ``debias=True`` the final support is refitted
    without penalty, and a term the refit leaves below the threshold is removed and
    the rest refitted again (the L1 stages shrink coefficients, so a term that the
    penalty kept alive only to stand in for a shrunk one can look large before the
    refit and negligible after it).

    A stage whose solution is all zero (``lam`` above the largest useful value)
    removes nothing; the schedule then simply lowers ``lam``. A datafit without a
    Lipschitz constant (case II's) runs its stages by :func:`proximal_gradient`.
    The defaults are those of :class:`~lagsindy.solvers.StagedFISTA`.

    Parameters
    ----------
    datafit : GramQuadratic or AccelerationDatafit
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
    equation_threshold : float or None, default=0.25
        See :class:`~lagsindy.solvers.StagedFISTA`; it needs a
        :class:`GramQuadratic` with ``equation_shares`` (else only ``threshold``
        applies).
    **schedule
        ``reference``, ``lam_decay``, ``step_growth``, ``alpha``, ``max_stages``,
        ``max_iter``, ``tol``, ``solver_tol``, ``debias``, ``verbose`` and
        ``equation_threshold`` as above: passed to :func:`staged_fista_batch`,
        whose signature holds their defaults.

    Returns
    -------
    StagedResult
    """
    return staged_fista_batch(
        [datafit],
        lam=lam,
        penalty_weights=[penalty_weights],
        threshold=[threshold],
        w0=[w0],
        nonneg=[nonneg],
        **schedule,
    )[0]


def staged_fista_batch(
    datafits,
    *,
    lam: float,
    penalty_weights=None,
    threshold=0.05,
    reference: float = 0.0,
    lam_decay: float = 10.0,
    step_growth: float = 2.0,
    alpha: float | None = None,
    max_stages: int = 5,
    max_iter: int = MAX_ITER,
    tol: float = 1e-3,
    solver_tol: float = SOLVER_TOL,
    debias: bool = True,
    verbose: int = 0,
    nonneg=None,
    shared=None,
    w0=None,
    equation_threshold: float | None = EQUATION_THRESHOLD,
) -> list:
    """:func:`staged_fista` of several problems, batched where they allow it.

    Every problem goes through the schedule of :func:`staged_fista` (the same
    code: same stages, thresholds, stopping rule and refit). Problems that are CPU
    double-precision :class:`GramQuadratic`\\ s of one size (or, with ``shared``,
    blocks of one matrix) advance in lockstep: the FISTA runs of one stage are one
    :func:`~lagsindy.solvers.fista_batch` call over the problems still in the
    schedule, so the interpreter overhead of an iteration is paid once per stage
    rather than once per problem, and their refits are one batched
    eigen-decomposition per round. The others, and a problem alone, are solved one
    by one on their own supports. The results are those of :func:`staged_fista` on
    each problem, up to rounding (the batched refit differs from a lone one by up to
    1e-10 relative on ill-conditioned supports).

    Parameters
    ----------
    datafits : list of GramQuadratic or AccelerationDatafit
    lam, reference, lam_decay, step_growth, alpha, max_stages, max_iter, tol, \
solver_tol, debias, verbose, equation_threshold
        As in :func:`staged_fista` (shared by the problems).
    penalty_weights : list of (Tensor or None), optional
        Each problem's L1 weights (default ones).
    threshold : float or list of (float or Tensor), default=0.05
        Each problem's relative hard thresholds (one value, or one per feature).
    nonneg : list of (Tensor of bool or None), optional
        Each problem's non-negative features.
    shared : tuple (ndarray of shape (m, m), list of int ndarray), optional
        One matrix ``C`` and, per problem, the indices ``idx`` with
        ``datafits[r].gram == C[idx][:, idx]``: the problems' gradients are then
        one product with ``C``.
    w0 : list of (Tensor or None), optional
        Each problem's starting point (default zeros).

    Returns
    -------
    list of StagedResult
        One per datafit, in order.
    """
    n = len(datafits)
    per = {
        "weights": [None] * n if penalty_weights is None else list(penalty_weights),
        "thresholds": (
            list(threshold) if isinstance(threshold, (list, tuple)) else [threshold] * n
        ),
        "nonneg": [None] * n if nonneg is None else list(nonneg),
        "w0": [None] * n if w0 is None else list(w0),
    }
    settings = dict(
        lam=lam,
        alpha=alpha,
        reference=reference,
        lam_decay=lam_decay,
        step_growth=step_growth,
        max_stages=max_stages,
        max_iter=max_iter,
        tol=tol,
        solver_tol=solver_tol,
        debias=debias,
        verbose=verbose,
        equation_threshold=equation_threshold,
    )
    results = [None] * n
    for members, kind, share in _batches(datafits, shared):
        args = [[per[key][j] for j in members] for key in per]
        if kind is Lockstep:
            problems = Lockstep([datafits[j] for j in members], *args, shared=share)
        else:
            problems = Alone([datafits[j] for j in members], *args)
        for j, res in zip(members, _schedule(problems, **settings)):
            results[j] = res
    return results


def _batches(datafits, shared):
    """The batches of :func:`staged_fista_batch`: ``(members, kind, shared)``.

    Lockstep batches of two or more CPU float64 Gram quadratics: all of them on
    ``shared`` when given, else one batch per size; every other problem alone.
    """
    lockstep = [
        type(d) is GramQuadratic
        and d.gram.device.type == "cpu"
        and d.gram.dtype == torch.float64
        for d in datafits
    ]
    n = len(datafits)
    if n > 1 and shared is not None and all(lockstep):
        return [(list(range(n)), Lockstep, shared)]
    by_size = {}
    for j, d in enumerate(datafits):
        if lockstep[j]:
            by_size.setdefault(d.n_features, []).append(j)
    out = [
        (members, Lockstep, None) for members in by_size.values() if len(members) > 1
    ]
    batched = {j for members, _, _ in out for j in members}
    alone = [j for j in range(n) if j not in batched]
    if alone:
        out.append((alone, Alone, None))
    return out


def _schedule(
    problems,
    *,
    lam,
    alpha,
    reference,
    lam_decay,
    step_growth,
    max_stages,
    max_iter,
    tol,
    solver_tol,
    debias,
    verbose,
    equation_threshold=EQUATION_THRESHOLD,
):
    """The staged schedule of every problem of ``problems`` (see
    :func:`staged_fista`); a list of :class:`StagedResult`, in order."""
    n = problems.n
    on = problems.mask.copy()  # the current supports
    w = problems.start.copy()  # the current (thresholded) solutions
    penalised = problems.weights > 0
    stages = [[] for _ in range(n)]
    total_iter = np.zeros(n, dtype=np.int64)
    reductions = np.zeros(n, dtype=np.int64)
    converged = np.ones(n, dtype=bool)
    costs = np.full(n, np.nan)
    first_stage = [None] * n
    rows = np.arange(n)
    cur_lam = float(lam)
    for s in range(max_stages):
        if rows.size == 0:
            break
        step = None if alpha is None else float(alpha) * step_growth**s
        res = problems.stage(
            rows, on[rows], w[rows], cur_lam, step, max_iter, solver_tol
        )
        coef = np.where(on[rows], res.coef, 0.0)
        if s == 0:
            for r, row in zip(rows, coef):
                first_stage[r] = problems.tensor(r, problems.own(r, row))
        # The hard threshold, relative to the largest coefficient (or ``reference``);
        # an all-zero stage (lam too high) removes nothing; unpenalised features stay.
        mags = np.abs(coef)
        largest = mags.max(1, initial=0.0)
        small = _small(problems, rows, mags, reference, equation_threshold)
        keep = on[rows] & ~(small & penalised[rows] & (largest > 0)[:, None])
        coef = np.where(keep, coef, 0.0)
        on[rows], w[rows] = keep, coef
        costs[rows] = problems.residuals(rows, coef)
        total_iter[rows] += res.n_iter
        reductions[rows] += res.step_reductions
        converged[rows] &= res.converged
        for i, r in enumerate(rows):
            record = Stage(
                cur_lam,
                float(res.step[i]),
                int(res.n_iter[i]),
                bool(res.converged[i]),
                float(res.stop_crit[i]),
                problems.own(r, coef[i]),
                np.flatnonzero(problems.own(r, keep[i])),
                float(costs[r]),
            )
            stages[r].append(record)
            if verbose:
                who = f"problem {r + 1}, " if n > 1 else ""
                print(
                    f"[lagsindy] {who}stage {s + 1}: lam={cur_lam:.3g} "
                    f"step={record.step:.3g} iterations={record.n_iter}"
                    f"{'' if record.converged else ' (max_iter)'} "
                    f"terms={record.support.size} relative residual={record.cost:.3g}"
                )
        done = (costs[rows] <= tol) & np.any(coef != 0, axis=1)
        rows = rows[~done]
        cur_lam /= lam_decay
    unset = np.flatnonzero(np.isnan(costs))  # no stage ran (max_stages=0)
    if unset.size:
        costs[unset] = problems.residuals(unset, w[unset])
    if debias:
        sel = np.flatnonzero(on.any(1))
        if sel.size:
            w[sel], on[sel] = _refit(
                problems, sel, on[sel], w[sel], reference, equation_threshold
            )
            costs[sel] = problems.residuals(sel, w[sel])
    return [
        StagedResult(
            problems.tensor(r, problems.own(r, w[r])),
            np.flatnonzero(problems.own(r, on[r])),
            stages[r],
            int(total_iter[r]),
            bool(converged[r]),
            float(costs[r]),
            int(reductions[r]),
            first_stage[r],
        )
        for r in range(n)
    ]


def _small(problems, rows, mags, reference, equation_threshold):
    """Which coefficients ``mags`` (rows ``rows`` of the batch) fall below the hard
    threshold.

    The paper's rule: below ``threshold * max(reference, max_k |w_k|)``. With an
    ``equation_threshold`` and problems whose rows are several coordinates'
    equations (with their shares), a term is kept anyway where, in some equation,
    its contribution ``|w_k| s_ik`` (``s_ik``: the share of its column's norm in
    equation ``i``) is at least ``equation_threshold`` times that equation's largest
    (or the fixed term's, ``reference * s_i,target``): the terms that make up a
    light or undriven link's equation are not judged against a heavier one's.
    """
    peak = np.maximum(mags.max(1, initial=0.0), reference)[:, None]
    small = mags < problems.thr[rows] * peak
    if equation_threshold is None or problems.shares is None:
        return small
    contrib = problems.shares[rows] * mags[:, None, :]  # (rows, equations, m)
    largest = contrib.max(2, initial=0.0)
    if reference:
        largest = np.maximum(largest, reference * problems.target_shares[rows])
    ratio = np.divide(
        contrib,
        largest[:, :, None],
        out=np.zeros_like(contrib),
        where=largest[:, :, None] > 0,
    )
    return small & (ratio.max(1, initial=0.0) < equation_threshold)


def _refit(problems, rows, on, start, reference, equation_threshold):
    """Unpenalised refit of the supports ``on`` of ``rows``, thresholding the refit
    until it is stable.

    The L1 stages shrink coefficients, so a term that the penalty kept alive only
    to stand in for a shrunk one can look large before the refit and negligible
    after it; it is removed and the rest refitted (until nothing is removed, or
    everything would be). Non-negative coefficients stay so (see
    ``problems.least_squares``). Returns the refitted coefficients and supports.
    """
    on = on.copy()
    w = np.zeros(on.shape)
    live = np.arange(len(rows))
    while live.size:
        r = rows[live]
        fit = problems.least_squares(r, on[live], start[live])
        w[live] = fit
        small = _small(problems, r, np.abs(fit), reference, equation_threshold)
        drop = on[live] & small & (problems.weights[r] > 0)
        n_drop, n_on = drop.sum(1), on[live].sum(1)
        again = (n_drop > 0) & (n_drop < n_on)
        on[live[again]] &= ~drop[again]
        live = live[again]
    return w, on


def fista_path(
    datafit, lams, *, penalty_weights=None, max_iter=MAX_ITER, tol=SOLVER_TOL
):
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
            stacklevel=outside_stacklevel(),
        )
