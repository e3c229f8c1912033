"""lagsindy: sparse identification of Lagrangians from trajectories (xL-SINDy)."""

from .differentiation import Derivatives, derivatives
from .dynamics import MechanicalModel, SingularMassMatrixError, rollout_error
from .estimator import LagrangianSINDy
from .io import load_model, save_model
from .library import CandidateLibrary

__version__ = "0.1.0.dev0"

__all__ = [
    "CandidateLibrary",
    "Derivatives",
    "LagrangianSINDy",
    "MechanicalModel",
    "SingularMassMatrixError",
    "derivatives",
    "load_model",
    "rollout_error",
    "save_model",
    "__version__",
]
