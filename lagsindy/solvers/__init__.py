r"""Sparse solvers: FISTA with an L1 penalty, and the paper's staged schedule.

The pieces follow a small duck-typed contract (in the spirit of skglm):

* a **datafit** provides ``value(w)``, ``gradient(w)``, ``lipschitz()``,
  ``restrict(idx)`` and ``relative_residual(w)``;
* a **penalty** provides ``value(w)``, ``prox(w, step)``,
  ``subdiff_distance(w, grad)`` and ``restrict(idx)``;
* :func:`fista` minimises ``datafit + penalty`` and returns a :class:`SolverResult`;
* :func:`staged_fista` runs the xL-SINDy schedule (stage, hard threshold, lower the
  penalty, raise the step) and an optional unpenalised refit on the final support.

For the linear cases (I and III) the datafit is :class:`GramQuadratic`, which works
on :math:`G = A^\top A / n` and :math:`b = A^\top y / n`, so an iteration costs
:math:`O(p^2)` whatever the number of samples.

The package holds one module per role: :mod:`~lagsindy.solvers.datafits`,
:mod:`~lagsindy.solvers.penalties`, :mod:`~lagsindy.solvers.fista` (with its
exact finishes in :mod:`~lagsindy.solvers.exact`) and
:mod:`~lagsindy.solvers.staged`. The solvers know nothing of mechanics: the
scaled problems they solve are made by
:class:`lagsindy.formulation.scaling.BalancedGram`.
"""

from __future__ import annotations

from .datafits import AccelerationDatafit, GramQuadratic
from .fista import SolverResult, fista, proximal_gradient
from .penalties import L1
from .staged import Stage, StagedResult, fista_path, staged_fista, warn_not_converged

__all__ = [
    "L1",
    "AccelerationDatafit",
    "GramQuadratic",
    "SolverResult",
    "Stage",
    "StagedResult",
    "fista",
    "fista_path",
    "proximal_gradient",
    "staged_fista",
    "warn_not_converged",
]
