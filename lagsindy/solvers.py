r"""Sparse solvers: FISTA with an L1 penalty, and the paper's staged schedule.

The pieces follow a small duck-typed contract (in the spirit of skglm):

* a **datafit** provides ``value(w)``, ``gradient(w)``, ``lipschitz()``,
  ``restrict(idx)`` and ``relative_residual(w)``;
* a **penalty** provides ``value(w)``, ``prox(w, step)``,
  ``subdiff_distance(w, grad)`` and ``restrict(idx)``;
* :func:`fista` minimises ``datafit + penalty`` and returns a :class:`SolverResult`;
* :func:`staged_fista` runs the xL-SINDy schedule (stage, hard threshold, lower the
  penalty, raise the step) and an optional unpenalised refit on the final support.

For the linear cases (I and III) the datafit is :class:`GramQuadratic`, which works
on :math:`G = A^\top A / n` and :math:`b = A^\top y / n`, so an iteration costs
:math:`O(p^2)` whatever the number of samples.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from sklearn.exceptions import ConvergenceWarning

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


# --------------------------------------------------------------------------- datafits
class GramQuadratic:
    r"""Least squares :math:`\frac{1}{2n}\|y - A w\|^2` from its Gram statistics.

    Parameters
    ----------
    gram : Tensor of shape (p, p)
        :math:`A^\top A / n`.
    rhs : Tensor of shape (p,)
        :math:`A^\top y / n`.
    const : float
        :math:`y^\top y / n`, so that :meth:`value` is the true objective.
    """

    def __init__(self, gram: torch.Tensor, rhs: torch.Tensor, const: float):
        self.gram = gram
        self.rhs = rhs
        self.const = float(const)
        self._lipschitz = None

    @property
    def n_features(self) -> int:
        return self.rhs.shape[0]

    def zeros(self) -> torch.Tensor:
        return torch.zeros_like(self.rhs)

    def value(self, w: torch.Tensor) -> float:
        return float(0.5 * w @ (self.gram @ w) - self.rhs @ w + 0.5 * self.const)

    def gradient(self, w: torch.Tensor) -> torch.Tensor:
        return self.gram @ w - self.rhs

    def lipschitz(self) -> float:
        """Largest eigenvalue of the Gram matrix."""
        if self._lipschitz is None:
            if self.n_features == 0:
                self._lipschitz = 0.0
            else:
                self._lipschitz = float(
                    torch.linalg.eigvalsh(self.gram)[-1].clamp(min=0)
                )
        return self._lipschitz

    def relative_residual(self, w: torch.Tensor) -> float:
        """:math:`\\|y - A w\\|^2 / \\|y\\|^2` (1 for ``w = 0``)."""
        if self.const <= 0:
            return 0.0
        return max(0.0, 2.0 * self.value(w) / self.const)

    def restrict(self, idx) -> GramQuadratic:
        idx = torch.as_tensor(idx, dtype=torch.long, device=self.rhs.device)
        return GramQuadratic(self.gram[idx][:, idx], self.rhs[idx], self.const)

    def least_squares(self, w0=None, rtol: float = 1e-13) -> torch.Tensor:
        """Minimum-norm unpenalised minimiser (eigen-decomposition of the Gram).

        ``w0`` is accepted for symmetry with non-convex datafits and ignored.
        """
        if self.n_features == 0:
            return self.rhs.clone()
        evals, evecs = torch.linalg.eigh(self.gram)
        keep = evals > rtol * evals[-1].clamp(min=1e-300)
        inv = torch.where(
            keep, 1.0 / torch.where(keep, evals, torch.ones_like(evals)), 0.0
        )
        return evecs @ (inv * (evecs.T @ self.rhs))


class AccelerationDatafit:
    r"""Case II datafit: error of the accelerations predicted by the Lagrangian.

    .. math::

        f(w) = \frac{1}{2n} \sum_s \| D^{-1} (\ddot q_s -
        \ddot q_{pred,s}(c)) \|^2, \quad
        \ddot q_{pred} = -\Big(\sum_k c_k M_k\Big)^{+} \sum_k c_k (N_k \dot q - O_k),

    with :math:`c = w / s` (column scales ``s``) and :math:`D` the per-coordinate
    RMS of the measured accelerations (paper eqs. 10-11). The prediction does not
    change when :math:`c` is scaled, so the L1 penalty alone would shrink :math:`c`
    to zero; :meth:`project` fixes the gauge :math:`\|w\|_2 = 1`, on which the L1
    norm is smallest for sparse :math:`w`. No global Lipschitz constant exists
    (``lipschitz()`` is ``None``), so solvers use backtracking.

    Parameters
    ----------
    mass : Tensor of shape (n_samples, p, n_dof, n_dof)
        :math:`M_k` per sample.
    bias : Tensor of shape (n_samples, p, n_dof)
        :math:`N_k \dot q - O_k` per sample.
    qdd : Tensor of shape (n_samples, n_dof)
        Measured accelerations.
    scale : Tensor of shape (p,)
        Column scales ``s``.
    """

    def __init__(self, mass, bias, qdd, scale):
        self.mass, self.bias, self.qdd, self.scale = mass, bias, qdd, scale
        rms = torch.sqrt((qdd**2).mean(dim=0))
        self.acc_scale = torch.where(rms > 0, rms, torch.ones_like(rms))
        self.const = float(((qdd / self.acc_scale) ** 2).sum(dim=1).mean())

    @property
    def n_features(self) -> int:
        return self.scale.shape[0]

    def zeros(self):
        return torch.zeros_like(self.scale)

    def lipschitz(self):
        return None

    def project(self, w):
        norm = torch.linalg.vector_norm(w)
        return w / norm if float(norm) > 0 else w

    def predict(self, w):
        c = w / self.scale
        mc = torch.einsum("skij,k->sij", self.mass, c)
        bc = torch.einsum("ski,k->si", self.bias, c)
        # A direct solve: a singular M(c) gives non-finite values, which the line
        # search rejects (cheaper than a pseudo-inverse and its SVD gradient).
        out, info = torch.linalg.solve_ex(mc, bc)
        if bool((info != 0).any()):
            return torch.full_like(out, math.inf)
        return -out

    def _loss(self, w):
        r = (self.qdd - self.predict(w)) / self.acc_scale
        return 0.5 * (r**2).sum(dim=1).mean()

    def value(self, w) -> float:
        v = float(self._loss(w))
        return v if math.isfinite(v) else math.inf

    def gradient(self, w):
        w = w.detach().requires_grad_(True)
        with torch.enable_grad():
            loss = self._loss(w)
            (grad,) = torch.autograd.grad(loss, w)
        return torch.nan_to_num(grad.detach(), nan=0.0, posinf=0.0, neginf=0.0)

    def relative_residual(self, w) -> float:
        if self.const <= 0:
            return 0.0
        return 2.0 * self.value(w) / self.const

    def restrict(self, idx):
        idx = torch.as_tensor(idx, dtype=torch.long, device=self.scale.device)
        return AccelerationDatafit(
            self.mass[:, idx], self.bias[:, idx], self.qdd, self.scale[idx]
        )

    def least_squares(self, w0=None, max_iter: int = 2000, tol: float = 1e-10):
        """Unpenalised minimiser from ``w0`` (local: the problem is not convex)."""
        res = proximal_gradient(self, L1(0.0), w0, max_iter=max_iter, tol=tol)
        return res.coef


# --------------------------------------------------------------------------- penalty
class L1:
    r"""Weighted L1 penalty :math:`\lambda \sum_k \omega_k |w_k|`.

    Parameters
    ----------
    lam : float
        Penalty strength (the paper's :math:`\lambda`).
    weights : Tensor of shape (p,), optional
        Per-coefficient weights; 0 leaves a coefficient unpenalised (known terms).
    """

    def __init__(
        self,
        lam: float,
        weights: torch.Tensor | None = None,
        nonneg: torch.Tensor | None = None,
    ):
        self.lam = float(lam)
        self.weights = weights
        self.nonneg = nonneg

    def _w(self, like):
        return torch.ones_like(like) if self.weights is None else self.weights

    def value(self, w):
        return float(self.lam * (self._w(w) * w.abs()).sum())

    def prox(self, w, step):
        thresh = step * self.lam * self._w(w)
        out = torch.sign(w) * torch.clamp(w.abs() - thresh, min=0.0)
        if self.nonneg is not None:
            # Projection onto w_k >= 0 (prox of the L1 term plus the indicator).
            out = torch.where(self.nonneg, torch.clamp(out, min=0.0), out)
        return out

    def subdiff_distance(self, w, grad):
        """Largest distance of ``-grad`` to the subdifferential (the KKT violation)."""
        lw = self.lam * self._w(w)
        nonzero = w != 0
        at_zero = torch.clamp(grad.abs() - lw, min=0.0)
        if self.nonneg is not None:
            # at w_k = 0 with w_k >= 0 imposed, any grad_k >= -lw_k is optimal
            at_zero = torch.where(
                self.nonneg, torch.clamp(-grad - lw, min=0.0), at_zero
            )
        dist = torch.where(nonzero, (grad + lw * torch.sign(w)).abs(), at_zero)
        return float(dist.max()) if dist.numel() else 0.0

    def restrict(self, idx):
        if self.weights is None and self.nonneg is None:
            return L1(self.lam)
        like = self.weights if self.weights is not None else self.nonneg
        idx = torch.as_tensor(idx, dtype=torch.long, device=like.device)
        return L1(
            self.lam,
            None if self.weights is None else self.weights[idx],
            None if self.nonneg is None else self.nonneg[idx],
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


# --------------------------------------------------------------------------- stages
@dataclass
class Stage:
    """Record of one stage of :func:`staged_fista` (indices refer to all features)."""

    lam: float
    step: float
    n_iter: int
    converged: bool
    stop_crit: float
    coef: np.ndarray
    support: np.ndarray
    cost: float


@dataclass
class StagedResult:
    """Outcome of :func:`staged_fista`."""

    coef: torch.Tensor
    support: np.ndarray
    stages: list
    n_iter: int
    converged: bool
    cost: float
    step_reductions: int = 0


def staged_fista(
    datafit: GramQuadratic,
    *,
    lam: float,
    penalty_weights: torch.Tensor | None = None,
    threshold: float | torch.Tensor = 0.05,
    reference: float = 0.0,
    lam_decay: float = 10.0,
    step_growth: float = 2.0,
    alpha: float | None = None,
    max_stages: int = 5,
    max_iter: int = 10_000,
    tol: float = 1e-3,
    solver_tol: float = 1e-8,
    debias: bool = True,
    verbose: int = 0,
    w0: torch.Tensor | None = None,
    nonneg: torch.Tensor | None = None,
) -> StagedResult:
    r"""The xL-SINDy schedule: FISTA stages with hard thresholding between them.

    Each stage solves the L1-penalised problem on the current support, then removes
    the penalised coefficients whose magnitude is below
    ``threshold * max(reference, max_k |w_k|)``; the next stage divides ``lam`` by
    ``lam_decay`` and, when ``alpha`` is given, multiplies the step by
    ``step_growth`` (with ``alpha=None`` the step is ``1/L`` of the current,
    smaller problem, which rises by itself as terms leave). The schedule stops when
    the relative residual of the stage's thresholded solution is at most ``tol``,
    or after ``max_stages``. With ``debias=True`` the final support is refitted
    without penalty.

    A stage whose solution is all zero (``lam`` above the largest useful value)
    removes nothing; the schedule then simply lowers ``lam``.

    Parameters
    ----------
    datafit : GramQuadratic
    lam : float
        Penalty of the first stage.
    penalty_weights : Tensor, optional
        0 for unpenalised (known) terms, 1 otherwise.
    threshold : float or Tensor of shape (p,), default=0.05
        Relative hard threshold (one value, or one per feature).
    reference : float, default=0.0
        Magnitude of a fixed term in the same units as ``w`` (1 for case III).
    lam_decay, step_growth : float
    alpha : float, optional
        Initial step; ``None`` means ``1/L`` at every stage.
    max_stages, max_iter : int
    tol : float
        Stage-level tolerance on the relative residual.
    solver_tol : float
        KKT tolerance of each FISTA run.
    debias : bool
    verbose : int
    w0 : Tensor, optional
        Starting point of the first stage (zeros by default).
    nonneg : Tensor of bool, shape (p,), optional
        Coefficients constrained to be non-negative (dissipation), enforced by
        projection in FISTA's proximal step and in the unpenalised refit.

    Returns
    -------
    StagedResult
    """
    p = datafit.n_features
    template = datafit.zeros()
    device = template.device
    weights = torch.ones_like(template) if penalty_weights is None else penalty_weights
    support = np.arange(p)
    thresholds = (
        torch.as_tensor(threshold, dtype=template.dtype, device=device)
        .expand(p)
        .clone()
    )
    w_full = template.clone() if w0 is None else w0.clone()
    if nonneg is not None:
        nonneg = torch.as_tensor(nonneg, dtype=torch.bool, device=device)
        w_full = torch.where(nonneg, torch.clamp(w_full, min=0.0), w_full)
    stages, total_iter, reductions = [], 0, 0
    converged = True
    cur_lam = float(lam)
    cost = datafit.relative_residual(w_full)
    for s in range(max_stages):
        sub = datafit.restrict(support)
        sup_idx = torch.as_tensor(support, device=device)
        pen = L1(cur_lam, weights[sup_idx], None if nonneg is None else nonneg[sup_idx])
        step = None if alpha is None else float(alpha) * step_growth**s
        solver = fista if sub.lipschitz() is not None else proximal_gradient
        res = solver(
            sub,
            pen,
            w_full[torch.as_tensor(support, device=device)],
            step=step,
            max_iter=max_iter,
            tol=solver_tol,
        )
        total_iter += res.n_iter
        reductions += res.step_reductions
        converged = converged and res.converged
        w_sub = res.coef
        mags = w_sub.abs()
        largest = float(mags.max()) if mags.numel() else 0.0
        if largest > 0:  # an all-zero stage (lam too high) removes nothing
            sup_t = torch.as_tensor(support, device=device)
            penalised = weights[sup_t] > 0
            keep = ~((mags < thresholds[sup_t] * max(largest, reference)) & penalised)
        else:
            keep = torch.ones_like(mags, dtype=torch.bool)
        w_sub = torch.where(keep, w_sub, torch.zeros_like(w_sub))
        w_full = template.clone()
        w_full[torch.as_tensor(support, device=device)] = w_sub
        cost = datafit.relative_residual(w_full)
        new_support = support[keep.cpu().numpy()]
        stages.append(
            Stage(
                cur_lam,
                res.step,
                res.n_iter,
                res.converged,
                res.stop_crit,
                w_full.detach().cpu().numpy().copy(),
                new_support.copy(),
                cost,
            )
        )
        if verbose:
            print(
                f"[lagsindy] stage {s + 1}: lam={cur_lam:.3g} step={res.step:.3g} "
                f"iterations={res.n_iter}{'' if res.converged else ' (max_iter)'} "
                f"terms={len(new_support)} relative residual={cost:.3g}"
            )
        support = new_support
        if cost <= tol and float(w_sub.abs().max() if w_sub.numel() else 0.0) > 0:
            break
        cur_lam /= lam_decay
    if debias and len(support):
        w_full, support = _debias(
            datafit, support, weights, thresholds, reference, w_full, nonneg
        )
        cost = datafit.relative_residual(w_full)
    return StagedResult(
        w_full, support, stages, total_iter, converged, cost, reductions
    )


def _debias(datafit, support, weights, thresholds, reference, w_start, nonneg=None):
    """Unpenalised refit of the support, thresholding the refit until it is stable.

    The L1 stages shrink coefficients, so a term that the penalty kept alive only
    to stand in for a shrunk one can look large before the refit and negligible
    after it; it is removed and the rest refitted (at most ``len(support)`` times).
    Coefficients in ``nonneg`` stay non-negative: where the unconstrained refit
    makes one negative, the refit is the non-negative least-squares solution
    (projected FISTA with no penalty).
    """
    device = datafit.zeros().device
    while True:
        idx = torch.as_tensor(support, device=device)
        sub = datafit.restrict(support)
        w_ls = sub.least_squares(w0=w_start[idx])
        if nonneg is not None and bool((nonneg[idx] & (w_ls < 0)).any()):
            start = torch.where(nonneg[idx], torch.clamp(w_ls, min=0.0), w_ls)
            w_ls = fista(
                sub, L1(0.0, None, nonneg[idx]), start, max_iter=50_000, tol=1e-12
            ).coef
        mags = w_ls.abs()
        peak = max(float(mags.max()), reference) if mags.numel() else 0.0
        drop = (mags < thresholds[idx] * peak) & (weights[idx] > 0)
        if not bool(drop.any()) or bool(drop.all()):
            break
        support = support[~drop.cpu().numpy()]
    w_full = datafit.zeros()
    w_full[idx] = w_ls
    return w_full, support


def fista_path(datafit, lams, *, penalty_weights=None, max_iter=10_000, tol=1e-8):
    """Solutions of the L1 problem along decreasing ``lams``, warm-started.

    Returns
    -------
    coefs : ndarray of shape (len(lams), p)
    n_iters : list of int
    """
    w = datafit.zeros()
    coefs, n_iters = [], []
    for lam in lams:
        res = fista(datafit, L1(lam, penalty_weights), w, max_iter=max_iter, tol=tol)
        w = res.coef
        coefs.append(w.detach().cpu().numpy().copy())
        n_iters.append(res.n_iter)
    return np.array(coefs), n_iters


def warn_not_converged(stages, max_iter):
    """Emit one ConvergenceWarning listing the stages that hit ``max_iter``."""
    bad = [i + 1 for i, st in enumerate(stages) if not st.converged]
    if bad:
        warnings.warn(
            f"FISTA reached max_iter={max_iter} before its KKT tolerance in stage(s) "
            f"{bad}; the support may be wrong. Increase max_iter, or raise "
            "solver_tol if the residual cost is already small.",
            ConvergenceWarning,
            stacklevel=3,
        )


# --------------------------------------------------------------------------- scaling
# The alternating row/column scaling converges linearly (about 100-150 iterations to
# rtol 1e-10 on the paper's systems); the fit is invariant to units only at its fixed
# point, so the cap must not cut it short (100 did, shifting noisy fits by ~1e-7).
_BALANCE_MAX_ITER = 2000


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
    """

    def __init__(
        self,
        gram: torch.Tensor,
        n_samples: int,
        n_features: int,
        normalize: bool = True,
        project_psd: bool = False,
    ):
        self.n_features = int(n_features)
        n_dof = gram.shape[0]
        mean_sq = torch.diagonal(gram, dim1=1, dim2=2)[:, : self.n_features] / n_samples
        mean_sq = torch.clamp(mean_sq, min=0)
        rows = torch.ones(n_dof, dtype=gram.dtype, device=gram.device)
        if normalize and self.n_features:
            for _ in range(_BALANCE_MAX_ITER):
                cols = torch.sqrt((mean_sq / rows[:, None] ** 2).mean(dim=0))
                active = cols > 0
                if not bool(active.any()):
                    break
                ratio = mean_sq[:, active] / cols[active] ** 2
                new_rows = torch.sqrt(ratio.mean(dim=1))
                new_rows = torch.where(
                    new_rows > 0, new_rows, torch.ones_like(new_rows)
                )
                new_rows = new_rows / torch.exp(torch.log(new_rows).mean())
                if torch.allclose(new_rows, rows, rtol=1e-10, atol=0):
                    rows = new_rows
                    break
                rows = new_rows
        self.row_scale = rows
        weights = 1.0 / rows**2
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

    def identifiable(self) -> torch.Tensor:
        """Boolean mask of candidate columns that are not identically zero on the data."""
        big = float(self.col_scale.max()) if self.col_scale.numel() else 0.0
        return self.col_scale > 1e-12 * max(big, 1e-300)

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
        free_t = torch.as_tensor(free, dtype=torch.long, device=self.gram.device)
        y_scale = self.target_scale(target)
        if y_scale <= 0:
            raise ValueError("the target is identically zero on the data")
        s = self.col_scale[free_t]
        s_safe = torch.where(s > 0, s, torch.ones_like(s))
        g = self.gram[free_t][:, free_t] / (s_safe[:, None] * s_safe[None, :])
        b = sign * self.gram[free_t, target] / (s_safe * y_scale)
        datafit = GramQuadratic(g, b, 1.0)

        def to_coef(w):
            return w * y_scale / s_safe

        return datafit, to_coef
