"""Row and column scaling of the Euler-Lagrange Gram statistics, and what the
scaled statistics say before any sparse solve (dense residual, identifiability)."""

from __future__ import annotations

import warnings

import numpy as np
import torch

from .._stacklevel import outside_stacklevel
from .._torch import to_numpy
from ..solvers.datafits import GramQuadratic

# --------------------------------------------------------------------------- scaling
# The alternating row/column scaling converges linearly (about 100-150 iterations to
# rtol 1e-10 on the paper's systems); the fit is invariant to units only at its fixed
# point, so the cap must not cut it short (100 did, shifting noisy fits by ~1e-7).
BALANCE_MAX_ITER = 2000


def balance_rows(mean_sq: np.ndarray) -> np.ndarray:
    """Row scales of the alternating row/column balancing of ``mean_sq``.

    ``mean_sq`` holds the mean squares of the columns per coordinate, of shape
    (n_dof, p), or (R, n_dof, p) for R problems balanced at once (each stops at its
    own iteration: the same scales as one at a time, up to rounding). On NumPy
    arrays with plain ufuncs: the iterations are on a few numbers each, where the
    per-call overhead of torch (about 0.3 ms per iteration) or of NumPy's
    Python-level ``mean``/``allclose`` would dominate.

    Returns
    -------
    ndarray of shape (n_dof,) or (R, n_dof)
    """
    single = mean_sq.ndim == 2
    stacked = mean_sq[None] if single else mean_sq
    with np.errstate(all="ignore"):  # inf and nan pass silently, as in torch
        rows = _balance(stacked)
    return rows[0] if single else rows


def _linked(nonzero) -> bool:
    """Whether the coordinates whose equations hold some column are linked through
    shared columns (``nonzero``: (n_dof, p) bool)."""
    rows = [i for i in range(nonzero.shape[0]) if nonzero[i].any()]
    if len(rows) < 2:
        return True
    reached, frontier = {rows[0]}, [rows[0]]
    while frontier:
        cols = nonzero[frontier].any(axis=0)
        frontier = [i for i in rows if i not in reached and (nonzero[i] & cols).any()]
        reached.update(frontier)
    return len(reached) == len(rows)


def _balance(mean_sq):
    n_prob, n_dof = mean_sq.shape[:2]
    rows = np.ones((n_prob, n_dof), dtype=mean_sq.dtype)
    live = np.ones(n_prob, dtype=bool)
    # Equations that share no column (a robot's joints with its URDF model held:
    # each joint's rotor inertia and friction on its own equation) have no common
    # scale: averaging each row over every active column drove their scales apart
    # by a constant factor per iteration (1e-88 against 1e88); such rows average
    # over their own columns.
    nonzero = mean_sq > 0
    own = nonzero.sum(axis=2)
    # resamples share one pattern: each distinct pattern is checked once
    linked = {}
    for m in nonzero:
        key = m.tobytes()
        if key not in linked:
            linked[key] = _linked(m)
    apart = np.array([not linked[m.tobytes()] for m in nonzero])
    for _ in range(BALANCE_MAX_ITER):
        cols = np.sqrt(np.add.reduce(mean_sq / rows[:, :, None] ** 2, axis=1) / n_dof)
        active = cols > 0
        count = np.where(apart[:, None], own, active.sum(axis=1)[:, None])
        safe = np.where(active, cols, 1.0)
        ratio = np.where(active[:, None, :], mean_sq / safe[:, None, :] ** 2, 0.0)
        new = np.sqrt(np.add.reduce(ratio, axis=2) / np.maximum(count, 1))
        new = np.where(new > 0, new, 1.0)
        new = new / np.exp(np.add.reduce(np.log(new), axis=1) / n_dof)[:, None]
        close = (np.abs(new - rows) <= 1e-10 * np.abs(rows)).all(axis=1)
        step = live & (active.sum(axis=1) > 0)
        rows = np.where(step[:, None], new, rows)
        live &= step & ~close
        if not live.any():
            break
    return rows


