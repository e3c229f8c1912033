"""A regular cycle under jittery time stamps, and whether the motion agrees with it.

A robot controller samples its state on an exact cycle (say 1 kHz) while a logging
computer stamps the rows with its own clock, which jitters; a camera exposes frames
evenly while the receiving computer stamps them late by varying amounts. The stamps
then scatter around ``phase + count * period`` with integer cycle counts. This
module finds such a cycle (:func:`find_cycle`: from the stamps alone when they
cluster on multiples of a base period, or from recorded velocities, where the
position increments divided by velocity x period sit on integers) and asks the
motion which time base is right (:func:`motion_scores`: the P-spline's GCV score,
an estimate of the residual variance of the positions, on each time base).
"""

from __future__ import annotations

import math

import numpy as np

from .pspline import _PSPLINE_ORDERS, _BandedBasis, _BandedPSpline

# Rows of the periodogram that starts the search for the cycle, and its range
# around the median step (relative).
_FIRST_ROWS = 256
_SEARCH = 0.1
# A cycle counts as found from the stamps when their phases on it are this
# concentrated (mean resultant length; uniform jitter of +-0.3 periods gives 0.50,
# +-0.2 gives 0.76, stamps with no cycle about 1 / sqrt(rows)) ...
MIN_CONCENTRATION = 0.3
# ... and at most this fraction of the stamps lies farther than _AMBIGUOUS periods
# from its cycle (there the count could be either neighbour).
MAX_AMBIGUOUS = 0.01
_AMBIGUOUS = 0.4
# Recorded velocities: a step's count (increment / (velocity x period)) is trusted
# when it is this close to an integer and the step moves at least _MIN_SPEED of the
# record's median movement per step.
_COUNT_TOL = 0.2
_MIN_SPEED = 0.2
# The motion check fits at most this many rows per trajectory.
MOTION_ROWS = 20000


def _line(t, c):
    """Least-squares ``t = phase + c * period``; returns (phase, period)."""
    c = c.astype(np.float64)
    cm, tm = c.mean(), t.mean()
    dc = c - cm
    denom = float(dc @ dc)
    period = float(dc @ (t - tm)) / denom if denom > 0 else float("nan")
    return tm - period * cm, period


def _periodogram(t, p0):
    """Frequency (1 / period) near ``1 / p0`` where the stamps' phases concentrate."""
    span = t[-1] - t[0]
    f0 = 1.0 / p0
    if not span > 0:
        return f0, 0.0
    step = 1.0 / (8.0 * span)
    n_f = int(2 * _SEARCH * f0 / step) + 1
    freqs = f0 * (1 - _SEARCH) + step * np.arange(n_f)
    x = t - t[0]
    power = np.empty(n_f)
    for a in range(0, n_f, 256):  # blocks of frequencies: bounded memory
        phase = np.outer(freqs[a : a + 256], x)
        power[a : a + 256] = np.hypot(
            np.cos(2 * np.pi * phase).sum(1), np.sin(2 * np.pi * phase).sum(1)
        )
    k = int(np.argmax(power))
    f = freqs[k]
    if 0 < k < n_f - 1:  # parabolic refinement of the peak
        y0, y1, y2 = power[k - 1], power[k], power[k + 1]
        denom = y0 - 2 * y1 + y2
        if denom < 0:
            f += step * 0.5 * (y0 - y2) / denom
    return f, power[k] / len(t)


def _refine(t, p, fit_period=True):
    """Phase (and period) of the cycle: the phase on the first rows, then least
    squares of the stamps on their nearest counts over a doubling number of rows
    (so that a small error of the period never adds up to half a cycle)."""
    n = len(t)
    first = t[: min(n, _FIRST_ROWS)]
    z = np.exp(2j * np.pi * (first - first[0]) / p).mean()
    phase = first[0] + p * (np.angle(z) / (2 * np.pi))
    m = len(first)
    while True:
        c = None
        for _ in range(8):  # to a fixed point of the counts on these rows
            new = np.round((t[:m] - phase) / p).astype(np.int64)
            if c is not None and np.array_equal(new, c):
                break
            c = new
            if fit_period and np.ptp(c) > 0:
                phase, p = _line(t[:m], c)
            else:
                phase = float(np.mean(t[:m] - c * p))
            if not (math.isfinite(p) and p > 0):
                return None
        if m == n:
            return phase, p
        m = min(n, 2 * m)


