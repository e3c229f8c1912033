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
path is the fit's own pipeline: the formulation's ``trajectory_statistics`` and
:func:`lagsindy.pipeline.solve` with the full fit's setup
(:func:`~lagsindy.pipeline.setup_of`). It checks itself: before any resample, it is
run on the full data's statistics and must reproduce the full fit (the weak form's
noise correction is summed over every sample per trajectory, over a subsample in a
fit of many rows); if it does not, every resample is a full refit
(``clone(est).fit``) instead, and the report says so (``fast_path``). Configurations that choose between models on the data
(case III without a fixed term or with ``fixed_term="mass"``, case II) always use full
refits.

Case I resamples are solved together (:func:`~._resampling.batched_resamples`): the
balancing of every resample's Gram matrix and each stage's FISTA iterations run on
stacked arrays
(:func:`lagsindy.solvers.staged.staged_fista_batch`), one batched product per iteration instead
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

import warnings
from dataclasses import dataclass
from numbers import Integral, Real

import numpy as np
import torch
from joblib import Parallel, delayed
from scipy.stats import norm
from sklearn.base import clone
from sklearn.utils import check_random_state

from .. import pipeline
from .._torch import resolve_dtype
from .._validation import validate_state
from ..formulation.forms import StrongForm, WeakForm, group_rows
from ..formulation.operator import NOISE_ROWS
from ..formulation.probes import without_probes
from ..partitioned import (
    as_partitioned,
    combine,
    is_partitioned,
    stack_trajectories,
    trajectory_pass,
)
from ..joint import refit_config, refit_setup
from ._resampling import (
    DT_NODES,
    GroupStats,
    batch_supported,
    batched_resamples,
    fast_path_supported,
    fast_resample,
    group_statistics,
    normalize_to,
    refit_resample,
    tensors,
)

__all__ = ["BootstrapReport", "bootstrap"]

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
# Fewer trajectories or blocks than this to resample: the report warns.
FEW_GROUPS = 5


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


def warn_few_groups(n_groups: int, resampling: str) -> bool:
    """Warn when fewer than ``FEW_GROUPS`` trajectories or blocks are resampled
    (the intervals are then too narrow). Returns whether it warned."""
    if n_groups >= FEW_GROUPS:
        return False
    warnings.warn(
        f"only {n_groups} {resampling} to resample: bootstrap intervals from so few "
        "independent units are too narrow; record more trajectories",
        UserWarning,
        stacklevel=3,
    )
    return True


