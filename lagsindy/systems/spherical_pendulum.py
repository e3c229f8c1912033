"""Spherical pendulum (paper section III-D)."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def spherical_pendulum(
    mass: float = 1.0, length: float = 1.0, g: float = 9.81
) -> System:
    """A point mass on a rod free to swing in 3-D; polar angle theta, azimuth phi.

    ``L = m l^2/2 (theta_dot^2 + sin(theta)^2 phi_dot^2) + m g l cos(theta)``. The mass
    matrix is singular at ``theta = 0``, so initial states are those of the paper:
    ``theta ~ U(pi/3, pi/2)``, ``phi = 0``, ``theta_dot = 0``, ``phi_dot = pi``
    (angular momentum keeps theta away from 0). Paper input: a constant 1 on phi;
    library: the separated construction with ``{cos, sin}`` of theta and
    ``{theta_dot, phi, phi_dot}`` (59 candidates).
    """
    theta, phi, theta_dot, phi_dot = sp.symbols(
        "theta phi theta_dot phi_dot", real=True
    )
    m, l, gg = map(sp.Float, (mass, length, g))
    lagrangian = (
        m * l**2 / 2 * phi_dot**2 * sp.sin(theta) ** 2
        + m * l**2 / 2 * theta_dot**2
        + m * gg * l * sp.cos(theta)
    )
    return System(
        lagrangian,
        ["theta", "phi"],
        angles=["theta", "phi"],
        initial_ranges={
            "theta": (math.pi / 3, math.pi / 2),
            "phi": (0.0, 0.0),
            "theta_dot": (0.0, 0.0),
            "phi_dot": (math.pi, math.pi),
        },
        library=lambda: CandidateLibrary.separated(
            ["theta", "phi"], angles=["theta"], degree=2
        ),
        paper_input=lambda t, w: np.stack([np.zeros_like(w), np.ones_like(w)], 1),
        fixed_term="theta_dot**2",
        prior_terms=["cos(theta)"],
        name="spherical pendulum",
        description="1 kg point mass on a 1 m rod, g = 9.81",
    )