def _stamps_period(t):
    """The period where the stamps' phases concentrate (None: no clear peak)."""
    steps = np.diff(t)
    positive = steps[steps > 0]
    if positive.size < 16:
        return None
    first = t[: 8 * _FIRST_ROWS]
    f, power = _periodogram(first, float(np.median(positive)))
    if power < max(0.05, 4 / np.sqrt(first.size)):
        return None
    fitted = _refine(t, 1.0 / f, True)
    return None if fitted is None else fitted[1]


def cycle_from_stamps(t, period=None):
    """Integer cycle counts under jittery stamps, or None when there is no cycle.

    Parameters
    ----------
    t : ndarray of shape (n,)
        Stamps of one trajectory (rows that repeat a stale sample removed).
    period : float, optional
        The cycle's period when known (then only the phase is fitted first).

    Returns
    -------
    (counts, phase, period, trusted) or None
        ``counts`` (int, non-decreasing) with ``t ~ phase + counts * period``;
        ``trusted``: the fraction of the stamps within 0.4 periods of their count.
    """
    n = len(t)
    steps = np.diff(t)
    positive = steps[steps > 0]
    if n < 16 or positive.size == 0:
        return None
    first = t[: min(n, _FIRST_ROWS)]
    if period is None:
        f, _ = _periodogram(first, float(np.median(positive)))
        p = 1.0 / f
    else:
        p = float(period)
    fitted = _refine(t, p, period is None)
    if fitted is None:
        return None
    phase, p = fitted
    c = np.round((t - phase) / p).astype(np.int64)
    r = (t - phase) / p - c
    concentration = float(np.abs(np.exp(2j * np.pi * r).mean()))
    ambiguous = float(np.mean(np.abs(r) > _AMBIGUOUS))
    if concentration < MIN_CONCENTRATION or ambiguous > MAX_AMBIGUOUS:
        return None
    if np.any(np.diff(c) < 0):
        return None
    return c - c[0], phase + c[0] * p, p, 1.0 - ambiguous


def cycle_from_velocities(t, q, v, period=None):
    """Cycle counts from recorded velocities: increments / (velocity x period).

    Each step's count is measured as ``dq . vbar / (|vbar|^2 period)`` (``vbar`` the
    mean velocity of its two rows); the counts are then the increasing integers
    closest to both the stamps and these measurements (:func:`_counts`).

    Returns
    -------
    (counts, phase, period, trusted) or None
        ``trusted``: fraction of the steps whose measured count is within
        ``_COUNT_TOL`` of an integer.
    """
    if len(t) < 16:
        return None
    vbar = 0.5 * (v[1:] + v[:-1])
    p = period
    if p is None:
        p = _stamps_period(t)
    from_motion = p is None
    if from_motion:  # no cycle in the stamps: the motion's single steps
        dq = np.diff(q, axis=0)
        speed2 = np.sum(vbar * vbar, axis=1)
        ok = speed2 > 0
        tau = np.sum(dq[ok] * vbar[ok], axis=1) / speed2[ok]
        base = tau[tau > 0]
        if base.size < 8:
            return None
        p = float(np.median(base[base < 1.5 * np.median(base)]))
    if not p > 0:
        return None
    return _counts(t, q, vbar * p, p, period is None, require_trust=from_motion)


