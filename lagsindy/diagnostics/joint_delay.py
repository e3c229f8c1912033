"""A delay per driven input (a robot's joints): the ``"joint_delay"`` candidate.

:func:`lagsindy.delay.estimate_delay` finds one shift of the whole input. On a robot
each joint's drive may lag by its own amount; :func:`estimate_joint_delays` finds one
delay per input column (the convention of :func:`lagsindy.delay.shift_input`: a
delay ``d_j > 0`` means the torque recorded on joint ``j`` at ``t`` acts at
``t + d_j``).

The search is the single delay's ``method="support"`` search per column: the
estimator is fitted at delay 0 and, with its support fixed, its forces are linear in
the coefficients, so every candidate shift of one column is a least squares on the
support's force columns, scored on held-out trajectories (``GroupKFold``). The
columns are searched one at a time with the others at their current estimate
(coordinate descent, whole sample shifts refined by a parabola through the best
candidate and its neighbours) until no estimate moves by a hundredth of a sampling
interval; the estimator is then refitted on the input shifted per column and the
search repeated until its support is stable (at most 3 fits). Each column's
uncertainty is the spread of its per-fold estimates (the other columns held at the
final estimate).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from sklearn.base import clone
from sklearn.model_selection import GroupKFold

from .._torch import resolve_device, resolve_dtype, to_tensor
from .._validation import validate_state
from ..delay import search_base, segment_clock, shift_input, worth_trying
from ..formulation.operator import reuse_weak_columns
from ..formulation.probes import without_probes

__all__ = ["JointDelayEstimate", "estimate_joint_delays"]

# Default largest delay tried, in sampling intervals (10 ms at 1 kHz is a common
# drive lag: twice the single delay's range, so that it is not at the edge).
MAX_STEPS = 20
# Smallest delay proposed, in sampling intervals. Measured on the two-link arm
# without any delay (1 kHz, 6 s, 1 % torque noise): the shoulder's estimate was
# -0.27 +- 0.11 ms, and the input shifted by it (each held-out fold by the delay
# estimated without it, the Fourier shift) improved the held-out trajectory
# criterion by 9 %: a fraction of a sample of shift fits that record's noise. The
# single delay's floor, a tenth of a sample, let it through.
MIN_STEPS = 0.5
# Coordinate-descent sweeps over the columns per fitted support, and the change
# (in sampling intervals) below which an estimate has stopped moving.
MAX_SWEEPS = 6
SAME_DELAY = 1e-2
# After the first sweep, each column tries the shifts within this many samples of
# its estimate (all of them again when the best is at the window's edge).
WINDOW = 3


@dataclass
class JointDelayEstimate:
    """Result of :func:`estimate_joint_delays`.

    Attributes
    ----------
    delays : ndarray of shape (n_inputs,)
        Estimated delay of every input column in seconds (0 for an undriven one).
    std : ndarray of shape (n_inputs,)
        Their uncertainty: standard deviation of the per-fold estimates over the
        square root of the number of folds (NaN undriven or with one fold).
    driven : ndarray of bool, shape (n_inputs,)
        Columns with a nonzero input (the others have no delay to estimate).
    coordinates : list of str
        The input columns' coordinates.
    candidates : ndarray of shape (n_candidates,)
        The whole-sample shifts tried for every column.
    fold_delays : ndarray of shape (n_splits, n_inputs)
        Each fold's estimate per column.
    dt : float
        The sampling interval.
    left_out : ndarray of shape (n_splits, n_inputs)
        Per fold, the delays estimated without that fold's held-out scores (the
        other columns at their estimate): what a held-out criterion of that fold
        may use without having seen it.
    method : str
        How the delays are applied (:func:`lagsindy.delay.shift_input`'s
        ``method``): ``"fourier"`` on evenly sampled data, else ``"linear"``.
    """

    delays: np.ndarray
    std: np.ndarray
    driven: np.ndarray
    coordinates: list
    candidates: np.ndarray = field(repr=False)
    fold_delays: np.ndarray = field(repr=False)
    dt: float = float("nan")
    method: str = "fourier"
    left_out: np.ndarray = field(default=None, repr=False)

    def significant(self) -> np.ndarray:
        """Columns whose delay is kept: driven, more than twice its standard error
        (the rule of the single delay, :func:`lagsindy.delay.worth_trying`) and at
        least half a sampling interval (:data:`MIN_STEPS`)."""
        out = np.zeros(len(self.delays), dtype=bool)
        for j in np.flatnonzero(self.driven):
            one = _One(self.delays[j], self.std[j])
            out[j] = worth_trying(one, self.dt) and abs(self.delays[j]) >= (
                MIN_STEPS * self.dt
            )
        return out

    def kept(self) -> np.ndarray:
        """The delays with the insignificant ones set to 0 (seconds)."""
        return np.where(self.significant(), self.delays, 0.0)

    def __str__(self):
        parts = [
            f"{c} {1e3 * d:.2f} ms +- {1e3 * s:.2f}"
            for c, d, s, on in zip(self.coordinates, self.delays, self.std, self.driven)
            if on
        ]
        return (
            f"input delay per joint: {', '.join(parts)} ({len(self.fold_delays)} "
            f"folds, shifts from {1e3 * self.candidates[0]:.1f} to "
            f"{1e3 * self.candidates[-1]:.1f} ms)"
        )


@dataclass
class _One:  # what worth_trying reads of one column
    delay: float
    std: float


def _vertex(candidates, score):
    """Sub-sample minimum by the parabola through the best point and its neighbours
    (the best candidate itself at the ends); ``(delay, at_edge)``."""
    k = int(np.argmin(score))
    if k == 0 or k == len(score) - 1:
        return float(candidates[k]), True
    y0, y1, y2 = score[k - 1], score[k], score[k + 1]
    curvature = y0 - 2 * y1 + y2
    if not curvature > 0:
        return float(candidates[k]), False
    h = candidates[k + 1] - candidates[k]
    return float(candidates[k] + 0.5 * h * (y0 - y2) / curvature), False


class _FoldSolver:
    """Held-out least-squares scores of many right-hand sides on fixed columns.

    One QR factorization with column pivoting of each fold's training rows of ``A``
    (``n_rows * n_dof`` rows, sample-major), reused for every candidate input;
    columns that the others span to 1e-10 (a force candidate equal to a
    combination of base parameters on these data) are left out.
    """

    def __init__(self, A, rows, folds, n_dof):
        self.parts = []
        for train, _ in folds:
            tr = np.repeat(np.isin(rows, train), n_dof)
            te = ~tr
            q, r, perm = scipy.linalg.qr(A[tr], mode="economic", pivoting=True)
            diag = np.abs(np.diagonal(r))
            rank = int(np.sum(diag > 1e-10 * diag.max())) if diag.size else 0
            cols = perm[:rank]
            self.parts.append((tr, te, q[:, :rank], r[:rank, :rank], A[te][:, cols]))

    def scores(self, B, scale):
        """``B`` of shape (n_candidates, n_rows * n_dof): mean squared held-out
        error per fold and candidate, over ``scale``."""
        out = np.empty((len(self.parts), B.shape[0]))
        for f, (tr, te, q, r, a_te) in enumerate(self.parts):
            xi = scipy.linalg.solve_triangular(r, q.T @ B[:, tr].T, check_finite=False)
            err = a_te @ xi - B[:, te].T
            out[f] = np.mean(err**2, axis=0) / scale
        return out


def _near(candidates, delay, window):
    """Indices of the candidates within ``window`` shifts of ``delay`` (all of
    them with ``window=None``)."""
    if window is None:
        return np.arange(len(candidates))
    centre = int(np.argmin(np.abs(candidates - delay)))
    lo, hi = max(0, centre - window), min(len(candidates), centre + window + 1)
    if hi - lo < 3:
        return np.arange(len(candidates))
    return np.arange(lo, hi)


def _column_scores(solver, current, shifted, j, near, scale):
    """Held-out scores of column ``j`` shifted by each of the ``near`` candidates,
    the other columns as in ``current``."""
    B = np.repeat(current[None], len(near), axis=0)
    B[:, :, j] = shifted[near, :, j]
    return solver.scores(B.reshape(len(near), -1), scale)


def _force_columns(est, X):
    """Force columns, (n_samples * n_dof, n_columns), of the fitted ``est``'s kept
    Lagrangian terms and of every one of its force candidates (kept or not: a
    friction term the fit at a wrong delay dropped must not bias the search), or
    None when it kept no term."""
    Xa, _, _ = validate_state(est, X, reset=False, coordinates=est.coordinates_)
    Xt = to_tensor(
        Xa, dtype=resolve_dtype(est.dtype), device=resolve_device(est.device)
    )
    coef = est.fitted_.all_coef()
    n_lib = len(np.asarray(est.coef_))
    index = np.r_[np.flatnonzero(coef[:n_lib]), np.arange(n_lib, len(coef))]
    if not np.any(coef):
        return None
    op = est.fitted_.feature_operator(index, Xt.device, Xt.dtype)
    cols = np.asarray(op.columns(Xt).detach().cpu().numpy())
    return cols.reshape(-1, len(index))


def _even(t, bounds) -> bool:
    """Whether every trajectory is evenly sampled (the Fourier shift's need)."""
    for a, b in bounds:
        steps = np.diff(t[a:b])
        if len(steps) and np.max(np.abs(steps - np.median(steps))) > 1e-6 * np.median(
            steps
        ):
            return False
    return True


def _take_rows(X, rows):
    import pandas as pd

    return X.iloc[rows] if isinstance(X, pd.DataFrame) else np.asarray(X)[rows]


def estimate_joint_delays(
    estimator,
    X,
    tau,
    t,
    *,
    groups=None,
    max_delay=None,
    n_splits=3,
    verbose=0,
    fitted_at_zero=None,
    folds=None,
):
    """Estimate one delay per input column (a robot joint's drive lag).

    Parameters
    ----------
    estimator : LagrangianSINDy
        An unfitted estimator with the library and options of the final fit (cloned
        for every fit).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
    tau : array-like of shape (n_samples, n_dof)
        Recorded inputs.
    t : array-like of shape (n_samples,)
        Time stamps (increasing within each trajectory).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels; ``None``: the record is cut into ``n_splits`` pieces.
    max_delay : float, default=None
        Largest absolute delay tried per column, in seconds; ``None``: 20 sampling
        intervals.
    n_splits : int, default=3
    verbose : int, default=0
    fitted_at_zero : LagrangianSINDy, default=None
        ``estimator`` already fitted on every row and the recorded input (used as
        the first fit).
    folds : list of (train, test) row indices, default=None
        The held-out folds; ``None``: ``GroupKFold`` over ``groups``.

    Returns
    -------
    JointDelayEstimate

    Warns
    -----
    UserWarning
        When a column's best shift is at the end of the range (increase
        ``max_delay``).
    """
    n = len(X)
    tau2 = np.asarray(tau, dtype=float)
    tau2 = tau2[:, None] if tau2.ndim == 1 else tau2
    t = np.asarray(t, dtype=float)
    if tau2.shape[0] != n or t.shape != (n,):
        raise ValueError("X, tau and t must have the same number of rows")
    if groups is None:
        groups = np.minimum(np.arange(n) * n_splits // n, n_splits - 1)
    groups = np.asarray(groups)
    change = np.flatnonzero(groups[1:] != groups[:-1]) + 1
    bounds = list(zip(np.r_[0, change], np.r_[change, n]))
    if len(bounds) < 2:
        raise ValueError("estimate_joint_delays needs at least 2 trajectories")
    dt = float(np.median(np.concatenate([np.diff(t[a:b]) for a, b in bounds])))
    steps = MAX_STEPS if max_delay is None else int(math.floor(max_delay / dt + 1e-9))
    if steps < 1:
        raise ValueError(f"max_delay={max_delay} is below one sampling interval")
    candidates = dt * np.arange(-steps, steps + 1)
    keep = np.zeros(n, dtype=bool)
    for a, b in bounds:
        ts = t[a:b]
        edge = steps * dt * 1.000001
        keep[a:b] = (ts >= ts[0] + edge) & (ts <= ts[-1] - edge)
    if keep.sum() < 10 * len(bounds):
        raise ValueError("the trajectories are too short for the delays tried")
    rows = np.flatnonzero(keep)
    if folds is None:
        k = min(int(n_splits), len(bounds))
        folds = list(GroupKFold(n_splits=k).split(np.zeros(n), groups=groups))
    folds = [(np.asarray(a), np.asarray(b)) for a, b in folds]
    k = len(folds)
    m = tau2.shape[1]
    driven = np.any(tau2 != 0, axis=0)
    scale = float(np.mean(np.var(tau2[keep][:, driven], axis=0))) or 1.0
    # Fractional shifts by the Fourier method (linear interpolation would smooth
    # the noise, and a smoother input predicts better whatever the delay); whole
    # sample shifts are the same with both.
    method = "fourier" if _even(t, bounds) else "linear"
    # every candidate shift of every column, on the kept rows
    shifted = np.stack([shift_input(tau2, t, c, groups)[rows] for c in candidates])
    Xk, gk = _take_rows(X, rows), groups[rows]
    delays = np.zeros(m)
    fold_delays = np.zeros((k, m))
    left_out = np.zeros((k, m))
    support, edges = None, set()
    for fit_no in range(3):
        if fit_no == 0 and fitted_at_zero is not None:
            est = fitted_at_zero
        else:
            est = clone(estimator)
            with warnings.catch_warnings(), without_probes():
                warnings.simplefilter("ignore")
                if fit_no == 0:
                    est.fit(X, tau2, groups=groups)
                else:
                    acting = shift_input(tau2, t, delays, groups, method=method)[rows]
                    est.fit(Xk, acting, groups=gk)
        new_support = tuple(np.flatnonzero(est.fitted_.all_coef()))
        A = _force_columns(est, Xk)
        if A is None:
            raise ValueError("the fitted model kept no term: no delay to estimate")
        solver = _FoldSolver(A, rows, folds, m)
        current = shift_input(tau2, t, delays, groups, method=method)[rows]
        last = {}
        for sweep in range(MAX_SWEEPS):
            moved = 0.0
            for j in np.flatnonzero(driven):
                full = fit_no == 0 and sweep == 0
                near = _near(candidates, delays[j], None if full else WINDOW)
                scores = _column_scores(solver, current, shifted, j, near, scale)
                new, at_edge = _vertex(candidates[near], scores.mean(axis=0))
                if at_edge and len(near) < len(candidates):  # left the window
                    near = _near(candidates, delays[j], None)
                    scores = _column_scores(solver, current, shifted, j, near, scale)
                    new, at_edge = _vertex(candidates[near], scores.mean(axis=0))
                last[j] = (candidates[near], scores, at_edge)
                moved = max(moved, abs(new - delays[j]))
                delays[j] = new
                current[:, j] = shift_input(tau2[:, j], t, new, groups, method=method)[
                    rows
                ]
            if verbose > 1:
                print("  sweep", np.round(1e3 * delays, 3), flush=True)
            if moved <= SAME_DELAY * dt:
                break
        for j, (tried, scores, at_edge) in last.items():
            fold_delays[:, j] = [_vertex(tried, s)[0] for s in scores]
            for f in range(k):  # the estimate without fold f's scores
                others = np.delete(scores, f, axis=0) if k > 1 else scores
                left_out[f, j] = _vertex(tried, others.mean(axis=0))[0]
            if at_edge:
                edges.add(j)
        if verbose:
            print(
                f"[lagsindy] support of {len(new_support)} terms: delays "
                + ", ".join(f"{1e3 * d:.2f}" for d in delays)
                + " ms",
                flush=True,
            )
        if new_support == support:
            break
        if not np.any(np.abs(delays[driven]) >= MIN_STEPS * dt):
            break  # nothing to propose: a refit would only move what is dropped
        support = new_support
    std = np.full(m, math.nan)
    if k > 1:
        std[driven] = np.std(fold_delays[:, driven], axis=0, ddof=1) / np.sqrt(k)
    coords = list(getattr(estimator, "coordinates_", None) or [])
    if len(coords) != m:
        coords = [f"input {j}" for j in range(m)]
    estimate = JointDelayEstimate(
        delays, std, driven, coords, candidates, fold_delays, dt, method, left_out
    )
    for j in sorted(edges):
        warnings.warn(
            f"the best delay of {coords[j]} is at the end of the range tried "
            f"({1e3 * delays[j]:.1f} ms); it may be larger: increase max_delay",
            UserWarning,
            stacklevel=2,
        )
    return estimate


def diagnose_joint_delays(
    est,
    X,
    tau,
    segments,
    dt,
    verbose,
    fitted_at_zero=None,
    coordinates=None,
    folds=None,
):
    """For :func:`lagsindy.diagnose`: ``(JointDelayEstimate, tau shifted per column by
    the significant delays)``, or None when no column's delay is significant or the
    estimate fails."""
    n = len(tau)
    t, groups = segment_clock(segments, n, dt)
    base = search_base(est)
    try:
        with warnings.catch_warnings(), reuse_weak_columns():
            warnings.simplefilter("ignore")
            estimate = estimate_joint_delays(
                base,
                X,
                tau,
                t,
                groups=groups,
                fitted_at_zero=fitted_at_zero,
                folds=None if folds is None else _index_folds(folds, n),
            )
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        if verbose:
            print(f"[lagsindy] no per-joint delay estimate: {exc}")
        return None
    if coordinates is not None:
        estimate.coordinates = list(coordinates)
    if verbose:
        print(f"[lagsindy] {estimate}")
    if not estimate.significant().any():
        return None
    shifted = shift_input(tau, t, estimate.kept(), groups, method=estimate.method)
    return estimate, shifted, _cross_fitted(estimate, tau, t, groups, folds)


def _index_folds(folds, n):
    """diagnose's folds (lists of row blocks) as (train, test) row indices."""
    out = []
    for blocks in folds:
        test = np.sort(np.concatenate([np.asarray(b) for b in blocks]))
        out.append((np.setdiff1d(np.arange(n), test), test))
    return out


def _cross_fitted(estimate, tau, t, groups, folds):
    """The input diagnose scores per-joint delays on: the rows of each held-out
    fold shifted by the delays estimated without that fold (the significant
    columns only), so that the held-out criterion never sees a delay fitted on
    its own rows (one fitted on every row made a spurious 0.27 ms delay improve
    the trajectory criterion by 10 % on a delay-free arm). ``None`` without
    ``folds``."""
    if folds is None:
        return None
    keep = estimate.significant()
    out = np.array(tau, dtype=float, copy=True)
    for f, blocks in enumerate(folds):
        delays = np.where(keep, estimate.left_out[f], 0.0)
        moved = shift_input(tau, t, delays, groups, method=estimate.method)
        for b in blocks:
            out[b] = moved[b]
    return out