def reproduces(got, want, rtol: float, scale: float) -> bool:
    """Whether coefficients ``got`` (``None``: a failed solve) have the support of
    ``want`` and differ from them by at most ``rtol * scale``: the test a fast path
    (``_SEAM_RTOL``) and the batched solve (``_BATCH_RTOL``) must pass before they
    are trusted."""
    return bool(
        got is not None
        and np.array_equal(got != 0, want != 0)
        and np.abs(got - want).max() <= rtol * scale
    )


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
    t=None,
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
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof), or partitioned data
        A Dask DataFrame or array, a Parquet path or chunks (see
        :mod:`lagsindy.partitioned`; ``tau`` and ``groups`` then name columns):
        the per-trajectory statistics are summed where the data are, and the
        resamples solved from them (case I, or case III with ``fixed_term``;
        at least 10 trajectories).
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
    t : array-like of shape (n_samples,) or CleanedClock, default=None
        The time stamps to fit with, as ``est.fit(X, tau, t=t)`` takes them (edge
        rows left out, the weak form's rows put on an even clock; resamples are
        drawn from those rows). Required when ``est`` was fitted with ``t=``.

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

    The intervals hold the fit's variability, not its bias. Derivatives estimated by
    smoothing noisy positions bias the fit (cart-pendulum, position noise 1e-2,
    P-spline: coefficients about 1 % low, intervals about +-0.5 % wide, coverage
    0.28 in ``benchmarks/results/calibration.md``); noise on measured states or
    forces does not (coverage 0.97). :func:`lagsindy.refine` (initial states fitted)
    lowered that bias on such data (1.2 % to 0.6 % on one cart-pendulum data set).
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if not (isinstance(n_resamples, Integral) and n_resamples >= 2):
        raise ValueError(f"n_resamples must be an integer >= 2, got {n_resamples!r}")
    if not (isinstance(level, Real) and 0 < level < 1):
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if not is_partitioned(X):  # the rows a fit given t= uses (t=None: as given)
        est, X, tau, groups = pipeline.on_fit_clock(
            est, X, tau, groups, t, what="bootstrap"
        )
    elif t is not None:
        raise ValueError("t= is for in-memory data; partitioned rows take no t=")
    full = clone(est).fit(X, tau, groups=groups)
    if is_partitioned(X):
        return _bootstrap_partitioned(
            full, X, tau, groups, n_resamples, level, method, random_state, verbose
        )
    Xa, tau_a, _ = validate_state(
        full, X, reset=False, y=tau, coordinates=full.coordinates_
    )
    n = Xa.shape[0]
    weak = full.formulation_ == "weak"
    params = {"library": clone(full.library_)}
    if weak:
        # The resamples estimate their own sampling interval (unless it was given);
        # the noise covariance and the window are the full fit's.
        form = pipeline.formulation_of(full.get_params(deep=False))
        params["formulation"] = type(form)(
            window=int(full.window_), dt=form.dt, noise_cov=full.noise_cov_
        )
    # a fit redone jointly with dissipation: the resamples' refits fit it too
    base = pipeline.copy_with(refit_config(full), **params)

    traj = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups)
    if traj.shape != (n,):
        raise ValueError(f"groups must have one label per row of X ({n})")
    trajectories = group_rows(traj)
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
    rows_of = group_rows(labels)
    n_groups = len(rows_of)
    warn_few_groups(n_groups, resampling)

    # Normalization of passive models: the full fit's fixed (or largest) term.
    all_coef = full.fitted_.all_coef()
    ref = None
    if full.case_ == "fixed":
        ref = full.library_.index(full.fixed_term_)
    elif full.case_ == "acceleration":
        ref = int(np.argmax(np.abs(all_coef)))

    mults, jack_mults = _draws(random_state, n_groups, n_resamples, method)

    fast = False
    stats = None
    start = full.stages_[0].coef if full.stages_ else None
    Xt, tau_t = tensors(full, Xa, tau_a)
    setup = refit_setup(full)  # with the rule the fit ended with
    memo = {}  # what the resamples' problems share (data and library only)
    if fast_path_supported(full):
        stats = group_statistics(full, Xt, tau_t, labels)
        if resampling == "blocks" and weak:
            with without_probes():  # the full fit above has reported them
                check = clone(base).fit(Xa, tau_a, groups=labels).fitted_.all_coef()
        else:
            check = all_coef
        seam = fast_resample(setup, stats, np.ones(n_groups), Xt, memo)
        scale = max(np.abs(check).max(), 1e-300)
        rtol = _SEAM_RTOL
        if weak and full.noise_cov_ is not None and n > NOISE_ROWS:
            rtol = _SEAM_RTOL_SUBSAMPLED
        fast = reproduces(seam, check, rtol, scale)
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

    plan = _Resamples(full, setup, stats, Xt, memo, all_coef, ref, resampling)
    plan.start = start
    if fast:
        plan.seam, plan.scale = seam, scale
    else:

        def refit(mult):
            return refit_resample(base, Xa, tau_a, rows_of, mult, weak)

        plan.refit = refit
    return _resample(plan, mults, jack_mults, level, method, n_jobs, verbose)


@dataclass
class _Resamples:
    """How :func:`bootstrap`'s resamples are solved and reported.

    The fit on all data (``full``, ``all_coef``; ``ref``: the term whose coefficient
    fixes a passive model's scale); the fast path's setup, per-group statistics
    and data (``Xt``, ``memo``), warm start and its solve of the full data
    (``seam``, agreeing with ``all_coef`` to ``scale``); ``refit(mult)``: a full
    refit of one resample, set instead when the fast path is not trusted.
    """

    full: object
    setup: object
    stats: object
    Xt: object
    memo: dict
    all_coef: np.ndarray
    ref: int | None
    resampling: str
    start: object = None
    seam: np.ndarray | None = None
    scale: float | None = None
    refit: object = None

    @property
    def fast(self) -> bool:
        """Whether the resamples are solved from the per-group statistics."""
        return self.refit is None

    def solve(self, mult):
        """One resample's coefficients (None where its solve fails)."""
        if not self.fast:
            return self.refit(mult)
        return fast_resample(
            self.setup, self.stats, mult, self.Xt, self.memo, self.start
        )


def _draws(random_state, n_groups, n_resamples, method):
    """The resamples' multiplicities of the groups (``n_resamples`` x ``n_groups``)
    and the jackknife's (leave one group out; none unless ``method="bca"``)."""
    rng = check_random_state(random_state)
    mults = rng.multinomial(
        n_groups, np.full(n_groups, 1.0 / n_groups), size=n_resamples
    )
    jack_mults = (
        1 - np.eye(n_groups, dtype=np.int64)
        if method == "bca"
        else np.zeros((0, n_groups))
    )
    return mults, jack_mults


