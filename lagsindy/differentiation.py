"""Derivative estimation from sampled positions q(t), per trajectory."""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter

METHODS = ("finite_difference", "savgol")


def _segments(groups, n):
    if groups is None:
        return [np.arange(n)]
    groups = np.asarray(groups)
    _, start = np.unique(groups, return_index=True)
    return [np.flatnonzero(groups == groups[s]) for s in np.sort(start)]


def derivatives(q, t, *, groups=None, method="savgol", window=11, polyorder=4):
    """Estimate ``[q, q_dot, q_ddot]`` from positions, trajectory by trajectory.

    Parameters
    ----------
    q : array-like of shape (n_samples, n_dof)
    t : array-like of shape (n_samples,)
        Sample times (uniform within a trajectory).
    groups : array-like of shape (n_samples,), optional
        Trajectory of each row; derivatives never cross trajectory boundaries.
    method : {"finite_difference", "savgol"}, default="savgol"
    window, polyorder : int
        Savitzky-Golay window length and polynomial order.

    Returns
    -------
    ndarray of shape (n_samples, 3 * n_dof)
    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[:, None]
    t = np.asarray(t, dtype=float)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    out = np.empty((q.shape[0], 3 * q.shape[1]))
    for idx in _segments(groups, q.shape[0]):
        qs, ts = q[idx], t[idx]
        dt = float(np.median(np.diff(ts)))
        if method == "finite_difference":
            q0 = qs
            q1 = np.gradient(qs, ts, axis=0, edge_order=2)
            q2 = np.gradient(q1, ts, axis=0, edge_order=2)
        else:
            w = min(window, len(idx) - (1 - len(idx) % 2))
            q0 = savgol_filter(qs, w, polyorder, axis=0)
            q1 = savgol_filter(qs, w, polyorder, deriv=1, delta=dt, axis=0)
            q2 = savgol_filter(qs, w, polyorder, deriv=2, delta=dt, axis=0)
        out[idx] = np.concatenate([q0, q1, q2], axis=1)
    return out
