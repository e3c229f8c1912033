"""Estimated states on an uneven clock, put on an even clock for the weak form.

:func:`to_even_clock` takes rows ``[q, q_dot, q_ddot]`` already estimated at their
time stamps (the output of :func:`~lagsindy.differentiation.derivatives`) and
evaluates, every ``dt`` inside each gap-free segment, the quintic Hermite
interpolant of those estimates (it matches ``q``, ``q_dot`` and ``q_ddot`` at every
sample, so between two samples it follows the smoothing spline to within
``h**6``). :meth:`lagsindy.LagrangianSINDy.fit` uses it when given time stamps
(``t=``): its weak form integrates over consecutive rows as if they were ``dt``
apart, which an uneven clock (jitter, dropped frames) breaks.

Measured (``benchmarks/results/clocks.md``): on a passive and a forced double
pendulum at 100 Hz nominal with 0-30 % jitter, 0-15 % dropped frames and two gaps
per record, the fit through this route gives the terms of the even-clock fit of the
same trajectories with coefficients within a fraction of a percent.
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Real

import numpy as np

from .clock import EDGE_SAMPLES
from .records import (
    _GAP_FACTOR,
    _GLITCH_FRACTION,
    _UNIFORM_RTOL,
    _segments,
)


@dataclass(frozen=True)
class EvenClock:
    """Rows on an even clock (see :func:`to_even_clock`).

    Attributes
    ----------
    X : ndarray of shape (n_rows, 3 * n_dof)
        ``[q, q_dot, q_ddot]`` every ``dt`` within each segment.
    tau : ndarray of shape (n_rows, ...) or None
        Forces, interpolated linearly.
    groups : ndarray of int of shape (n_rows,)
        Segment of each row (0, 1, ...; trajectories cut at their gaps).
    t : ndarray of shape (n_rows,)
        Time of each row.
    dt : float
        The step of the even clock.
    changed : bool
        False when the input already was on an even clock (rows returned as they
        were, only cut at gaps); True when rows were interpolated or left out.
    report : str
        One line saying what was done (empty when nothing was).
    """

    X: np.ndarray
    tau: np.ndarray | None
    groups: np.ndarray
    t: np.ndarray
    dt: float
    changed: bool
    report: str = ""


def to_even_clock(
    X, t, groups=None, tau=None, *, dt=None, gap_factor=_GAP_FACTOR
) -> EvenClock:
    """Put estimated states ``[q, q_dot, q_ddot]`` on an even clock, per segment.

    Rows repeating the previous row exactly (a dropped stale or duplicate row that
    :func:`~lagsindy.differentiation.derivatives` filled with the estimate of the row
    it repeats) and rows less than a quarter step after the previous one are left
    out; each trajectory is cut where a step exceeds ``gap_factor`` steps; a segment
    whose steps are all equal keeps its rows as they are; any other is evaluated
    every ``dt`` from its first sample to its last through the quintic Hermite
    interpolant of ``q``, ``q_dot`` and ``q_ddot`` (forces: linear interpolation).

    Parameters
    ----------
    X : array-like of shape (n_samples, 3 * n_dof)
        Rows ``[q..., q_dot..., q_ddot...]`` estimated at the times ``t``.
    t : array-like of shape (n_samples,)
        Time of each row, increasing within each trajectory (the cleaned clock
        ``clock.t`` of ``derivatives(..., return_clock=True)`` when the stamps were
        rebuilt).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (contiguous rows); ``None``: one trajectory.
    tau : array-like of shape (n_samples,) or (n_samples, n_tau), default=None
        Forces at the rows.
    dt : float, default=None
        Step of the even clock; ``None``: the frame step, the time the steps span
        (gaps left out) over the number of frames they hold (each step a whole
        number of median steps: dropped frames counted).
    gap_factor : float, default=5.0
        A step longer than ``gap_factor * dt`` cuts the trajectory there.

    Returns
    -------
    EvenClock

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import to_even_clock
    >>> t = np.sort(np.r_[0.0, np.random.default_rng(0).uniform(0, 4, 398), 4.0])
    >>> X = np.c_[np.sin(t), np.cos(t), -np.sin(t)]
    >>> out = to_even_clock(X, t, dt=0.01)
    >>> bool(np.max(np.abs(out.X[:, 0] - np.sin(out.t))) < 1e-8)
    True
    """
    X = np.asarray(X, dtype=np.float64)
    n = X.shape[0]
    if X.ndim != 2 or X.shape[1] % 3:
        raise ValueError(f"X must be (n_samples, 3 * n_dof), got shape {X.shape}")
    d = X.shape[1] // 3
    t = np.asarray(t, dtype=np.float64).ravel()
    if t.shape != (n,):
        raise ValueError(f"t must have one time per row of X ({n}), got {t.size}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t contains NaN or infinite values")
    if dt is not None and not (isinstance(dt, Real) and dt > 0):
        raise ValueError(f"dt must be a number > 0 or None, got {dt!r}")
    if not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1, got {gap_factor!r}")
    one = False
    if tau is not None:
        tau = np.asarray(tau, dtype=np.float64)
        one = tau.ndim == 1
        tau = tau.reshape(n, -1)
    trajectories = _segments(groups, n)
    # rows carried over from another row (same state) add nothing
    carried = np.zeros(n, dtype=bool)
    for _, sl in trajectories:
        same = np.all(X[sl][1:] == X[sl][:-1], axis=1)
        carried[sl.start + 1 : sl.stop] = same
    steps_all = []
    for _, sl in trajectories:
        idx = np.arange(sl.start, sl.stop)[~carried[sl]]
        steps = np.diff(t[idx])
        if np.any(steps < 0):
            k = int(idx[1:][steps < 0][0])
            raise ValueError(
                f"t goes back at row {k} ({t[k - 1]!r} -> {t[k]!r}): rows of one "
                "trajectory must be in time order; clean the clock first "
                "(lagsindy.differentiation.clean_clock, or derivatives(..., "
                "return_clock=True) and pass clock.t)"
            )
        steps_all.append(steps[steps > 0])
    positive = np.concatenate(steps_all) if steps_all else np.zeros(0)
    if positive.size == 0:
        raise ValueError("no trajectory has two distinct time stamps")
    if dt is None:
        # the frame step: the time the steps span (gaps left out) over the frames
        # they hold, each step counted as a whole number of median steps (dropped
        # frames), at least one
        median = float(np.median(positive))
        used = positive[positive <= gap_factor * median]
        frames = np.maximum(1.0, np.round(used / median))
        step = float(used.sum() / frames.sum())
    else:
        step = float(dt)
    # segments: kept rows, cut at gaps; near-duplicate stamps left out
    pieces = []
    dropped = int(carried.sum())
    for _, sl in trajectories:
        idx = np.arange(sl.start, sl.stop)[~carried[sl]]
        keep = np.ones(idx.size, dtype=bool)
        last = t[idx[0]] if idx.size else 0.0
        for j in range(1, idx.size):
            if t[idx[j]] - last < _GLITCH_FRACTION * step:
                keep[j] = False
            else:
                last = t[idx[j]]
        dropped += int((~keep).sum())
        idx = idx[keep]
        cut = np.flatnonzero(np.diff(t[idx]) > gap_factor * step) + 1
        pieces.extend(p for p in np.split(idx, cut) if p.size)
    parts = {"X": [], "tau": [], "t": [], "g": []}
    interpolated = 0
    for k, idx in enumerate(pieces):
        ts = t[idx]
        steps = np.diff(ts)
        if idx.size < 2 or np.max(np.abs(steps - step)) <= _UNIFORM_RTOL * step:
            grid, Xg = ts, X[idx]
            tg = None if tau is None else tau[idx]
        else:
            interpolated += 1
            m = int(np.floor((ts[-1] - ts[0]) / step + 1e-9))
            grid = ts[0] + step * np.arange(m + 1)
            Xg = _hermite5(X[idx], ts, grid, d)
            tg = None
            if tau is not None:
                tg = np.stack(
                    [np.interp(grid, ts, tau[idx, j]) for j in range(tau.shape[1])],
                    axis=1,
                )
        parts["X"].append(Xg)
        parts["t"].append(grid)
        parts["g"].append(np.full(grid.size, k))
        if tau is not None:
            parts["tau"].append(tg)
    X_out = np.concatenate(parts["X"])
    tau_out = None
    if tau is not None:
        tau_out = np.concatenate(parts["tau"])
        if one:
            tau_out = tau_out[:, 0]
    changed = bool(interpolated or dropped)
    parts_report = []
    if interpolated:
        parts_report.append(
            f"{interpolated} of {len(pieces)} segment(s) put on an even clock of dt "
            f"= {step:.4g} s ({n} rows -> {X_out.shape[0]}; quintic Hermite "
            "interpolation of the estimated q, q_dot, q_ddot)"
        )
    if dropped:
        parts_report.append(f"{dropped} repeated or near-duplicate row(s) left out")
    report = ("uneven clock: " + "; ".join(parts_report)) if changed else ""
    return EvenClock(
        X=X_out,
        tau=tau_out,
        groups=np.concatenate(parts["g"]),
        t=np.concatenate(parts["t"]),
        dt=step,
        changed=changed,
        report=report,
    )


def _hermite5(X, ts, grid, d):
    """The quintic Hermite interpolant of ``[q, qd, qdd]`` at ``ts``, and its first
    two derivatives, at ``grid`` (inside ``[ts[0], ts[-1]]``)."""
    q, v, a = X[:, :d], X[:, d : 2 * d], X[:, 2 * d : 3 * d]
    i = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, ts.size - 2)
    h = (ts[i + 1] - ts[i])[:, None]
    s = ((grid - ts[i])[:, None]) / h
    s2, s3 = s * s, s * s * s
    s4, s5 = s3 * s, s3 * s2
    # basis (value, first and second derivative in s)
    h0 = (1 - 10 * s3 + 15 * s4 - 6 * s5, -30 * s2 + 60 * s3 - 30 * s4,
          -60 * s + 180 * s2 - 120 * s3)  # fmt: skip
    h1 = (s - 6 * s3 + 8 * s4 - 3 * s5, 1 - 18 * s2 + 32 * s3 - 15 * s4,
          -36 * s + 96 * s2 - 60 * s3)  # fmt: skip
    h2 = (0.5 * (s2 - 3 * s3 + 3 * s4 - s5), 0.5 * (2 * s - 9 * s2 + 12 * s3 - 5 * s4),
          0.5 * (2 - 18 * s + 36 * s2 - 20 * s3))  # fmt: skip
    h3 = (0.5 * (s3 - 2 * s4 + s5), 0.5 * (3 * s2 - 8 * s3 + 5 * s4),
          0.5 * (6 * s - 24 * s2 + 20 * s3))  # fmt: skip
    h4 = (-4 * s3 + 7 * s4 - 3 * s5, -12 * s2 + 28 * s3 - 15 * s4,
          -24 * s + 84 * s2 - 60 * s3)  # fmt: skip
    h5 = (10 * s3 - 15 * s4 + 6 * s5, 30 * s2 - 60 * s3 + 30 * s4,
          60 * s - 180 * s2 + 120 * s3)  # fmt: skip
    out = []
    for k in range(3):
        val = (
            h0[k] * q[i] + h * h1[k] * v[i] + h * h * h2[k] * a[i]
            + h * h * h3[k] * a[i + 1] + h * h4[k] * v[i + 1] + h5[k] * q[i + 1]
        )  # fmt: skip
        out.append(val / h**k)
    return np.concatenate(out, axis=1)


def edge_rows(
    t,
    groups=None,
    *,
    edge_samples: int = EDGE_SAMPLES,
    min_samples: int = 7,
    gap_factor: float = _GAP_FACTOR,
) -> np.ndarray:
    """Rows near the end of a gap-free segment, whose derivative estimates are poor.

    The rows of each trajectory are cut where a step exceeds ``gap_factor`` times the
    trajectory's median step (as :func:`clean_clock` and :func:`to_even_clock` cut
    them); the first and last ``edge_samples`` rows of every segment, and every row
    of a segment of fewer than ``min_samples`` rows, are flagged. It is
    :attr:`CleanedClock.edge <lagsindy.differentiation.CleanedClock>` for time
    stamps given as an array (``LagrangianSINDy.fit(X, tau, t=t)``).

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Time of each row, increasing within each trajectory.
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (contiguous rows); ``None``: one trajectory.
    edge_samples : int, default=3
        Rows flagged at each end of a segment.
    min_samples : int, default=7
        Every row of a shorter segment is flagged.
    gap_factor : float, default=5.0

    Returns
    -------
    ndarray of bool of shape (n_samples,)

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import edge_rows
    >>> t = np.r_[np.arange(10), 20 + np.arange(10)] * 0.01  # a gap after row 9
    >>> np.flatnonzero(~edge_rows(t, edge_samples=2)).tolist()
    [2, 3, 4, 5, 6, 7, 12, 13, 14, 15, 16, 17]
    """
    t = np.asarray(t, dtype=np.float64).ravel()
    n = t.size
    if not (isinstance(edge_samples, (int, np.integer)) and edge_samples >= 0):
        raise ValueError(f"edge_samples must be an integer >= 0, got {edge_samples!r}")
    edge = np.zeros(n, dtype=bool)
    for _, sl in _segments(groups, n):
        steps = np.diff(t[sl])
        moves = steps[steps > 0]
        cut = []
        if moves.size:
            cut = np.flatnonzero(steps > gap_factor * np.median(moves)) + 1
        bounds = np.r_[0, cut, sl.stop - sl.start] + sl.start
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < min_samples:
                edge[a:b] = True
            else:
                edge[a : a + edge_samples] = True
                edge[b - edge_samples : b] = True
    return edge
