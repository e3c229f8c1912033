"""Refine a fitted model's coefficients by the error of its rollouts.

A sparse fit minimises the residual of the Euler-Lagrange equations at the samples
(equation error). Its coefficients carry the errors of the estimated derivatives and
of every effect the model leaves out, and small coefficient errors grow along a
simulated trajectory. :func:`refine` keeps the structure the fit chose and adjusts its
nonzero coefficients so that the model, integrated from the measured state at the
start of many short windows, follows the measured positions (output error, or
multiple shooting with the initial states held at their estimates).

The integration is a fixed-step classical Runge-Kutta scheme on the sample grid
(``substeps`` steps per sample), evaluated for all windows and all finite-difference
perturbations of the coefficients at once, so one Gauss-Newton iteration costs one
batched integration. Passive data fix a Lagrangian only up to a factor: one
coefficient (the fit's fixed term, else the largest) is held, the others move.
Dissipative coefficients (viscous, relative, drag, Coulomb) keep the kinetic
energy's sign (non-negative in the fit's scale); a bias or custom force is signed.
A robot's refined coefficients (a URDF library with ``consistent=True``) are made
physically consistent by the fit's own constrained refit, on the rollouts'
Gauss-Newton model (``BaseParameterLibrary.consistent_refit``).
"""

from __future__ import annotations

import dataclasses
import warnings
from numbers import Integral

import numpy as np
import torch
from scipy import sparse
from scipy.optimize import least_squares
from sklearn.exceptions import ConvergenceWarning
from sklearn.utils.validation import check_is_fitted

from . import _validation as val
from . import pipeline
from ._torch import resolve_dtype
from .evaluator import TermEvaluator, subset_terms
from .formulation.weak import (
    estimate_sampling_interval,
    position_jumps,
    trajectory_segments,
)

# A coefficient that moves by more than this (relative) is reported: the equation
# error and the rollouts then disagree about the model, which a missing effect or
# biased derivatives explain more often than the refinement's own error.
LARGE_CHANGE = 0.2
# The rollout error must exceed the integrator's own error (estimated by halving the
# step) by this factor, else the refinement would fit the discretisation.
INTEGRATOR_MARGIN = 10.0
# ...unless it is below this fraction of the positions' spread (an exact model on
# noise-free data, where the integrator's error is all that is left and harmless).
NEGLIGIBLE_ERROR = 1e-5
# Residual of a window whose integration failed (singular mass matrix, overflow),
# in units of each coordinate's spread: large and finite, so the solver backs off.
FAILED_RESIDUAL = 10.0


@dataclasses.dataclass
class Refinement:
    """What :func:`refine` did (``est.refinement_``).

    Attributes
    ----------
    horizon, stride, substeps : int
        Window length and spacing in samples; integration steps per sample.
    n_windows : int
    rmse_before, rmse_after : float
        Weighted root mean square of the position errors over the windows' samples
        (in the data's units with the default equal weights).
    n_iter : int
        Batched integrations (each gives the residuals and their Jacobian).
    converged : bool
    held : str or None
        The term held fixed (passive models), else ``None``.
    changes : dict
        Relative change of every refined coefficient, by feature name.
    integrator_error : float
        Estimated error of the fixed-step integration of the refined model, in the
        units of ``rmse_after``.
    """

    horizon: int
    stride: int
    substeps: int
    n_windows: int
    rmse_before: float
    rmse_after: float
    n_iter: int
    converged: bool
    held: str | None
    changes: dict
    integrator_error: float

    def __str__(self) -> str:
        worst = max(self.changes.items(), key=lambda kv: abs(kv[1]), default=None)
        move = f"; largest change {worst[0]} {100 * worst[1]:+.1f} %" if worst else ""
        return (
            f"rollout refinement over {self.n_windows} windows of {self.horizon} "
            f"samples: RMSE {self.rmse_before:.4g} -> {self.rmse_after:.4g} "
            f"({self.n_iter} integrations){move}"
        )


