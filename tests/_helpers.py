"""Helpers shared by test files (the fixtures are in ``conftest.py``).

Import them by name (``from _helpers import recorded_fit``): ``tests/`` is on the
path of every test module, as for ``_sympy_reference``.
"""

import re
import warnings

import pytest

from lagsindy import CandidateLibrary, LagrangianSINDy

# A small single-pendulum library: the two true terms first, then three others.
SMALL_PENDULUM_TERMS = [
    "cos(theta)",
    "theta_dot**2",
    "sin(theta)",
    "theta_dot**2*cos(theta)",
    "sin(theta)**2",
]


def small_pendulum_library():
    """:data:`SMALL_PENDULUM_TERMS` as an (unbuilt) library over ``theta``."""
    return CandidateLibrary.from_terms(["theta"], SMALL_PENDULUM_TERMS)


def messages_of(call):
    """``call()``'s result and the messages of every warning it raised."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = call()
    return out, [str(w.message) for w in caught]


def recorded_fit(library, X, tau=None, groups=None, **params):
    """``LagrangianSINDy(library, **params).fit(X, tau, groups=groups)`` and the
    messages of the warnings the fit raised."""
    return messages_of(
        lambda: LagrangianSINDy(library, **params).fit(X, tau, groups=groups)
    )


def degrees(X, columns):
    """A copy of ``X`` with the angle ``columns`` (and their derivatives) in
    degrees."""
    import numpy as np

    X = np.array(X, dtype=float)
    n = X.shape[1] // 3
    for j in columns:
        X[:, [j, j + n, j + 2 * n]] *= 180 / np.pi
    return X


# Three single-pendulum terms: the true two and a spurious one.
THREE_PENDULUM_TERMS = ["theta_dot**2", "cos(theta)", "theta**2"]


def three_term_estimator(**params):
    """An unfitted estimator over :data:`THREE_PENDULUM_TERMS`."""
    library = CandidateLibrary.from_terms(["theta"], THREE_PENDULUM_TERMS)
    return LagrangianSINDy(library, **params)


def value_error(match):
    """``pytest.raises(ValueError)`` with a literal (not regex) message fragment."""
    return pytest.raises(ValueError, match=re.escape(match))


def first_problem(est, X, y=None, groups=None):
    """The first case Problem ``est.fit(X, y, groups=groups)`` solves (quietly)."""
    seen = []
    import lagsindy.pipeline as estimator

    original = estimator.solve_case
    try:
        estimator.solve_case = lambda case, p: seen.append(p) or original(case, p)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(X, y, groups=groups)
    finally:
        estimator.solve_case = original
    return seen[0]
