r"""Physically consistent base parameters as a constraint of the fit.

After the sparse solve has chosen the dissipation candidates (friction kinds, a
spring, ...), :func:`constrained_refit` refits the coefficients on the same Gram
statistics subject to physical consistency:

* the base parameters are ``beta = K pi`` for full link parameters ``pi`` whose
  bodies each have a positive semidefinite pseudo-inertia ``J_b`` (Wensing, Kim and
  Slotine, 2018);
* rotor inertias ``>= 0``;
* dissipative coefficients (viscous, Coulomb, ...) ``>= 0``, the others (offsets,
  springs) free.

The objective is the fit's own least squares, ``x^T G x / 2 - g^T x`` with the
balanced Gram matrix ``[G g]`` of the statistics: a convex problem in the
pseudo-inertias, solved by ADMM (a linear solve, then the projection: eigenvalues
clipped at 0 per body, rotor inertias and dissipative coefficients at 0), started
from the URDF's own link parameters. When the sparse solution is itself consistent
(to round-off) it is kept as it is. The full parameters found are a consistent
representative for :func:`lagsindy.robots.to_urdf`.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import scipy.linalg

from .export import consistent_parameters, feasibility, pseudo_inertia

# ADMM's relative tolerance on the primal and dual residuals, and its iteration cap.
TOL = 1e-8
MAX_ITER = 5000
# Negative pseudo-inertia eigenvalues (relative to the largest mass) taken as
# round-off when the sparse solution is checked for consistency.
ROUND_OFF = 1e-9
# The smallest residual (relative to the torques' weighted sum of squares in the
# fit's Gram statistics) a constrained fit's residual is compared with
# (ConsistentFit.residual_ratio): an exact fit of noise-free torques leaves none.
RESIDUAL_FLOOR = 1e-4
# ADMM step, relative to the mean curvature of the least squares.
RHO = 0.003  # measured on the 7-joint arm: 1.0 converges 10 times slower
# Fitted base parameters whose nearest consistent full parameters miss them by more
# than this (relative) are reported as inconsistent when the constraint is off.
VIOLATION_TOL = 1e-6


@dataclasses.dataclass
class ConsistentFit:
    """What the constrained refit found.

    Attributes
    ----------
    coef : ndarray of shape (n_features,)
        Base parameters, then dissipation coefficients.
    parameters : ndarray of shape (n_full,)
        Consistent full link parameters (10 per body, then rotor inertias) with
        ``base.matrix @ parameters == coef[:n_base]``.
    min_eigenvalue : ndarray of shape (n_bodies,)
        Smallest eigenvalue of each body's pseudo-inertia (>= 0).
    objective_increase : float
        How much the constraint raised the least-squares objective, relative to the
        target's sum of squares (0 when the unconstrained fit was consistent).
    n_iter : int
    converged : bool
        Whether ADMM met its tolerance within ``MAX_ITER`` iterations (or the
        unconstrained fit was consistent). When not, the parameters are still
        feasible (every iterate is projected) but may not be the constrained
        optimum.
    residual_ratio : float
        The constrained fit's residual sum of squares over the unconstrained
        one's, or over ``RESIDUAL_FLOOR`` of the torques' sum of squares when that
        is larger (an exact fit of noise-free torques leaves nothing to compare
        with); 1 when the unconstrained fit was consistent.
    """

    coef: np.ndarray
    parameters: np.ndarray
    min_eigenvalue: np.ndarray
    objective_increase: float
    n_iter: int
    converged: bool = True
    residual_ratio: float = 1.0


def _pi_of_j(j):
    """Link parameters ``[m, h, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]`` of pseudo-inertias
    (..., 4, 4), the inverse of :func:`lagsindy.robots.export.pseudo_inertia`."""
    sigma = j[..., :3, :3]
    tr = sigma[..., 0, 0] + sigma[..., 1, 1] + sigma[..., 2, 2]
    inertia = tr[..., None, None] * np.eye(3) - sigma
    return np.stack(
        [
            j[..., 3, 3],
            j[..., 0, 3],
            j[..., 1, 3],
            j[..., 2, 3],
            inertia[..., 0, 0],
            inertia[..., 0, 1],
            inertia[..., 1, 1],
            inertia[..., 0, 2],
            inertia[..., 1, 2],
            inertia[..., 2, 2],
        ],
        axis=-1,
    )


_TRIL = np.tril_indices(4)


def _svec_basis():
    """``(10, 4, 4)``: the symmetric matrices of the unit vectors of ``svec`` (lower
    triangle, off-diagonal entries weighted by sqrt(2), so that the Euclidean norm of
    ``svec(J)`` is the Frobenius norm of ``J``)."""
    out = np.zeros((10, 4, 4))
    for k, (a, c) in enumerate(zip(*_TRIL)):
        w = 1.0 if a == c else 1.0 / np.sqrt(2.0)
        out[k, a, c] = out[k, c, a] = w
    return out


_SVEC = _svec_basis()


_SVEC_FLAT = _SVEC.reshape(10, 16)


def _project_psd(u, n_bodies):
    """Each body's ``svec`` block projected onto the positive semidefinite cone."""
    j = (u.reshape(n_bodies, 10) @ _SVEC_FLAT).reshape(n_bodies, 4, 4)
    w, v = np.linalg.eigh(j)
    j = (v * np.maximum(w, 0.0)[:, None, :]) @ v.transpose(0, 2, 1)
    return (j.reshape(n_bodies, 16) @ _SVEC_FLAT.T).reshape(-1)


