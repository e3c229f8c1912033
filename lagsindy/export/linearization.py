r"""Linearization of a model's dynamics about an equilibrium, continuous and discrete.

For :math:`\dot x = f(x, u)` with :math:`x = [q, \dot q]` and
:math:`\ddot q = M^{-1}(B u - r)`,

.. math::

    A = \begin{bmatrix} 0 & I \\ \partial \ddot q/\partial q &
        \partial \ddot q / \partial \dot q \end{bmatrix}, \quad
    B_c = \begin{bmatrix} 0 \\ M^{-1} B \end{bmatrix}, \quad
    \frac{\partial \ddot q}{\partial x_k} = -M^{-1}\Big(\frac{\partial r}{\partial x_k}
        + \frac{\partial M}{\partial x_k} \ddot q\Big),

with the derivatives of ``M`` and ``r`` taken symbolically (sympy), so ``A`` and
``B`` are exact to rounding. Given a sampling interval, the zero-order-hold pair is
read off the exponential of the block matrix :math:`[[A, B_c], [0, 0]]\,dt`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import sympy as sp
from scipy.linalg import expm

from .equations import model_equations
from .printing import NumpyExactPrinter

# |f(x_eq, u_eq)| above this fraction of ||A||_2 (the change of f per unit change
# of the state) makes linearize warn that x_eq is not an equilibrium. The ratio is
# about the distance to the equilibrium in state units: the cart-pendulum at
# theta = pi + d gives 1.00 d (d = 1e-4 .. 1e-2), a cart moving at 0.01 m/s 6.4e-4;
# the upright state of the true and of the identified cart-pendulum
# (examples/control_lqr_cartpole.py) 1.2e-16 (sin(pi) in floating point).
EQUILIBRIUM_RTOL = 1e-3


@dataclass
class Linearization:
    """Continuous (and discrete) linear models about an operating point.

    Attributes
    ----------
    A : ndarray of shape (2 n_dof, 2 n_dof)
    B : ndarray of shape (2 n_dof, n_inputs)
        ``dx/dt = A (x - x_eq) + B (u - u_eq)`` to first order.
    Ad, Bd : ndarray or None
        The zero-order-hold discretization at ``dt`` (``None`` without ``dt``):
        ``x[k+1] - x_eq = Ad (x[k] - x_eq) + Bd (u[k] - u_eq)``.
    dt : float or None
    x_eq : ndarray of shape (2 n_dof,)
    u_eq : ndarray of shape (n_inputs,)
    f_eq : ndarray of shape (2 n_dof,)
        ``f(x_eq, u_eq)``: zero at an equilibrium.
    residual : float
        ``|f(x_eq, u_eq)| / ||A||_2``: how far from an equilibrium the point is,
        relative to the change of ``f`` per unit change of the state (warned above
        ``EQUILIBRIUM_RTOL``).
    coordinates : list of str
    """

    A: np.ndarray
    B: np.ndarray
    Ad: np.ndarray | None
    Bd: np.ndarray | None
    dt: float | None
    x_eq: np.ndarray
    u_eq: np.ndarray
    f_eq: np.ndarray
    residual: float
    coordinates: list


def discretize(A, B, dt: float):
    """Zero-order-hold discretization ``(Ad, Bd)`` of ``dx/dt = A x + B u``.

    ``expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]]``.
    """
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    n, m = B.shape
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = A, B
    e = expm(block * dt)
    return e[:n, :n], e[:n, n:]


def _jacobian_functions(eq):
    """Lambdified ``(M, r, dM/dx, dr/dx)`` of the equations (numpy)."""
    n = eq.n_dof
    x = list(eq.q) + list(eq.qd)
    mass = [eq.mass[i, j] for i in range(n) for j in range(n)]
    exprs = mass + list(eq.rest)
    jac = [sp.diff(e, v) for e in exprs for v in x]
    # sympy's printer writes a Float made from a Python float with 15 significant
    # digits (a learned coefficient's last bits); this one writes every bit
    return sp.lambdify(
        x, exprs + jac, modules="numpy", cse=True, printer=NumpyExactPrinter
    )


def linearize(
    source, x_eq, u_eq=None, dt=None, *, input_matrix=None, warn: bool = True
) -> Linearization:
    """Jacobians ``A``, ``B`` of the forward dynamics at an equilibrium.

    Parameters
    ----------
    source : LagrangianSINDy, FittedLagrangian or MechanicalModel
        A fitted (or loaded) estimator, its ``fitted_`` state, or a model.
    x_eq : array-like of shape (2 * n_dof,)
        The operating state ``[q..., q_dot...]``.
    u_eq : array-like of shape (n_inputs,), optional
        The inputs there (default zero).
    dt : float, optional
        Sampling interval: also return the zero-order-hold pair ``Ad``, ``Bd``.
    input_matrix : array-like of shape (n_dof, n_inputs), optional
        How the inputs enter (generalized force ``B u``); default: the model's own
        (the identity for a learned model: ``u`` are the generalized forces).
    warn : bool, default=True
        Warn when ``x_eq`` is not an equilibrium (see ``Linearization.residual``).

    Returns
    -------
    Linearization

    Warns
    -----
    UserWarning
        When ``|f(x_eq, u_eq)| > EQUILIBRIUM_RTOL * ||A||_2``: the point is not an
        equilibrium of the model, so the linear model has a constant drift term
        ``f_eq`` that ``A`` and ``B`` leave out.

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.systems import cart_pendulum
    >>> from lagsindy.export import linearize
    >>> lin = linearize(cart_pendulum(), [0, np.pi, 0, 0], [0.0])
    >>> lin.A.shape, lin.B.shape
    ((4, 4), (4, 1))
    """
    eq = model_equations(source, input_matrix)
    n, m = eq.n_dof, eq.n_inputs
    x_eq = np.asarray(x_eq, dtype=float).reshape(-1)
    if x_eq.shape != (2 * n,):
        raise ValueError(
            f"x_eq must have {2 * n} entries [q..., q_dot...] for the coordinates "
            f"{eq.coordinates}, got shape {np.shape(x_eq)}"
        )
    u_eq = np.zeros(m) if u_eq is None else np.asarray(u_eq, dtype=float).reshape(-1)
    if u_eq.shape != (m,):
        raise ValueError(f"u_eq must have {m} entries, got shape {u_eq.shape}")
    if not (np.all(np.isfinite(x_eq)) and np.all(np.isfinite(u_eq))):
        raise ValueError("x_eq and u_eq must be finite")
    values = np.asarray(
        [np.broadcast_to(v, ()) for v in _jacobian_functions(eq)(*x_eq)], dtype=float
    )
    k = n * n + n
    M = values[: n * n].reshape(n, n)
    r = values[n * n : k]
    jac = values[k:].reshape(k, 2 * n)
    dM = jac[: n * n].reshape(n, n, 2 * n)  # dM_ij/dx_l
    dr = jac[n * n :]  # dr_i/dx_l
    qdd = np.linalg.solve(M, eq.input_matrix @ u_eq - r)
    dqdd = -np.linalg.solve(M, dr + np.einsum("ijl,j->il", dM, qdd))
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    A[n:] = dqdd
    B = np.zeros((2 * n, m))
    B[n:] = np.linalg.solve(M, eq.input_matrix)
    f_eq = np.concatenate([x_eq[n:], qdd])
    scale = max(np.linalg.norm(A, 2), np.finfo(float).tiny)
    residual = float(np.linalg.norm(f_eq) / scale)
    if warn and residual > EQUILIBRIUM_RTOL:
        warnings.warn(
            f"x_eq is not an equilibrium of the model: f(x_eq, u_eq) = "
            f"{np.array2string(f_eq, precision=4)} ({residual:.2g} of ||A||, the "
            f"change of f per unit change of the state; above {EQUILIBRIUM_RTOL:g}). "
            "The linear model leaves out this constant drift. Choose a state with "
            "zero velocities where the forces balance (for a learned model, its "
            "equilibrium may sit slightly off the true one), or the inputs u_eq "
            "that hold it there.",
            UserWarning,
            stacklevel=2,
        )
    Ad = Bd = None
    if dt is not None:
        Ad, Bd = discretize(A, B, float(dt))
    return Linearization(
        A=A,
        B=B,
        Ad=Ad,
        Bd=Bd,
        dt=None if dt is None else float(dt),
        x_eq=x_eq,
        u_eq=u_eq,
        f_eq=f_eq,
        residual=residual,
        coordinates=list(eq.coordinates),
    )


__all__ = ["EQUILIBRIUM_RTOL", "Linearization", "discretize", "linearize"]
