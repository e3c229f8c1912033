"""The solver's settings (lagsindy.solvers.settings): StagedFISTA as a scikit-learn
parameter object, and one set of defaults for every entry point."""

import inspect

import numpy as np
import pytest
from lasso_problems import gram_problem
from sklearn.base import BaseEstimator, RegressorMixin, clone
from sklearn.model_selection import GridSearchCV

from lagsindy import LagrangianSINDy
from lagsindy.solvers import (
    MAX_ITER,
    SOLVER_TOL,
    StagedFISTA,
    fista,
    fista_batch,
    fista_path,
    proximal_gradient,
    staged_fista,
    staged_fista_batch,
)


def test_parameters_round_trip_and_clone():
    settings = StagedFISTA(threshold=0.1, max_stages=3)
    params = settings.get_params()
    assert params["threshold"] == 0.1 and params["max_stages"] == 3
    assert settings.set_params(debias=False) is settings and not settings.debias
    copy = clone(settings)
    assert copy is not settings and copy.get_params() == settings.get_params()
    assert "threshold=0.1" in repr(settings)  # scikit-learn's repr: what differs


@pytest.mark.parametrize(
    "name, value",
    [("threshold", 1.0), ("threshold", -0.1), ("max_stages", 0), ("solver_tol", 0.0)],
)
def test_validate_names_the_bad_setting(name, value):
    with pytest.raises(ValueError, match=name):
        StagedFISTA(**{name: value}).validate()
    # the boundary values just inside are accepted
    inside = {"threshold": 0.0, "max_stages": 1, "solver_tol": 1e-300}[name]
    assert StagedFISTA(**{name: inside}).validate().get_params()[name] == inside


def test_thresholds_and_schedule():
    settings = StagedFISTA(threshold=0.2, dissipation_threshold=0.01, tol=1e-4)
    np.testing.assert_array_equal(
        settings.thresholds([False, True, False]), [0.2, 0.01, 0.2]
    )
    schedule = settings.schedule()
    keywords = inspect.signature(staged_fista_batch).parameters
    assert set(schedule) <= set(keywords) and schedule["tol"] == 1e-4
    # the schedule's keywords drive staged_fista directly
    rng = np.random.default_rng(0)
    A = rng.normal(size=(100, 4))
    y = A @ np.array([1.0, 0.0, -1.0, 0.0])
    res = staged_fista(gram_problem(A, y), lam=1e-2, threshold=0.2, **schedule)
    np.testing.assert_array_equal(res.support, [0, 2])


def _defaults(fn):
    return {
        k: v.default
        for k, v in inspect.signature(fn).parameters.items()
        if v.default is not inspect.Parameter.empty
    }


def test_one_set_of_defaults():
    """Every entry point takes its iteration cap and KKT tolerance, and the staged
    functions their schedule, from the one definition (StagedFISTA's)."""
    assert (MAX_ITER, SOLVER_TOL) == (20_000, 1e-7)
    settings = StagedFISTA().get_params()
    assert settings["max_iter"] == MAX_ITER and settings["solver_tol"] == SOLVER_TOL
    for fn in (fista, fista_batch, fista_path, proximal_gradient):
        defaults = _defaults(fn)
        assert (defaults["max_iter"], defaults["tol"]) == (MAX_ITER, SOLVER_TOL), fn
    for fn in (staged_fista, staged_fista_batch):
        defaults = _defaults(fn)
        for name, value in settings.items():
            if name in defaults:
                assert defaults[name] == value, (fn, name)
    # the estimator's solver is these settings (its flat parameters are deprecated)
    estimator = LagrangianSINDy().get_params()
    assert estimator["solver"] is None
    # every flat setting deprecated (equation_threshold never had a flat one)
    assert all(
        estimator[name] == "deprecated" for name in settings if name in estimator
    )
    assert set(settings) - set(estimator) == {"equation_threshold"}


class _Toy(RegressorMixin, BaseEstimator):
    """A least-squares estimator with a ``solver`` settings object, as
    LagrangianSINDy holds one: grid searches reach ``solver__threshold``."""

    def __init__(self, solver=None, lam=1e-2):
        self.solver = solver
        self.lam = lam

    def fit(self, X, y):
        settings = StagedFISTA() if self.solver is None else self.solver
        res = staged_fista(
            gram_problem(np.asarray(X), np.asarray(y)),
            lam=self.lam,
            threshold=settings.threshold,
            **settings.schedule(),
        )
        self.coef_ = res.coef.numpy()
        return self

    def predict(self, X):
        return np.asarray(X) @ self.coef_


def test_grid_search_sweeps_the_solver_settings():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(200, 5))
    # a term at 5 % of the largest: kept by a threshold of 0.01, lost by 0.2
    y = X @ np.array([1.0, 0.05, 0.0, -0.7, 0.0]) + 1e-3 * rng.normal(size=200)
    search = GridSearchCV(
        _Toy(solver=StagedFISTA()),
        {"solver__threshold": [0.01, 0.2], "lam": [1e-3]},
        cv=3,
    ).fit(X, y)
    assert search.best_params_["solver__threshold"] == 0.01
    assert search.best_estimator_.solver.threshold == 0.01
    assert np.count_nonzero(search.best_estimator_.coef_) == 3
    # the estimator passed in is untouched (clone of the nested settings)
    assert search.estimator.solver.threshold == 0.05
