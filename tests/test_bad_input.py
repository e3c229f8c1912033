"""Bad input gives a ValueError that names the problem (issue #8, item 1).

Every case listed in the issue is here, each asserting that the message names what
is wrong (the column, the row, the shape or the parameter received). None of them
may surface as a numpy, pandas, sympy or torch error.
"""

import re
import warnings

import numpy as np
import pandas as pd
import pytest
import scipy.sparse as sps
from sklearn.exceptions import NotFittedError

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)

TERMS = ["theta_dot**2", "cos(theta)", "theta**2"]


@pytest.fixture(scope="module")
def pend():
    return make_dataset(
        single_pendulum(), n_trajectories=3, duration=1.0, random_state=0
    )


@pytest.fixture(scope="module")
def cart():
    return make_dataset(
        cart_pendulum(),
        n_trajectories=2,
        duration=1.0,
        excitation="sincos",
        random_state=0,
    )


def small(**kwargs):
    return LagrangianSINDy(CandidateLibrary.from_terms(["theta"], TERMS), **kwargs)


def raises(match):
    """``pytest.raises(ValueError)`` with a literal (not regex) message fragment."""
    return pytest.raises(ValueError, match=re.escape(match))


# ----------------------------------------------------------------- layout of X
def test_columns_not_divisible_by_three(pend):
    with raises("n_features = 4 is not divisible by 3"):
        LagrangianSINDy().fit(np.hstack([pend.X, pend.X[:, :1]]), pend.tau)


def test_columns_not_matching_the_library(pend):
    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"])
    with raises("3 * n_dof = 6 columns") as err:
        LagrangianSINDy(lib).fit(pend.X, pend.tau)
    assert "n_features = 3" in str(err.value) and "2 coordinate(s)" in str(err.value)


def test_wrong_width_at_predict(pend):
    est = small().fit(pend.X, pend.tau)
    with raises("n_features = 6"):
        est.predict(np.hstack([pend.X, pend.X]))
    with raises("n_features = 2"):
        est.predict_acceleration(pend.X[:, :2])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda X: X[:, :, None], "got a 3-D array of shape (300, 3, 1)"),
        (lambda X: X[:, 0], "got a 1-D array of shape (300,). Reshape your data"),
        (lambda X: 3.0, "got a scalar"),
        (lambda X: None, "X is None"),
        (lambda X: "X.csv", "X must be an array of numbers, got a str"),
        (lambda X: {"theta": X[:, 0]}, "got a dict"),
        (lambda X: [[1.0, 2.0, 3.0], [1.0, 2.0]], "rows all have the same length"),
        (lambda X: X + 1j, "Complex data not supported"),
        (lambda X: sps.csr_matrix(X), "X is a sparse matrix"),
        (lambda X: X[:0], "0 sample(s)"),
        (lambda X: X[:1], "1 sample(s)"),
        (lambda X: X[:, :0], "0 feature(s)"),
    ],
    ids=[
        "3d",
        "1d",
        "scalar",
        "none",
        "str",
        "dict",
        "ragged",
        "complex",
        "sparse",
        "empty",
        "one-row",
        "no-columns",
    ],
)
def test_malformed_X(pend, make, match):
    with raises(match):
        small().fit(make(pend.X), pend.tau)


def test_malformed_X_at_predict(pend):
    est = small().fit(pend.X, pend.tau)
    with raises("Reshape your data"):
        est.predict(pend.X[0])
    with raises("got a 3-D array"):
        est.predict(pend.X[None])
    with raises("Complex data not supported"):
        est.predict(pend.X + 1j)


# ----------------------------------------------------------------- tau
def test_tau_wrong_number_of_columns(pend):
    with raises("tau must have shape (n_samples, n_dof=1)") as err:
        small().fit(pend.X, np.hstack([pend.tau, pend.tau]))
    assert "got shape (300, 2)" in str(err.value) and "tau_theta" in str(err.value)


def test_tau_one_dimensional_for_several_coordinates(cart):
    with raises("n_dof=2), got a 1-D array"):
        LagrangianSINDy(cart_pendulum().paper_library()).fit(cart.X, cart.tau[:, 0])


