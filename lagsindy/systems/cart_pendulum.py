"""Cart-pendulum (paper section III-B)."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def cart_pendulum(
    cart_mass: float = 1.0, mass: float = 0.5, length: float = 1.0, g: float = 9.81
) -> System:
    """A pendulum (point mass on a rod) hanging from a cart on a rail; only the cart is driven.

    ``L = (M + m)/2 x_dot^2 + m l x_dot theta_dot cos(theta) + m l^2/2 theta_dot^2
    + m g l cos(theta)``. The defaults (1 kg cart, 0.5 kg bob) give the paper's tables'
    true Lagrangian ``0.75 x_dot^2 + 0.5 x_dot theta_dot cos(theta) + 0.25
    theta_dot^2 + 4.905 cos(theta)``; the masses in the paper's figure caption
    (0.5 kg cart, 1 kg bob) would not. Initial states ``theta ~ U(-pi, pi)``, the rest
    zero. Paper input ``cos(w t)`` on the cart; library: monomials of
    ``{theta_dot, cos, sin, x, x_dot}`` to degree 3 (55 candidates).
    """
    x, theta, x_dot, theta_dot = sp.symbols("x theta x_dot theta_dot", real=True)
    mc, m, l, gg = map(sp.Float, (cart_mass, mass, length, g))
    lagrangian = (
        (mc + m) / 2 * x_dot**2
        + m * l * x_dot * theta_dot * sp.cos(theta)
        + m * l**2 / 2 * theta_dot**2
        + m * gg * l * sp.cos(theta)
    )
    return System(
        lagrangian,
        ["x", "theta"],
        angles=["theta"],
        initial_ranges={
            "x": (0.0, 0.0),
            "theta": (-math.pi, math.pi),
            "x_dot": (0.0, 0.0),
            "theta_dot": (0.0, 0.0),
        },
        input_matrix=[[1.0], [0.0]],
        library=lambda: CandidateLibrary.polynomial(
            ["x", "theta"], angles=["theta"], degree=3
        ),
        paper_input=lambda t, w: np.cos(w * t)[:, None],
        fixed_term="theta_dot**2",
        prior_terms=["cos(theta)"],
        name="cart-pendulum",
        description="1 kg cart, 0.5 kg point mass on a 1 m rod, g = 9.81; force on the cart",
    )
