"""Models you can use: standalone code, CasADi functions and linearizations.

A fitted :class:`~lagsindy.LagrangianSINDy` (or a model loaded from a file, its
``fitted_`` state, or any :class:`~lagsindy.MechanicalModel` such as a benchmark
system) becomes

* :func:`export_model`: a Python module (numpy only) or a C file and header with
  ``forward_dynamics(x, u)``, ``inverse_dynamics(q, q_dot, q_ddot)``,
  ``mass_matrix(q, q_dot)`` and ``energy(q, q_dot)``, numerically equal to the
  estimator, recording the model's provenance;
* :func:`to_casadi`: the same quantities as differentiable ``casadi.Function``
  objects (optional dependency);
* :func:`linearize`: continuous and zero-order-hold discrete ``A``, ``B`` at an
  equilibrium, which it checks.

States are ``x = [q..., q_dot...]``; the inputs ``u`` enter as generalized forces
``B u``. A learned model's ``B`` is the identity (``u`` are the generalized forces
the estimator was fitted with); pass ``input_matrix`` to say that, for example,
only a cart is driven.

The names below are imported on first use (PEP 562), so registering the
``lagsindy export`` command (:mod:`lagsindy.export.command`, part of the command
line) costs no sympy or numpy import.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

# public name -> submodule that defines it
_EXPORTS = {
    "BUILD_LINE": "c_code",
    "c_identifier": "c_code",
    "c_sources": "c_code",
    "CasadiModel": "casadi_model",
    "CModel": "compiled",
    "compile_c": "compiled",
    "discretize": "linearization",
    "EQUILIBRIUM_RTOL": "linearization",
    "export_model": "files",
    "export_source": "files",
    "find_compiler": "compiled",
    "FORMATS": "files",
    "Linearization": "linearization",
    "linearize": "linearization",
    "load_python": "python_code",
    "model_equations": "equations",
    "ModelEquations": "equations",
    "python_source": "python_code",
    "to_casadi": "casadi_model",
}

__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from .c_code import BUILD_LINE, c_identifier, c_sources  # noqa: F401
    from .casadi_model import CasadiModel, to_casadi  # noqa: F401
    from .compiled import CModel, compile_c, find_compiler  # noqa: F401
    from .equations import ModelEquations, model_equations  # noqa: F401
    from .files import FORMATS, export_model, export_source  # noqa: F401
    from .linearization import EQUILIBRIUM_RTOL, Linearization, discretize, linearize  # noqa: F401
    from .python_code import load_python, python_source  # noqa: F401