def test_tau_wrong_number_of_rows(pend):
    with raises("different numbers of rows: 300 and 297"):
        small().fit(pend.X, pend.tau[:-3])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda t: t[:, :, None], "tau must be a 1-D or 2-D array, got a 3-D array"),
        (lambda t: 2.0, "tau must be a 1-D or 2-D array, got a scalar"),
        (lambda t: "tau", "tau must be an array of numbers, got a str"),
        (lambda t: t + 1j, "Complex data not supported: tau"),
        (lambda t: sps.csr_matrix(t), "tau is a sparse matrix"),
    ],
    ids=["3d", "scalar", "str", "complex", "sparse"],
)
def test_malformed_tau(pend, make, match):
    with raises(match):
        small().fit(pend.X, make(pend.tau))


def test_tau_all_zero_and_too_small(pend):
    with raises("tau is identically zero"):
        small().fit(pend.X, 0 * pend.tau)
    with raises("tau is too small to use"):
        small().fit(pend.X, 1e-300 * pend.tau)


def test_tau_dataframe_columns_are_matched_by_name(cart):
    lib = CandidateLibrary.from_terms(
        ["x", "theta"],
        [
            "x_dot**2",
            "theta_dot**2",
            "x_dot*theta_dot*cos(theta)",
            "cos(theta)",
            "x**2",
        ],
    )
    ref = LagrangianSINDy(lib).fit(cart.X, cart.tau)
    # named like Dataset.to_frame, in the wrong order: reordered by name
    frame = pd.DataFrame({"tau_theta": cart.tau[:, 1], "tau_x": cart.tau[:, 0]})
    est = LagrangianSINDy(lib).fit(cart.X, frame)
    np.testing.assert_array_equal(est.coef_, ref.coef_)
    bare = pd.DataFrame({"theta": cart.tau[:, 1], "x": cart.tau[:, 0]})
    np.testing.assert_array_equal(
        LagrangianSINDy(lib).fit(cart.X, bare).coef_, ref.coef_
    )
    # names that do not identify the coordinates are ambiguous: an error, not a guess
    with raises("name them ['tau_x', 'tau_theta']"):
        LagrangianSINDy(lib).fit(cart.X, frame.set_axis(["f1", "f2"], axis=1))
    with raises("tau_x"):
        LagrangianSINDy(lib).fit(cart.X, frame[["tau_theta"]])
    with raises("repeated column names ['tau_x']"):
        LagrangianSINDy(lib).fit(cart.X, frame.set_axis(["tau_x", "tau_x"], axis=1))


def test_tau_at_score_and_predict_acceleration(pend):
    est = small().fit(pend.X, pend.tau)
    with raises("tau must have shape (n_samples, n_dof=1)"):
        est.score(pend.X, np.hstack([pend.tau, pend.tau]))
    with raises("got shape (150, 2)"):  # the same size: once silently reshaped
        est.score(pend.X, pend.tau.reshape(150, 2))
    with raises("different numbers of rows: 300 and 3"):
        est.predict_acceleration(pend.X, pend.tau[:3])
    with raises("tau contains 300 NaN"):
        est.score(pend.X, np.full_like(pend.tau, np.nan))


# ----------------------------------------------------------------- NaN / inf
@pytest.mark.parametrize(
    "value, kind", [(np.nan, "NaN"), (np.inf, "infinite"), (-np.inf, "infinite")]
)
def test_non_finite_X_names_row_and_column(pend, value, kind):
    X = pend.X.copy()
    X[7, 1] = value
    X[9, 2] = value
    with raises(
        f"X contains 2 NaN or infinite value(s); the first is {kind} at row 7, "
        "column 'theta_dot'"
    ):
        small().fit(X, pend.tau)


@pytest.mark.parametrize("value, kind", [(np.nan, "NaN"), (np.inf, "infinite")])
def test_non_finite_tau_names_row_and_column(pend, value, kind):
    tau = pend.tau.copy()
    tau[4, 0] = value
    with raises(
        f"tau contains 1 NaN or infinite value(s); the first is {kind} at row 4, "
        "column 'tau_theta'"
    ):
        small().fit(pend.X, tau)


