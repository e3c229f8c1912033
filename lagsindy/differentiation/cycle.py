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
    (counts, phase, period, concentration) or None
        ``counts`` (int, non-decreasing) with ``t ~ phase + counts * period``.
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
    # phase on the first rows, then least squares over a doubling number of rows
    z = np.exp(2j * np.pi * (first - first[0]) / p).mean()
    phase = first[0] + p * (np.angle(z) / (2 * np.pi))
    m = len(first)
    while True:
        c = np.round((t[:m] - phase) / p).astype(np.int64)
        if period is None and np.ptp(c) > 0:
            phase, p = _line(t[:m], c)
        else:
            phase = float(np.mean(t[:m] - c * p))
        if not (math.isfinite(p) and p > 0):
            return None
        if m == n:
            break
        m = min(n, 2 * m)
    c = np.round((t - phase) / p).astype(np.int64)
    r = (t - phase) / p - c
    concentration = float(np.abs(np.exp(2j * np.pi * r).mean()))
    ambiguous = float(np.mean(np.abs(r) > _AMBIGUOUS))
    if concentration < MIN_CONCENTRATION or ambiguous > MAX_AMBIGUOUS:
        return None
    if np.any(np.diff(c) < 0):
        return None
    return c - c[0], phase + c[0] * p, p, concentration


def cycle_from_velocities(t, q, v, period=None):
    """Cycle counts from recorded velocities: increments / (velocity x period).

    Each step's count is ``dq . vbar / (|vbar|^2 period)`` rounded, where it sits
    within ``_COUNT_TOL`` of an integer and the step moves enough; elsewhere (rest,
    turning points) the stamps' step in periods, rounded.

    Returns
    -------
    (counts, phase, period, trusted) or None
        ``trusted``: fraction of the steps counted from the motion.
    """
    n = len(t)
    if n < 16:
        return None
    dq = np.diff(q, axis=0)
    vbar = 0.5 * (v[1:] + v[:-1])
    speed2 = np.sum(vbar * vbar, axis=1)
    move = np.sqrt(np.sum(dq * dq, axis=1))
    moving = (speed2 > 0) & (move >= _MIN_SPEED * np.median(move))
    if moving.sum() < 8:
        return None
    tau = np.zeros(n - 1)
    tau[moving] = np.sum(dq[moving] * vbar[moving], axis=1) / speed2[moving]
    if period is None:
        base = tau[moving & (tau > 0)]
        if base.size < 8:
            return None
        base = base[base < 1.5 * np.median(base)]  # single steps
        p = float(np.median(base))
    else:
        p = float(period)
    if not p > 0:
        return None
    counts = tau / p
    nearest = np.round(counts)
    trusted = moving & (np.abs(counts - nearest) <= _COUNT_TOL) & (nearest >= 0)
    if trusted.mean() < 0.5:
        return None
    from_stamps = np.maximum(np.round(np.diff(t) / p), 0)
    steps = np.where(trusted, nearest, from_stamps).astype(np.int64)
    c = np.r_[0, np.cumsum(steps)]
    phase, fitted = _line(t, c) if np.ptp(c) > 0 else (t[0], p)
    if period is None and math.isfinite(fitted) and abs(fitted / p - 1) < 0.05:
        p = fitted  # the stamps' units (a logging clock may run slightly off)
    phase = float(np.mean(t - c * p))
    return c, phase, p, float(trusted.mean())


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
