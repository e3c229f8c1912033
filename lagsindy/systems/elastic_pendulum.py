"""Elastic pendulum (not in the paper): a point mass on a spring that can swing."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def elastic_pendulum(
    mass: float = 1.0,
    stiffness: float = 40.0,
    rest_length: float = 1.0,
    g: float = 9.81,
) -> System:
    """Polar coordinates: length ``r`` of the spring and angle ``theta`` from the vertical.

    ``L = m/2 (r_dot^2 + r^2 theta_dot^2) + m g r cos(theta) - k/2 (r - l0)^2``.
    Initial states ``r ~ U(0.9, 1.4)``, ``theta ~ U(-pi/3, pi/3)``, at rest. Input form:
    ``[cos(w t), sin(w t)]`` (radial force, torque). Library: monomials of
    ``{r, r_dot, theta_dot, sin(theta), cos(theta)}`` to degree 2, plus the degree-3
    and 4 products a polar coordinate brings (``r theta_dot^2``, ``r^2 theta_dot^2``,
    ``r^2 cos(theta)``, ``r^3``, ``r r_dot^2``).
    """
    r, theta, r_dot, theta_dot = sp.symbols("r theta r_dot theta_dot", real=True)
    m, k, l0, gg = map(sp.Float, (mass, stiffness, rest_length, g))
    lagrangian = (
        m / 2 * (r_dot**2 + r**2 * theta_dot**2)
        + m * gg * r * sp.cos(theta)
        - k / 2 * (r - l0) ** 2
    )
    return System(
        sp.expand(lagrangian),
        ["r", "theta"],
        angles=["theta"],
        initial_ranges={
            "r": (0.9, 1.4),
            "theta": (-math.pi / 3, math.pi / 3),
            "r_dot": (0.0, 0.0),
            "theta_dot": (0.0, 0.0),
        },
        library=lambda: CandidateLibrary.polynomial(
            ["r", "theta"],
            angles=["theta"],
            degree=2,
            terms=[
                "r*theta_dot**2",
                "r**2*theta_dot**2",
                "r**2*cos(theta)",
                "r**3",
                "r*r_dot**2",
            ],
        ),
        paper_input=lambda t, w: np.stack([np.cos(w * t), np.sin(w * t)], 1),
        fixed_term="r_dot**2",
        name="elastic pendulum",
        description="1 kg on a spring (k = 40 N/m, rest length 1 m), g = 9.81",
    )
