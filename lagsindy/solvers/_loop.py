"""The FISTA iterations, written once for a batch of problems advancing in lockstep.

One problem is a batch of one. Two kinds of batch supply the arithmetic:

* :class:`GramRows`: L1-penalised quadratics on NumPy arrays (the Gram matrices of
  cases I and III on the CPU), any number of them, with the exact finishes of
  :mod:`~lagsindy.solvers.exact`;
* :class:`ContractRow`: one problem through the duck-typed datafit/penalty contract
  of :func:`~lagsindy.solvers.fista` (torch tensors on any device, datafits other
  than Gram quadratics), without exact finishes.

While several problems run, an iterate is an array of shape (n, m): one row per
problem, in the batch's coordinates (each problem's own under a mask). A single
problem, and the last one of a batch still running, is iterated as a 1-d array on
its own coordinates: its products are then those of one problem (a matrix-vector
product, dot products) and its per-iteration overhead that of one.
"""

from __future__ import annotations

import math

import numpy as np

from .exact import _active_set, _kkt_distance, _polish

# Iterations at which a run on NumPy arrays that is still going tries to finish by
# an active-set search from its iterate (exact._active_set).
ACTIVE_SET_AT = frozenset(50 * 2**k for k in range(12))
# An objective above the best so far by more than this (relative) is a rise; two
# rises in a row (or a non-finite objective) halve the step (divergence guard).
RISE_RTOL = 1e-10


def _col(values, n):
    """Per-row ``values`` shaped to scale an iterate: a column for a batch, a float
    for a single problem (1-d iterate)."""
    return values[:, None] if n > 1 else float(values[0])


def _per_row(values, n):
    """``values`` (one number per row, or one number) as an array of shape (n,)."""
    return np.asarray(values, dtype=float).reshape(n)


def _select(mask, a, b, copy):
    """Rows of ``a`` where ``mask``, of ``b`` elsewhere (``copy``: the batch's)."""
    if not mask.any():
        return b
    if mask.all():
        return copy(a)
    return np.where(mask[:, None], a, b)


def _rowdot(a, b):
    """Per-row dot products (a 1-d iterate: BLAS's dot)."""
    return a @ b if a.ndim == 1 else np.einsum("ri,ri->r", a, b)


def initial_steps(step, lip, n):
    """Steps ``1 / L`` (``step=None``), or ``step`` halved below ``2 / L``.

    A step above ``2/L`` diverges along the top eigenvector whatever the momentum:
    it is halved below ``2/L`` at once instead of being discovered by iterating.

    Returns
    -------
    steps : ndarray of shape (n,)
    reductions : ndarray of int, shape (n,)
        The halvings applied.
    """
    known = lip is not None
    lip = np.zeros(n) if lip is None else np.asarray(lip, dtype=float) * np.ones(n)
    positive = lip > 0
    safe = np.where(positive, lip, 1.0)
    if step is None:
        if not known:
            raise ValueError(
                "fista needs a step (alpha) when the datafit has no Lipschitz "
                "constant (lipschitz() is None); give one, or use proximal_gradient"
            )
        return np.where(positive, 1.0 / safe, 1.0), np.zeros(n, dtype=np.int64)
    steps = np.asarray(step, dtype=float) * np.ones(n)
    excess = np.log2(steps) + np.log2(safe) - 1.0
    halve = positive & (excess > 0)
    n_halvings = np.where(halve, np.ceil(np.where(halve, excess, 0.0)), 0.0)
    return steps / 2.0**n_halvings, n_halvings.astype(np.int64)


def run(rows, w, step, *, history=None, **settings):
    """FISTA on every problem of ``rows`` from ``w`` (see :func:`iterate`).

    NumPy rows whose warm start already has their minimiser's support and signs end
    before iterating. The steps (``step``: ``None``, or one per row) are set by
    :func:`initial_steps` from the Lipschitz constants: before that check when the
    constants are at hand (a single problem's, cached by its datafit), else after
    it for the rows that iterate only (one batched eigenvalue call).
    """
    # Divergence shows as inf/nan objectives, handled by the guard: no warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        _run(rows, w, step, history, settings)