class BalancedGram:
    r"""Scaled least-squares problems from per-coordinate Gram statistics.

    The Euler-Lagrange rows of different coordinates carry different units (a force
    on a cart, a torque on a joint) and the candidate columns differ in scale by
    orders of magnitude. With ``normalize=True`` each coordinate's equation is
    weighted by :math:`1/r_i` and each column by :math:`1/s_k`, where ``r`` and ``s``
    balance the mean squares of the weighted columns (alternating scaling of rows and
    columns, as in matrix equilibration). The target is then scaled to unit mean
    square. The fit is therefore unchanged by a change of units of any coordinate,
    input or term, and ``lam`` and ``threshold`` mean the same thing for every system.

    Parameters
    ----------
    gram : Tensor of shape (n_dof, P, P)
        ``A_i^T A_i`` for each coordinate ``i``, where ``A`` holds the ``n_features``
        candidate columns followed by any target columns.
    n_samples : int
    n_features : int
        Number of candidate columns (the rest are targets).
    normalize : bool, default=True
    project_psd : bool, default=False
        Replace the combined Gram matrix by its nearest positive semi-definite
        matrix (after a noise correction has been subtracted).
    row_scale : Tensor of shape (n_dof,), default=None
        Row scales to use instead of balancing (with ``normalize``): those of
        another fit of the same rows.
    """

    def __init__(
        self,
        gram: torch.Tensor,
        n_samples: int,
        n_features: int,
        normalize: bool = True,
        project_psd: bool = False,
        row_scale=None,
    ):
        self.n_features = int(n_features)
        # rows per coordinate of the statistics (samples, or test windows)
        self.n_samples = int(n_samples)
        n_dof = gram.shape[0]
        mean_sq = torch.diagonal(gram, dim1=1, dim2=2)[:, : self.n_features] / n_samples
        mean_sq = torch.clamp(mean_sq, min=0)
        rows = torch.ones(n_dof, dtype=gram.dtype, device=gram.device)
        if normalize and row_scale is not None:
            rows = row_scale
        elif normalize and self.n_features:
            rows = torch.as_tensor(
                balance_rows(to_numpy(mean_sq)), dtype=gram.dtype, device=gram.device
            )
        self.row_scale = rows
        weights = 1.0 / rows**2
        # Each column's squared norm per equation (weighted rows), and the share of
        # its norm each equation holds: what the staged threshold judges terms by.
        per_eq = torch.clamp(torch.diagonal(gram, dim1=1, dim2=2), min=0)
        per_eq = per_eq * weights[:, None]
        total = per_eq.sum(dim=0)
        self.equation_shares = torch.sqrt(
            torch.where(total > 0, per_eq / torch.where(total > 0, total, 1.0), 0.0)
        )
        self.gram = (gram * weights[:, None, None]).sum(dim=0) / (n_samples * n_dof)
        if project_psd:
            # A corrected Gram (noise contribution subtracted) can have slightly
            # negative eigenvalues; use the nearest positive semi-definite matrix.
            evals, evecs = torch.linalg.eigh((self.gram + self.gram.T) / 2)
            self.gram = (evecs * torch.clamp(evals, min=0)) @ evecs.T
        col = torch.sqrt(
            torch.clamp(torch.diagonal(self.gram)[: self.n_features], min=0)
        )
        if normalize:
            self.col_scale = col
        else:
            self.col_scale = torch.where(col > 0, torch.ones_like(col), col)
        self.normalize = normalize

    @classmethod
    def many(cls, grams, n_samples, n_features, normalize=True, project_psd=False):
        """:class:`BalancedGram` of several statistics, their row scales balanced at
        once (:func:`balance_rows` on the stack; each problem stops at its own
        iteration, so each gets the scales it would get alone, up to rounding).

        Parameters
        ----------
        grams : Tensor of shape (R, n_dof, P, P)
        n_samples : sequence of int, length R
        n_features : int
        normalize, project_psd : bool

        Returns
        -------
        list of BalancedGram
        """
        n_rows = torch.as_tensor(
            np.asarray(n_samples, dtype=float), dtype=grams.dtype, device=grams.device
        )
        rows = [None] * grams.shape[0]
        if normalize and n_features:
            diag = torch.diagonal(grams, dim1=2, dim2=3)[:, :, :n_features]
            mean_sq = torch.clamp(diag / n_rows[:, None, None], min=0)
            scales = torch.as_tensor(
                balance_rows(to_numpy(mean_sq)), dtype=grams.dtype, device=grams.device
            )
            rows = list(scales)
        return [
            cls(g, int(n), n_features, normalize, project_psd, row_scale=r)
            for g, n, r in zip(grams, n_samples, rows)
        ]

    def identifiable(self) -> torch.Tensor:
        """Boolean mask of candidate columns that are not identically zero on the data."""
        big = float(self.col_scale.max()) if self.col_scale.numel() else 0.0
        return self.col_scale > 1e-12 * max(big, 1e-300)

    def block(self, free):
        """Scaled Gram block of the columns ``free`` and their (safe) column scales.

        The one place where a sub-block of the balanced Gram matrix is scaled to unit
        diagonal: ``g[i, j] = G[f_i, f_j] / (s_i s_j)`` with ``s`` the column scales
        (1 where a column is zero).

        Returns
        -------
        g : Tensor of shape (len(free), len(free))
        scale : Tensor of shape (len(free),)
        """
        idx = torch.as_tensor(free, dtype=torch.long, device=self.gram.device)
        s = self.col_scale[idx]
        s = torch.where(s > 0, s, torch.ones_like(s))
        return self.gram[idx][:, idx] / (s[:, None] * s[None, :]), s

    def target_scale(self, target: int) -> float:
        return float(torch.sqrt(torch.clamp(self.gram[target, target], min=0)))

    def problem(self, free, target: int, sign: float = 1.0):
        """Normalized :class:`GramQuadratic` for ``sign * column[target] ~ columns[free]``.

        Returns
        -------
        datafit : GramQuadratic
            In scaled variables ``w``.
        to_coef : callable
            Maps ``w`` to coefficients of the unscaled columns.
        """
        return self.problems([(free, target, sign)])[0][0]

    def problems(self, jobs):
        """:meth:`problem` of several ``(free, target, sign)``.

        Every block is cut from one scaled block (:meth:`block`) of the union of
        the ``free`` columns: its entries are element-wise those of each job's own
        block, so the result does not depend on which jobs go together.

        Returns
        -------
        pairs : list of (GramQuadratic, callable)
            As :meth:`problem` returns, in the order of ``jobs``.
        union : ndarray of int
            The sorted union of the ``free`` columns.
        block : Tensor of shape (len(union), len(union))
            ``block(union)[0]``.
        """
        device = self.gram.device
        frees = [np.asarray(free, dtype=np.int64) for free, _, _ in jobs]
        union = np.unique(np.concatenate(frees)) if frees else np.zeros(0, np.int64)
        g_all, s_all = self.block(union)
        # target_scale of every column at once (element-wise: the same values)
        y_scales = torch.sqrt(torch.clamp(torch.diagonal(self.gram), min=0)).tolist()
        if any(y_scales[target] <= 0 for _, target, _ in jobs):
            raise ValueError("the target is identically zero on the data")
        pairs = [None] * len(jobs)
        by_size = {}
        for j, f in enumerate(frees):
            by_size.setdefault(f.size, []).append(j)
        # The jobs with as many columns at once: their blocks, scales and targets'
        # columns are gathers, the right-hand sides element-wise (the same values).
        for group in by_size.values():
            if len(group) == 1 and np.array_equal(frees[group[0]], union):
                # one job on the whole union (every single solve): no gathers
                j = group[0]
                _, target, sign = jobs[j]
                y_scale = y_scales[target]
                column = self.gram[torch.as_tensor(frees[j], device=device), target]
                rhs = sign * column / (s_all * y_scale)
                datafit = GramQuadratic(
                    g_all, rhs, 1.0, *self._shares(frees[j], target)
                )
                pairs[j] = (datafit, _unscaler(s_all, y_scale))
                continue
            pos = torch.as_tensor(
                np.stack([np.searchsorted(union, frees[j]) for j in group]),
                device=device,
            )
            cols = torch.as_tensor(np.stack([frees[j] for j in group]), device=device)
            targets = torch.as_tensor([jobs[j][1] for j in group], device=device)
            signs, y_scale = (
                torch.as_tensor(v, dtype=g_all.dtype, device=device)[:, None]
                for v in (
                    [float(jobs[j][2]) for j in group],
                    [y_scales[jobs[j][1]] for j in group],
                )
            )
            s_safe = s_all[pos]
            grams = g_all[pos[:, :, None], pos[:, None, :]]
            rhs = signs * self.gram[cols, targets[:, None]] / (s_safe * y_scale)
            for i, j in enumerate(group):
                to_coef = _unscaler(s_safe[i], y_scales[jobs[j][1]])
                shares = self._shares(frees[j], jobs[j][1])
                pairs[j] = (GramQuadratic(grams[i], rhs[i], 1.0, *shares), to_coef)
        return pairs, union, g_all

    def _shares(self, free, target):
        """``(equation_shares, target_shares)`` of a problem (see
        :class:`~lagsindy.solvers.GramQuadratic`); ``(None, None)`` for one
        equation (or unscaled columns), where the threshold compares coefficients."""
        if self.equation_shares.shape[0] < 2 or not self.normalize:
            return None, None
        idx = torch.as_tensor(free, dtype=torch.long, device=self.gram.device)
        return self.equation_shares[:, idx], self.equation_shares[:, target]


