"""Mechanical models and their simulation.

* :mod:`~lagsindy.dynamics.mechanical`: :class:`MechanicalModel` (a Lagrangian,
  dissipation, forces and inputs; or terms and coefficients) and its equations of
  motion, symbolic and numeric;
* :mod:`~lagsindy.dynamics.simulation`: ``simulate`` and :func:`rollout_error`;
* :mod:`~lagsindy.dynamics.steppers`: explicit Runge-Kutta steps to every sample,
  on Python floats for small models;
* :mod:`~lagsindy.dynamics.checks`: singular or indefinite mass matrices.
"""

from .checks import MASS_MATRIX_RCOND, NEAR_SINGULAR, SingularMassMatrixError
from .mechanical import MechanicalModel
from .simulation import InputFunction, rollout_error

__all__ = [
    "MASS_MATRIX_RCOND",
    "NEAR_SINGULAR",
    "InputFunction",
    "MechanicalModel",
    "SingularMassMatrixError",
    "rollout_error",
]
