"""Exact finishes of FISTA on small NumPy problems.

FISTA finds the support of an L1 problem long before its iterates converge on
nearly collinear columns, and may wander among supports for hundreds of
iterations before it settles. Two exact steps end such runs early: the minimiser
of a steady support and signs (one linear solve, :func:`_polish`), and an
active-set search from a rough iterate (:func:`_active_set`). Both are kept only
where the KKT conditions hold to the solver's tolerance (:func:`_kkt_distance`,
FISTA's own stopping criterion), so they change when a run stops, not what it
converges to. Both take a batch of problems (rows); one problem is a batch of one.
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
    return _kkt_signed(grad, lw, nn, w != 0, np.sign(w))


def _kkt_signed(grad, lw, nn, nz, signs):
    """:func:`_kkt_distance` given ``nz = w != 0`` and ``signs = np.sign(w)``."""
    at_zero = np.maximum(np.abs(grad) - lw, 0.0)
    if nn is not None:
        at_zero = np.where(nn, np.maximum(-grad - lw, 0.0), at_zero)
    return np.where(nz, np.abs(grad + lw * signs), at_zero)


def _active_set(gram, b, lw, nn, x, fmask, tol, max_steps=None):
    """Minimisers of ``0.5 x' G x - b' x + sum_k lw_k |x_k|`` by an active-set search,
    for each row (one problem is a batch of one).

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

    The rows search in lockstep, each with its own solves, points and stopping
    rules: apart from the solves (one LAPACK call per row) a step is some 60 NumPy
    calls for all the rows together, so a batch costs about as much as its
    longest search.

    Parameters
    ----------
    gram : ndarray of shape (m, m) or (R, m, m)
        One matrix shared by the rows, or one per row.
    b, lw, x : ndarray of shape (R, m)
        Right-hand sides, L1 weights (``lam`` included) and starting iterates, zero
        outside each row's coordinates.
    nn : ndarray of bool, shape (R, m), or None
        Coordinates constrained to be non-negative (within each row's coordinates).
    fmask : ndarray of shape (R, m)
        1 on each row's coordinates, 0 elsewhere.
    tol : float
    max_steps : int, optional
        Steps allowed to every row (default ``2 p + 10`` for a row of ``p``
        coordinates).

    Returns
    -------
    x : ndarray of shape (R, m)
    ok : ndarray of bool, shape (R,)
        Whether ``x`` meets the KKT conditions to ``tol`` (the criterion of
        :func:`fista`); ``False`` when a step fails to lower the objective, a block
        is singular or the steps run out: the caller then goes on iterating.
    dist : ndarray of shape (R,)
        The KKT distance of ``x``.
    """
    n_rows, m = x.shape
    shared = gram.ndim == 2
    mask = fmask > 0
    x = np.where(nn, np.maximum(x, 0.0), x) if nn is not None else x
    free = (lw == 0) & mask if nn is None else (lw == 0) & mask & ~nn
    steps = 2 * mask.sum(1) + 10 if max_steps is None else np.full(n_rows, max_steps)
    st = {  # the rows still searching, compacted as rows finish
        "x": x, "b": b, "lw": lw, "nn": nn, "mask": mask, "free": free,
        "pen": mask & ~free, "steps": steps, "g": gram, "live": np.arange(n_rows),
    }  # fmt: skip
    out_x, ok, out_dist = x.copy(), np.zeros(n_rows, dtype=bool), np.zeros(n_rows)
    gesv = get_lapack_funcs("gesv", (gram,))

    def objective(points):  # points of shape (rows, k, m)
        g, b_ = st["g"], st["b"]
        if shared:  # one matrix product (a stacked one is several times slower)
            pg = (points.reshape(-1, m) @ g).reshape(points.shape)
        else:
            pg = np.matmul(points, g)
        quad_lin = np.einsum("rki,rki->rk", points, 0.5 * pg - b_[:, None])
        return quad_lin + (np.abs(points) @ st["lw"][:, :, None])[:, :, 0]

    def retire(stop, good, dist):
        """Record the rows ``stop`` (``good``: KKT met) and drop them."""
        rows = st["live"][stop]
        out_x[rows], ok[rows], out_dist[rows] = st["x"][stop], good[stop], dist[stop]
        keep = ~stop
        for key, value in st.items():
            if value is not None and not (key == "g" and shared):
                st[key] = value[keep]
        return keep

    f = objective(x[:, None])[:, 0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for step in range(int(st["steps"].max(initial=0)) + 1):
            x, b, lw, nn, g = st["x"], st["b"], st["lw"], st["nn"], st["g"]
            grad = (x @ g if shared else np.einsum("ri,rij->rj", x, g)) - b
            nz = x != 0
            signs = np.sign(x)
            dist = np.where(st["mask"], _kkt_signed(grad, lw, nn, nz, signs), 0.0)
            worst = dist.max(1) if m else np.zeros(len(x))
            ended = worst <= tol
            stop = ended | (step >= st["steps"])  # met, or out of steps
            if stop.any():
                keep = retire(stop, ended, worst)
                if not keep.any():
                    break
                f, grad, nz, signs, dist, worst = (
                    v[keep] for v in (f, grad, nz, signs, dist, worst)
                )
                x, b, lw, nn, g = st["x"], st["b"], st["lw"], st["nn"], st["g"]
            n_live = len(x)
            rows = np.arange(n_live)
            on = nz | st["free"]
            grow = ~np.any(on & (dist > tol), axis=1)
            if grow.any():  # optimal on the active set: the worst violator joins
                gi = grow.nonzero()[0]
                i = np.where(on[gi] | ~st["mask"][gi], -1.0, dist[gi]).argmax(1)
                on[gi, i] = True
                joined = -np.sign(grad[gi, i])
                signs[gi, i] = (
                    joined if nn is None else np.where(nn[gi, i], 1.0, joined)
                )
            # The minimisers on the active sets, one LAPACK solve each (gesv
            # directly: np.linalg.solve's overhead dominated a step; a batched
            # solve of padded matrices costs as much).
            rhs = b - lw * signs
            target = np.zeros(x.shape)
            failed = np.zeros(n_live, dtype=bool)
            for r in rows:
                act = on[r].nonzero()[0]
                sub_gram = (g if shared else g[r]).take(act, 0).take(act, 1)
                *_, sub, info = gesv(sub_gram, rhs[r].take(act))
                if info != 0 or not math.isfinite(sub.sum()):  # singular
                    failed[r] = True
                else:
                    target[r, act] = sub
            d = target - x
            # The points where a coordinate of x reaches zero on the way to the
            # target, sorted, then the target (1.0); as far as a non-negative
            # coordinate may go.
            flips = np.sign(target) != signs
            cross = np.where(nz & flips, x / -d, np.inf)
            inner = (cross > 0) & (cross < 1)
            n_ts = inner.sum(1) + 1
            ts = np.ones((n_live, m + 1))
            ts[:, :m] = np.where(inner, cross, 1.0)
            ts.sort(axis=1)
            if nn is not None:
                limit = np.where(nn & (d < 0), x / -d, np.inf).min(1)
                below = (ts <= limit[:, None]) & (np.arange(m + 1) < n_ts[:, None])
                n_ts = np.where(limit > 0, below.sum(1), 0)
            failed |= n_ts == 0
            top = int(n_ts.max())
            if top:
                # The candidates, in order (segment points,
                # jump, clamped points), padded to the longest row's.
                tv = ts[:, :top, None]
                on_segment = x[:, None] + tv * d[:, None]
                passed = (cross[:, None] <= tv[:, :-1]) & st["pen"][:, None]
                points = np.concatenate(
                    (
                        np.where(cross[:, None] == tv, 0.0, on_segment),
                        np.where(st["pen"] & flips, 0.0, target)[:, None],
                        np.where(passed, 0.0, on_segment[:, :-1]),
                    ),
                    axis=1,
                )
                if nn is not None:
                    points = np.where(nn[:, None], np.maximum(points, 0.0), points)
                index = np.arange(2 * top)
                usable = (index < n_ts[:, None]) | (index == top)
                if CLAMP_POINTS:
                    clamped = (index > top) & (index < top + n_ts[:, None])
                    usable |= clamped & (n_ts[:, None] > 2)
                usable &= ~failed[:, None]
                values = np.where(usable, objective(points), np.inf)
                j = values.argmin(1)
                best = values[rows, j]
                failed |= ~(best < f)
                moved = ~failed
                st["x"] = np.where(moved[:, None], points[rows, j], x)
                f = np.where(moved, best, f)
            if failed.any():
                keep = retire(failed, np.zeros(n_live, dtype=bool), worst)
                f = f[keep]
                if not keep.any():
                    break
    return out_x, ok, out_dist