def _unscaler(s_safe, y_scale):
    """``to_coef`` of a problem: its scaled variables ``w`` in coefficient units."""

    def to_coef(w):
        return w * y_scale / s_safe

    return to_coef


# Eigenvalue ratio of the scaled Gram matrix below which a combination of terms is
# treated as having no effect on the data.
NULL_RCOND = 1e-11


class IdentifiabilityWarning(UserWarning):
    """The data leave a combination of candidate terms undetermined."""


def dense_residual(datafit: GramQuadratic) -> float:
    """Relative residual of the unpenalised least-squares fit of every feature.

    A lower bound of the relative residual of any sparse (or constrained) solution of
    ``datafit``; eigenvalues below ``NULL_RCOND`` times the largest are treated as
    zero.
    """
    if datafit.const <= 0 or datafit.n_features == 0:
        return 0.0
    vals, vecs = torch.linalg.eigh(datafit.gram)
    return _unexplained(vals, vecs, datafit)


def dense_solution(datafit: GramQuadratic):
    """The minimum-norm unpenalised least-squares solution (in ``datafit``'s scaled
    variables) and its :func:`dense_residual`, from one eigen-decomposition."""
    vals, vecs = torch.linalg.eigh(datafit.gram)
    keep, proj = _projection(vals, vecs, datafit)
    return vecs[:, keep] @ (proj / vals[keep]), _unexplained(vals, vecs, datafit)