def _resample(plan, mults, jack_mults, level, method, n_jobs, verbose):
    """Solve every resample (and jackknife sample) of ``plan`` and build the
    report."""
    full, setup, stats, start = plan.full, plan.setup, plan.stats, plan.start
    all_coef, fast, n_groups = plan.all_coef, plan.fast, mults.shape[1]
    n_resamples = len(mults)
    all_mults = np.concatenate([mults, jack_mults])
    n_jobs_eff = 1 if n_jobs is None else n_jobs
    chunks = np.array_split(
        np.arange(len(all_mults)), max(1, min(len(all_mults), _n_workers(n_jobs_eff)))
    )
    batched = None
    if fast and batch_supported(setup, plan.Xt.dtype):
        # Every resample in one batch (so the result does not depend on n_jobs),
        # the full data's statistics with them: the batch must reproduce the fit too.
        both = np.concatenate(
            [np.ones((1, n_groups), dtype=all_mults.dtype), all_mults]
        )
        try:
            solved = batched_resamples(setup, stats, both, start)
        except (ValueError, FloatingPointError, RuntimeError):
            # one unsolvable resample (a motionless stretch drawn many times:
            # "Eigenvalues did not converge") fails the batch: one at a time instead
            solved = None
        if solved is not None and reproduces(
            solved[0], plan.seam, _BATCH_RTOL, plan.scale
        ):
            batched = solved[1:]
    if batched is not None:
        missing = [i for i, c in enumerate(batched) if c is None]
        for i in missing:  # what the batch could not take: one at a time
            batched[i] = plan.solve(all_mults[i])
        results = [batched]
    else:

        def work(ix):
            return [plan.solve(all_mults[i]) for i in ix]

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
        c = normalize_to(c, plan.ref)
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
        resampling=plan.resampling,
        n_groups=n_groups,
        n_resamples=int(n_resamples),
        fast_path=bool(fast),
        n_failed=n_failed,
        estimator=full,
    )


def _bootstrap_partitioned(
    full, X, tau, groups, n_resamples, level, method, random_state, verbose
):
    """:func:`bootstrap` of partitioned data (Dask, Parquet, chunks): the
    per-trajectory statistics summed where the data are (one pass), the resamples
    solved from them like the in-memory fast path."""
    if not fast_path_supported(full):
        raise ValueError(
            "a bootstrap of partitioned data solves the resamples from "
            "per-trajectory statistics, which needs case I (forces) or case III "
            "with fixed_term=<a known term>; this configuration chooses between "
            f"models on the data (case={full.case_!r}, fixed_term="
            f"{full.fixed_term!r}): pass fixed_term=, or bootstrap in memory"
        )
    data = as_partitioned(X, groups=groups, y=tau)
    setup = refit_setup(full)  # with the rule the fit ended with
    dtype = resolve_dtype(full.dtype)
    estimated, dts = False, None
    form = StrongForm()
    if full.formulation_ == "weak":
        dt = float(full.dt_)
        estimated = pipeline.formulation_of(full.get_params(deep=False)).dt is None
        dts = [c * dt for c in DT_NODES] if estimated else [dt]
        form = WeakForm(window=int(full.window_), dt=dt, noise_cov=full.noise_cov_)
    task = trajectory_pass(setup, dtype, form, dts, steps=estimated)
    total = data.map_reduce(task, combine)
    nodes = stack_trajectories(total["traj"])
    n_groups = len(nodes[0])
    if n_groups < _MIN_TRAJECTORIES:
        raise ValueError(
            f"a bootstrap of partitioned data resamples whole trajectories and needs "
            f"at least {_MIN_TRAJECTORIES}, got {n_groups}: record more trajectories "
            "or bootstrap in memory (time blocks)"
        )
    stats = GroupStats(nodes)
    if estimated:
        owner = [np.full(r.size, k) for k, (r, _) in enumerate(total["rows"])]
        r = torch.as_tensor(np.concatenate([r for r, _ in total["rows"]]))
        w = torch.as_tensor(np.concatenate([w for _, w in total["rows"]]))
        order = torch.argsort(r)
        steps = (r[order], w[order], torch.as_tensor(np.concatenate(owner))[order])
        stats = GroupStats(nodes, np.asarray(dts), steps)
    all_coef = full.fitted_.all_coef()
    ref = full.library_.index(full.fixed_term_) if full.case_ == "fixed" else None
    mults, jack_mults = _draws(random_state, n_groups, n_resamples, method)
    Xt = torch.zeros((0, 3 * full.n_dof_), dtype=dtype)  # the statistics suffice
    memo = {}
    seam = fast_resample(setup, stats, np.ones(n_groups), Xt, memo)
    scale = max(np.abs(all_coef).max(), 1e-300)
    if not reproduces(seam, all_coef, _SEAM_RTOL, scale):
        raise ValueError(
            "the per-trajectory statistics of the partitions do not reproduce the "
            "partitioned fit (a solve that depends on rounding?); bootstrap in "
            "memory instead"
        )
    if verbose:
        print(
            f"[lagsindy] bootstrap: {n_resamples} resamples of {n_groups} "
            "trajectories (partitioned data), fast path"
        )
    start = full.stages_[0].coef if full.stages_ else None
    plan = _Resamples(full, setup, stats, Xt, memo, all_coef, ref, "trajectories")
    plan.start, plan.seam, plan.scale = start, seam, scale
    return _resample(plan, mults, jack_mults, level, method, None, verbose)


def _n_workers(n_jobs):
    from joblib import effective_n_jobs

    return max(1, effective_n_jobs(n_jobs))
