"""Double pendulum (paper section III-C)."""

import math

import numpy as np
import sympy as sp

from ..library import CandidateLibrary
from .base import System


def double_pendulum(
    m1: float = 1.0, m2: float = 1.0, l1: float = 1.0, l2: float = 1.0, g: float = 9.81
) -> System:
    """Two point masses on rigid rods, absolute angles from the downward vertical.

    ``L = (m1 + m2)/2 l1^2 th1d^2 + m2/2 l2^2 th2d^2 + m2 l1 l2 th1d th2d
    (cos th1 cos th2 + sin th1 sin th2) + (m1 + m2) g l1 cos th1 + m2 g l2 cos th2``
    (the cosine of the difference written out, as in the paper's table). Initial
    angles ``U(-pi, pi)``, velocities zero. Paper input ``[cos(wt) - sin(wt),
    sin(wt)]``; library: the separated construction of degree 2 (89 candidates).
    """
    t1, t2, t1d, t2d = sp.symbols("theta1 theta2 theta1_dot theta2_dot", real=True)
    m1_, m2_, l1_, l2_, gg = map(sp.Float, (m1, m2, l1, l2, g))
    lagrangian = (
        (m1_ + m2_) / 2 * l1_**2 * t1d**2
        + m2_ / 2 * l2_**2 * t2d**2
        + m2_
        * l1_
        * l2_
        * t1d
        * t2d
        * (sp.cos(t1) * sp.cos(t2) + sp.sin(t1) * sp.sin(t2))
        + (m1_ + m2_) * gg * l1_ * sp.cos(t1)
        + m2_ * gg * l2_ * sp.cos(t2)
    )
    return System(
        sp.expand(lagrangian),
        ["theta1", "theta2"],
        angles=["theta1", "theta2"],
        initial_ranges={
            "theta1": (-math.pi, math.pi),
            "theta2": (-math.pi, math.pi),
            "theta1_dot": (0.0, 0.0),
            "theta2_dot": (0.0, 0.0),
        },
        library=lambda: CandidateLibrary.separated(
            ["theta1", "theta2"], angles="all", degree=2
        ),
        paper_input=lambda t, w: np.stack(
            [np.cos(w * t) - np.sin(w * t), np.sin(w * t)], 1
        ),
        fixed_term="theta1_dot**2",
        prior_terms=["cos(theta1)"],
        name="double pendulum",
        description="two 1 kg point masses on 1 m rods, g = 9.81",
    )
