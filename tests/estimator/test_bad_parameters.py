"""Bad libraries, terms and parameters give a ValueError that names the problem, and
a failed fit leaves the estimator unfitted (issue #8, item 1; the data's checks are
in test_bad_input.py).

Every case listed in the issue is here, each asserting that the message names what
is wrong (the column, the row, the shape or the parameter received). None of them
may surface as a numpy, pandas, sympy or torch error.
"""

import numpy as np
import pytest
from _helpers import THREE_PENDULUM_TERMS
from _helpers import three_term_estimator as small
from _helpers import value_error as raises
from sklearn.exceptions import NotFittedError

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import (
    cart_pendulum,
    single_pendulum,
)


# ----------------------------------------------------------------- library and terms
def test_unknown_coordinate_in_library_term(pend):
    lib = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "phi_dot**2"])
    with raises("unknown name 'phi_dot' in 'phi_dot**2'"):
        LagrangianSINDy(lib).fit(pend.X, pend.tau)


@pytest.mark.parametrize(
    "library, match",
    [
        (
            lambda: CandidateLibrary.from_terms(["sin"], ["sin_dot**2"]),
            "'sin' is reserved",
        ),
        (
            lambda: CandidateLibrary.from_terms(["theta_dot"], ["theta_dot_dot**2"]),
            "'theta_dot' ends in '_dot'",
        ),
        (lambda: CandidateLibrary.from_terms(["2x"], ["x"]), "'2x' is not valid"),
        (
            lambda: CandidateLibrary.polynomial(["theta"], angles=["phi"]),
            "angles ['phi'] are not among the coordinates",
        ),
        (lambda: CandidateLibrary.polynomial(["theta"], degree=0), "degree must be"),
        (
            lambda: CandidateLibrary.from_terms(["theta"], ["theta_dot**2 +"]),
            "unexpected end of text",
        ),
        (
            lambda: CandidateLibrary.from_terms(["theta"], ["__import__('os')"]),
            "unexpected character",
        ),
        (
            lambda: CandidateLibrary.from_terms(
                ["theta"], ["theta_dot", "theta*theta_dot"]
            ),
            "every candidate term is trivial",
        ),
    ],
    ids=[
        "reserved",
        "suffix",
        "identifier",
        "angles",
        "degree",
        "syntax",
        "injection",
        "all-trivial",
    ],
)
def test_bad_library(pend, library, match):
    with raises(match):
        LagrangianSINDy(library()).fit(pend.X, pend.tau)


@pytest.mark.parametrize(
    "fixed_term, match",
    [
        ("phi_dot**2", "fixed_term='phi_dot**2': unknown name 'phi_dot'"),
        (
            "theta_dot**4",
            "fixed_term='theta_dot**4': term 'theta_dot**4' is not in the library",
        ),
        (
            "theta_dot",
            "fixed_term='theta_dot': term 'theta_dot' is not in the library: trivial",
        ),
        ("theta_dot**", "fixed_term='theta_dot**': unexpected end of text"),
    ],
)
def test_bad_fixed_term(pend, fixed_term, match):
    lib = CandidateLibrary.from_terms(["theta"], THREE_PENDULUM_TERMS + ["theta_dot"])
    with raises(match):
        LagrangianSINDy(lib, fixed_term=fixed_term).fit(pend.X)


def test_fixed_term_outside_case_III(pend):
    with raises("fixed_term='theta_dot**2' is only used in case III") as err:
        small(fixed_term="theta_dot**2").fit(pend.X, pend.tau)
    assert "case='forces'" in str(err.value)
    with raises("case='acceleration'"):
        small(fixed_term="theta_dot**2", case="acceleration").fit(pend.X)


def test_bad_unpenalized_terms(pend):
    with raises(
        "unpenalized='theta_dot**4': term 'theta_dot**4' is not in the library"
    ):
        small(unpenalized=["cos(theta)", "theta_dot**4"]).fit(pend.X, pend.tau)
    with raises("unpenalized='phi'"):
        small(unpenalized=["phi"]).fit(pend.X, pend.tau)
    with raises("'unpenalized' parameter"):
        small(unpenalized="cos(theta)").fit(pend.X, pend.tau)  # a list is needed


