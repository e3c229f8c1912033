"""Triple pendulum (not in the paper): three point masses on rigid rods."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def n_link_lagrangian(masses, lengths, g=9.81, names=None):
    """Lagrangian of a planar chain of point masses on rigid rods (absolute angles).

    Cosines of angle differences are expanded into products of sines and cosines, so
    the separated library can represent every term.
    """
    n = len(masses)
    names = names or [f"theta{i + 1}" for i in range(n)]
    th = [sp.Symbol(nm, real=True) for nm in names]
    thd = [sp.Symbol(nm + "_dot", real=True) for nm in names]
    m = [sp.Float(v) for v in masses]
    lens = [sp.Float(v) for v in lengths]
    gg = sp.Float(g)
    lagrangian = sp.Integer(0)
    for i in range(n):
        mass_below = sum(m[i:], sp.Integer(0))  # links at or below link i
        lagrangian += mass_below * lens[i] ** 2 / 2 * thd[i] ** 2
        lagrangian += mass_below * gg * lens[i] * sp.cos(th[i])
        for j in range(i + 1, n):
            coupling = sum(m[j:], sp.Integer(0)) * lens[i] * lens[j]
            lagrangian += (
                coupling
                * thd[i]
                * thd[j]
                * (sp.cos(th[i]) * sp.cos(th[j]) + sp.sin(th[i]) * sp.sin(th[j]))
            )
    return sp.expand(lagrangian), names


def triple_pendulum(
    masses=(1.0, 1.0, 1.0), lengths=(1.0, 1.0, 1.0), g: float = 9.81
) -> System:
    """Three point masses on massless rods; all joints driven for active runs.

    Initial angles ``U(-pi/2, pi/2)``, velocities zero. Library: the separated
    construction of degree 2 over the three angles.
    """
    lagrangian, names = n_link_lagrangian(masses, lengths, g)
    ranges = {n: (-math.pi / 2, math.pi / 2) for n in names}
    ranges.update({n + "_dot": (0.0, 0.0) for n in names})
    return System(
        lagrangian,
        names,
        angles=names,
        initial_ranges=ranges,
        library=lambda: CandidateLibrary.separated(names, angles="all", degree=2),
        paper_input=lambda t, w: np.stack(
            [np.cos(w * t), np.sin(w * t), np.cos(w * t) - np.sin(w * t)], 1
        ),
        fixed_term="theta1_dot**2",
        prior_terms=["cos(theta1)"],
        name="triple pendulum",
        description="three 1 kg point masses on 1 m rods, g = 9.81",
    )