def _run(rows, w, step, history, settings):
    steps = reductions = None
    if rows.lipschitz_at_hand:
        steps, reductions = initial_steps(step, rows.lipschitz(), rows.n)
    if rows.exact:
        going = rows.warm_finish(w, settings["tol"], steps)
        if not going.any():
            return
        if not going.all():
            (w,) = rows.keep(going, w)
            step = None if step is None else step[going]
            if steps is not None:
                steps, reductions = steps[going], reductions[going]
    if steps is None:
        steps, reductions = initial_steps(step, rows.lipschitz(), rows.n)
    iterate(rows, w, steps, reductions, history=history, **settings)


def iterate(
    rows,
    w,
    step,
    reductions,
    *,
    max_iter,
    tol,
    check_every,
    restart,
    max_step_reductions,
    history=None,
):
    r"""FISTA on every problem of ``rows`` from ``w`` (each ends by ``rows.finish``).

    The momentum is the paper's (eq. 18), :math:`v = w^{i-1} + \frac{i-2}{i+1}
    (w^{i-1} - w^{i-2})`, then :math:`w^i = \mathrm{prox}(v - \alpha \nabla f(v))`,
    with the gradient-based adaptive restart of O'Donoghue and Candes (the momentum
    is reset when it points uphill). Every ``check_every`` iterations: the
    divergence guard (two rises of the objective in a row, or a non-finite one,
    halve the step and return to the best iterate, at most
    ``max_step_reductions`` times), the KKT stop, and on NumPy problems the exact
    finishes (the minimiser of a support and signs steady since the last check;
    an active-set search at the iterations of :data:`ACTIVE_SET_AT`). The problems
    advance in lockstep; each stops at its own check, and the batch shrinks to
    those still running.

    ``step`` and ``reductions`` are arrays of shape (n,); ``history``, a list, gets
    the objective at every check (one problem).
    """
    n = rows.n
    rows.set_step(step)
    step_col = _col(step, n)
    copy = rows.copy
    w_prev = copy(w)
    best_w, best_obj = copy(w), _per_row(rows.objective(w), n)
    if history is not None:
        history.append(float(best_obj[0]))
    momentum = _Momentum(n, max_iter)
    rises = np.zeros(n, dtype=np.int64)
    guard = np.zeros(n, dtype=np.int64)
    stop = np.full(n, math.inf)
    last = rows.pattern(None) if rows.exact else None
    gradient, prox, rowdot = rows.gradient, rows.prox, rows.rowdot
    for it in range(1, max_iter + 1):
        v = w + momentum.beta() * (w - w_prev)
        w_new = prox(v - step_col * gradient(v))
        # the momentum restarts where it points uphill
        momentum.advance(restart and rowdot(v - w_new, w_new - w) > 0)
        w_prev, w = w, w_new
        if it % check_every != 0 and it != max_iter:
            continue
        obj = _per_row(rows.objective(w), n)
        if history is not None:
            history.append(float(obj[0]))
        finite = np.isfinite(obj)
        up = ~finite | (obj > best_obj + RISE_RTOL * np.maximum(1.0, np.abs(best_obj)))
        reset = up
        if up.any():  # the divergence guard (rare: the objective rose)
            rises = np.where(up, rises + 1, 0)
            reset = up & (~finite | (rises >= 2))
            if reset.any():
                spent = reset & (guard >= max_step_reductions)
                if spent.any():
                    bad = int(np.flatnonzero(spent)[0])
                    raise FloatingPointError(
                        "FISTA diverged: the objective kept growing after the step "
                        f"was halved {int(guard[bad])} times (step now "
                        f"{step[bad]:.3g}); use a smaller step (alpha) or alpha=None"
                    )
                step = np.where(reset, step * 0.5, step)
                rows.set_step(step)
                step_col = _col(step, n)
                guard = guard + reset
                reductions = reductions + reset
                w = _select(reset, best_w, w, copy)
                w_prev = _select(reset, best_w, w_prev, copy)
                momentum.reset(reset)
                rises = np.where(reset, 0, rises)
        else:
            rises[:] = 0
        better = ~up & (obj <= best_obj)
        best_obj = np.where(better, obj, best_obj)
        best_w = _select(better, w, best_w, copy)
        dist = _per_row(rows.kkt(w), n)
        stop = np.where(reset, stop, dist)
        done = ~reset & (dist <= tol)
        if rows.exact:
            # Rows whose support and signs held since the last check: the exact
            # minimiser of that pattern; then, at times, an active-set search.
            pattern = rows.pattern(w)
            steady = ~done & ~reset & (pattern == last).all(-1)
            last = pattern
            if steady.any():
                w = rows.exact_finish(_polish, steady, w, stop, done, tol)
            if it in ACTIVE_SET_AT and (~done & ~reset).any():
                w = rows.exact_finish(_active_set, ~done & ~reset, w, stop, done, tol)
        if it == max_iter:
            rows.finish(np.ones(n, dtype=bool), w, it, done, stop, step, reductions)
            return
        if done.any():
            rows.finish(done, w, it, True, stop, step, reductions)
            keep = ~done
            if not keep.any():
                return
            w, w_prev, best_w, last = rows.keep(keep, w, w_prev, best_w, last)
            best_obj, rises, guard, stop, step, reductions = (
                x[keep] for x in (best_obj, rises, guard, stop, step, reductions)
            )
            momentum.keep(keep)
            n = rows.n
            rows.set_step(step)
            step_col = _col(step, n)


