"""Finite differences, Savitzky-Golay and scipy's cubic smoothing spline.

The simple estimators behind ``method="finite_difference"``, ``"savgol"`` and
``"spline"`` of :func:`lagsindy.differentiation.derivatives`, each applied to one
trajectory (segment) at a time.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.signal import savgol_filter


# ----------------------------------------------------------------- finite differences
def _fd_weights(offsets: np.ndarray, order: int) -> np.ndarray:
    """Finite-difference weights for the ``order``-th derivative at offset 0.

    ``offsets`` has shape (m, k): the k stencil nodes of m evaluation points, relative
    to the point. The weights solve the Taylor (Vandermonde) conditions
    ``sum_j w_j d_j**p / p! = [p == order]`` for ``p < k``.
    """
    m, k = offsets.shape
    scale = np.max(np.abs(offsets), axis=1, keepdims=True)
    d = offsets / scale
    powers = np.arange(k)
    A = d[:, None, :] ** powers[None, :, None]  # (m, p, j)
    A = A / np.array([math.factorial(p) for p in powers])[None, :, None]
    rhs = np.zeros((m, k, 1))
    rhs[:, order, 0] = 1.0
    w = np.linalg.solve(A, rhs)[..., 0]
    return w / scale**order


def _finite_difference(q: np.ndarray, t: np.ndarray):
    """Second-order finite differences on possibly non-uniform time stamps.

    Interior points: three-point central stencils (i-1, i, i+1) for both derivatives
    (second order for the first derivative on any grid; second order for the second
    derivative on a uniform or smoothly varying grid). End points: one-sided stencils,
    three points for the first derivative and four for the second (second order).
    """
    n = len(t)
    idx = np.arange(n)
    d1 = np.empty_like(q)
    d2 = np.empty_like(q)
    # first derivative: 3-point stencils, centred inside, one-sided at the ends
    start = np.clip(idx - 1, 0, n - 3)
    nodes = start[:, None] + np.arange(3)[None, :]
    w1 = _fd_weights(t[nodes] - t[:, None], 1)
    d1[:] = np.einsum("ij,ijk->ik", w1, q[nodes])
    # second derivative: 3-point centred inside, 4-point one-sided at the ends
    inner = idx[1:-1]
    nodes = inner[:, None] + np.arange(-1, 2)[None, :]
    w2 = _fd_weights(t[nodes] - t[inner, None], 2)
    d2[1:-1] = np.einsum("ij,ijk->ik", w2, q[nodes])
    k = min(4, n)
    for i, nodes in ((0, np.arange(k)), (n - 1, np.arange(n - k, n))):
        w = _fd_weights((t[nodes] - t[i])[None, :], 2)[0]
        d2[i] = w @ q[nodes]
    return q, d1, d2


# ----------------------------------------------------------------- Savitzky-Golay
def _local_polynomial(q: np.ndarray, t: np.ndarray, window: int, polyorder: int):
    """Savitzky-Golay on arbitrary time stamps (``polyorder >= 2``).

    Each sample gets the polynomial of degree ``polyorder`` fitted to the ``window``
    samples centred on it (shifted inwards at the ends, as ``savgol_filter``'s
    ``mode="interp"`` does); value, slope and curvature at the sample's own time are
    returned. On a uniform grid this equals ``scipy.signal.savgol_filter``.
    """
    n = len(t)
    half = window // 2
    start = np.clip(np.arange(n) - half, 0, n - window)
    nodes = start[:, None] + np.arange(window)[None, :]
    d = t[nodes] - t[:, None]
    scale = np.max(np.abs(d), axis=1, keepdims=True)
    V = (d / scale)[..., None] ** np.arange(polyorder + 1)  # (n, window, p+1)
    coef = np.linalg.pinv(V) @ q[nodes]  # (n, p+1, n_cols)
    return coef[:, 0], coef[:, 1] / scale, 2.0 * coef[:, 2] / scale**2


def _savgol(q, t, window, polyorder, uniform):
    if uniform:
        dt = (t[-1] - t[0]) / (len(t) - 1)
        kw = dict(window_length=window, polyorder=polyorder, axis=0, delta=dt)
        return (
            savgol_filter(q, **kw),
            savgol_filter(q, deriv=1, **kw),
            savgol_filter(q, deriv=2, **kw),
        )
    return _local_polynomial(q, t, window, polyorder)


# ----------------------------------------------------------------- cubic spline
def _cubic_spline(q, t, lam):
    """scipy's cubic smoothing spline, column by column (GCV when ``lam`` is None)."""
    q0 = np.empty_like(q)
    q1 = np.empty_like(q)
    q2 = np.empty_like(q)
    for j in range(q.shape[1]):
        spl = make_smoothing_spline(t, q[:, j], lam=lam)
        q0[:, j] = spl(t)
        q1[:, j] = spl(t, nu=1)
        q2[:, j] = spl(t, nu=2)
    return q0, q1, q2


def _check_savgol_params(window, polyorder):
    if not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3, got {window!r}")
    if not isinstance(polyorder, (int, np.integer)) or polyorder < 2:
        raise ValueError(
            f"polyorder must be an integer >= 2 (q_ddot needs a quadratic), got "
            f"{polyorder!r}"
        )
    if polyorder >= window:
        raise ValueError(
            f"polyorder must be less than window, got polyorder={polyorder}, "
            f"window={window}"
        )