def _projection(vals, vecs, datafit):
    """The eigenvalues kept (above ``NULL_RCOND`` times the largest) and the
    right-hand side's coordinates along their eigenvectors."""
    keep = vals > NULL_RCOND * float(vals[-1].clamp(min=0))
    return keep, vecs[:, keep].T @ datafit.rhs


def _unexplained(vals, vecs, datafit) -> float:
    """:func:`dense_residual` from the eigen-decomposition of ``datafit.gram``."""
    keep, proj = _projection(vals, vecs, datafit)
    explained = float((proj * proj / vals[keep]).sum())
    return max(0.0, 1.0 - explained / datafit.const)


def dense_residuals(datafits) -> list:
    """:func:`dense_residual` of several problems, their eigen-decompositions batched
    where they have the same size (the same values: LAPACK runs on each matrix)."""
    out = [None] * len(datafits)
    by_size = {}
    for j, d in enumerate(datafits):
        if d.const <= 0 or d.n_features == 0:
            out[j] = 0.0
        else:
            by_size.setdefault(d.n_features, []).append(j)
    for idx in by_size.values():
        vals, vecs = torch.linalg.eigh(torch.stack([datafits[j].gram for j in idx]))
        for k, j in enumerate(idx):
            out[j] = _unexplained(vals[k], vecs[k], datafits[j])
    return out


