"""The staged solver's settings: one object, and the defaults every entry point uses."""

from __future__ import annotations

from numbers import Integral, Real

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils._param_validation import Interval

# The defaults of every solver entry point (the estimator's, :class:`StagedFISTA`'s,
# :func:`~lagsindy.solvers.fista`'s and the staged functions'), defined once.
MAX_ITER = 20_000
SOLVER_TOL = 1e-7
# Iterations between FISTA's objective and KKT checks, and how many times its
# divergence guard may halve the step.
CHECK_EVERY = 10
MAX_STEP_REDUCTIONS = 40
# A term carrying at least this share of some coordinate's equation's dominant term
# is kept whatever the global threshold says (StagedFISTA.equation_threshold).
EQUATION_THRESHOLD = 0.25


class StagedFISTA(BaseEstimator):
    r"""Settings of the xL-SINDy staged sparse solve (FISTA stages, hard thresholds).

    Each stage minimises, in the scaled variables :math:`w`,
    :math:`\frac{1}{2n}\|y - \Theta w\|_2^2 + \lambda \|w\|_1` by FISTA on the
    current support; after it, the terms below a relative ``threshold`` are
    removed, :math:`\lambda` is divided by ``lam_decay`` and a given step raised by
    ``step_growth``, until the relative residual is below ``tol`` or
    ``max_stages`` have run; the final support is refitted without penalty
    (``debias``). The L1 weight ``lam`` and the step ``alpha`` are not settings of
    this object: they stay flat parameters of :class:`~lagsindy.LagrangianSINDy` so
    that grid searches sweep them directly.

    A scikit-learn style parameter object (``get_params``/``set_params``,
    ``clone``), so that an estimator holding it as ``solver`` exposes
    ``solver__threshold`` and the others to
    :class:`~sklearn.model_selection.GridSearchCV`.

    Parameters
    ----------
    threshold : float, default=0.05
        Hard threshold between stages, relative to the largest scaled coefficient: a
        term contributing less than ``threshold`` times the dominant term is dropped;
        a link 100 times lighter than the rest needs e.g. 1e-3 (a fit with forces
        warns when a coordinate's accelerations are then predicted poorly).
    dissipation_threshold : float, default=1e-3
        The hard threshold for dissipation terms. Friction and damping forces are
        usually a few percent of the conservative ones, so they get a lower
        threshold; with noisy data prefer :func:`lagsindy.diagnose`, which adds an
        effect only when it improves held-out predictions.
    lam_decay : float, default=10.0
        Division of ``lam`` between stages.
    step_growth : float, default=2.0
        Multiplication of a given ``alpha`` between stages.
    max_stages : int, default=5
    max_iter : int, default=20000
        FISTA iterations per stage.
    tol : float, default=1e-3
        Stop the stages when the relative residual
        :math:`\|y - \Theta w\|^2 / \|y\|^2` is at most ``tol``.
    solver_tol : float, default=1e-7
        KKT tolerance of each FISTA stage (scaled problem).
    debias : bool, default=True
        Refit the final support without penalty (removes L1 shrinkage).
    equation_threshold : float or None, default=0.25
        Judges terms within the coordinates' Euler-Lagrange equations too: a term
        that contributes at least ``equation_threshold`` times the dominant term
        of some coordinate's equation is kept whatever ``threshold`` says. The
        terms that make up a light or undriven link's equation (a pendulum 20 to
        100 times lighter than the cart or link that carries it) are then not
        judged against the heavy coordinate's, which removed them. ``None``: the
        paper's rule, ``threshold`` alone. The two agree for one coordinate.

    See Also
    --------
    lagsindy.solvers.staged_fista : the schedule on one problem.
    lagsindy.cases.SparseSolve : the schedule with an estimator's ``lam`` and
        ``alpha``, started from several values of ``lam``.

    Examples
    --------
    >>> from lagsindy.solvers import StagedFISTA
    >>> settings = StagedFISTA(threshold=0.1)
    >>> settings.set_params(max_stages=3).get_params()["max_stages"]
    3
    """

    _parameter_constraints: dict = {
        "threshold": [Interval(Real, 0, 1, closed="left")],
        "dissipation_threshold": [Interval(Real, 0, 1, closed="left")],
        "lam_decay": [Interval(Real, 1, None, closed="left")],
        "step_growth": [Interval(Real, 0, None, closed="neither")],
        "max_stages": [Interval(Integral, 1, None, closed="left")],
        "max_iter": [Interval(Integral, 1, None, closed="left")],
        "tol": [Interval(Real, 0, None, closed="left")],
        "solver_tol": [Interval(Real, 0, None, closed="neither")],
        "debias": ["boolean"],
        "equation_threshold": [Interval(Real, 0, 1, closed="both"), None],
    }

    def __init__(
        self,
        threshold=0.05,
        dissipation_threshold=1e-3,
        lam_decay=10.0,
        step_growth=2.0,
        max_stages=5,
        max_iter=MAX_ITER,
        tol=1e-3,
        solver_tol=SOLVER_TOL,
        debias=True,
        equation_threshold=EQUATION_THRESHOLD,
    ):
        self.threshold = threshold
        self.dissipation_threshold = dissipation_threshold
        self.lam_decay = lam_decay
        self.step_growth = step_growth
        self.max_stages = max_stages
        self.max_iter = max_iter
        self.tol = tol
        self.solver_tol = solver_tol
        self.debias = debias
        self.equation_threshold = equation_threshold

    def validate(self) -> StagedFISTA:
        """Check the settings (a clear ``InvalidParameterError`` names a bad one).

        Returns
        -------
        StagedFISTA
            ``self``.
        """
        self._validate_params()
        return self

    def thresholds(self, dissipation) -> np.ndarray:
        """Per-feature hard thresholds: ``dissipation_threshold`` where
        ``dissipation`` is true, ``threshold`` elsewhere.

        Parameters
        ----------
        dissipation : array-like of bool

        Returns
        -------
        ndarray of float
        """
        return np.where(dissipation, self.dissipation_threshold, self.threshold)

    def schedule(self) -> dict:
        """The keyword arguments of :func:`~lagsindy.solvers.staged_fista` (and
        :func:`~lagsindy.solvers.staged.staged_fista_batch`) these settings give,
        apart from the thresholds (:meth:`thresholds`).

        Returns
        -------
        dict
            ``lam_decay``, ``step_growth``, ``max_stages``, ``max_iter``, ``tol``,
            ``solver_tol``, ``debias`` and ``equation_threshold``.
        """
        return {
            "lam_decay": self.lam_decay,
            "step_growth": self.step_growth,
            "max_stages": self.max_stages,
            "max_iter": self.max_iter,
            "tol": self.tol,
            "solver_tol": self.solver_tol,
            "debias": self.debias,
            "equation_threshold": self.equation_threshold,
        }
