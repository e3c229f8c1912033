"""Uneven records onto an even clock, through the P-spline.

:func:`resample` fits the GCV P-spline of :func:`~lagsindy.differentiation.derivatives`
to each segment of a cleaned clock (:func:`~lagsindy.differentiation.clean_clock`)
and evaluates it, with its first two derivatives, on an evenly spaced grid inside the
segment; forces are interpolated linearly onto the same grid. The result is a record
every fit that assumes evenly spaced rows (the weak form of
:class:`~lagsindy.LagrangianSINDy` included) can take as it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Real

import numpy as np

from .clock import CleanedClock, clean_clock
from .core import _MIN_SAMPLES, _blas_controller
from .pspline import _pspline_curve
from .records import _angle_mask

_MIN_ROWS = _MIN_SAMPLES["pspline"]


@dataclass(frozen=True)
class Resampled:
    """A record on an even clock (see :func:`resample`).

    Attributes
    ----------
    X : ndarray of shape (n_rows, 3 * n_dof)
        ``[q, q_dot, q_ddot]`` on the grid (angles unwrapped).
    t : ndarray of shape (n_rows,)
        Grid times, ``dt`` apart within each segment.
    groups : ndarray of int of shape (n_rows,)
        Segment of each grid row (the segments of the cleaned clock).
    tau : ndarray of shape (n_rows, n_tau) or None
        Forces interpolated linearly onto the grid.
    dt : float
        The grid's step.
    clock : CleanedClock
        The cleaned clock of the input rows.
    """

    X: np.ndarray
    t: np.ndarray
    groups: np.ndarray
    tau: np.ndarray | None
    dt: float
    clock: CleanedClock


def resample(
    q,
    t,
    dt: float | None = None,
    *,
    groups=None,
    tau=None,
    angles=None,
    clean=True,
    smoothing: float | None = None,
) -> Resampled:
    """Positions on an uneven clock to ``[q, q_dot, q_ddot]`` on an even clock.

    Each segment of the cleaned clock (gaps cut, stale and duplicate rows dropped,
    a jittery clock rebuilt on its cycle) gets the P-spline of
    :func:`~lagsindy.differentiation.derivatives` (quintic, smoothing by GCV per
    coordinate), evaluated every ``dt`` from the segment's first sample to its last.
    Segments of fewer than 7 samples are left out.

    Parameters
    ----------
    q : array-like of shape (n_samples, n_dof) or (n_samples,)
        Measured positions.
    t : array-like of shape (n_samples,)
        Time stamps.
    dt : float, default=None
        Step of the even grid; ``None``: the clock's base period (the rebuilt
        cycle, or the median step of the kept rows).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels.
    tau : array-like of shape (n_samples,) or (n_samples, n_tau), default=None
        Forces (inputs) at the rows, interpolated linearly onto the grid.
    angles : list of int, boolean mask or "all", default=None
        Angular coordinates, unwrapped per trajectory before fitting.
    clean : True or CleanedClock, default=True
        Clean the clock with :func:`clean_clock` (one warning per defect), or the
        cleaned clock to use (e.g. ``clean_clock(t, q, velocities=...)``).
    smoothing : float, default=None
        Fixed P-spline smoothing instead of GCV.

    Returns
    -------
    Resampled

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import resample
    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(400) * 0.01 + rng.uniform(-0.003, 0.003, 400)  # +-30 % jitter
    >>> out = resample(np.sin(2 * t), t, dt=0.01)
    >>> bool(np.allclose(np.diff(out.t), 0.01))
    True
    >>> inner = slice(5, -5)
    >>> bool(np.max(np.abs(out.X[inner, 2] + 4 * np.sin(2 * out.t[inner]))) < 1e-3)
    True
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1:
        q = q[:, None]
    n, n_dof = q.shape
    if dt is not None and not (isinstance(dt, Real) and dt > 0):
        raise ValueError(f"dt must be a number > 0 or None, got {dt!r}")
    if tau is not None:
        tau = np.asarray(tau, dtype=np.float64)
        one = tau.ndim == 1
        tau = tau.reshape(n, -1)
    if isinstance(clean, CleanedClock):
        clock = clean
    elif clean is True:
        clock = clean_clock(t, q, groups, angles=angles, warn=True)
    else:
        raise ValueError(f"clean must be True or a CleanedClock, got {clean!r}")
    mask = _angle_mask(angles, n_dof)
    rows = np.flatnonzero(clock.keep)
    labels = clock.groups[rows]
    if dt is None:
        dt = _base_period(clock, rows, labels)
    bounds = np.r_[0, np.flatnonzero(np.diff(labels)) + 1, rows.size]
    parts_X, parts_t, parts_g, parts_tau = [], [], [], []
    with _blas_controller().limit(limits=1, user_api="blas"):
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < _MIN_ROWS:
                continue  # too short for the P-spline (reported by the cleaning)
            idx = rows[a:b]
            ts = clock.t[idx]
            qs = q[idx].copy()
            if mask.any():
                qs[:, mask] = np.unwrap(qs[:, mask], axis=0)
            steps = int(np.floor((ts[-1] - ts[0]) / dt + 1e-9))
            grid = ts[0] + dt * np.arange(steps + 1)
            curve = _pspline_curve(qs, ts, smoothing)
            parts_X.append(
                np.concatenate([curve(grid), curve(grid, 1), curve(grid, 2)], axis=1)
            )
            parts_t.append(grid)
            parts_g.append(np.full(grid.size, int(labels[a])))
            if tau is not None:
                cols = [np.interp(grid, ts, tau[idx, j]) for j in range(tau.shape[1])]
                parts_tau.append(np.stack(cols, axis=1))
    X = np.concatenate(parts_X) if parts_X else np.zeros((0, 3 * n_dof))
    tau_out = None
    if tau is not None:
        tau_out = (
            np.concatenate(parts_tau) if parts_tau else np.zeros((0, tau.shape[1]))
        )
        if one:
            tau_out = tau_out[:, 0]
    return Resampled(
        X=X,
        t=np.concatenate(parts_t) if parts_t else np.zeros(0),
        groups=np.concatenate(parts_g) if parts_g else np.zeros(0, dtype=int),
        tau=tau_out,
        dt=float(dt),
        clock=clock,
    )


def _base_period(clock, rows, labels) -> float:
    if clock.period is not None:
        return float(clock.period)
    same = np.diff(labels) == 0
    steps = np.diff(clock.t[rows])[same]
    if steps.size == 0:
        raise ValueError("no segment has two samples: nothing to resample")
    return float(np.median(steps))
