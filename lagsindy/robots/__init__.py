"""Robot arms from URDF kinematics.

* :class:`RobotLibrary` (also ``CandidateLibrary.from_urdf``): the energy regressor of
  every moving link's 10 inertial parameters and a rotor inertia per joint, as torch
  term functions (:class:`RobotTerms`);
* :func:`base_parameters`: the identifiable combinations of those parameters;
* :func:`consistent_parameters` and :func:`to_urdf`: physically consistent link
  parameters for identified base parameters, written back into a copy of the URDF.
"""

from .base_parameters import (
    BaseParameters,
    base_parameters,
    base_parameters_from_columns,
)
from .effects import FRICTION_KINDS, ROBOT_CATALOGUE
from .energy import RobotTerms, euler_lagrange_columns
from .examples import example_urdf, multisine
from .export import ConsistentParameters, consistent_parameters, feasibility, to_urdf
from .fitting import BaseParameterLibrary, BaseTerms
from .library import RobotLibrary
from .report import fitted_to_urdf, joint_coefficients, parameter_table
from .urdf import RobotTree, build_tree

__all__ = [
    "FRICTION_KINDS",
    "ROBOT_CATALOGUE",
    "BaseParameterLibrary",
    "BaseParameters",
    "BaseTerms",
    "ConsistentParameters",
    "RobotLibrary",
    "RobotTerms",
    "RobotTree",
    "base_parameters",
    "base_parameters_from_columns",
    "build_tree",
    "consistent_parameters",
    "euler_lagrange_columns",
    "example_urdf",
    "multisine",
    "feasibility",
    "fitted_to_urdf",
    "joint_coefficients",
    "parameter_table",
    "to_urdf",
]
