"""Simulation of mechanical models: inputs, right-hand sides, integration.

:func:`simulate` integrates a :class:`~lagsindy.dynamics.MechanicalModel`'s
equations of motion with :func:`scipy.integrate.solve_ivp`, or, with a sampled
input, stepping to every sample (:mod:`.steppers`); one trajectory of a 1- or 2-dof
model runs on Python floats. :func:`rollout_error` compares two models' rollouts.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable

import numpy as np
from scipy.integrate import solve_ivp

from .checks import SingularMassMatrixError, check_mass, diagnose_failure
from .steppers import EXPLICIT_RK, integrate_between, integrate_floats

#: An input given as a function ``u(t, state)``: time (float) and state
#: ``[q..., qdot...]`` to the inputs, shape (n_inputs,) (a batch: states of shape
#: (n_trajectories, 2 * n_dof) to inputs of shape (n_trajectories, n_inputs)).
InputFunction = Callable[[float, np.ndarray], np.ndarray]


def input_function(model, tau, t, batch):
    """Turn ``tau`` (None, array sampled at t, or callable) into u(t, states)."""
    m = model.n_inputs
    if tau is None:
        return None
    if callable(tau):
        return tau
    arr = np.asarray(tau, dtype=float)
    t = np.asarray(t, dtype=float)
    if batch is None:
        if arr.ndim == 1 and m == 1:
            arr = arr[:, None]
        if arr.shape != (t.shape[0], m):
            raise ValueError(
                f"tau sampled at t must have shape ({t.shape[0]}, {m}), got {arr.shape}"
            )
        return lambda tt, _x: np.array([np.interp(tt, t, arr[:, j]) for j in range(m)])
    if arr.shape != (batch, t.shape[0], m):
        raise ValueError(
            f"tau for {batch} trajectories must have shape "
            f"({batch}, {t.shape[0]}, {m}), got {arr.shape}"
        )
    return lambda tt, _x: np.stack(
        [[np.interp(tt, t, arr[b, :, j]) for j in range(m)] for b in range(batch)]
    )


def simulate(
    model,
    x0,
    t,
    tau=None,
    *,
    method: str = "DOP853",
    rtol: float = 1e-9,
    atol: float = 1e-9,
    max_step: float = np.inf,
) -> np.ndarray:
    """Integrate ``model``'s equations of motion from ``x0`` over the times ``t``.

    What :meth:`MechanicalModel.simulate` runs; its parameters, notes, return
    value and errors are documented there.
    """
    x0 = np.asarray(x0, dtype=float)
    t = np.asarray(t, dtype=float).ravel()
    n = model.n_dof
    batch = None if x0.ndim == 1 else x0.shape[0]
    if x0.shape[-1] != 2 * n or x0.ndim > 2:
        raise ValueError(
            f"x0 must have shape ({2 * n},) or (n_trajectories, {2 * n}), "
            f"got {x0.shape}"
        )
    if t.size < 1 or np.any(np.diff(t) <= 0):
        raise ValueError("t must be a non-empty, strictly increasing array of times")
    u_fn = input_function(model, tau, t, batch)
    b_mat = model.input_matrix
    rows = 1 if batch is None else batch
    x_start = x0.reshape(rows, 2 * n)
    start_mass, _ = model._mass_and_rest(x_start[:, :n], x_start[:, n:])
    check_mass(model, start_mass, x_start[:, :n], x_start[:, n:], t[0])
    reference = np.abs(np.linalg.eigvalsh(start_mass)).max(axis=1)
    last = {}
    mass_and_rest = model._mass_and_rest

    def rhs(tt, y):
        # The mass matrix is checked at the start and at every output time
        # (below), not here: an eigen-decomposition per step dominated the cost.
        x = y.reshape(rows, 2 * n)
        q, qd = x[:, :n], x[:, n:]
        last["t"], last["y"] = tt, y
        mass, rest = mass_and_rest(q, qd)
        force = -rest
        if u_fn is not None:
            u = np.asarray(u_fn(tt, x[0] if batch is None else x), dtype=float)
            force = force + np.reshape(u, (rows, -1)) @ b_mat.T
        try:
            qdd = np.linalg.solve(mass, force[..., None])[..., 0]
        except np.linalg.LinAlgError:
            qdd = np.full_like(force, np.nan)
        if not np.all(np.isfinite(qdd)):
            check_mass(model, mass, q, qd, tt, reference)
        return np.concatenate([qd, qdd], axis=1).ravel()

    if t.size == 1:
        return x0.copy()[None] if batch is None else x0.copy()[:, None]
    sampled = tau is not None and not callable(tau)
    if batch is None and n <= 2:
        fast = scalar_rhs(model, tau, t, sampled, u_fn, reference, last)
        rhs = fast or rhs
    floats = (
        float_rhs(model, tau, t)
        if sampled and method in EXPLICIT_RK and batch is None and n <= 2
        else None
    )
    if floats is not None:
        rows_out, status, message, (t_last, y_last) = integrate_floats(
            EXPLICIT_RK[method], *floats, t, x0.ravel(), rtol, atol, max_step
        )
        y = np.array(rows_out, dtype=float)
        if status != 0:
            last["t"], last["y"] = t_last, np.array(y_last, dtype=float)
    elif sampled and method in EXPLICIT_RK:
        y, status, message = integrate_between(
            EXPLICIT_RK[method], rhs, t, x0.ravel(), rtol, atol, max_step
        )
    else:
        sol = solve_ivp(
            rhs,
            (t[0], t[-1]),
            x0.ravel(),
            method=method,
            t_eval=t,
            rtol=rtol,
            atol=atol,
            max_step=max_step,
        )
        y, status, message = sol.y.T, sol.status, sol.message
    if status != 0:
        if "y" in last:
            last["x"] = np.asarray(last["y"]).reshape(rows, 2 * n)
        diagnose_failure(model, last, reference, message)
    states = y.reshape(t.size, rows, 2 * n)
    # One check of the mass matrix at all output times together.
    flat = states.reshape(-1, 2 * n)
    mass, _ = model._mass_and_rest(flat[:, :n], flat[:, n:])
    check_mass(
        model,
        mass,
        flat[:, :n],
        flat[:, n:],
        np.repeat(t, rows),
        np.tile(reference, t.size),
    )
    return states[:, 0] if batch is None else states.transpose(1, 0, 2)


def scalar_rhs(model, tau, t, sampled, u_fn, reference, last):
    """Right-hand side of one trajectory on Python floats (1 or 2 dof), or None.

    Numpy's per-call overhead on arrays of one sample dominates a small model's
    right-hand side; the ``math`` module on floats is several times faster.
    """
    n = model.n_dof
    f = model._float_terms()
    if f is None:
        return None
    b_mat = model.input_matrix
    if sampled:
        arr = np.asarray(tau, dtype=float).reshape(t.size, -1) @ b_mat.T
        times, forces = t.tolist(), arr.tolist()
        slopes = (np.diff(arr, axis=0) / np.diff(t)[:, None]).tolist()
        last_index = t.size - 2

    def rhs(tt, y):
        last["t"], last["y"] = tt, y
        v = f(*y.tolist())
        if sampled:
            k = min(max(bisect.bisect_right(times, tt) - 1, 0), last_index)
            h = tt - times[k]
            extra = [a + h * b for a, b in zip(forces[k], slopes[k])]
        elif u_fn is not None:
            extra = (np.reshape(u_fn(tt, y), (-1,)) @ b_mat.T).tolist()
        else:
            extra = [0.0] * n
        if n == 1:
            m, r = v[0], extra[0] - v[1]
            qdd = [r / m] if m != 0 else [math.nan]
        else:
            a, b, c, d = v[0], v[1], v[2], v[3]
            r0, r1 = extra[0] - v[4], extra[1] - v[5]
            det = a * d - b * c
            qdd = (
                [(d * r0 - b * r1) / det, (a * r1 - c * r0) / det]
                if det != 0
                else [math.nan, math.nan]
            )
        if not all(math.isfinite(x) for x in qdd):
            x = np.asarray(y, dtype=float)[None]
            mass = np.asarray(v[: n * n], dtype=float).reshape(1, n, n)
            check_mass(model, mass, x[:, :n], x[:, n:], tt, reference)
        return np.array(y.tolist()[n:] + qdd)

    return rhs


def float_rhs(model, tau, t):
    """``(rhs, segment)`` on tuples of floats for a sampled input (1 or 2 dof), or None.

    ``segment(k)`` selects the input's linear piece on ``[t[k], t[k+1]]`` so the
    right-hand side needs no search; ``rhs(t, y)`` returns ``(qd..., qdd...)``
    with the 1x1 or 2x2 mass matrix solved in closed form (a zero determinant
    raises ZeroDivisionError, which the integrator treats as a failed step).
    """
    n = model.n_dof
    f = model._float_terms()
    if f is None:
        return None
    arr = np.asarray(tau, dtype=float).reshape(t.size, -1) @ model.input_matrix.T
    forces = arr.tolist()
    slopes = (np.diff(arr, axis=0) / np.diff(t)[:, None]).tolist()
    times = t.tolist()
    piece = [0.0] * (1 + 2 * n)

    def segment(k):
        piece[0] = times[k]
        piece[1 : 1 + n] = forces[k]
        piece[1 + n :] = slopes[k]

    if n == 1:

        def rhs(tt, y):
            m, r = f(*y)
            return (y[1], (piece[1] + (tt - piece[0]) * piece[2] - r) / m)

    else:

        def rhs(tt, y):
            a, b, c, d, r0, r1 = f(*y)
            dt = tt - piece[0]
            r0 = piece[1] + dt * piece[3] - r0
            r1 = piece[2] + dt * piece[4] - r1
            det = a * d - b * c
            return (y[2], y[3], (d * r0 - b * r1) / det, (a * r1 - c * r0) / det)

    return rhs, segment


def rollout_error(model_a, model_b, x0, t, tau=None) -> dict:
    """Integrate two models from the same state and compare their trajectories.

    Used as the paper's validation metric: train on 5 s, integrate both the learned
    and the true model for a further horizon and measure how far they drift apart.

    Returns
    -------
    dict with keys ``"max_abs_q"`` (largest absolute position difference),
    ``"rmse_q"``, ``"states_a"``, ``"states_b"``; a model that fails to integrate
    gives ``inf`` errors and the exception text under ``"error"``.
    """
    sa = model_a.simulate(x0, t, tau)
    try:
        sb = model_b.simulate(x0, t, tau)
    except (SingularMassMatrixError, RuntimeError, np.linalg.LinAlgError) as exc:
        return {
            "max_abs_q": np.inf,
            "rmse_q": np.inf,
            "states_a": sa,
            "states_b": None,
            "error": str(exc),
        }
    n = model_a.n_dof
    diff = sa[..., :n] - sb[..., :n]
    return {
        "max_abs_q": float(np.abs(diff).max()),
        "rmse_q": float(np.sqrt(np.mean(diff**2))),
        "states_a": sa,
        "states_b": sb,
    }
