r"""How sure is each term? Bootstrap intervals, inclusion probabilities, library bagging.

:func:`bootstrap` refits an estimator's configuration on resamples of whole
trajectories (or of contiguous time blocks of one long record) and reports, for every
library and dissipation term, how often it is kept (``inclusion``) and an interval for
its coefficient.

Cost. The Euler-Lagrange regression only needs Gram statistics, and those of a
resample that takes trajectory :math:`g` :math:`m_g` times are
:math:`\sum_g m_g G_g` (strong form: per-sample rows; weak form: per-window rows, since
a window never spans two trajectories). The per-trajectory statistics are computed once,
so a resample costs one scaled staged solve, not a rebuild of the regression. This fast
path goes through one private seam, :func:`_solve_from_gram`, which repeats what
:meth:`LagrangianSINDy.fit` does after building the Gram matrix (balancing, then the
staged solve of case I, or of case III with a given ``fixed_term``). It checks itself:
before any resample, the seam is run on the full data's statistics and must reproduce
the full fit; if it does not (a configuration it does not know, or estimator internals
that changed), every resample is a full refit (``clone(est).fit``) instead, and the
report says so (``fast_path_``). Configurations that choose between models on the data
(case III without a fixed term or with ``fixed_term="mass"``, case II) always use full
refits.

Case I resamples are solved together (:func:`_batched_resamples`): the balancing of
every resample's Gram matrix and each stage's FISTA iterations run on stacked arrays
(:mod:`lagsindy.solvers.batched_fista`), one batched product per iteration instead
of one Python-level loop per resample, while the per-resample decisions (thresholds,
the path's second start, the debiasing refit) follow
:class:`~lagsindy.cases.SparseSolve`. Each resample gets the coefficients its own
solve would, up to rounding; the batch must reproduce the one-at-a-time solve of
the full data's statistics (``_BATCH_RTOL``), else the resamples are solved one at a
time.

Nuisance parameters of the weak form. The sampling interval ``dt`` is estimated
again on every resample (unless the estimator was given one): its estimate from noisy
positions and velocities moves the kinetic terms against the potential and force
terms (on the cart-pendulum with noise 0.02 on q and q_dot, its error of up to 0.9 %
was most of the coefficients' spread over noise draws), so holding it fixed made the
intervals too narrow. A weak Gram matrix is a quadratic polynomial in ``dt``, so the
per-trajectory statistics are built at three sampling intervals and a resample's
Gram matrix is interpolated exactly at its own ``dt``. The noise covariance of the
errors-in-variables correction and the test-function window are the full fit's,
held fixed (in full refits too, so that both paths fit the same model); replacing
the estimated covariance by the true one changed the coefficients by at most 3e-4
relative on those data, against a spread of 0.2 % to 0.8 %.
"""

from __future__ import annotations

import math
import warnings
from numbers import Integral, Real

import numpy as np
import torch
from joblib import Parallel, delayed
from scipy.stats import norm
from sklearn.base import BaseEstimator, MetaEstimatorMixin, RegressorMixin, clone
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_is_fitted

from ._torch import resolve_device, resolve_dtype, to_numpy, to_tensor
from ._validation import validate_state
from .cases import SparseSolve
from .formulation import window_stride
from .formulation.operator import NOISE_ROWS, EulerLagrangeOperator
from .formulation.scaling import _BALANCE_MAX_ITER, BalancedGram
from .solvers.datafits import GramQuadratic
from .formulation.weak import trajectory_segments
from .library import CandidateLibrary

__all__ = ["BootstrapReport", "LibraryBaggingLagrangianSINDy", "bootstrap"]

_METHODS = ("percentile", "basic", "bca")
# Agreement the fast path must show with the full fit before it is trusted (max abs
# coefficient difference relative to the largest coefficient).
_SEAM_RTOL = 1e-6
# Looser agreement where the full fit's weak-form noise correction is a row subsample
# (above NOISE_ROWS rows) and the per-trajectory statistics are exact.
_SEAM_RTOL_SUBSAMPLED = 1e-2
# Agreement the batched solve of the resamples must show with the one-at-a-time
# solve on the full data's statistics (measured: 5e-13 strong, 9e-9 weak form).
_BATCH_RTOL = 1e-6
# Samples (strong form) or windows (weak form) per block, at least, in block mode.
_MAX_BLOCKS = 20
# Fewer trajectories than this: resample time blocks within them instead.
_MIN_TRAJECTORIES = 10


class BootstrapReport:
    """Result of :func:`bootstrap`: one row per library and dissipation term.

    Attributes
    ----------
    terms : list of str
    kinds : list of str
        ``"lagrangian"`` or ``"dissipation"`` per term.
    coefficient : ndarray of shape (n_terms,)
        The fit on all data (in the estimator's normalization).
    inclusion : ndarray of shape (n_terms,)
        Fraction of resamples whose fit keeps the term.
    low, high : ndarray of shape (n_terms,)
        Interval at ``level`` (``method``).
    samples : ndarray of shape (n_resamples, n_terms)
        Coefficients of every resample (NaN for a resample that failed or could not
        be put in the full fit's normalization).
    level : float
    method : str
    resampling : {"trajectories", "blocks"}
    n_groups : int
        Trajectories or blocks resampled.
    fast_path : bool
        True when resamples were solved from per-trajectory Gram statistics.
    n_failed : int
        Resamples whose fit raised or could not be normalized (left out of the
        intervals; inclusion counts them as not keeping any term).
    estimator : LagrangianSINDy
        The fit on all data.
    """

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)

    def to_frame(self):
        """The report as a DataFrame.

        Returns
        -------
        pandas.DataFrame
            Columns ``term``, ``kind``, ``coefficient``, ``inclusion``, ``low``,
            ``high``.
        """
        import pandas as pd

        return pd.DataFrame(
            {
                "term": self.terms,
                "kind": self.kinds,
                "coefficient": self.coefficient,
                "inclusion": self.inclusion,
                "low": self.low,
                "high": self.high,
            }
        )

    def __str__(self):
        head = (
            f"Bootstrap of {self.n_resamples} resamples of {self.n_groups} "
            f"{self.resampling}; {self.level:.0%} {self.method} intervals"
            f"{'' if self.fast_path else ' (full refits)'}"
        )
        if self.n_failed:
            head += f"; {self.n_failed} resample(s) failed and are left out"
        width = max(12, *(len(t) for t in self.terms)) if self.terms else 12
        lines = [
            head,
            f"{'term':<{width}}  {'coefficient':>12}  {'inclusion':>9}  "
            f"{'low':>12}  {'high':>12}",
        ]
        for k, t in enumerate(self.terms):
            lines.append(
                f"{t:<{width}}  {self.coefficient[k]:>12.5g}  {self.inclusion[k]:>9.2f}  "
                f"{self.low[k]:>12.5g}  {self.high[k]:>12.5g}"
            )
        return "\n".join(lines)

    def __repr__(self):
        return self.__str__()


