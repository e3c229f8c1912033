"""Planar chains of rigid links on revolute joints (n-link pendulums), compound or point mass."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def _floats(values, n, what):
    values = [float(v) for v in values]
    if len(values) != n:
        raise ValueError(f"{what} needs {n} values (one per link), got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what} must be finite, got {values}")
    return values


def chain_lagrangian(
    masses: Sequence[float],
    lengths: Sequence[float],
    *,
    com: Sequence[float] | None = None,
    inertia: Sequence[float] | None = None,
    damping: Sequence[float] | None = None,
    g: float = 9.81,
    names: Sequence[str] | None = None,
    compact: bool = True,
):
    """Lagrangian and Rayleigh function of a planar chain of rigid links.

    Link ``i`` hangs from joint ``i`` (joint 1 fixed), has mass ``m_i``, its centre of
    mass at distance ``a_i`` from its joint, inertia ``I_i`` about its centre of mass,
    and carries joint ``i + 1`` at distance ``L_i``. Angles are absolute, measured from
    the downward vertical (0 hanging down). With ``M_j = sum_{i > j} m_i`` (mass below
    link ``j``)::

        L = sum_j (I_j + m_j a_j^2 + L_j^2 M_j) / 2 * q_j_dot^2
          + sum_{j < k} L_j (m_k a_k + L_k M_k) q_j_dot q_k_dot cos(q_j - q_k)
          + g sum_j (m_j a_j + L_j M_j) cos(q_j)
        D = sum_j k_j / 2 (q_j_dot - q_{j-1}_dot)^2      (q_0_dot = 0)

    so joint ``j``'s damping torque ``-k_j (q_j_dot - q_{j-1}_dot)`` acts on the
    relative velocity of the links it joins.

    Parameters
    ----------
    masses, lengths : sequence of float
        ``m_i`` and ``L_i`` (the last length matters only as the default ``a_n``).
    com : sequence of float, optional
        ``a_i``; default ``lengths`` (point masses at the link ends).
    inertia : sequence of float, optional
        ``I_i``; default zeros (point masses).
    damping : sequence of float, optional
        Joint coefficients ``k_i``; default none (conservative).
    g : float, default=9.81
    names : sequence of str, optional
        Coordinate names; default ``theta1..thetan``.
    compact : bool, default=True
        Keep ``cos(q_j - q_k)``; ``False`` writes it as
        ``cos(q_j) cos(q_k) + sin(q_j) sin(q_k)`` (the form of the paper's tables).

    Returns
    -------
    lagrangian : sympy.Expr
    dissipation : sympy.Expr
    names : list of str
    """
    n = len(masses)
    if n < 1:
        raise ValueError("a chain needs at least one link")
    m = _floats(masses, n, "masses")
    length = _floats(lengths, n, "lengths")
    a = _floats(com, n, "com") if com is not None else list(length)
    inert = _floats(inertia, n, "inertia") if inertia is not None else [0.0] * n
    k = _floats(damping, n, "damping") if damping is not None else [0.0] * n
    names = list(names) if names is not None else [f"theta{i + 1}" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"names needs {n} entries, got {len(names)}")
    q = [sp.Symbol(nm, real=True) for nm in names]
    qd = [sp.Symbol(nm + "_dot", real=True) for nm in names]
    below = [sum(m[j + 1 :]) for j in range(n)]
    F = sp.Float
    lag = sp.Integer(0)
    for j in range(n):
        inertia_j = inert[j] + m[j] * a[j] ** 2 + length[j] ** 2 * below[j]
        lag += F(inertia_j / 2) * qd[j] ** 2
        lag += F(g * (m[j] * a[j] + length[j] * below[j])) * sp.cos(q[j])
        for i in range(j + 1, n):
            c = F(length[j] * (m[i] * a[i] + length[i] * below[i]))
            coupling = (
                sp.cos(q[j] - q[i])
                if compact
                else sp.cos(q[j]) * sp.cos(q[i]) + sp.sin(q[j]) * sp.sin(q[i])
            )
            lag += c * qd[j] * qd[i] * coupling
    diss = sp.Integer(0)
    for j in range(n):
        if k[j]:
            rel = qd[j] - (qd[j - 1] if j else 0)
            diss += F(k[j] / 2) * rel**2
    return sp.expand(lag), sp.expand(diss), names


def chain_inputs(n: int):
    """Input form of :func:`planar_chain`: ``cos(w t + 2 pi i / n)`` on joint ``i``."""
    phases = 2 * math.pi * np.arange(n) / n

    def u(t, w):
        return np.cos(np.outer(w * t, np.ones(n)) + phases)

    return u


def planar_chain(
    n: int = 3,
    masses: Sequence[float] | None = None,
    lengths: Sequence[float] | None = None,
    *,
    com: Sequence[float] | None = None,
    inertia: Sequence[float] | None = None,
    damping: Sequence[float] | None = None,
    g: float = 9.81,
) -> System:
    """An ``n``-link planar pendulum (see :func:`chain_lagrangian`), every joint driven.

    Defaults: 1 kg point masses on 1 m links. Initial angles ``U(-pi/2, pi/2)``,
    velocities zero. Input form ``cos(w t + 2 pi i / n)`` on joint ``i`` (torques on
    the absolute angles). Library: :meth:`CandidateLibrary.chain` over the angles
    (``n + n(n-1)/2 + 2n`` terms). The Lagrangian keeps ``cos(q_i - q_j)``.

    Parameters
    ----------
    n : int, default=3
        Number of links (ignored when ``masses`` is given).
    masses, lengths, com, inertia, damping, g
        As for :func:`chain_lagrangian`.

    Returns
    -------
    System
    """
    if masses is None:
        masses = [1.0] * int(n)
    n = len(masses)
    if lengths is None:
        lengths = [1.0] * n
    lag, diss, names = chain_lagrangian(
        masses, lengths, com=com, inertia=inertia, damping=damping, g=g
    )
    return chain_system(
        lag,
        diss,
        names,
        library=lambda: CandidateLibrary.chain(names),
        paper_input=chain_inputs(n),
        name=f"{n}-link pendulum",
        description=chain_description(masses, lengths, g, com, inertia, damping),
    )


def chain_description(masses, lengths, g, com=None, inertia=None, damping=None):
    """A chain's parameters in words (the :class:`System`'s ``description``)."""
    compound = com is not None or inertia is not None
    return (
        f"{len(masses)} {'compound links' if compound else 'point masses'}: masses "
        f"{list(masses)} kg, lengths {list(lengths)} m, g = {g}"
        + (f", joint damping {list(damping)}" if damping is not None else "")
    )


def chain_system(
    lag, diss, names, *, library, name, description, paper_input=None, prior=True
):
    """A :class:`System` of a chain of links on revolute joints: initial angles
    ``U(-pi/2, pi/2)`` and velocities zero, the first link's ``theta_dot**2``
    fixed (case III) and, with ``prior``, its ``cos(theta)`` the prior term."""
    ranges = {nm: (-math.pi / 2, math.pi / 2) for nm in names}
    ranges.update({nm + "_dot": (0.0, 0.0) for nm in names})
    return System(
        lag,
        names,
        angles=names,
        initial_ranges=ranges,
        dissipation=diss,
        library=library,
        paper_input=paper_input,
        fixed_term=f"{names[0]}_dot**2",
        prior_terms=[f"cos({names[0]})"] if prior else (),
        name=name,
        description=description,
    )