def test_unpenalized_as_an_array_of_terms(pend):
    """Regression: ``unpenalized or []`` raised numpy's 'truth value is ambiguous'."""
    est = small(unpenalized=np.array(["cos(theta)", "theta**2"])).fit(pend.X, pend.tau)
    assert est.support_[est.library_.index("theta**2")]


def test_case_and_tau_mismatch(pend):
    with raises("case='forces' needs tau"):
        small(case="forces").fit(pend.X)
    with raises("case='fixed' is for passive data"):
        small(case="fixed").fit(pend.X, pend.tau)


# ----------------------------------------------------------------- parameters
@pytest.mark.parametrize(
    "params, name",
    [
        (dict(lam=-1.0), "lam"),
        (dict(lam=np.nan), "lam"),
        (dict(lam=np.inf), "lam"),
        (dict(alpha=0.0), "alpha"),
        (dict(alpha=-0.1), "alpha"),
        (dict(alpha=np.nan), "alpha"),
        (dict(threshold=1.0), "threshold"),
        (dict(threshold=-0.1), "threshold"),
        (dict(max_iter=0), "max_iter"),
        (dict(max_stages=2.5), "max_stages"),
        (dict(lam_decay=0.5), "lam_decay"),
        (dict(solver_tol=0.0), "solver_tol"),
        (dict(case="passive"), "case"),
        (dict(dtype="float16"), "dtype"),
        (dict(random_state="seed"), "random_state"),
        (dict(fixed_term=3), "fixed_term"),
    ],
)
def test_invalid_parameters(pend, params, name):
    with pytest.raises(
        ValueError, match=f"The '{name}' parameter of LagrangianSINDy must be"
    ):
        small(**params).fit(pend.X, pend.tau)


def test_invalid_library_and_device(pend):
    with pytest.raises(ValueError, match="The 'library' parameter"):
        LagrangianSINDy(library="polynomial").fit(pend.X, pend.tau)
    with raises("device='gpu0' is not a torch device"):
        small(device="gpu0").fit(pend.X, pend.tau)


# ----------------------------------------------------------------- failed fits
def test_failed_fit_leaves_the_estimator_unfitted(pend):
    est = small()
    with pytest.raises(ValueError):
        est.fit(pend.X[:2], pend.tau[:2])  # too few samples, after the library is built
    with pytest.raises(NotFittedError):
        est.predict(pend.X)
    est.fit(pend.X, pend.tau)
    with pytest.raises(ValueError):
        est.set_params(fixed_term="theta_dot**2").fit(pend.X, pend.tau)
    with pytest.raises(NotFittedError):
        est.predict(pend.X)  # not the previous model with a half-replaced state


def test_refit_replaces_the_compiled_model(pend):
    """Regression: a refit reused the previous model's cached torch operator."""
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(pend.X, pend.tau)
    other = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "theta**2"])
    est.set_params(library=other).fit(pend.X, pend.tau)
    fresh = LagrangianSINDy(other).fit(pend.X, pend.tau)
    np.testing.assert_array_equal(est.predict(pend.X), fresh.predict(pend.X))


def test_reversed_views_are_read_as_their_values(cart):
    """Negative-stride views (tau[:, ::-1], X[::-1]) raised a raw torch error."""
    library = cart_pendulum().paper_library()
    views = LagrangianSINDy(library, formulation="strong").fit(
        cart.X[::-1], cart.tau[:, ::-1][:, ::-1][::-1]
    )
    copies = LagrangianSINDy(library, formulation="strong").fit(
        cart.X[::-1].copy(), cart.tau[::-1].copy()
    )
    np.testing.assert_array_equal(views.coef_, copies.coef_)
    np.testing.assert_array_equal(
        views.predict(cart.X[::-1]), copies.predict(cart.X[::-1].copy())
    )