def _Dynamics(coordinates, terms, forces):  # was a class; its callers keep the name
    """Per-term Euler-Lagrange parts as one numpy function of the state.

    The evaluator's NumPy path (:meth:`lagsindy.evaluator.TermEvaluator.numpy_parts`,
    compiled once per term set): ``parts(q, qd)`` gives, for Lagrangian terms,
    ``M_k = d2 phi_k / dqd2`` and ``h_k = (d2 phi_k / dqd dq) qd - d phi_k / dq``,
    for force terms ``M_k = 0`` and ``h_k = -Q_k``, so that the model
    ``sum_k c_k phi_k`` has ``M(c) qdd + h(c) = tau``.
    """
    return TermEvaluator(coordinates, terms, forces).numpy_parts()


class _Rollouts:
    """Fixed-step Runge-Kutta integration of many windows and parameter sets."""

    def __init__(self, dynamics, tau_nodes, horizon, dt, substeps):
        self.dyn, self.d = dynamics, dynamics.n_dof
        self.tau_nodes = tau_nodes  # (B, horizon + 1, d) or None
        self.horizon, self.substeps = horizon, substeps
        self.h = dt / substeps

    def _acc(self, q, qd, coef_rows, tau):
        mass, rest = self.dyn.parts(q, qd)
        n_lag = self.dyn.n_lagrangian
        mc = np.einsum("skij,sk->sij", mass, coef_rows[:, :n_lag])
        h = np.einsum("ski,sk->si", rest, coef_rows)
        rhs = -h if tau is None else tau - h
        with np.errstate(all="ignore"):
            try:
                return np.linalg.solve(mc, rhs[..., None])[..., 0]
            except np.linalg.LinAlgError:  # a singular matrix: solve row by row
                out = np.full_like(rhs, np.nan)
                for i in range(rhs.shape[0]):
                    try:
                        out[i] = np.linalg.solve(mc[i], rhs[i])
                    except np.linalg.LinAlgError:
                        pass
                return out

    def _tau(self, k, frac, repeats):
        if self.tau_nodes is None:
            return None
        a, b = self.tau_nodes[:, k], self.tau_nodes[:, min(k + 1, self.horizon)]
        return np.tile((1 - frac) * a + frac * b, (repeats, 1))

    def positions(self, coefs, states):
        """Positions ``(P, B, horizon + 1, d)``.

        ``coefs`` (P, K): one coefficient vector per set; ``states`` (P, B, 2 d):
        each set's initial state of every window.
        """
        P, B, _ = states.shape
        d = self.d
        rows = np.repeat(coefs, B, axis=0)  # (P * B, K)
        q = states[..., :d].reshape(P * B, d)
        qd = states[..., d:].reshape(P * B, d)
        out = np.empty((self.horizon + 1, P * B, d))
        out[0] = q
        h, n = self.h, self.substeps
        for k in range(self.horizon):
            for j in range(n):
                t0, t1, t2 = (
                    self._tau(k, j / n, P),
                    self._tau(k, (j + 0.5) / n, P),
                    self._tau(k, (j + 1) / n, P),
                )
                a1 = self._acc(q, qd, rows, t0)
                v2 = qd + 0.5 * h * a1
                a2 = self._acc(q + 0.5 * h * qd, v2, rows, t1)
                v3 = qd + 0.5 * h * a2
                a3 = self._acc(q + 0.5 * h * v2, v3, rows, t1)
                v4 = qd + h * a3
                a4 = self._acc(q + h * v3, v4, rows, t2)
                q = q + h / 6 * (qd + 2 * v2 + 2 * v3 + v4)
                qd = qd + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            out[k + 1] = q
        return out.transpose(1, 0, 2).reshape(P, B, self.horizon + 1, d)


def large_changes(changes: dict) -> dict:
    """The coefficients of ``changes`` (relative, by name) that moved by more than
    ``LARGE_CHANGE``: what :func:`refine` warns about."""
    return {k: v for k, v in changes.items() if abs(v) > LARGE_CHANGE}


