"""lagsindy: sparse identification of Lagrangians from trajectories (xL-SINDy).

The public names below are imported on first use (PEP 562), so ``import lagsindy``
and the ``lagsindy`` command's ``--help`` do not pay for torch, sympy and
scikit-learn until a name that needs them is used.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING

from ._lazy import lazy_exports
from ._version import __version__

# public name -> submodule that defines it
_EXPORTS = {
    "BootstrapReport": "uncertainty",
    "CandidateLibrary": "library",
    "DelayEstimate": "delay",
    "Derivatives": "differentiation",
    "DiagnosisReport": "diagnostics",
    "DissipationLibrary": "dissipation",
    "IdentifiabilityWarning": "formulation",
    "LagrangianSINDy": "estimator",
    "LibraryBaggingLagrangianSINDy": "uncertainty",
    "MechanicalModel": "dynamics",
    "SingularMassMatrixError": "dynamics",
    "Refinement": "refine",
    "UnmodelledForceWarning": "formulation",
    "WindowWarning": "formulation",
    "bootstrap": "uncertainty",
    "derivatives": "differentiation",
    "diagnose": "diagnostics",
    "estimate_delay": "delay",
    "load_model": "io",
    "refine": "refine",
    "rollout_error": "dynamics",
    "save_model": "io",
    "shift_input": "delay",
}

__all__ = [*sorted(_EXPORTS), "__version__"]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


class _Namespace(types.ModuleType):
    """The package's module type: a public function keeps its name when its
    submodule of the same name is imported (``lagsindy.refine``, the function, and
    ``lagsindy/refine.py``). Python binds an imported submodule to the package's
    attribute of that name, so after ``import lagsindy.refine`` (or any import of
    that module inside the package), ``from lagsindy import refine`` gave the module.
    """

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and _EXPORTS.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Namespace


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from .delay import DelayEstimate, estimate_delay, shift_input
    from .diagnostics import DiagnosisReport, diagnose
    from .differentiation import Derivatives, derivatives
    from .dissipation import DissipationLibrary
    from .dynamics import MechanicalModel, SingularMassMatrixError, rollout_error
    from .estimator import LagrangianSINDy
    from .io import load_model, save_model
    from .library import CandidateLibrary
    from .refine import Refinement, refine
    from .uncertainty import (
        BootstrapReport,
        LibraryBaggingLagrangianSINDy,
        bootstrap,
    )
