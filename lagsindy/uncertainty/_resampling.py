"""Resamples of the bootstrap, solved from per-trajectory Gram statistics.

The machinery behind :func:`lagsindy.uncertainty.bootstrap` (see its module for the
design): the per-group statistics (:class:`GroupStats`, from the fit's formulation's
``trajectory_statistics``), one resample solved by the pipeline's solve
(:func:`fast_resample`) or by a full refit (:func:`refit_resample`), and case I
resamples solved in one batch (:func:`batched_resamples`).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import torch
from sklearn.base import clone

from .. import pipeline
from .._torch import resolve_device, resolve_dtype, to_numpy, to_tensor
from ..cases import Solution
from ..formulation.forms import StrongForm, WeakForm, group_rows
from ..formulation.probes import without_probes
from ..formulation.scaling import BalancedGram

# The weak statistics are built at these multiples of the full fit's sampling
# interval (any three distinct values interpolate the quadratic exactly).
DT_NODES = (0.5, 1.0, 1.5)


def fast_path_supported(full) -> bool:
    """Whether a resample can be solved from statistics with the full fit's setup:
    the configuration makes no choice between models on the data (case I, or case
    III with a fixed term given), in the strong or the weak form."""
    if full.formulation_ not in ("strong", "weak"):
        return False
    if full.case_ == "forces":
        return True
    fixed = full.fixed_term
    return (
        full.case_ == "fixed"
        and full.normalization_ == "term"
        and fixed is not None
        and not (isinstance(fixed, str) and fixed == "mass")
    )


class GroupStats:
    """Per-group statistics from which a resample's statistics are summed.

    Parameters
    ----------
    nodes : list of TrajectoryStatistics
        The groups' statistics at each sampling interval of ``dts`` (weak form with
        an estimated ``dt``: three; else one). A weak Gram matrix is a quadratic
        polynomial in ``dt`` (each column is a kinetic part that does not depend on
        it plus ``dt`` times a potential and force part; the noise correction has
        the same form), so three nodes give it exactly at any ``dt`` by Lagrange
        interpolation.
    dts : ndarray or None
        The sampling intervals of ``nodes``; ``None`` when ``dt`` is held fixed.
    steps : tuple of Tensor or None
        ``(ratios, weights, owner)`` of
        :func:`~lagsindy.formulation.weak.estimate_sampling_interval`, sorted by
        ratio, with the group of each step: a resample's sampling interval is the
        weighted median with the weights times the group's multiplicity.
    """

    def __init__(self, nodes, dts=None, steps=None):
        self.nodes = nodes
        self.dts = dts
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

    def statistics(self, mult):
        """The statistics of the resample taking group ``g`` ``mult[g]`` times."""
        per_node = [node.total(mult) for node in self.nodes]
        dt = self.sampling_interval(mult)
        if dt is None:
            return per_node[0]
        x = self.dts
        basis = [
            np.prod([(dt - x[m]) / (x[j] - x[m]) for m in range(3) if m != j])
            for j in range(3)
        ]
        gram = sum(float(c) * s.gram for c, s in zip(basis, per_node))
        return dataclasses.replace(per_node[0], gram=gram, dt=dt)


def _step_ratios(Xt, n_dof, groups):
    """The sampling-interval statistics of every group (see :class:`GroupStats`).

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


def tensors(full, Xa, tau):
    """``Xa`` and ``tau`` as tensors of the estimator's device and precision."""
    device, dtype = resolve_device(full.device), resolve_dtype(full.dtype)
    Xt = to_tensor(Xa, dtype=dtype, device=device)
    return Xt, None if tau is None else to_tensor(tau, dtype=dtype, device=device)


