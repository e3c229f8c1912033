"""Single pendulum (paper section III-A)."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def single_pendulum(mass: float = 1.0, length: float = 1.0, g: float = 9.81) -> System:
    """A point mass on a massless rod, ``L = m l^2 thetadot^2 / 2 + m g l cos(theta)``.

    With the paper's parameters ``L = 0.5 theta_dot**2 + 9.81 cos(theta)``. Initial
    states ``theta ~ U(-pi, pi)``, ``theta_dot = 0``. The paper's input is
    ``2 cos(w t)``; its library is ``{theta, theta_dot, cos, sin}`` to degree 2 (14
    monomials; the paper keeps 12; this library keeps 9 after also removing
    ``theta_dot*sin(theta)`` and ``theta_dot*cos(theta)``, which are total
    derivatives, and ``cos(theta)**2``, whose Euler-Lagrange column is minus that of
    ``sin(theta)**2``).
    """
    theta, theta_dot = sp.symbols("theta theta_dot", real=True)
    m, l, gg = sp.Float(mass), sp.Float(length), sp.Float(g)
    lagrangian = m * l**2 / 2 * theta_dot**2 + m * gg * l * sp.cos(theta)
    return System(
        lagrangian,
        ["theta"],
        angles=["theta"],
        initial_ranges={"theta": (-math.pi, math.pi), "theta_dot": (0.0, 0.0)},
        library=lambda: CandidateLibrary.polynomial(
            ["theta"], angles=["theta"], degree=2, raw_angles=True
        ),
        paper_input=lambda t, w: (2.0 * np.cos(w * t))[:, None],
        fixed_term="theta_dot**2",
        name="single pendulum",
        description="point mass 1 kg on a 1 m rod, g = 9.81",
    )
