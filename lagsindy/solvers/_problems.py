"""The problems of a staged schedule: their stages, residuals and refits.

The schedule (:func:`~lagsindy.solvers.staged._schedule`) is written once over a
batch of problems, one problem being a batch of one. It keeps each problem's
coefficients, supports, L1 weights and thresholds as rows of NumPy arrays in the
batch's coordinates (problem ``r``'s features at ``index[r]``) and asks the batch
for the three things that depend on how the problems are held:

* :meth:`stage`: one FISTA stage of some rows on their supports;
* :meth:`residuals`: relative residuals of some rows at given coefficients;
* :meth:`least_squares`: the unpenalised fit of some rows on their supports.

:class:`Lockstep` holds CPU double-precision Gram quadratics (blocks of one shared
matrix, or each its own of one size) and batches all three on NumPy arrays;
:class:`Alone` holds any datafits (torch tensors on any device, case II's
non-convex datafit) and solves each on its own, restricted to its support.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .fista import fista, fista_batch, proximal_gradient
from .penalties import L1

# The unpenalised refit with coefficients held non-negative: projected FISTA
# without penalty, to this tolerance.
NNLS_MAX_ITER = 50_000
NNLS_TOL = 1e-12


@dataclass
class StageRuns:
    """One stage's FISTA runs, one entry per row (coefficients in the batch's
    coordinates)."""

    coef: np.ndarray
    step: np.ndarray
    n_iter: np.ndarray
    converged: np.ndarray
    stop_crit: np.ndarray
    step_reductions: np.ndarray


def _equation_shares(datafits, index, m):
    """Every problem's equation shares in the batch's coordinates, ``(n, n_eq, m)``
    and ``(n, n_eq)`` (see :class:`~lagsindy.solvers.GramQuadratic`), or ``(None,
    None)`` when no problem has them. A problem without them (or with fewer
    equations) gets zeros there, which leave it the global threshold alone."""
    shares = [getattr(d, "equation_shares", None) for d in datafits]
    n_eq = max((s.shape[0] for s in shares if s is not None), default=0)
    if n_eq == 0:
        return None, None
    out = np.zeros((len(datafits), n_eq, m))
    targets = np.zeros((len(datafits), n_eq))
    for r, (d, s, idx) in enumerate(zip(datafits, shares, index)):
        if s is not None:
            out[r, : s.shape[0]][:, idx] = s.detach().cpu().numpy()
            targets[r, : s.shape[0]] = d.target_shares.detach().cpu().numpy()
    return out, targets


def _numpy(values, size):
    """``values`` (a tensor, an array, a number or ``None``) as a float array of
    ``size`` entries."""
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.broadcast_to(np.asarray(values, dtype=float), (size,))


class Problems:
    """Problems in a batch's coordinates (see the module); the base of both kinds.

    Parameters
    ----------
    datafits : list
    index : list of int ndarray
        Each problem's features' positions among the ``m`` coordinates.
    m : int
    weights, thresholds : list
        Each problem's L1 weights (``None``: ones) and relative hard thresholds
        (one value or one per feature).
    nonneg : list
        Each problem's non-negative features (bool, or ``None``).
    w0 : list
        Each problem's starting point (``None``: zeros; FISTA projects it on the
        non-negative features).
    """

    def __init__(self, datafits, index, m, weights, thresholds, nonneg, w0):
        n = len(datafits)
        self.datafits, self.index, self.n, self.m = datafits, index, n, m
        self.mask = np.zeros((n, m), dtype=bool)
        self.weights = np.zeros((n, m))
        self.thr = np.zeros((n, m))
        self.start = np.zeros((n, m))
        self.nonneg = None
        for r, idx in enumerate(index):
            self.mask[r, idx] = True
            if weights[r] is None:
                self.weights[r, idx] = 1.0
            else:
                self.weights[r, idx] = _numpy(weights[r], idx.size)
            self.thr[r, idx] = _numpy(thresholds[r], idx.size)
            if w0[r] is not None:
                self.start[r, idx] = _numpy(w0[r], idx.size)
            if nonneg[r] is not None:
                if self.nonneg is None:
                    self.nonneg = np.zeros((n, m), dtype=bool)
                self.nonneg[r, idx] = _numpy(nonneg[r], idx.size) > 0
        self._like = [d.zeros() for d in datafits]
        self.shares, self.target_shares = _equation_shares(datafits, index, m)

    def own(self, r, row):
        """Problem ``r``'s features of a row in the batch's coordinates (a copy)."""
        return row[self.index[r]]

    def tensor(self, r, values):
        """``values`` as a tensor of problem ``r``'s dtype and device."""
        like = self._like[r]
        return torch.as_tensor(np.asarray(values), dtype=like.dtype, device=like.device)

    def _alone_least_squares(self, r, on, start):
        """The unpenalised fit of problem ``r`` on its features ``on`` (own
        coordinates), from ``start``; with non-negative features held so (a
        non-negative least squares where the plain fit makes one negative)."""
        sub = self.datafits[r].restrict(on)
        w_ls = sub.least_squares(w0=self.tensor(r, start[on]))
        if self.nonneg is not None:
            nn = torch.as_tensor(
                self.own(r, self.nonneg[r])[on], device=self._like[r].device
            )
            if bool((nn & (w_ls < 0)).any()):
                w_start = torch.where(nn, torch.clamp(w_ls, min=0.0), w_ls)
                w_ls = fista(
                    sub,
                    L1(0.0, None, nn),
                    w_start,
                    max_iter=NNLS_MAX_ITER,
                    tol=NNLS_TOL,
                ).coef
        return w_ls.detach().cpu().numpy()

    def _alone_rows(self, rows, on, start):
        """:meth:`least_squares` of ``rows`` one problem at a time."""
        out = np.zeros(on.shape)
        for i, r in enumerate(rows):
            own_on = np.flatnonzero(self.own(r, on[i]))
            out[i, self.index[r][own_on]] = self._alone_least_squares(
                r, own_on, self.own(r, start[i])
            )
        return out


