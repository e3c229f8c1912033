"""FISTA on many Gram problems at once (the bootstrap's resamples), in lockstep.

:func:`batched_fista` runs the iterations of :func:`~lagsindy.solvers.fista` (the
NumPy loop: momentum, adaptive restart, objective and KKT checks every
``check_every`` iterations) on ``R`` quadratic problems of the same size stacked in
arrays, so one iteration is one batched matrix product instead of ``R`` Python-level
loops. Each problem keeps its own step, momentum counter, support (a mask: the
coordinates outside it stay zero, which is the restricted problem) and stopping
iteration, so each follows the sequence of iterates its own ``fista`` call would,
up to the rounding of the batched product, including ``fista``'s divergence guard
(a step halved where the objective rises).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BatchedResult", "batched_fista"]


@dataclass
class BatchedResult:
    """Outcome of :func:`batched_fista` (one row per problem).

    Attributes
    ----------
    coef : ndarray of shape (R, p)
        Zero outside each problem's support.
    n_iter : ndarray of int, shape (R,)
    converged : ndarray of bool, shape (R,)
    flagged : ndarray of bool, shape (R,)
        Problems that ``fista`` would give up on (it raises): their ``coef`` is not
        a solution.
    """

    coef: np.ndarray
    n_iter: np.ndarray
    converged: np.ndarray
    flagged: np.ndarray


def _value(gram, rhs, const, w):
    return 0.5 * np.einsum("ri,ri->r", w, np.matmul(gram, w[:, :, None])[:, :, 0]) - (
        np.einsum("ri,ri->r", rhs, w) - 0.5 * const
    )


def batched_fista(
    gram,
    rhs,
    const,
    mask,
    lam,
    weights,
    step,
    w0,
    *,
    nonneg=None,
    max_iter=10_000,
    tol=1e-8,
    check_every=10,
    max_step_reductions=40,
):
    r"""Solve ``R`` problems :math:`\tfrac12 w^\top G_r w - b_r^\top w + \lambda
    \sum_k \omega_k |w_k|` (restricted to ``mask[r]``) by FISTA in lockstep.

    Parameters
    ----------
    gram : ndarray of shape (R, p, p)
    rhs : ndarray of shape (R, p)
    const : ndarray of shape (R,)
        Constant of each datafit (its value at ``w = 0`` is ``const / 2``).
    mask : ndarray of bool, shape (R, p)
        Each problem's support; ``w`` stays zero outside it.
    lam : float
    weights : ndarray of shape (p,)
        L1 weights (0: unpenalized).
    step : ndarray of shape (R,)
        Each problem's step (``1 / L`` of its restricted Gram matrix).
    w0 : ndarray of shape (R, p)
        Starting points (zero outside the masks).
    nonneg : ndarray of bool, shape (p,), optional
        Coefficients projected onto ``w >= 0``.
    max_iter, tol, check_every, max_step_reductions
        As in :func:`~lagsindy.solvers.fista`: a problem whose objective rises at
        two consecutive checks has its step halved and restarts from its best
        iterate; after ``max_step_reductions`` halvings it is flagged.

    Returns
    -------
    BatchedResult
    """
    R = gram.shape[0]
    mask = mask.astype(bool)
    lw = lam * weights[None, :]
    step = np.asarray(step, dtype=float)[:, None]
    w = np.where(mask, w0, 0.0)
    w_prev = w.copy()
    best_w = w.copy()
    best_obj = _value(gram, rhs, const, w) + (lw * np.abs(w)).sum(axis=1)
    k = np.ones(R)
    rises = np.zeros(R, dtype=np.int64)
    guard = np.zeros(R, dtype=np.int64)
    live = np.ones(R, dtype=bool)
    n_iter = np.full(R, max_iter, dtype=np.int64)
    converged = np.zeros(R, dtype=bool)
    flagged = np.zeros(R, dtype=bool)
    if R == 0 or max_iter < 1:
        return BatchedResult(w, np.zeros(R, dtype=np.int64), converged, flagged)
    for it in range(1, max_iter + 1):
        beta = np.where(k > 1, (k - 2) / (k + 1), 0.0)[:, None]
        v = w + beta * (w - w_prev)
        grad = np.matmul(gram, v[:, :, None])[:, :, 0] - rhs
        u = v - step * grad
        w_new = np.sign(u) * np.maximum(np.abs(u) - step * lw, 0.0)
        if nonneg is not None:
            w_new = np.where(nonneg[None, :], np.maximum(w_new, 0.0), w_new)
        w_new = np.where(mask, w_new, 0.0)
        restart = np.einsum("ri,ri->r", v - w_new, w_new - w) > 0
        k = np.where(live, np.where(restart, 1.0, k + 1.0), k)
        upd = live[:, None]
        w_prev = np.where(upd, w, w_prev)
        w = np.where(upd, w_new, w)
        if it % check_every == 0 or it == max_iter:
            with np.errstate(over="ignore", invalid="ignore"):
                obj = _value(gram, rhs, const, w) + (lw * np.abs(w)).sum(axis=1)
            finite = np.isfinite(obj)
            rise = ~finite | (
                obj > best_obj + 1e-10 * np.maximum(1.0, np.abs(best_obj))
            )
            rises = np.where(live & rise, rises + 1, np.where(live, 0, rises))
            bad = live & rise & (~finite | (rises >= 2))
            # fista's divergence guard: halve the step, restart from the best iterate
            give_up = bad & (guard >= max_step_reductions)
            flagged |= give_up
            live &= ~give_up
            halve = bad & ~give_up
            if halve.any():
                step = np.where(halve[:, None], 0.5 * step, step)
                guard = guard + halve
                w = np.where(halve[:, None], best_w, w)
                w_prev = np.where(halve[:, None], best_w, w_prev)
                k = np.where(halve, 1.0, k)
                rises = np.where(halve, 0, rises)
            better = live & ~rise & (obj <= best_obj)
            best_obj = np.where(better, obj, best_obj)
            best_w = np.where(better[:, None], w, best_w)
            g = np.matmul(gram, w[:, :, None])[:, :, 0] - rhs
            at_zero = np.maximum(np.abs(g) - lw, 0.0)
            if nonneg is not None:
                at_zero = np.where(nonneg[None, :], np.maximum(-g - lw, 0.0), at_zero)
            dist = np.where(w != 0, np.abs(g + lw * np.sign(w)), at_zero)
            dist = np.where(mask, dist, 0.0).max(axis=1) if dist.size else np.zeros(R)
            done = live & ~halve & (dist <= tol)
            n_iter[done] = it
            converged |= done
            live &= ~done
            if not live.any():
                break
    return BatchedResult(w, n_iter, converged, flagged)


def lipschitz_steps(gram, mask):
    """``1 / L`` of each problem's Gram block on its mask (1 where ``L`` is 0), as
    :func:`~lagsindy.solvers.fista` chooses its step."""
    steps = np.ones(gram.shape[0])
    for r in range(gram.shape[0]):
        idx = np.flatnonzero(mask[r])
        if idx.size == 0:
            continue
        top = max(float(np.linalg.eigvalsh(gram[r][np.ix_(idx, idx)])[-1]), 0.0)
        steps[r] = 1.0 / top if top > 0 else 1.0
        if not math.isfinite(steps[r]):
            steps[r] = 1.0
    return steps
