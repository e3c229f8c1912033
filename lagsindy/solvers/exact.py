"""Exact finishes of FISTA on small NumPy problems.

FISTA finds the support of an L1 problem long before its iterates converge on
nearly collinear columns, and may wander among supports for hundreds of
iterations before it settles. Two exact steps end such runs early: the minimiser
of a steady support and signs (one linear solve, :func:`_polish`), and an
active-set search from a rough iterate (:func:`_active_set`). Both are kept only
where the KKT conditions hold to the solver's tolerance (:func:`_kkt_distance`,
FISTA's own stopping criterion), so they change when a run stops, not what it
converges to.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import get_lapack_funcs

# The active-set search also tries, at each point where a coordinate of the
# iterate reaches zero, the point with every coordinate that passed zero on the
# way set to zero (several leave the active set in one step).
CLAMP_POINTS = True


def _polish(gram, b, lw, nn, w, fmask, tol):
    """Exact minimisers on the iterates' supports and signs, where they are optimal.

    For ``0.5 w' G w - b' w + sum_k lw_k |w_k|`` with the support ``S`` and signs
    ``s`` of ``w`` known, the minimiser solves ``G_SS x_S = b_S - lw_S s_S``
    (``x`` zero off ``S``). Where ``x`` keeps the signs ``s`` and satisfies the
    optimality (KKT) conditions to ``tol``, it is the problem's solution: FISTA
    identifies the support long before its iterates converge on it (slowly, on
    nearly collinear columns), so this ends the iterations early with the exact
    minimiser instead of one within ``tol``.

    Parameters
    ----------
    gram : ndarray of shape (p, p) or (R, p, p)
    b, lw, w : ndarray of shape (R, p)
        Right-hand sides, L1 weights (``lam`` included) and iterates (zero
        outside each problem's coordinates).
    nn : ndarray of bool, shape (R, p), or None
        Coordinates constrained to be non-negative.
    fmask : ndarray of shape (R, p)
        1 on each problem's coordinates, 0 elsewhere.
    tol : float

    Returns
    -------
    x : ndarray of shape (R, p)
    optimal : ndarray of bool, shape (R,)
    dist : ndarray of shape (R,)
        The KKT distance of ``x`` (as :func:`fista`'s stopping criterion).
    """
    on = w != 0
    sgn = np.sign(w)
    p = w.shape[1]
    both = on[:, :, None] & on[:, None, :]
    mat = np.where(both, gram, 0.0) + np.eye(p) * (~on)[:, :, None]
    rhs = np.where(on, b - lw * sgn, 0.0)
    try:
        x = np.linalg.solve(mat, rhs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # a singular block: keep iterating
        return w, np.zeros(w.shape[0], dtype=bool), np.full(w.shape[0], np.inf)
    grad = (x @ gram if gram.ndim == 2 else np.matmul(gram, x[:, :, None])[:, :, 0]) - b
    dist = np.where(fmask > 0, _kkt_distance(x, grad, lw, nn), 0.0).max(1)
    optimal = (
        np.all(np.where(on, np.sign(x) == sgn, True), axis=1)
        & np.all(np.isfinite(x), axis=1)
        & (dist <= tol)
    )
    return x, optimal, dist


def _kkt_distance(w, grad, lw, nn):
    """Per row: distance of ``-grad`` to the subdifferential of the (weighted) L1
    penalty at ``w`` (rows of ``w``; ``lw`` zero outside a row's coordinates, where
    ``grad`` is not used)."""
    at_zero = np.maximum(np.abs(grad) - lw, 0.0)
    if nn is not None:
        at_zero = np.where(nn, np.maximum(-grad - lw, 0.0), at_zero)
    return np.where(w != 0, np.abs(grad + lw * np.sign(w)), at_zero)


def _active_set(gram, b, lw, nn, x, tol, max_steps=None):
    """Minimiser of ``0.5 x' G x - b' x + sum_k lw_k |x_k|`` by an active-set search.

    The feature-sign search of Lee et al. (2007), started from an iterate ``x`` of
    :func:`fista` (coordinates in ``nn`` kept non-negative): on the active set
    (the non-zero coordinates, and those without penalty) with the signs of
    ``x``, the minimiser is one linear solve; the step to it stops at the best
    point where a coordinate changes sign (the objective is evaluated at each),
    which then leaves the set, or jumps to the minimiser with every coordinate
    whose sign it flips set to zero, if that is lower (from a dense iterate many
    coordinates leave in one step); with :data:`CLAMP_POINTS`, also the points
    where a coordinate reaches zero with every coordinate that passed zero
    before it set to zero (on nearly collinear columns about half the steps from
    a dense start). When the active coordinates are optimal, the zero
    coordinate that violates the optimality conditions most joins with the sign
    that lowers the objective. Every step lowers the objective, so no support is
    visited twice. Where FISTA wanders among supports on nearly collinear columns
    (hundreds of iterations to settle), this needs a few solves from a rough
    iterate.

    Returns
    -------
    x : ndarray
    ok : bool
        Whether ``x`` meets the KKT conditions to ``tol`` (the criterion of
        :func:`fista`); ``False`` when a step fails to lower the objective, a block
        is singular or ``max_steps`` (default ``2 p + 10``) run out: the caller
        then goes on iterating.
    dist : float
        The KKT distance of ``x``.
    """
    p = x.size
    max_steps = 2 * p + 10 if max_steps is None else max_steps
    x = x if nn is None else np.where(nn, np.maximum(x, 0.0), x)
    free = lw == 0 if nn is None else (lw == 0) & ~nn
    penalised = ~free

    gesv = get_lapack_funcs("gesv", (gram,))

    def objective(points):
        quad = np.einsum("ki,ki->k", points, points @ gram)
        return 0.5 * quad - points @ b + np.abs(points) @ lw

    f = objective(x[None])[0]
    # A step is some 45 small NumPy calls whose overhead is its cost: method calls
    # and whole-vector products rather than index-then-compute.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(max_steps):
            grad = gram @ x - b
            nz = x != 0
            signs = np.sign(x)
            dist = _kkt_signed(grad, lw, nn, nz, signs)
            worst = dist.max() if p else 0.0
            if worst <= tol:
                return x, True, float(worst)
            on = nz | free
            if not (dist[on] > tol).any():  # optimal on the active set: grow it
                i = int(np.where(on, -1.0, dist).argmax())
                on[i] = True
                signs[i] = 1.0 if nn is not None and nn[i] else -np.sign(grad[i])
            act = on.nonzero()[0]
            # LAPACK's gesv directly (as np.linalg.solve, without its overhead,
            # which dominated a step)
            sub_gram = gram.take(act, 0).take(act, 1)
            *_, sub, info = gesv(sub_gram, (b - lw * signs)[act])
            if info != 0 or not math.isfinite(sub.sum()):  # singular: keep iterating
                return x, False, float(worst)
            target = np.zeros(p, dtype=x.dtype)
            target[act] = sub
            d = target - x
            # Points where a coordinate of x reaches zero on the way to the target.
            flips = np.sign(target) != signs
            cross = np.where(nz & flips, x / -d, np.inf)
            ts = np.sort(cross[(cross > 0) & (cross < 1)])
            ts = np.concatenate((ts, [1.0]))
            if nn is not None:  # a non-negative coordinate may not pass zero
                limit = float(np.where(nn & (d < 0), x / -d, np.inf).min())
                ts = ts[ts <= limit] if limit > 0 else ts[:0]
            if ts.size == 0:
                return x, False, float(worst)
            n_ts = ts.size
            # the points on the segment, the coordinate that reaches zero at each
            # set to zero; the jump to the target with every coordinate whose sign
            # it flips set to zero (many leave at once when the iterate is dense);
            # and the segment's points before the target with every coordinate
            # that passed zero on the way set to zero (CLAMP_POINTS)
            on_segment = x + ts[:, None] * d
            clamped = CLAMP_POINTS and n_ts > 2
            points = np.empty((2 * n_ts if clamped else n_ts + 1, p), dtype=x.dtype)
            points[:n_ts] = on_segment
            points[:n_ts][cross == ts[:, None]] = 0.0
            points[n_ts] = np.where(penalised & flips, 0.0, target)
            if clamped:
                passed = (cross <= ts[:-1, None]) & penalised
                points[n_ts + 1 :] = np.where(passed, 0.0, on_segment[:-1])
            if nn is not None:
                points = np.where(nn, np.maximum(points, 0.0), points)
            values = objective(points)
            j = int(values.argmin())
            if not values[j] < f:
                return x, False, float(worst)
            x, f = points[j], values[j]
    dist = _kkt_distance(x, gram @ x - b, lw, nn)
    worst = float(dist.max()) if p else 0.0
    return x, worst <= tol, worst


def _kkt_signed(grad, lw, nn, nz, signs):
    """:func:`_kkt_distance` given ``nz = w != 0`` and ``signs = np.sign(w)``."""
    at_zero = np.maximum(np.abs(grad) - lw, 0.0)
    if nn is not None:
        at_zero = np.where(nn, np.maximum(-grad - lw, 0.0), at_zero)
    return np.where(nz, np.abs(grad + lw * signs), at_zero)