def integration_too_coarse(integrator_error, rmse_after, spread) -> bool:
    """Whether :func:`refine` warns that its fixed-step integration is too coarse:
    its error is not ``INTEGRATOR_MARGIN`` times below the rollout error, and not
    negligible (``NEGLIGIBLE_ERROR`` of the positions' ``spread``)."""
    return bool(
        integrator_error * INTEGRATOR_MARGIN > rmse_after
        and integrator_error > NEGLIGIBLE_ERROR * spread
    )


def _scale(weights, q):
    """Divisor of each coordinate's position error."""
    d = q.shape[1]
    if weights is None:
        return np.ones(d)
    if isinstance(weights, str):
        if weights != "std":
            raise ValueError(
                f'weights must be None, "std" or {d} numbers, got {weights!r}'
            )
        spread = q.std(axis=0)
        return np.where(spread > 0, spread, 1.0)
    w = np.asarray(weights, dtype=float)
    if w.shape != (d,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"weights must be {d} positive numbers, got {weights!r}")
    return 1.0 / w


def _windows(segments, horizon, stride):
    starts = []
    for seg in segments:
        seg = np.asarray(seg)
        if seg.size < horizon + 1:
            continue
        for s in range(0, seg.size - horizon, stride):
            starts.append(seg[s : s + horizon + 1])
    return starts


def _split_at_gaps(segments, t, dt):
    out = []
    for seg in segments:
        seg = np.asarray(seg)
        steps = np.diff(t[seg])
        if np.any(steps <= 0):
            raise ValueError("t must increase within each trajectory (group)")
        cuts = np.flatnonzero(np.abs(steps - dt) > 0.01 * dt) + 1
        out.extend(p for p in np.split(seg, cuts) if p.size)
    return out