# --------------------------------------------------------------------------- seam
def _fast_path_supported(fitted) -> bool:
    """Whether :func:`_solve_from_gram` reproduces this fitted configuration."""
    formulation = getattr(fitted, "formulation_", fitted.formulation)
    if formulation not in ("strong", "weak"):
        return False
    if fitted.case_ == "forces":
        return True
    return (
        fitted.case_ == "fixed"
        and fitted.normalization_ == "term"
        and fitted.fixed_term is not None
        and not (isinstance(fitted.fixed_term, str) and fitted.fixed_term == "mass")
    )


def _solve_from_gram(fitted, gram, n_rows, start=None):
    """Coefficients of ``fitted``'s configuration from Gram statistics.

    The seam between the bootstrap and :class:`~lagsindy.LagrangianSINDy`: it
    repeats what ``fit`` does once the Gram matrix is built (balancing with
    :class:`~lagsindy.solvers.BalancedGram`, then the staged solve of case I, or of
    case III with the scale fixed by ``fixed_term``), using the estimator's own
    private solve, so the settings (``lam``, thresholds, ``unpenalized``,
    ``debias``...) are the estimator's.

    Parameters
    ----------
    fitted : LagrangianSINDy
        Fitted on all data; only its configuration and fitted library are used.
    gram : Tensor of shape (n_dof, P, P)
        Summed per-coordinate Gram statistics (columns: terms, dissipation, then tau
        in case I).
    n_rows : int
        Rows (samples, or windows in the weak form) behind ``gram``.
    start : ndarray of shape (n_features,), optional
        Warm start of the first stage, in coefficient units (the full fit's first
        stage, ``fitted.stages_[0].coef``); ``None`` starts from zero as ``fit`` does.

    Returns
    -------
    ndarray of shape (n_features,)
    """
    n_features = len(fitted.feature_names_)
    correct = getattr(fitted, "noise_cov_", None) is not None
    balanced = BalancedGram(
        gram, n_rows, n_features, normalize=fitted.normalize, project_psd=correct
    )
    identifiable = balanced.identifiable().cpu().numpy()
    penalty = np.ones(n_features)
    for term in fitted.unpenalized if fitted.unpenalized is not None else []:
        penalty[fitted.fitted_.feature_index(term)] = 0.0
    if fitted.case_ == "forces":
        free = np.flatnonzero(identifiable)
        return _staged_solve(
            fitted, balanced, free, n_features, 1.0, penalty, 0.0, start
        )
    r = fitted.library_.index(fitted.fixed_term)
    if not identifiable[r]:
        raise ValueError("the fixed term has a zero column on this resample")
    free = np.array([k for k in np.flatnonzero(identifiable) if k != r])
    coef = _staged_solve(fitted, balanced, free, r, -1.0, penalty, 1.0, start)
    coef[r] = 1.0
    return coef


def _staged_solve(fitted, balanced, free, target, sign, penalty, reference, start):
    """The estimator's staged solve with a warm start (the full fit's first stage).

    The first stage is a strictly convex problem (when its Gram block is definite),
    so the start changes only the iterations to reach ``solver_tol``, not the
    answer; later stages and the debiasing refit continue from it as in ``fit``.
    """
    state = fitted.fitted_
    n_terms = len(state.terms)
    dissipative = [False] * n_terms + [t.dissipative for t in state.dissipation_terms]
    solver = SparseSolve.from_params(
        fitted.get_params(deep=False), n_terms, dissipative, verbose=0
    )
    coef, _ = solver.solve(
        balanced, free, target, sign, penalty, reference, 0, start=start
    )
    return coef


class _GroupStats:
    """Per-group statistics from which a resample's Gram matrix is summed.

    Attributes
    ----------
    grams : Tensor of shape (n_nodes, n_groups, n_dof, P, P)
        Per-group Gram statistics, built at each sampling interval of ``nodes``
        (weak form; the strong form has one node).
    rows : ndarray of shape (n_groups,)
        Rows (samples, or windows in the weak form) per group.
    nodes : ndarray of shape (n_nodes,) or None
        Sampling intervals the weak statistics were built at. A weak Gram matrix
        is a quadratic polynomial in ``dt`` (each column is a kinetic part that
        does not depend on it plus ``dt`` times a potential and force part; the
        noise correction has the same form), so three nodes give it exactly at
        any ``dt`` by Lagrange interpolation.
    steps : tuple of Tensor or None
        ``(ratios, weights, owner)`` of
        :func:`~lagsindy.formulation.weak.estimate_sampling_interval`, sorted by
        ratio, with the group of each step: the sampling interval of a resample is
        the weighted median with the weights times the group's multiplicity.
        ``None`` when the estimator's ``dt`` is given (held fixed).
    """

    def __init__(self, grams, rows, nodes=None, steps=None):
        self.grams = grams
        self.rows = rows
        self.nodes = nodes
        self.steps = steps

    def sampling_interval(self, mult):
        """The weak form's estimated ``dt`` on a resample (None: not estimated)."""
        if self.steps is None:
            return None
        ratios, weights, owner = self.steps
        w = torch.as_tensor(mult, dtype=weights.dtype, device=weights.device)
        cum = torch.cumsum(weights * w[owner], 0)
        k = int(torch.searchsorted(cum, cum[-1] / 2))
        return float(ratios[min(k, ratios.numel() - 1)])

    def gram(self, mult):
        """Summed Gram statistics and rows of the resample taking group ``g``
        ``mult[g]`` times."""
        w = torch.as_tensor(mult, dtype=self.grams.dtype, device=self.grams.device)
        per_node = torch.einsum("g,jgipq->jipq", w, self.grams)
        n = int(np.dot(mult, self.rows))
        dt = self.sampling_interval(mult)
        if dt is None:
            return per_node[0], n
        nodes = self.nodes
        basis = [
            np.prod([(dt - nodes[m]) / (nodes[j] - nodes[m]) for m in range(3) if m != j])
            for j in range(3)
        ]
        gram = sum(float(c) * per_node[j] for j, c in enumerate(basis))
        return gram, n