def fixed_term_bounds(gram) -> np.ndarray:
    r"""Lower bounds of every column's relative residual when the others fit it.

    For each ``r``, :math:`\min_{x:\,x_r = 1} x^\top G x / G_{rr}`: the relative
    residual of the unpenalised least-squares fit of column ``r`` by all the other
    columns of ``gram`` (the Schur complement of :math:`G_{rr}`). No sparse or
    sign-constrained fit of that column by a subset of the others can do better, so
    the value bounds from below the cost of case III with ``r`` as the fixed term.

    All the columns at once, from one eigen-decomposition: the Schur complement is
    :math:`1 / (G^{-1})_{rr} = 1 / \sum_i V_{ri}^2 / \lambda_i`. Each eigenvalue is
    lowered by ``delta``, a multiple of the decomposition's rounding error, so that
    rounding cannot raise a bound; eigenvalues at that level (a null combination of
    the columns, as the Lagrangian itself on passive data) are set to ``delta``, so
    a column that such a combination explains gets a bound at rounding level.
    Compare with a margin above rounding.

    Parameters
    ----------
    gram : Tensor or ndarray of shape (m, m)
        A symmetric positive semi-definite Gram matrix with a positive diagonal.

    Returns
    -------
    ndarray of shape (m,)
    """
    g = np.asarray(to_numpy(gram) if torch.is_tensor(gram) else gram, dtype=float)
    g = (g + g.T) / 2
    m = g.shape[0]
    if m == 0:
        return np.zeros(0)
    if m == 1:
        return np.ones(1)
    # The bounds do not depend on the columns' scales: decompose the matrix with a
    # unit diagonal, whose rounding is the smallest.
    d = np.sqrt(np.diagonal(g))
    g = g / np.outer(d, d)
    vals, vecs = np.linalg.eigh(g)
    delta = 64 * m * np.finfo(float).eps * max(float(np.abs(vals).max()), 1e-300)
    lowered = np.maximum(vals - delta, delta)
    inv_diag = (vecs * vecs / lowered) @ np.ones(m)
    return np.clip(1.0 / inv_diag, 0.0, 1.0)


def warn_if_not_identifiable(balanced, free, names, *, allowed):
    """Warn when the data leave more than ``allowed`` exact null combinations of terms.

    In case I a null combination of Euler-Lagrange columns means the data cannot
    tell those terms apart (e.g. a constant input is indistinguishable from a linear
    potential); in case III one null combination is expected (the Lagrangian itself).
    """
    if len(free) < 2:
        return
    g, _ = balanced.block(free)
    evals, evecs = torch.linalg.eigh(g)
    tiny = evals <= NULL_RCOND * evals[-1]
    n_null = int(tiny.sum())
    if n_null <= allowed:
        return
    v = to_numpy(evecs[:, n_null - 1 - allowed] if allowed else evecs[:, 0])
    order = np.argsort(-np.abs(v))
    parts = [f"{v[k]:+.3g}*[{names[free[k]]}]" for k in order[:6] if abs(v[k]) > 1e-3]
    warnings.warn(
        f"the data do not determine the Lagrangian uniquely: {n_null - allowed} "
        "combination(s) of candidate terms have (near) zero Euler-Lagrange residual on "
        f"these trajectories, e.g. {' '.join(parts)} (scaled units). Excite the system "
        "differently (a constant input cannot be told from a linear potential), add "
        "trajectories, or remove terms from the library.",
        IdentifiabilityWarning,
        stacklevel=outside_stacklevel(),
    )
