r"""Sparse solvers: FISTA with an L1 penalty, and the paper's staged schedule.

The pieces follow a small duck-typed contract (in the spirit of skglm):

* a **datafit** provides ``value(w)``, ``gradient(w)``, ``lipschitz()``,
  ``restrict(idx)`` and ``relative_residual(w)``;
* a **penalty** provides ``value(w)``, ``prox(w, step)``,
  ``subdiff_distance(w, grad)`` and ``restrict(idx)``;
* :func:`fista` minimises ``datafit + penalty`` and returns a :class:`SolverResult`;
* :func:`staged_fista` runs the xL-SINDy schedule (stage, hard threshold, lower the
  penalty, raise the step) and an optional unpenalised refit on the final support;
* :class:`StagedFISTA` holds the schedule's settings, whose defaults (with
  :data:`MAX_ITER` and :data:`SOLVER_TOL`) every entry point shares.

One problem is a batch of one: :func:`fista` and :func:`fista_batch` run the same
iterations, :func:`staged_fista` and :func:`~lagsindy.solvers.staged.staged_fista_batch`
the same schedule.

For the linear cases (I and III) the datafit is :class:`GramQuadratic`, which works
on :math:`G = A^\top A / n` and :math:`b = A^\top y / n`, so an iteration costs
:math:`O(p^2)` whatever the number of samples.

The package holds one module per role: :mod:`~lagsindy.solvers.datafits`,
:mod:`~lagsindy.solvers.penalties`, :mod:`~lagsindy.solvers.fista` (its iterations
in ``_loop``, its exact finishes in :mod:`~lagsindy.solvers.exact`),
:mod:`~lagsindy.solvers.staged` (the problems it batches in ``_problems``) and
:mod:`~lagsindy.solvers.settings`. The solvers know nothing of mechanics: the
scaled problems they solve are made by
:class:`lagsindy.formulation.scaling.BalancedGram`.
"""

from __future__ import annotations

from .datafits import AccelerationDatafit, GramQuadratic
from .fista import BatchResult, SolverResult, fista, fista_batch, proximal_gradient
from .penalties import L1
from .settings import MAX_ITER, SOLVER_TOL, StagedFISTA
from .staged import (
    Stage,
    StagedResult,
    fista_path,
    staged_fista,
    staged_fista_batch,
    warn_not_converged,
)

__all__ = [
    "L1",
    "MAX_ITER",
    "SOLVER_TOL",
    "AccelerationDatafit",
    "BatchResult",
    "GramQuadratic",
    "SolverResult",
    "Stage",
    "StagedFISTA",
    "StagedResult",
    "fista",
    "fista_batch",
    "fista_path",
    "proximal_gradient",
    "staged_fista",
    "staged_fista_batch",
    "warn_not_converged",
]