# The weak statistics are built at these multiples of the full fit's sampling
# interval (any three distinct values interpolate the quadratic exactly).
_DT_NODES = (0.5, 1.0, 1.5)


def _step_ratios(Xt, n_dof, groups):
    """The sampling-interval statistics of every group (see :class:`_GroupStats`).

    The same per-step ratios and weights as
    :func:`~lagsindy.formulation.weak.estimate_sampling_interval`, in the same
    order, so that the resample that takes every group once gets the fit's ``dt``.
    """
    ratios, weights, owner = [], [], []
    for k, g in enumerate(groups):
        idx = torch.as_tensor(g, device=Xt.device)
        q, qd = Xt[idx, :n_dof], Xt[idx, n_dof : 2 * n_dof]
        if q.shape[0] < 2:
            continue
        mid = (qd[1:] + qd[:-1]) / 2
        ok = mid.abs() > 0
        r = ((q[1:] - q[:-1])[ok] / mid[ok]).flatten()
        ratios.append(r)
        weights.append((mid[ok] ** 2).flatten())
        owner.append(torch.full((r.numel(),), k, device=Xt.device, dtype=torch.long))
    r, w, o = torch.cat(ratios), torch.cat(weights), torch.cat(owner)
    order = torch.argsort(r)
    return r[order], w[order], o[order]


def _group_gram(fitted, Xa, tau, labels):
    """Per-group statistics (:class:`_GroupStats`) of ``fitted``'s configuration.

    Weak form: the integrands are evaluated once for every trajectory; each
    segment's Gram statistics are summed per group, at three sampling intervals
    when the fit estimated ``dt`` (so that a resample can use its own estimate).
    The noise covariance and the window are the full fit's.
    """
    device = resolve_device(fitted.device)
    dtype = resolve_dtype(fitted.dtype)
    operator = EulerLagrangeOperator(
        fitted.coordinates_,
        fitted.library_.terms_,
        forces=[t.forces for t in fitted.dissipation_terms_],
        dtype=dtype,
        device=device,
    )
    Xt = to_tensor(Xa, dtype=dtype, device=device)
    tau_t = None if tau is None else to_tensor(tau, dtype=dtype, device=device)
    weak = getattr(fitted, "formulation_", fitted.formulation) == "weak"
    cov = None
    if weak and fitted.noise_cov_ is not None:
        cov = to_tensor(fitted.noise_cov_, dtype=dtype, device=device)
    d = fitted.n_dof_
    if not weak:
        # Columns once for all rows (one compiled evaluation), then one Gram per group.
        parts = []
        step = max(1, int(getattr(operator, "chunk_size", 32768)))
        for a in range(0, Xt.shape[0], step):
            theta = operator.columns(Xt[a : a + step])
            if tau_t is not None:
                theta = torch.cat([theta, tau_t[a : a + step].unsqueeze(2)], dim=2)
            parts.append(theta)
        theta = torch.cat(parts)
        grams, rows = [], []
        for g in _group_rows(labels):
            tg = theta[torch.as_tensor(g, device=device)]
            grams.append(torch.einsum("sip,siq->ipq", tg, tg))
            rows.append(len(g))
        return _GroupStats(torch.stack(grams)[None], np.asarray(rows, dtype=np.int64))
    # Weak form: the integrands once for every trajectory (one evaluation), then
    # each segment's statistics apart, summed per group.
    window = int(fitted.window_)
    groups = _group_rows(labels)
    segments, owner = [], []
    for k, g in enumerate(groups):
        idx = torch.as_tensor(g, device=device)
        for s in trajectory_segments(Xt[idx], d, np.zeros(len(g))):
            if len(s) >= window:
                segments.append(idx[s])
                owner.append(k)
    if not segments:
        raise ValueError(
            f"no trajectory is as long as the fit's window ({window} samples)"
        )
    dt = float(fitted.dt_)
    build = operator.weak_grams(
        Xt,
        tau_t,
        {window: segments},
        strides={window: window_stride(window)},
        dt=dt,
        noise_cov=cov,
        per_segment=True,
        lazy=True,
    )[window]
    estimated = fitted.dt is None
    nodes = np.array([c * dt for c in _DT_NODES]) if estimated else np.array([dt])
    owner = torch.as_tensor(owner, device=device)
    per_node = []
    for node in nodes:
        gram, n_win = build(dt=float(node))
        out = gram.new_zeros((len(groups), *gram.shape[1:]))
        out.index_add_(0, owner, gram)
        per_node.append(out)
    rows = np.bincount(owner.cpu().numpy(), weights=n_win, minlength=len(groups))
    return _GroupStats(
        torch.stack(per_node),
        rows.astype(np.int64),
        nodes=nodes if estimated else None,
        steps=_step_ratios(Xt, d, groups) if estimated else None,
    )


