"""Spring-mass chain (not in the paper): masses in a line between two walls."""

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def spring_chain(
    n_masses: int = 2, mass: float = 1.0, stiffness: float = 10.0
) -> System:
    """``n_masses`` equal masses joined by equal springs, the ends fixed to walls.

    Coordinates ``x1..xn`` are displacements from rest:
    ``L = sum m/2 xi_dot^2 - k/2 [x1^2 + sum (x(i+1) - xi)^2 + xn^2]``. Initial
    displacements ``U(-0.5, 0.5)`` m, velocities ``U(-1, 1)`` m/s. Input form:
    ``cos(w t)`` on every mass. Library: monomials of ``{x, x_dot}`` to degree 2.
    """
    names = [f"x{i + 1}" for i in range(n_masses)]
    x = [sp.Symbol(n, real=True) for n in names]
    xd = [sp.Symbol(n + "_dot", real=True) for n in names]
    m, k = sp.Float(mass), sp.Float(stiffness)
    kinetic = sum((m / 2 * v**2 for v in xd), sp.Integer(0))
    stretch = [x[0]] + [x[i + 1] - x[i] for i in range(n_masses - 1)] + [x[-1]]
    potential = sum((k / 2 * e**2 for e in stretch), sp.Integer(0))
    ranges = {n: (-0.5, 0.5) for n in names}
    ranges.update({n + "_dot": (-1.0, 1.0) for n in names})
    return System(
        sp.expand(kinetic - potential),
        names,
        angles=[],
        initial_ranges=ranges,
        library=lambda: CandidateLibrary.polynomial(names, degree=2),
        paper_input=lambda t, w: np.outer(np.cos(w * t), np.ones(n_masses)),
        fixed_term="x1_dot**2",
        name=f"spring chain ({n_masses} masses)",
        description=f"{n_masses} x {mass} kg, springs k = {stiffness} N/m, fixed ends",
    )