def refine(
    est,
    X,
    tau=None,
    *,
    groups=None,
    t=None,
    horizon=100,
    stride=None,
    weights=None,
    initial_states="fit",
    substeps=1,
    max_iter=30,
    tol=1e-6,
    verbose=0,
):
    r"""Adjust a fitted model's coefficients to the error of its rollouts.

    The learned structure is kept; its nonzero coefficients are moved so that the
    model, integrated from the measured state at the start of each window of
    ``horizon`` samples, follows the measured positions (least squares over every
    window and sample, each coordinate in units of its standard deviation over the
    data; Gauss-Newton with a trust region, :func:`scipy.optimize.least_squares`).
    This is the output-error (simulation-error) refinement of system identification:
    the sparse fit gives the structure and a start near the optimum, the refinement
    removes the bias that derivative errors and smoothing leave in equation-error
    coefficients, as seen from what users do with a model (simulate it).

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator (not changed: a refined copy is returned).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        The states ``[q, q_dot, q_ddot]`` (the accelerations are not used), sampled
        uniformly within each trajectory; usually the data of the fit.
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces at the rows of ``X``; required when the model was fitted
        with forces (case I), linearly interpolated between samples.
    groups : array-like of shape (n_samples,), default=None
        Trajectory label of each row. Without it, trajectories are split where the
        positions jump (as in the fit).
    t : array-like of shape (n_samples,), default=None
        Sample times. With it, windows never span a gap (a step that differs from the
        sampling interval by more than 1 %). Without it, the sampling interval is the
        fit's ``dt_`` (or estimated from ``q`` and ``q_dot``). For a model fitted
        with time stamps (``fit(X, tau, t=clock)``), pass the same ``t``: the rows
        are then refined as that fit used them, on its even clock (without it,
        ``refine`` refuses the model).
    horizon : int, default=100
        Window length in samples. Long windows weigh slow drifts (energy, phase)
        but make the problem less convex for fast or chaotic motion.
    stride : int, default=None
        Samples between window starts; ``None``: ``horizon // 2``.
    weights : None, "std" or array-like of shape (n_dof,), default=None
        Weight of each coordinate's position error. ``None``: equal, in the data's
        units (the RMS rollout error of :func:`lagsindy.rollout_error`); ``"std"``:
        each coordinate in units of its standard deviation over the data (for
        coordinates of different units and very different spreads).
    initial_states : {"fit", "data"}, default="fit"
        ``"fit"``: each window's initial positions and velocities are estimated with
        the coefficients (multiple shooting); ``"data"``: they are held at the
        estimated states of ``X``. Held states carry the errors of estimated
        velocities (largest at the ends of a trajectory) into every rollout, and
        the coefficients then absorb them: on a simulated cart-pendulum with
        position noise 1e-2 the largest coefficient error went from 1.2 % (the
        sparse fit) to 14 % with held states, and to 0.6 % with fitted ones.
    substeps : int, default=1
        Runge-Kutta steps per sample. A warning says when the integration error
        (estimated with twice the steps) is not small against the rollout error.
    max_iter : int, default=30
        Most batched integrations.
    tol : float, default=1e-6
        Relative tolerance on the cost and the coefficients.
    verbose : int, default=0

    Returns
    -------
    LagrangianSINDy
        A copy of ``est`` with the refined coefficients (``coef_``,
        ``dissipation_coef_``, ``model_``...) and ``refinement_``
        (:class:`Refinement`: windows, RMSE before and after, changes).

    Warns
    -----
    ConvergenceWarning
        When ``max_iter`` integrations end before the tolerance is met.
    UserWarning
        When a coefficient moves by more than 20 % (the rollouts and the equation
        error disagree: often a missing effect, see :func:`lagsindy.diagnose`), or
        when the fixed-step integration is too coarse for the sampling.

    Notes
    -----
    With ``initial_states="fit"`` each window adds ``2 n_dof`` unknowns; their
    Jacobian is block-diagonal and every window's start is perturbed in the same
    integration, so an iteration still costs one batched integration (of
    ``1 + n_coefficients + 2 n_dof`` parameter sets). Rollouts of chaotic motion
    diverge from the data whatever the model; keep ``horizon`` within the time over
    which a good model tracks. A model refined with held states
    (``initial_states="data"``) predicts better from states estimated the same way
    (the same smoothing, the same end effects), at the cost of coefficients that
    absorb those estimates' errors.

    Examples
    --------
    >>> refined = lagsindy.refine(est, X, groups=groups)      # doctest: +SKIP
    >>> print(refined.refinement_)                            # doctest: +SKIP
    """
    check_is_fitted(est)
    if getattr(est, "clock_", None) is not None:
        # a fit given time stamps: refine its rows on its even clock (the rollouts
        # step at one interval); without the stamps, a refusal
        est, X, tau, groups = pipeline.on_fit_clock(
            est, X, tau, groups, t, what="refine", even=True
        )
        t = None
    for name, value, low in (
        ("horizon", horizon, 2),
        ("substeps", substeps, 1),
        ("max_iter", max_iter, 1),
    ):
        if not (isinstance(value, Integral) and value >= low):
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if initial_states not in ("fit", "data"):
        raise ValueError(
            f'initial_states must be "fit" or "data", got {initial_states!r}'
        )
    stride = horizon // 2 if stride is None else stride
    if not (isinstance(stride, Integral) and stride >= 1):
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    fitted = est.fitted_
    if not np.any(fitted.all_coef()):
        raise ValueError("the learned model is zero: nothing to refine")
    forced = fitted.case == "forces"
    if forced and tau is None:
        raise ValueError(
            "the model was fitted with forces (case I): pass the forces tau of X"
        )
    if not forced and tau is not None:
        raise ValueError(
            "the model was fitted without forces (passive): refine it without tau"
        )
    Xa, tau_a, _ = val.validate_state(
        est, X, reset=False, y=tau, coordinates=est.coordinates_
    )
    dtype = resolve_dtype(est.dtype)
    d = fitted.n_dof
    Xt = torch.as_tensor(np.array(Xa), dtype=dtype)
    segments = [s.numpy() for s in trajectory_segments(Xt, d, groups, fitted.dt)]
    if t is not None:
        t = np.asarray(t, dtype=float).ravel()
        if t.shape != (Xa.shape[0],):
            raise ValueError(f"t must have one time per row of X ({Xa.shape[0]})")
        steps = np.concatenate([np.diff(t[s]) for s in segments if s.size > 1])
        dt = float(np.median(steps))
        segments = _split_at_gaps(segments, t, dt)
    else:
        dt = (
            float(fitted.dt)
            if fitted.dt is not None
            else estimate_sampling_interval(
                Xt, d, [torch.as_tensor(s) for s in segments]
            )
        )
        # no times: split where the positions jump against the velocities (gaps)
        segments = [
            part
            for seg in segments
            if seg.size > 2
            for part in np.split(
                seg,
                np.flatnonzero(position_jumps(Xt[seg, :d], Xt[seg, d : 2 * d], dt).numpy()) + 1,
            )
            if part.size
        ]
    wins = _windows(segments, horizon, stride)
    if not wins:
        raise ValueError(
            f"no trajectory has {horizon + 1} samples without a gap: lower horizon"
        )
    idx = np.stack(wins)  # (B, horizon + 1)
    all_coef = fitted.all_coef()
    support = np.flatnonzero(all_coef)
    names = [str(n) for n in fitted.feature_names[support]]
    n_lag = int(np.count_nonzero(fitted.coef))
    p_lag = fitted.coef.size
    dynamics = _Dynamics(
        fitted.coordinates,
        subset_terms(fitted.terms, support[:n_lag]),
        [fitted.dissipation_terms[k - p_lag].forces for k in support[n_lag:]],
    )
    c0 = all_coef[support].astype(float)

    held = None
    free = np.arange(support.size)
    if not forced:
        lag_names = names[:n_lag]
        k = (
            lag_names.index(fitted.fixed_term)
            if fitted.fixed_term in lag_names
            else int(np.argmax(np.abs(c0[:n_lag])))
        )
        held = names[k]
        free = np.delete(free, k)
    for name in getattr(fitted.library, "known_terms_", None) or {}:
        if forced and name in names:  # a known term (a robot's URDF model): held
            held, free = name, free[free != names.index(name)]
    if free.size == 0:
        raise ValueError("the model has a single term: nothing to refine")

    x0 = Xa[idx[:, 0], : 2 * d]  # (B, 2d): the estimated states at the starts
    B = x0.shape[0]
    measured = Xa[idx, :d]  # (B, horizon + 1, d)
    scale = _scale(weights, Xa[:, :d])
    spread = float(
        np.sqrt(np.mean((Xa[:, :d] - Xa[:, :d].mean(axis=0)) ** 2 / scale**2))
    )
    tau_nodes = None
    if forced:
        tau_nodes = np.asarray(tau_a, dtype=float)[idx]
    sim = _Rollouts(dynamics, tau_nodes, horizon, dt, substeps)
    fit_states = initial_states == "fit"
    first = 0 if fit_states else 1  # a fitted start is compared with its sample too
    n_res = measured[:, first:].size
    per_window = measured[0, first:].size

    def residuals(positions):
        diff = (positions[..., first:, :] - measured[None, :, first:]) / scale
        diff = np.where(np.isfinite(diff), diff, FAILED_RESIDUAL)
        return diff.reshape(positions.shape[0], -1) / np.sqrt(n_res)

    nf, ns = free.size, 2 * d if fit_states else 0
    state_spread = Xa[:, : 2 * d].std(axis=0)
    state_spread = np.where(state_spread > 0, state_spread, 1.0)
    steps_c = 1e-6 * np.maximum(np.abs(c0[free]), 1e-3 * np.abs(c0).max())
    steps_s = 1e-6 * state_spread[:ns]
    # Jacobian layout: the coefficients' dense block, then each window's own state
    # block (its residuals depend on its start only), all perturbed at once.
    rows_s = (
        np.arange(B)[:, None, None] * per_window
        + np.arange(per_window)[None, :, None]
        + 0 * np.arange(ns)[None, None, :]
    )
    cols_s = nf + np.arange(B)[:, None, None] * ns + np.arange(ns)[None, None, :]
    cols_s = np.broadcast_to(cols_s, rows_s.shape)
    cache = {}

    def unpack(x):
        coef = c0.copy()
        coef[free] = x[:nf]
        states = x0 + (x[nf:].reshape(B, ns) if fit_states else 0.0)
        return coef, states

    def evaluate(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            coef, states = unpack(x)
            coefs = np.repeat(coef[None], 1 + nf + ns, axis=0)
            coefs[np.arange(1, nf + 1), free] += steps_c
            sets = np.repeat(states[None], 1 + nf + ns, axis=0)
            for j in range(ns):
                sets[1 + nf + j, :, j] += steps_s[j]
            pos = sim.positions(coefs, sets)
            r = residuals(pos)
            failed.append(not np.all(np.isfinite(pos[0])))
            dense = ((r[1 : nf + 1] - r[0]) / steps_c[:, None]).T  # (n_res, nf)
            if ns:
                blocks = (r[nf + 1 :] - r[0]) / steps_s[:, None]  # (ns, n_res)
                values = blocks.T.reshape(B, per_window, ns)
                jac = sparse.hstack(
                    [
                        sparse.csr_matrix(dense),
                        sparse.csr_matrix(
                            (values.ravel(), (rows_s.ravel(), (cols_s - nf).ravel())),
                            shape=(n_res, B * ns),
                        ),
                    ],
                    format="csr",
                )
            else:
                jac = dense
            cache[key] = (r[0], jac)
            if verbose:
                print(
                    f"[refine] integration {len(calls) + 1}: RMSE "
                    f"{np.sqrt(np.sum(r[0] ** 2)):.6g}",
                    flush=True,
                )
            calls.append(key)
        return cache[key]

    calls, failed = [], []
    x_start = np.concatenate([c0[free], np.zeros(B * ns)])
    r_start = evaluate(x_start)[0]
    if failed[0]:
        raise ValueError(
            "the fitted model cannot be integrated over every window (singular mass "
            "matrix or divergence): refine needs a model whose rollouts exist"
        )
    # Dissipative kinds (viscous, relative, drag, Coulomb) oppose the motion only
    # with a coefficient of the kinetic energy's sign (positive in the fit's scale;
    # a passive model may carry an overall negative factor); a bias (a constant
    # force) or a custom force has either sign and stays unbounded.
    dissipative = np.array(
        [False] * n_lag
        + [fitted.dissipation_terms[k - p_lag].dissipative for k in support[n_lag:]]
    )
    kinetic = 1.0
    if dissipative.any():
        mass = dynamics.parts(x0[:, :d], x0[:, d : 2 * d])[0]
        trace = np.einsum("k,skii->", c0[:n_lag], mass)
        kinetic = -1.0 if trace < 0 else 1.0
    wrong_sign = [names[k] for k in free if dissipative[k] and kinetic * c0[k] < 0]
    if wrong_sign:
        raise ValueError(
            f"the model's dissipative term(s) {', '.join(wrong_sign)} have "
            "coefficients of the sign opposite to its kinetic energy: they feed "
            "energy in, and refine keeps dissipation dissipative. Refit with the "
            "default sign constraint, or model the effect with a signed (bias or "
            "custom) term."
        )
    bounded = np.concatenate([dissipative[free], np.zeros(B * ns, dtype=bool)])
    low = np.where(bounded & (kinetic > 0), 0.0, -np.inf)
    high = np.where(bounded & (kinetic < 0), 0.0, np.inf)
    with np.errstate(all="ignore"):
        result = least_squares(
            lambda x: evaluate(x)[0],
            x_start,
            jac=lambda x: evaluate(x)[1],
            bounds=(low, high),
            x_scale="jac",  # |c| and the states' spread: 30+ iterations on a cart
            method="trf",
            tr_solver="lsmr" if ns else "exact",
            ftol=tol,
            xtol=tol,
            gtol=tol,
            max_nfev=max_iter,
        )
    coef, states = unpack(result.x)
    rmse_before = float(np.sqrt(np.sum(r_start**2)))
    rmse_after = float(np.sqrt(np.sum(evaluate(result.x)[0] ** 2)))
    if rmse_after > rmse_before:  # the trust region never accepts a worse point
        coef, states, rmse_after = c0.copy(), x0, rmse_before
    project = getattr(fitted.library, "consistent_refit", None)
    if forced and callable(project) and not np.array_equal(coef, c0):
        # a robot's link parameters stay consistent: the fit's constrained refit on
        # the rollouts' Gauss-Newton model (states held), kept if it beats the start
        shift = (states - x0).ravel() if fit_states else np.zeros(0)
        x = np.concatenate([coef[free], shift])
        r_x, jac = evaluate(x)
        jac_c = jac[:, :nf].toarray() if sparse.issparse(jac) else jac[:, :nf]
        gram = np.zeros((all_coef.size + 1,) * 2)
        cols = np.append(support[free], -1)
        block = np.column_stack([jac_c, jac_c @ coef[free] - r_x])
        gram[np.ix_(cols, cols)] = block.T @ block
        pin = 1e6 * max(np.diag(gram).max(), 1e-300)  # terms off the support stay 0
        off = np.setdiff1d(np.arange(p_lag), support)
        gram[off, off] = pin
        trial = all_coef.astype(float)
        trial[support] = coef
        dissipative_all = [t.dissipative for t in fitted.dissipation_terms]
        found = project(gram, trial, dissipative_all)
        if found is not None and not np.array_equal(found.coef[support], coef):
            coef = found.coef[support]
            x = np.concatenate([coef[free], shift])
            rmse_after = float(np.sqrt(np.sum(evaluate(x)[0] ** 2)))
            if rmse_after > rmse_before:  # the fit's own coefficients are consistent
                coef, states, rmse_after = c0.copy(), x0, rmse_before
    finer = _Rollouts(dynamics, tau_nodes, horizon, dt, 2 * substeps).positions(
        coef[None], states[None]
    )
    coarse = sim.positions(coef[None], states[None])
    integrator_error = float(
        np.sqrt(np.mean(((finer - coarse)[..., 1:, :] / scale) ** 2))
    )
    changes = {names[k]: float(coef[k] / c0[k] - 1) for k in free}
    converged = bool(result.status > 0)
    if not converged:
        warnings.warn(
            f"refine stopped after {result.nfev} integrations before converging "
            f"(rollout RMSE {rmse_before:.4g} -> {rmse_after:.4g}); raise max_iter",
            ConvergenceWarning,
            stacklevel=2,
        )
    large = large_changes(changes)
    if large:
        listed = ", ".join(f"{k} {100 * v:+.0f} %" for k, v in large.items())
        warnings.warn(
            f"refine moved coefficients by more than {LARGE_CHANGE:.0%} ({listed}): "
            "the rollouts and the equation-error fit disagree. A missing effect "
            "(friction, damping: see lagsindy.diagnose) or biased derivative "
            "estimates are the usual cause; do not read these terms as physical "
            "parameters before checking.",
            UserWarning,
            stacklevel=2,
        )
    if integration_too_coarse(integrator_error, rmse_after, spread):
        warnings.warn(
            f"the fixed-step integration error ({integrator_error:.3g}) is not small "
            f"against the rollout error ({rmse_after:.3g}): raise substeps",
            UserWarning,
            stacklevel=2,
        )

    all_new = all_coef.astype(float)
    all_new[support] = coef
    new_fitted = dataclasses.replace(
        fitted, coef=all_new[:p_lag], dissipation_coef=all_new[p_lag:]
    )
    # checked (and warned about, naming the coordinates) as after a fit
    new_fitted.mass_check = new_fitted.checked_mass(Xt, stacklevel=2)
    out = type(est).from_fitted(
        new_fitted,
        feature_names_in=getattr(est, "feature_names_in_", None),
        **est.get_params(deep=False),
    )
    out.refinement_ = Refinement(
        horizon=int(horizon),
        stride=int(stride),
        substeps=int(substeps),
        n_windows=len(wins),
        rmse_before=rmse_before,
        rmse_after=rmse_after,
        n_iter=len(calls),
        converged=converged,
        held=held,
        changes=changes,
        integrator_error=integrator_error,
    )
    return out