class Alone(Problems):
    """Problems each solved on its own (any datafits; see the module).

    A stage restricts each problem to its support and runs :func:`fista` on it, or
    :func:`proximal_gradient` when its datafit has no Lipschitz constant (case
    II). ``index[r]`` is ``arange(p_r)``: the batch's coordinates are the first
    ``max(p_r)``.
    """

    def __init__(self, datafits, weights, thresholds, nonneg, w0):
        index = [np.arange(d.n_features) for d in datafits]
        m = max((d.n_features for d in datafits), default=0)
        super().__init__(datafits, index, m, weights, thresholds, nonneg, w0)

    def stage(self, rows, on, w, lam, step, max_iter, tol):
        coef, runs = np.zeros(on.shape), []
        for i, r in enumerate(rows):
            support = np.flatnonzero(on[i])
            sub = self.datafits[r].restrict(support)
            nonneg = None
            if self.nonneg is not None:
                nonneg = torch.as_tensor(
                    self.nonneg[r, support], device=self._like[r].device
                )
            pen = L1(lam, self.tensor(r, self.weights[r, support]), nonneg)
            solver = fista if sub.lipschitz() is not None else proximal_gradient
            res = solver(
                sub,
                pen,
                self.tensor(r, w[i, support]),
                step=step,
                max_iter=max_iter,
                tol=tol,
            )
            coef[i, support] = res.coef.detach().cpu().numpy()
            runs.append(
                (
                    res.step,
                    res.n_iter,
                    res.converged,
                    res.stop_crit,
                    res.step_reductions,
                )
            )
        step, n_iter, converged, stop, reductions = map(np.array, zip(*runs))
        return StageRuns(
            coef,
            step,
            n_iter.astype(np.int64),
            converged.astype(bool),
            stop,
            reductions.astype(np.int64),
        )

    def residuals(self, rows, w):
        return np.array(
            [
                self.datafits[r].relative_residual(self.tensor(r, self.own(r, row)))
                for r, row in zip(rows, w)
            ]
        )

    def least_squares(self, rows, on, start):
        return self._alone_rows(rows, on, start)


