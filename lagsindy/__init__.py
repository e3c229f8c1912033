"""lagsindy: sparse identification of Lagrangians from trajectories (xL-SINDy)."""

from .delay import DelayEstimate, estimate_delay, shift_input
from .diagnostics import DiagnosisReport, diagnose
from .differentiation import Derivatives, derivatives
from .dissipation import DissipationLibrary
from .dynamics import MechanicalModel, SingularMassMatrixError, rollout_error
from .estimator import LagrangianSINDy
from .io import load_model, save_model
from .library import CandidateLibrary
from .uncertainty import BootstrapReport, LibraryBaggingLagrangianSINDy, bootstrap

__version__ = "0.1.0"

__all__ = [
    "BootstrapReport",
    "CandidateLibrary",
    "DelayEstimate",
    "Derivatives",
    "DiagnosisReport",
    "DissipationLibrary",
    "LagrangianSINDy",
    "LibraryBaggingLagrangianSINDy",
    "MechanicalModel",
    "SingularMassMatrixError",
    "bootstrap",
    "derivatives",
    "diagnose",
    "estimate_delay",
    "load_model",
    "rollout_error",
    "save_model",
    "shift_input",
    "__version__",
]
