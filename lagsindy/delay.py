"""Input delay: estimate the lag between recorded inputs and positions, and apply it.

Actuators, drives and cameras delay the recorded input tau against the recorded
positions q by tens of milliseconds. Fitted as recorded, the Euler-Lagrange
regression then matches q_ddot(t) with tau(t) although the force acting at t was
recorded earlier; on a cart-pole this gave a negative cart mass. Convention here: a
delay ``d > 0`` means the input recorded at time ``t`` acts at ``t + d``, so the force
in the equations at time ``t`` is ``tau(t - d)``, which :func:`shift_input` returns.

:func:`estimate_delay` fits a clone of the estimator for each candidate delay on
training trajectories and scores it on held-out ones (GroupKFold), so the delay is
chosen by prediction, not by in-sample fit. Candidates are whole sample shifts (no
interpolation error); the estimate is refined below one sample by the vertex of the
parabola through the best candidate and its two neighbours, and its uncertainty is
the spread of the per-fold estimates. The support is refitted at every candidate
with ``method="refit"`` (``n_candidates * n_splits`` fits); the default
``method="support"`` fits the estimator at most 3 times and scores every candidate
by least squares on the fitted support (see :func:`estimate_delay`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from sklearn.base import clone
from sklearn.model_selection import GroupKFold

from . import pipeline
from ._torch import resolve_device, resolve_dtype, to_tensor
from ._validation import validate_state
from .joint import refit_config

__all__ = ["DelayEstimate", "estimate_delay", "shift_input"]


def _blocks(groups, n):
    """(label, slice) of contiguous blocks, one per trajectory."""
    if groups is None:
        return [(0, slice(0, n))]
    labels = np.asarray(groups)
    if labels.shape != (n,):
        raise ValueError(
            f"groups must have one label per row ({n}), got shape {labels.shape}"
        )
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts, stops = np.r_[0, change], np.r_[change, n]
    keys = [labels[a] for a in starts]
    if len(set(map(_hashable, keys))) != len(keys):
        raise ValueError(
            "the rows of each trajectory must be contiguous (sort by trajectory, t)"
        )
    return [(k, slice(int(a), int(b))) for k, a, b in zip(keys, starts, stops)]


def _hashable(x):
    return x.item() if hasattr(x, "item") else x


def shift_input(tau, t, delay, groups=None, *, method="linear"):
    """The input acting at each sample: ``tau(t - delay)``, per trajectory.

    Linear interpolation between samples (``method="linear"``), within each
    trajectory only. Where ``t - delay`` falls before the first (after the last)
    sample of a trajectory, the first (last) recorded value is held; drop the first
    ``delay`` seconds of each trajectory (or the last ``-delay``) if those rows
    matter.

    Parameters
    ----------
    tau : array-like of shape (n_samples, n_inputs) or (n_samples,)
        Recorded inputs.
    t : array-like of shape (n_samples,)
        Time stamps, increasing within each trajectory.
    delay : float or array-like of shape (n_inputs,)
        Seconds between recording an input and its action (> 0: the input acts
        later than recorded). 0 returns a copy. One delay per column of ``tau``
        shifts each input by its own (a robot's joints, whose drives lag
        differently: :func:`lagsindy.diagnose` with ``"joint_delay"``).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (contiguous rows); ``None``: one trajectory.
    method : {"linear", "fourier"}, default="linear"
        ``"fourier"``: a band-limited fractional shift (the phase of every
        frequency turned by the delay, evenly sampled trajectories only; beyond a
        trajectory's ends its mirror image stands in for the held values). Linear
        interpolation between two samples averages their noise (a shift by half a
        sample halves white noise's variance), so a noisy input shifted by a
        fraction of a sample is smoother than the recorded one whatever the true
        delay; the Fourier shift keeps the noise's variance (``diagnose``'s
        per-joint delays use it, so that smoothing is never taken for a delay).
        Whole-sample shifts are the same with both, away from the first (last)
        ``delay`` seconds.

    Returns
    -------
    ndarray, the shape of ``tau``
        The shifted inputs.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(5) * 0.01
    >>> shift_input(t * 100, t, 0.02).tolist()
    [0.0, 0.0, 0.0, 1.0, 2.0]
    >>> shift_input(np.c_[t, t] * 100, t, [0.0, 0.01])[:, 1].tolist()
    [0.0, 0.0, 1.0, 2.0, 3.0]
    """
    tau = np.asarray(tau, dtype=float)
    flat = tau.ndim == 1
    tau2 = tau[:, None] if flat else tau
    t = np.asarray(t, dtype=float)
    delays = np.asarray(delay, dtype=float)
    if delays.ndim > 1 or (delays.ndim == 1 and delays.shape != (tau2.shape[1],)):
        raise ValueError(
            f"delay must be a number of seconds or one per column of tau "
            f"({tau2.shape[1]}), got shape {delays.shape}"
        )
    if not np.all(np.isfinite(delays)):
        raise ValueError(f"delay must be a finite number of seconds, got {delay!r}")
    if t.shape != (tau2.shape[0],):
        raise ValueError(
            f"t must have one time stamp per row of tau ({tau2.shape[0]}), got shape "
            f"{t.shape}"
        )
    if method not in ("linear", "fourier"):
        raise ValueError(f"method must be 'linear' or 'fourier', got {method!r}")
    shift = _shift_many if method == "linear" else _shift_fourier
    if delays.ndim == 0:
        out = shift(tau2, t, delays[None], groups)[0]
    else:  # one delay per column
        out = np.empty_like(tau2)
        for j, dj in enumerate(delays):
            out[:, j] = shift(tau2[:, j : j + 1], t, dj[None], groups)[0, :, 0]
    return out[:, 0] if flat else out


def _shift_fourier(tau2, t, delays, groups):
    """:func:`_shift_many` by a band-limited shift (``method="fourier"``): each
    trajectory followed by its mirror image (periodic and continuous), every
    frequency's phase turned by ``delay``, the mirror image cut."""
    out = np.empty((len(delays),) + tau2.shape)
    for _, sl in _blocks(groups, len(t)):
        ts = t[sl]
        steps = np.diff(ts)
        if len(ts) < 2 or np.any(steps <= 0):
            raise ValueError(
                "t must increase within each trajectory; pass groups= for stacked "
                "trajectories"
            )
        dt = float(np.median(steps))
        if np.max(np.abs(steps - dt)) > 1e-6 * dt:
            raise ValueError(
                "method='fourier' needs evenly sampled trajectories; use "
                "method='linear' on an uneven clock"
            )
        x = tau2[sl]
        n = x.shape[0]
        # the trajectory and its mirror image: a periodic signal without a jump
        # (a jump from the last value to the first rings through the record)
        ext = np.concatenate([x, x[::-1]], axis=0)
        spectrum = np.fft.rfft(ext, axis=0)
        freq = np.fft.rfftfreq(2 * n, d=dt)
        for k, delay in enumerate(delays):
            turned = spectrum * np.exp(-2j * np.pi * freq * delay)[:, None]
            out[k, sl] = np.fft.irfft(turned, n=2 * n, axis=0)[:n]
    return out


def _shift_many(tau2, t, delays, groups):
    """:func:`shift_input` of the 2-d ``tau2`` for every delay in ``delays``.

    One interpolation per trajectory and input for all the delays (the same
    points, so the same values as one call per delay). Returns shape
    ``(len(delays),) + tau2.shape``.
    """
    out = np.empty((len(delays),) + tau2.shape)
    for _, sl in _blocks(groups, len(t)):
        ts = t[sl]
        if np.any(np.diff(ts) <= 0):
            raise ValueError(
                "t must increase within each trajectory; pass groups= for stacked "
                "trajectories"
            )
        at = (ts[None, :] - delays[:, None]).ravel()
        for j in range(tau2.shape[1]):
            out[:, sl, j] = np.interp(at, ts, tau2[sl, j]).reshape(len(delays), -1)
    return out


@dataclass
class DelayEstimate:
    """Result of :func:`estimate_delay`.

    Attributes
    ----------
    delay : float
        Estimated delay in seconds (> 0: the input acts after it is recorded).
    std : float
        Its uncertainty: standard deviation of the per-fold estimates divided by
        the square root of the number of folds (NaN with one fold).
    candidates : ndarray of shape (n_candidates,)
        The delays tried (whole sample shifts: every ``stride``-th of the range,
        then every one around the best; increasing).
    scores : ndarray of shape (n_splits, n_candidates)
        Held-out mean squared force error per fold and candidate, relative to the
        variance of the recorded input (lower is better).
    fold_delays : ndarray of shape (n_splits,)
        The estimate of each fold.
    """

    delay: float
    std: float
    candidates: np.ndarray = field(repr=False)
    scores: np.ndarray = field(repr=False)
    fold_delays: np.ndarray = field(repr=False)

    def __str__(self):
        return (
            f"input delay {1e3 * self.delay:.1f} ms +- {1e3 * self.std:.1f} ms "
            f"({len(self.fold_delays)} folds, {len(self.candidates)} candidates from "
            f"{1e3 * self.candidates[0]:.1f} to {1e3 * self.candidates[-1]:.1f} ms)"
        )


def _vertex(candidates, score):
    """Sub-sample minimum: vertex of the parabola through the best point and its
    neighbours (the best candidate itself at the ends of the range)."""
    k = int(np.argmin(score))
    if k == 0 or k == len(score) - 1:
        return float(candidates[k]), True
    y0, y1, y2 = score[k - 1], score[k], score[k + 1]
    h = candidates[k + 1] - candidates[k]
    curvature = y0 - 2 * y1 + y2
    if not curvature > 0:
        return float(candidates[k]), False
    return float(candidates[k] + 0.5 * h * (y0 - y2) / curvature), False


def estimate_delay(
    estimator,
    X,
    tau,
    t,
    *,
    groups=None,
    max_delay=None,
    n_splits=3,
    method="support",
    verbose=0,
):
    """Estimate the delay between the recorded input tau and the positions.

    For each candidate delay (whole sample shifts from ``-max_delay`` to
    ``max_delay``: every ``max(1, steps // 4)``-th first, then every one near the
    best of those), the input is shifted with :func:`shift_input`, a clone of
    ``estimator`` is fitted on the training trajectories of each ``GroupKFold``
    fold and its forces are compared with the shifted input on the held-out
    trajectories. The delay minimising the mean held-out error is refined between
    samples by a parabola through the best candidate and its neighbours. The same
    rows (without the first and last ``max_delay`` seconds of each trajectory,
    where a shift would run out of data) are used for every candidate.

    Parameters
    ----------
    estimator : LagrangianSINDy
        An unfitted estimator with the library and options of the final fit
        (cloned for every fit; pass ``formulation=`` explicitly).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        ``[q, q_dot, q_ddot]`` (e.g. from :func:`~lagsindy.derivatives`).
    tau : array-like of shape (n_samples, n_dof)
        Recorded inputs.
    t : array-like of shape (n_samples,)
        Time stamps (increasing within each trajectory).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels. ``None``: the record is cut into ``n_splits``
        contiguous pieces for the folds.
    max_delay : float, default=None
        Largest absolute delay tried, in seconds. ``None``: 10 sampling intervals.
    n_splits : int, default=3
        Folds of trajectories (at most the number of trajectories).
    method : {"support", "refit"}, default="support"
        ``"refit"``: a sparse fit of a clone of ``estimator`` per candidate and fold
        (``n_candidates * n_splits`` fits; slow). ``"support"``: fit the estimator
        once (at delay 0), then, with its support fixed, the model's forces are
        linear in the coefficients, so each candidate and fold is an ordinary least
        squares on the support's force columns (all candidates cost less than one
        sparse fit; the fit at delay 0 uses every row, since no shift runs out of
        data there); the estimator is refitted at the estimated delay and the search
        repeated until the support no longer changes or the estimate stays where the
        last fit was made (within a hundredth of a sampling interval; at most 3
        fits). The sparse penalty only chooses the support, so with the right
        support both rank the delays alike. Falls back to ``"refit"`` if the
        estimator's force columns cannot be read.
    verbose : int, default=0
        Print progress (one line per candidate) when > 0.

    Returns
    -------
    DelayEstimate
        ``delay`` (seconds), ``std`` (its uncertainty), and the score table.

    Raises
    ------
    ValueError
        If there are fewer than 2 trajectories (pieces), or the data are too
        short for ``max_delay``.

    Warns
    -----
    UserWarning
        When the best candidate is at the end of the range: the delay may be
        larger; increase ``max_delay``.

    Examples
    --------
    >>> from lagsindy import LagrangianSINDy  # doctest: +SKIP
    >>> est = LagrangianSINDy(library, formulation="strong")  # doctest: +SKIP
    >>> d = estimate_delay(est, X, tau, t, groups=groups)  # doctest: +SKIP
    >>> est.fit(X, shift_input(tau, t, d.delay, groups), groups=groups)  # doctest: +SKIP
    """
    return _estimate_delay(
        refit_config(estimator),  # a jointly refitted model: its dissipation
        X,
        tau,
        t,
        groups=groups,
        max_delay=max_delay,
        n_splits=n_splits,
        method=method,
        verbose=verbose,
    )


def _estimate_delay(
    estimator,
    X,
    tau,
    t,
    *,
    groups=None,
    max_delay=None,
    n_splits=3,
    method="support",
    verbose=0,
    fitted_at_zero=None,
):
    """:func:`estimate_delay`; ``fitted_at_zero``: ``estimator`` already fitted on
    every row of ``X`` and the unshifted ``tau`` (with ``groups``), used as the
    support search's first fit instead of fitting it again."""
    import warnings

    from .formulation.probes import without_probes

    n = len(X)
    tau = np.asarray(tau, dtype=float)
    tau2 = tau[:, None] if tau.ndim == 1 else tau
    t = np.asarray(t, dtype=float)
    if tau2.shape[0] != n or t.shape != (n,):
        raise ValueError(
            f"X, tau and t must have the same number of rows, got {n}, "
            f"{tau2.shape[0]} and {t.shape[0] if t.ndim else 'a scalar'}"
        )
    if groups is None:
        if n_splits < 2:
            raise ValueError("n_splits must be at least 2")
        groups = np.minimum(np.arange(n) * n_splits // n, n_splits - 1)
    groups = np.asarray(groups)
    blocks = _blocks(groups, n)
    if len(blocks) < 2:
        raise ValueError(
            "estimate_delay needs at least 2 trajectories to hold some out; pass "
            "groups=None to cut a single record into pieces"
        )
    dt = float(np.median(np.concatenate([np.diff(t[sl]) for _, sl in blocks])))
    if max_delay is None:
        max_delay = 10 * dt
    steps = int(math.floor(float(max_delay) / dt + 1e-9))
    if steps < 1:
        raise ValueError(
            f"max_delay={max_delay} is below one sampling interval ({dt:.4g} s)"
        )
    candidates = dt * np.arange(-steps, steps + 1)
    keep = np.zeros(n, dtype=bool)
    for _, sl in blocks:
        ts = t[sl]
        keep[sl] = (ts >= ts[0] + steps * dt * 1.000001) & (
            ts <= ts[-1] - steps * dt * 1.000001
        )
    if keep.sum() < 10 * len(blocks):
        raise ValueError(
            f"the trajectories are too short for max_delay={max_delay}: too few rows "
            "remain once the first and last max_delay seconds are dropped"
        )
    k = min(int(n_splits), len(blocks))
    folds = list(GroupKFold(n_splits=k).split(np.zeros(n), groups=groups))
    scale = float(np.mean(np.var(tau2[keep], axis=0)))
    scores = np.full((k, len(candidates)), np.nan)
    rows = np.flatnonzero(keep)

    if method not in ("support", "refit"):
        raise ValueError(f"method must be 'support' or 'refit', got {method!r}")
    if method == "support":
        result = _support_search(
            estimator,
            X,
            tau2,
            t,
            groups,
            rows,
            folds,
            candidates,
            scale,
            verbose,
            fitted_at_zero,
        )
        if result is not None:
            scores, fold_delays, delay, at_edge = result
            return _finish(delay, at_edge, candidates, scores, fold_delays, k)
    Xk, gk = _take_rows(X, rows), groups[rows]

    def evaluate(c):
        if not np.isnan(scores[0, c]):
            return
        shifted = shift_input(tau2, t, candidates[c], groups)[rows]
        for f, (train, _) in enumerate(folds):
            tr = np.isin(rows, train)
            te = ~tr
            est = clone(estimator)
            with warnings.catch_warnings(), without_probes():
                warnings.simplefilter("ignore")
                est.fit(_take_rows(Xk, tr), shifted[tr], groups=gk[tr])
                pred = np.asarray(est.predict(_take_rows(Xk, te)))
            pred = pred.reshape(shifted[te].shape)
            scores[f, c] = float(np.mean((pred - shifted[te]) ** 2)) / scale
        if verbose:
            print(
                f"delay {1e3 * candidates[c]:+.1f} ms: held-out error "
                f"{scores[:, c].mean():.4g}",
                flush=True,
            )

    # every stride-th shift first, then every shift around the best of those
    stride = max(1, steps // 4)
    coarse = sorted(set(range(0, 2 * steps + 1, stride)) | {2 * steps})
    for c in coarse:
        evaluate(c)
    best = coarse[int(np.argmin(np.nanmean(scores[:, coarse], axis=0)))]
    for c in range(max(best - stride, 0), min(best + stride, 2 * steps) + 1):
        evaluate(c)
    best = int(np.nanargmin(np.nanmean(scores, axis=0)))
    for c in (best - 1, best + 1):
        if 0 <= c <= 2 * steps:
            evaluate(c)
    tried = ~np.isnan(scores[0])
    candidates, scores = candidates[tried], scores[:, tried]
    delay, at_edge = _vertex(candidates, scores.mean(axis=0))
    fold_delays = np.array([_vertex(candidates, s)[0] for s in scores])
    return _finish(delay, at_edge, candidates, scores, fold_delays, k)


def _take_rows(X, rows):
    """The ``rows`` of ``X`` (an array-like or a DataFrame, whose columns stay)."""
    import pandas as pd

    return X.iloc[rows] if isinstance(X, pd.DataFrame) else np.asarray(X)[rows]


def _finish(delay, at_edge, candidates, scores, fold_delays, k):
    import warnings

    std = float(np.std(fold_delays, ddof=1) / np.sqrt(k)) if k > 1 else math.nan
    if at_edge:
        warnings.warn(
            f"the best delay is at the end of the range tried ({1e3 * delay:.1f} ms); "
            "the delay may be larger: call estimate_delay again with a larger "
            "max_delay",
            UserWarning,
            stacklevel=3,
        )
    return DelayEstimate(delay, std, candidates, scores, fold_delays)


def _force_columns(est, X):
    """Force of each support term at X, (n_samples * n_dof, n_support), or None
    when the model kept no term."""
    Xa, _, _ = validate_state(est, X, reset=False, coordinates=est.coordinates_)
    device, dtype = resolve_device(est.device), resolve_dtype(est.dtype)
    Xt = to_tensor(Xa, dtype=dtype, device=device)
    cols, coef = est.fitted_.support_columns(Xt)
    if coef.size == 0:
        return None
    return cols.reshape(-1, coef.size)


# Delays within this fraction of a sampling interval count as the same for the
# support search's refits.
SAME_DELAY = 1e-2


def _support_search(
    estimator,
    X,
    tau2,
    t,
    groups,
    rows,
    folds,
    candidates,
    scale,
    verbose,
    fitted_at_zero=None,
):
    """Least squares on a fixed support for every candidate; refit at the estimate
    until the support is stable. Returns None when the columns cannot be read.

    The first fit, at delay 0, sees every row of ``X`` (``fitted_at_zero`` when
    given); the refits at other delays see the ``rows`` that every candidate's
    shift covers. The scores are always on those rows."""
    import warnings

    from .formulation.probes import without_probes

    n_dof = tau2.shape[1]
    Xk, gk = _take_rows(X, rows), groups[rows]
    shifted = _shift_many(tau2, t, np.asarray(candidates, dtype=float), groups)[:, rows]
    step = float(candidates[1] - candidates[0])
    delay, support, fitted_at = 0.0, None, None
    for _ in range(3):
        if fitted_at is not None and abs(delay - fitted_at) <= SAME_DELAY * step:
            # The estimate is where the last fit was made: a refit there would see
            # the input it saw (to a hundredth of a sample's change) and keep its
            # support, so the search has converged.
            break
        first = fitted_at is None
        fitted_at = delay
        if first and fitted_at_zero is not None:
            est = fitted_at_zero
        else:
            est = clone(estimator)
            with warnings.catch_warnings(), without_probes():
                warnings.simplefilter("ignore")
                if first:  # delay 0: the recorded input, no row runs out of data
                    est.fit(X, tau2, groups=groups)
                else:
                    est.fit(Xk, shift_input(tau2, t, delay, groups)[rows], groups=gk)
        new_support = tuple(np.flatnonzero(np.asarray(est.coef_)))
        A = _force_columns(est, Xk)
        if A is None:
            return None
        B = shifted.reshape(len(candidates), -1)
        scores = _fold_scores(A, B, rows, folds, n_dof, scale)
        delay, at_edge = _vertex(candidates, scores.mean(axis=0))
        if verbose:
            print(
                f"support of {len(new_support)} terms: delay {1e3 * delay:.2f} ms",
                flush=True,
            )
        if new_support == support:
            break
        support = new_support
    fold_delays = np.array([_vertex(candidates, s)[0] for s in scores])
    return scores, fold_delays, delay, at_edge


def _fold_scores(A, B, rows, folds, n_dof, scale):
    """Held-out error of the least-squares fit of every candidate's input, per fold.

    Row ``c`` of ``B`` is candidate ``c``'s (shifted) input, flattened as the rows of
    ``A``. In each fold the training rows' least squares of all the candidates is
    one factorization of the fold's columns with a right-hand side per candidate
    (:func:`_least_squares`), equal to one :func:`numpy.linalg.lstsq` per candidate
    up to rounding. NumPy's BLAS runs on one thread here: on a loaded machine its
    threaded products of this size wait for a busy core far longer than they
    compute.

    Returns
    -------
    ndarray of shape (n_folds, n_candidates)
        Mean squared held-out error divided by ``scale``.
    """
    scores = np.empty((len(folds), B.shape[0]))
    with _one_blas_thread():
        for f, (train, _) in enumerate(folds):
            tr = np.repeat(np.isin(rows, train), n_dof)
            te = ~tr
            xi = _least_squares(A[tr], B[:, tr].T)
            err = A[te] @ xi - B[:, te].T  # (held-out rows, candidates)
            scores[f] = np.mean(err**2, axis=0) / scale
    return scores


def _least_squares(A, B):
    """``numpy.linalg.lstsq(A, B)[0]`` for a tall ``A``, by QR where it is well
    conditioned (a third of the SVD's time on the delay search's folds); the SVD's
    minimum-norm solution where ``R``'s diagonal says ``A`` is near rank deficient."""
    if A.shape[0] >= A.shape[1] > 0:
        q, r = np.linalg.qr(A)
        diag = np.abs(np.diagonal(r))
        if diag.min() > 1e-8 * diag.max():
            return scipy.linalg.solve_triangular(r, q.T @ B, check_finite=False)
    return np.linalg.lstsq(A, B, rcond=None)[0]


_CONTROLLER = []  # threadpoolctl's controller, made once (it scans the libraries)


def _one_blas_thread():
    """Context limiting NumPy's BLAS to one thread (``threadpoolctl``, which
    scikit-learn requires; a no-op without it)."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - scikit-learn depends on it
        import contextlib

        return contextlib.nullcontext()
    if not _CONTROLLER:
        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0].limit(limits=1, user_api="blas")


def diagnose_delay(est, X, tau, segments, dt, verbose, fitted_at_zero=None):
    """Estimate an input delay; ``(DelayEstimate, shifted tau)`` or None.

    For :func:`lagsindy.diagnose`: :func:`estimate_delay` (held-out force
    prediction over folds of trajectories, up to 10 sampling intervals either way)
    with the (unfitted) configuration ``est``; ``fitted_at_zero``, when given, is
    ``est`` already fitted on every row and the recorded input (the search's first
    fit). Kept only when the estimate is at least a tenth of a sampling interval and
    twice its standard error; diagnose then accepts it only if the model refitted
    on the shifted input improves its held-out criterion.
    """
    import warnings

    from .formulation.operator import reuse_weak_columns

    t, groups = segment_clock(segments, len(tau), dt)
    base = search_base(est)
    try:
        # Its refits differ only in the shifted input: with the weak form they
        # reuse the first one's feature integrals (the Gram matrices agree with
        # fits afresh to rounding; the search reads the refits' supports).
        with warnings.catch_warnings(), reuse_weak_columns():
            warnings.simplefilter("ignore")
            estimate = _estimate_delay(
                base, X, tau, t, groups=groups, fitted_at_zero=fitted_at_zero
            )
            shifted = shift_input(tau, t, estimate.delay, groups)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        if verbose:
            print(f"[lagsindy] no input delay estimate: {exc}")
        return None
    if verbose:
        print(f"[lagsindy] {estimate}")
    if not worth_trying(estimate, dt):
        return None
    return estimate, shifted


def segment_clock(segments, n, dt):
    """A clock restarting at 0 in each segment (index arrays of ``n`` rows, sampling
    interval ``dt``) and the rows' segment labels: ``(t, groups)``, ``groups``
    ``None`` for one segment. What the delay searches of diagnose run on."""
    t = np.zeros(n)
    labels = np.zeros(n, dtype=np.int64)
    for k, seg in enumerate(segments):
        t[seg] = np.arange(len(seg)) * dt
        labels[seg] = k
    return t, (labels if len(segments) >= 2 else None)


def search_base(est):
    """The estimator a delay search refits: ``est``'s configuration (its rule, its
    joint fit), quiet, with the formulation and window its fit used."""
    return pipeline.copy_with(
        refit_config(est), verbose=0, formulation=pipeline.fitted_formulation(est)
    )


def worth_trying(estimate, dt) -> bool:
    """Whether :func:`diagnose_delay` keeps a :class:`DelayEstimate` for diagnose to
    try: at least a tenth of the sampling interval ``dt`` and more than twice its
    standard error."""
    size = abs(estimate.delay)
    if size < 0.1 * dt or (np.isfinite(estimate.std) and size <= 2 * estimate.std):
        return False
    return True