class _Momentum:
    """FISTA's momentum ``(k - 2) / (k + 1)`` (0 for ``k = 1``) by the counter ``k``
    of each row: an integer for a single problem (as cheap as the arithmetic on
    it), an array looked up in one table for a batch."""

    _table = np.zeros(2)

    def __init__(self, n, max_iter):
        self.one = n == 1
        self.k = 1 if self.one else np.ones(n, dtype=np.int64)
        if n > 1 and _Momentum._table.size < max_iter + 2:
            counts = np.arange(max_iter + 2, dtype=float)
            _Momentum._table = np.maximum((counts - 2) / (counts + 1), 0.0)

    def beta(self):
        k = self.k
        if self.one:
            return (k - 2) / (k + 1) if k > 1 else 0.0
        return self._table[k][:, None]

    def advance(self, uphill):
        """The next counters: 1 where ``uphill`` (a restart), else one more."""
        if self.one:
            self.k = 1 if uphill else self.k + 1
        else:
            self.k = np.where(uphill, 1, self.k + 1)

    def reset(self, rows):
        if self.one:
            self.k = 1 if rows[0] else self.k
        else:
            self.k = np.where(rows, 1, self.k)

    def keep(self, rows):
        k = self.k[rows]
        self.one = k.size == 1
        self.k = int(k[0]) if self.one else k