def test_non_finite_at_predict_and_in_dataframes(cart, pend):
    est = small().fit(pend.X, pend.tau)
    X = pend.X.copy()
    X[3, 2] = np.nan
    with raises("row 3, column 'theta_ddot'"):
        est.predict(X)
    df = pd.DataFrame(cart.X, columns=cart.feature_names)
    df.loc[11, "x_dot"] = np.inf
    with raises("row 11, column 'x_dot'"):
        LagrangianSINDy(cart_pendulum().paper_library()).fit(df, cart.tau)
    # numeric columns with missing values (pandas NA, None) are NaN, named as such
    nullable = pd.DataFrame(cart.X, columns=cart.feature_names).astype(object)
    nullable.loc[5, "theta"] = None
    with raises("NaN at row 5, column 'theta'"):
        LagrangianSINDy(cart_pendulum().paper_library()).fit(nullable, cart.tau)


# ----------------------------------------------------------------- dtypes
def test_integer_and_numeric_object_dtypes_are_converted(pend):
    ref = small().fit(pend.X, pend.tau)
    est = small().fit(pend.X.astype(object), pend.tau.astype(object))
    np.testing.assert_array_equal(est.coef_, ref.coef_)
    scaled = np.round(pend.X * 1e6).astype(np.int64)  # integer micro-units
    est = small().fit(scaled, np.round(pend.tau * 1e6).astype(np.int64))
    assert np.all(np.isfinite(est.coef_)) and est.coef_.dtype == np.float64


def test_strings_that_are_not_numbers(pend):
    X = pend.X.astype(object)
    X[3, 2] = "abc"
    with raises("X could not be converted to floating point numbers") as err:
        small().fit(X, pend.tau)
    assert "'abc' at row 3, column 'theta_ddot'" in str(err.value)
    tau = pend.tau.astype(object)
    tau[2, 0] = "n/a"
    with raises("'n/a' at row 2, column 'tau_theta'"):
        small().fit(pend.X, tau)


def test_dataframe_columns_that_are_not_numbers(pend):
    df = pd.DataFrame(pend.X, columns=pend.feature_names)
    text = df.assign(theta=df["theta"].astype(str).where(df.index != 4, "bad"))
    with raises("X column 'theta' could not be converted") as err:
        small().fit(text, pend.tau)
    assert "'bad' at row 4" in str(err.value)
    with raises("X column 'theta' could not be converted"):
        small().fit(df.assign(theta=pd.Categorical(["a"] * len(df))), pend.tau)
    with raises("X column 'theta_dot' holds dates"):
        small().fit(df.assign(theta_dot=pd.Timestamp("2024-01-01")), pend.tau)


# ----------------------------------------------------------------- DataFrames
def test_dataframe_missing_columns(pend):
    df = pd.DataFrame(pend.X, columns=pend.feature_names)
    with raises("the DataFrame is missing the columns ['theta_ddot']"):
        small().fit(df.drop(columns=["theta_ddot"]), pend.tau)
    est = small().fit(df, pend.tau)
    with raises("missing the columns ['theta']"):
        est.predict(df.drop(columns=["theta"]))


def test_library_coordinates_not_in_dataframe(pend):
    df = pd.DataFrame(pend.X, columns=pend.feature_names)
    lib = CandidateLibrary.from_terms(["phi"], ["phi_dot**2", "cos(phi)"])
    with raises("missing the columns ['phi', 'phi_dot', 'phi_ddot']") as err:
        LagrangianSINDy(lib).fit(df, pend.tau)
    assert "library's coordinates ['phi']" in str(err.value)


def test_dataframe_without_readable_coordinates(pend):
    with raises("could not read coordinates from the DataFrame columns"):
        LagrangianSINDy().fit(pd.DataFrame(pend.X), pend.tau)
    renamed = pd.DataFrame(pend.X, columns=["theta", "omega", "alpha"])
    with raises("missing ['theta_dot', 'omega_dot'"):
        LagrangianSINDy().fit(renamed, pend.tau)