def constrained_refit(
    robot, base, gram, coef, n_terms, dissipative, support, max_iter=None
):
    """Refit ``coef`` on the Gram statistics with consistent link parameters.

    The convex problem in the bodies' pseudo-inertias (as ``svec``), rotor inertias
    and kept dissipation coefficients, solved by ADMM: a linear solve for the least
    squares, then the projection onto the constraints (eigenvalue clipping per body,
    clipping at 0 for rotor inertias and dissipative coefficients).

    Parameters
    ----------
    robot : RobotLibrary
        The link-level library (built).
    base : BaseParameters
    gram : ndarray of shape (P + 1, P + 1)
        Balanced Gram matrix of the features and the target (last), coefficient units.
    coef : ndarray of shape (P,)
        The sparse solution (its dissipation support is kept).
    n_terms : int
        Number of base parameters (the first features).
    dissipative : array-like of bool, shape (P - n_terms,)
        Which dissipation coefficients must be non-negative.
    support : array-like of bool, shape (P - n_terms,)
        Which dissipation features the sparse solve kept (the others stay 0).
    max_iter : int, default=None
        ADMM's iteration cap (None: ``MAX_ITER``).

    Returns
    -------
    ConsistentFit
    """
    from threadpoolctl import threadpool_limits

    n_bodies = len(robot.tree_.bodies)
    n_link = 10 * n_bodies
    n_rotor = len(robot) - n_link
    k_mat = np.asarray(base.matrix, float)
    diss_idx = np.flatnonzero(np.asarray(support, bool))
    n_d = len(diss_idx)
    nonneg = np.asarray(dissipative, bool)[diss_idx]
    n_x = gram.shape[0] - 1
    scale = max(float(gram[-1, -1]), 1e-300)
    g, h_y = gram[:-1, :-1] / scale, gram[:-1, -1] / scale
    # x = T u, u = [svec(J_b) per body, rotor inertias, kept dissipation coefficients]
    p_body = _pi_of_j(_SVEC).T  # (10 parameters, 10 svec entries)
    n_u = n_link + n_rotor + n_d
    t_mat = np.zeros((n_x, n_u))
    for b in range(n_bodies):
        sl = slice(10 * b, 10 * b + 10)
        t_mat[:n_terms, sl] = k_mat[:, sl] @ p_body
    t_mat[:n_terms, n_link : n_link + n_rotor] = k_mat[:, n_link:]
    t_mat[n_terms + diss_idx, n_link + n_rotor + np.arange(n_d)] = 1.0
    hess = t_mat.T @ g @ t_mat
    lin = t_mat.T @ h_y
    rho = max(RHO * np.trace(hess) / n_u, 1e-300)

    def project(u):
        out = u.copy()
        out[:n_link] = _project_psd(u[:n_link], n_bodies)
        out[n_link : n_link + n_rotor] = np.maximum(u[n_link : n_link + n_rotor], 0)
        d = out[n_link + n_rotor :]
        d[nonneg] = np.maximum(d[nonneg], 0.0)
        return out

    with threadpool_limits(1):  # tiny matrices: BLAS threads only cost
        ref = np.asarray(robot.nominal_, float)
        j0 = np.stack([pseudo_inertia(p) for p in ref[:n_link].reshape(-1, 10)])
        u0 = np.concatenate(
            [
                np.einsum("bij,kij->bk", j0, _SVEC).reshape(-1),
                np.zeros(n_rotor),
                np.asarray(coef[n_terms:], float)[diss_idx],
            ]
        )
        # the inverse once: a product per iteration costs a tenth of a triangular
        # solve's call on these small systems
        inverse = scipy.linalg.cho_solve(
            scipy.linalg.cho_factor(hess + rho * np.eye(n_u)), np.eye(n_u)
        )
        v, w = project(u0), np.zeros(n_u)
        size = max(np.linalg.norm(v), 1e-300)
        converged = False
        for it in range(1, (max_iter or MAX_ITER) + 1):
            u = inverse @ (lin + rho * (v - w))
            v_old = v
            v = project(u + w)
            w = w + u - v
            if (
                np.linalg.norm(u - v) <= TOL * size
                and np.linalg.norm(v - v_old) <= TOL * size
            ):
                converged = True
                break
        x = t_mat @ v
        pi = np.concatenate(
            [
                np.einsum(
                    "bk,pk->bp", v[:n_link].reshape(n_bodies, 10), p_body
                ).ravel(),
                v[n_link : n_link + n_rotor],
            ]
        )
    xu = np.asarray(coef, float)
    f_con = 0.5 * x @ g @ x - h_y @ x
    f_unc = 0.5 * xu @ g @ xu - h_y @ xu
    # The sparse solution itself, when consistent, is the constrained optimum (the
    # least squares on its support): its base parameters with link parameters moved
    # from ADMM's by the least-norm change, if those are consistent.
    pi_u = pi + np.linalg.lstsq(k_mat, xu[:n_terms] - k_mat @ pi, rcond=None)[0]
    d_u = xu[n_terms:][diss_idx]
    # (consistent to round-off: a body on the boundary, a rod, has eigenvalue 0)
    slack = ROUND_OFF * max(1.0, float(np.abs(ref[0:n_link:10]).max(initial=0.0)))
    if (
        feasibility(pi_u, n_bodies).min() >= -slack
        and pi_u[n_link:].min(initial=0.0) >= -slack
        and np.all(d_u[nonneg] >= 0)
    ):
        clipped = pi_u.copy()
        clipped[:n_link] = _project_psd(
            np.einsum(
                "bij,kij->bk",
                np.stack([pseudo_inertia(p) for p in pi_u[:n_link].reshape(-1, 10)]),
                _SVEC,
            ).reshape(-1),
            n_bodies,
        )
        clipped[:n_link] = np.einsum(
            "bk,pk->bp", clipped[:n_link].reshape(n_bodies, 10), p_body
        ).ravel()
        clipped[n_link:] = np.maximum(pi_u[n_link:], 0.0)
        x, pi, f_con, converged = xu.copy(), clipped, f_unc, True
    return ConsistentFit(
        coef=x,
        parameters=pi,
        min_eigenvalue=feasibility(pi, n_bodies),
        objective_increase=float(f_con - f_unc),
        residual_ratio=float((2 * f_con + 1) / max(2 * f_unc + 1, RESIDUAL_FLOOR)),
        n_iter=it,
        converged=converged,
    )


def violation(robot, base, beta, max_iter=2000) -> float:
    """How far base parameters are from any consistent full parameters (relative;
    0: consistent), by :func:`lagsindy.robots.consistent_parameters`."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = consistent_parameters(robot, base, beta, max_iter=max_iter)
    return 0.0 if found.success else float(found.violation)