def group_statistics(full, Xt, tau_t, labels) -> GroupStats:
    """Per-group statistics of the fitted ``full``'s configuration.

    Weak form: the fit's window and noise covariance; at three sampling intervals
    when the fit estimated ``dt`` (so a resample can use its own estimate).
    """
    setup = pipeline.setup_of(full)
    operator = setup.operator(range(setup.n_features), Xt.device, Xt.dtype)
    if full.formulation_ != "weak":
        strong = StrongForm().trajectory_statistics(operator, Xt, tau_t, labels)
        return GroupStats([strong])
    dt = float(full.dt_)
    estimated = pipeline.formulation_of(full.get_params(deep=False)).dt is None
    dts = np.array([c * dt for c in DT_NODES]) if estimated else np.array([dt])
    form = WeakForm(window=int(full.window_), dt=dt, noise_cov=full.noise_cov_)
    nodes = form.trajectory_statistics(operator, Xt, tau_t, labels, dts=dts)
    if not estimated:
        return GroupStats(nodes)
    steps = _step_ratios(Xt, full.n_dof_, group_rows(labels))
    return GroupStats(nodes, dts, steps)


def fast_resample(setup, stats, mult, Xt, memo, start=None):
    """One resample solved from the statistics; coefficients, or None if it fails."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            solution = pipeline.solve(
                stats.statistics(mult), setup, Xt, memo=memo, start=start, warn=False
            )
        except (ValueError, FloatingPointError, RuntimeError):
            return None
    coef = solution.coef
    return coef if np.all(np.isfinite(coef)) else None


def batch_supported(setup, dtype) -> bool:
    """Whether :func:`batched_resamples` knows this configuration (case I, steps
    ``1 / L``, float64); the others are solved one resample at a time."""
    return (
        setup.case == "forces"
        and not getattr(setup.library, "known_terms_", None)  # held terms: alone
        and setup.solver.alpha is None
        and setup.solver.max_stages >= 1
        and dtype == torch.float64
    )


def batched_resamples(setup, stats, mults, start=None):
    """Case I resamples solved together: the setup's staged solve on every resample
    at once (:meth:`~lagsindy.cases.SparseSolve.solve_across`: every stage's FISTA
    iterations batched over the resamples, every start of the path).

    The resamples are balanced together (:meth:`BalancedGram.many`), so each gets
    what its own solve would, up to rounding; the library's constraint (a robot's
    physical consistency: :func:`lagsindy.pipeline.constrained`) is then applied to
    each resample as :func:`lagsindy.pipeline.solve` applies it to a fit. Returns a
    list with the coefficients of each resample, or ``None`` where that resample
    must be solved alone (a different set of identifiable columns, a step the
    divergence guard would change, a failure).
    """
    n_features = setup.n_features
    out = [None] * len(mults)
    if len(mults) == 0:
        return out
    summed = [stats.statistics(m) for m in mults]
    balanced = BalancedGram.many(
        torch.stack([s.gram for s in summed]).to(torch.float64),
        [s.n_rows for s in summed],
        n_features,
        setup.normalize,
        summed[0].corrected,
    )
    ident = np.stack([b.identifiable().cpu().numpy() for b in balanced])
    same = np.flatnonzero((ident == ident[0]).all(axis=1))
    solved = setup.solver.solve_across(
        [balanced[i] for i in same],
        np.flatnonzero(ident[0]),
        n_features,
        1.0,
        setup.penalty(),
        0.0,
        start=start,
    )
    constrain = callable(getattr(setup.library, "constrain", None))
    for i, res in zip(same, solved):
        if res is None:
            continue
        out[i] = res[0]
        if constrain:  # the fit's constraint on each resample (a robot's consistency)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # as fast_resample's solves
                try:
                    p = pipeline.problem(summed[i], setup)
                    out[i] = pipeline.constrained(setup, p, Solution(*res)).coef
                except (ValueError, FloatingPointError, RuntimeError):
                    out[i] = None  # solved alone instead, like a failed member
    return out


def refit_resample(base, Xa, tau, groups_rows, mult, weak):
    """One resample by a full refit on the resampled trajectories."""
    idx, labels = [], []
    for g, m in enumerate(mult):
        for _ in range(int(m)):
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


def normalize_to(coef, ref):
    """Rescale ``coef`` so that feature ``ref`` has coefficient 1 (None if it is 0)."""
    if coef is None or ref is None:
        return coef
    if coef[ref] == 0:
        return None
    return coef / coef[ref]


__all__ = [
    "GroupStats",
    "batch_supported",
    "batched_resamples",
    "fast_path_supported",
    "fast_resample",
    "group_statistics",
    "normalize_to",
    "refit_resample",
    "tensors",
]
