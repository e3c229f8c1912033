"""Resamples of the bootstrap solved from per-trajectory Gram statistics.

The machinery behind :func:`lagsindy.uncertainty.bootstrap` (see its module for the
design): the seam that repeats the estimator's solve from Gram statistics
(:func:`_solve_from_gram`), the per-group statistics (:class:`_GroupStats`,
:func:`_group_gram`), one resample solved alone (:func:`_fast_resample`) or by a
full refit (:func:`_refit_resample`), and case I resamples solved in one batch
(:func:`_batched_resamples`).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from sklearn.base import clone

from ._torch import resolve_device, resolve_dtype, to_numpy, to_tensor
from .cases import SparseSolve
from .formulation import window_stride
from .formulation.operator import EulerLagrangeOperator
from .formulation.probes import without_probes
from .formulation.scaling import _BALANCE_MAX_ITER, BalancedGram
from .formulation.weak import trajectory_segments


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
    penalty = _penalty(fitted, n_features)
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
    coef, _ = _solver(fitted).solve(
        balanced, free, target, sign, penalty, reference, 0, start=start
    )
    return coef


def _solver(fitted):
    """The :class:`~lagsindy.cases.SparseSolve` of ``fitted``'s settings (quiet)."""
    state = fitted.fitted_
    n_terms = len(state.terms)
    dissipative = [False] * n_terms + [t.dissipative for t in state.dissipation_terms]
    return SparseSolve.from_params(
        fitted.get_params(deep=False), n_terms, dissipative, verbose=0
    )


def _penalty(fitted, n_features):
    """L1 weight per feature: 0 for ``fitted``'s ``unpenalized`` terms."""
    penalty = np.ones(n_features)
    for term in fitted.unpenalized if fitted.unpenalized is not None else []:
        penalty[fitted.fitted_.feature_index(term)] = 0.0
    return penalty


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
            np.prod(
                [(dt - nodes[m]) / (nodes[j] - nodes[m]) for m in range(3) if m != j]
            )
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
    :func:`_solve_from_gram` on every resample at once
    (:meth:`~lagsindy.cases.SparseSolve.solve_across`: every stage's FISTA
    iterations batched over the resamples, every start of the path).

    The resamples are balanced together (:func:`_row_scales_many`), so each gets
    what its own solve would, up to rounding. Returns a list with the coefficients
    of each resample, or ``None`` where that resample must be solved alone (a
    different set of identifiable columns, a step the divergence guard would
    change, a failure).
    """
    out = [None] * len(mults)
    if len(mults) == 0:
        return out
    n_features = len(fitted.feature_names_)
    correct = getattr(fitted, "noise_cov_", None) is not None
    summed = [stats.gram(m) for m in mults]
    rows = _row_scales_many(
        np.stack([to_numpy(g) for g, _ in summed]).astype(np.float64),
        np.array([n for _, n in summed], dtype=np.float64),
        n_features,
        fitted.normalize,
    )
    balanced = [
        BalancedGram(
            gram,
            n,
            n_features,
            normalize=fitted.normalize,
            project_psd=correct,
            row_scale=torch.as_tensor(r, dtype=gram.dtype, device=gram.device),
        )
        for (gram, n), r in zip(summed, rows)
    ]
    identifiable = np.stack([to_numpy(b.identifiable()) for b in balanced])
    same = np.flatnonzero((identifiable == identifiable[0]).all(axis=1))
    solved = _solver(fitted).solve_across(
        [balanced[i] for i in same],
        np.flatnonzero(identifiable[0]),
        n_features,
        1.0,
        _penalty(fitted, n_features),
        0.0,
        start=start,
    )
    for i, res in zip(same, solved):
        if res is not None:
            out[i] = res[0]
    return out


def _row_scales_many(grams, n_rows, n_features, normalize):
    """The row scales of :class:`~lagsindy.formulation.scaling.BalancedGram` of many
    Gram statistics (R, n_dof, P, P): the same alternating row/column scaling (each
    problem stops at its own iteration), on stacked arrays. Returns (R, n_dof)."""
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
                ratio = np.where(
                    active[:, None, :], mean_sq / safe[:, None, :] ** 2, 0.0
                )
                new = np.sqrt(ratio.sum(axis=2) / np.maximum(count, 1)[:, None])
                new = np.where(new > 0, new, 1.0)
                new = new / np.exp(np.log(new).mean(axis=1, keepdims=True))
                close = (np.abs(new - rows) <= 1e-10 * np.abs(rows)).all(axis=1)
                step = live & (count > 0)
                rows = np.where(step[:, None], new, rows)
                live &= step & ~close
                if not live.any():
                    break
    return rows


def _refit_resample(base, Xa, tau, groups_rows, mult, weak):
    """One resample by a full refit on the resampled trajectories."""
    idx, labels = [], []
    for g, m in enumerate(mult):
        for copy in range(int(m)):
            idx.append(groups_rows[g])
            labels.append(np.full(len(groups_rows[g]), len(labels)))
    idx = np.concatenate(idx)
    labels = np.concatenate(labels)
    with warnings.catch_warnings(), without_probes():
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