def _local_rate(dq, steps, half=3):
    """Per-coordinate increment per cycle at each step: the median of
    ``dq_j / steps_j`` over the ``half`` steps on each side (robust to a few wrong
    counts; the step itself left out)."""
    m = dq.shape[0]
    per = dq / np.maximum(steps, 1)[:, None]
    padded = np.pad(per, ((half, half), (0, 0)), mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1, axis=0)
    others = np.delete(windows, half, axis=2)  # (m, n_dof, 2 half)
    return np.median(others, axis=2)[:m]


def _counts(t, q, rate, p, fit_period=True, require_trust=True):
    """Counts from per-step expected increments per cycle ``rate`` and the stamps.

    ``require_trust``: give up (None) when fewer than half the steps are counted
    from the motion with confidence (where the period itself came from the motion);
    otherwise the stamps fill in where the motion cannot tell.

    Returns (counts, phase, period, trusted) or None.
    """
    n = len(t)
    dq = np.diff(q, axis=0)
    r2 = np.sum(rate * rate, axis=1)
    move = np.sqrt(np.sum(dq * dq, axis=1))
    some = (r2 > 0) & (move > 0)
    if some.sum() < 8:
        return None
    measured = np.zeros(n - 1)
    measured[some] = np.sum(dq[some] * rate[some], axis=1) / r2[some]
    nearest = np.round(measured)
    moving = some & (move >= _MIN_SPEED * np.median(move[some]))
    trusted = moving & (np.abs(measured - nearest) <= _COUNT_TOL) & (nearest >= 1)
    if require_trust and trusted.mean() < 0.5:
        return None
    fitted = _refine(t, p, fit_period)
    if fitted is None:
        return None
    phase, p_stamps = fitted
    x = (t - phase) / p_stamps  # stamps in periods
    # the stamps' jitter (periods), from chains of rows linked by trusted steps
    # (their counts are known relative to each other)
    chain = np.r_[0, np.cumsum(~trusted)]
    rel = np.r_[0, np.cumsum(np.where(trusted, nearest, 0))]
    first = np.r_[0, np.flatnonzero(np.diff(chain)) + 1]
    rel = rel - rel[first][chain]  # 0 at each chain's first row
    size = np.bincount(chain)
    lag = x - rel
    centre = np.bincount(chain, lag) / size
    long = size[chain] >= 8
    jitter = (
        float(np.sqrt(np.mean((lag[long] - centre[chain][long]) ** 2)))
        if long.sum() >= 32
        else 0.3
    )
    # the measured counts: as precise as the trusted ones where the step moves as
    # much, less where it moves less, nothing where it stands still
    spread = max(float(np.sqrt(np.mean((measured - nearest)[trusted] ** 2))), 0.02)
    sigma = np.full(n - 1, np.inf)
    sigma[some] = spread * np.maximum(1.0, np.median(move[some]) / move[some])
    c = _most_likely_counts(x, measured, sigma, max(jitter, 0.02))
    phase, fitted_p = _line(t, c)
    if fit_period and math.isfinite(fitted_p) and abs(fitted_p / p - 1) < 0.05:
        p = fitted_p  # the stamps' units (a logging clock may run slightly off)
    phase = float(np.mean(t - c * p))
    return c - c[0], phase + c[0] * p, p, float(trusted.mean())