# --------------------------------------------------------------------- NumPy rows
class GramRows:
    r"""L1-penalised quadratics on NumPy arrays: the batch of :func:`iterate`.

    Row ``r`` minimises ``0.5 w' G_r w - b_r' w + 0.5 c_r + lam sum_k wts_rk |w_k|``
    over its coordinates ``mask[r]`` (its other coordinates stay zero), with
    ``w_k >= 0`` where ``nonneg``; ``G_r`` is ``gram`` (one matrix shared by the rows)
    or ``gram[r]``. Results go to :attr:`out` (:class:`BatchResult` fields, one row
    per problem, in the batch's coordinates).

    Parameters
    ----------
    gram : ndarray of shape (m, m) or (R, m, m)
    rhs, weights : ndarray of shape (R, m)
    const : ndarray of shape (R,)
    lam : float
    mask : ndarray of bool, shape (R, m)
    nonneg : ndarray of bool, shape (R, m), or None
    out : object
        With ``coef``, ``n_iter``, ``converged``, ``stop_crit``, ``step`` and
        ``step_reductions`` arrays (one row per problem).
    lipschitz : ndarray of shape (R,), optional
        The rows' Lipschitz constants when they are at hand (else computed when
        needed, by one batched eigenvalue call).
    """

    exact = True

    def __init__(self, gram, rhs, const, lam, weights, mask, nonneg, out, lipschitz):
        self.out = out
        self.lam = float(lam)
        self.ids = np.flatnonzero(mask.any(1))  # rows without coordinates are done
        self.lip = None if lipschitz is None else np.asarray(lipschitz)[self.ids]
        fmask = mask[self.ids].astype(gram.dtype)
        self.shared = gram.ndim == 2
        # Own matrices with zeros off each row's coordinates; a shared one as it is
        # (the iterates are zero off the coordinates, the products there unused).
        self.g = gram if self.shared else _masked(gram[self.ids], fmask)
        self.b = np.where(mask, rhs, 0.0)[self.ids]
        self.c = np.asarray(const, dtype=float)[self.ids]
        self.wts = np.where(mask, weights, 0.0)[self.ids]
        self.fmask = fmask
        self.nn = None if nonneg is None else (nonneg & mask)[self.ids]
        self.cols = None  # the coordinates of a single row (1-d iterates)
        if self.ids.size == 1:
            self._single(0)
        else:
            self._derived()

    # ----------------------------------------------------------------- layout
    @property
    def n(self) -> int:
        return self.ids.size

    @property
    def lipschitz_at_hand(self) -> bool:
        return self.lip is not None

    def _derived(self):
        self.lw = self.lam * self.wts
        if self.cols is None:  # prox bounds: infinite off the coordinates
            off = self.fmask == 0
            self._off = off
            self._nn_or_off = off if self.nn is None else off | self.nn

    def _single(self, j):
        """Iterate row ``j`` alone on its own coordinates (1-d)."""
        on = self.fmask[j] > 0
        cols = np.flatnonzero(on)
        g = self.g if self.shared else self.g[j]
        self.g = g if on.all() else g[np.ix_(cols, cols)]
        self.b, self.wts = self.b[j, cols], self.wts[j, cols]
        self.c = self.c[j : j + 1]
        self.nn = None if self.nn is None else self.nn[j, cols]
        self.ids, self.cols = self.ids[j : j + 1], cols
        if self.lip is not None:
            self.lip = self.lip[j : j + 1]
        self.fmask = None
        self._derived()

    def keep(self, keep, *arrays):
        """Drop the rows not in ``keep`` from the batch and from ``arrays``."""
        if keep.sum() == 1:
            j = int(np.flatnonzero(keep)[0])
            cols = np.flatnonzero(self.fmask[j] > 0)
            out = [None if a is None else a[j, cols] for a in arrays]
            self._single(j)
            return out
        self.ids, self.b, self.c = self.ids[keep], self.b[keep], self.c[keep]
        self.wts, self.fmask = self.wts[keep], self.fmask[keep]
        self.g = self.g if self.shared else self.g[keep]
        self.nn = None if self.nn is None else self.nn[keep]
        if self.lip is not None:
            self.lip = self.lip[keep]
        self._derived()
        return [None if a is None else a[keep] for a in arrays]

    def copy(self, x):
        return x.copy()

    def start(self, w0):
        """The rows' starting iterates (from ``w0`` in the batch's coordinates),
        projected on ``w >= 0`` where required: an infeasible start would let the
        exact finish of its own signs end the run outside the feasible set."""
        w = w0[self.ids]
        w = w[0, self.cols] if self.cols is not None else w
        return w if self.nn is None else np.where(self.nn, np.maximum(w, 0.0), w)

    # ------------------------------------------------------------- arithmetic
    def times_gram(self, x):
        if x.ndim == 1:
            return self.g @ x
        if self.shared:  # rows zero off their coordinates; g symmetric
            return x @ self.g
        return np.matmul(self.g, x[:, :, None])[:, :, 0]

    def gradient(self, v):
        if v.ndim == 1:  # (the hot path of a single problem: one call)
            return self.g @ v - self.b
        return self.times_gram(v) - self.b

    def set_step(self, step):
        """Bounds of the proximal step ``w = z - clip(z, lo, hi)``: the soft
        threshold ``sign(z) max(|z| - thr, 0)`` bit for bit, projected on ``w >= 0``
        where ``lo`` is ``-inf``, and 0 off a row's coordinates (both infinite)."""
        if self.cols is not None:
            thr = float(step[0]) * self.lam * self.wts
            self._hi = thr
            self._lo = -thr if self.nn is None else np.where(self.nn, -np.inf, -thr)
        else:
            thr = (step * self.lam)[:, None] * self.wts
            self._lo = np.where(self._nn_or_off, -np.inf, -thr)
            self._hi = np.where(self._off, np.inf, thr)

    def prox(self, z):
        return z - np.minimum(np.maximum(z, self._lo), self._hi)

    rowdot = staticmethod(_rowdot)

    def objective(self, w):
        gw = self.times_gram(w)
        fit = 0.5 * _rowdot(w, gw) - _rowdot(self.b, w)
        if w.ndim == 1:
            return fit + 0.5 * self.c[0] + self.lam * (self.wts * np.abs(w)).sum()
        return fit + 0.5 * self.c + self.lam * (self.wts * np.abs(w)).sum(1)

    def kkt(self, w):
        """KKT distance (the distance of ``-grad`` to the subdifferential) per row."""
        dist = _kkt_distance(w, self.gradient(w), self.lw, self.nn)
        if w.ndim == 1:
            return dist.max() if dist.size else 0.0
        return np.where(self.fmask > 0, dist, 0.0).max(1)

    def lipschitz(self):
        """Largest eigenvalue of each row's Gram matrix (on its coordinates)."""
        if self.lip is None:
            if self.cols is not None:
                top = np.linalg.eigvalsh(self.g)[-1] if self.g.size else 0.0
                self.lip = np.array([max(float(top), 0.0)])
            else:
                stacked = _masked(self.g, self.fmask)
                self.lip = np.clip(np.linalg.eigvalsh(stacked)[:, -1], 0.0, None)
        return self.lip

    # --------------------------------------------------------- exact finishes
    def pattern(self, w):
        """Signs of ``w`` (``None``: the zero pattern)."""
        if w is None:
            shape = self.b.shape
            return np.zeros(shape, dtype=np.int8)
        return np.sign(w).astype(np.int8)

    def exact_finish(self, search, sel, w, stop, done, tol):
        """End the rows ``sel`` that ``search`` (:func:`_polish` or
        :func:`_active_set`) solves to the KKT tolerance (``stop`` and ``done``
        updated in place); returns the iterate."""
        if w.ndim == 1:
            x, ok, xdist = _one(search, self.g, self.b, self.lw, self.nn, w, tol)
            if ok:
                stop[0], done[0] = xdist, True
                return x
            return w
        pos = np.flatnonzero(sel)
        x, ok, xdist = search(
            self.g if self.shared else self.g[pos],
            self.b[pos],
            self.lw[pos],
            None if self.nn is None else self.nn[pos],
            w[pos],
            self.fmask[pos],
            tol,
        )
        hit = pos[ok]
        w[hit] = x[ok]
        stop[hit] = xdist[ok]
        done[hit] = True
        return w

    def warm_finish(self, w, tol, steps):
        """End the rows whose warm start (non-zero) already has the support and
        signs of their minimiser (as the stages after the first usually do), before
        iterating, with ``steps`` (``None``: nan, no step was computed); returns the
        mask of the rows that go on."""
        warm = np.any(w != 0, axis=-1)
        if not warm.any():
            return np.ones(self.n, dtype=bool)
        if w.ndim == 1:
            x, ok, xdist = _one(_polish, self.g, self.b, self.lw, self.nn, w, tol)
            ended, x, xdist = np.array([ok]), x[None], np.array([xdist])
        else:
            pos = np.flatnonzero(warm)
            g = self.g if self.shared else self.g[pos]
            nn = None if self.nn is None else self.nn[pos]
            got, optimal, dist = _polish(
                g, self.b[pos], self.lw[pos], nn, w[pos], self.fmask[pos], tol
            )
            ended = np.zeros(self.n, dtype=bool)
            ended[pos[optimal]] = True
            x, xdist = got[optimal], dist[optimal]
        if ended.any():
            step = np.nan if steps is None else steps[ended]
            self._record(ended, x, 0, True, xdist, step, 0)
        return ~ended

    # ---------------------------------------------------------------- results
    def finish(self, sel, w, it, converged, stop, step, reductions):
        """Record the rows ``sel`` (a mask over the running rows)."""
        if not np.isscalar(converged):
            converged = converged[sel]
        coef = w[sel] if w.ndim == 2 else w[None]
        self._record(sel, coef, it, converged, stop[sel], step[sel], reductions[sel])

    def _record(self, sel, coef, it, converged, stop, step, reductions):
        """Results of the rows ``sel``; ``coef``: theirs alone (own coordinates for
        a single row)."""
        out, o = self.out, self.ids[sel]
        if self.cols is not None:
            out.coef[o] = 0.0
            out.coef[o[0], self.cols] = coef[0]
        else:
            out.coef[o] = coef
        out.n_iter[o] = it
        out.converged[o] = converged
        out.stop_crit[o] = stop
        out.step[o] = step
        out.step_reductions[o] = reductions


