"""FISTA and plain proximal gradient, with the duck-typed datafit/penalty contract."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .datafits import GramQuadratic
from .penalties import L1

_REQUIRED = {
    "datafit": (
        "value",
        "gradient",
        "lipschitz",
        "restrict",
        "relative_residual",
        "zeros",
    ),
    "penalty": ("value", "prox", "subdiff_distance", "restrict"),
}


def _check_contract(obj, role, solver):
    missing = [m for m in _REQUIRED[role] if not callable(getattr(obj, m, None))]
    if missing:
        raise AttributeError(
            f"{solver} needs a {role} with methods {list(_REQUIRED[role])}; "
            f"{type(obj).__name__} lacks {missing}"
        )


# --------------------------------------------------------------------------- FISTA
@dataclass
class SolverResult:
    """Outcome of :func:`fista`."""

    coef: torch.Tensor
    n_iter: int
    converged: bool
    stop_crit: float
    step: float
    objective: list = field(default_factory=list)
    step_reductions: int = 0


def fista(
    datafit,
    penalty,
    w0: torch.Tensor | None = None,
    *,
    step: float | None = None,
    max_iter: int = 10_000,
    tol: float = 1e-8,
    check_every: int = 10,
    restart: bool = True,
    max_step_reductions: int = 40,
) -> SolverResult:
    r"""Accelerated proximal gradient (FISTA) for ``datafit(w) + penalty(w)``.

    The momentum is the paper's (eq. 18),
    :math:`v = w^{i-1} + \frac{i-2}{i+1}(w^{i-1} - w^{i-2})`, followed by
    :math:`w^i = \mathrm{prox}(v - \alpha \nabla f(v))`, with the gradient-based
    adaptive restart of O'Donoghue and Candes (momentum is reset when it points
    uphill), which keeps FISTA's rate and removes its oscillations.

    Parameters
    ----------
    datafit, penalty
        Objects following the contracts in this module.
    w0 : Tensor, optional
        Starting point (zeros by default).
    step : float, optional
        Step size :math:`\alpha`. ``None``: ``1 / datafit.lipschitz()``.
    max_iter : int, default=10000
    tol : float, default=1e-8
        Stop when the KKT violation (distance of ``-grad`` to the subdifferential
        of the penalty) is below ``tol``.
    check_every : int, default=10
        Iterations between KKT and objective checks.
    restart : bool, default=True
        Use adaptive restart.
    max_step_reductions : int, default=40
        Divergence guard: when the objective grows or turns non-finite at two
        consecutive checks, the step is halved and the iterate reset to the best
        so far, at most this many times. A given ``step`` above ``2 / L`` (where
        the datafit has a Lipschitz constant ``L``) is first halved below it, since
        such a step diverges along the top eigenvector.

    Returns
    -------
    SolverResult

    References
    ----------
    A. Beck and M. Teboulle, "A fast iterative shrinkage-thresholding algorithm for
    linear inverse problems", SIAM J. Imaging Sci. 2(1), 2009.
    B. O'Donoghue and E. Candes, "Adaptive restart for accelerated gradient
    schemes", Found. Comput. Math. 15, 2015.
    """
    _check_contract(datafit, "datafit", "fista")
    _check_contract(penalty, "penalty", "fista")
    p = datafit.n_features
    w = datafit.zeros() if w0 is None else w0.clone()
    if p == 0:
        return SolverResult(w, 0, True, 0.0, 0.0)
    lip = datafit.lipschitz()
    like = w
    numpy_loop = _numpy_problem(datafit, penalty, w)
    if numpy_loop is not None:
        # Small CPU problems: the same iterations on NumPy arrays, whose per-call
        # overhead is several times lower than torch's (the loop is overhead-bound).
        datafit, penalty, w = numpy_loop
    # Divergence shows as inf/nan objectives, handled below: no NumPy warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        res = _fista_loop(
            datafit,
            penalty,
            w,
            step,
            lip,
            max_iter,
            tol,
            check_every,
            restart,
            max_step_reductions,
        )
    res.coef = _back(res.coef, like)
    return res


def _fista_loop(
    datafit,
    penalty,
    w,
    step,
    lip,
    max_iter,
    tol,
    check_every,
    restart,
    max_step_reductions,
):
    """The iterations of :func:`fista` (on tensors or NumPy arrays)."""
    copy = _copy
    reductions = 0
    if step is None:
        step = 1.0 / lip if lip > 0 else 1.0
    step = float(step)
    if lip is not None and lip > 0 and math.log2(step) + math.log2(lip) > 1.0:
        # A step above 2/L diverges along the top eigenvector whatever the momentum:
        # halve it below 2/L at once instead of discovering it by iterating.
        n_halvings = math.ceil(math.log2(step) + math.log2(lip) - 1.0)
        step = step / 2.0**n_halvings
        reductions += n_halvings
    w_prev = copy(w)
    best_w, best_obj = copy(w), datafit.value(w) + penalty.value(w)
    history = [best_obj]
    k = 1
    rises = 0
    guard = 0
    stop = math.inf
    n_iter = 0
    for it in range(1, max_iter + 1):
        n_iter = it
        beta = (k - 2) / (k + 1) if k > 1 else 0.0
        v = w + beta * (w - w_prev)
        w_new = penalty.prox(v - step * datafit.gradient(v), step)
        if restart and float((v - w_new) @ (w_new - w)) > 0:
            k = 1  # momentum points uphill: restart
        else:
            k += 1
        w_prev, w = w, w_new
        if it % check_every == 0 or it == max_iter:
            obj = datafit.value(w) + penalty.value(w)
            history.append(obj)
            if not math.isfinite(obj) or obj > best_obj + 1e-10 * max(
                1.0, abs(best_obj)
            ):
                rises += 1
                if not math.isfinite(obj) or rises >= 2:
                    if guard >= max_step_reductions:
                        raise FloatingPointError(
                            "FISTA diverged: the objective kept growing after the step "
                            f"was halved {guard} times (step now {step:.3g}); use a "
                            "smaller step (alpha) or alpha=None"
                        )
                    step *= 0.5
                    guard += 1
                    reductions += 1
                    w, w_prev, k, rises = copy(best_w), copy(best_w), 1, 0
                    continue
            else:
                rises = 0
                if obj <= best_obj:
                    best_obj, best_w = obj, copy(w)
            stop = penalty.subdiff_distance(w, datafit.gradient(w))
            if stop <= tol:
                return SolverResult(w, it, True, stop, step, history, reductions)
    return SolverResult(w, n_iter, False, stop, step, history, reductions)


def _copy(x):
    return x.copy() if isinstance(x, np.ndarray) else x.clone()


def _back(w, like: torch.Tensor) -> torch.Tensor:
    """``w`` as a tensor like ``like`` (a no-op for tensors)."""
    if isinstance(w, np.ndarray):
        return torch.from_numpy(w).to(dtype=like.dtype, device=like.device)
    return w


class _NumpyQuadratic:
    """:class:`GramQuadratic` on NumPy arrays (value and gradient only)."""

    def __init__(self, gram, rhs, const):
        self.gram, self.rhs, self.const = gram, rhs, const

    def value(self, w):
        return float(0.5 * w @ (self.gram @ w) - self.rhs @ w + 0.5 * self.const)

    def gradient(self, w):
        return self.gram @ w - self.rhs


class _NumpyL1:
    """:class:`L1` on NumPy arrays (value, prox and KKT distance only)."""

    def __init__(self, lam, weights, nonneg):
        self.lam, self.weights, self.nonneg = lam, weights, nonneg

    def value(self, w):
        return float(self.lam * (self.weights * np.abs(w)).sum())

    def prox(self, w, step):
        out = np.sign(w) * np.maximum(np.abs(w) - step * self.lam * self.weights, 0.0)
        if self.nonneg is not None:
            out = np.where(self.nonneg, np.maximum(out, 0.0), out)
        return out

    def subdiff_distance(self, w, grad):
        lw = self.lam * self.weights
        at_zero = np.maximum(np.abs(grad) - lw, 0.0)
        if self.nonneg is not None:
            at_zero = np.where(self.nonneg, np.maximum(-grad - lw, 0.0), at_zero)
        dist = np.where(w != 0, np.abs(grad + lw * np.sign(w)), at_zero)
        return float(dist.max()) if dist.size else 0.0


def _numpy_problem(datafit, penalty, w):
    """NumPy copies of a CPU :class:`GramQuadratic` and :class:`L1`, else ``None``."""
    if (
        type(datafit) is not GramQuadratic
        or type(penalty) is not L1
        or w.device.type != "cpu"
        or w.dtype not in (torch.float32, torch.float64)
    ):
        return None

    def arr(t):
        return t.detach().cpu().numpy().copy()

    weights = (
        np.ones(w.shape[0], dtype=arr(w).dtype)
        if penalty.weights is None
        else arr(penalty.weights)
    )
    nonneg = None if penalty.nonneg is None else arr(penalty.nonneg).astype(bool)
    return (
        _NumpyQuadratic(arr(datafit.gram), arr(datafit.rhs), datafit.const),
        _NumpyL1(penalty.lam, weights, nonneg),
        arr(w),
    )


def proximal_gradient(
    datafit,
    penalty,
    w0: torch.Tensor | None = None,
    *,
    step: float | None = None,
    max_iter: int = 10_000,
    tol: float = 1e-8,
    max_backtracks: int = 60,
) -> SolverResult:
    r"""Monotone proximal gradient with backtracking, for non-convex datafits.

    Used when the datafit has no global Lipschitz constant (``lipschitz()`` returns
    ``None``), as in case II. Each step ``w+ = P(prox(w - a grad f(w)))`` is accepted
    when ``F(w+) <= F(w) - ||w+ - w||^2 / (2a)`` (sufficient decrease), otherwise the
    step ``a`` is halved; an accepted step lets the next try a larger one. ``P`` is the
    datafit's ``project`` (the gauge of a scale-invariant datafit), if it has one.
    Stops when the relative change of ``w`` falls below ``tol``.
    """
    project = getattr(datafit, "project", lambda w: w)
    w = project(datafit.zeros() if w0 is None else w0.clone())
    step = 1.0 if step is None else float(step)
    obj = datafit.value(w) + penalty.value(w)
    if not math.isfinite(obj):
        raise FloatingPointError(
            "the objective is not finite at the starting point (a scale-invariant "
            "datafit such as case II's is undefined where the mass matrix is singular)"
        )
    history = [obj]
    reductions = 0
    change = math.inf
    n_iter = 0
    for it in range(1, max_iter + 1):
        n_iter = it
        grad = datafit.gradient(w)
        for _ in range(max_backtracks):
            w_new = project(penalty.prox(w - step * grad, step))
            obj_new = datafit.value(w_new) + penalty.value(w_new)
            decrease = float(((w_new - w) ** 2).sum()) / (2 * step)
            if math.isfinite(obj_new) and obj_new <= obj - 0.5 * decrease + 1e-15 * abs(
                obj
            ):
                break
            step *= 0.5
            reductions += 1
        else:
            return SolverResult(w, it, False, change, step, history, reductions)
        change = float((w_new - w).abs().max()) / max(float(w.abs().max()), 1e-300)
        w, obj = w_new, obj_new
        history.append(obj)
        step *= 1.5
        if change <= tol:
            return SolverResult(w, it, True, change, step, history, reductions)
    return SolverResult(w, n_iter, False, change, step, history, reductions)
