"""Bad input gives a ValueError that names the problem (issue #8, item 1).

Every case listed in the issue is here, each asserting that the message names what
is wrong (the column, the row, the shape or the parameter received). None of them
may surface as a numpy, pandas, sympy or torch error.
"""

import numpy as np
import pandas as pd
import pytest
import scipy.sparse as sps
from _helpers import three_term_estimator as small
from _helpers import value_error as raises

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import (
    cart_pendulum,
    single_pendulum,
)


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
        (lambda X: X[:, :, None], "got a 3-D array of shape (800, 3, 1)"),
        (lambda X: X[:, 0], "got a 1-D array of shape (800,). Reshape your data"),
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
    assert "got shape (800, 2)" in str(err.value) and "tau_theta" in str(err.value)


def test_tau_one_dimensional_for_several_coordinates(cart):
    with raises("n_dof=2), got a 1-D array"):
        LagrangianSINDy(cart_pendulum().paper_library()).fit(cart.X, cart.tau[:, 0])


def test_tau_wrong_number_of_rows(pend):
    with raises("different numbers of rows: 800 and 797"):
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
    with raises("got shape (400, 2)"):  # the same size: once silently reshaped
        est.score(pend.X, pend.tau.reshape(400, 2))
    with raises("different numbers of rows: 800 and 3"):
        est.predict_acceleration(pend.X, pend.tau[:3])
    with raises("tau contains 800 NaN"):
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