class Lockstep(Problems):
    """CPU double-precision Gram quadratics whose FISTA runs, residuals and refits
    are batched (see the module).

    With ``shared = (C, index)`` every problem's Gram matrix is the block
    ``C[index[r]][:, index[r]]`` of one matrix, so a batched gradient is one matrix
    product; otherwise the problems have one size and each its own matrix. The
    refit of the problems without non-negative features is one batched
    eigen-decomposition per round (each support padded with zeros to the batch's
    coordinates); those with some are refitted one by one.
    """

    def __init__(self, datafits, weights, thresholds, nonneg, w0, shared=None):
        def arr(t):
            return t.detach().cpu().numpy()

        if shared is None:
            self.gram = np.stack([arr(d.gram) for d in datafits])
            index = [np.arange(d.n_features) for d in datafits]
        else:
            self.gram, index = np.asarray(shared[0]), [np.asarray(i) for i in shared[1]]
        m = self.gram.shape[-1]
        super().__init__(datafits, index, m, weights, thresholds, nonneg, w0)
        self.rhs = np.zeros((self.n, m))
        for r, (d, idx) in enumerate(zip(datafits, index)):
            self.rhs[r, idx] = arr(d.rhs)
        self.const = np.array([d.const for d in datafits])
        self.plain = np.ones(self.n, dtype=bool)
        if self.nonneg is not None:
            self.plain = ~self.nonneg.any(1)

    def _gram(self, rows):
        return self.gram if self.gram.ndim == 2 else self.gram[rows]

    def stage(self, rows, on, w, lam, step, max_iter, tol):
        res = fista_batch(
            self._gram(rows),
            self.rhs[rows],
            self.const[rows],
            lam,
            self.weights[rows],
            w,
            on,
            None if self.nonneg is None else self.nonneg[rows],
            step=None if step is None else np.full(len(rows), step),
            max_iter=max_iter,
            tol=tol,
        )
        return StageRuns(
            res.coef,
            res.step,
            res.n_iter,
            res.converged,
            res.stop_crit,
            res.step_reductions,
        )

    def residuals(self, rows, w):
        return _relative_residuals(
            self._gram(rows), self.rhs[rows], self.const[rows], w
        )

    def least_squares(self, rows, on, start):
        out = np.zeros(on.shape)
        plain = self.plain[rows]
        if plain.any():
            sel = rows[plain]
            out[plain] = _padded_least_squares(
                self._gram(sel), on[plain], self.rhs[sel]
            )
        if not plain.all():
            out[~plain] = self._alone_rows(rows[~plain], on[~plain], start[~plain])
        return out


def _padded_least_squares(gram, on, rhs, rtol=1e-13):
    """Minimum-norm least squares of each row on its support ``on``, as
    ``GramQuadratic.least_squares`` (eigenvalues up to ``rtol`` times the largest
    dropped), on its block of ``gram`` (shared, or one per row) padded with zeros to
    the batch's coordinates: the padding adds zero eigenvalues, which are dropped,
    so the kept eigenvectors lie on the support."""
    both = on[:, :, None] & on[:, None, :]
    evals, evecs = np.linalg.eigh(np.where(both, gram, 0.0))
    keep = evals > rtol * np.maximum(evals[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    proj = np.einsum("rji,rj->ri", evecs, np.where(on, rhs, 0.0))
    fit = np.einsum("rij,rj->ri", evecs, inv * proj)
    return np.where(on, fit, 0.0)


def _relative_residuals(gram, rhs, const, w):
    """``GramQuadratic.relative_residual`` of every row of ``w`` (batch coordinates).

    ``gram`` is one matrix shared by the rows, shape (m, m), or one per row,
    (R, m, m); ``w`` and ``rhs`` are zero off each row's coordinates.
    """
    gw = w @ gram if gram.ndim == 2 else np.matmul(gram, w[:, :, None])[:, :, 0]
    value = 0.5 * np.einsum("ri,ri->r", w, gw) - np.einsum("ri,ri->r", rhs, w)
    value = value + 0.5 * const
    out = np.where(const > 0, 2.0 * value / np.where(const > 0, const, 1.0), 0.0)
    return np.where(out > 0.0, out, 0.0)  # as max(0.0, .): nan gives 0