def _masked(gram, fmask):
    """``gram`` (one matrix, or one per row) with zeros off each row's ``fmask``."""
    return gram * fmask[:, :, None] * fmask[:, None, :]


def _one(search, g, b, lw, nn, w, tol):
    """An exact finish (``search``) of one problem (1-d arrays) as a batch of one:
    ``(x, ok, dist)``."""
    x, ok, dist = search(
        g, b[None], lw[None], None if nn is None else nn[None], w[None],
        np.ones((1, w.shape[0])), tol,
    )  # fmt: skip
    return x[0], bool(ok[0]), float(dist[0])


# ------------------------------------------------------------------- torch row
class ContractRow:
    """One problem through the datafit/penalty contract: the batch of one of
    :func:`iterate` on any arrays (torch tensors on any device). No exact finishes."""

    exact = False
    n = 1
    lipschitz_at_hand = True

    def __init__(self, datafit, penalty):
        self.datafit, self.penalty = datafit, penalty
        self.result = None

    def copy(self, x):
        return x.clone()

    def gradient(self, v):
        return self.datafit.gradient(v)

    def set_step(self, step):
        self._step = float(step[0])

    def prox(self, z):
        return self.penalty.prox(z, self._step)

    def rowdot(self, a, b):
        return float(a @ b)

    def objective(self, w):
        return self.datafit.value(w) + self.penalty.value(w)

    def kkt(self, w):
        return self.penalty.subdiff_distance(w, self.datafit.gradient(w))

    def lipschitz(self):
        return self.datafit.lipschitz()

    def finish(self, sel, w, it, converged, stop, step, reductions):
        self.result = (w, it, bool(np.all(converged)), float(stop[0]),
                       float(step[0]), int(reductions[0]))  # fmt: skip