def test_dataframe_repeated_columns(pend):
    df = pd.DataFrame(pend.X, columns=pend.feature_names)
    with raises("repeated column names ['theta']"):
        small().fit(pd.concat([df, df[["theta"]]], axis=1), pend.tau)


# ----------------------------------------------------------------- data content
def test_fewer_samples_than_terms(pend):
    with raises(
        "too few samples: 5 sample(s) x 1 coordinate(s) give 5 equations for 9"
    ):
        LagrangianSINDy(single_pendulum().paper_library()).fit(pend.X[:5], pend.tau[:5])


def test_constant_data(pend):
    X = np.tile(pend.X[:1], (50, 1))
    with raises("X is constant: all 50 rows are the same sample"):
        small().fit(X, pend.tau[:50])
    with raises("X is constant"):
        small().fit(np.zeros((50, 3)))


def test_all_zero_velocities(pend):
    X = pend.X.copy()
    X[:, 1:] = 0.0
    with raises("all velocities in X (['theta_dot']) are zero"):
        small().fit(X, pend.tau)
    with raises("all velocities in X"):
        small(fixed_term="theta_dot**2").fit(X)


def test_overflow_and_undefined_terms(pend):
    with raises("not finite on this data") as err:
        small().fit(pend.X * 1e200, pend.tau)
    assert "theta_dot**2" in str(err.value)
    with raises("overflows in float64"):
        small().fit(pend.X, pend.tau * 1e300)
    # sqrt(theta) is undefined for the negative angles of the swing
    lib = CandidateLibrary.from_terms(
        ["theta"], ["theta_dot**2", "cos(theta)", "sqrt(theta)"]
    )
    with raises("['sqrt(theta)'] are not finite"):
        LagrangianSINDy(lib).fit(pend.X, pend.tau)


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
    lib = CandidateLibrary.from_terms(["theta"], TERMS + ["theta_dot"])
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


# ------------------------------------------- forces that no Lagrangian explains
@pytest.fixture(scope="module")
def double():
    return make_dataset(
        double_pendulum(), n_trajectories=6, duration=5.0, excitation="sincos",
        random_state=0,
    )  # fmt: skip


def _fit_recorded(data, tau):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est = LagrangianSINDy(double_pendulum().paper_library()).fit(
            data.X, tau, groups=data.groups
        )
    return est, [str(w.message) for w in caught]


def test_right_forces_give_no_warning(double):
    est, caught = _fit_recorded(double, double.tau)
    assert est.residual_ < 1e-6  # measured: 3.5e-8
    assert est.mass_check_.negative == 0.0
    assert caught == []


def test_negated_forces_say_the_kinetic_energy_is_negative(double):
    """-tau fits -L exactly: the residual says nothing, the mass matrix does."""
    est, caught = _fit_recorded(double, -double.tau)
    assert est.residual_ < 1e-6  # measured: 3.5e-8, as with the right sign
    assert est.mass_check_.negative == 1.0 and est.mass_check_.ok
    assert any("negative definite" in m and "sign convention" in m for m in caught)


@pytest.mark.parametrize("wrong", ["one sign flipped", "columns swapped"])
def test_forces_no_lagrangian_explains_are_reported(double, wrong):
    tau = double.tau * [-1, 1] if wrong == "one sign flipped" else double.tau[:, ::-1]
    est, caught = _fit_recorded(double, np.ascontiguousarray(tau))
    # measured: 0.73 (flipped), 0.75 (swapped)
    assert est.residual_ > 0.6
    assert any(
        "of the measured forces' sum of squares unexplained" in m for m in caught
    )


def test_default_library_on_several_coordinates_says_it_cannot_couple(double, pend):
    """Degree-2 products cannot hold cos(theta1 - theta2) * velocities: a double
    pendulum fitted with library=None got 27 meaningless terms without a word."""
    with pytest.warns(UserWarning, match=r"library=None fits degree-2 polynomials"):
        LagrangianSINDy().fit(double.X, double.tau, groups=double.groups)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        LagrangianSINDy().fit(pend.X, groups=pend.groups)  # one coordinate
    assert not any("library=None" in str(w.message) for w in caught)


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