def _most_likely_counts(x, step, sigma, jitter, reach=2):
    """Increasing integer counts closest to the stamps and to the motion's steps.

    Minimises ``sum_k (x_k - c_k)^2 / jitter^2 + sum_k (step_k - (c_{k+1} -
    c_k))^2 / sigma_k^2`` over integers with ``c_{k+1} > c_k`` (Viterbi, each
    count within ``reach`` of its stamp's nearest).

    Parameters
    ----------
    x : ndarray of shape (n,)
        Stamps in periods.
    step : ndarray of shape (n - 1,)
        Counts of each step measured from the motion (any value where ``sigma`` is
        inf).
    sigma : ndarray of shape (n - 1,)
        Their standard deviations (inf: no information).
    jitter : float
        Standard deviation of the stamps, in periods.
    """
    n = x.size
    offsets = np.arange(-reach, reach + 1)
    base = np.round(x).astype(np.int64)
    cand = base[:, None] + offsets[None, :]  # (n, states)
    own = ((x[:, None] - cand) / jitter) ** 2
    known = np.isfinite(sigma)
    weight = np.where(known, 1.0 / np.where(known, sigma, 1.0) ** 2, 0.0)
    step = np.where(known, step, 0.0)
    cost = own[0].copy()
    back = np.empty((n, offsets.size), dtype=np.int64)
    for k in range(1, n):
        jump = cand[k][None, :] - cand[k - 1][:, None]  # (from, to)
        total = cost[:, None] + weight[k - 1] * (step[k - 1] - jump) ** 2
        total[jump < 1] = np.inf
        back[k] = np.argmin(total, axis=0)
        cost = total[back[k], np.arange(offsets.size)] + own[k]
    state = int(np.argmin(cost))
    c = np.empty(n, dtype=np.int64)
    for k in range(n - 1, -1, -1):
        c[k] = cand[k, state]
        state = back[k, state] if k else state
    return c


def cycle_from_motion(t, q, period=None, rounds=3):
    """Cycle counts from the motion itself, for stamps too jittery to count on.

    The stamps' periodogram gives the period and phase (their phases need only be
    weakly concentrated) and each stamp's nearest count (made increasing) a first
    guess; each step is then measured against the increment per cycle of the steps
    around it (their median: a few wrong counts do not move it) and the counts
    redone as with recorded velocities (:func:`_counts`), ``rounds`` times.

    Parameters
    ----------
    t : ndarray of shape (n,)
    q : ndarray of shape (n, n_dof)
        Positions (angles unwrapped).
    period : float, optional
    rounds : int, default=3

    Returns
    -------
    (counts, phase, period, trusted) or None
    """
    n = len(t)
    steps = np.diff(t)
    positive = steps[steps > 0]
    if n < _FIRST_ROWS or positive.size == 0:
        return None
    p = _stamps_period(t) if period is None else float(period)
    if p is None:
        return None
    fitted = _refine(t, p, period is None)
    if fitted is None:
        return None
    phase, p = fitted
    r = (t - phase) / p
    if np.abs(np.exp(2j * np.pi * r).mean()) < 4 / np.sqrt(n):
        return None
    c = np.round(r).astype(np.int64)
    ramp = np.arange(n)
    c = np.maximum.accumulate(c - ramp) + ramp  # strictly increasing
    dq = np.diff(q, axis=0)
    found = None
    for _ in range(rounds):
        found = _counts(t, q, _local_rate(dq, np.diff(c)), p, fit_period=False)
        if found is None:
            return None
        c = found[0]
    return found


def motion_scores(q, t, pieces):
    """Pooled GCV score per column of P-spline fits to ``q`` over ``t``.

    The GCV score estimates the variance of what the spline cannot explain: noise,
    plus the position error of wrong time stamps (velocity x stamp error).

    Parameters
    ----------
    q : ndarray of shape (n, n_cols)
    t : ndarray of shape (n,)
        Strictly increasing within each piece.
    pieces : list of slice
        Stretches fitted separately (segments between gaps).

    Returns
    -------
    ndarray of shape (n_cols,)
        Row-weighted mean GCV score (nan when no piece has 12 rows).
    """
    total = np.zeros(q.shape[1])
    rows = 0
    for sl in pieces:
        ts = t[sl]
        if len(ts) < 12:
            continue
        qs = q[sl]
        basis = _BandedBasis(ts)
        best = None
        for order in _PSPLINE_ORDERS:
            _, _, score = _BandedPSpline(ts, order, basis).coefficients(qs)
            best = score if best is None else np.minimum(best, score)
        total += len(ts) * best
        rows += len(ts)
    return total / rows if rows else np.full(q.shape[1], np.nan)
