r"""Base (identifiable) parameters of a robot's regressor.

The joint torque regressor ``Y(q, qd, qdd)`` of a robot's inertial parameters has
dependent columns: a link's mass is indistinguishable from the same mass added to its
neighbour at the joint, the first link's ``Ixx`` never moves, ... Identification can
only find the *base parameters* :math:`\beta = K \pi`, combinations of the link
parameters with ``Y pi = Y_b beta``, where ``Y_b`` keeps one independent column per
base parameter (Gautier 1990; Khalil and Dombre, *Modeling, identification and
control of robots*, 2002, ch. 12).

The combinations are found numerically, as in the classical literature, from the
regressor at random exciting states (joint positions within the limits, random
velocities and accelerations): QR with column pivoting gives the rank, and the
columns are kept in parameter order (a column is kept when it is not a combination
of the kept ones), so each base parameter is named after its first link parameter
and the later, dependent ones are regrouped into it: ``"m_link2 + m_link3"``,
``"Izz_link1 + Iyy_link2 + 0.1*m_link3 ..."``. Nothing here depends on parameter
values: a base parameter is never dropped because it is small.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
import torch

# Relative tolerances. Measured on Panda, UR5 and the test URDFs (unit columns, 100
# random states): the last kept QR pivot is >= 0.38 of the first, the first dropped
# one <= 8e-16; zero columns are exactly 0, the smallest non-zero one 4e-3 of the
# largest.
RANK_TOL = 1e-9
RANK_TOL_ORDERED = 1e-8  # residual of a unit column after projection
CLEAN_TOL = 1e-9  # combination coefficients below this (relative) are round-off


@dataclasses.dataclass
class BaseParameters:
    """Identifiable combinations of a robot's parameters.

    Attributes
    ----------
    names : list of str
        All parameter (term) names.
    independent : ndarray of int
        Indices of the kept (base) columns, in parameter order.
    unidentifiable : ndarray of int
        Parameters whose column is zero everywhere (no effect on the torques, e.g.
        the first link's ``Ixx`` about a vertical axis); they enter no base parameter.
    matrix : ndarray of shape (n_base, n_params)
        ``beta = matrix @ pi``; its ``independent`` columns form the identity.
    labels : list of str
        Each base parameter as a combination of link parameters.
    rank_qr : int
        The rank from QR with column pivoting (equals ``len(independent)``).
    """

    names: list[str]
    independent: np.ndarray
    unidentifiable: np.ndarray
    matrix: np.ndarray
    labels: list[str]
    rank_qr: int

    @property
    def n_base(self) -> int:
        return len(self.independent)

    def values(self, parameters) -> np.ndarray:
        """Base parameter values of full parameters: ``matrix @ parameters``."""
        return self.matrix @ np.asarray(parameters, dtype=float)

    def columns(self, full_columns) -> np.ndarray:
        """The base regressor: the ``independent`` columns (last axis) of a full one."""
        return np.asarray(full_columns)[..., self.independent]

    def table(self, values=None) -> list[tuple[str, float | None]]:
        """``(label, value)`` per base parameter (value ``None`` when not given)."""
        vals = [None] * self.n_base if values is None else [float(v) for v in values]
        return list(zip(self.labels, vals))

    def __str__(self) -> str:
        return "\n".join(
            f"beta{i + 1:<3d} = {lab}" for i, lab in enumerate(self.labels)
        )


def exciting_states(lower, upper, n_samples, rng, speed=2.0, acceleration=5.0):
    """Random positions within the limits, velocities and accelerations."""
    lower = np.where(np.isfinite(lower), lower, -np.pi)
    upper = np.where(np.isfinite(upper), upper, np.pi)
    n = len(lower)
    q = rng.uniform(lower, upper, (n_samples, n))
    qd = rng.uniform(-speed, speed, (n_samples, n))
    qdd = rng.uniform(-acceleration, acceleration, (n_samples, n))
    return q, qd, qdd


def _label(names, row, keep):
    parts = []
    big = np.abs(row).max()
    for j in np.flatnonzero(np.abs(row) > CLEAN_TOL * big):
        c = row[j]
        if j == keep:
            parts.insert(0, names[j])
            continue
        if abs(c - 1.0) < 1e-9:
            parts.append(f"+ {names[j]}")
        elif abs(c + 1.0) < 1e-9:
            parts.append(f"- {names[j]}")
        else:
            parts.append(f"{'+' if c > 0 else '-'} {abs(c):.6g}*{names[j]}")
    return " ".join(parts)


def base_parameters_from_columns(columns, names) -> BaseParameters:
    """Base parameters of a regressor evaluated at exciting states.

    Parameters
    ----------
    columns : array-like of shape (n_rows, n_params) or (n_samples, n_dof, n_params)
        Regressor columns at enough random exciting states (rows at least the number
        of parameters).
    names : list of str
        One name per parameter.

    Returns
    -------
    BaseParameters
    """
    a = np.asarray(columns, dtype=float)
    a = a.reshape(-1, a.shape[-1])
    n = a.shape[1]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} columns")
    if a.shape[0] < n:
        raise ValueError(f"need at least {n} rows of the regressor, got {a.shape[0]}")
    norms = np.linalg.norm(a, axis=0)
    scale = norms.max(initial=0.0)
    zero = norms <= RANK_TOL * scale
    # rank by QR with column pivoting on unit-norm columns
    unit = a[:, ~zero] / norms[~zero]
    r = scipy.linalg.qr(unit, mode="r", pivoting=True)[0]
    diag = np.abs(np.diag(r))
    rank_qr = int(np.sum(diag > RANK_TOL * diag[0])) if diag.size else 0
    # order-preserving choice: keep a column unless it is a combination of kept ones
    kept: list[int] = []
    basis = np.zeros((a.shape[0], 0))
    for j in range(n):
        if zero[j]:
            continue
        u = a[:, j] / norms[j]
        res = u - basis @ (basis.T @ u)
        res = res - basis @ (basis.T @ res)
        rn = np.linalg.norm(res)
        if rn > RANK_TOL_ORDERED:
            basis = np.concatenate([basis, (res / rn)[:, None]], axis=1)
            kept.append(j)
    kept_arr = np.array(kept, dtype=int)
    dependent = np.array(
        [j for j in range(n) if j not in kept and not zero[j]], dtype=int
    )
    matrix = np.zeros((len(kept), n))
    matrix[np.arange(len(kept)), kept_arr] = 1.0
    if dependent.size:
        coef, *_ = np.linalg.lstsq(a[:, kept_arr], a[:, dependent], rcond=None)
        coef[np.abs(coef) < CLEAN_TOL * max(1.0, np.abs(coef).max())] = 0.0
        matrix[:, dependent] = coef
    labels = [_label(names, matrix[i], kept_arr[i]) for i in range(len(kept))]
    return BaseParameters(
        names=list(names),
        independent=kept_arr,
        unidentifiable=np.flatnonzero(zero),
        matrix=matrix,
        labels=labels,
        rank_qr=rank_qr,
    )


def base_parameters(library, n_samples=None, random_state=0) -> BaseParameters:
    """Base parameters of a :class:`~lagsindy.robots.RobotLibrary`.

    The regressor is evaluated at ``n_samples`` random exciting states (positions
    uniform within the joint limits, or [-pi, pi] for continuous joints;
    velocities in [-2, 2] rad/s; accelerations in [-5, 5] rad/s^2) and reduced by
    :func:`base_parameters_from_columns`.

    Parameters
    ----------
    library : RobotLibrary
    n_samples : int, default=None
        ``None``: ``4 * n_terms / n_dof + 20`` (4 times the rows needed).
    random_state : int, default=0

    Returns
    -------
    BaseParameters

    Raises
    ------
    ValueError
        When QR with pivoting and the order-preserving choice disagree on the rank
        (the tolerance does not separate the columns at these states).
    """
    library._ensure_built()
    tree, names = library.tree_, library.terms_
    n_dof = tree.n_dof
    if n_samples is None:
        n_samples = int(4 * len(names) / n_dof) + 20
    rng = np.random.default_rng(random_state)
    q, qd, qdd = exciting_states(tree.lower, tree.upper, n_samples, rng)
    t = [torch.as_tensor(x) for x in (q, qd, qdd)]
    cols = library.torch_terms().columns(*t).numpy()
    out = base_parameters_from_columns(cols, names)
    if out.rank_qr != out.n_base:
        raise ValueError(
            f"the regressor's rank is ambiguous: QR with pivoting gives {out.rank_qr}, "
            f"the ordered choice {out.n_base}; try more samples (n_samples=)"
        )
    return out