def _group_rows(labels):
    """Row indices of each label, labels in order of first appearance."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first)
    return [np.flatnonzero(inverse == k) for k in order]


# --------------------------------------------------------------------------- resamples
def _fast_resample(fitted, stats, mult, start=None):
    """One resample by the seam; coefficients, or None when it fails."""
    gram, n = stats.gram(mult)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            coef = _solve_from_gram(fitted, gram, n, start)
        except (ValueError, FloatingPointError, RuntimeError):
            return None
    return coef if np.all(np.isfinite(coef)) else None


def _batch_supported(fitted) -> bool:
    """Whether :func:`_batched_resamples` knows this configuration (case I, steps
    ``1 / L``, float64); the others are solved one resample at a time."""
    return (
        fitted.case_ == "forces"
        and fitted.alpha is None
        and fitted.max_stages >= 1
        and resolve_dtype(fitted.dtype) == torch.float64
    )


def _batched_resamples(fitted, stats, mults, start=None):
    """Case I resamples solved together: the staged solve of
    :func:`_solve_from_gram` with every stage's FISTA iterations batched over the
    resamples (:func:`~lagsindy.solvers.batched_fista.batched_fista`).

    The per-resample steps (balancing, thresholds, the path's second start,
    debiasing) are those of :class:`~lagsindy.cases.SparseSolve`, so each resample
    gets what its own solve would, up to rounding. Returns a list with the
    coefficients of each resample, or ``None`` where that resample must be solved
    alone (a different set of identifiable columns, a step the divergence guard
    would change, a failure).
    """
    from .cases.sparse import LAM_STARTS, PATH_FLOOR, PATH_TIE
    from .formulation.scaling import dense_residual
    from .solvers.batched_fista import batched_fista, lipschitz_steps
    from .solvers.staged import _debias

    n_features = len(fitted.feature_names_)
    correct = getattr(fitted, "noise_cov_", None) is not None
    state = fitted.fitted_
    n_terms = len(state.terms)
    dissipative = [False] * n_terms + [t.dissipative for t in state.dissipation_terms]
    solver = SparseSolve.from_params(
        fitted.get_params(deep=False), n_terms, dissipative, verbose=0
    )
    penalty = np.ones(n_features)
    for term in fitted.unpenalized if fitted.unpenalized is not None else []:
        penalty[fitted.fitted_.feature_index(term)] = 0.0
    out = [None] * len(mults)
    if len(mults) == 0:
        return out
    summed = [stats.gram(m) for m in mults]
    grams = np.stack([to_numpy(g) for g, _ in summed]).astype(np.float64)
    n_rows = np.array([n for _, n in summed], dtype=np.float64)
    g_bal, col_scale = _balance_many(
        grams, n_rows, n_features, fitted.normalize, correct
    )
    big = np.maximum(col_scale.max(axis=1, initial=0.0), 1e-300)
    identifiable = col_scale > 1e-12 * big[:, None]
    free_ref = np.flatnonzero(identifiable[0])
    y_scale = np.sqrt(np.maximum(g_bal[:, n_features, n_features], 0.0))
    ok = (identifiable == identifiable[0]).all(axis=1) & (y_scale > 0)
    ok &= np.isfinite(g_bal).all(axis=(1, 2))
    problems = []  # (index, datafit)
    scales = []
    sf = col_scale[:, free_ref]
    sf = np.where(sf > 0, sf, 1.0)
    for i in np.flatnonzero(ok):
        g = g_bal[i][np.ix_(free_ref, free_ref)] / (sf[i][:, None] * sf[i][None, :])
        rhs = g_bal[i][free_ref, n_features] / (sf[i] * y_scale[i])
        datafit = GramQuadratic(torch.from_numpy(g), torch.from_numpy(rhs), 1.0)
        problems.append((i, datafit))
        scales.append(y_scale[i] / sf[i])
    if not problems:
        return out
    scales = np.stack(scales)
    free = free_ref
    p = len(free)
    G = np.stack([d.gram.numpy() for _, d in problems])
    b = np.stack([d.rhs.numpy() for _, d in problems])
    c = np.array([d.const for _, d in problems])
    weights = penalty[free].astype(float)
    thresholds = solver.thresholds(free).astype(float)
    nonneg_t = solver.nonneg(free, "cpu")
    nonneg = None if nonneg_t is None else nonneg_t.numpy()
    w0 = np.zeros((len(problems), p))
    if start is not None:
        w0 = np.asarray(start)[free][None, :] / scales
    if nonneg is not None:
        w0 = np.where(nonneg[None, :], np.maximum(w0, 0.0), w0)

    def path(rows, lam):
        """The staged schedule of ``staged_fista`` for the problems ``rows``."""
        Gr, br, cr = G[rows], b[rows], c[rows]
        mask = np.ones((len(rows), p), dtype=bool)
        w = w0[rows].copy()
        finished = np.zeros(len(rows), dtype=bool)
        flagged = np.zeros(len(rows), dtype=bool)
        cur = float(lam)
        for _ in range(solver.max_stages):
            act = np.flatnonzero(~finished & ~flagged)
            if act.size == 0:
                break
            # Only the columns some active problem still has (later stages: few).
            cols = np.flatnonzero(mask[act].any(axis=0))
            sub = np.ix_(act, cols, cols)
            res = batched_fista(
                Gr[sub],
                br[np.ix_(act, cols)],
                cr[act],
                mask[np.ix_(act, cols)],
                cur,
                weights[cols],
                lipschitz_steps(Gr[sub], mask[np.ix_(act, cols)]),
                w[np.ix_(act, cols)],
                nonneg=None if nonneg is None else nonneg[cols],
                max_iter=solver.max_iter,
                tol=solver.solver_tol,
            )
            full_coef = np.zeros((len(act), p))
            full_coef[:, cols] = res.coef
            res.coef = full_coef
            flagged[act[res.flagged]] = True
            for j, r in enumerate(act):
                if res.flagged[j]:
                    continue
                sup = np.flatnonzero(mask[r])
                w_sub = res.coef[j][sup]
                mags = np.abs(w_sub)
                largest = float(mags.max()) if mags.size else 0.0
                if largest > 0:
                    keep = ~(
                        (mags < thresholds[sup] * max(largest, 0.0))
                        & (weights[sup] > 0)
                    )
                else:
                    keep = np.ones(mags.shape, dtype=bool)
                w_sub = np.where(keep, w_sub, 0.0)
                w[r] = 0.0
                w[r, sup] = w_sub
                mask[r] = False
                mask[r, sup[keep]] = True
            costs = np.array(
                [_rel(Gr[r], br[r], cr[r], w[r]) for r in range(len(rows))]
            )
            for r in act:
                if flagged[r]:
                    continue
                if costs[r] <= solver.tol and np.abs(w[r][mask[r]]).max(initial=0.0) > 0:
                    finished[r] = True
            cur /= solver.lam_decay
        results = []
        for r in range(len(rows)):
            if flagged[r]:
                results.append(None)
                continue
            _, datafit = problems[rows[r]]
            w_t = torch.as_tensor(w[r], dtype=datafit.rhs.dtype)
            support = np.flatnonzero(mask[r])
            if solver.debias and len(support):
                w_t, support = _debias(
                    datafit,
                    support,
                    torch.as_tensor(weights, dtype=w_t.dtype),
                    torch.as_tensor(thresholds, dtype=w_t.dtype),
                    0.0,
                    w_t,
                    nonneg_t,
                )
            results.append((w_t.cpu().numpy(), datafit.relative_residual(w_t)))
        return results

    rows = np.arange(len(problems))
    first = path(rows, solver.lam)
    chosen = list(first)
    if solver.lam != 0 and LAM_STARTS > 1 and solver.lam_decay > 1:
        again = []
        for r, res in enumerate(first):
            if res is None:
                continue
            bound = dense_residual(problems[r][1])
            if res[1] > (1 + PATH_TIE) * bound + PATH_FLOOR:
                again.append(r)
        if LAM_STARTS > 2 and again:
            return out  # more starts than one restart: not batched
        if again:
            second = path(np.array(again), solver.lam / solver.lam_decay)
            for r, res in zip(again, second):
                if res is None:
                    chosen[r] = None
                    continue
                cands = [first[r], res]
                best = min(x[1] for x in cands)
                near = [x for x in cands if x[1] <= (1 + PATH_TIE) * best + 1e-12]
                chosen[r] = min(near, key=lambda x: int((x[0] != 0).sum()))
    for r, res in enumerate(chosen):
        if res is None:
            continue
        i, _ = problems[r]
        coef = np.zeros(n_features)
        coef[free] = res[0] * scales[r]
        if np.all(np.isfinite(coef)):
            out[i] = coef
    return out


def _balance_many(grams, n_rows, n_features, normalize, project_psd):
    """:class:`~lagsindy.formulation.scaling.BalancedGram` of many Gram statistics.

    The same alternating row/column scaling (each problem stops at its own
    iteration), combined Gram matrix, positive semi-definite projection and column
    scales, on stacked arrays. Returns the balanced Gram matrices (R, P, P) and the
    column scales (R, n_features).
    """
    R, d = grams.shape[:2]
    diag = np.diagonal(grams, axis1=2, axis2=3)[:, :, :n_features]
    mean_sq = np.maximum(diag / n_rows[:, None, None], 0.0)
    rows = np.ones((R, d))
    if normalize and n_features:
        live = np.ones(R, dtype=bool)
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(_BALANCE_MAX_ITER):
                cols = np.sqrt((mean_sq / rows[:, :, None] ** 2).mean(axis=1))
                active = cols > 0
                count = active.sum(axis=1)
                safe = np.where(active, cols, 1.0)
                ratio = np.where(active[:, None, :], mean_sq / safe[:, None, :] ** 2, 0.0)
                new = np.sqrt(ratio.sum(axis=2) / np.maximum(count, 1)[:, None])
                new = np.where(new > 0, new, 1.0)
                new = new / np.exp(np.log(new).mean(axis=1, keepdims=True))
                close = (np.abs(new - rows) <= 1e-10 * np.abs(rows)).all(axis=1)
                step = live & (count > 0)
                rows = np.where(step[:, None], new, rows)
                live &= step & ~close
                if not live.any():
                    break
    weights = 1.0 / rows**2
    gram = (grams * weights[:, :, None, None]).sum(axis=1) / (n_rows * d)[:, None, None]
    if project_psd:
        evals, evecs = np.linalg.eigh((gram + np.swapaxes(gram, 1, 2)) / 2)
        gram = (evecs * np.maximum(evals, 0.0)[:, None, :]) @ np.swapaxes(evecs, 1, 2)
    col = np.sqrt(np.maximum(np.diagonal(gram, axis1=1, axis2=2)[:, :n_features], 0))
    if not normalize:
        col = np.where(col > 0, 1.0, col)
    return gram, col


def _rel(gram, rhs, const, w):
    """Relative residual of one Gram problem (``GramQuadratic.relative_residual``)."""
    if const <= 0:
        return 0.0
    val = float(0.5 * w @ (gram @ w) - rhs @ w + 0.5 * const)
    return max(0.0, 2.0 * val / const)


def _refit_resample(base, Xa, tau, groups_rows, mult, weak):
    """One resample by a full refit on the resampled trajectories."""
    idx, labels = [], []
    for g, m in enumerate(mult):
        for copy in range(int(m)):
            idx.append(groups_rows[g])
            labels.append(np.full(len(groups_rows[g]), len(labels)))
    idx = np.concatenate(idx)
    labels = np.concatenate(labels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            est = clone(base).fit(
                Xa[idx],
                None if tau is None else tau[idx],
                groups=labels if weak else None,
            )
        except (ValueError, FloatingPointError, RuntimeError):
            return None
    return est.fitted_.all_coef()


def _normalize_to(coef, ref):
    """Rescale ``coef`` so that feature ``ref`` has coefficient 1 (None if it is 0)."""
    if coef is None or ref is None:
        return coef
    if coef[ref] == 0:
        return None
    return coef / coef[ref]


# --------------------------------------------------------------------------- intervals
def _intervals(samples, theta, level, method, jack):
    """Interval per column of ``samples`` (NaN rows ignored)."""
    alpha = 1.0 - level
    lo_q, hi_q = alpha / 2, 1 - alpha / 2
    p = samples.shape[1]
    low, high = np.full(p, np.nan), np.full(p, np.nan)
    for k in range(p):
        s = samples[:, k]
        s = s[np.isfinite(s)]
        if s.size == 0:
            continue
        if method == "percentile":
            low[k], high[k] = np.quantile(s, [lo_q, hi_q])
        elif method == "basic":
            a, b = np.quantile(s, [lo_q, hi_q])
            low[k], high[k] = 2 * theta[k] - b, 2 * theta[k] - a
        else:  # BCa with jackknife acceleration over groups
            below = np.mean(s < theta[k]) + 0.5 * np.mean(s == theta[k])
            below = min(max(below, 0.5 / s.size), 1 - 0.5 / s.size)
            z0 = norm.ppf(below)
            jk = jack[:, k]
            jk = jk[np.isfinite(jk)]
            acc = 0.0
            if jk.size > 2:
                dev = jk.mean() - jk
                den = 6.0 * (dev**2).sum() ** 1.5
                acc = float((dev**3).sum() / den) if den > 0 else 0.0
            qs = []
            for z in (norm.ppf(lo_q), norm.ppf(hi_q)):
                t = z0 + (z0 + z) / (1 - acc * (z0 + z))
                qs.append(norm.cdf(t))
            low[k], high[k] = np.quantile(s, qs)
    return low, high


# --------------------------------------------------------------------------- bootstrap
def bootstrap(
    est,
    X,
    tau=None,
    *,
    groups=None,
    n_resamples=100,
    level=0.95,
    method="bca",
    n_blocks=None,
    random_state=None,
    n_jobs=None,
    verbose=0,
):
    r"""Bootstrap intervals and inclusion probabilities of every term.

    The estimator's configuration is fitted on all data, then on ``n_resamples``
    resamples drawn with replacement from whole trajectories (``groups``), or, when
    there are fewer than 10 trajectories, from about ``n_blocks`` contiguous time
    blocks cut from them (a block bootstrap with non-overlapping blocks: the errors
    within a block may be correlated, those of different blocks are taken as
    independent; in the weak form, test windows that straddle two blocks are not
    used by the resamples).

    Parameters
    ----------
    est : LagrangianSINDy
        Its parameters define the configuration (it is cloned; ``est`` is not
        changed).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces (case I); ``None`` for passive data.
    groups : array-like of shape (n_samples,), default=None
        Trajectory label of each row. ``None`` (one record) or fewer than 10
        trajectories: block bootstrap.
    n_resamples : int, default=100
    level : float, default=0.95
        Coverage of the intervals.
    method : {"bca", "percentile", "basic"}, default="bca"
        Interval construction. ``"bca"``: bias-corrected and accelerated percentile
        interval (Efron 1987), the acceleration from a leave-one-trajectory-out
        jackknife; it corrects the skew and median bias of the sparse fit's bootstrap
        distribution. ``"percentile"``: quantiles of the resampled coefficients;
        ``"basic"``: reflected about the full fit. See the calibration tests for the
        measured coverage.
    n_blocks : int, default=None
        Blocks in block mode (about; each trajectory gets a share by its length).
        ``None``: 20, or fewer where blocks would hold less than four test windows
        (weak form).
    random_state : int, RandomState instance or None, default=None
        Seeds the resamples; the result does not depend on ``n_jobs``.
    n_jobs : int, default=None
        Parallel resamples (joblib).
    verbose : int, default=0

    Returns
    -------
    BootstrapReport
        ``to_frame()`` has columns ``term``, ``kind``, ``coefficient``,
        ``inclusion``, ``low``, ``high``. Passive models (case III, case II) are
        reported in the full fit's normalization: each resample's coefficients are
        divided by its coefficient of the full fit's fixed term (``fixed_term_``, or
        the largest term in case II).

    Notes
    -----
    With few trajectories (fewer than about 10), bootstrap intervals of any kind
    under-cover; so do they for terms whose inclusion is well below 1 (a point mass
    at 0 in the resampled distribution).
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if not (isinstance(n_resamples, Integral) and n_resamples >= 2):
        raise ValueError(f"n_resamples must be an integer >= 2, got {n_resamples!r}")
    if not (isinstance(level, Real) and 0 < level < 1):
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    full = clone(est).fit(X, tau, groups=groups)
    Xa, tau_a, _ = validate_state(
        full, X, reset=False, y=tau, coordinates=full.coordinates_
    )
    n = Xa.shape[0]
    weak = getattr(full, "formulation_", full.formulation) == "weak"
    params = {"library": clone(full.library_)}
    if weak:
        # The resamples estimate their own sampling interval (unless it was given);
        # the noise covariance and the window are the full fit's.
        params.update(noise_cov=full.noise_cov_, window=full.window_)
    base = clone(est).set_params(**params)

    traj = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups)
    if traj.shape != (n,):
        raise ValueError(f"groups must have one label per row of X ({n})")
    trajectories = _group_rows(traj)
    if len(trajectories) >= _MIN_TRAJECTORIES:
        resampling, labels = "trajectories", traj
    else:
        resampling = "blocks"
        shortest = 1
        if weak:
            shortest = int(full.window_) + 4 * max(1, int(full.window_) // 4)
        room = sum(len(r) // shortest for r in trajectories)
        if n_blocks is None:
            n_blocks = min(_MAX_BLOCKS, room)
        if n_blocks < 2 or n_blocks > room:
            raise ValueError(
                f"cannot cut {n} samples in {len(trajectories)} trajectories into "
                f"n_blocks={n_blocks} blocks (at least 2, each of at least {shortest} "
                "samples, four test windows in the weak form); record longer or more "
                "trajectories"
            )
        labels = np.zeros(n, dtype=np.int64)
        next_label = 0
        for r in trajectories:
            k = int(round(n_blocks * len(r) / n))
            k = max(1, min(k, len(r) // shortest))
            labels[r] = next_label + np.minimum(np.arange(len(r)) * k // len(r), k - 1)
            next_label += k
    rows_of = _group_rows(labels)
    n_groups = len(rows_of)
    if n_groups < 5:
        warnings.warn(
            f"only {n_groups} {resampling} to resample: bootstrap intervals from so few "
            "independent units are too narrow; record more trajectories",
            UserWarning,
            stacklevel=2,
        )

    # Normalization of passive models: the full fit's fixed (or largest) term.
    all_coef = full.fitted_.all_coef()
    ref = None
    if full.case_ == "fixed":
        ref = full.library_.index(full.fixed_term_)
    elif full.case_ == "acceleration":
        ref = int(np.argmax(np.abs(all_coef)))

    rng = check_random_state(random_state)
    mults = rng.multinomial(
        n_groups, np.full(n_groups, 1.0 / n_groups), size=n_resamples
    )
    jack_mults = (
        1 - np.eye(n_groups, dtype=np.int64)
        if method == "bca"
        else np.zeros((0, n_groups))
    )

    fast = False
    stats = None
    start = full.stages_[0].coef if full.stages_ else None
    if _fast_path_supported(full):
        stats = _group_gram(full, Xa, tau_a, labels)
        if resampling == "blocks" and weak:
            check = clone(base).fit(Xa, tau_a, groups=labels).fitted_.all_coef()
        else:
            check = all_coef
        seam = _fast_resample(full, stats, np.ones(n_groups))
        scale = max(np.abs(check).max(), 1e-300)
        rtol = _SEAM_RTOL
        if weak and full.noise_cov_ is not None and n > NOISE_ROWS:
            rtol = _SEAM_RTOL_SUBSAMPLED
        fast = (
            seam is not None
            and np.array_equal(seam != 0, check != 0)
            and np.abs(seam - check).max() <= rtol * scale
        )
        if not fast:
            warnings.warn(
                "the bootstrap's fast path (resamples solved from per-trajectory Gram "
                "statistics) does not reproduce the estimator's fit for this "
                "configuration; every resample is a full refit instead (slower)",
                UserWarning,
                stacklevel=2,
            )
    if verbose:
        print(
            f"[lagsindy] bootstrap: {n_resamples} resamples of {n_groups} {resampling}, "
            f"{'fast path' if fast else 'full refits'}"
        )

    all_mults = np.concatenate([mults, jack_mults])
    n_jobs_eff = 1 if n_jobs is None else n_jobs
    chunks = np.array_split(
        np.arange(len(all_mults)), max(1, min(len(all_mults), _n_workers(n_jobs_eff)))
    )
    batched = None
    if fast and _batch_supported(full):
        # Every resample in one batch (so the result does not depend on n_jobs),
        # the full data's statistics with them: the batch must reproduce the fit too.
        both = np.concatenate([np.ones((1, n_groups), dtype=all_mults.dtype), all_mults])
        solved = _batched_resamples(full, stats, both, start)
        same = solved[0] is not None and np.array_equal(solved[0] != 0, seam != 0)
        if same and np.abs(solved[0] - seam).max() <= _BATCH_RTOL * scale:
            batched = solved[1:]
    if batched is not None:
        missing = [i for i, c in enumerate(batched) if c is None]
        for i in missing:  # what the batch could not take: one at a time
            batched[i] = _fast_resample(full, stats, all_mults[i], start)
        results = [batched]
    else:
        if fast:

            def work(ix):
                return [_fast_resample(full, stats, all_mults[i], start) for i in ix]
        else:

            def work(ix):
                return [
                    _refit_resample(base, Xa, tau_a, rows_of, all_mults[i], weak)
                    for i in ix
                ]

        results = Parallel(n_jobs=n_jobs, verbose=max(0, verbose - 1))(
            delayed(work)(ix) for ix in chunks
        )
    coefs = [c for chunk in results for c in chunk]
    p = len(all_coef)
    out = np.full((len(coefs), p), np.nan)
    kept = np.zeros((len(coefs), p), dtype=bool)
    for i, c in enumerate(coefs):
        if c is None:
            continue
        kept[i] = c != 0
        c = _normalize_to(c, ref)
        if c is not None:
            out[i] = c
    samples, jack = out[:n_resamples], out[n_resamples:]
    n_failed = int((~np.isfinite(samples).all(axis=1)).sum())
    if n_failed:
        warnings.warn(
            f"{n_failed} of {n_resamples} bootstrap resamples failed to fit (or lost "
            "the term that fixes the scale) and are left out of the intervals",
            UserWarning,
            stacklevel=2,
        )
    low, high = _intervals(samples, all_coef, level, method, jack)
    terms = [str(t) for t in full.feature_names_]
    n_lag = len(full.coef_)
    return BootstrapReport(
        terms=terms,
        kinds=["lagrangian"] * n_lag + ["dissipation"] * (p - n_lag),
        coefficient=np.asarray(all_coef, dtype=float),
        inclusion=kept[:n_resamples].mean(axis=0),
        low=low,
        high=high,
        samples=samples,
        level=float(level),
        method=method,
        resampling=resampling,
        n_groups=n_groups,
        n_resamples=int(n_resamples),
        fast_path=bool(fast),
        n_failed=n_failed,
        estimator=full,
    )


def _n_workers(n_jobs):
    from joblib import effective_n_jobs

    return max(1, effective_n_jobs(n_jobs))


# --------------------------------------------------------------------------- bagging
class LibraryBaggingLagrangianSINDy(MetaEstimatorMixin, RegressorMixin, BaseEstimator):
    """Library bagging (Ensemble-SINDy) for large candidate libraries.

    Each of ``n_estimators`` fits sees a random subset of the Lagrangian candidate
    terms (the dissipation library, the ``fixed_term`` and ``unpenalized`` terms are
    always offered). A term's inclusion is the fraction of the fits that offered it
    and kept it. Terms whose inclusion exceeds ``inclusion_threshold`` form the final
    library, on which the base estimator is refitted.

    Parameters
    ----------
    estimator : LagrangianSINDy, default=None
        The base configuration; its ``library`` is the full candidate set. ``None``:
        ``LagrangianSINDy()``.
    n_estimators : int, default=50
    max_terms : int or float, default=0.5
        Terms offered to each fit: an integer count, or a fraction of the library.
    inclusion_threshold : float, default=0.5
    random_state : int, RandomState instance or None, default=None
    n_jobs : int, default=None
        Parallel fits (joblib).
    verbose : int, default=0

    Attributes
    ----------
    estimator_ : LagrangianSINDy
        The refit on the kept terms.
    library_ : CandidateLibrary
        The full candidate library (built).
    inclusion_ : ndarray of shape (n_terms,)
        Per term of ``library_``; NaN for a term never offered.
    n_offered_ : ndarray of shape (n_terms,)
        Fits that offered each term.
    kept_ : ndarray of bool, shape (n_terms,)
    coef_ : ndarray of shape (n_terms,)
        Final coefficients over ``library_``'s terms.
    lagrangian_ : sympy.Expr
    n_failed_ : int
        Bagged fits that raised (left out).

    References
    ----------
    U. Fasel, J. N. Kutz, B. W. Brunton and S. L. Brunton, "Ensemble-SINDy: Robust
    sparse model discovery in the low-data, high-noise limit, with active learning
    and control", Proc. R. Soc. A 478, 2022.
    """

    def __init__(
        self,
        estimator=None,
        *,
        n_estimators=50,
        max_terms=0.5,
        inclusion_threshold=0.5,
        random_state=None,
        n_jobs=None,
        verbose=0,
    ):
        self.estimator = estimator
        self.n_estimators = n_estimators
        self.max_terms = max_terms
        self.inclusion_threshold = inclusion_threshold
        self.random_state = random_state
        self.n_jobs = n_jobs
        self.verbose = verbose

    def _base(self):
        if self.estimator is not None:
            return clone(self.estimator)
        import lagsindy  # the public facade: this module never imports the estimator

        return lagsindy.LagrangianSINDy()

    def fit(self, X, y=None, groups=None):
        """Fit the bagged ensemble, then the base estimator on the kept terms.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        y : array-like of shape (n_samples, n_dof), default=None
        groups : array-like of shape (n_samples,), default=None

        Returns
        -------
        self
        """
        if not (isinstance(self.n_estimators, Integral) and self.n_estimators >= 1):
            raise ValueError(
                f"n_estimators must be a positive integer, got {self.n_estimators!r}"
            )
        if not 0 <= self.inclusion_threshold < 1:
            raise ValueError(
                f"inclusion_threshold must be in [0, 1), got {self.inclusion_threshold!r}"
            )
        base = self._base()
        library = clone(base.library) if base.library is not None else None
        lib_coords = None if library is None else library.coordinates
        if isinstance(lib_coords, str):
            lib_coords = [lib_coords]
        _, _, coordinates = validate_state(
            clone(base), X, reset=True, coordinates=lib_coords
        )
        if library is None:
            library = CandidateLibrary.polynomial(
                coordinates, angles="all", degree=2, raw_angles=True
            )
        elif library.coordinates is None:
            library.set_params(coordinates=coordinates)
        library.build()
        self.library_ = library
        terms = list(library.terms_)
        n_terms = len(terms)
        if isinstance(self.max_terms, Integral):
            k = int(self.max_terms)
        elif isinstance(self.max_terms, Real) and 0 < self.max_terms <= 1:
            k = int(math.ceil(self.max_terms * n_terms))
        else:
            raise ValueError(
                f"max_terms must be a positive integer or a fraction in (0, 1], got "
                f"{self.max_terms!r}"
            )
        always = set()
        fixed = base.fixed_term
        if fixed is not None and not (isinstance(fixed, str) and fixed == "mass"):
            always.add(library.index(fixed))
        for t in base.unpenalized if base.unpenalized is not None else []:
            try:
                always.add(library.index(t))
            except (ValueError, TypeError):
                pass  # a dissipation term: always offered anyway
        k = min(max(k, 1), n_terms)
        rng = check_random_state(self.random_state)
        pool = np.array([j for j in range(n_terms) if j not in always])
        subsets = []
        for _ in range(self.n_estimators):
            pick = rng.choice(
                pool, size=min(max(k - len(always), 0), len(pool)), replace=False
            )
            subsets.append(np.sort(np.concatenate([sorted(always), pick]).astype(int)))

        def one(subset):
            lib = CandidateLibrary.from_terms(
                library.coordinates_,
                [terms[j] for j in subset],
                remove_trivial=False,
                remove_dependent=False,
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    est = clone(base).set_params(library=lib).fit(X, y, groups=groups)
                except (ValueError, FloatingPointError, RuntimeError):
                    return None
            return est.coef_ != 0

        if self.verbose:
            print(
                f"[lagsindy] library bagging: {self.n_estimators} fits of {k} of "
                f"{n_terms} terms"
            )
        kept_lists = Parallel(n_jobs=self.n_jobs, verbose=max(0, self.verbose - 1))(
            delayed(one)(s) for s in subsets
        )
        offered = np.zeros(n_terms)
        chosen = np.zeros(n_terms)
        failed = 0
        for subset, kept in zip(subsets, kept_lists):
            if kept is None:
                failed += 1
                continue
            offered[subset] += 1
            chosen[subset[kept]] += 1
        self.n_failed_ = failed
        if failed == len(subsets):
            raise ValueError(
                "every bagged fit failed; check that the base estimator fits the full "
                "library, or offer more terms per fit (max_terms)"
            )
        if failed:
            warnings.warn(
                f"{failed} of {len(subsets)} bagged fits failed and are left out",
                UserWarning,
                stacklevel=2,
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            self.inclusion_ = np.where(
                offered > 0, chosen / np.maximum(offered, 1), np.nan
            )
        self.n_offered_ = offered
        kept = np.nan_to_num(self.inclusion_, nan=0.0) > self.inclusion_threshold
        kept[list(always)] = True
        if not kept.any():
            raise ValueError(
                f"no term has inclusion above {self.inclusion_threshold}; lower "
                "inclusion_threshold"
            )
        self.kept_ = kept
        final = CandidateLibrary.from_terms(
            library.coordinates_,
            [terms[j] for j in np.flatnonzero(kept)],
            remove_trivial=False,
            remove_dependent=False,
        )
        self.estimator_ = clone(base).set_params(library=final).fit(X, y, groups=groups)
        coef = np.zeros(n_terms)
        coef[np.flatnonzero(kept)] = self.estimator_.coef_
        self.coef_ = coef
        self.lagrangian_ = self.estimator_.lagrangian_
        self.term_names_ = library.get_feature_names_out()
        self.n_features_in_ = self.estimator_.n_features_in_
        return self

    def __sklearn_is_fitted__(self):
        return "estimator_" in self.__dict__

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.target_tags.required = False
        return tags

    def predict(self, X):
        """Generalized forces of the refitted model (see ``LagrangianSINDy.predict``)."""
        check_is_fitted(self)
        return self.estimator_.predict(X)

    def predict_acceleration(self, X, tau=None):
        """Accelerations of the refitted model."""
        check_is_fitted(self)
        return self.estimator_.predict_acceleration(X, tau)

    def score(self, X, y=None, sample_weight=None):
        """R^2 of the refitted model (see ``LagrangianSINDy.score``)."""
        check_is_fitted(self)
        return self.estimator_.score(X, y, sample_weight=sample_weight)

    def equation(self, precision: int = 4) -> str:
        check_is_fitted(self)
        return self.estimator_.equation(precision)
